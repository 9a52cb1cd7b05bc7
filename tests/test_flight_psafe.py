"""Calibrated P(safe) (flight_sw/psafe.py) and the FP-budget call: the model is calibrated on a
tuning scene, the call respects its budget, and on a rendered held-out pair the undetected-hazard
share stays under 1 % while more truly safe ground is called safe than with the Gaussian model.
"""

from __future__ import annotations

import dataclasses
import json
from importlib import resources
from pathlib import Path

import numpy as np
import pytest
from evalpairs import eval_pair

from flight_sw.evidence import classify_calibrated
from flight_sw.pipeline import PRESETS, run_pipeline
from flight_sw.psafe import (
    MODEL_PATH,
    SHIPPED_MODELS,
    PsafeModel,
    TreeModel,
    budget_rule,
    load_model,
    model_call,
    model_for_image,
)
from flight_sw.validate import FlightInputError
from ground_sim.seeds import HELD_OUT_SEEDS, TUNING_SEEDS
from protocol.pairdir import STATE_SAFE, STATE_UNKNOWN, STATE_UNSAFE, read_pair


def _run(pair, sun: bool = True, **over):
    """``fast`` (with ``over``) on the pair, told its sun as HIL frames tell it (``sun=False``: not told)."""
    prm = dataclasses.replace(PRESETS["fast"], **over)
    told = {"sun_azimuth_deg": pair.sun.azimuth_deg, "sun_elevation_deg": pair.sun.elevation_deg} if sun else {}
    return run_pipeline(pair.images[0], pair.images[-1], pair.poses[0], pair.poses[-1], pair.camera, preset=prm, **told)


@pytest.mark.parametrize(
    "name, px", [("psafe_model.json", 512), ("psafe_model_256.json", 256), ("psafe_model_128.json", 128)]
)
def test_model_is_package_data_small_and_fitted_on_tuning_seeds_only(name, px):
    text = resources.files("flight_sw").joinpath(name).read_text()
    assert len(text) < 150_000
    m = TreeModel.from_json(json.loads(text))
    assert m.fitted_on and set(m.fitted_on) <= set(TUNING_SEEDS)
    assert not set(m.fitted_on) & set(HELD_OUT_SEEDS)
    assert m.info["image_px"] == [[px, px]] and 0.5 < m.info["safe_share"] < 1.0
    shipped, path = model_for_image(None, (px, px))
    assert Path(path).name == name and isinstance(shipped, TreeModel) and shipped.to_json() == m.to_json()
    bad = dict(json.loads(text), format="other")
    with pytest.raises(ValueError, match="psafe-trees"):
        TreeModel.from_json(bad)
    with pytest.raises(ValueError, match="psafe-gam"):
        PsafeModel.from_json(bad)


def test_budget_rule_takes_the_most_probable_points_within_the_budget():
    rng = np.random.default_rng(5)
    p = rng.uniform(0.5, 1.0, 20_000).astype(np.float32)
    p[:100] = np.nan  # never called
    for budget in (0.0, 0.001, 0.01, 0.05):
        call = budget_rule(p, budget, n=p.size)
        assert float(np.sum(1.0 - p[call])) <= budget * p.size + 1e-3  # expected FP within the budget
        if call.any():  # the called points are the most probable ones, and close to the budget
            assert np.nanmin(p[call]) >= np.nanmax(np.where(call, np.nan, p)) - 1e-4
            assert float(np.sum(1.0 - p[call])) > 0.95 * budget * p.size
    assert not budget_rule(p, 0.05, p_min=0.99, n=p.size)[p < 0.99].any()
    assert not budget_rule(p, 0.05, n=p.size)[:100].any()


class _ConstModel:
    """A stand-in P(safe) model: the same probability at every covered point."""

    def __init__(self, p: float) -> None:
        self.p = p

    def predict(self, feats: dict[str, np.ndarray], mask: np.ndarray) -> np.ndarray:
        return np.full(int(np.count_nonzero(mask)), self.p, np.float32)


