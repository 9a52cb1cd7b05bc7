"""The DEM seen from the lower frame too: a second dense DEM with i2 as the reference, read back in i1's pixels.

Semi-global matching computes a disparity image with either image of the pair as the base; Hirschmüller
(2008, sec. 3.3) uses the second one for the left-right check. Here the second DEM is *averaged* with the
first where both have a match::

    z(x1) = (z_1(x1) + z_2(pi_2(x1, z))) / 2          where both are finite, else z_1(x1)

with ``z_1`` the usual DEM of i1 (:func:`flight_sw.dense.dense_dem`), ``z_2`` the DEM of the same plane
sweep with i2 as the reference and i1 as the image warped onto it, and ``pi_2(x1, z)`` the pixel of i2 that
sees i1's ray at elevation ``z`` (found by fixed-point iteration, as the world grid is read:
:func:`read_into_reference`). On a descent the lower frame is the finer one (its ground sample distance is
``h2 / h1`` of i1's), so its matching support and the aggregation's smoothing span less ground, and a
wall's edge is blurred over less of it; the two DEMs' errors are only partly shared (different supports,
different aggregation paths), so their mean is less noisy than either.

The reference i2 is low-passed by the same area prefilter the first DEM gives it as the warped image
(:func:`flight_sw.warping.area_sigma` of the pair's GSD ratio, sigma^2 = (1/s^2 - 1) / 12 i2 pixels), so
both DEMs compare images of one effective resolution. Tuning renders (seeds 0-1, vertical and approach
pairs): 0.5 px (the area sigma at s = 0.5) gave the lowest DEM error of 0.5, 0.85 and 1.2 px; none at all,
the highest. Measured in docs/benchmarks/pipeline.md (stop 40).

**Limits.** The second sweep covers all of i2 (4x the overlap's pixels of i1 on a 2:1 pair), so it costs about
four first DEMs (0.25 s CPU on a 512 px pair, against 0.06 s), and with both images at half resolution the
gain is lost (the finer reference is the point). Where the ground's texture is finer than i1's pixel and
nothing coarser (tests/synthetic.py's noise texture), the finer reference finds nothing in i1 to match and
its DEM is 3-4x worse than i1's; the rendered lunar scenes have texture at every scale (craters, shading).
Off in every preset (``Params.lower_view_dem``); a model fitted on its DEM comes from ``bench/fit_psafe.py
--set-param lower_view_dem=true``. Held-out it raised the pixel map's median CDI by 1.4 points at a lower
worst-pair FP for twice the CPU, but in the landing Monte Carlo its top sites were truly clear less often (0.587
against 0.619) and 4 of 596 were not clear at all, against none of `fast`'s 624 (docs/benchmarks/pipeline.md,
stop 40).

Only where both DEMs matched is the mean taken; pixels the first DEM did not match stay unmatched (coverage
and the dark-shadow gap fill are the first DEM's), and the first DEM's sigma is kept: the P(safe) trees
are fitted on the DEM this module delivers and calibrate what its sigma means.
"""

from __future__ import annotations

import cv2
import numpy as np

from protocol.pairdir import Camera, Pose

from .dense import DenseParams, dense_dem
from .georef import backproject
from .mapping import project, remap_maps, remap_with

READ_PASSES = 3  # fixed-point passes of read_into_reference (the ray's elevation moves < 1 cm after 3 on tuning pairs)


def read_into_reference(
    z2: np.ndarray,
    camera: Camera,
    pose1: Pose,
    pose2: Pose,
    z_start: np.ndarray,
    passes: int = READ_PASSES,
) -> np.ndarray:
    """``z_2`` read along each of i1's rays: float32, i1's shape, NaN where i2 has no elevation there.

    Each pass backprojects i1's pixels to the current elevation ``z`` (start: ``z_start``, finite everywhere),
    projects those ground points into i2 and reads ``z_2`` there (bilinear; NaN if any neighbour is NaN); a
    ray whose read is NaN keeps its elevation for the next pass.
    """
    z = np.asarray(z_start, np.float64)
    zn = np.full(z.shape, np.nan, np.float32)
    for _ in range(max(1, int(passes))):
        X, Y = backproject(camera, pose1, z)
        u, v = project(camera, pose2, X, Y, z)
        zn = remap_with(z2, remap_maps(u, v))
        z = np.where(np.isfinite(zn), zn, z)
    return zn


def lower_view_dem(
    a1: np.ndarray,
    a2: np.ndarray,
    camera: Camera,
    pose1: Pose,
    pose2: Pose,
    planes: np.ndarray,
    dp: DenseParams,
    *,
    area_sigma_px: float,
    ignore2: np.ndarray | None = None,
    deadline: float | None = None,
) -> tuple[np.ndarray | None, dict[str, float | int | bool]]:
    """``z_2``, the DEM of i2 (reference, low-passed by ``area_sigma_px``) against i1 over ``planes``
    (world elevations), in i2's pixels; None if the sweep did not finish before ``deadline``."""
    ref: np.ndarray = np.asarray(a2, np.float32)
    if area_sigma_px > 0:
        ref = cv2.GaussianBlur(ref, (0, 0), float(area_sigma_px))
    dem = dense_dem(
        ref, np.asarray(a1, np.float32), camera, pose2, pose1, planes, dp, ignore=ignore2, deadline=deadline
    )
    info: dict[str, float | int | bool] = {"complete": bool(dem.complete), "planes": int(planes.size)}
    if not dem.complete:
        return None, info
    info["matched"] = float(np.isfinite(dem.elevation).mean())
    return dem.elevation, info


def average_where_both(z1: np.ndarray, z2_in_1: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(z, both)``: the mean of the two DEMs where both are finite, ``z1`` elsewhere (module doc)."""
    both = np.isfinite(z1) & np.isfinite(z2_in_1)
    z = np.where(both, np.float32(0.5) * (z1 + np.where(both, z2_in_1, np.float32(0.0))), z1).astype(np.float32)
    return z, both
