"""The DEM seen from the lower frame too (flight_sw/lowerview.py): read-back geometry, the averaged DEM,
and the P(safe) model's guard against a DEM it was not fitted on."""

from __future__ import annotations

import dataclasses
import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
from synthetic import camera_fov30

from flight_sw.lowerview import average_where_both, read_into_reference
from flight_sw.pipeline import PRESETS, _check_model_dem, run_pipeline
from flight_sw.psafe import MODEL_PATH
from flight_sw.validate import FlightInputError
from protocol.pairdir import Pose


def _tilted_pose(alt: float, x: float, pitch_deg: float) -> Pose:
    """A camera at (x, 0, alt) looking down, pitched about its x axis (an oblique approach view)."""
    c, s = math.cos(math.radians(pitch_deg)), math.sin(math.radians(pitch_deg))
    nadir = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])
    tilt = np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])
    return Pose(np.array([x, 0.0, alt]), tilt @ nadir)


def test_read_into_reference_follows_each_ray_to_the_lower_views_ground():
    """A lower view whose DEM is a tilted plane z = 0.05 X - 3: read along i1's rays (an oblique pair, rays
    started at the wrong height) it gives that plane at the point each ray meets it."""
    cam = camera_fov30(128)
    p1, p2 = _tilted_pose(300.0, -60.0, 10.0), _tilted_pose(150.0, 0.0, 5.0)
    from flight_sw.georef import backproject

    X2, Y2 = backproject(cam, p2, np.zeros((128, 128)))  # i2's ground at z = 0, then the plane's height
    z2 = np.zeros((128, 128), np.float32)
    for _ in range(30):  # each i2 pixel's ray meets the plane where z = 0.05 X - 3
        X2, Y2 = backproject(cam, p2, z2.astype(np.float64))
        z2 = (0.05 * X2 - 3.0).astype(np.float32)
    got = read_into_reference(z2, cam, p1, p2, np.full((128, 128), 20.0), passes=8)
    X1, Y1 = backproject(cam, p1, np.where(np.isfinite(got), got, 0.0))
    ok = np.isfinite(got)
    assert ok.mean() > 0.15  # the part of i1 that the lower, narrower view sees
    np.testing.assert_allclose(got[ok], 0.05 * X1[ok] - 3.0, atol=0.02)


def test_average_where_both_keeps_the_first_dems_coverage():
    z1 = np.array([[1.0, np.nan, 3.0]], np.float32)
    z2 = np.array([[2.0, 5.0, np.nan]], np.float32)
    z, both = average_where_both(z1, z2)
    np.testing.assert_array_equal(both, [[True, False, False]])
    np.testing.assert_array_equal(z, np.array([[1.5, np.nan, 3.0]], np.float32))


@pytest.mark.slow
def test_the_lower_views_dem_lowers_the_dem_error():
    """A rendered vertical 600 -> 300 m pair (tuning seed): the average of the two references' DEMs is closer
    to the truth than i1's own DEM (0.466 -> 0.362 m; docs/benchmarks/pipeline.md, stop 40), on the same pixels.
    (Not on tests/synthetic.py's pairs: their texture is noise finer than i1's pixel, which i1 cannot resolve
    and the finer reference then cannot match; the module doc's limits.)"""
    from evalpairs import eval_pair

    from ground_sim.seeds import TUNING_SEEDS

    pair = eval_pair("vertical", "default", TUNING_SEEDS[0], "600/300")
    cam, (p1, p2), (i1, i2), z = pair.camera, pair.poses, pair.images, pair.truth["elevation"]
    prm = dataclasses.replace(PRESETS["fast"], psafe_model="gaussian", refine_pose=False)
    sun = {"sun_azimuth_deg": pair.sun.azimuth_deg, "sun_elevation_deg": pair.sun.elevation_deg}
    base = run_pipeline(i1, i2, p1, p2, cam, preset=prm, **sun)
    both = run_pipeline(i1, i2, p1, p2, cam, preset=dataclasses.replace(prm, lower_view_dem=True), **sun)
    assert base.level == both.level == "full"
    lv = both.info["lower_view"]
    assert lv["complete"] and lv["averaged"] > 0.15 and "lower_dem" in both.timings
    m = base.covered & np.isfinite(base.elevation)
    assert np.array_equal(m, both.covered & np.isfinite(both.elevation))  # the same pixels have an elevation
    e_base, e_both = np.abs(base.elevation - z)[m].mean(), np.abs(both.elevation - z)[m].mean()
    assert e_both < 0.9 * e_base