def test_slope_cap_judged_against_its_uncertainty():
    # a (slope / limit) and u (its uncertainty / limit) per point; the model vouches for all of them
    a = np.array([[0.2, 0.7, 0.7, 0.95, np.nan]], np.float32)
    u = np.array([[0.3, 0.05, 0.2, 0.01, 0.1]], np.float32)
    feats = {"a": a, "u": u, "rough": np.zeros_like(a)}
    cov = np.ones(a.shape, bool)
    cues = np.zeros(a.shape, bool)
    model = _ConstModel(0.999)
    hard = classify_calibrated(model, feats, cues, cov, 0.01, 0.97, a_max=0.4)  # type: ignore[arg-type]
    soft = classify_calibrated(model, feats, cues, cov, 0.01, 0.97, a_max=0.4, a_sigma_k=2.5)  # type: ignore[arg-type]
    # the hard cap calls only the gentle slope; judged against sigma, 0.7 +- 0.05 and 0.95 +- 0.01 are
    # below the limit by 2.5 sigma, 0.7 +- 0.2 is not; a point without an elevation is never called
    assert (hard.state[0] == STATE_SAFE).tolist() == [True, False, False, False, False]
    assert (soft.state[0] == STATE_SAFE).tolist() == [True, True, False, True, False]
    with pytest.raises(FlightInputError, match="call_slope_sigma_k"):
        dataclasses.replace(PRESETS["fast"], call_slope_sigma_k=-1.0).validate()


def test_a_point_without_a_slope_is_unknown_unless_a_cue_condemns_it():
    """DESIGN.md: unknown = not enough evidence. With no elevation the trees' P(safe) is a context prior
    (0.08-0.13 on an image-only pair): below p_unsafe it must not read as a hazard. A hard cue
    (dark shadow) is unsafe with or without an elevation; a measured slope with a low P(safe) is unsafe."""
    a = np.array([[np.nan, np.nan, 0.2, 0.2]], np.float32)
    feats = {"a": a, "u": np.full_like(a, 0.1), "rough": np.zeros_like(a)}
    cues = np.array([[False, True, False, True]])
    ev = classify_calibrated(_ConstModel(0.09), feats, cues, np.ones(a.shape, bool), 0.01, 0.97)  # type: ignore[arg-type]
    assert ev.state[0].tolist() == [STATE_UNKNOWN, STATE_UNSAFE, STATE_UNSAFE, STATE_UNSAFE]
    assert ev.psafe[0, 1] == 0.0 and ev.psafe[0, 3] == 0.0  # a cue's P(safe) is 0 whatever the model says
    # with p_min 0 (Params.validate allows it) a budget large enough took a cue's P(safe) 0 and called it safe
    ev = classify_calibrated(_ConstModel(0.9999), feats, cues, np.ones(a.shape, bool), 0.5, 0.0)  # type: ignore[arg-type]
    assert ev.state[0].tolist() == [STATE_UNKNOWN, STATE_UNSAFE, STATE_SAFE, STATE_UNSAFE]
    assert ev.hazard[0, 1] == 1.0 and ev.hazard[0, 3] == 1.0


@pytest.mark.slow
def test_psafe_is_calibrated_on_a_tuning_scene():
    """Predicted P(safe) against the observed safe share, tuning seed 0 (the model was fitted on it).

    Over-confidence is what would let hazards through, so it is held tight in every band. The trees of
    stop 26 (the shading slope; the library's tuning renders in the fit) are under-confident on this gentle
    `default` pair below 0.8: predicted 0.26, observed 0.37 (0.25 / 0.37 fitted on the eval pairs alone;
    stop 25's trees were within 0.04 overall and 0.08 per band). That costs calls, not safety.
    """
    pair = eval_pair("vertical", "default", TUNING_SEEDS[0], "400/200")
    res = _run(pair)
    cov = res.covered & np.isfinite(pair.truth["hazard"])
    p = res.psafe[cov].astype(np.float64)
    safe = pair.truth["hazard"][cov] < 1.0
    assert -0.06 < p.mean() - safe.mean() < 0.02  # overall
    for lo, hi in ((0.0, 0.8), (0.8, 0.95), (0.95, 1.01)):  # per band, where it is populated
        m = (p >= lo) & (p < hi)
        if m.sum() > 2000:
            assert -0.12 < p[m].mean() - safe[m].mean() < 0.03, (lo, hi, p[m].mean(), safe[m].mean())
    hi = p >= 0.97
    assert hi.mean() > 0.3 and safe[hi].mean() > 0.97


def _fp_tp(pair, sun: bool = True, res=None, **over) -> tuple[float, float]:
    """(FP, TP) in % of the covered pixels: undetected hazards and truly safe ground called safe (``res``: the
    result of ``_run(pair, sun, **over)`` where the caller has it already)."""
    truth = pair.truth["hazard"]
    res = _run(pair, sun, **over) if res is None else res
    cov = res.covered & np.isfinite(truth)
    called = (res.state == STATE_SAFE) & cov
    n = cov.sum()
    return 100.0 * float((called & (truth >= 1.0)).sum()) / n, 100.0 * float((called & (truth < 1.0)).sum()) / n


