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

REMAP_ROW = 16384  # flat remap maps are folded into rows of this length (< SHRT_MAX)


@dataclass
class Raster:
    x0: float
    y0: float
    cell: float
    H: np.ndarray  # float64 (ny, nx)

    def __post_init__(self) -> None:
        self.zref = float(self.H.mean())
        self._H32 = (self.H - self.zref).astype(np.float32)

    @property
    def shape(self) -> tuple[int, int]:
        return self.H.shape

    def sample_fast(self, x: np.ndarray, y: np.ndarray, img: np.ndarray | None = None) -> np.ndarray:
        """Bilinear sample (cv2.remap) of ``img`` (default heights) at world (x, y); flat arrays."""
        src = self._H32 if img is None else img
        mx = ((x - self.x0) / self.cell).astype(np.float32)
        my = ((y - self.y0) / self.cell).astype(np.float32)
        out = remap_flat(src, mx, my).astype(np.float64)
        return out + self.zref if img is None else out

    def sample(self, x: np.ndarray, y: np.ndarray, img: np.ndarray | None = None) -> np.ndarray:
        """Exact float64 bilinear interpolation at world (x, y) (clamped to the raster)."""
        A = self.H if img is None else img
        ny, nx = A.shape
        gx = np.clip((x - self.x0) / self.cell, 0.0, nx - 1.000001)
        gy = np.clip((y - self.y0) / self.cell, 0.0, ny - 1.000001)
        j, i = np.floor(gx), np.floor(gy)
        fx, fy = gx - j, gy - i
        k = i.astype(np.int64) * nx + j.astype(np.int64)
        flat = A.ravel()
        a = np.take(flat, k)
        a += (np.take(flat, k + 1) - a) * fx
        b = np.take(flat, k + nx)
        b += (np.take(flat, k + nx + 1) - b) * fx
        return a + (b - a) * fy

    def contains(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        ny, nx = self.H.shape
        return (
            (x >= self.x0)
            & (x <= self.x0 + (nx - 1) * self.cell)
            & (y >= self.y0)
            & (y <= self.y0 + (ny - 1) * self.cell)
        )


def remap_flat(src: np.ndarray, mx: np.ndarray, my: np.ndarray) -> np.ndarray:
    """cv2.remap bilinear lookup of float32 ``src`` at flat float32 pixel coordinates (one call).

    Remap maps are limited to SHRT_MAX per side, so the flat maps are folded into rows.
    """
    n = mx.size
    w = REMAP_ROW if n > REMAP_ROW else max(n, 1)
    rows = -(-n // w)
    if rows * w != n:
        pad = rows * w - n
        mx = np.concatenate([mx, np.zeros(pad, np.float32)])
        my = np.concatenate([my, np.zeros(pad, np.float32)])
    out = cv2.remap(src, mx.reshape(rows, w), my.reshape(rows, w), cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return out.ravel()[:n]


def intersect(
    r: Raster, C: np.ndarray, d: np.ndarray, t0: np.ndarray, t1: np.ndarray, step: np.ndarray, refine: int = 3
) -> tuple[np.ndarray, np.ndarray]:
    """First t in [t0, t1] where the ray ``C + t d`` meets the height raster.

    March with per-ray ``step`` until the ray is at or below the surface, then refine
    in the last bracket. Returns (t, hit) - ``hit`` False where the ray stayed above
    (t is then t1). Rays already below the surface at t0 report t0 (caller restarts them).
    The march runs in float32 raster units (remap quantises to 1/32 cell anyway) on
    arrays of the rays still in flight (compacted once a quarter have finished); the refinement is float64.
    """
    n = d.shape[0]
    t = t0.astype(np.float64).copy()
    lo = t.copy()
    hit = np.zeros(n, bool)
    inv = 1.0 / r.cell
    ax, ay, az = np.float32((C[0] - r.x0) * inv), np.float32((C[1] - r.y0) * inv), np.float32(C[2] - r.zref)
    idx = np.arange(n)
    ta = t.astype(np.float32)
    la = ta.copy()
    bx = (d[:, 0] * inv).astype(np.float32)
    by = (d[:, 1] * inv).astype(np.float32)
    bz = d[:, 2].astype(np.float32)
    sa = step.astype(np.float32)
    t1a = t1.astype(np.float32)
    # Finished rays stay in the arrays (``alive`` False) until they are a quarter of them: most steps
    # finish a few rays only, and compacting seven arrays each step cost about as much as the step.
    # A finished ray's entries are never read again, so the live rays march exactly as before.
    alive = np.ones(n, bool)
    live, dead = n, 0
    while live:
        f = az + ta * bz - remap_flat(r._H32, ax + ta * bx, ay + ta * by)
        below = f <= 0.0
        if dead:
            below &= alive
        if below.any():
            bi = idx[below]
            hit[bi] = True
            t[bi] = ta[below]
            lo[bi] = la[below]
        nt = ta + sa
        over = ~below & (nt > t1a)
        if dead:
            over &= alive
        if over.any():
            # one last probe exactly at t1
            oi = idx[over]
            tz = t1[oi]
            fz = C[2] + tz * d[oi, 2] - r.sample_fast(C[0] + tz * d[oi, 0], C[1] + tz * d[oi, 1])
            t[oi] = tz
            lo[oi] = ta[over]
            hit[oi] = fz <= 0
        done = below | over
        nd = int(np.count_nonzero(done))
        la, ta = ta, nt
        if not nd:
            continue
        alive &= ~done
        live, dead = live - nd, dead + nd
        if 4 * dead >= live + dead:
            keep = alive
            idx, la, ta = idx[keep], la[keep], ta[keep]
            bx, by, bz, sa, t1a = bx[keep], by[keep], bz[keep], sa[keep], t1a[keep]
            alive = np.ones(live, bool)
            dead = 0
    return refine_roots(r, C, d, t, lo, hit, refine), hit


def refine_roots(
    r: Raster, C: np.ndarray, d: np.ndarray, t: np.ndarray, lo: np.ndarray, hit: np.ndarray, refine: int
) -> np.ndarray:
    """``t`` with each hit ray's root refined by regula falsi on the exact bilinear surface inside its
    march bracket ``[lo, t]`` (``refine`` steps: the bracket narrowed on the fast sampler, finished on
    the exact one). ``t`` is updated in place and returned."""
    m = hit & (t > lo)
    a, b = lo[m], t[m]
    dm = d[m]

    def fast(tv):
        return C[2] + tv * dm[:, 2] - r.sample_fast(C[0] + tv * dm[:, 0], C[1] + tv * dm[:, 1])

    def fn(tv):
        return C[2] + tv * dm[:, 2] - r.sample(C[0] + tv * dm[:, 0], C[1] + tv * dm[:, 1])

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
    return t
