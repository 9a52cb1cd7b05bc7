"""Safe landing-site selection on the hazard grid.

Flight v2 (``fast``, issue 9; :func:`select_safe_sites`): a cell qualifies when every cell within the
footprint radius plus a margin is known safe (the three-state grid), and candidates are ranked by P(safe),
then by distance to the aim point, and taken greedily at least one footprint apart.

The thesis (sec 2.1: a Chang'e-3 style spiral search; :func:`select_sites`): a cell is a candidate when every
cell of the lander footprint around it is known and safe (hazard < 1). Its margin is ``1 - max hazard over the
footprint``. Candidates are visited as a spiral around the nominal site: in rings one footprint wide
(``ring = floor(distance / footprint)``), and within a ring by decreasing margin; sites are taken greedily at
least one footprint apart.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, dataclass

import cv2
import numpy as np

from protocol.pairdir import STATE_OUTSIDE, STATE_SAFE, STATE_UNKNOWN
from reports.console import apart

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
    p_safe: float = float("nan")  # the smallest cell P(safe) over the footprint and its margin; NaN: not estimated
    clearance_m: float = float("nan")  # distance from the centre to the nearest cell not known safe

    def to_dict(self) -> dict[str, float]:
        return {k: float(v) for k, v in asdict(self).items()}


P_QUANTUM = 0.01  # sites are ranked by P(safe) in steps of this, then by distance to the aim point


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


def _spread_sites(
    grid: HazardGrid,
    ii: np.ndarray,
    jj: np.ndarray,
    x: np.ndarray,
    y: np.ndarray,
    order: np.ndarray,
    footprint_m: float,
    k: int,
    scores: Callable[[int, int, int], tuple[float, ...]],
) -> list[Site]:
    """Up to ``k`` candidates (cell ``ii[o], jj[o]`` at world ``x[o], y[o]``) taken greedily in ``order``
    at least one footprint apart. ``scores(o, i, j)``: a site's fields after its x, y, z and hazard."""
    sites: list[Site] = []
    for o in order:
        if any((x[o] - a.x) ** 2 + (y[o] - a.y) ** 2 < footprint_m**2 for a in sites):
            continue
        i, j = ii[o], jj[o]
        sites.append(
            Site(float(x[o]), float(y[o]), float(grid.elevation[i, j]), float(grid.hazard[i, j]), *scores(o, i, j))
        )
        if len(sites) == k:
            break
    return sites


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
    return _spread_sites(grid, ii, jj, x, y, order, footprint_m, k, lambda o, i, j: (float(margin[o]), float(dist[o])))


def no_site_reason(grid: HazardGrid, footprint_m: float) -> str:
    """Why :func:`select_sites` found no site on ``grid`` (the v1 hazard map has no states to cite)."""
    if grid.hazard.size == 0 or not np.isfinite(grid.hazard).any():
        return "nothing was mapped"
    if not np.isfinite(grid.elevation).any():
        return "no elevation was recovered (the image cues alone vouch for no ground)"
    return f"no {footprint_m:g} m footprint of the hazard map is clear of hazards"


