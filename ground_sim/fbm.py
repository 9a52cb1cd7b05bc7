"""Band-limited fractional Brownian relief, evaluable at any point or on a raster.

Each octave ``o`` is cubic-B-spline interpolated white noise on a square lattice
of spacing ``lambda_o = max_wavelength / 2**o`` (node values from a hash, so any
window is reproducible). The amplitude per octave follows the fBm power law
``a_o ~ lambda_o**H`` (H = Hurst exponent, scenes.md sec. 4), normalised so the
whole sum has the requested RMS; an optional "micro-roughness" component adds
variance to octaves shorter than ``micro_scale``. B-splines make the surface C2,
so shading from normals shows no lattice creases.

Band-limiting is the terrain-level anti-aliasing: octaves with wavelength below
``min_wavelength`` are dropped and the octave just above it fades in with a
smoothstep, so a raster with cell ``c`` evaluated with ``min_wavelength = 2c``
holds no content above its Nyquist frequency.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ground_sim.hashing import uniform

STREAM = 1


def _bspline_weights(t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Uniform cubic B-spline weights for nodes i-1, i, i+1, i+2 at fraction t."""
    t2, t3 = t * t, t * t * t
    return ((1 - t) ** 3 / 6.0, (3 * t3 - 6 * t2 + 4) / 6.0, (-3 * t3 + 3 * t2 + 3 * t + 1) / 6.0, t3 / 6.0)


def _bspline_var() -> float:
    """Mean over t of sum_k w_k(t)^2: variance of 1-D B-spline interpolated unit white noise."""
    t = (np.arange(4096) + 0.5) / 4096
    return float(np.mean(sum(w * w for w in _bspline_weights(t))))


_VAR1D = _bspline_var()


def _smoothstep(x: np.ndarray | float) -> np.ndarray | float:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3 - 2 * x)


@dataclass(frozen=True)
class FBm:
    """fBm parameters; ``amplitudes()`` gives the node scale per octave."""

    seed: int
    rms_m: float
    hurst: float
    max_wavelength_m: float = 2048.0
    n_octaves: int = 18
    micro_rms_m: float = 0.0
    micro_scale_m: float = 4.0

    def wavelengths(self) -> np.ndarray:
        return self.max_wavelength_m / 2.0 ** np.arange(self.n_octaves)

    def amplitudes(self) -> np.ndarray:
        """Node standard deviation per octave (before band-limiting)."""
        lam = self.wavelengths()
        base = (lam / lam[0]) ** self.hurst
        base = self.rms_m * base / np.sqrt(np.sum(base**2))
        micro = np.where(lam <= self.micro_scale_m, (lam / self.micro_scale_m) ** self.hurst, 0.0)
        if micro.any():
            micro = self.micro_rms_m * micro / np.sqrt(np.sum(micro**2))
        return np.sqrt(base**2 + micro**2) / _VAR1D  # 2-D variance is _VAR1D**2

    def _weights(self, min_wavelength: float) -> np.ndarray:
        lam = self.wavelengths()
        return self.amplitudes() * _smoothstep(lam / max(min_wavelength, 1e-9) - 1.0)

    def _offset(self, o: int) -> tuple[float, float]:
        u = uniform(self.seed, STREAM, o, -1, np.array([0, 1]))
        return float(u[0]), float(u[1])

    def _nodes(self, o: int, ix: np.ndarray, iy: np.ndarray) -> np.ndarray:
        return (uniform(self.seed, STREAM, o, ix, iy) - 0.5) * np.sqrt(12.0)

    def at(self, x: np.ndarray, y: np.ndarray, min_wavelength: float = 0.0) -> np.ndarray:
        """Height at scattered points (any shape): 16 hashed nodes per octave."""
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        out = np.zeros(np.broadcast(x, y).shape)
        for o, (lam, a) in enumerate(zip(self.wavelengths(), self._weights(min_wavelength))):
            if a == 0.0:
                continue
            ox, oy = self._offset(o)
            gx, gy = x / lam + ox, y / lam + oy
            ix, iy = np.floor(gx), np.floor(gy)
            wx, wy = _bspline_weights(gx - ix), _bspline_weights(gy - iy)
            ix, iy = ix.astype(np.int64), iy.astype(np.int64)
            acc = np.zeros_like(out)
            for j in range(4):
                row = np.zeros_like(out)
                for i in range(4):
                    row += wx[i] * self._nodes(o, ix + i - 1, iy + j - 1)
                acc += wy[j] * row
            out += a * acc
        return out

    def raster(self, xs: np.ndarray, ys: np.ndarray, min_wavelength: float = 0.0) -> np.ndarray:
        """Height on the grid ``ys[:,None] x xs[None,:]`` (both regularly spaced, ascending).

        Separable: each octave is interpolated along x on the node rows, then along y.
        Coarse octaves use a small dense weight matrix (BLAS); when the node spacing is an
        integer number of cells the fine ones use strided per-phase slices (no gathers).
        """
        xs = np.asarray(xs, dtype=np.float64)
        ys = np.asarray(ys, dtype=np.float64)
        out = np.zeros((ys.size, xs.size))
        for o, (lam, a) in enumerate(zip(self.wavelengths(), self._weights(min_wavelength))):
            if a == 0.0:
                continue
            ox, oy = self._offset(o)
            gx, gy = xs / lam + ox, ys / lam + oy
            x0 = int(np.floor(gx.min())) - 1
            y0 = int(np.floor(gy.min())) - 1
            nodes = self._nodes(
                o,
                np.arange(x0, int(np.floor(gx.max())) + 3)[None, :],
                np.arange(y0, int(np.floor(gy.max())) + 3)[:, None],
            )
            tmp = _interp_axis(nodes.T, gx - x0).T  # (ny_nodes, nx)
            out += a * _interp_axis(tmp, gy - y0)
        return out


def _interp_axis(nodes: np.ndarray, g: np.ndarray) -> np.ndarray:
    """B-spline interpolate ``nodes`` along axis 0 at lattice coordinates ``g`` (node 0 at g=0)."""
    n = g.size
    step = (g[-1] - g[0]) / (n - 1) if n > 1 else 1.0
    k = int(round(1.0 / step)) if step > 0 else 0
    ig = np.floor(g).astype(np.int64)
    w = _bspline_weights(g - ig)
    if nodes.shape[0] <= 48 or k < 2:
        # dense weights: (n x n_nodes) @ nodes
        W = np.zeros((n, nodes.shape[0]))
        rows = np.arange(n)
        for i in range(4):
            np.add.at(W, (rows, ig + i - 1), w[i])
        return W @ nodes
    if k <= 64 and abs(1.0 / k - step) < 1e-9 * max(1.0, abs(g[-1])):
        out = np.empty((n,) + nodes.shape[1:])
        for p in range(min(k, n)):
            sl = slice(p, n, k)
            m = len(range(p, n, k))
            b = ig[p]
            acc = w[0][p] * nodes[b - 1 : b - 1 + m]
            for i in range(1, 4):
                acc += w[i][p] * nodes[b - 1 + i : b - 1 + i + m]
            out[sl] = acc
        return out
    return sum(w[i].reshape((n,) + (1,) * (nodes.ndim - 1)) * nodes[ig + i - 1] for i in range(4))
