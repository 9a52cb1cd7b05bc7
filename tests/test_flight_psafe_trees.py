"""The boosted-tree P(safe) model (flight_sw.psafe.TreeModel): exported trees score what scikit-learn
scores, the compiled kernel equals the numpy reference, and a malformed model is refused."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

from flight_sw.psafe import TreeModel, load_model, tree_kernel

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
FEATS = ("a", "u", "rough", "rho", "arho", "nbad", "nbad_w", "nwall", "nwall_w", "amean", "nknown", "scale", "gbad")


def _features(n: int, seed: int) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Synthetic features with NaNs (no elevation, no shading) and a label that depends on interactions."""
    rng = np.random.default_rng(seed)
    f = {k: rng.uniform(0, 2, n).astype(np.float32) for k in FEATS}
    f["a"][rng.random(n) < 0.1] = np.nan
    f["rho"][rng.random(n) < 0.05] = np.nan
    logit = 3.0 - 2.5 * np.nan_to_num(f["a"], nan=1.0) - 2.0 * f["rough"] * (f["nwall"] > 1) + 0.5 * f["scale"]
    y = rng.random(n) < 1.0 / (1.0 + np.exp(-logit))
    return f, y


@pytest.fixture(scope="module")
def fitted():
    pytest.importorskip("sklearn", reason="bench/fit_psafe.py's trees need scikit-learn (make installs it)")
    from fit_psafe import fit_trees

    f, y = _features(20_000, 1)
    m = fit_trees(f, y, [0, 1], {"iters": 25, "leaves": 9, "lr": 0.2}, {"image_px": [[512, 512]]})
    return m, f, y


def test_exported_trees_score_what_sklearn_scores(fitted):
    from sklearn.ensemble import HistGradientBoostingClassifier

    m, f, y = fitted
    X = np.stack([f[k] for k in FEATS], axis=1)
    clf = HistGradientBoostingClassifier(
        max_iter=25, max_leaf_nodes=9, learning_rate=0.2, l2_regularization=1.0, early_stopping=False,
        monotonic_cst=[-1 if k in ("a", "rough", "nbad", "nbad_w") else 0 for k in FEATS], random_state=0,
    ).fit(X, y)  # fmt: skip
    g, _ = _features(5_000, 2)
    Xg = np.stack([g[k] for k in FEATS], axis=1)
    assert np.allclose(m.logit(g), clf.decision_function(Xg), atol=1e-4)
    assert np.allclose(m.predict(g), clf.predict_proba(Xg)[:, 1], atol=1e-5)
    # and it learned something: held-out log-loss well below the prior's
    p = m.predict(g)
    _, yg = _features(5_000, 2)
    ll = -np.mean(np.where(yg, np.log(p), np.log1p(-p)))
    q = yg.mean()
    assert ll < 0.8 * -(q * np.log(q) + (1 - q) * np.log(1 - q))


def test_kernel_equals_numpy_reference_and_json_round_trips(fitted, tmp_path):
    m, _, _ = fitted
    g, _ = _features(7_000, 3)
    mask = np.ones(7_000, bool)
    mask[::3] = False
    assert tree_kernel() is not None, "the install builds flight_sw/_treesc.c"
    assert np.array_equal(m.logit(g, mask), m.logit(g, mask, use_kernel=False))
    path = tmp_path / "m.json"
    path.write_text(json.dumps(m.to_json()))
    m2 = load_model(str(path))
    assert isinstance(m2, TreeModel) and np.array_equal(m2.logit(g), m.logit(g))
    assert m2.fitted_on == (0, 1) and m2.fits_image((512, 512)) and not m2.fits_image((128, 128))


def test_malformed_trees_are_refused(fitted):
    m, _, _ = fitted
    doc = m.to_json()
    split = next(i for i, f in enumerate(doc["feature"]) if f >= 0)
    for key, value in (
        ("left", split),  # a child that is its own parent: the C loop would never end
        ("right", len(doc["feature"])),  # outside the model
        ("feature", len(FEATS)),  # an unknown feature
    ):
        bad = json.loads(json.dumps(doc))
        bad[key][split] = value
        with pytest.raises(ValueError, match="psafe trees"):
            TreeModel.from_json(bad)
    with pytest.raises(ValueError, match="psafe-trees"):
        TreeModel.from_json(dict(doc, format="psafe-gam/1"))


