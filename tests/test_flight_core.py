"""DEM-computation blocks (thesis Table 5.2): homography, warping, SAD/SSD, sweep, georeferencing."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
import itertools

from synthetic import NADIR_R, camera_fov30, crater, make_pair, plane, tilted_R

from flight_sw.correlation import parabolic_offset, window_cost
from flight_sw.georef import backproject
from flight_sw.homography import map_points
from flight_sw.sweep import coverage_mask, plane_homography, planes_uniform_disparity, planes_uniform_dz, sweep_dem
from flight_sw.warping import area_sigma, bilinear_sample, warp_to_i1
from protocol.pairdir import Pose


def project(cam, pose, X):
    xc = pose.R @ (X - pose.position[:, None])
    return cam.fx * xc[0] / xc[2] + cam.cx, cam.fy * xc[1] / xc[2] + cam.cy


@pytest.mark.parametrize(
    "R1,R2", [(NADIR_R, NADIR_R), (tilted_R(40), tilted_R(38, "x")), (tilted_R(10, "y"), tilted_R(-5, "x"))]
)
def test_plane_homography_maps_projections_of_plane_points(R1, R2):
    cam = camera_fov30(512)
    p1 = Pose([3.0, -2.0, 600.0], R1)
    p2 = Pose([10.0, 150.0, 300.0], R2)
    rng = np.random.default_rng(1)
    h = 7.5
    X = np.vstack([rng.uniform(-100, 100, 50), rng.uniform(-100, 300, 50), np.full(50, h)])
    u1, v1 = project(cam, p1, X)
    u2, v2 = project(cam, p2, X)
    mu, mv = map_points(plane_homography(cam, p1, p2, h), u1, v1)
    np.testing.assert_allclose(mu, u2, atol=1e-7)
    np.testing.assert_allclose(mv, v2, atol=1e-7)
    # a different plane must not map them
    mu2, _ = map_points(plane_homography(cam, p1, p2, h + 5), u1, v1)
    assert np.abs(mu2 - u2).max() > 0.1


def test_nadir_homography_is_thesis_scaling():
    """Eq. 3.11/3.12: for a vertical descent x2 - v = (Z1 / Z2)(x1 - v)."""
    cam = camera_fov30(512)
    H = plane_homography(cam, Pose([0, 0, 600.0], NADIR_R), Pose([0, 0, 300.0], NADIR_R), 0.0)
    u2, v2 = map_points(H, np.array([0.0, 400.0]), np.array([100.0, 255.5]))
    np.testing.assert_allclose(u2, cam.cx + 2 * (np.array([0.0, 400.0]) - cam.cx))
    np.testing.assert_allclose(v2, cam.cy + 2 * (np.array([100.0, 255.5]) - cam.cy))


def test_bilinear_warp_matches_reference():
    rng = np.random.default_rng(2)
    src = cv2.GaussianBlur(rng.uniform(0, 255, (120, 140)).astype(np.float32), (0, 0), 2.0)
    H = np.array([[0.98, 0.03, 5.3], [-0.02, 1.01, 3.7], [1e-4, -5e-5, 1.0]])
    roi = (7, 9, 90, 80)
    out = warp_to_i1(src, H, roi, border_value=-1)
    v, u = np.mgrid[9:89, 7:97].astype(np.float64)
    ref = bilinear_sample(src, *map_points(H, u, v))
    inside = np.isfinite(ref)
    assert inside.mean() > 0.9
    # OpenCV interpolates with 1/32-pixel weights: error bounded by gradient / 32
    assert np.abs(out[inside] - ref[inside]).max() < 0.5
    # an unfiltered reference on a pixel grid point is exact
    assert bilinear_sample(src, np.array([3.0]), np.array([4.0]))[0] == pytest.approx(src[4, 3])


def test_sad_ssd_hand_checked_3x3():
    i1 = np.arange(1, 10, dtype=np.float32).reshape(3, 3)
    i2 = np.ones((3, 3), np.float32)
    assert window_cost(i1, i2, 1, "sad")[1, 1] == pytest.approx(36.0)  # 0+1+...+8
    assert window_cost(i1, i2, 1, "ssd")[1, 1] == pytest.approx(204.0)  # 0+1+4+...+64
    c = window_cost(i1, i2, 1, "sad")
    assert np.isnan(c[0]).all() and np.isnan(c[:, 2]).all()
    i2b = i1.copy()
    i2b[0, 0] = 11
    assert window_cost(i1, i2b, 1, "sad")[1, 1] == pytest.approx(10.0)
    assert window_cost(i1, i2b, 1, "ssd")[1, 1] == pytest.approx(100.0)


def test_parabolic_refinement_recovers_vertex():
    k = np.array([-1.0, 0.0, 1.0])
    for x0 in (-0.4, 0.0, 0.3):
        c = 2.0 * (k - x0) ** 2 + 5.0
        assert parabolic_offset(c[0], c[1], c[2]) == pytest.approx(x0)
    assert parabolic_offset(np.float32(1), np.float32(1), np.float32(1)) == 0.0


def test_uniform_disparity_planes_step_in_pixels():
    cam = camera_fov30(256)
    p1, p2 = Pose([0, 0, 200.0], NADIR_R), Pose([0, 0, 100.0], NADIR_R)
    pl = planes_uniform_disparity(cam, p1, p2, -10, 10, 0.5)
    assert pl[0] == pytest.approx(-10) and pl[-1] == pytest.approx(10)
    # largest move between adjacent planes over the covered area is <= 0.5 px (and close to it)
    cov = coverage_mask(cam, p1, p2, -10, 10)
    v, u = np.nonzero(cov)
    moves = [
        np.hypot(
            *(
                np.subtract(
                    map_points(plane_homography(cam, p1, p2, b), u, v),
                    map_points(plane_homography(cam, p1, p2, a), u, v),
                )
            )
        ).max()
        for a, b in itertools.pairwise(pl)
    ]
    assert max(moves) <= 0.5 + 1e-3 and max(moves) > 0.4
    np.testing.assert_allclose(np.diff(planes_uniform_dz(-1, 1, 0.15)), 0.15)


@pytest.fixture(scope="module")
def plane_pair():
    return make_pair(256, 200.0, 100.0, plane(5.0), seed=3)


@pytest.mark.parametrize("mode", ["thesis", "fast"])
def test_textured_plane_recovered_within_centimetres(plane_pair, mode):
    cam, p1, p2, i1, i2, z = plane_pair
    if mode == "thesis":
        res = sweep_dem(i1, i2, cam, p1, p2, planes_uniform_dz(-15, 15, 0.15), half_window=8)
    else:
        res = sweep_dem(
            i1,
            i2,
            cam,
            p1,
            p2,
            planes_uniform_disparity(cam, p1, p2, -15, 15, 0.5),
            half_window=6,
            prefilter_sigma=area_sigma(0.5),
        )
    err = res.elevation - z
    ok = np.isfinite(err)
    assert ok.mean() > 0.12  # i2 sees the central quarter of i1, minus window borders
    # "a few centimetres per 100 m of altitude": 200 m -> mean |error| <= 0.1 m
    assert np.abs(err[ok]).mean() < 0.10
    assert abs(np.median(err[ok])) < 0.03
    # everything outside i2's view is NaN
    assert not np.isfinite(res.elevation[~coverage_mask(cam, p1, p2, 5.0)]).any()


def test_prefilter_reduces_error_on_relief():
    cam, p1, p2, i1, i2, z = make_pair(256, 200.0, 100.0, crater(30.0, 6.0), seed=4)
    pl = planes_uniform_disparity(cam, p1, p2, -15, 15, 0.5)
    errs = []
    for sigma in (0.0, area_sigma(0.5)):
        e = sweep_dem(i1, i2, cam, p1, p2, pl, half_window=4, prefilter_sigma=sigma).elevation - z
        errs.append(np.nanmean(np.abs(e)))
    assert errs[1] < 0.8 * errs[0]


def test_rock_pixels_are_nan_and_ignored(plane_pair):
    cam, p1, p2, i1, i2, z = plane_pair
    ign = np.zeros(i1.shape, bool)
    ign[120:130, 120:130] = True
    res = sweep_dem(i1, i2, cam, p1, p2, planes_uniform_disparity(cam, p1, p2, -15, 15, 0.5), half_window=6, ignore=ign)
    assert np.isnan(res.elevation[ign]).all()
    assert np.isfinite(res.elevation[115:118, 115:135]).all()


def test_sweep_stops_at_deadline(plane_pair):
    cam, p1, p2, i1, i2, z = plane_pair
    res = sweep_dem(i1, i2, cam, p1, p2, planes_uniform_dz(-15, 15, 0.15), deadline=0.0)
    assert not res.complete and res.planes_done == 0 and np.isnan(res.elevation).all()


def thesis_georef(h, theta, x_c, y_c, Zp):
    """Eq. 4.16/4.17 with alpha = atan(y_c) in the pitch plane, beta the out-of-plane angle."""
    alpha = math.atan(y_c)
    beta = math.atan(x_c / math.sqrt(1 + y_c**2))
    return ((h - Zp) / math.cos(theta + alpha) * math.tan(beta), (h - Zp) * math.tan(theta + alpha))


@pytest.mark.parametrize("tilt", [0.0, 20.0, 40.0])
def test_georeferencing_matches_thesis_equations(tilt):
    cam = camera_fov30(64)
    h = 500.0
    pose = Pose([0.0, 0.0, h], tilted_R(tilt))
    rng = np.random.default_rng(5)
    Z = rng.uniform(-20, 20, (64, 64))
    X, Y = backproject(cam, pose, Z)
    for r, c in [(0, 0), (10, 50), (31, 31), (63, 5), (40, 63)]:
        x_c, y_c = (c - cam.cx) / cam.fx, (r - cam.cy) / cam.fy
        Xo, Yo = thesis_georef(h, math.radians(tilt), x_c, y_c, Z[r, c])
        assert X[r, c] == pytest.approx(Xo, abs=1e-6)
        assert Y[r, c] == pytest.approx(-Yo, abs=1e-6)  # tilted_R looks toward -Y
    assert np.isnan(backproject(cam, pose, np.full((64, 64), np.nan))[0]).all()


@pytest.mark.parametrize("tilt,off", [(0.0, 0.0), (40.0, -100.0), (49.0, -250.0)])
def test_coverage_polygon_is_conservative_per_pixel_test(tilt, off):
    from flight_sw.sweep import _inside

    cam = camera_fov30(256)
    p1, p2 = Pose([0, 0, 500.0], tilted_R(tilt)), Pose([0, off, 250.0], tilted_R(tilt))
    fast = coverage_mask(cam, p1, p2, -20.0)
    v, u = np.mgrid[0:256, 0:256].astype(np.float64)
    exact = _inside(cam, plane_homography(cam, p1, p2, -20.0), u, v)
    assert not (fast & ~exact).any()  # never claims an uncovered pixel
    assert (exact & ~fast).sum() < 4 * 256  # loses at most a thin boundary ring


@pytest.mark.parametrize("n", [128, 129])
def test_a_pyramid_levels_layer_comes_back_where_it_was_measured(n):
    """pyrDown puts level pixel j at full pixel 2j: read back with resize, the coarse DEM sat half a full pixel off
    on an even width and up to 0.43 px either way on an odd one (review of stop 64)."""
    import cv2

    from flight_sw.mapping import from_pyramid

    u = np.tile(np.arange(n, dtype=np.float32), (n, 1))
    back = from_pyramid(cv2.pyrDown(u), (n, n))
    assert np.abs(back - u)[:, 3:-3].max() < 1e-3
