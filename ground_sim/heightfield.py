"""A world-aligned height raster and ray intersection against it.

Raster convention: ``H[i, j]`` is the height at ``x = x0 + j*cell, y = y0 + i*cell``.
Marching uses OpenCV bilinear sampling (fast; positions quantised to 1/32 cell), the
final root is refined by regula falsi on exact float64 bilinear interpolation, so the
returned hit lies on the bilinear surface through the raster samples.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass
class Raster:
    x0: float
    y0: float
    cell: float
    H: np.ndarray            # float64 (ny, nx)

    def __post_init__(self) -> None:
        self.zref = float(self.H.mean())
        self._H32 = (self.H - self.zref).astype(np.float32)

    @property
    def shape(self) -> tuple[int, int]:
        return self.H.shape

    def sample_fast(self, x: np.ndarray, y: np.ndarray, img: np.ndarray | None = None) -> np.ndarray:
        """Bilinear sample (cv2.remap) of ``img`` (default heights) at world (x, y); flat arrays."""
        src = self._H32 if img is None else img
        mx = ((x - self.x0) / self.cell).astype(np.float32).reshape(1, -1)
        my = ((y - self.y0) / self.cell).astype(np.float32).reshape(1, -1)
        out = np.empty(mx.shape, np.float32)
        n = mx.shape[1]
        step = 32000   # remap maps are limited to SHRT_MAX columns
        for s in range(0, n, step):
            out[:, s:s + step] = cv2.remap(src, mx[:, s:s + step], my[:, s:s + step], cv2.INTER_LINEAR,
                                           borderMode=cv2.BORDER_REPLICATE)
        out = out.ravel().astype(np.float64)
        return out + self.zref if img is None else out

    def sample(self, x: np.ndarray, y: np.ndarray, img: np.ndarray | None = None) -> np.ndarray:
        """Exact float64 bilinear interpolation at world (x, y) (clamped to the raster)."""
        A = self.H if img is None else img
        ny, nx = A.shape
        gx = np.clip((x - self.x0) / self.cell, 0.0, nx - 1.000001)
        gy = np.clip((y - self.y0) / self.cell, 0.0, ny - 1.000001)
        j, i = np.floor(gx).astype(np.int64), np.floor(gy).astype(np.int64)
        fx, fy = gx - j, gy - i
        a = A[i, j] * (1 - fx) + A[i, j + 1] * fx
        b = A[i + 1, j] * (1 - fx) + A[i + 1, j + 1] * fx
        return a * (1 - fy) + b * fy

    def contains(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        ny, nx = self.H.shape
        return ((x >= self.x0) & (x <= self.x0 + (nx - 1) * self.cell)
                & (y >= self.y0) & (y <= self.y0 + (ny - 1) * self.cell))


def intersect(r: Raster, C: np.ndarray, d: np.ndarray, t0: np.ndarray, t1: np.ndarray,
              step: np.ndarray, refine: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """First t in [t0, t1] where the ray ``C + t d`` meets the height raster.

    March with per-ray ``step`` until the ray is at or below the surface, then refine
    in the last bracket. Returns (t, hit) - ``hit`` False where the ray stayed above
    (t is then t1). Rays already below the surface at t0 report t0 (caller restarts them).
    """
    n = d.shape[0]
    t = t0.astype(np.float64).copy()
    lo = t.copy()
    hit = np.zeros(n, bool)
    done = np.zeros(n, bool)
    active = np.arange(n)
    first = True
    while active.size:
        tt = t[active]
        px = C[0] + tt * d[active, 0]
        py = C[1] + tt * d[active, 1]
        f = C[2] + tt * d[active, 2] - r.sample_fast(px, py)
        below = f <= 0.0
        if first:
            lo[active[below]] = t[active[below]]   # no bracket: already under
            first = False
        idx = active[below]
        hit[idx] = True
        done[idx] = True
        rest = active[~below]
        lo[rest] = t[rest]
        t[rest] = t[rest] + step[rest]
        over = t[rest] > t1[rest]
        if np.any(over):
            ov = rest[over]
            # one last probe exactly at t1
            fz = C[2] + t1[ov] * d[ov, 2] - r.sample_fast(C[0] + t1[ov] * d[ov, 0], C[1] + t1[ov] * d[ov, 1])
            ok = fz <= 0
            t[ov] = t1[ov]
            hit[ov[ok]] = True
            done[ov] = True
        active = rest[~over]
    # regula falsi on the exact bilinear surface inside [lo, t]
    m = hit & (t > lo)
    a, b = lo[m], t[m]
    dm = d[m]

    def fast(tv):
        return C[2] + tv * dm[:, 2] - r.sample_fast(C[0] + tv * dm[:, 0], C[1] + tv * dm[:, 1])

    def fn(tv):
        return C[2] + tv * dm[:, 2] - r.sample(C[0] + tv * dm[:, 0], C[1] + tv * dm[:, 1])

    # narrow the bracket on the fast sampler, finish on the exact surface
    fa, fb = fast(a), fast(b)
    for it in range(refine):
        if it == refine - 2 or refine == 1:
            fa, fb = fn(a), fn(b)
        fn_it = fn if it >= refine - 2 else fast
        fa_pos = fa > 0
        denom = np.where(fa - fb == 0, 1.0, fa - fb)
        c = np.where(fa_pos & (fb <= 0), a + (b - a) * fa / denom, b)
        fc = fn_it(c)
        up = fc > 0
        a, fa = np.where(up, c, a), np.where(up, fc, fa)
        b, fb = np.where(up, b, c), np.where(up, fb, fc)
    t[m] = np.where(np.abs(fa) < np.abs(fb), a, b)
    return t, hit
