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

import cv2
import numpy as np

SLOPE_LIMIT_DEG = 15.0
ROUGH_LIMIT_M = 0.30
FOOTPRINT_M = 3.0


def plane_fit_factor(cell: float, footprint: float = FOOTPRINT_M, max_radius_cells: int = 12) -> int:
    """Coarsening factor of :func:`plane_fit`: the disk spans at most ``max_radius_cells`` coarse cells."""
    return max(1, int(math.ceil((footprint / 2) / (max_radius_cells * cell))))


def plane_fit(H: np.ndarray, cell: float, footprint: float = FOOTPRINT_M, max_radius_cells: int = 12):
    """(a, b, c) rasters of the LSQ plane ``z = a + b dx + c dy`` over a disk around each cell."""
    k = plane_fit_factor(cell, footprint, max_radius_cells)
    Hc = cv2.resize(H, (H.shape[1] // k, H.shape[0] // k), interpolation=cv2.INTER_AREA) if k > 1 else H
    cc = cell * k
    rad = footprint / 2 / cc
    n = int(math.floor(rad))
    off = np.arange(-n, n + 1) * cc
    dx, dy = np.meshgrid(off, off)
    disk = (dx**2 + dy**2 <= (footprint / 2) ** 2 + 1e-9).astype(np.float64)
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


def hazard_layers(z: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray, shadow: np.ndarray) -> np.ndarray:
    """Hazard in [0,1] per DESIGN.md from point heights z and the local plane (a, b, c)."""
    slope = np.degrees(np.arctan(np.hypot(b, c)))
    hz = np.maximum(np.clip(slope / SLOPE_LIMIT_DEG, 0, 1), np.clip(np.abs(z - a) / ROUGH_LIMIT_M, 0, 1))
    return np.maximum(hz, shadow.astype(np.float64)).astype(np.float32)


# a pixel's ground grid has at most this many cells per image pixel: an oblique view's far field spreads its
# pixels over a wide area, and the grid is coarsened rather than allocated without bound
MAX_GRID_CELLS_PER_PIXEL = 4.0
MIN_DISK_SHARE = 0.5  # a footprint disk less than half seen has no truth (its plane is an extrapolation)


def weighted_plane_fit(
    Z: np.ndarray, W: np.ndarray, cell: float, footprint: float = FOOTPRINT_M, min_share: float = MIN_DISK_SHARE
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(a, b, c) rasters of the weighted LSQ plane ``z = a + b dx + c dy`` over a disk of diameter ``footprint``
    around each cell of a grid where only some cells hold a height (``W`` > 0; ``Z`` is ignored elsewhere).

    The disk is no longer symmetric about the cell once some of it is missing, so the normal equations do not
    decouple as in :func:`plane_fit`: with sums over the disk's cells q, S_fg = sum W(q) f(q) g(q) for f, g in
    {1, dx, dy, z}, each one correlation (``cv2.filter2D``, O(1) per cell for a fixed disk),
    ``[[S_11, S_1x, S_1y], [S_1x, S_xx, S_xy], [S_1y, S_xy, S_yy]] (a, b, c) = (S_1z, S_xz, S_yz)``,
    solved per cell by Cramer's rule. NaN where the disk holds less than ``min_share`` of its cells or the
    system is singular (a line of cells), and everywhere when the footprint spans under ~2 cells (unlike
    :func:`plane_fit`, which then takes the 3x3 neighbourhood of a raster finer than any pixel: here the cells
    are the camera's, and a wider plane would be truth at another scale than DESIGN.md's)."""
    n = max(1, int(math.floor(footprint / 2 / cell)))
    off = np.arange(-n, n + 1) * cell
    dx, dy = np.meshgrid(off, off)
    disk = (dx**2 + dy**2 <= (footprint / 2) ** 2 + 1e-9).astype(np.float64)
    nan = np.full(np.shape(Z), np.nan)
    if disk.sum() < 5:  # a footprint of under ~2 cells: the grid cannot tell its slope
        return nan, nan.copy(), nan.copy()
    w = np.where(W > 0, W, 0.0).astype(np.float64)
    zref = float(np.sum(w * np.nan_to_num(Z)) / max(np.sum(w), 1e-12))
    wz = w * np.where(w > 0, np.nan_to_num(Z) - zref, 0.0)

    def corr(img: np.ndarray, k: np.ndarray) -> np.ndarray:
        return cv2.filter2D(img, cv2.CV_64F, k, borderType=cv2.BORDER_CONSTANT)  # outside the grid: no data

    s1, sx, sy = corr(w, disk), corr(w, disk * dx), corr(w, disk * dy)
    sxx, sxy, syy = corr(w, disk * dx * dx), corr(w, disk * dx * dy), corr(w, disk * dy * dy)
    sz, sxz, syz = corr(wz, disk), corr(wz, disk * dx), corr(wz, disk * dy)
    det = s1 * (sxx * syy - sxy * sxy) - sx * (sx * syy - sxy * sy) + sy * (sx * sxy - sxx * sy)
    # a plane needs a disk seen in two directions: det relative to a full disk's (scale-free)
    full = disk.sum() * np.sum(disk * dx * dx) * np.sum(disk * dy * dy)
    ok = (s1 >= min_share * disk.sum()) & (det > 1e-6 * full)
    det = np.where(ok, det, 1.0)
    a = (sz * (sxx * syy - sxy * sxy) - sx * (sxz * syy - sxy * syz) + sy * (sxz * sxy - sxx * syz)) / det
    b = (s1 * (sxz * syy - syz * sxy) - sz * (sx * syy - sxy * sy) + sy * (sx * syz - sxz * sy)) / det
    c = (s1 * (sxx * syz - sxy * sxz) - sx * (sx * syz - sxz * sy) + sz * (sx * sxy - sxx * sy)) / det
    return np.where(ok, a + zref, np.nan), np.where(ok, b, np.nan), np.where(ok, c, np.nan)


def coarser_step_m(X: np.ndarray, Y: np.ndarray) -> float:
    """The ground sample distance along the image's coarser direction: the median ground distance between
    neighbouring pixels in rows and in columns (of each pixel's ground X, Y), the larger of the two; 0 when no two
    neighbours have ground. A grid finer than this leaves gaps between the pixels' rows."""
    steps = [np.hypot(np.diff(X, axis=k), np.diff(Y, axis=k)) for k in (0, 1)]
    return max(
        float(np.median(s[np.isfinite(s) & (s > 0)])) if np.any(np.isfinite(s) & (s > 0)) else 0.0 for s in steps
    )


def hazard_from_points(points: np.ndarray, shadow: np.ndarray | None = None) -> np.ndarray:
    """Ground-truth hazard (float32 HxW in [0, 1], NaN where unknown) from each pixel's true ground point
    (``points``, H x W x 3 world X, Y, Z; NaN where none), by DESIGN.md's rules as :func:`hazard_layers`
    applies them to the true height raster: slope of the LSQ plane over the 3 m footprint, roughness
    |z - plane|, and the true shadow.

    For a pair whose truth is only DESIGN.md's files (``gt_elevation`` / ``gt_depth`` / ``gt_shadow``): the
    pixels' points are binned on a horizontal grid of about the ground sample distance (each cell their mean
    height), and the plane is fitted on the cells seen (:func:`weighted_plane_fit`). It sees the relief the
    camera resolves, not the finer relief a renderer's own raster holds, and no ground the view hides; where
    the ground is sampled coarser than about half the footprint, it is NaN (the camera cannot resolve it)."""
    P = np.asarray(points, np.float64)
    h, w = P.shape[:2]
    X, Y, Zp = P[..., 0], P[..., 1], P[..., 2]
    valid = np.isfinite(X) & np.isfinite(Y) & np.isfinite(Zp)
    out = np.full((h, w), np.nan, np.float32)
    if np.count_nonzero(valid) < 3:
        return out
    cell = max(coarser_step_m(X, Y), FOOTPRINT_M / 24)
    x0, y0 = float(X[valid].min()), float(Y[valid].min())
    span_x, span_y = float(X[valid].max()) - x0, float(Y[valid].max()) - y0
    budget = MAX_GRID_CELLS_PER_PIXEL * h * w
    cell = max(cell, math.sqrt((span_x + cell) * (span_y + cell) / budget))
    gw, gh = int(span_x / cell) + 1, int(span_y / cell) + 1
    ix = np.minimum(((X[valid] - x0) / cell).astype(np.int64), gw - 1)
    iy = np.minimum(((Y[valid] - y0) / cell).astype(np.int64), gh - 1)
    idx = iy * gw + ix
    count = np.bincount(idx, minlength=gw * gh).reshape(gh, gw).astype(np.float64)
    total = np.bincount(idx, weights=Zp[valid], minlength=gw * gh).reshape(gh, gw)
    Zg = np.where(count > 0, total / np.maximum(count, 1), np.nan)
    a, b, c = weighted_plane_fit(Zg, (count > 0).astype(np.float64), cell)
    # each pixel's coefficients at its own ground point (cell centres at x0 + (i + 0.5) cell)
    mx = ((X - x0) / cell - 0.5).astype(np.float32)
    my = ((Y - y0) / cell - 0.5).astype(np.float32)
    mx[~valid] = -10.0
    my[~valid] = -10.0

    def at(g: np.ndarray) -> np.ndarray:
        return cv2.remap(g.astype(np.float32), mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)

    pa, pb, pc = at(a), at(b), at(c)
    sh = np.zeros((h, w), bool) if shadow is None else np.asarray(shadow, bool)
    known = valid & np.isfinite(pa) & np.isfinite(pb) & np.isfinite(pc)
    hz = hazard_layers(np.where(known, Zp, 0.0), np.where(known, pa, 0.0), np.where(known, pb, 0.0),
                       np.where(known, pc, 0.0), sh)  # fmt: skip
    out[known] = hz[known]  # a shadowed pixel without a plane stays unknown: scoring only those would skew
    return out
