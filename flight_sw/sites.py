"""Safe landing-site selection on the hazard grid (thesis sec 2.1: Chang'e-3 style spiral search).

A cell is a candidate when every cell of the lander footprint around it is
known and safe (hazard < 1). Its margin is ``1 - max hazard over the
footprint``. Candidates are visited as a spiral around the nominal site: in
rings one footprint wide (``ring = floor(distance / footprint)``), and within a
ring by decreasing margin; sites are taken greedily at least one footprint
apart.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import cv2
import numpy as np

from .mapping import HazardGrid
from .slope import footprint_cells


@dataclass(frozen=True)
class Site:
    """A safe landing site in world coordinates."""

    x: float
    y: float
    z: float
    hazard: float  # hazard of the centre cell
    margin: float  # 1 - max hazard over the footprint
    distance_m: float  # from the nominal site
    p_safe: float = float("nan")  # probability that the whole footprint is safe; NaN: not estimated
    clearance_m: float = float("nan")  # distance from the centre to the nearest cell not known safe

    def to_dict(self) -> dict[str, float]:
        return {k: float(v) for k, v in asdict(self).items()}


def footprint_stats(hazard: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Per cell: whether the n x n footprint is all known-safe, and the max hazard over it."""
    h = np.where(np.isfinite(hazard), hazard, np.float32(1.0)).astype(np.float32)
    unsafe = (h >= 1.0).astype(np.float32)
    bad = cv2.boxFilter(unsafe, -1, (n, n), normalize=False, borderType=cv2.BORDER_CONSTANT)
    hmax = cv2.dilate(h, np.ones((n, n), np.uint8), borderType=cv2.BORDER_CONSTANT, borderValue=1.0)
    safe = bad < 0.5
    # footprints reaching past the grid edge are unknown ground
    r = n // 2
    safe[:r], safe[-r:], safe[:, :r], safe[:, -r:] = False, False, False, False
    return safe, hmax


def select_sites(
    grid: HazardGrid, footprint_m: float = 3.0, nominal_xy: tuple[float, float] = (0.0, 0.0), k: int = 5
) -> list[Site]:
    """Top-``k`` safe sites by spiral order around ``nominal_xy`` (see module doc)."""
    if grid.hazard.size == 0 or k <= 0:
        return []
    n = footprint_cells(footprint_m, grid.cell_m)
    safe, hmax = footprint_stats(grid.hazard, n)
    ii, jj = np.nonzero(safe)
    if ii.size == 0:
        return []
    X, Y = grid.cell_xy()
    x, y = X[ii, jj], Y[ii, jj]
    dist = np.hypot(x - nominal_xy[0], y - nominal_xy[1])
    margin = 1.0 - hmax[ii, jj]
    ring = np.floor(dist / footprint_m)
    order = np.lexsort((dist, -margin, ring))
    sites: list[Site] = []
    taken: list[tuple[float, float]] = []
    for o in order:
        if any((x[o] - a) ** 2 + (y[o] - b) ** 2 < footprint_m**2 for a, b in taken):
            continue
        i, j = ii[o], jj[o]
        sites.append(
            Site(
                float(x[o]),
                float(y[o]),
                float(grid.elevation[i, j]),
                float(grid.hazard[i, j]),
                float(margin[o]),
                float(dist[o]),
            )
        )
        taken.append((x[o], y[o]))
        if len(sites) == k:
            break
    return sites
