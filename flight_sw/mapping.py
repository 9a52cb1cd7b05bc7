"""Mapping (thesis sec 4.4.5): combine hazard layers; move layers between i1's image plane and a world grid.

Hazard = max(slope/15 deg, roughness/0.30 m, shadow, rock), each scaled 0 -> 1.
The world grid (:class:`HazardGrid`) is regular in X, Y: cell ``[i, j]`` has its
centre at ``x = origin_x + j * cell_m``, ``y = origin_y - i * cell_m`` - the row
index increases toward -Y (north up, like a nadir image with DESIGN.md's
conventions). Image -> grid resampling "pulls": each cell centre is projected
into i1 at the elevation seen there (two fixed-point passes), and the layer is
read bilinearly, so the grid has no holes from perspective sampling.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np

from protocol.pairdir import STATE_OUTSIDE, STATE_SAFE, STATE_UNKNOWN, STATE_UNSAFE, Camera, Pose


@dataclass
class HazardGrid:
    """Hazard and elevation on a regular world grid; rows go toward -Y (see module doc).

    ``state`` uses the pair format's codes (``protocol.pairdir.STATE_*``: safe,
    unsafe, unknown, outside) and ``psafe`` is the probability that a cell is
    safe (NaN outside). When not given they are derived from ``hazard`` and
    ``elevation`` by :func:`three_state`.
    """

    hazard: np.ndarray  # float32 (rows, cols) in [0, 1], NaN outside the covered area
    elevation: np.ndarray  # float32 (rows, cols), NaN where not recovered
    origin_xy: tuple[float, float]  # world x, y of the centre of cell [0, 0]
    cell_m: float
    state: np.ndarray = field(default_factory=lambda: np.empty(0, np.uint8))  # uint8 (rows, cols)
    psafe: np.ndarray = field(default_factory=lambda: np.empty(0, np.float32))  # float32, NaN outside
    # float32 (rows, cols): the elevation the map reports, the DEM's gap fills too (pipeline.Params.dark_fill_m);
    # None: ``elevation``. ``elevation`` holds matched elevations only: the evidence and the sites read those
    dem: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.state.size != self.hazard.size or self.psafe.size != self.hazard.size:
            self.state, self.psafe = three_state(self.hazard, self.elevation)
        if self.dem is not None and np.shape(self.dem) != np.shape(self.hazard):
            raise ValueError(f"HazardGrid: dem shape {np.shape(self.dem)} != grid shape {np.shape(self.hazard)}")

    @property
    def reported_elevation(self) -> np.ndarray:
        """The elevation a Result and a score read: ``dem`` where given, else ``elevation``."""
        return self.elevation if self.dem is None else self.dem

    @property
    def filled(self) -> np.ndarray:
        """bool (rows, cols): cells whose reported elevation is a gap fill only (``dem`` finite where no
        match reached the cell); all False without ``dem``."""
        if self.dem is None:
            return np.zeros(np.shape(self.hazard), bool)
        return np.isfinite(self.dem) & ~np.isfinite(self.elevation)

    def cell_xy(self) -> tuple[np.ndarray, np.ndarray]:
        """World X, Y of every cell centre."""
        return grid_xy(self.hazard.shape, self.origin_xy, self.cell_m)


def grid_xy(shape: tuple[int, int], origin_xy: tuple[float, float], cell_m: float) -> tuple[np.ndarray, np.ndarray]:
    """World ``(X, Y)`` of every cell centre: ``x = x0 + j cell``, ``y = y0 - i cell`` (rows toward -Y)."""
    i, j = np.mgrid[0 : shape[0], 0 : shape[1]].astype(np.float64)
    return origin_xy[0] + j * cell_m, origin_xy[1] - i * cell_m


def grid_extent(x: np.ndarray, y: np.ndarray, cell_m: float) -> tuple[tuple[float, float], tuple[int, int]]:
    """Origin (cell [0,0] centre) and shape of a cell-aligned grid covering the finite points."""
    ok = np.isfinite(x) & np.isfinite(y)
    if not ok.any():
        return (0.0, 0.0), (0, 0)
    x0 = np.floor(x[ok].min() / cell_m) * cell_m
    x1 = np.ceil(x[ok].max() / cell_m) * cell_m
    y0 = np.floor(y[ok].min() / cell_m) * cell_m
    y1 = np.ceil(y[ok].max() / cell_m) * cell_m
    shape = (int(round((y1 - y0) / cell_m)) + 1, int(round((x1 - x0) / cell_m)) + 1)
    return (float(x0), float(y1)), shape


def ground_sample_distance(x: np.ndarray, y: np.ndarray, mask: np.ndarray, q: float = 90.0) -> float:
    """``q``-th percentile over ``mask`` of the distance between horizontally adjacent pixels (m)."""
    d = np.hypot(np.diff(x, axis=1), np.diff(y, axis=1))
    d = d[mask[:, 1:] & mask[:, :-1]]
    d = d[np.isfinite(d)]
    return float(np.percentile(d, q)) if d.size else float("nan")


def project(camera: Camera, pose: Pose, X: np.ndarray, Y: np.ndarray, Z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates of world points in a camera (pinhole, eq. 3.1-3.2)."""
    R, C = pose.R, pose.position
    dx, dy, dz = X - C[0], Y - C[1], Z - C[2]
    xc = R[0, 0] * dx + R[0, 1] * dy + R[0, 2] * dz
    yc = R[1, 0] * dx + R[1, 1] * dy + R[1, 2] * dz
    zc = R[2, 0] * dx + R[2, 1] * dy + R[2, 2] * dz
    with np.errstate(divide="ignore", invalid="ignore"):
        u = np.where(zc > 0, camera.fx * xc / zc + camera.cx, np.nan)
        v = np.where(zc > 0, camera.fy * yc / zc + camera.cy, np.nan)
    return u, v


