"""End-to-end pipeline on synthetic scenes: accuracy, hazards, anytime levels, validation, determinism."""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
from synthetic import make_pair, plane, roof, tilted_R

from flight_sw.pipeline import PRESETS, Params, PipelineResult, run_pipeline
from flight_sw.sweep import plane_homography  # noqa: F401  (part of the interface contract)
from flight_sw.validate import FlightInputError
from protocol.errors import InputError
from protocol.pairdir import STATE_UNSAFE, Pose


@pytest.fixture(scope="module")
def plane_scene():
    return make_pair(256, 200.0, 100.0, plane(-3.0), seed=11)


@pytest.fixture(scope="module")
def plane_scene_512():
    return make_pair(512, 200.0, 100.0, plane(-3.0), seed=11)


@pytest.mark.parametrize("preset", ["fast", "thesis"])
def test_pipeline_recovers_plane(plane_scene, plane_scene_512, preset):
    # fast is tuned for the thesis's 512 px camera (21x21 window): its border loss on a 256 px
    # pair would dominate the valid fraction, so it is held to the same limits at 512 px
    cam, p1, p2, i1, i2, z = plane_scene_512 if preset == "fast" else plane_scene
    res = run_pipeline(i1, i2, p1, p2, cam, preset=preset)
    assert isinstance(res, PipelineResult)
    assert res.level == "full" and not res.degraded
    err = res.elevation - z
    assert np.nanmean(np.abs(err)) < 0.10
    assert res.valid_fraction > 0.6
    assert res.elevation.dtype == np.float32 and res.hazard.dtype == np.float32
    assert np.isnan(res.hazard[~res.covered]).all() and np.isfinite(res.hazard[res.covered]).all()
    assert np.nanmedian(res.slope_deg[res.covered]) < 2.0
    # world_xy lies on the plane's ray intersection
    ok = np.isfinite(res.elevation)
    assert res.world_xy.shape == i1.shape + (2,)
    assert set(res.timings) >= {"rocks", "coarse_dem", "full_dem", "slope", "sites", "total"}
    assert all(t["wall_s"] >= 0 and t["cpu_s"] >= 0 for t in res.timings.values())
    g = res.grid
    assert g.hazard.shape == g.elevation.shape and g.cell_m > 0
    assert np.nanmedian(np.abs(g.elevation - (-3.0))) < 0.1
    for s in res.sites:  # sites are on known-safe ground
        assert s.hazard < 1 and 0 < s.margin <= 1
        assert abs(s.z + 3.0) < (0.3 if preset == "fast" else 1.0)  # thesis preset: window-sized blobs
    assert ok.sum() > 0


@pytest.mark.parametrize("slope_deg", [10.0, 20.0])
def test_pipeline_measures_roof_slope(slope_deg):
    cam, p1, p2, i1, i2, z = make_pair(192, 120.0, 60.0, roof(slope_deg), seed=12)
    res = run_pipeline(i1, i2, p1, p2, cam, preset="fast")
    X = res.world_xy[..., 0]
    flank = res.covered & (np.abs(X) > 4) & np.isfinite(res.slope_deg)
    assert flank.sum() > 500
    assert np.median(res.slope_deg[flank]) == pytest.approx(slope_deg, abs=1.5)
    assert (res.slope_deg[flank] >= 15).mean() > 0.9 if slope_deg > 15 else (res.slope_deg[flank] >= 15).mean() < 0.05
    unsafe = res.state[flank] == STATE_UNSAFE
    if slope_deg > 15:
        assert unsafe.mean() > 0.9 and (res.hazard[flank] >= 1).all()
    else:
        # 10 deg is safe by the 15 deg rule. At 192 px `fast` uses the Gaussian rule (the calibrated model is
        # fitted for 512 px): the shading cue (lit and dark flanks differ) still calls part of the flank
        # unsafe; it must stay far from "everything unsafe"
        assert unsafe.mean() < 0.7


def test_oblique_approach_pair():
    cam, p1, p2, i1, i2, z = make_pair(256, 250.0, 125.0, plane(2.0), seed=13, R=tilted_R(20), offset2=(0.0, -45.0))
    res = run_pipeline(i1, i2, p1, p2, cam, preset="fast")
    err = res.elevation - z
    assert res.level == "full" and res.valid_fraction > 0.5
    assert np.nanmean(np.abs(err)) < 0.2


def test_anytime_levels(plane_scene):
    cam, p1, p2, i1, i2, _ = plane_scene
    r0 = run_pipeline(i1, i2, p1, p2, cam, deadline_s=0.0)
    assert r0.level == "image_only" and r0.degraded
    assert np.isnan(r0.elevation).all() and np.isfinite(r0.hazard[r0.covered]).all()
    assert r0.grid.hazard.size > 0
    # ~120000 planes: about 8 s on this host. 12000 planes no longer outlasted the 1 s deadline on a fast CI
    # host once the sweep got faster
    slow = dataclasses.replace(PRESETS["thesis"], dz_m=0.0002, check_every=1)
    r1 = run_pipeline(i1, i2, p1, p2, cam, preset=slow, deadline_s=1.0)
    assert r1.level == "coarse" and r1.degraded
    assert r1.timings["total"]["wall_s"] < 1.5
    # half-resolution DEM: unbiased but noisy, worst near the epipole (image centre)
    assert np.nanmean(np.abs(r1.elevation + 3.0)) < 1.5
    assert abs(np.nanmedian(r1.elevation + 3.0)) < 0.3
    r2 = run_pipeline(i1, i2, p1, p2, cam, deadline_s=30.0)
    assert r2.level == "full" and not r2.degraded