def test_eval_cache_of_another_raster_is_refused(tmp_path):
    """bench/eval_flight.py names a case's renders by raster (``_tiles``, ``_cells<N>``: studies.evaluate's
    tag) and refuses a pair of another raster found under its name (an untagged tiled cache of old)."""
    import json

    from eval_flight import cached_raster, case_key, render_case
    from synthetic import make_pair, plane

    from ground_sim.render import RENDER_VERSION
    from protocol.pairdir import Pair, write_pair

    assert case_key("approach", 0) == "approach_s0_tiles"
    assert case_key("approach", 0, raster="view") == "approach_s0"
    assert case_key("approach", 0, 20_000, "view") == "approach_s0_cells20000"
    d = tmp_path / "approach_s0_tiles" / "500_250"
    # a whole pair (a small synthetic one: a cache hit reads its files' structure, not what they show), from before
    # pairs recorded their render fingerprints (trusted here), of this renderer version (another one would be
    # redrawn, not refused: ground_sim.render_cache)
    cam, p1, p2, i1, i2, _ = make_pair(64, 500.0, 250.0, plane(0.0), seed=1)
    write_pair(d, Pair(cam, (p1, p2), (i1, i2)))
    doc = json.loads((d / "pair.json").read_text())
    views = [{"raster_cell_over_target": 2.2}, {"raster_cell_over_target": 2.6}]
    (d / "pair.json").write_text(json.dumps({**doc, "render": views, "render_version": RENDER_VERSION}))
    assert cached_raster(d) == "view"
    with pytest.raises(SystemExit, match="raster=view renders, not tiles"):
        render_case("approach", 0, tmp_path, [250])
    tiled = [dict(v, raster_tiles=4) for v in views]
    (d / "pair.json").write_text(json.dumps({**doc, "render": tiled, "render_version": RENDER_VERSION}))
    assert cached_raster(d) == "tiles"
    (e,) = render_case("approach", 0, tmp_path, [250])
    assert e["pair_dir"] == str(d) and json.loads((d / "pair.json").read_text())["render"] == tiled  # reused


def test_library_caches_are_scored_per_scene_and_fitted_on_tuning_seeds_only(tmp_path):
    """bench/eval_flight.py --library scores every pair of a landing render cache of its raster, one row per
    scene, counting the pairs over 1 % FP; bench/fit_psafe.py --library refuses a held-out scene seed."""
    from eval_flight import library_pairs, library_table
    from fit_psafe import load_library

    def pair(name: str, scene: str, seed: int, tiles: bool) -> None:
        d = tmp_path / name
        d.mkdir()
        views = [{"raster_tiles": 4} if tiles else {"raster_cell_over_target": 2.0}] * 2
        meta = {"scene": scene, "scenario": "vertical", "scene_seed": seed, "altitude_m": 200.0, "render": views}
        (d / "pair.json").write_text(json.dumps(meta))

    pair("a_tiles", "mare", 1003, True)
    pair("b_tiles", "highland", 1004, True)
    pair("c", "mare", 1003, False)  # the capped render of the same landing: another raster
    got = library_pairs(tmp_path)
    assert [(e["case"], e["seed"], e["altitude_m"]) for e in got] == [("mare", 1003, 200), ("highland", 1004, 200)]
    assert [e["case"] for e in library_pairs(tmp_path, "view")] == ["mare"]
    rows = [
        {**got[0], "fp": 1.4, "cdi": 60.0, "valid": 95.0, "top_safe": 100.0},
        {**got[1], "fp": 0.2, "cdi": 50.0, "valid": 80.0, "top_safe": float("nan")},
    ]
    lines = library_table(rows, "t").splitlines()
    assert "| mare | 1 | 1.40 | 1 |" in "\n".join(lines)
    (total,) = [ln for ln in lines if ln.startswith("| all |")]
    assert total == "| all | 2 | 1.40 | 1 | 0.80 | 55.0 / 50.0 | 80.0 | 1/1 |"
    with pytest.raises(SystemExit, match="not a tuning seed"):
        load_library([str(tmp_path)], tmp_path / "layers")
    with pytest.raises(SystemExit, match="no rendered pair"):
        library_pairs(tmp_path / "layers")