def test_a_psafe_model_is_refused_with_a_dem_it_was_not_fitted_on(tmp_path):
    """The shipped trees read i1's DEM: with the lower view's DEM their P(safe) would not be calibrated, so the
    run is refused with one line; a model that records lower_view_dem in its info is taken, and refused without."""
    on = dataclasses.replace(PRESETS["fast"], lower_view_dem=True)
    with pytest.raises(FlightInputError, match="lower_view_dem"):
        _check_model_dem(on)
    _check_model_dem(PRESETS["fast"])
    doc = json.loads(Path(MODEL_PATH).read_text())
    doc["info"]["pipeline"] = {"lower_view_dem": True}
    path = tmp_path / "psafe_lv.json"
    path.write_text(json.dumps(doc))
    _check_model_dem(dataclasses.replace(on, psafe_model_path=str(path)))
    with pytest.raises(FlightInputError, match="fitted with lower_view_dem=True"):
        _check_model_dem(dataclasses.replace(PRESETS["fast"], psafe_model_path=str(path)))


@pytest.mark.slow
def test_a_pair_without_its_lower_view_is_called_as_fast_calls_it(monkeypatch, tmp_path):
    """When the second sweep does not finish (its deadline), the DEM is the first one alone, so it must be called
    with the fallback trees and budget (fast's): the map is then fast's, pixel for pixel, and the result says why."""
    from synthetic import make_pair, plane

    import flight_sw.pipeline as pl

    doc = json.loads(Path(MODEL_PATH).read_text())
    doc["info"]["pipeline"] = {"lower_view_dem": True}  # stands for trees fitted on the lower view's DEM
    # ... and other trees, prior and operating point than fast's: the fallback must call with none of them
    doc["base"] += 2.0
    doc["info"]["safe_share"], doc["info"]["call"] = 0.6, {"psafe_min": 0.9}
    path = tmp_path / "psafe_lv.json"
    path.write_text(json.dumps(doc))
    prm = dataclasses.replace(PRESETS["fast"], lower_view_dem=True, psafe_model_path=str(path), fp_budget=0.002)
    cam, p1, p2, i1, i2, _ = make_pair(512, 600.0, 300.0, plane(0.0), seed=5, spots_per_km2=2000.0)
    sun = {"sun_azimuth_deg": 135.0, "sun_elevation_deg": 25.0}
    fast = run_pipeline(i1, i2, p1, p2, cam, preset="fast", **sun)
    monkeypatch.setattr(pl, "lower_view_dem", lambda *a, **k: (None, {"complete": False}))
    lv = run_pipeline(i1, i2, p1, p2, cam, preset=prm, **sun)
    assert lv.level == fast.level == "full"
    assert "lower_view_fallback" in lv.info and lv.info["lower_view"] == {"complete": False}
    assert lv.params["psafe_model_path"] == "" and lv.params["fp_budget"] == PRESETS["fast"].fp_budget
    assert lv.params["psafe_min"] == PRESETS["fast"].psafe_min and "psafe_call" not in lv.info
    assert lv.info["psafe_safe_share"] == fast.info["psafe_safe_share"] != 0.6
    assert not lv.params["lower_view_dem"]
    np.testing.assert_array_equal(lv.state, fast.state)
    np.testing.assert_array_equal(lv.psafe, fast.psafe)
    with pytest.raises(FlightInputError, match="lower_view_fallback_model"):  # a fallback fitted on the lower view
        _check_model_dem(dataclasses.replace(prm, lower_view_fallback_model=str(path)))
    with pytest.raises(FlightInputError, match="lower_view_fallback_budget"):
        dataclasses.replace(prm, lower_view_fallback_budget=0.5).validate()


def test_a_pair_whose_fallback_has_no_model_for_its_size_keeps_fasts_wall_cue(monkeypatch, tmp_path):
    """A lower-view model fitted on 160 px and no shipped model for that size: without its lower view the pair
    drops to the Gaussian rule, which needs the wall cue the calibrated path had left out; ~500 crater-wall
    pixels a pair were called safe that `fast` calls unsafe (review of stop 63)."""
    from synthetic import crater, make_pair

    import flight_sw.pipeline as pl

    doc = json.loads(Path(MODEL_PATH).read_text())
    doc["info"]["pipeline"] = {"lower_view_dem": True}
    doc["info"]["image_px"] = [[160, 160]]
    path = tmp_path / "psafe_lv160.json"
    path.write_text(json.dumps(doc))
    prm = dataclasses.replace(
        PRESETS["fast"],
        lower_view_dem=True,
        psafe_model_path=str(path),
        lower_view_fallback_budget=PRESETS["fast"].fp_budget,
    )
    cam, p1, p2, i1, i2, _ = make_pair(160, 150.0, 75.0, crater(20.0, 4.0), seed=5)
    sun = {"sun_azimuth_deg": 135.0, "sun_elevation_deg": 25.0}
    fast = run_pipeline(i1, i2, p1, p2, cam, preset="fast", **sun)
    monkeypatch.setattr(pl, "lower_view_dem", lambda *a, **k: (None, {"complete": False}))
    lv = run_pipeline(i1, i2, p1, p2, cam, preset=prm, **sun)
    assert "lower_view_fallback" in lv.info and "psafe_fallback" in lv.info and "psafe_fallback" in fast.info
    assert (fast.state == 1).sum() > 1000  # the wall cue's unsafe ground, to keep
    np.testing.assert_array_equal(lv.state, fast.state)
