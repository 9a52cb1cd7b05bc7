"""Ground-truth hazard from the true height raster (DESIGN.md "Hazard definitions").

Least-squares plane over a disk of diameter ``footprint`` (3 m) around each raster cell:
with offsets (dx, dy) over a symmetric disk, the normal equations decouple, so
``a = sum z / N``, ``b = sum dx z / sum dx^2``, ``c = sum dy z / sum dy^2`` (three
correlations). Slope = atan(sqrt(b^2 + c^2)), scaled 0->1 at 15 deg; roughness = |z - a|
(the plane's height at the point), scaled 0->1 at 0.30 m; hazard = max(slope, rough, shadow).
The plane is fitted on a raster coarsened so the disk spans <= ~25 cells (bounded cost),
and its coefficients are interpolated back (they are smooth at that scale).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import cv2
import numpy as np

SLOPE_LIMIT_DEG = 15.0
ROUGH_LIMIT_M = 0.30
FOOTPRINT_M = 3.0


def plane_fit_factor(cell: float, footprint: float = FOOTPRINT_M, max_radius_cells: int = 12) -> int:
    """Coarsening factor of :func:`plane_fit`: the disk spans at most ``max_radius_cells`` coarse cells."""
    return max(1, int(math.ceil((footprint / 2) / (max_radius_cells * cell))))


def footprint_disk(n: int, cell: float, footprint: float = FOOTPRINT_M) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(dx, dy, disk): the offsets (m) of a (2n+1)^2 block of ``cell`` cells and the float mask of those within
    ``footprint / 2`` of its centre, the support of every plane fit here (DESIGN.md "Hazard definitions")."""
    off = np.arange(-n, n + 1) * cell
    dx, dy = np.meshgrid(off, off)
    return dx, dy, (dx**2 + dy**2 <= (footprint / 2) ** 2 + 1e-9).astype(np.float64)


