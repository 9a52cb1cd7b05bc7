"""The shading cue read under the sun the P(safe) model was fitted under (flight_sw/shading.py).

Every pair `fast`'s P(safe) model was fitted on had a 25 deg sun. Under a higher sun the same wall
shades less, and the model read it as flatter: on the tuning library renders with a 40-60 deg sun,
undetected hazards had a median of 0.33 % and reached 1.40 % (docs/benchmarks/pipeline.md, stop 24).
"""

from __future__ import annotations

import dataclasses
import math
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
from synthetic import make_pair, plane

from flight_sw.pipeline import PRESETS, run_pipeline
from flight_sw.shading import rho_at_sun
from flight_sw.validate import FlightInputError
from protocol.codec import decode_message, encode_message
from protocol.messages import Frame, SchemaError


def _lambert_rho(tilt_deg: np.ndarray, sun_deg: float) -> np.ndarray:
    """Relative brightness of a facet tilted toward the sun, over flat ground's (Lambert)."""
    e, t = math.radians(sun_deg), np.radians(tilt_deg)
    return (np.sin(e + t) / math.sin(e) - 1.0).astype(np.float32)


@pytest.mark.parametrize("sun", [30.0, 45.0, 60.0, 80.0])
def test_a_tilt_reads_as_under_the_reference_sun(sun):
    # beyond 90 - sun the facet faces past the sun and darkens again: brightness no longer tells the tilt
    tilt = np.linspace(-20.0, min(20.0, 90.0 - sun), 81)
    got = rho_at_sun(_lambert_rho(tilt, sun), sun, 25.0)
    assert got.dtype == np.float32
    np.testing.assert_allclose(got, _lambert_rho(tilt, 25.0), atol=2e-5)


def test_a_high_sun_no_longer_hides_a_wall():
    """A 5 deg tilt under a 45 deg sun brightens by 8 %, under the wall cue's 10 %; read at 25 deg, 18 %."""
    rho45 = _lambert_rho(np.array([5.0, -5.0]), 45.0)
    assert np.all(np.abs(rho45) < 0.1)
    assert np.all(np.abs(rho_at_sun(rho45, 45.0, 25.0)) > 0.15)


def test_the_map_is_the_identity_at_the_reference_and_keeps_nan():
    rho = np.array([-0.5, -0.1, 0.0, 0.2, np.nan], np.float32)
    np.testing.assert_allclose(rho_at_sun(rho, 25.0, 25.0), rho, atol=1e-6)
    assert np.isnan(rho_at_sun(rho, 50.0, 25.0)[-1])
    # a facet darker than anything a tilt explains, or brighter than facing the sun, is clipped, not NaN
    ext = rho_at_sun(np.array([-1.0, 5.0], np.float32), 50.0, 25.0)
    assert np.all(np.isfinite(ext)) and ext[0] < -0.9 and ext[1] > 1.0
    for bad in (0.0, -3.0, 91.0, math.nan):
        with pytest.raises(ValueError, match="sun elevations"):
            rho_at_sun(rho, bad, 25.0)


@pytest.fixture(scope="module")
def flat_pair():
    return make_pair(256, 200.0, 100.0, plane(0.0), seed=41)


def _rho(pair, sun):
    cam, p1, p2, i1, i2, _ = pair
    res = run_pipeline(
        i1, i2, p1, p2, cam, preset=dataclasses.replace(PRESETS["fast"], keep_layers=True), sun_elevation_deg=sun
    )
    return res.layers["rho"], res.info["shading_sun"]


def test_the_pipeline_reads_shading_under_the_models_sun(flat_pair):
    base, info = _rho(flat_pair, None)
    assert info == {"elevation_deg": None, "read_as_deg": None}
    low, info = _rho(flat_pair, 15.0)  # below the reference: never mapped (it would weaken the cue)
    assert info == {"elevation_deg": 15.0, "read_as_deg": 15.0}
    np.testing.assert_array_equal(low, base)
    high, info = _rho(flat_pair, 50.0)
    assert info == {"elevation_deg": 50.0, "read_as_deg": PRESETS["fast"].shading_sun_ref_deg}
    ok = np.isfinite(base)
    assert ok.sum() > 1000
    np.testing.assert_allclose(high[ok], rho_at_sun(base, 50.0, 25.0)[ok], atol=1e-6)
    assert np.nanpercentile(np.abs(high), 90) > 1.5 * np.nanpercentile(np.abs(base), 90)
    nan_sun, info = _rho(flat_pair, math.nan)  # NaN = unknown, as None
    np.testing.assert_array_equal(nan_sun, base)


@pytest.mark.parametrize("bad", [-5.0, 0.0, 95.0, "high", True])
def test_a_bad_sun_is_refused(flat_pair, bad):
    cam, p1, p2, i1, i2, _ = flat_pair
    with pytest.raises(FlightInputError, match="sun_elevation_deg"):
        run_pipeline(i1, i2, p1, p2, cam, sun_elevation_deg=bad)


def _frame(**kw):
    img = np.arange(64, dtype=np.uint8).reshape(8, 8)
    return Frame(
        seq=1, capture_time_s=0.0, position_m=(0, 0, 100), R_world_to_cam=np.eye(3), altimeter_m=100.0, image=img, **kw
    )


def test_frames_carry_the_sun_and_refuse_an_impossible_one():
    back = decode_message(encode_message(_frame(sun_azimuth_deg=135.0, sun_elevation_deg=42.5)))
    assert (back.sun_azimuth_deg, back.sun_elevation_deg) == (135.0, 42.5)
    plain = decode_message(encode_message(_frame()))
    assert plain.sun_azimuth_deg is None and plain.sun_elevation_deg is None
    with pytest.raises(SchemaError, match="sun_elevation_deg"):
        encode_message(_frame(sun_elevation_deg=120.0))
    with pytest.raises(SchemaError, match="sun_azimuth_deg"):
        encode_message(_frame(sun_azimuth_deg=math.inf))


def test_the_ground_simulator_sends_the_pairs_sun():
    from ground_sim.stream import _frame_from_pair
    from protocol.pairdir import Pair, Sun

    cam, p1, p2, i1, i2, _ = make_pair(64, 200.0, 100.0, plane(0.0), seed=2)
    pair = Pair(cam, (p1, p2), (i1, i2), Sun(120.0, 33.0))
    f = _frame_from_pair(pair, 1, 7, "p0")
    assert (f.sun_azimuth_deg, f.sun_elevation_deg) == (120.0, 33.0)
    assert _frame_from_pair(Pair(cam, (p1, p2), (i1, i2)), 0, 6, "p0").sun_elevation_deg is None
