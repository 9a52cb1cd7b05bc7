"""Match confidence, gap filling and photometric cues (flight_sw.confidence / gapfill / shading)."""

from __future__ import annotations

import numpy as np
import pytest

from flight_sw.confidence import elevation_uncertainty, reject_uncertain
from flight_sw.gapfill import fill_small_gaps
from flight_sw.shading import local_shadow_mask, relative_brightness, shading_mask
from flight_sw.shadow import shadow_mask


def test_uncertainty_is_plane_step_over_root_curvature():
    planes = np.array([0.0, 1.0, 3.0, 6.0])  # spacings 1, 2, 3 centred at 0.5, 2, 4.5
    z = np.array([[2.0, 4.5, np.nan]])
    kappa = np.array([[0.25, 0.09, 1.0]])
    u = elevation_uncertainty(z, kappa, planes)
    assert u[0, 0] == pytest.approx(2.0 / 0.5)
    assert u[0, 1] == pytest.approx(3.0 / 0.3)
    assert np.isnan(u[0, 2])
    assert np.isinf(elevation_uncertainty(np.array([[2.0]]), np.array([[0.0]]), planes)[0, 0])


def test_reject_uncertain_drops_outliers_but_keeps_sharp_matches():
    rng = np.random.default_rng(0)
    z = rng.normal(0, 1, (50, 50)).astype(np.float32)
    u = np.ones_like(z)
    u[10, 10] = u[20, 20] = 5.0  # two flat cost curves
    kappa = np.full_like(z, 0.05)
    kappa[20, 20] = 0.5  # ... one of them sharp in absolute terms
    out = reject_uncertain(z, u, 1.5, kappa, sharp_curvature=0.2)
    assert np.isnan(out[10, 10]) and out[20, 20] == z[20, 20]
    assert np.isfinite(out).sum() == z.size - 1
    np.testing.assert_array_equal(reject_uncertain(z, u, 0.0), z)  # off


def test_fill_small_gaps_interpolates_small_holes_and_keeps_large_ones():
    yy, xx = np.mgrid[0:80, 0:80].astype(np.float32)
    z = 0.3 * xx - 0.2 * yy + 5.0
    holed = z.copy()
    holed[20:23, 20:23] = np.nan  # 3x3 gap surrounded by data
    holed[45:80, 45:80] = np.nan  # 35x35 hole: must stay unknown
    out = fill_small_gaps(holed, 4, 0.3)
    # a symmetric neighbourhood of a linear surface averages to its centre value
    assert out[21, 21] == pytest.approx(z[21, 21], abs=1e-4)
    assert np.nanmax(np.abs(out[20:23, 20:23] - z[20:23, 20:23])) < 0.5
    assert np.isnan(out[60:80, 60:80]).all()
    ok = np.isfinite(holed)
    np.testing.assert_array_equal(out[ok], holed[ok])
    np.testing.assert_array_equal(fill_small_gaps(holed, 0), holed)


def _lambert(normal_tilt_deg: np.ndarray, sun_elev_deg: float) -> np.ndarray:
    """Brightness of facets tilted toward the sun (positive) under a sun at ``sun_elev_deg``."""
    inc = np.radians(90.0 - sun_elev_deg - normal_tilt_deg)
    return np.maximum(np.cos(inc), 0.0)


def test_shading_flags_steep_facets_not_flat_ground():
    rng = np.random.default_rng(1)
    tilt = np.zeros((200, 200))
    tilt[90:110, 40:60] = 20.0  # wall facing the sun
    tilt[90:110, 140:160] = -20.0  # wall facing away
    tilt[20:40, 90:110] = 3.0  # gentle undulation: safe
    img = 100.0 * _lambert(tilt, 35.0) * (1 + 0.02 * rng.standard_normal(tilt.shape))
    mask = shading_mask(relative_brightness(img, 10.0), 0.15)
    assert mask[95:105, 45:55].mean() > 0.9 and mask[95:105, 145:155].mean() > 0.9
    assert mask[25:35, 95:105].mean() < 0.05
    assert mask[160:, :].mean() < 0.01


def test_local_shadow_test_ignores_a_smooth_illumination_gradient():
    # a dim half from a smooth brightness ramp is not shadow; a small dark pocket is
    xx = np.mgrid[0:128, 0:256][1].astype(np.float32)
    img = 40.0 + 120.0 * xx / 255.0
    img[60:70, 200:210] *= 0.2
    g = shadow_mask(img)
    assert g[:, :50].all()  # eq. 4.9 alone flags the whole dim side
    local = local_shadow_mask(img, g, relative_brightness(img, 10.0), 0.1)
    assert not local[:, :50].any() and g[:, :50].sum() > 6000
    assert local[62:68, 202:208].all()


def test_filled_gap_on_a_slope_keeps_the_slope():
    # a local mean would make the gap a flat terrace (a hidden wall); the plane fill must not
    from flight_sw.slope import plane_fit

    xx = np.mgrid[0:60, 0:60][1].astype(np.float32)
    z = np.tan(np.radians(25.0)) * xx  # 25 deg wall, 1 m cells
    holed = z.copy()
    holed[:, 28:35] = np.nan  # a 7-cell strip across the wall
    holed[:, 55:] = np.nan  # one-sided gap at the edge
    out = fill_small_gaps(holed, 6, 0.3)
    assert np.nanmax(np.abs(out[:, 28:35] - z[:, 28:35])) < 1e-3
    assert np.nanmax(np.abs(out[:, 55:] - z[:, 55:])) < 1e-3
    slope, _ = plane_fit(out, 1.0, 3.0)
    assert np.nanmin(slope[5:-5, 5:-5]) > 24.0