@pytest.mark.slow
def test_fp_budget_holds_on_a_held_out_pair_and_calls_more_safe_ground():
    pair = eval_pair("approach", "approach", HELD_OUT_SEEDS[0], "600/300")
    fp, tp = _fp_tp(pair)
    tp_gauss = _fp_tp(pair, psafe_model="gaussian")[1]
    assert fp <= 1.0
    # the Gaussian model leaves most of this pair unknown (tiled render: TP 18.9 %; calibrated 63.4 %; on the
    # capped renders before 2026-11-25: 1.7 % and 20.7 %)
    assert tp > 2.0 * tp_gauss and tp > tp_gauss + 15.0


@pytest.mark.slow
def test_fp_budget_holds_on_the_thesis_scene():
    """The product's default scene (more hazardous than `default`): the model fitted on `default` scenes alone
    gave FP 1.54 % on this held-out pair; refitted on both scene families 0.51 %, with 65 % of the covered
    ground called truly safe."""
    pair = eval_pair("approach", "thesis", HELD_OUT_SEEDS[1], "250/125")
    fp, tp = _fp_tp(pair)
    assert fp <= 1.0 and tp > 50.0


def test_other_image_sizes_fall_back_to_the_gaussian_rule():
    """The models are fitted on 512, 256 and 128 px images; on another camera their calibration does not hold
    (the 512 px trees on a 128 px camera: FP 1.6-5 %), so the Gaussian rule calls it, and the result says so."""
    import sys

    sys.path.insert(0, str(Path(__file__).parent))
    from synthetic import make_pair, plane

    cam, p1, p2, i1, i2, _ = make_pair(160, 200.0, 100.0, plane(-2.0), seed=3)
    res = run_pipeline(i1, i2, p1, p2, cam, preset="fast")
    assert "160x160" in res.info["psafe_fallback"] and "psafe_safe_share" not in res.info
    assert load_model().fits_image((512, 512)) and not load_model().fits_image((128, 128))
    assert model_for_image(None, (160, 160)) is None and model_for_image(str(MODEL_PATH), (256, 256)) is None
    assert Path(model_for_image(None, (128, 128))[1]).name == "psafe_model_128.json"
    safe = res.state == STATE_SAFE
    assert np.all(res.psafe[safe] >= PRESETS["fast"].psafe_min)


@pytest.mark.slow
def test_a_256_px_camera_is_called_by_its_own_model_within_the_fp_limit():
    """Held-out 256 px pairs: the trees fitted on 256 px tuning renders call them with their own operating point
    (the 512 px trees' calibration does not hold there). The Gaussian rule that stood in before put a thesis
    vertical 150/75 pair's FP at 1.97 %, over the 1 % limit, and left an approach 600/300 pair almost all
    unknown (docs/benchmarks/pipeline.md, "A P(safe) model for 256 px cameras")."""
    low = eval_pair("vertical", "thesis", HELD_OUT_SEEDS[1], "150/75", image_px=256)
    res = _run(low, True)
    assert "psafe_fallback" not in res.info and res.info["psafe_call"] == model_call(load_model(str(SHIPPED_MODELS[1])))
    assert res.info["psafe_safe_share"] == load_model(str(SHIPPED_MODELS[1])).info["safe_share"]
    assert _fp_tp(low, psafe_model="gaussian")[0] > 1.0 and _fp_tp(low, res=res)[0] <= 1.0
    high = eval_pair("approach", "approach", HELD_OUT_SEEDS[0], "600/300", image_px=256)
    fp, tp = _fp_tp(high)
    assert fp <= 1.0 and tp > _fp_tp(high, psafe_model="gaussian")[1] + 15.0


@pytest.mark.slow
def test_the_shading_slope_calls_more_safe_ground_within_the_fp_limit():
    """Held-out thesis-scene vertical pair at 300 m (a 3 m footprint is ~5 px): told the sun, fast reads the
    footprints' sun-ward tilt from the shading (photoclinometry.py) and calls more truly safe ground safe;
    not told, it falls back to the DEM's slope (the trees were fitted with a_pc blanked on a quarter of the
    points), and neither call lets more than 1 % of the pixels through as undetected hazards."""
    pair = eval_pair("vertical", "thesis", HELD_OUT_SEEDS[0], "600/300")
    fp_sun, tp_sun = _fp_tp(pair)
    fp_blind, tp_blind = _fp_tp(pair, sun=False)
    assert fp_sun <= 1.0 and fp_blind <= 1.0
    # TP 15.1 against 12.1 % (stop 27, FP budget 0.2 %; 18.8 against 11.5 % at stop 26's 0.3 %)
    assert tp_sun > tp_blind + 2.0, (tp_sun, tp_blind)


