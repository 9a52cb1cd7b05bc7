/* Tree-ensemble kernel for flight_sw.psafe.TreeModel (the calibrated P(safe) model, format psafe-trees/1).
 *
 * Same arithmetic as the numpy reference TreeModel.logit (tested equal): for every point i,
 *
 *   z_i = base + sum_t value[leaf_t(x_i)],
 *
 * where leaf_t is reached from roots[t] by going right when x[feature] > threshold, and to the node's
 * missing side when x[feature] is NaN. The layout is TreeModel.kernel_layout(): each tree's nodes in
 * breadth-first order with the two children adjacent (right = left + 1), and every leaf absorbing
 * (feature 0, threshold +inf, missing side left, left = itself), so a fixed number of steps per tree
 * (its depth) reaches the leaf without a data-dependent branch; eight points are walked together so
 * the loads of one hide the latency of the others. X is C-contiguous float32 (n, nf).
 * Loaded with ctypes (no Python objects cross this boundary); the module init below only makes the
 * file importable so setuptools builds and installs it like any extension.
 */
#include <Python.h>
#include <stdint.h>

enum { B = 8 };

int psafe_trees(const float *X, int64_t n, int nf, int ntrees, const int32_t *roots, const uint8_t *depth,
                const int16_t *feature, const uint8_t *missing_left, const float *threshold, const int32_t *left,
                const float *value, float base, float *out) {
    for (int64_t i = 0; i < n; i += B) {
        int m = (n - i) < B ? (int)(n - i) : B;
        float z[B];
        const float *x[B];
        for (int j = 0; j < B; j++) {
            z[j] = base;
            x[j] = X + (i + (j < m ? j : 0)) * nf;
        }
        for (int t = 0; t < ntrees; t++) {
            int32_t k[B];
            for (int j = 0; j < B; j++) k[j] = roots[t];
            for (int d = 0; d < depth[t]; d++) {
                for (int j = 0; j < B; j++) {
                    int32_t kk = k[j];
                    float v = x[j][feature[kk]];
                    int right = (v != v) ? !missing_left[kk] : (v > threshold[kk]);
                    k[j] = left[kk] + right;
                }
            }
            for (int j = 0; j < B; j++) z[j] += value[k[j]];
        }
        for (int j = 0; j < m; j++) out[i + j] = z[j];
    }
    return 0;
}

static struct PyModuleDef treesc_module = {PyModuleDef_HEAD_INIT, "_treesc", "P(safe) tree kernel (ctypes)", -1, NULL};

PyMODINIT_FUNC PyInit__treesc(void) { return PyModule_Create(&treesc_module); }
