"""Sweep range from the data: find the ground wherever it is before the fine sweeps narrow in on it.

The thesis sweeps a fixed band around the reference plane (sec 4.3). A descent into a deep
crater has its ground tens of metres below that datum, so the band misses it entirely. Here:

1. The prior range is either the altimeter's ground point ``Z_alt = C_z + r R_22`` (``r`` the
   slant range along the optical axis, ``R_22`` the optical axis's world-Z component; DESIGN.md)
   +- ``max(min_m, frac_alt * r)`` (its top: :func:`prior_range`), or without an altimeter a wide band
   ``[-below * h, min(above * h, 0.3 * h_2)]`` around the datum (``h``, ``h_2``: the two camera
   heights above it; planes must stay below camera 2).
2. A quarter-resolution winner-take-all sweep over that range (planes uniform in disparity,
   :func:`flight_sw.sweep.planes_uniform_disparity`; 16x fewer pixel-planes than half
   resolution; flat cost curves dropped, :mod:`flight_sw.confidence`) gives a rough elevation per
   pixel; its ``[q, 100 - q]`` percentiles (q = 5), padded by
   two coarse plane steps and a relative margin, are the range the finer levels sweep.

If the quarter-resolution pass finds too few matches, the prior range is returned unchanged.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from protocol.pairdir import Camera, Pose

from .confidence import elevation_uncertainty, reject_uncertain
from .sweep import planes_uniform_disparity, scaled_camera, sweep_dem


@dataclass
class GroundRange:
    z_lo: float
    z_hi: float
    prior: tuple[float, float]
    source: str  # "altimeter", "wide", "fixed"
    found: bool  # the quarter-resolution pass narrowed the prior
    planes: int  # quarter-resolution planes swept
    median_z: float = math.nan


def altimeter_point(pose: Pose, slant_range_m: float) -> np.ndarray:
    """The altimeter's ground point ``C + r a`` in world, ``a = R^T e_z`` the optical axis (R's third row)."""
    return np.asarray(pose.position, float) + slant_range_m * np.asarray(pose.R, float)[2]


def altimeter_ground(pose: Pose, slant_range_m: float) -> float:
    """World Z of the altimeter's ground point: ``C_z + r * R[2, 2]`` (:func:`altimeter_point`)."""
    return float(altimeter_point(pose, slant_range_m)[2])


# How far apart the ground elevations that two frames' altimeters and positions imply may lie: relief between the
# points their optical axes hit, which lie up to 13 % of the range apart on the approach pairs and further across
# its tilt change at 300 m. Allowed: max(ALT_AGREE_MIN_M, ALT_AGREE_FRAC r) + ALT_AGREE_SLOPE d, d the points'
# horizontal distance. Clean renders (the evaluation cache's 288 pairs, deep-crater, highland, boulder-field, mare
# and polar-low-sun descents to 1200 m; stop 59): (dz - 0.5 d) / r at most 0.7 % (a deep-crater approach 1000/500:
# 27 m apart in height, 44 m across). Stop 61 (tuning renders: the six scenes' approach 250-1000 m, vertical
# 50-500 m): 0.71 % the same crater, every other pair under 0.05 m, so 10 m and 3 % became 4 m and 1.5 % (2.1x
# the worst clean case; navigation's +-0.5 m a frame adds at most 1 m): a nadir pair's lower frame reported 5 m
# high (its beam hits the ground frame 0's does) had passed, the DEM 10 m off with sites (stop 61's QA)
ALT_AGREE_MIN_M = 4.0
ALT_AGREE_FRAC = 0.015
ALT_AGREE_SLOPE = 0.5


def altimeter_disagreement(poses: list[Pose], ranges: list[float], numbers: list[int] | None = None) -> str:
    """Why the frames' altimeter readings and reported positions cannot both be right ("" when they agree).

    Each reading puts the ground point its beam hits at ``C_k + r_k a_k`` (``a_k`` the optical axis in world,
    :func:`altimeter_ground` its Z); two may differ in Z by the relief between those points,
    ``max(ALT_AGREE_MIN_M, ALT_AGREE_FRAC min r) + ALT_AGREE_SLOPE d`` with ``d`` their horizontal distance.
    More means a wrong position (a frame reported at 200 m whose altimeter read 151 m: the DEM 24 m off, unsaid)
    or a wrong reading (50 m long on frame 0: its prior cut off the ground above the datum, FP 1.4 %).
    ``numbers``: what the message calls the frames (default their positions).
    """
    got = []
    for k, (p, r) in enumerate(zip(poses, ranges)):
        if math.isfinite(r) and r > 0:
            got.append((k if numbers is None else numbers[k], altimeter_point(p, r), r))
    worst: tuple[float, int, int, float] | None = None
    for i, (ki, gi, ri) in enumerate(got):
        for kj, gj, rj in got[i + 1 :]:
            tol = max(ALT_AGREE_MIN_M, ALT_AGREE_FRAC * min(ri, rj)) + ALT_AGREE_SLOPE * float(np.hypot(*(gi - gj)[:2]))
            excess = abs(float(gi[2] - gj[2])) - tol
            if excess > 0 and (worst is None or excess > worst[0]):
                worst = (excess, ki, kj, tol)
    if worst is None:
        return ""
    _, ki, kj, tol = worst
    zi, zj = (float(g[2]) for k, g, _ in got if k in (ki, kj))
    return (
        f"the frames' altimeters and positions disagree on the ground's elevation: frame {ki} puts it at "
        f"{zi:.1f} m, frame {kj} at {zj:.1f} m ({abs(zi - zj):.1f} m apart, more than the {tol:.1f} m relief "
        "allows): a position or a reading is wrong, and the images cannot tell the scale; the ground is searched "
        "without the altimeter"
    )


