"""Hazard-computation blocks (thesis Table 5.2): shadows, rocks, slope/roughness, mapping, sites."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from flight_sw.mapping import (
    HazardGrid,
    combine,
    grid_extent,
    grid_xy,
    remap_maps,
    remap_valid,
    remap_with,
    sample_grid,
    widen_hazards,
)
from flight_sw.rocks import rock_mask
from flight_sw.shadow import shadow_mask, shadow_threshold
from flight_sw.sites import footprint_stats, select_sites
from flight_sw.slope import footprint_cells, plane_fit, roughness


def test_chessboard_shadows():
    sq = (np.indices((128, 128)) // 16).sum(axis=0) % 2
    img = np.where(sq == 1, 200, 40).astype(np.uint8)
    assert shadow_threshold(img) == pytest.approx((120 + 80) / 2)
    np.testing.assert_array_equal(shadow_mask(img), sq == 0)


@pytest.mark.parametrize("slope_deg", [10.0, 20.0])
def test_roof_dem_slope_at_1m(slope_deg):
    cell = 1.0
    x = (np.arange(61) - 30) * cell
    X, Y = np.meshgrid(x, x)
    g = math.tan(math.radians(slope_deg))
    z = 100.0 - g * np.abs(X)
    slope, zp = plane_fit(z, cell, footprint_m=3.0)
    r = footprint_cells(3.0, cell) // 2
    away = (np.abs(X) > r) & (np.abs(X) < 28) & (np.abs(Y) < 28)
    np.testing.assert_allclose(slope[away], slope_deg, atol=1e-3)
    np.testing.assert_allclose(roughness(z, zp)[away], 0.0, atol=1e-3)
    ridge = (X == 0) & (np.abs(Y) < 28)
    assert np.all(slope[ridge] < 1.0)  # symmetric roof: the fit is level at the ridge
    assert np.all(roughness(z, zp)[ridge] > 0.5 * g)  # ... and the ridge stands above it


def test_plane_fit_matches_lstsq_with_holes():
    rng = np.random.default_rng(7)
    z = cv2.GaussianBlur(rng.normal(0, 1, (40, 40)), (0, 0), 2.0) * 5
    z[rng.random(z.shape) < 0.2] = np.nan
    cell, n = 0.5, 7
    slope, zp = plane_fit(z, cell, footprint_m=n * cell, min_fraction=0.3)
    for i, j in [(10, 10), (20, 25), (30, 8)]:
        win = z[i - 3 : i + 4, j - 3 : j + 4]
        yy, xx = np.mgrid[-3:4, -3:4] * cell
        ok = np.isfinite(win)
        A = np.column_stack([xx[ok], yy[ok], np.ones(ok.sum())])
        (p, q, c), *_ = np.linalg.lstsq(A, win[ok], rcond=None)
        assert slope[i, j] == pytest.approx(math.degrees(math.atan(math.hypot(p, q))), abs=1e-3)
        assert zp[i, j] == pytest.approx(c, abs=1e-4)
    sparse = np.full((20, 20), np.nan)
    sparse[10, 10] = 1.0
    assert np.isnan(plane_fit(sparse, 1.0)[0]).all()


def test_rock_detection_finds_rocks_and_surroundings():
    rng = np.random.default_rng(8)
    img = 120 + cv2.GaussianBlur(rng.normal(0, 1, (200, 200)), (0, 0), 3.0) * 30
    rocks = [(40, 50), (100, 150), (160, 70)]
    for r, c in rocks:
        img[r : r + 4, c : c + 4] = 250  # sunlit boulder
        img[r + 4 : r + 7, c : c + 4] = 5  # its shadow
    m = rock_mask(np.clip(img, 0, 255).astype(np.uint8))
    for r, c in rocks:
        assert m[r : r + 7, c : c + 4].mean() > 0.5
        assert m[r - 1, c + 1] or m[r + 7, c + 1]  # immediate surroundings included
    assert m.mean() < 0.05
    assert not rock_mask(np.full((50, 50), 90, np.uint8)).any()


def test_combine_on_artificial_maps():
    slope = np.array([[0.0, 7.5, 30.0, np.nan, 0.0, 0.0]], np.float32)
    rough = np.array([[0.0, 0.15, 0.0, 0.0, 0.0, 0.0]], np.float32)
    shadow = np.array([[0, 0, 0, 0, 1, 0]], bool)
    rock = np.array([[0, 0, 0, 0, 0, 1]], bool)
    cov = np.ones((1, 6), bool)
    np.testing.assert_allclose(combine(slope, rough, shadow, rock, cov), [[0, 0.5, 1, 1, 1, 1]])
    cov[0, 0] = False
    assert np.isnan(combine(slope, rough, shadow, rock, cov)[0, 0])
    # image-only: DEM layers ignored
    np.testing.assert_allclose(combine(None, None, shadow, rock, np.ones((1, 6), bool)), [[0, 0, 0, 0, 1, 1]])


def test_keep_out_margin_grows_hazards_by_a_disk_and_leaves_uncovered_alone():
    h = np.zeros((9, 9), np.float32)
    h[4, 4] = 1.0
    h[0, :] = np.nan  # outside the covered area
    h[8, 8] = 0.4
    assert widen_hazards(h, 0.0) is h
    w = widen_hazards(h, 1.0)
    unsafe = w >= 1.0
    assert unsafe.sum() == 5 and unsafe[3:6, 4].all() and unsafe[4, 3:6].all()  # 4-neighbours, no corners
    assert np.isnan(w[0]).all() and not np.isnan(w[1:]).any()
    assert w[7, 8] == pytest.approx(0.4) and w[7, 7] == 0.0 and w[8, 8] == pytest.approx(0.4)  # graded values too
    w2 = widen_hazards(h, 2.0)
    assert (w2 >= 1.0).sum() == 13 and w2[2, 4] == 1.0 and w2[3, 3] == 1.0 and w2[2, 3] < 1.0
    with pytest.raises(ValueError):
        widen_hazards(h, float("nan"))
    # in combine: only the measured DEM layer is widened; image cues and unknown DEM stay put
    slope = np.zeros((1, 9), np.float32)
    slope[0, 1], slope[0, 7] = 30.0, np.nan
    shadow = np.zeros((1, 9), bool)
    shadow[0, 4] = True
    out = combine(slope, np.zeros_like(slope), shadow, np.zeros_like(shadow), np.ones((1, 9), bool), margin_px=1.0)
    np.testing.assert_array_equal(out[0] >= 1, [1, 1, 1, 0, 1, 0, 0, 1, 0])


def test_grid_round_trip():
    origin, shape = grid_extent(np.array([-3.2, 4.9]), np.array([-1.0, 2.6]), 0.5)
    X, Y = grid_xy(shape, origin, 0.5)
    assert X.min() <= -3.2 and X.max() >= 4.9 and Y.min() <= -1.0 and Y.max() >= 2.6
    assert Y[0, 0] > Y[1, 0]  # rows go toward -Y
    px, py = np.array([[0.3, -2.0]]), np.array([[1.1, 0.4]])
    np.testing.assert_allclose(sample_grid(X, origin, 0.5, px, py), px, atol=1e-5)
    np.testing.assert_allclose(sample_grid(Y, origin, 0.5, px, py), py, atol=1e-5)


def test_sites_avoid_hazards_and_spiral_out():
    cell = 0.5
    haz = np.full((81, 81), 0.2, np.float32)
    haz[30:51, 30:51] = 1.0  # unsafe block around the nominal site
    haz[10:20, 60:70] = 0.0  # the safest area, far away
    haz[:, 0:3] = np.nan  # unknown strip
    grid = HazardGrid(haz, np.zeros_like(haz), (-20.0, 20.0), cell)  # cell [40, 40] is (0, 0)
    sites = select_sites(grid, 3.0, (0.0, 0.0), k=4)
    assert len(sites) == 4
    n = footprint_cells(3.0, cell)
    safe, hmax = footprint_stats(haz, n)
    X, Y = grid.cell_xy()
    for s in sites:
        j, i = int(round((s.x + 20) / cell)), int(round((20 - s.y) / cell))
        assert safe[i, j] and np.all(haz[i - n // 2 : i + n // 2 + 1, j - n // 2 : j + n // 2 + 1] < 1)
        assert s.margin == pytest.approx(0.8)
    d = [s.distance_m for s in sites]
    assert min(d) >= 5.0 + 1.5 - 1e-9 and max(d) < 5.0 + 1.5 + 3.0 + 1e-9  # first ring outside the block
    for a in sites:
        for b in sites:
            if a is not b:
                assert math.hypot(a.x - b.x, a.y - b.y) >= 3.0
    assert select_sites(HazardGrid(np.ones((20, 20), np.float32), np.zeros((20, 20)), (0, 0), 1.0)) == []


def test_remap_valid_reads_a_holes_rim_from_its_finite_neighbours():
    """A plane with a hole: the plain bilinear read loses a pixel's width around the hole; the finite read is,
    point by point, the bilinear weights' mean over the finite corners, NaN where they carry under half."""
    v, u = np.mgrid[0:20, 0:20].astype(np.float32)
    z = 2.0 * u - 0.5 * v + 3.0
    z[8:12, 8:12] = np.nan
    rng = np.random.default_rng(7)
    mu, mv = rng.uniform(0, 19, 4000).astype(np.float32), rng.uniform(0, 19, 4000).astype(np.float32)
    maps = remap_maps(mu[None, :], mv[None, :])
    plain, finite = remap_with(z, maps)[0], remap_valid(z, maps)[0]
    assert np.allclose(finite[np.isfinite(plain)], plain[np.isfinite(plain)], atol=1e-4)
    assert (~np.isfinite(plain) & np.isfinite(finite)).sum() > 100  # the rim the plain read lost
    u0, v0 = np.floor(mu).astype(int), np.floor(mv).astype(int)
    fu, fv = mu - u0, mv - v0
    num = np.zeros(mu.shape)
    den = np.zeros(mu.shape)
    for du, dv, w in ((0, 0, (1 - fu) * (1 - fv)), (1, 0, fu * (1 - fv)), (0, 1, (1 - fu) * fv), (1, 1, fu * fv)):
        c = z[np.minimum(v0 + dv, 19), np.minimum(u0 + du, 19)]
        ok = np.isfinite(c)
        num += np.where(ok, w * np.nan_to_num(c), 0.0)
        den += np.where(ok, w, 0.0)
    clear = np.abs(den - 0.5) > 0.01  # OpenCV's fixed-point weights decide the ties
    want = np.where(den >= 0.5, num / np.maximum(den, 1e-9), np.nan)
    assert np.array_equal(np.isnan(finite[clear]), np.isnan(want[clear]))
    ok = clear & np.isfinite(want)
    assert np.allclose(finite[ok], want[ok], atol=0.02)