def test_cached_layers_of_other_code_or_settings_are_refused(tmp_path, monkeypatch):
    """bench/fit_psafe.py and bench/op_ceiling.py fit and choose the FP budget on cached per-pixel layers. Stop
    34's trees were fitted on layers from before that stop's band rule changed the DEM, so a layers directory is
    stamped with the flight code and the --set-param overrides that made it, and refused for any other."""
    import fit_psafe

    layers = tmp_path / "layers"
    assert fit_psafe.claim_layers(layers, {}) is None  # a fresh directory is claimed and stamped
    np.savez_compressed(layers / "pair.npz", a=np.zeros(3))
    assert fit_psafe.claim_layers(layers, {}) is None  # the same code and settings: its layers are used
    refused = fit_psafe.claim_layers(layers, {"lower_view_dem": True})
    assert refused is not None and "made with {}" in refused
    monkeypatch.setattr(fit_psafe, "layers_code", lambda: "0123456789abcdef")  # the flight code was edited
    refused = fit_psafe.claim_layers(layers, {})
    assert refused is not None and "other flight_sw code" in refused and "0123456789abcdef" in refused
    (layers / "code.txt").unlink()  # a directory from before the stamp
    refused = fit_psafe.claim_layers(layers, {})
    assert refused is not None and "unknown settings or code" in refused
    assert fit_psafe.claim_layers(tmp_path / "fresh", {}) is None


@pytest.mark.parametrize("value", ["fp_budget=0.5", "psafe_min=nan", "call_slope_max=-1", "fp_budget=x"])
def test_fit_psafe_refuses_an_operating_point_out_of_bounds_before_it_fits(value, tmp_path, capsys):
    """An out-of-bounds --call passed the first check and failed after the renders, layers and fit, in a traceback
    (review of stop 63)."""
    from fit_psafe import main

    layers = tmp_path / "layers"
    argv = ["--seeds", "0", "--cases", "vertical", "--layers", str(layers), "--write", str(tmp_path / "m.json")]
    assert main([*argv, "--call", value]) == 2
    assert "error: --call" in capsys.readouterr().out and not layers.exists()


def test_the_trees_can_be_fitted_on_the_view_raster_truth_where_a_render_took_a_finer_one(tmp_path):
    """The shipped trees are fitted on the view-raster truth (``--fit-truth view``, stop 68): on a pair whose truth
    is on its view raster the rule reproduces the stored truth on every pixel; on one with a footprint raster it
    differs where sub-pixel relief is, and only such a pair's labels are swapped."""
    import math

    from fit_psafe import fit_labelled, footprint_truth, view_raster_safe

    from ground_sim.descent import render_scenario
    from protocol.pairdir import Camera, read_pair

    f = 64.0 / math.tan(math.radians(15.0))
    cam = Camera(128, 128, f, f, 63.5, 63.5)
    render_scenario("approach", tmp_path / "hi", frames=[[1200, 600]], camera=cam, progress=False, workers=1)
    render_scenario("vertical", tmp_path / "lo", frames=[[100, 50]], camera=cam, progress=False, workers=1)
    (hi,) = [p for p in (tmp_path / "hi").iterdir() if p.is_dir()]
    (lo,) = [p for p in (tmp_path / "lo").iterdir() if p.is_dir()]
    assert footprint_truth(str(hi)) and not footprint_truth(str(lo)) and not footprint_truth(str(tmp_path))
    for d, fine in ((lo, False), (hi, True)):
        pair = read_pair(d)
        stored = pair.truth["hazard"] < 1.0
        view = view_raster_safe(pair, np.ones(stored.shape, bool)).reshape(stored.shape)
        if fine:
            assert 0 < np.count_nonzero(view != stored) < 0.2 * stored.size
        else:
            assert np.array_equal(view, stored)
    # a pair drawn from a .toml scene names only the scene: its file is given (the `crater` and `tilted` cases)
    pair = read_pair(lo)
    spec = pair.meta["scene_spec"]
    pair.meta["scene_spec"] = pair.meta["scene"] = "no_such_scene"
    with pytest.raises(Exception, match="no_such_scene"):
        view_raster_safe(pair, np.ones(pair.truth["hazard"].shape, bool))
    view = view_raster_safe(pair, np.ones(pair.truth["hazard"].shape, bool), spec)
    assert np.array_equal(view.reshape(pair.truth["hazard"].shape), pair.truth["hazard"] < 1.0)
    rows = [{"safe": np.array([True]), "safe_view": np.array([False])}, {"safe": np.array([True])}]
    assert [r["safe"][0] for r in fit_labelled(rows, "view")] == [False, True]
    assert [r["safe"][0] for r in fit_labelled(rows, "footprint")] == [True, True]