# How far the DEM about frame 0's optical axis may lie from the ground frame 0's altimeter reads there: the DEM's
# error and the relief over the ring it is read on. Clean renders (288 tuning and held-out pairs of the thesis
# scene, 48 of deep-crater, highland and boulder-field; stop 59): 1.2 m median, 7.0 m worst (3.6 % of a 87 m range),
# deep crater 17 m at 1040 m (1.8 %). A frame reported 50 m high put it 44 m off at 301 m
ALT_DEM_MIN_M = 10.0
ALT_DEM_FRAC = 0.04
# the DEM's median over an annulus about the principal point, radii these shares of the image's shorter side: at
# the point itself a nadir pair has its epipole, where the DEM is its worst (10-25 m off on clean 400-800 m pairs)
ALT_DEM_RING = (0.04, 0.12)


ALT_DEM_MIN_SHARE = 0.25  # of the ring with an elevation, or the check is not made


def altimeter_ring(elevation: np.ndarray, camera: Camera) -> np.ndarray:
    """The DEM's elevations (NaN included) on the ring :data:`ALT_DEM_RING` about frame 0's principal point."""
    z = np.asarray(elevation)
    side = min(z.shape)
    r0, r1 = ALT_DEM_RING[0] * side, ALT_DEM_RING[1] * side
    y0, y1 = max(0, int(camera.cy - r1)), min(z.shape[0], int(camera.cy + r1) + 1)
    x0, x1 = max(0, int(camera.cx - r1)), min(z.shape[1], int(camera.cx + r1) + 1)
    if y1 <= y0 or x1 <= x0:  # a principal point off the image (the camera check allows it): no ring
        return np.empty(0, z.dtype)
    v, u = np.mgrid[y0:y1, x0:x1]
    d = np.hypot(u - camera.cx, v - camera.cy)
    return z[y0:y1, x0:x1][(d >= r0) & (d <= r1)]


def altimeter_dem_gap(
    elevation: np.ndarray, camera: Camera, pose: Pose, slant_range_m: float, frame: int = 0
) -> tuple[float, str]:
    """``(z_DEM - Z_alt, "")``: the DEM's median elevation on a ring about frame 0's principal point (the beam lands
    at its centre, DESIGN.md; :func:`altimeter_ring`) less the altimeter's ground point (:func:`altimeter_ground`).
    ``(NaN, why)`` where the DEM has too little there (under :data:`ALT_DEM_MIN_SHARE` of the ring) or the ring
    is off the image: said rather than passed over (on 21 of 315 clean directories the check was silently not
    made). ``frame``: what ``why`` calls frame 0 (``run_pipeline_multi``'s ``frame_numbers``)."""
    ring = altimeter_ring(elevation, camera)
    if ring.size == 0:
        return math.nan, (
            f"frame {frame}'s altimeter was not checked against the DEM: its optical axis meets the ground off the "
            "image"
        )
    share = float(np.count_nonzero(np.isfinite(ring))) / ring.size
    if share < ALT_DEM_MIN_SHARE:
        return math.nan, (  # floored: 24.6 % is not "25 % (it needs 25 %)"
            f"frame {frame}'s altimeter was not checked against the DEM: {math.floor(100 * share)} % of the ring about "
            f"its optical axis has a matched elevation (it needs {100 * ALT_DEM_MIN_SHARE:.0f} %)"
        )
    return float(np.nanmedian(ring)) - altimeter_ground(pose, slant_range_m), ""