def plane_fit(
    H: np.ndarray, cell: float, footprint: float = FOOTPRINT_M, max_radius_cells: int = 12
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(a, b, c) rasters of the LSQ plane ``z = a + b dx + c dy`` over a disk around each cell."""
    k = plane_fit_factor(cell, footprint, max_radius_cells)
    Hc = cv2.resize(H, (H.shape[1] // k, H.shape[0] // k), interpolation=cv2.INTER_AREA) if k > 1 else H
    cc = cell * k
    rad = footprint / 2 / cc
    dx, dy, disk = footprint_disk(int(math.floor(rad)), cc, footprint)
    if disk.sum() < 5:  # footprint under ~2 cells: 3x3 neighbourhood
        disk = np.ones((3, 3))
        dx, dy = np.meshgrid(np.array([-cc, 0, cc]), np.array([-cc, 0, cc]))
    kz = disk / disk.sum()
    kx = disk * dx / np.sum(disk * dx * dx)
    ky = disk * dy / np.sum(disk * dy * dy)
    zref = float(Hc.mean())
    Z = Hc - zref
    a = cv2.filter2D(Z, -1, kz, borderType=cv2.BORDER_REFLECT) + zref
    b = cv2.filter2D(Z, -1, kx, borderType=cv2.BORDER_REFLECT)  # filter2D is correlation
    c = cv2.filter2D(Z, -1, ky, borderType=cv2.BORDER_REFLECT)
    if k > 1:
        size = (H.shape[1], H.shape[0])
        # coarse cell centre (i+0.5)k-0.5 in fine indices: cv2.resize linear uses the same convention
        a, b, c = (cv2.resize(m, size, interpolation=cv2.INTER_LINEAR) for m in (a, b, c))  # type: ignore[assignment]
    return a, b, c


# The slope and roughness truth is taken on a raster of at most this cell: on a coarser one the 3 m disk holds
# too few cells and plane_fit falls back to a 3x3 block, a window of 2-3 cells a side (5-10 m on high oblique
# views), which smooths footprint-scale slopes away (docs/scenes.md, "Ground-truth accuracy", item 6).
TRUTH_CELL_M = 0.5
# The footprint raster's cost grows with the ground a view covers, not with its pixels: a view may spend at most
# this many cells per pixel on it, and a coarser cell of TRUTH_CELLS_M is taken beyond (a small camera high up).
# Every 512 px view of the table altitudes stays at TRUTH_CELL_M (the approach's 2400 m view, the widest, takes
# 109-114 cells a pixel); a 128 px camera there would take 1746, and gets the view raster. A coarser cell is a
# coarser truth: the raster's band limit (2 cells) drops boulders under one cell, and a 0.5-1 m boulder can stand
# the 0.30 m roughness limit high, so the same ground's truth then depends on the camera.
TRUTH_CELLS_PER_PIXEL = 128
TRUTH_CELLS_M = (TRUTH_CELL_M, 0.75, 1.0)
# cells of one strip of footprint_planes' raster: about 10 float64 arrays of it live at once (~160 MB)
STRIP_CELLS = 2_000_000

HeightRaster = Callable[[float, float, float, int, int], np.ndarray]


def footprint_cell(view_cell: float, ground_m2_per_pixel: float) -> float | None:
    """The cell of the raster :func:`footprint_planes` takes a view's slope and roughness truth on: the finest of
    :data:`TRUTH_CELLS_M` that is finer than the view raster's ``view_cell`` and costs at most
    :data:`TRUTH_CELLS_PER_PIXEL` cells per pixel (``ground_m2_per_pixel / cell^2``). None when the view raster
    is as fine (it holds the disk: :func:`plane_fit` on it), or when none fits (the view raster again)."""
    for cell in TRUTH_CELLS_M:
        if cell >= view_cell:
            return None
        if ground_m2_per_pixel / cell**2 <= TRUTH_CELLS_PER_PIXEL:
            return cell
    return None


def disk_kernels(cell: float, footprint: float = FOOTPRINT_M) -> tuple[int, np.ndarray, np.ndarray, np.ndarray]:
    """(halo n, kz, kx, ky): correlation kernels of the LSQ plane over the cell centres within ``footprint / 2``
    of a raster node, never coarsened and never a 3x3 block. The disk is symmetric, so the normal equations
    decouple: a = sum z / N, b = sum dx z / sum dx^2, c = sum dy z / sum dy^2."""
    n = int(math.floor(footprint / 2 / cell + 1e-9))
    if n < 1:
        raise ValueError(f"a raster of {cell:g} m cells holds no {footprint:g} m disk")
    dx, dy, disk = footprint_disk(n, cell, footprint)
    return n, disk / disk.sum(), disk * dx / np.sum(disk * dx * dx), disk * dy / np.sum(disk * dy * dy)


def bilinear_inside(A: np.ndarray, gx: np.ndarray, gy: np.ndarray) -> np.ndarray:
    """``A`` at fractional (column, row) positions that lie inside it, float64 bilinear."""
    j, i = np.floor(gx).astype(np.int64), np.floor(gy).astype(np.int64)
    fx, fy = gx - j, gy - i
    top = A[i, j] + (A[i, j + 1] - A[i, j]) * fx
    bottom = A[i + 1, j] + (A[i + 1, j + 1] - A[i + 1, j]) * fx
    return top + (bottom - top) * fy


def footprint_planes(
    heights: HeightRaster,
    X: np.ndarray,
    Y: np.ndarray,
    cell: float = TRUTH_CELL_M,
    footprint: float = FOOTPRINT_M,
    strip_cells: int = STRIP_CELLS,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(z, a, b, c) at ground points (X, Y): the terrain height and the LSQ plane ``z = a + b dx + c dy`` over
    the ``footprint`` disk (DESIGN.md "Hazard definitions"), on a world-aligned raster of ``cell`` (nodes at
    multiples of ``cell``) whose heights ``heights(x0, y0, cell, nx, ny)`` gives (row i at y0 + i cell).

    The plane's moments are correlations with :func:`disk_kernels` at the nodes, interpolated bilinearly to the
    points, as :func:`plane_fit` does on a view raster. The raster is built in row strips of about
    ``strip_cells`` cells, each only as wide as its points need and a disk plus two cells beyond them, so no disk
    reaches a strip's edge: the result does not depend on the strips (to rounding), and the same ground point gets
    the same truth from every view on the same cell. Memory stays bounded by ``strip_cells``."""
    X = np.asarray(X, np.float64).ravel()
    Y = np.asarray(Y, np.float64).ravel()
    out = tuple(np.full(X.shape, np.nan) for _ in range(4))
    if X.size == 0:
        return out  # type: ignore[return-value]
    if not (np.all(np.isfinite(X)) and np.all(np.isfinite(Y))):
        raise ValueError("footprint_planes: ground points must be finite")
    n, kz, kx, ky = disk_kernels(cell, footprint)
    pad = n + 2  # the disk and the bilinear neighbour stay on the strip
    gx_all, gy_all = X / cell, Y / cell
    row = np.floor(gy_all).astype(np.int64)
    order = np.argsort(row, kind="stable")
    rows = row[order]
    width = float(np.floor(gx_all.max()) - np.floor(gx_all.min())) + 2 * pad + 2
    strip = max(16, int(strip_cells / width) - 2 * pad)
    for r0 in range(int(rows[0]), int(rows[-1]) + 1, strip):
        k0, k1 = np.searchsorted(rows, [r0, r0 + strip])
        if k1 <= k0:
            continue
        idx = order[k0:k1]
        gx, gy = gx_all[idx], gy_all[idx]
        c0 = int(np.floor(gx.min())) - pad
        c1 = int(np.floor(gx.max())) + 1 + pad
        i0, i1 = r0 - pad, int(np.floor(gy.max())) + 1 + pad
        H = np.asarray(heights(c0 * cell, i0 * cell, cell, c1 - c0 + 1, i1 - i0 + 1), np.float64)
        zref = float(H.mean())
        Z = H - zref
        lx, ly = gx - c0, gy - i0
        sample = (bilinear_inside(m, lx, ly) for m in (H, *(cv2.filter2D(Z, cv2.CV_64F, k) for k in (kz, kx, ky))))
        for dst, v, shift in zip(out, sample, (0.0, zref, 0.0, 0.0)):
            dst[idx] = v + shift
    return out  # type: ignore[return-value]


def hazard_layers(z: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray, shadow: np.ndarray) -> np.ndarray:
    """Hazard in [0,1] per DESIGN.md from point heights z and the local plane (a, b, c)."""
    slope = np.degrees(np.arctan(np.hypot(b, c)))
    hz = np.maximum(np.clip(slope / SLOPE_LIMIT_DEG, 0, 1), np.clip(np.abs(z - a) / ROUGH_LIMIT_M, 0, 1))
    return np.maximum(hz, shadow.astype(np.float64)).astype(np.float32)


# a pixel's ground grid has at most this many cells per image pixel: an oblique view's far field spreads its
# pixels over a wide area, and the grid is coarsened rather than allocated without bound
MAX_GRID_CELLS_PER_PIXEL = 2.0
MIN_DISK_SHARE = 0.5  # a footprint disk less than half seen has no truth (its plane is an extrapolation)
# the grid spans the points between these percentiles of X and of Y (plus a footprint): a few stray points (a
# far-plane depth written for the sky) made it so wide that every cell grew past the footprint
EXTENT_PCT = (0.5, 99.5)
BAND_ROWS = 128  # the plane fit runs over bands of this many grid rows (plus the disk's halo): memory stays bounded


def weighted_plane_fit(
    Z: np.ndarray, W: np.ndarray, cell: float, footprint: float = FOOTPRINT_M, min_share: float = MIN_DISK_SHARE
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(a, b, c) rasters (float32) of the weighted LSQ plane ``z = a + b dx + c dy`` over a disk of diameter
    ``footprint`` around each cell of a grid where only some cells hold a height (``W`` > 0; ``Z`` is ignored
    elsewhere).

    The disk is no longer symmetric about the cell once some of it is missing, so the normal equations do not
    decouple as in :func:`plane_fit`: with sums over the disk's cells q, S_fg = sum W(q) f(q) g(q) for f, g in
    {1, dx, dy, z}, each one correlation (``cv2.filter2D``, O(1) per cell for a fixed disk),
    ``[[S_11, S_1x, S_1y], [S_1x, S_xx, S_xy], [S_1y, S_xy, S_yy]] (a, b, c) = (S_1z, S_xz, S_yz)``,
    solved per cell by Cramer's rule, over bands of :data:`BAND_ROWS` rows with the disk's halo (exact: outside
    the grid counts as no data either way). NaN where the disk holds less than ``min_share`` of its cells or the
    system is singular (a line of cells), and everywhere when the footprint spans under ~2 cells (unlike
    :func:`plane_fit`, which then takes the 3x3 neighbourhood of a raster finer than any pixel: here the cells
    are the camera's, and a wider plane would be truth at another scale than DESIGN.md's)."""
    n = max(1, int(math.floor(footprint / 2 / cell)))
    dx, dy, disk = footprint_disk(n, cell, footprint)
    shape = np.shape(Z)
    out: tuple[np.ndarray, np.ndarray, np.ndarray] = (
        np.full(shape, np.nan, np.float32),
        np.full(shape, np.nan, np.float32),
        np.full(shape, np.nan, np.float32),
    )
    if disk.sum() < 5:  # a footprint of under ~2 cells: the grid cannot tell its slope
        return out
    seen = W > 0
    zref = float(np.mean(Z[seen])) if seen.any() else 0.0
    # a plane needs a disk seen in two directions: det relative to a full disk's (scale-free)
    full = disk.sum() * np.sum(disk * dx * dx) * np.sum(disk * dy * dy)
    kernels = [disk, disk * dx, disk * dy, disk * dx * dx, disk * dx * dy, disk * dy * dy]

    def corr(img: np.ndarray, k: np.ndarray) -> np.ndarray:
        return cv2.filter2D(img, cv2.CV_64F, k, borderType=cv2.BORDER_CONSTANT)  # outside the grid: no data

    for r0 in range(0, shape[0], BAND_ROWS):
        r1 = min(shape[0], r0 + BAND_ROWS)
        h0, h1 = max(0, r0 - n), min(shape[0], r1 + n)  # the halo the disk reaches into
        w = np.where(seen[h0:h1], W[h0:h1], 0.0).astype(np.float64)
        wz = w * np.where(seen[h0:h1], Z[h0:h1] - zref, 0.0)
        s1, sx, sy, sxx, sxy, syy = (corr(w, k)[r0 - h0 : r1 - h0] for k in kernels)
        sz, sxz, syz = (corr(wz, k)[r0 - h0 : r1 - h0] for k in kernels[:3])
        m11, m12, m13 = sxx * syy - sxy * sxy, sx * syy - sxy * sy, sx * sxy - sxx * sy  # cofactors of row 1
        det = s1 * m11 - sx * m12 + sy * m13
        ok = (s1 >= min_share * disk.sum()) & (det > 1e-6 * full)
        det = np.where(ok, det, 1.0)
        a = (sz * m11 - sx * (sxz * syy - sxy * syz) + sy * (sxz * sxy - sxx * syz)) / det
        b = (s1 * (sxz * syy - syz * sxy) - sz * m12 + sy * (sx * syz - sxz * sy)) / det
        c = (s1 * (sxx * syz - sxy * sxz) - sx * (sx * syz - sxz * sy) + sz * m13) / det
        for dst, v in zip(out, (a + zref, b, c)):
            dst[r0:r1][ok] = v[ok]
    return out


def coarser_step_m(X: np.ndarray, Y: np.ndarray) -> float:
    """The ground sample distance along the image's coarser direction: the median ground distance between
    neighbouring pixels in rows and in columns (of each pixel's ground X, Y), the larger of the two; 0 when no two
    neighbours have ground. A grid finer than this leaves gaps between the pixels' rows."""
    steps = [np.hypot(np.diff(X, axis=k), np.diff(Y, axis=k)) for k in (0, 1)]
    return max(
        float(np.median(s[np.isfinite(s) & (s > 0)])) if np.any(np.isfinite(s) & (s > 0)) else 0.0 for s in steps
    )


def truth_grid(points: np.ndarray) -> tuple[float, float, float, int, int, np.ndarray]:
    """The ground grid :func:`hazard_from_points` bins ``points`` on: (cell m, x0, y0, columns, rows, and the
    pixels it holds). The cell is the coarser-direction ground sample distance (:func:`coarser_step_m`), grown
    when the grid would pass :data:`MAX_GRID_CELLS_PER_PIXEL`; the grid spans the points within
    :data:`EXTENT_PCT` of X and Y plus a footprint, and the points beyond are left out."""
    X, Y, Z = points[..., 0], points[..., 1], points[..., 2]
    valid = np.isfinite(X) & np.isfinite(Y) & np.isfinite(Z)
    if np.count_nonzero(valid) < 3:
        return math.inf, 0.0, 0.0, 0, 0, np.zeros(X.shape, bool)
    (x0, x1), (y0, y1) = (np.percentile(v[valid], EXTENT_PCT) for v in (X, Y))
    x0, y0, x1, y1 = x0 - FOOTPRINT_M, y0 - FOOTPRINT_M, x1 + FOOTPRINT_M, y1 + FOOTPRINT_M
    held = valid & (np.abs(X - (x0 + x1) / 2) <= (x1 - x0) / 2) & (np.abs(Y - (y0 + y1) / 2) <= (y1 - y0) / 2)
    cell = max(coarser_step_m(np.where(held, X, np.nan), np.where(held, Y, np.nan)), FOOTPRINT_M / 24)
    budget = MAX_GRID_CELLS_PER_PIXEL * X.size
    cell = max(cell, math.sqrt((x1 - x0 + cell) * (y1 - y0 + cell) / budget))
    return cell, float(x0), float(y0), int((x1 - x0) / cell) + 1, int((y1 - y0) / cell) + 1, held


def _bilinear(grids: tuple[np.ndarray, ...], fx: np.ndarray, fy: np.ndarray) -> list[np.ndarray]:
    """Each grid at fractional (column, row) positions, bilinear, clamped at the edges; NaN spreads to the four
    cells' neighbourhood (numpy: ``cv2.remap`` refuses grids of 32767 or more cells a side)."""
    gh, gw = grids[0].shape
    fx = np.clip(fx, 0.0, gw - 1.0)
    fy = np.clip(fy, 0.0, gh - 1.0)
    i0 = np.minimum(fx.astype(np.int64), max(gw - 2, 0))
    j0 = np.minimum(fy.astype(np.int64), max(gh - 2, 0))
    tx, ty = (fx - i0).astype(np.float32), (fy - j0).astype(np.float32)
    k00 = j0 * gw + i0
    k01, k10 = k00 + (1 if gw > 1 else 0), k00 + (gw if gh > 1 else 0)
    k11 = k10 + (1 if gw > 1 else 0)
    out = []
    for g in grids:
        f = g.ravel()
        out.append((f[k00] * (1 - tx) + f[k01] * tx) * (1 - ty) + (f[k10] * (1 - tx) + f[k11] * tx) * ty)
    return out


POINTS_PER_CHUNK = 1 << 20  # the pixels are sampled and judged this many at a time: their temporaries stay bounded


def hazard_from_points(points: np.ndarray, shadow: np.ndarray | None = None) -> np.ndarray:
    """Ground-truth hazard (float32 HxW in [0, 1], NaN where unknown) from each pixel's true ground point
    (``points``, H x W x 3 world X, Y, Z; NaN where none), by DESIGN.md's rules as :func:`hazard_layers`
    applies them to the true height raster: slope of the LSQ plane over the 3 m footprint, roughness
    |z - plane|, and the true shadow.

    For a pair whose truth is only DESIGN.md's files (``gt_elevation`` / ``gt_depth`` / ``gt_shadow``): the
    pixels' points are binned on a horizontal grid of about the ground sample distance (:func:`truth_grid`, each
    cell their mean height), and the plane is fitted on the cells seen (:func:`weighted_plane_fit`). It sees the
    relief the camera resolves, not the finer relief a renderer's own raster holds, and no ground the view
    hides; where the ground is sampled coarser than about half the footprint, it is NaN (the camera cannot
    resolve it)."""
    P = np.asarray(points, np.float64)
    h, w = P.shape[:2]
    out = np.full((h, w), np.nan, np.float32)
    cell, x0, y0, gw, gh, held = truth_grid(P)
    if not held.any() or cell > FOOTPRINT_M / 2:  # no disk of two cells: nothing to fit (and no grid to build)
        return out
    X, Y, Zp = P[..., 0][held], P[..., 1][held], P[..., 2][held]
    ix = np.clip(((X - x0) / cell).astype(np.int64), 0, gw - 1)
    iy = np.clip(((Y - y0) / cell).astype(np.int64), 0, gh - 1)
    idx = iy * gw + ix
    count = np.bincount(idx, minlength=gw * gh).reshape(gh, gw).astype(np.float32)
    total = np.bincount(idx, weights=Zp, minlength=gw * gh).reshape(gh, gw)
    Zg = (total / np.maximum(count, 1)).astype(np.float64)
    del total
    a, b, c = weighted_plane_fit(Zg, (count > 0).astype(np.float32), cell)  # one weight per cell seen
    del Zg, count
    del ix, iy, idx
    sh = np.zeros(X.shape, bool) if shadow is None else np.asarray(shadow, bool)[held]
    values = np.full(X.shape, np.nan, np.float32)
    for k0 in range(0, X.size, POINTS_PER_CHUNK):
        k = slice(k0, k0 + POINTS_PER_CHUNK)
        # each pixel's coefficients at its own ground point (cell centres at x0 + (i + 0.5) cell)
        pa, pb, pc = _bilinear((a, b, c), (X[k] - x0) / cell - 0.5, (Y[k] - y0) / cell - 0.5)
        known = np.isfinite(pa) & np.isfinite(pb) & np.isfinite(pc)
        # a shadowed pixel without a plane stays unknown: scoring only those would skew
        values[k][known] = hazard_layers(Zp[k][known], pa[known], pb[known], pc[known], sh[k][known])
    out[held] = values
    return out
