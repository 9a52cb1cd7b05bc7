"""Slope and roughness over the lander footprint (thesis sec 4.4.2 and 4.4.4), O(1) per cell.

On a regular world grid, each cell gets the least-squares plane
``Z = p X + q Y + r`` (eq. 4.11/4.12) of the valid cells in the square
footprint around it. Instead of a per-cell solver, the normal equations are
assembled from box sums of ``1, x, y, z, x^2, xy, y^2, xz, yz`` (NaN cells have
weight 0) and solved in closed form through the centred moments::

    [cxx cxy] [p]   [cxz]
    [cxy cyy] [q] = [cyz],     slope = atan(sqrt(p^2 + q^2))   (eq. 4.13)

Roughness is the deviation from that plane at the cell (eq. 4.18).
"""

from __future__ import annotations

import cv2
import numpy as np


def footprint_cells(footprint_m: float, cell_m: float) -> int:
    """Odd window size (cells) approximating a ``footprint_m`` square, at least 3."""
    n = int(round(footprint_m / cell_m))
    n = max(3, n)
    return n if n % 2 == 1 else n + 1


def _box(a: np.ndarray, n: int) -> np.ndarray:
    return cv2.boxFilter(a, cv2.CV_64F, (n, n), normalize=False, borderType=cv2.BORDER_CONSTANT)


def plane_fit(
    z: np.ndarray, cell_m: float, footprint_m: float = 3.0, min_fraction: float = 0.5
) -> tuple[np.ndarray, np.ndarray]:
    """Per-cell LSQ plane over the footprint: returns ``(slope_deg, z_plane)``, float32.

    ``z_plane`` is the fitted plane evaluated at the cell centre. Cells whose
    footprint holds fewer than ``min_fraction`` valid cells, or only collinear
    ones, are NaN. Grid axes are treated as metric with spacing ``cell_m``;
    the orientation of the axes does not change slope or roughness.
    """
    z = np.asarray(z, dtype=np.float64)
    n = footprint_cells(footprint_m, cell_m)
    h, w = z.shape
    w8 = np.isfinite(z).astype(np.float64)
    zz = np.where(w8 > 0, z, 0.0)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    # coordinates relative to the grid centre keep the moments well conditioned
    xx -= w / 2.0
    yy -= h / 2.0
    s1 = _box(w8, n)
    sx, sy, sz = _box(w8 * xx, n), _box(w8 * yy, n), _box(zz, n)
    sxx, sxy, syy = _box(w8 * xx * xx, n), _box(w8 * xx * yy, n), _box(w8 * yy * yy, n)
    sxz, syz = _box(zz * xx, n), _box(zz * yy, n)
    with np.errstate(divide="ignore", invalid="ignore"):
        mx, my, mz = sx / s1, sy / s1, sz / s1
        cxx, cxy, cyy = sxx / s1 - mx * mx, sxy / s1 - mx * my, syy / s1 - my * my
        cxz, cyz = sxz / s1 - mx * mz, syz / s1 - my * mz
        det = cxx * cyy - cxy * cxy
        p = (cxz * cyy - cyz * cxy) / det
        q = (cyz * cxx - cxz * cxy) / det
        zc = mz + p * (xx - mx) + q * (yy - my)
    ok = (s1 >= min_fraction * n * n) & (det > 1e-6)
    slope = np.degrees(np.arctan(np.hypot(p, q) / cell_m))
    return (np.where(ok, slope, np.nan).astype(np.float32), np.where(ok, zc, np.nan).astype(np.float32))


def roughness(z: np.ndarray, z_plane: np.ndarray) -> np.ndarray:
    """Eq. 4.18: ``|z - z_plane|`` (NaN where either is NaN)."""
    return np.abs(np.asarray(z, np.float32) - np.asarray(z_plane, np.float32))


def scale_hazard(value: np.ndarray, limit: float) -> np.ndarray:
    """Map ``0 -> 0`` and ``limit -> 1`` linearly, clipped at 1 (thesis sec 4.4.2, 4.4.4)."""
    return np.minimum(np.asarray(value, np.float32) / np.float32(limit), np.float32(1.0))