@pytest.fixture(scope="module")
def tuning_run():
    """The tuning pair vertical 600/300 and ``fast``'s run on it, told its sun: what the grid tests read (only)."""
    pair = eval_pair("vertical", "default", TUNING_SEEDS[0], "600/300")
    return pair, _run(pair)


@pytest.mark.slow
def test_the_grid_calls_what_the_pixels_call(tuning_run):
    """The world grid (what sites, the fused map and the HIL Result read) takes the pixels' call: read back at
    each pixel's true ground point it calls as much truly safe ground safe as the pixel map, and lets no more
    hazards through. A cell safe only where every pixel its bilinear read touches was called safe
    (``grid_call_share=0.999``, before stop 38) eroded the fragmented safe ground of this tuning pair by half a
    pixel all round: the grid called 20.7 % of the covered pixels truly safe, the pixel map 24.9 % (now 25.0
    against 24.9 %; FP 0.009 against 0.016 %)."""
    from protocol.pairdir import STATE_OUTSIDE
    from studies.multiframe import pixel_world, sample_cells

    pair, run = tuning_run
    truth = pair.truth["hazard"]
    xy = pixel_world(pair)

    def fp_tp(res) -> tuple[tuple[float, float], tuple[float, float]]:
        cov = res.covered & np.isfinite(truth)
        st = sample_cells(res.grid, xy[0], xy[1], res.grid.state.astype(np.float32), float(STATE_OUTSIDE))
        out = []
        for called in (res.state == STATE_SAFE, st == STATE_SAFE):
            c = called & cov
            n = cov.sum()
            out.append((100.0 * float((c & (truth >= 1.0)).sum()) / n, 100.0 * float((c & (truth < 1.0)).sum()) / n))
        return out[0], out[1]

    (fp_px, tp_px), (fp_g, tp_g) = fp_tp(run)
    assert tp_px > 20.0 and fp_px <= 1.0
    assert abs(tp_g - tp_px) < 1.0 and fp_g <= fp_px + 0.05, (tp_px, tp_g, fp_px, fp_g)
    (_, tp_px0), (_, tp_g0) = fp_tp(_run(pair, grid_call_share=0.999))
    assert tp_g0 < tp_px0 - 3.0  # the erosion this rule replaced


@pytest.mark.slow
def test_the_grid_reports_the_dems_gap_fills_as_the_pixel_map_does(tuning_run):
    """The DEM carries its elevation up to 1 m into dark shadow (``dark_fill_m``); the pixel map reports those
    fills, and now so does the grid (``HazardGrid.dem``, what a Result sends and the fused map reports), read
    back at each pixel's true ground point: its DEM coverage of the covered pixels is within 1 point of the
    pixel map's (tuning pair vertical 600/300: 99.2 against 99.3 %; 97.8 without the fills). What the hazard
    stage and the sites read is unchanged: matched elevations only, and a match beats a fill beside it."""
    from studies.multiframe import pixel_world, sample_cells

    pair, on = tuning_run
    xy = pixel_world(pair)
    off = _run(pair, grid_dem_filled=False)
    cov = on.covered & np.isfinite(pair.truth["hazard"])

    def coverage(g, layer) -> float:
        return 100.0 * float(np.isfinite(sample_cells(g, xy[0], xy[1], layer, np.nan))[cov].mean())

    pixel = 100.0 * float(np.isfinite(on.elevation)[cov].mean())
    assert on.grid.dem is not None and off.grid.dem is None
    reported, matched = coverage(on.grid, on.grid.reported_elevation), coverage(off.grid, off.grid.elevation)
    assert abs(reported - pixel) < 1.0 and matched < pixel - 1.0, (pixel, reported, matched)
    for name in ("elevation", "state", "psafe", "hazard"):  # the evidence: bit-identical
        assert np.array_equal(getattr(on.grid, name), getattr(off.grid, name), equal_nan=True), name
    assert on.sites == off.sites
    filled = np.isfinite(on.grid.dem) & ~np.isfinite(on.grid.elevation)
    assert filled.any() and np.array_equal(on.grid.dem[~filled], on.grid.elevation[~filled], equal_nan=True)