def _bad(plane_scene, **kw):
    cam, p1, p2, i1, i2, _ = plane_scene
    args = dict(i1=i1, i2=i2, pose1=p1, pose2=p2, camera=cam)
    args.update(kw)
    with pytest.raises(InputError) as exc:
        run_pipeline(
            args["i1"],
            args["i2"],
            args["pose1"],
            args["pose2"],
            args["camera"],
            **{k: v for k, v in kw.items() if k in ("preset", "deadline_s", "nominal_site_xy")},
        )
    assert isinstance(exc.value, FlightInputError)
    return str(exc.value)


def test_bad_inputs_raise_clear_errors(plane_scene):
    cam, p1, p2, i1, i2, _ = plane_scene
    assert "size" in _bad(plane_scene, i2=i2[:100])
    assert "2-D" in _bad(plane_scene, i1=np.stack([i1, i1], -1))
    assert "orthonormal" in _bad(plane_scene, pose1=Pose(p1.position, p1.R * 1.1))
    assert "NaN" in _bad(plane_scene, pose2=Pose([0, np.nan, 100.0], p2.R))
    assert "below" in _bad(plane_scene, pose1=p2, pose2=p1)
    assert "preset" in _bad(plane_scene, preset="turbo")
    assert "deadline" in _bad(plane_scene, deadline_s=float("nan"))
    assert "half_window" in _bad(plane_scene, preset=Params(half_window=0))
    assert "NaN" in _bad(plane_scene, i1=np.full(i1.shape, np.nan))
    # grey levels are 8-bit: a 0-1 float image gave an empty DEM called "full", a 16-bit one 9 % of it
    assert "multiply by 255" in _bad(plane_scene, i1=i1.astype(np.float32) / 255.0)
    assert "must lie in 0-255" in _bad(plane_scene, i2=i2.astype(np.uint16) * 257)
    assert "must lie in 0-255" in _bad(plane_scene, i2=i2.astype(np.float32) - 10.0)


def test_an_image_of_grey_levels_in_another_dtype_gives_the_uint8_result(plane_scene):
    cam, p1, p2, i1, i2, _ = plane_scene
    a = run_pipeline(i1, i2, p1, p2, cam)
    b = run_pipeline(i1.astype(np.float32), i2.astype(np.uint16), p1, p2, cam)
    assert np.array_equal(a.state, b.state) and np.allclose(a.elevation, b.elevation, equal_nan=True)


def test_deterministic(plane_scene):
    cam, p1, p2, i1, i2, _ = plane_scene
    a = run_pipeline(i1, i2, p1, p2, cam)
    b = run_pipeline(i1, i2, p1, p2, cam)
    assert a.elevation.tobytes() == b.elevation.tobytes()
    assert a.hazard.tobytes() == b.hazard.tobytes()
    assert a.sites == b.sites


def test_tiny_sensor_still_gets_a_dem():
    """96 px pair: the window is capped to the ~46 px overlap; an empty coarse level falls back to the full range."""
    from flight_sw.pipeline import window_px

    assert window_px(8, 256) == 8 and window_px(8, 46) == 5 and window_px(8, 10) == 2
    assert window_px(8, 46, cap=False) == 8
    cam, p1, p2, i1, i2, z = make_pair(96, 200.0, 100.0, plane(1.0), seed=14)
    res = run_pipeline(i1, i2, p1, p2, cam, preset="fast_v1")
    assert res.level == "full" and res.info["half_window_px"] == 5
    assert np.isfinite(res.elevation).sum() > 300
    assert np.nanmean(np.abs(res.elevation - z)) < 0.3
    v2 = run_pipeline(i1, i2, p1, p2, cam)  # flight v2: small support, no window cap needed
    assert v2.level == "full" and np.isfinite(v2.elevation).sum() > 300
    assert np.nanmean(np.abs(v2.elevation - z)) < 0.3


@pytest.fixture(scope="module")
def rendered_pair():
    from evalpairs import eval_pair

    return eval_pair("vertical", "default", 0, "600/300")


@pytest.mark.parametrize("preset", ["fast_v1", "thesis", "fast"])
def test_state_and_hazard_make_the_same_call(rendered_pair, preset):
    """DESIGN.md: a pixel is called safe when hazard.npy < 1, and state.npy says the same. fast_v1 maps its
    hazards on a DEM with small gaps filled, but derived its states from the unfilled one: 1815 pixels of this
    pair were unknown in state.npy and safe in hazard.npy, and `score` refused the output."""
    from protocol.pairdir import STATE_SAFE, STATE_UNKNOWN

    pair = rendered_pair
    r = run_pipeline(*pair.images, *pair.poses, pair.camera, preset=preset)
    cov = r.covered
    assert np.array_equal(r.state[cov] == STATE_SAFE, r.hazard[cov] < 1.0)
    assert np.all(r.hazard[r.state == STATE_UNKNOWN] == 1.0)
