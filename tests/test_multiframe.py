"""Multi-baseline plane sweep (issue 10): 2-16 frames in one cost volume, two frames exactly as a pair.

Synthetic descents (tests/synthetic.py): a seeded random texture draped on analytic terrain, seen
from several altitudes straight above it.
"""

from __future__ import annotations

import dataclasses
import json
import math
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
from synthetic import NADIR_R, Texture, camera_fov30, plane, render, roof

from flight_sw.costvolume import cost_slab, multi_cost_slab, parallax_px
from flight_sw.dense import roi_of
from flight_sw.homography import plane_homography
from flight_sw.pipeline import PRESETS, run_pipeline, run_pipeline_multi
from flight_sw.validate import FlightInputError
from protocol.pairdir import Pair, Pose, write_pair


def descent(size: int, alts: list[float], height, seed: int, noise: float = 0.0):
    """Camera, nadir poses, 8-bit images (optional Gaussian sensor noise per frame) and frame 0's true elevation."""
    cam = camera_fov30(size)
    poses = [Pose(np.array([0.0, 0.0, h]), NADIR_R) for h in alts]
    tex = Texture.random(alts[0] * 0.6 + 10, alts[-1] / cam.fx / 1.5, seed)
    views = [render(cam, p, height, tex) for p in poses]
    rng = np.random.default_rng(seed + 1)
    imgs = [np.clip(v[0] + rng.normal(0.0, noise, v[0].shape), 0, 255).astype(np.uint8) for v in views]
    return cam, poses, imgs, views[0][1]


@pytest.fixture(scope="module")
def close_baselines():
    """200 m -> 108, 104, 100 m over a 8 deg roof: three nearly equal long baselines, noisy sensor."""
    return descent(160, [200.0, 108.0, 104.0, 100.0], roof(8.0, -3.0), seed=5, noise=12.0)


def test_one_frame_slab_is_cost_slab_bit_for_bit(close_baselines):
    cam, poses, imgs, _ = close_baselines
    planes = np.linspace(-8.0, 2.0, 21)
    roi = roi_of(cam, poses[0], poses[3], planes[0], planes[-1])
    a = cost_slab(imgs[0], imgs[3], cam, poses[0], poses[3], planes, roi, prefilter_sigma=0.7)
    b = multi_cost_slab(imgs[0], [imgs[3]], cam, poses[0], [poses[3]], planes, roi, prefilter_sigmas=[0.7])
    assert np.array_equal(a.cost, b.cost) and np.array_equal(a.valid, b.valid)
    # three frames: every entry is the weighted mean of the frames that saw it
    c = [cost_slab(imgs[0], imgs[k], cam, poses[0], poses[k], planes, roi) for k in (1, 2, 3)]
    w = [0.5, 0.25, 1.0]
    m = multi_cost_slab(imgs[0], imgs[1:], cam, poses[0], poses[1:], planes, roi, weights=w)
    num = sum(wi * np.where(s.valid, s.cost, 0).astype(np.float64) for wi, s in zip(w, c))
    den = sum(wi * s.valid for wi, s in zip(w, c))
    seen = den > 0
    assert np.array_equal(m.valid, seen)
    # the slabs quantise each frame's cost to uint16 before the mean, the combination after: within 1 unit
    assert np.abs(m.cost[seen].astype(np.float64) - num[seen] / den[seen]).max() <= 1.0 + 1e-6
    # drop_worst: where all three saw the entry, the frame with the largest cost is left out
    d = multi_cost_slab(imgs[0], imgs[1:], cam, poses[0], poses[1:], planes, roi, weights=w, rule="drop_worst")
    costs = np.stack([s.cost for s in c]).astype(np.float64)
    all3 = np.all(np.stack([s.valid for s in c]), axis=0)
    worst = costs.argmax(axis=0)
    keep = np.ones(costs.shape, bool)
    np.put_along_axis(keep, worst[None], False, axis=0)
    wv = np.array(w)[:, None, None, None] * keep
    want = (wv * costs).sum(axis=0) / wv.sum(axis=0)
    ties = np.sort(costs, axis=0)[-1] - np.sort(costs, axis=0)[-2] < 2  # quantisation may swap near-equal worsts
    sel = all3 & ~ties
    assert sel.sum() > 1000 and np.abs(d.cost[sel] - want[sel]).max() <= 1.0 + 1e-6
    assert not np.array_equal(d.cost[sel], m.cost[sel])