def image_direction(
    camera: Camera, pose: Pose, ground_xy: tuple[float, float], direction_xy: tuple[float, float], z: float = 0.0
) -> tuple[float, float] | None:
    """Unit image direction ``(du, dv)`` of a horizontal world direction at the ground point ``ground_xy``
    (height ``z``): the projection of a 1 m step along it (eq. 3.1-3.2). None where it does not project."""
    x0, y0 = float(ground_xy[0]), float(ground_xy[1])
    n = math.hypot(float(direction_xy[0]), float(direction_xy[1]))
    if not (math.isfinite(n) and n > 0 and math.isfinite(x0) and math.isfinite(y0)):
        return None
    ex, ey = float(direction_xy[0]) / n, float(direction_xy[1]) / n
    u, v = project(camera, pose, np.array([x0, x0 + ex]), np.array([y0, y0 + ey]), np.array([z, z]))
    du, dv = float(u[1] - u[0]), float(v[1] - v[0])
    m = math.hypot(du, dv)
    if not (math.isfinite(m) and m > 1e-9):
        return None
    return du / m, dv / m


def from_pyramid(layer: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """A ``cv2.pyrDown`` level's layer read back at full resolution (``size`` = (width, height)), bilinear.

    pyrDown's level has its pixel ``j`` at full pixel ``2 j`` (:func:`flight_sw.sweep.scaled_camera`), so full
    pixel ``u`` reads the level at ``u / 2``. ``cv2.resize`` assumes pixel areas instead (``u / 2 - 0.25``): the
    coarse DEM came back half a full pixel off on an even width, and up to 0.43 px either way on an odd one
    (review of stop 64). Beyond the level's last centre the edge value stands, as resize's does; NaN spreads to the
    four pixels it touches, as resize's does.
    """
    m = np.array([[0.5, 0.0, 0.0], [0.0, 0.5, 0.0]])
    flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
    return cv2.warpAffine(np.asarray(layer, np.float32), m, size, flags=flags, borderMode=cv2.BORDER_REPLICATE)


def remap_maps(mx: np.ndarray, my: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """float32 copies of source coordinates for ``cv2.remap``, NaN (no source) at -1e4: outside, so NaN out.
    (Half the cost of ``nan_to_num`` then ``astype``, with the same values: +-inf stay +-inf.)"""
    out = []
    for m in (mx, my):
        a = np.array(m, dtype=np.float32)
        np.copyto(a, np.float32(-1e4), where=np.isnan(a))
        out.append(a)
    return out[0], out[1]


def remap_with(layer: np.ndarray, maps: tuple[np.ndarray, np.ndarray], interp: int = cv2.INTER_LINEAR) -> np.ndarray:
    """Read ``layer`` at :func:`remap_maps` coordinates (bilinear by default); NaN outside (float32)."""
    src = np.asarray(layer, np.float32)
    return cv2.remap(src, maps[0], maps[1], interp, borderMode=cv2.BORDER_CONSTANT, borderValue=float("nan"))


def remap_valid(layer: np.ndarray, maps: tuple[np.ndarray, np.ndarray], min_weight: float = 0.5) -> np.ndarray:
    """Bilinear read of ``layer`` over its finite samples only: ``sum w_k z_k / sum w_k`` over the finite
    ``z_k`` of the four neighbours, where that weight ``sum w_k`` reaches ``min_weight``; NaN elsewhere.

    :func:`remap_with` returns NaN as soon as one neighbour is NaN, which takes a pixel's width off every
    hole's rim (a DEM's unmatched pixels, say)."""
    src = np.asarray(layer, np.float32)
    ok = np.isfinite(src)
    num = remap_with(np.where(ok, src, np.float32(0.0)), maps)
    den = remap_with(ok.astype(np.float32), maps)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(den >= min_weight, num / den, np.float32(np.nan)).astype(np.float32)


def _remap(layer: np.ndarray, mx: np.ndarray, my: np.ndarray, interp: int = cv2.INTER_LINEAR) -> np.ndarray:
    return remap_with(layer, remap_maps(mx, my), interp)


def image_to_grid_coords(
    camera: Camera,
    pose: Pose,
    elevation_filled: np.ndarray,
    X: np.ndarray,
    Y: np.ndarray,
    z_ref: float,
    passes: int = 2,
) -> tuple[np.ndarray, np.ndarray]:
    """i1 pixel (u, v) seeing each grid cell centre: project at ``z_ref``, then at the elevation read there."""
    Z = np.full(X.shape, z_ref)
    for _ in range(passes):
        u, v = project(camera, pose, X, Y, Z)
        zn = _remap(elevation_filled, u, v)
        Z = np.where(np.isfinite(zn), zn, Z)
    return project(camera, pose, X, Y, Z)


def pull(layer: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Bilinear read of an image-plane layer at (u, v); NaN outside the image."""
    return _remap(layer, u, v)


def sample_grid(
    grid: np.ndarray, origin_xy: tuple[float, float], cell_m: float, X: np.ndarray, Y: np.ndarray
) -> np.ndarray:
    """Bilinear read of a grid layer at world (X, Y) (e.g. back to i1's pixels); NaN outside."""
    return remap_with(grid, grid_maps(origin_xy, cell_m, X, Y))


def grid_maps(
    origin_xy: tuple[float, float], cell_m: float, X: np.ndarray, Y: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`sample_grid`'s coordinates, for reading several layers of one grid at the same points."""
    return remap_maps((X - origin_xy[0]) / cell_m, (origin_xy[1] - Y) / cell_m)


def combine(
    slope_deg: np.ndarray | None,
    rough_m: np.ndarray | None,
    shadow: np.ndarray,
    rock: np.ndarray,
    covered: np.ndarray,
    slope_limit_deg: float = 15.0,
    rough_limit_m: float = 0.30,
    margin_px: float = 0.0,
) -> np.ndarray:
    """Hazard = max of the scaled layers (sec 4.4.5); NaN outside ``covered``.

    With a DEM (``slope_deg`` given), a covered point whose slope or roughness
    is unknown is unsafe (1): flight software must not call unknown ground safe.
    Without one (image-only level) only shadow and rocks count. ``margin_px``
    widens the measured DEM layer (:func:`widen_hazards`) before the maximum;
    the image cues are pixel-exact and rocks are already dilated.
    """
    haz = np.maximum(np.asarray(shadow, np.float32), np.asarray(rock, np.float32))
    if slope_deg is not None and rough_m is not None:
        s = np.minimum(slope_deg / np.float32(slope_limit_deg), 1.0)
        r = np.minimum(rough_m / np.float32(rough_limit_m), 1.0)
        dem = widen_hazards(np.maximum(s, r).astype(np.float32), margin_px)
        haz = np.maximum(haz, np.where(np.isfinite(dem), dem, np.float32(1.0)))
    return np.where(covered, haz, np.nan).astype(np.float32)


def three_state(hazard: np.ndarray, elevation: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(state, psafe) from a hazard map alone: the fallback when no uncertainty is known.

    Outside (hazard NaN) -> ``STATE_OUTSIDE``; no elevation -> ``STATE_UNKNOWN``
    unless an image cue (shadow, rock) already made it unsafe; otherwise safe
    below 1 and unsafe at 1. ``psafe`` is 1 for safe, 0 for unsafe and 0.5 for
    unknown: with no error model, the map's own call is all there is.
    """
    h = np.asarray(hazard, np.float32)
    outside = np.isnan(h)
    unsafe = ~outside & (h >= 1.0)
    unknown = ~outside & ~np.isfinite(np.asarray(elevation, np.float32)) & ~unsafe
    state = np.full(h.shape, STATE_SAFE, np.uint8)
    state[unsafe] = STATE_UNSAFE
    state[unknown] = STATE_UNKNOWN
    state[outside] = STATE_OUTSIDE
    psafe = np.where(state == STATE_SAFE, 1.0, np.where(state == STATE_UNKNOWN, 0.5, 0.0)).astype(np.float32)
    psafe[outside] = np.nan
    return state, psafe


def widen_hazards(hazard: np.ndarray, margin_px: float) -> np.ndarray:
    """Keep-out margin: ``h'(p) = max{h(q) : |q - p| <= margin_px}`` (grey dilation by a disk).

    Not in the thesis. The correlation window blurs the DEM, so a slope hazard's
    edge is only known to about a pixel; without a margin the pixels just
    outside an estimated hazard carry most undetected hazards (on ground_sim's
    approach pairs, 75-88 % of false "safe" pixels lie within 2 px of an
    estimated hazard). NaN (unknown) neither spreads nor is filled.
    ``margin_px = 0`` returns the map unchanged.
    """
    if not (math.isfinite(margin_px) and margin_px >= 0):
        raise ValueError(f"margin_px must be finite and >= 0, got {margin_px}")
    r = int(math.floor(margin_px))
    if r == 0:
        return hazard
    yy, xx = np.mgrid[-r : r + 1, -r : r + 1]
    disk = ((xx * xx + yy * yy) <= margin_px * margin_px + 1e-9).astype(np.uint8)
    outside = np.isnan(hazard)
    grown = cv2.dilate(
        np.where(outside, np.float32(0.0), hazard).astype(np.float32),
        disk,
        borderType=cv2.BORDER_CONSTANT,
        borderValue=0.0,
    )
    return np.where(outside, np.nan, grown).astype(np.float32)
