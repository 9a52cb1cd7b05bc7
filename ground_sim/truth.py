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
