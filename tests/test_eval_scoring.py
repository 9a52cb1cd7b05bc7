"""Scoring against closed forms and hand-counted confusion matrices."""

from __future__ import annotations

import math

import numpy as np
import pytest

from ground_sim import scoring
from protocol.errors import InputError
from protocol.pairdir import Camera, Pose

NADIR = np.array([[1.0, 0, 0], [0, -1.0, 0], [0, 0, -1.0]])  # camera z = world -Z


def test_error_stats_hand_values_and_nan_ignored():
    truth = np.zeros((1, 6))
    est = np.array([[-1.0, 0.0, 0.0, 1.0, 10.0, np.nan]])
    s = scoring.dem_error_stats(est, truth)
    assert s["n"] == 5
    assert s["mean_abs"] == pytest.approx(12 / 5)
    assert s["median"] == 0.0
    assert s["mad"] == 1.0  # median of |[-1,0,0,1,10] - 0|


def test_detrended_error_removes_a_tilt_and_a_datum_shift_but_not_a_bump():
    h, w = 40, 50
    y, x = np.mgrid[0:h, 0:w].astype(float)
    xy = np.dstack([x * 2.0 + 100.0, y * 2.0 - 30.0])  # world metres of each pixel
    truth = np.sin(x / 5.0) * np.cos(y / 7.0)  # some terrain
    tilt = 0.4 + 0.01 * xy[..., 0] - 0.02 * xy[..., 1]  # 0.6 deg of tilt and a 0.4 m datum shift
    est = truth + tilt
    assert scoring.dem_error_stats(est, truth)["mean_abs"] > 1.0
    assert scoring.detrended_error(est, truth, xy) == pytest.approx(0.0, abs=1e-9)
    bump = np.where(np.hypot(x - 25, y - 20) < 5, 1.0, 0.0)  # a 1 m shape error the plane cannot absorb
    d = scoring.detrended_error(est + bump, truth, xy)
    assert 0.5 * bump.mean() < d < 2.0 * bump.mean()
    est[0, :] = np.nan  # NaN and the mask are honoured
    mask = np.ones((h, w), bool)
    mask[:, :10] = False
    assert scoring.detrended_error(est, truth, xy, mask) == pytest.approx(0.0, abs=1e-9)
    assert math.isnan(scoring.detrended_error(est[:1], truth[:1], xy[:1]))
    with pytest.raises(ValueError):
        scoring.detrended_error(est, truth, xy[..., :1])


def test_error_stats_moments_match_bernoulli_closed_form():
    p = 0.2
    n = 1000
    err = np.zeros((1, n))
    err[0, : int(p * n)] = 1.0  # Bernoulli(p) sample with exact proportions
    s = scoring.error_stats(err, np.zeros_like(err))
    q = 1 - p
    assert s["skewness"] == pytest.approx((q - p) / math.sqrt(p * q), rel=1e-9)
    assert s["kurtosis"] == pytest.approx((1 - 6 * p * q) / (p * q), rel=1e-9)  # excess


def test_error_stats_gaussian_is_near_zero_moments_and_mask_applies():
    rng = np.random.default_rng(0)
    err = rng.normal(0.0, 2.0, (400, 400))
    s = scoring.error_stats(err, np.zeros_like(err))
    assert abs(s["skewness"]) < 0.03 and abs(s["kurtosis"]) < 0.06
    assert s["mad"] == pytest.approx(2.0 * 0.6745, rel=0.02)
    mask = np.zeros(err.shape, bool)
    mask[:10] = True
    assert scoring.error_stats(err, np.zeros_like(err), mask)["n"] == 4000
    empty = scoring.error_stats(err, np.zeros_like(err), np.zeros_like(mask))
    assert empty["n"] == 0 and math.isnan(empty["mean_abs"])


