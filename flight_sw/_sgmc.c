/* Semi-global aggregation kernel (Hirschmueller 2008, eq. 13) for flight_sw.sgm.
 *
 * Same arithmetic as the numpy reference flight_sw.sgm.aggregate (tested equal): for one
 * path direction r = (dr, dc) and every pixel p, in path order,
 *
 *   L_r(p, k) = C(p, k) + min(L(p-r, k), L(p-r, k-1) + P1, L(p-r, k+1) + P1, m + P2(p)) - m,
 *   m = min_i L(p-r, i),   L_r(p, k) = C(p, k) where p - r lies outside the image,
 *
 * and S(p, k) += L_r(p, k). Arrays are C-contiguous int16: cost and S (h, w, D), P2 (h, w).
 * Loaded with ctypes (no Python objects cross this boundary); the module init below only
 * makes the file importable so setuptools builds and installs it like any extension.
 */
#include <Python.h>
#include <stdint.h>
#include <stdlib.h>

static void one_path(const int16_t *C, const int16_t *P2, int h, int w, int D, int p1, int dr, int dc, int16_t *S,
                     int16_t *bufA, int16_t *bufB, int *minA, int *minB) {
    int r0 = dr >= 0 ? 0 : h - 1, rstep = dr >= 0 ? 1 : -1;
    int c0 = dc >= 0 ? 0 : w - 1, cstep = dc >= 0 ? 1 : -1;
    int16_t *prev = bufA, *cur = bufB;
    int *pmin = minA, *cmin = minB;
    for (int ri = 0; ri < h; ri++) {
        int r = r0 + ri * rstep;
        for (int ci = 0; ci < w; ci++) {
            int c = c0 + ci * cstep;
            const int16_t *cc = C + ((size_t)r * w + c) * D;
            int16_t *L = cur + (size_t)c * D;
            int16_t *Sp = S + ((size_t)r * w + c) * D;
            int pr = r - dr, pc = c - dc;
            int mn = 32767;
            if (pr < 0 || pr >= h || pc < 0 || pc >= w) {
                for (int d = 0; d < D; d++) {
                    int v = cc[d];
                    L[d] = (int16_t)v;
                    Sp[d] = (int16_t)(Sp[d] + v);
                    if (v < mn) mn = v;
                }
            } else {
                const int16_t *Lp = (dr == 0 ? cur : prev) + (size_t)pc * D;
                int mp = dr == 0 ? cmin[pc] : pmin[pc];
                int16_t big = (int16_t)(mp + P2[(size_t)r * w + c]), m16 = (int16_t)mp, q1 = (int16_t)p1;
                int16_t v0 = Lp[0], t0 = (int16_t)(Lp[1] + q1);
                v0 = t0 < v0 ? t0 : v0;
                v0 = big < v0 ? big : v0;
                L[0] = (int16_t)(cc[0] + v0 - m16);
                int16_t vn = Lp[D - 1], tn = (int16_t)(Lp[D - 2] + q1);
                vn = tn < vn ? tn : vn;
                vn = big < vn ? big : vn;
                L[D - 1] = (int16_t)(cc[D - 1] + vn - m16);
                /* branch-free interior: the compiler vectorises it (int16 lanes) */
                for (int d = 1; d < D - 1; d++) {
                    int16_t a = Lp[d - 1] < Lp[d + 1] ? Lp[d - 1] : Lp[d + 1];
                    a = (int16_t)(a + q1);
                    int16_t v = Lp[d] < a ? Lp[d] : a;
                    v = big < v ? big : v;
                    L[d] = (int16_t)(cc[d] + v - m16);
                }
                int16_t m2 = 32767;
                for (int d = 0; d < D; d++) {
                    Sp[d] = (int16_t)(Sp[d] + L[d]);
                    m2 = L[d] < m2 ? L[d] : m2;
                }
                mn = m2;
            }
            cmin[c] = mn;
        }
        if (dr != 0) {
            int16_t *t = prev;
            prev = cur;
            cur = t;
            int *tm = pmin;
            pmin = cmin;
            cmin = tm;
        }
    }
}

/* dirs: n pairs (dr, dc); P2: n maps of h*w; adds every path to S (zeroed by the caller).
 * Returns 0, or -1 if a line buffer could not be allocated. */
int sgm_aggregate(const int16_t *C, const int16_t *P2, const int *dirs, int n, int h, int w, int D, int p1,
                  int16_t *S) {
    int16_t *a = malloc(sizeof(int16_t) * (size_t)w * D), *b = malloc(sizeof(int16_t) * (size_t)w * D);
    int *ma = malloc(sizeof(int) * (size_t)w), *mb = malloc(sizeof(int) * (size_t)w);
    if (!a || !b || !ma || !mb) {
        free(a), free(b), free(ma), free(mb);
        return -1;
    }
    for (int i = 0; i < n; i++)
        one_path(C, P2 + (size_t)i * h * w, h, w, D, p1, dirs[2 * i], dirs[2 * i + 1], S, a, b, ma, mb);
    free(a), free(b), free(ma), free(mb);
    return 0;
}

static struct PyModuleDef moddef = {PyModuleDef_HEAD_INIT, "_sgmc", "SGM kernel, loaded with ctypes", -1, NULL};

PyMODINIT_FUNC PyInit__sgmc(void) { return PyModule_Create(&moddef); }