def test_two_frames_behave_exactly_as_a_pair():
    cam, poses, imgs, _ = descent(128, [150.0, 75.0], roof(12.0, -2.0), seed=8)
    a = run_pipeline(imgs[0], imgs[1], poses[0], poses[1], cam)
    b = run_pipeline_multi(imgs, poses, cam)
    for name in ("elevation", "sigma", "state", "psafe", "hazard", "covered"):
        assert np.array_equal(getattr(a, name), getattr(b, name), equal_nan=True), name
    assert np.array_equal(a.grid.state, b.grid.state) and np.array_equal(a.grid.psafe, b.grid.psafe, equal_nan=True)
    assert [s.to_dict() for s in a.sites] == [s.to_dict() for s in b.sites]
    assert "multi_frame" not in b.info


def test_added_frames_average_out_sensor_noise(close_baselines):
    """Okutomi & Kanade: with independent noise per frame, the combined cost's minimum is better determined."""
    cam, poses, imgs, z = close_baselines
    pair = run_pipeline(imgs[0], imgs[3], poses[0], poses[3], cam)
    multi = run_pipeline_multi(imgs, poses, cam)
    ok = np.isfinite(pair.elevation) & np.isfinite(multi.elevation) & pair.covered
    e_pair = float(np.mean(np.abs(pair.elevation - z)[ok]))
    e_multi = float(np.mean(np.abs(multi.elevation - z)[ok]))
    assert e_multi < 0.93 * e_pair, (e_pair, e_multi)  # measured 0.89 (frame 0 noise is common to all pairs)
    # and no better pair exists: every (0, k) pair alone, scored on the same pixels, is worse than all frames
    for k in (1, 2):
        other = run_pipeline(imgs[0], imgs[k], poses[0], poses[k], cam)
        okk = ok & np.isfinite(other.elevation) & other.covered
        e_k = float(np.mean(np.abs(other.elevation - z)[okk]))
        e_m = float(np.mean(np.abs(multi.elevation - z)[okk]))
        assert okk.sum() > 0.5 * ok.sum() and e_m <= e_k, (k, e_k, e_m)
    assert multi.valid_fraction >= pair.valid_fraction
    mf = multi.info["multi_frame"]
    assert mf["frames"] == 4 and all(r > 0.9 for r in mf["parallax_rel"])  # three nearly equal baselines
    assert np.nanmedian(multi.sigma[ok]) < np.nanmedian(pair.sigma[ok])  # and the sigma says so


def test_a_frame_that_sees_something_else_is_outvoted(close_baselines):
    """Frame 2 sees another texture over a region (an occluder, a moved shadow): the DEM there holds."""
    cam, poses, imgs, z = close_baselines
    imgs = list(imgs)
    rng = np.random.default_rng(9)
    patch = cv2.GaussianBlur(rng.normal(128, 50, (60, 60)).astype(np.float32), (0, 0), 1.5)
    imgs[2] = imgs[2].copy()
    imgs[2][30:90, 90:150] = np.clip(patch, 0, 255).astype(np.uint8)
    H = plane_homography(cam, poses[0], poses[2], -3.0)
    v, u = np.mgrid[0 : cam.height, 0 : cam.width].astype(float)
    q = H @ np.stack([u.ravel(), v.ravel(), np.ones(u.size)])
    u2, v2 = (q[0] / q[2]).reshape(u.shape), (q[1] / q[2]).reshape(u.shape)
    region = (u2 >= 94) & (u2 < 146) & (v2 >= 34) & (v2 < 86)  # frame-0 pixels frame 2 sees corrupted
    pair = run_pipeline(imgs[0], imgs[3], poses[0], poses[3], cam)  # does not use frame 2
    e_pair = float(np.nanmean(np.abs(pair.elevation - z)[region & pair.covered]))
    for rule in ("drop_worst", "mean"):
        prm = dataclasses.replace(PRESETS["fast"], multi_rule=rule, multi_weight_exp=0.0)
        res = run_pipeline_multi(imgs, poses, cam, preset=prm)
        m = region & res.covered
        assert m.sum() > 300
        e = np.abs(res.elevation - z)[m]
        assert np.isfinite(e).mean() > 0.9 and float(np.nanmean(e)) < 1.2 * e_pair, (rule, np.nanmean(e), e_pair)
    # a rule that trusts the worst frame would not hold it: the corrupted frame alone is far off there
    alone = run_pipeline(imgs[0], imgs[2], poses[0], poses[2], cam)
    assert float(np.nanmean(np.abs(alone.elevation - z)[region & alone.covered])) > 2.0 * e_pair