def altimeter_dem_disagreement(gap_m: float, slant_range_m: float, frame: int = 0) -> str:
    """Why the DEM and frame 0's altimeter cannot both be right ("" when they agree or there is no gap to judge);
    ``frame`` is what the words call frame 0.

    The images fix the DEM's shape, not its scale: a frame reported 50 m from where it was (or an image from
    another frame) scales the whole DEM, and the pose refinement cannot see it (stop 59's QA: a DEM 24 m off,
    poses "kept"). The altimeter can: beyond ``max(ALT_DEM_MIN_M, ALT_DEM_FRAC r)`` the two disagree."""
    tol = max(ALT_DEM_MIN_M, ALT_DEM_FRAC * slant_range_m)
    if not math.isfinite(gap_m) or abs(gap_m) <= tol:
        return ""
    return (
        f"the DEM puts the ground under frame {frame}'s optical axis {gap_m:+.1f} m from where its altimeter reads it "
        f"(more than {tol:.1f} m): a frame's position or image is wrong, or the reading, and the DEM's scale with it"
    )


def prior_range(
    pose1: Pose,
    pose2: Pose,
    altimeter_m: float | None,
    *,
    below_frac: float = 0.6,
    above_frac: float = 0.2,
    alt_frac: float = 0.15,
    alt_min_m: float = 10.0,
) -> tuple[float, float, str]:
    """Range to search before any image evidence (module doc, step 1).

    Planes must stay well below camera 2: at most ``0.3 h_2`` above the datum, where wider ranges let
    spurious near-camera matches stretch the range the finer levels sweep. With an altimeter that top is
    raised to half the relief margin above its ground ``z_g`` when the ground lies that high
    (``max(0.3 h_2, z_g + m / 2)``, never above ``z_g + (h_2 - z_g) / 2``): from the datum alone, a
    highland 18 m above it seen from 50 m was cut off at 15 m.
    """
    h1, h2 = float(pose1.position[2]), float(pose2.position[2])
    if altimeter_m is not None and math.isfinite(altimeter_m) and altimeter_m > 0:
        zg = altimeter_ground(pose1, altimeter_m)
        m = max(alt_min_m, alt_frac * altimeter_m)
        top = max(0.3 * h2, min(zg + 0.5 * m, zg + 0.5 * (h2 - zg)))
        lo, hi = zg - m, min(zg + m, top)
        if hi > lo:
            return lo, hi, "altimeter"
    return -below_frac * h1, min(above_frac * h1, 0.3 * h2), "wide"


def find_ground(
    i1: np.ndarray,
    i2: np.ndarray,
    camera: Camera,
    pose1: Pose,
    pose2: Pose,
    z_lo: float,
    z_hi: float,
    *,
    source: str = "wide",
    step_px: float = 0.5,
    half_window: int = 3,
    pct: float = 5.0,
    pad_frac: float = 0.03,
    min_valid: int = 40,
    prefilter_sigma: float = 0.0,
    deadline: float | None = None,
    min_size_px: int = 64,
) -> GroundRange:
    """Quarter-resolution sweep over ``[z_lo, z_hi]``; the range of the ground it sees (module doc).

    Small sensors are reduced less: the level is the coarsest (at most 2) that keeps the
    image at least ``min_size_px`` wide.
    """
    level = 0
    while level < 2 and min(camera.width, camera.height) >> (level + 1) >= min_size_px:
        level += 1
    cam_q = scaled_camera(camera, level)
    q1: np.ndarray = np.asarray(i1, np.float32)
    q2: np.ndarray = np.asarray(i2, np.float32)
    for _ in range(level):
        q1, q2 = cv2.pyrDown(q1), cv2.pyrDown(q2)
    planes = planes_uniform_disparity(cam_q, pose1, pose2, z_lo, z_hi, step_px)
    if planes.size < 3:
        return GroundRange(z_lo, z_hi, (z_lo, z_hi), source, False, int(planes.size))
    res = sweep_dem(
        q1,
        q2,
        cam_q,
        pose1,
        pose2,
        planes,
        half_window=half_window,
        cost="ssd",
        prefilter_sigma=prefilter_sigma,
        deadline=deadline,
        end_erosion=1,
    )
    elev: np.ndarray = res.elevation
    if res.complete and res.curvature is not None:  # drop flat cost curves: they scatter over the range
        u = elevation_uncertainty(elev, res.curvature, res.planes)
        elev = reject_uncertain(elev, u, 1.5, res.curvature, 0.2)
    z = elev[np.isfinite(elev)]
    if not res.complete or z.size < min_valid:
        return GroundRange(z_lo, z_hi, (z_lo, z_hi), source, False, int(planes.size))
    lo, hi = np.percentile(z, [pct, 100.0 - pct])
    step = float(np.max(np.diff(planes)))
    depth = float(pose1.position[2]) - float(np.median(z))
    pad = 2.0 * step + pad_frac * max(depth, 1.0)
    return GroundRange(
        max(z_lo, float(lo) - pad),
        min(z_hi, float(hi) + pad),
        (z_lo, z_hi),
        source,
        True,
        int(planes.size),
        float(np.median(z)),
    )
