"""Multi-baseline dense DEM over a descent's frames (issue #10; Okutomi & Kanade 1993).

Every frame's matching cost against the reference is computed on the same planes and combined per pixel
into one cost slab (:func:`flight_sw.costvolume.multi_cost_slab`), which the pair's aggregation, winner and
sigma then take (:func:`flight_sw.dense.dem_from_slab`).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from protocol.pairdir import Camera, Pose

from .anytime import Clock
from .costvolume import frame_roi, multi_cost_slab, parallax_px
from .dense import DenseDEM, dem_from_slab, roi_of
from .homography import centre_gsd, gsd_scale
from .params import Params, dense_params
from .warping import area_sigma


def multi_baseline_dem(
    a1: np.ndarray,
    a2: np.ndarray,
    pose1: Pose,
    pose2: Pose,
    extra: Sequence[tuple[np.ndarray, Pose]],
    camera: Camera,
    planes: np.ndarray,
    p: Params,
    ignore: np.ndarray,
    clock: Clock,
    prior: np.ndarray | None,
    info: dict[str, Any],
    reserve: float,
) -> DenseDEM:
    """Multi-baseline dense DEM (issue 10): the widest pair and the ``extra`` frames in one cost volume.

    The slab covers the widest pair's reach (``multi_extent="widest"``) or every frame's
    (``"union"``). Frame f's parallax per plane relative to the widest frame, ``s_f``
    (:func:`flight_sw.costvolume.parallax_px`), sets its weight ``w_f = s_f^multi_weight_exp``
    in the robust mean (:func:`flight_sw.costvolume.multi_cost_slab`): near its minimum a frame's
    cost is ``~ kappa s_f^2 dk^2`` plus noise, so a short-baseline frame carries little depth
    signal and mostly adds interpolation noise. The slab then goes through the pair's SGM,
    winner and sigma (:func:`flight_sw.dense.dem_from_slab`).

    Sigma: the curvature-based sigma of the combined cost assumes one pair's noise. If the
    frames' cost noise were independent, the minimum of the combination would be
    ``sqrt(I)`` times better determined, ``I = sum_f s_f^2`` over the frames that saw the pixel
    (1 for a pair); the frames share the reference image, so ``sigma / I^(gamma / 2)`` with
    ``gamma = multi_sigma_gamma`` in [0, 1] calibrated on tuning seeds (docs/benchmarks/multiframe.md).
    """
    frames = [(a2, pose2)] + [(np.ascontiguousarray(img, dtype=np.float32), pose) for img, pose in extra]
    z_lo, z_hi = float(planes[0]), float(planes[-1])
    roi = roi_of(camera, pose1, pose2, z_lo, z_hi)
    if p.multi_extent == "union":
        whole = (0, 0, camera.width, camera.height)
        boxes = [roi] + [frame_roi(camera, pose1, pose, z_lo, z_hi, whole) for _, pose in extra]
        boxes = [b for b in boxes if b[2] > 0 and b[3] > 0]
        if boxes:
            bx0, by0 = min(b[0] for b in boxes), min(b[1] for b in boxes)
            bx1, by1 = max(b[0] + b[2] for b in boxes), max(b[1] + b[3] for b in boxes)
            roi = (bx0, by0, bx1 - bx0, by1 - by0)
    dp = dense_params(p)
    deadline = clock.before(reserve)  # the v2 reserve (scaled with the pixel count)
    par = [parallax_px(camera, pose1, pose, z_lo, z_hi, roi) for _, pose in frames]
    rel = [min(1.0, v / par[0]) if par[0] > 0 else 1.0 for v in par]
    weights = [max(r, 1e-3) ** p.multi_weight_exp for r in rel]
    slab = multi_cost_slab(
        a1,
        [f[0] for f in frames],
        camera,
        pose1,
        [f[1] for f in frames],
        planes,
        roi,
        prefilter_sigmas=[area_sigma(gsd_scale(camera, pose1, f[1])) if p.prefilter else 0.0 for f in frames],
        weights=weights,
        info=[r * r for r in rel],
        rule=p.multi_rule,
        gain=p.multi_cost_gain,
        truncate=p.multi_truncate,
        radius=dp.radius,
        mean_radius=dp.mean_radius,
        ignore=ignore,
        deadline=deadline,
        check_every=p.check_every,
    )
    dem = dem_from_slab(slab, a1, a1.shape, dp, deadline, prior, ignore, centre_gsd(camera, pose1), release=True)
    gain_img = np.ones(a1.shape, np.float32)
    if slab.info is not None:
        x0, y0, w, h = roi
        gain_img[y0 : y0 + h, x0 : x0 + w] = np.maximum(slab.info, 1.0)
    if dem.complete and p.multi_sigma_gamma > 0:
        if dem.filled is not None:  # more frames sharpen a match, not an elevation carried into a gap
            gain_img[dem.filled] = 1.0
        dem.sigma = (dem.sigma * gain_img ** np.float32(-0.5 * p.multi_sigma_gamma)).astype(np.float32)
    ok = np.isfinite(dem.elevation)
    info["multi_frame"] = {
        "frames": len(frames) + 1,
        "rule": p.multi_rule,
        "extent": p.multi_extent,
        "roi": [int(v) for v in roi],
        "parallax_rel": [round(v, 3) for v in rel],
        "weights": [round(v, 3) for v in weights],
        "info_median": float(np.median(gain_img[ok])) if ok.any() else 0.0,
    }
    return dem