def test_confusion_hand_counted():
    truth = np.zeros((10, 10), np.float32)
    truth[:, :4] = 1.0  # 40 % hazards
    est = np.zeros((10, 10), np.float32)
    est[:, :3] = 1.0  # misses one hazard column -> 10 % FP
    est[:, 9] = 2.0  # one false-alarm column -> 10 % FN
    c = scoring.confusion(est, truth, np.ones((10, 10), bool))
    assert (c["tp"], c["tn"], c["fp"], c["fn"]) == (50.0, 30.0, 10.0, 10.0)
    assert c["tn_rate"] == pytest.approx(75.0) and c["tp_rate"] == pytest.approx(50 / 60 * 100)
    assert c["cdi"] == 80.0 and c["hazards_pct"] == 40.0 and c["n"] == 100


def test_confusion_threshold_flag_flips_and_nan_is_unsafe():
    truth = np.ones((1, 2), np.float32)
    assert scoring.confusion(np.full((1, 2), 0.999), truth, None)["fp"] == 100.0
    assert scoring.confusion(np.full((1, 2), 1.0), truth, None)["fp"] == 0.0
    c = scoring.confusion(np.array([[np.nan, 0.0]]), np.zeros((1, 2)), None)
    assert c["fn"] == 50.0 and c["tp"] == 50.0 and c["fp"] == 0.0


def test_confusion_coverage_exclusion_and_nan_truth_not_scored():
    truth = np.zeros((4, 4))
    truth[0, 0] = np.nan
    est = np.zeros((4, 4))
    covered = np.ones((4, 4), bool)
    covered[3] = False
    exclude = np.zeros((4, 4), bool)
    exclude[2] = True
    assert scoring.confusion(est, truth, covered, exclude)["n"] == 7


def test_shape_mismatch_is_input_error():
    with pytest.raises(InputError, match="shape"):
        scoring.confusion(np.zeros((3, 3)), np.zeros((3, 4)), None)
    with pytest.raises(InputError):
        scoring.disk_kernel(float("nan"))


def test_site_scores_missed_rock_spoils_every_site_around_it():
    truth = np.zeros((41, 41), np.float32)
    truth[20, 20] = 1.0  # one small rock the detector misses
    est = np.zeros_like(truth)
    r = 3.0
    s = scoring.site_scores(est, truth, None, r)
    disk = int(scoring.disk_kernel(r).sum())
    n_sites = (41 - 6) ** 2  # footprint must fit inside the image
    assert s["n"] == n_sites
    assert s["fp"] == pytest.approx(100.0 * disk / n_sites)
    pix = scoring.confusion(est, truth, None)
    assert pix["fp"] == pytest.approx(100 / 41**2)  # pixel level sees one pixel only
    est[20, 20] = 1.0
    assert scoring.site_scores(est, truth, None, r)["fp"] == 0.0


def test_epipole_nadir_descent_is_principal_point_and_box_is_thesis_80px():
    cam = Camera.thesis()
    p1 = Pose(np.array([0.0, 0, 600]), NADIR)
    p2 = Pose(np.array([0.0, 0, 300]), NADIR)
    assert scoring.epipole_px(cam, p1, p2) == pytest.approx((255.5, 255.5))
    side = Pose(np.array([5.0, 0, 600]), NADIR)
    assert scoring.epipole_px(cam, p1, side) is None
    m = scoring.box_mask((512, 512), (255.5, 255.5), 80)
    rows, cols = np.nonzero(m)
    assert (rows.min(), rows.max(), cols.min(), cols.max()) == (216, 295, 216, 295)
    assert scoring.box_mask((10, 10), (-50.0, 3.0), 8).sum() == 0


def test_epipole_tilted_motion_projects_second_centre():
    cam = Camera.thesis()
    a = math.radians(20)
    tilt = np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]]) @ NADIR
    p1 = Pose(np.array([0.0, 0, 600]), tilt)
    p2 = Pose(np.array([0.0, 40, 300]), tilt)
    u, v = scoring.epipole_px(cam, p1, p2)
    x = cam.K @ (tilt @ (p2.position - p1.position))
    assert (u, v) == pytest.approx((x[0] / x[2], x[1] / x[2]))