def test_a_models_own_operating_point_is_used_and_said(tmp_path):
    """A model that records the operating point its CV chose (info.call: the 256 px model's) is called with it,
    and the result says so; ``psafe_call="params"`` keeps the preset's, and an out-of-bounds call is refused."""
    import sys

    sys.path.insert(0, str(Path(__file__).parent))
    from synthetic import make_pair, plane

    doc = json.loads(Path(MODEL_PATH).read_text())
    doc["info"]["call"] = {"psafe_min": 0.975, "fp_budget": 0.0015}
    path = tmp_path / "psafe_call.json"
    path.write_text(json.dumps(doc))
    cam, p1, p2, i1, i2, _ = make_pair(512, 600.0, 300.0, plane(-2.0), seed=3)
    own = run_pipeline(i1, i2, p1, p2, cam, preset=dataclasses.replace(PRESETS["fast"], psafe_model_path=str(path)))
    assert own.info["psafe_call"] == {"psafe_min": 0.975, "fp_budget": 0.0015}
    assert own.params["psafe_min"] == 0.975 and own.params["fp_budget"] == 0.0015
    safe = own.state == STATE_SAFE
    assert safe.any() and np.all(own.psafe[safe] >= 0.975)
    prm = dataclasses.replace(PRESETS["fast"], psafe_model_path=str(path), psafe_call="params")
    theirs = run_pipeline(i1, i2, p1, p2, cam, preset=prm)
    assert "psafe_call" not in theirs.info and theirs.params["psafe_min"] == PRESETS["fast"].psafe_min
    assert (theirs.state == STATE_SAFE).sum() > safe.sum()  # the preset's lower floor and larger budget call more
    for bad in ({"fp_budget": 0.5}, {"psafe_min": 1.0}, {"call_slope_max": 0.0}, {"p_min": 0.9}):
        doc["info"]["call"] = bad
        with pytest.raises(ValueError, match=r"info\.call"):
            model_call(TreeModel.from_json(doc))
    with pytest.raises(FlightInputError, match="psafe_call"):
        dataclasses.replace(PRESETS["fast"], psafe_call="mine").validate()


def test_a_footprint_finer_than_the_models_fitted_scale_is_called_unknown_and_offers_no_site(tmp_path):
    """A 128 px camera at 5000 m sees the 3 m footprint as 0.14 px, below the 0.19 px its trees were fitted down to:
    they called 17 points safe at P >= 0.99, one a hazard, and the top site sat on it (review of stop 64). Below the
    fitted scale nothing is called safe, and the no-site reason says why; at 1000 m (0.72 px) the call is as before."""
    from hilkit import scaled_camera

    from ground_sim.descent import render_scenario

    render_scenario(
        "vertical", tmp_path, frames=[[5000.0, 2500.0], [1000.0, 500.0]], camera=scaled_camera(128), progress=False
    )
    high, low = (_run(read_pair(tmp_path / d)) for d in ("5000_2500", "1000_500"))
    assert high.info["footprint_px"] < 0.19 < low.info["footprint_px"]
    assert not (high.state == STATE_SAFE).any() and not high.sites
    assert "below the 0.19 px the P(safe) model was fitted down to" in high.info["no_site_reason"]
    assert (high.state == STATE_UNKNOWN).any() and np.all(high.hazard[high.state == STATE_UNKNOWN] == 1.0)
    # and no P(safe) above the model's prior, which fusion would read as evidence for "safe"
    prior = load_model(SHIPPED_MODELS[2]).info["safe_share"]
    assert np.nanmax(high.psafe) <= prior + 1e-6 and np.nanmax(high.grid.psafe) <= prior + 1e-6
    assert np.array_equal(np.isnan(high.psafe), ~high.covered)  # NaN outside, as ever
    assert (low.state == STATE_SAFE).any() and "psafe_beyond_scale" not in low.info


def test_below_model_scale_turns_safe_calls_unknown_caps_psafe_and_keeps_the_rest():
    """The evidence stage's footprint-scale guard on its own: safe -> unknown with hazard 1, P(safe) capped at the
    prior, unsafe and uncovered (NaN) points unchanged; at or above the fitted scale nothing changes."""
    from flight_sw.evidence import Evidence, below_model_scale

    state = np.array([[STATE_SAFE, STATE_UNSAFE, STATE_UNKNOWN]], np.uint8)
    ev = Evidence(state, np.array([[0.99, 0.0, np.nan]], np.float32), np.array([[0.1, 1.0, np.nan]], np.float32))
    assert below_model_scale(ev, 0.19, 0.19, 0.6) is ev
    out = below_model_scale(ev, 0.14, 0.19, 0.6)
    assert out.state.tolist() == [[STATE_UNKNOWN, STATE_UNSAFE, STATE_UNKNOWN]]
    assert np.allclose(out.psafe[0, :2], [0.6, 0.0]) and np.isnan(out.psafe[0, 2])
    assert out.hazard[0, :2].tolist() == [1.0, 1.0] and np.isnan(out.hazard[0, 2])
