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


def altimeter_ground(pose: Pose, slant_range_m: float) -> float:
    """World Z of the altimeter's ground point: ``C_z + r * R[2, 2]`` (optical axis in world = R^T e_z)."""
    return float(pose.position[2] + slant_range_m * pose.R[2, 2])


# How far apart the ground elevations that two frames' altimeters and positions imply may lie: relief between the
# points their optical axes hit. Rendered descents, exact poses: 0.04 m median, 6.5 m worst over 288 pairs of the
# thesis scene (0.4 % of the range); a deep-crater approach 23.9 m at 791 m (3.0 %; stop 59). Twice that is refused
ALT_AGREE_MIN_M = 10.0
ALT_AGREE_FRAC = 0.06


def altimeter_disagreement(poses: list[Pose], ranges: list[float]) -> str:
    """Why the frames' altimeter readings and reported positions cannot both be right ("" when they agree).

    Each reading puts the ground at ``Z_k = C_z,k + r_k R_k[2, 2]`` (:func:`altimeter_ground`); they may differ by
    the relief between the points the optical axes hit, ``max(ALT_AGREE_MIN_M, ALT_AGREE_FRAC min r_k)``. More
    means a wrong position (a frame reported at 200 m whose altimeter read 151 m: the DEM 24 m off, unsaid) or a
    wrong reading (50 m long on frame 0: its prior cut off the ground above the datum, FP 1.4 %).
    """
    got = [(k, altimeter_ground(p, r), r) for k, (p, r) in enumerate(zip(poses, ranges)) if math.isfinite(r) and r > 0]
    if len(got) < 2:
        return ""
    lo, hi = min(got, key=lambda g: g[1]), max(got, key=lambda g: g[1])
    tol = max(ALT_AGREE_MIN_M, ALT_AGREE_FRAC * min(g[2] for g in got))
    if hi[1] - lo[1] <= tol:
        return ""
    return (
        f"the frames' altimeters and positions disagree on the ground's elevation: frame {lo[0]} puts it at "
        f"{lo[1]:.1f} m, frame {hi[0]} at {hi[1]:.1f} m ({hi[1] - lo[1]:.1f} m apart, more than the {tol:.1f} m "
        "relief allows): a position or a reading is wrong, and the images cannot tell the scale; the ground is "
        "searched without the altimeter"
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
