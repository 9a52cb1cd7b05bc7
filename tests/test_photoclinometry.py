"""Footprint slope from shading plus stereo (flight_sw/photoclinometry.py): it must beat a noisy DEM's slope."""

from __future__ import annotations

import math

import numpy as np
import pytest

from flight_sw.photoclinometry import incidence_cosine, measured_incidence, shading_gradient, sunward_split
from protocol.pairdir import Sun


def sun_vector(azimuth_deg: float, elevation_deg: float) -> np.ndarray:
    return Sun(azimuth_deg, elevation_deg).direction()


def test_sun_vector_follows_the_design_convention() -> None:
    # azimuth clockwise from +Y toward +X
    np.testing.assert_allclose(sun_vector(90.0, 0.0), [1.0, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(sun_vector(0.0, 90.0), [0.0, 0.0, 1.0], atol=1e-12)
    s = sun_vector(135.0, 25.0)
    assert s[0] > 0 > s[1] and abs(np.linalg.norm(s) - 1.0) < 1e-12


@pytest.mark.parametrize("elevation", [10.0, 25.0, 45.0, 70.0])
def test_exact_incidence_gives_back_the_exact_gradient(elevation: float) -> None:
    """With the true cos i, a DEM error in the sun-ward component is replaced by the truth.

    Brightness is two-valued around the brightest tilt ``a* = -s_h (1 + b^2) / s_z``; the DEM picks the
    branch, so a DEM on the other side of ``a*`` (only under a high sun, near ``a*``) is not expected to.
    """
    rng = np.random.default_rng(3)
    sun = sun_vector(135.0, elevation)
    gx = rng.uniform(-0.25, 0.25, 4000)  # up to ~19 deg
    gy = rng.uniform(-0.25, 0.25, 4000)
    c = incidence_cosine(gx, gy, sun)
    # the DEM gets the across-sun component right and the sun-ward one wrong by up to 0.1 (5.7 deg)
    sh = math.hypot(sun[0], sun[1])
    hx, hy = sun[0] / sh, sun[1] / sh
    err = rng.uniform(-0.1, 0.1, gx.size)
    a, b = gx * hx + gy * hy, gy * hx - gx * hy
    a_star = -sh * (1 + b * b) / sun[2]
    keep = (c > 0.05) & (np.sign(a - a_star) == np.sign(a + err - a_star))
    assert keep.mean() > 0.6
    g = shading_gradient(gx + err * hx, gy + err * hy, c, sun)
    np.testing.assert_allclose(g[keep], np.hypot(gx, gy)[keep], atol=2e-4)
    # the split itself: the signed sun-ward tilt from the brightness, the across-sun one from the DEM
    a_s, b_s = sunward_split(gx + err * hx, gy + err * hy, c, sun)
    # (float32 roots: within 0.002, 0.1 deg, where the two roots are close to each other near a*)
    np.testing.assert_allclose(a_s[keep], a[keep], atol=2e-3)
    np.testing.assert_allclose(b_s, b, atol=1e-6)


def test_shading_slope_beats_a_noisy_dem_on_a_rendered_surface() -> None:
    """Lambert image of undulating ground with a slowly varying albedo; the DEM's gradient carries noise."""
    n = 256
    yy, xx = np.mgrid[0:n, 0:n].astype(np.float64)
    cell = 1.0
    # world X along columns, world Y against rows: dz/dX and dz/dY of a sum of sinusoids
    X, Y = xx * cell, -yy * cell
    k1, k2 = 2 * math.pi / 40.0, 2 * math.pi / 27.0
    gx = 1.6 * k1 * np.cos(k1 * X + 0.3) + 0.8 * k2 * np.cos(k2 * (X + Y))
    gy = 1.1 * k2 * np.cos(k2 * Y) + 0.8 * k2 * np.cos(k2 * (X + Y))
    sun = sun_vector(135.0, 30.0)
    cos_i = incidence_cosine(gx, gy, sun)
    albedo = 0.12 * (1.0 + 0.15 * np.sin(2 * math.pi * X / 300.0))  # slow: the gain absorbs it
    rng = np.random.default_rng(0)
    img = np.clip(albedo * np.clip(cos_i, 0, None) / 0.12 * 180.0 + rng.normal(0, 1.0, (n, n)), 0, 255)
    lit = cos_i > 0.05
    noise = 0.08  # ~4.6 deg of slope noise per component
    gx_d = gx + rng.normal(0, noise, gx.shape)
    gy_d = gy + rng.normal(0, noise, gy.shape)
    c_meas = measured_incidence(img.astype(np.float32), incidence_cosine(gx_d, gy_d, sun), lit, 1.0, 24.0)
    g_pc = shading_gradient(gx_d, gy_d, c_meas, sun)
    inner = np.zeros((n, n), bool)
    inner[32:-32, 32:-32] = True
    ok = inner & lit & np.isfinite(g_pc)
    assert ok.mean() > 0.5
    truth = np.hypot(gx, gy)
    err_dem = np.median(np.abs(np.hypot(gx_d, gy_d) - truth)[ok])
    err_pc = np.median(np.abs(g_pc - truth)[ok])
    assert err_pc < 0.75 * err_dem, (err_pc, err_dem)


def test_nothing_lit_gives_no_incidence() -> None:
    img = np.full((64, 64), 100.0, np.float32)
    c = measured_incidence(img, np.full((64, 64), 0.5, np.float32), np.zeros((64, 64), bool), 3.0, 16.0)
    assert np.isnan(c).all()
    g = shading_gradient(np.zeros(3), np.zeros(3), np.array([np.nan, 0.4, 0.4]), sun_vector(0.0, 25.0))
    assert np.isnan(g[0]) and np.isfinite(g[1:]).all()


@pytest.mark.parametrize("sigma", [4.0, 20.0, 60.0])
def test_wide_blur_matches_a_gaussian_blur(sigma: float) -> None:
    import cv2

    from flight_sw.photoclinometry import wide_blur

    rng = np.random.default_rng(1)
    a = cv2.GaussianBlur(rng.uniform(0, 255, (256, 256)).astype(np.float32), (0, 0), 3.0) + np.linspace(0, 80, 256)
    exact = cv2.GaussianBlur(a.astype(np.float32), (0, 0), sigma, borderType=cv2.BORDER_REFLECT)
    inner = (slice(64, -64), slice(64, -64))
    assert np.max(np.abs(wide_blur(a, sigma) - exact)[inner]) < 0.02 * float(np.ptp(a))


@pytest.mark.parametrize("sigma", [12.0, 29.0, 60.0])
def test_the_compensated_wide_blur_is_closer_to_the_gaussian(sigma: float) -> None:
    """The wall cue's local mean (shading.relative_brightness, wide=True) takes the small copy's extra
    variance out of its blur: it must land closer to the full-size Gaussian than the plain small-copy blur."""
    import cv2

    from flight_sw.shading import relative_brightness, wide_blur

    rng = np.random.default_rng(2)
    a = cv2.GaussianBlur(rng.uniform(0, 255, (512, 512)).astype(np.float32), (0, 0), 2.0) + 60.0
    exact = cv2.GaussianBlur(a, (0, 0), sigma, borderType=cv2.BORDER_REFLECT)
    inner = (slice(96, -96), slice(96, -96))
    err_plain = np.abs(wide_blur(a, sigma) - exact)[inner]
    err_comp = np.abs(wide_blur(a, sigma, compensate=True) - exact)[inner]
    assert float(err_comp.mean()) <= float(err_plain.mean())
    assert float(np.max(np.abs(err_comp / exact[inner]))) < 2e-3
    rho_exact = relative_brightness(a, sigma, 1.0)
    assert float(np.max(np.abs(relative_brightness(a, sigma, 1.0, wide=True) - rho_exact)[inner])) < 2e-3


def test_the_pipeline_reads_it_only_when_told_the_sun_and_skips_it_when_late(monkeypatch):
    import dataclasses
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).parent))
    from synthetic import make_pair, plane

    from flight_sw import pipeline
    from flight_sw.validate import FlightInputError

    cam, p1, p2, i1, i2, _ = make_pair(256, 200.0, 100.0, plane(0.0), seed=41)
    prm = dataclasses.replace(pipeline.PRESETS["fast"], keep_layers=True)
    sun = {"sun_azimuth_deg": 135.0, "sun_elevation_deg": 25.0}
    told = pipeline.run_pipeline(i1, i2, p1, p2, cam, preset=prm, **sun)
    a_pc = told.layers["a_pc"][told.covered]
    assert np.isfinite(a_pc).mean() > 0.5 and "shading_slope" not in told.info["skipped"]
    # an elevation alone is not the sun's direction: no shading slope
    blind = pipeline.run_pipeline(i1, i2, p1, p2, cam, preset=prm, sun_elevation_deg=25.0)
    assert np.isnan(blind.layers["a_pc"]).all()
    with pytest.raises(FlightInputError, match="sun_azimuth_deg"):
        pipeline.run_pipeline(i1, i2, p1, p2, cam, preset=prm, sun_azimuth_deg=400.0, sun_elevation_deg=25.0)
    # when its cost no longer fits before the deadline it is skipped, said so, and the map still comes
    monkeypatch.setattr(pipeline, "SHADING_SLOPE_S", 1e6)
    late = pipeline.run_pipeline(i1, i2, p1, p2, cam, preset=prm, deadline_s=120.0, **sun)
    assert "shading_slope" in late.info["skipped"] and np.isnan(late.layers["a_pc"]).all()
    assert late.level == "full" and np.isfinite(late.hazard[late.covered]).all()