def test_union_extent_maps_what_only_some_frames_see():
    cam, poses, imgs, z = descent(128, [160.0, 120.0, 80.0], plane(-2.0), seed=12)
    widest = run_pipeline_multi(imgs, poses, cam)
    union = run_pipeline_multi(imgs, poses, cam, preset=dataclasses.replace(PRESETS["fast"], multi_extent="union"))
    assert union.covered.sum() > 1.5 * widest.covered.sum()
    assert np.all(union.covered[widest.covered])
    only = union.covered & ~widest.covered & np.isfinite(union.elevation)
    assert only.sum() > 0.8 * (union.covered & ~widest.covered).sum()  # the band frame 1 alone sees is mapped
    assert float(np.median(np.abs(union.elevation - z)[only])) < 0.6


def test_parallax_of_each_frame_follows_the_geometry():
    cam = camera_fov30(256)
    p0, p1, p2 = (Pose(np.array([0.0, 0.0, h]), NADIR_R) for h in (300.0, 250.0, 150.0))
    roi = (64, 64, 128, 128)
    a, b = parallax_px(cam, p0, p1, -10.0, 10.0, roi), parallax_px(cam, p0, p2, -10.0, 10.0, roi)
    # nadir: a reference pixel's match moves by ~ r dz (1/h_k - 1/h_0) reference pixels (r from the centre)
    assert b > 0 and a / b == pytest.approx((1 / 250 - 1 / 300) / (1 / 150 - 1 / 300), rel=0.08)


def test_bad_frame_lists_are_one_line_errors():
    cam, poses, imgs, _ = descent(64, [150.0, 110.0, 75.0], plane(0.0), seed=3)
    with pytest.raises(FlightInputError, match="below pose2"):
        run_pipeline_multi([imgs[0], imgs[2], imgs[1]], [poses[0], poses[2], poses[1]], cam)
    with pytest.raises(FlightInputError, match="2-16 frames"):
        run_pipeline_multi(imgs[:1], poses[:1], cam)
    with pytest.raises(FlightInputError, match="i3: size"):
        run_pipeline_multi([imgs[0], imgs[1], imgs[2][:32]], poses, cam)
    with pytest.raises(FlightInputError, match="multi_rule"):
        run_pipeline_multi(imgs, poses, cam, preset=dataclasses.replace(PRESETS["fast"], multi_rule="median"))
    with pytest.raises(FlightInputError, match="2 readings for 3 frames"):
        run_pipeline_multi(imgs, poses, cam, altimeter_m=[150.0, 75.0])
    # the v1 flow says it used the widest pair only
    res = run_pipeline_multi(imgs, poses, cam, preset="fast_v1")
    assert res.info["frames_used"] == [0, 2]


def test_process_uses_every_frame_and_keeps_the_deadline(tmp_path):
    from hil_server.cli import main

    cam, poses, imgs, z = descent(128, [160.0, 120.0, 80.0], roof(10.0, -2.0), seed=14)
    d = write_pair(tmp_path / "descent", Pair(cam, tuple(poses), tuple(imgs), truth={"elevation": z}))
    out = tmp_path / "out"
    assert main(["process", str(d), "--out", str(out)]) == 0
    doc = json.loads((out / "result.json").read_text())
    assert doc["frames"] == 3 and doc["info"]["multi_frame"]["frames"] == 3
    assert np.load(out / "state.npy").shape == (128, 128)
    # an anytime result within the deadline (5 ms: the whole 128 px descent takes ~40 ms on a fast host, so
    # 50 ms was sometimes met in full and the result was not degraded)
    t0 = time.monotonic()
    res = run_pipeline_multi(imgs, poses, cam, deadline_s=0.005)
    assert time.monotonic() - t0 < 1.0 and res.degraded
    assert math.isfinite(res.valid_fraction)


def test_frame_numbers_must_be_one_whole_number_per_frame():
    from flight_sw.pipeline import _frame_numbers
    from flight_sw.validate import FlightInputError

    assert _frame_numbers(None, 3) == [0, 1, 2] and _frame_numbers([0, np.int64(5)], 2) == [0, 5]
    for bad in ([0, 2.7], [0, True], [0, 0], [0, -1], [0, 1, 2]):
        with pytest.raises(FlightInputError, match="frame_numbers"):
            _frame_numbers(bad, 2)