def local_relief(elevation: np.ndarray, cell_m: float, window_m: float) -> np.ndarray:
    """Per cell, ``max z - min z`` of the measured elevation within about ``window_m`` (a square).

    NaN cells are ignored; a window without any elevation gives 0. The grid is first max/min-pooled
    in blocks of ``s = max(1, window_cells // 8)`` cells, so the cost does not grow with the window;
    the window then reaches ``window_cells // 2`` to ``window_cells // 2 + 2 s`` cells to each side
    (conservative: never narrower than asked).
    """
    z = np.asarray(elevation, np.float32)
    if z.size == 0:
        return np.zeros_like(z)
    ok = np.isfinite(z)
    w = max(1, int(round(window_m / cell_m)))
    s = max(1, w // 8)
    H, W = z.shape
    hp, wp = -(-H // s) * s, -(-W // s) * s
    hi = np.full((hp, wp), -np.inf, np.float32)
    lo = np.full((hp, wp), np.inf, np.float32)
    hi[:H, :W] = np.where(ok, z, -np.inf)
    lo[:H, :W] = np.where(ok, z, np.inf)
    hi, lo = _block_reduce(hi, s, np.max, cv2.dilate), _block_reduce(lo, s, np.min, cv2.erode)
    hb = -(-(w // 2) // s)  # half-window in blocks, rounded up: never narrower than asked
    ker = np.ones((2 * hb + 1, 2 * hb + 1), np.uint8)
    hi = cv2.dilate(hi, ker, borderType=cv2.BORDER_CONSTANT, borderValue=-np.inf)
    lo = cv2.erode(lo, ker, borderType=cv2.BORDER_CONSTANT, borderValue=np.inf)
    rel = np.where(np.isfinite(hi) & np.isfinite(lo), hi - lo, np.float32(0.0))
    return np.repeat(np.repeat(rel, s, axis=0), s, axis=1)[:H, :W]


def _block_reduce(
    a: np.ndarray, s: int, red: Callable[..., np.ndarray], morph: Callable[..., np.ndarray]
) -> np.ndarray:
    """Max or min over s x s blocks of ``a`` (shape a multiple of s)."""
    if s >= 4:  # numpy's reductions are quick over long runs ...
        h, w = a.shape
        return red(red(a.reshape(h // s, s, w), axis=1).reshape(h // s, w // s, s), axis=2)
    # ... OpenCV's morphology over short ones: a filter anchored at the block corner, read at the corners
    return morph(a, np.ones((s, s), np.uint8), anchor=(0, 0))[::s, ::s]


def select_safe_sites(
    grid: HazardGrid,
    footprint_m: float = 3.0,
    nominal_xy: tuple[float, float] = (0.0, 0.0),
    k: int = 5,
    margin_m: float = 0.5,
    p_quantum: float = P_QUANTUM,
    relief_max_m: float = 0.0,
    relief_window_m: float = 30.0,
    reach_cells: float = 0.0,
) -> tuple[list[Site], str]:
    """Sites whose whole footprint plus ``margin_m`` is known-safe, ranked by P(safe), then distance.

    Uses ``grid.state`` / ``grid.psafe`` (uncertainty-aware, :mod:`flight_sw.evidence`). A cell
    qualifies when every cell whose centre lies within ``footprint_m / 2 + margin_m + reach_cells *
    cell_m`` of it is ``STATE_SAFE`` (a disk; cells past the grid edge are not known). With
    ``reach_cells = 0.5`` that is about every cell the disk reaches into, not only those whose centre
    it holds. The site's ``p_safe`` is the smallest
    cell P(safe) over that disk - cell errors are correlated over a footprint, so the minimum
    is used rather than a product - and ``clearance_m`` the distance from its centre to the
    nearest cell not known safe. Candidates are ordered by ``p_safe`` (in steps of
    ``p_quantum``, so that equally certain sites are told apart by distance) and then by distance
    to ``nominal_xy``, and taken greedily at least one footprint apart. Returns
    ``(sites, reason)``: ``reason`` says why the list is empty (``""`` otherwise).

    A cell without a measured elevation is never a site (its ``z`` would be unknown).
    With ``relief_max_m > 0`` a cell is also refused when the measured elevation in the
    ``relief_window_m`` square around it spans more than ``relief_max_m`` (:func:`local_relief`). Semi-global
    aggregation flattens a steep wall (its smoothness penalty, Hirschmueller 2008), so a footprint
    next to tens of metres of relief can look flat and certain while standing on the wall.
    """
    if k <= 0:
        return [], "no sites requested"
    if grid.hazard.size == 0:
        return [], "no overlap between the images: nothing was mapped"
    safe = grid.state == STATE_SAFE
    n_cov = int((grid.state != STATE_OUTSIDE).sum())
    if n_cov == 0:
        return [], "nothing was mapped"
    if not safe.any():
        unk = 100.0 * float((grid.state == STATE_UNKNOWN).sum()) / max(1, n_cov)
        return [], f"no cell is known safe ({unk:.0f} % of the mapped grid cells unknown, the rest unsafe)"
    radius = 0.5 * footprint_m + max(0.0, margin_m)
    rc = radius / grid.cell_m + max(0.0, reach_cells)
    r = int(np.ceil(rc))
    yy, xx = np.mgrid[-r : r + 1, -r : r + 1]
    disk = ((xx * xx + yy * yy) <= rc * rc + 1e-9).astype(np.uint8)
    s8 = safe.astype(np.uint8)
    ok = cv2.erode(s8, disk, borderType=cv2.BORDER_CONSTANT, borderValue=0).astype(bool)
    # distance (cells) to the nearest cell not known safe; the grid edge counts as not known
    # exact Euclidean (the 5x5 chamfer mask read up to 0.12 m off; sites QA of stop 75)
    dist = cv2.distanceTransform(np.pad(s8, 1), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)[1:-1, 1:-1]
    if not ok.any():
        # both in metres from a cell's centre: "clearance 3.3 m" read as room to spare beside a 2.5 m radius, where a
        # site also needs the cells its disk reaches into (QA round 2 of stop 78)
        clear, need = apart(float(dist.max()) * grid.cell_m, rc * grid.cell_m, 1)
        return [], (
            f"no {footprint_m:g} m footprint with a {margin_m:g} m margin is entirely known safe (largest clearance "
            f"{clear} m from a cell's centre to the nearest cell not known safe, where a site needs over {need} m on "
            f"this {grid.cell_m:.2g} m grid)"
        )
    # a site is reported with its height: a cell the DEM did not measure is none (its state comes from
    # the pixels' calls pulled onto the grid, its elevation from the pixels' DEM, which can have a hole)
    ok &= np.isfinite(grid.elevation)
    if not ok.any():
        return [], f"no {footprint_m:g} m footprint known safe around a cell with a measured elevation"
    if relief_max_m > 0:
        ok &= local_relief(grid.elevation, grid.cell_m, relief_window_m) <= relief_max_m
        if not ok.any():
            return [], (
                f"every known-safe {footprint_m:g} m footprint lies in a {relief_window_m:g} m square with more "
                f"than {relief_max_m:g} m of relief (a wall the DEM may have flattened)"
            )
    rf = 0.5 * footprint_m / grid.cell_m
    rr = int(np.ceil(rf))
    fy, fx = np.mgrid[-rr : rr + 1, -rr : rr + 1]
    fdisk = ((fx * fx + fy * fy) <= rf * rf + 1e-9).astype(np.uint8)
    hz = np.where(np.isfinite(grid.hazard), grid.hazard, np.float32(1.0)).astype(np.float32)
    hmax = cv2.dilate(hz, fdisk, borderType=cv2.BORDER_CONSTANT, borderValue=1.0)
    ps = np.where(np.isfinite(grid.psafe), grid.psafe, 0.0).astype(np.float32)
    pmin = cv2.erode(ps, disk, borderType=cv2.BORDER_CONSTANT, borderValue=0.0)
    ii, jj = np.nonzero(ok)
    X, Y = grid.cell_xy()
    x, y = X[ii, jj], Y[ii, jj]
    d = np.hypot(x - nominal_xy[0], y - nominal_xy[1])
    p = pmin[ii, jj]
    order = np.lexsort((d, -np.floor(p / p_quantum + 1e-6)))

    def scores(o: int, i: int, j: int) -> tuple[float, ...]:
        return float(1.0 - hmax[i, j]), float(d[o]), float(p[o]), float(dist[i, j] * grid.cell_m)

    return _spread_sites(grid, ii, jj, x, y, order, footprint_m, k, scores), ""
