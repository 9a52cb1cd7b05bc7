"""The DEM carried into dark shadow (issue 9: a dense DEM whose sigma grows where texture vanishes).

Semi-global aggregation gives every pixel of the cost volume an elevation, even one whose own cost is
flat; ``dense.dem_from_slab`` keeps it for ignored (dark) pixels within ``dark_fill_m`` of a match, with
the sigma of ``dense.gap_fill_sigma``, and the hazard stage still reads the matches only.
"""

from __future__ import annotations

import dataclasses
import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from synthetic import make_pair, roof

from flight_sw.dense import gap_fill_sigma
from flight_sw.pipeline import PRESETS, run_pipeline
from protocol.pairdir import STATE_SAFE


def test_the_fill_sigma_grows_from_the_nearest_match():
    measured = np.zeros((9, 40), bool)
    measured[:, :5] = True
    measured[:, 35:] = True
    sigma = np.where(np.arange(40) < 20, 0.1, 0.3).astype(np.float32)[None, :].repeat(9, 0)
    sig, within = gap_fill_sigma(sigma, measured, gsd_m=0.5, slope=0.6, max_m=2.0)
    row = sig[4]
    for k in range(1, 10):  # k px right of the left match (sigma 0.1), k px left of the right one (0.3)
        assert math.isclose(row[4 + k], math.hypot(0.1, 0.6 * 0.5 * k), rel_tol=1e-5)
        assert math.isclose(row[35 - k], math.hypot(0.3, 0.6 * 0.5 * k), rel_tol=1e-5)
    assert within[4, 5:9].all() and not within[4, 10:30].any() and within[4, 31:35].all()
    assert np.array_equal(sig[measured], sigma[measured])  # a match keeps its own sigma
    none, nowhere = gap_fill_sigma(sigma, np.zeros_like(measured), 0.5, 0.6, 2.0)
    assert np.isnan(none).all() and not nowhere.any()


def test_dark_ground_near_a_match_gets_an_elevation_but_no_safe_call():
    cam, p1, p2, i1, i2, z = make_pair(256, 100.0, 50.0, roof(6.0), seed=43)
    yy, xx = np.mgrid[:256, :256]
    dark = (yy - 150) ** 2 + (xx - 100) ** 2 < 14**2  # a shadow: nothing to match, nothing lit
    i1 = np.where(dark, 2, i1).astype(i1.dtype)
    sun = {"sun_azimuth_deg": 135.0, "sun_elevation_deg": 25.0}
    fill = run_pipeline(i1, i2, p1, p2, cam, preset="fast", **sun)
    none = run_pipeline(i1, i2, p1, p2, cam, preset=dataclasses.replace(PRESETS["fast"], dark_fill_m=0.0), **sun)
    assert not np.isfinite(none.elevation[dark]).any()  # the matcher leaves dark ground blank
    got = dark & np.isfinite(fill.elevation)
    gsd = 50.0 / cam.fx * 2  # i1 at 100 m
    # the shadow's rim, within 1 m of lit ground, is filled; its centre, 14 px = 2.9 m in, is not
    assert got.sum() > 0.3 * dark.sum() and not got[150, 100]
    dist = np.hypot(yy - 150, xx - 100)
    assert (14 - dist[got]).max() * gsd <= 1.0 + 2 * gsd
    err = np.abs(fill.elevation - z)[got]
    assert np.median(err) < 0.3 and np.mean(err <= 3 * fill.sigma[got]) > 0.85  # sigma covers the error
    assert np.median(fill.sigma[got]) > 2 * np.median(fill.sigma[~dark & np.isfinite(fill.elevation)])
    # the matched pixels and the whole hazard call are those of the DEM without the fill
    lit = np.isfinite(none.elevation)
    assert np.array_equal(fill.elevation[lit], none.elevation[lit])
    for a, b in ((fill.state, none.state), (fill.hazard, none.hazard), (fill.psafe, none.psafe)):
        assert np.array_equal(a, b, equal_nan=True)
    assert not np.any(fill.state[got] == STATE_SAFE)
    assert fill.valid_fraction > none.valid_fraction and fill.info["dense"]["filled"] > 0
    # the outputs say which elevations are fills: exactly those the DEM without fills lacks
    assert fill.filled is not None and none.filled is not None and not none.filled.any()
    assert np.array_equal(fill.filled, np.isfinite(fill.elevation) & ~lit)
    cov = fill.covered
    assert math.isclose(fill.info["dem_filled_fraction"], (fill.filled & cov).sum() / cov.sum(), rel_tol=1e-6)
    assert none.info["dem_filled_fraction"] == 0.0
    # ... and so does the world grid a Result is built from, and the Result itself
    g = fill.grid
    assert g.filled.any() and not none.grid.filled.any()
    assert np.isfinite(g.reported_elevation[g.filled]).all() and not np.isfinite(g.elevation[g.filled]).any()
    _result_round_trip(g)


def _result_round_trip(g) -> None:
    from protocol.codec import decode_message, encode_message
    from protocol.grids import filled_to_wire
    from protocol.messages import Result

    for step in (1, 2, 3):
        wire = filled_to_wire(g.filled, step)
        rows, cols = g.filled.shape
        assert wire.shape == (-(-rows // step), -(-cols // step))
        for i, j in zip(*np.nonzero(g.filled)):  # a block with any fill is flagged
            assert wire[i // step, j // step] == 1
        for i, j in zip(*np.nonzero(wire == 0)):
            assert not g.filled[i * step : i * step + step, j * step : j * step + step].any()
    from protocol.grids import elevation_to_wire

    z, off = elevation_to_wire(g.reported_elevation, 2)
    msg = Result(
        frame_seqs=(0, 1),
        state_grid=np.asarray(g.state, np.uint8),
        psafe_grid=np.zeros(g.state.shape, np.uint8),
        elevation_grid=z,
        grid_origin_xy=g.origin_xy,
        grid_cell_m=g.cell_m,
        elevation_step=2,
        elevation_offset_m=off,
        elevation_filled=filled_to_wire(g.filled, 2),
    ).validated()
    back = decode_message(encode_message(msg))
    assert np.array_equal(back.elevation_filled, filled_to_wire(g.filled, 2))
