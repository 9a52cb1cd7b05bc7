"""Fit the calibrated P(safe) model (flight_sw/psafe.py) on TUNING seeds; cross-validate it and the FP budget.

    .venv/bin/python bench/fit_psafe.py --seeds 0 1 2 3 4 5 6 7 8 9 --cv --budgets 0.003 0.004 0.005
    .venv/bin/python bench/fit_psafe.py --seeds 0 1 2 3 4 5 6 7 8 9 --write flight_sw/psafe_model.json

Every pair of the given tuning seeds (cases ``vertical`` and ``approach``, rendered by
``bench/eval_flight.py`` into ``--cache``) is run through the ``fast`` front end with
``keep_layers``; the per-pixel features of the covered area and the truth (``gt_hazard < 1`` =
safe) are kept in ``--layers`` (reused). Held-out seeds are refused. ``--cv`` fits on all seeds
but one fold and scores the held-back fold with the FP-budget rule for each budget: the table
gives the worst and median pixel FP and the median CDI per scenario (what the budget is chosen
on). ``--reliability`` prints predicted vs observed P(safe) per footprint-size band.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import statistics
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))
from _cli import bounded_int, out_file, positive_int, run, unknown, write_out  # noqa: E402

from flight_sw import psafe  # noqa: E402
from ground_sim.render import DEFAULT_RASTER, RASTERS  # noqa: E402

ALL_FEATS = (
    "a",
    "a_pc",
    "upsun",
    "speck",
    "speck_fp",
    "u",
    "rough",
    "rho",
    "arho",
    "nbad",
    "nbad_w",
    "nwall",
    "nwall_w",
    "amean",
    "nknown",
    "scale",
    "gbad",
)
SUN_FEATS = ("a_pc", "upsun")  # NaN together when the pipeline is not told the sun (or skips the shading stage)


def pair_layers(pair_dir: str, out: Path, set_param: tuple[str, ...] = (), scene: str | None = None) -> dict[str, Any]:
    """Features (covered pixels, 1-D float32), dark-shadow cue, truth and footprint size of one pair (cached);
    ``set_param``: ``K=V`` overrides of ``fast`` (bench_multiframe.preset_with) the layers are made with."""
    needs_view = footprint_truth(pair_dir)
    if out.is_file():
        with np.load(out) as z:
            cached = {k: z[k] for k in z.files}
        if "safe_view" in cached or not needs_view:
            return cached
    from bench_multiframe import preset_with
    from eval_flight import run_pair

    from protocol.pairdir import read_pair

    pair = read_pair(pair_dir)
    res = run_pair(pair, dataclasses.replace(preset_with("fast", set_param), psafe_model="gaussian", keep_layers=True))
    cov = res.covered
    d: dict[str, Any] = {k: res.layers[k][cov].astype(np.float32) for k in ALL_FEATS}
    d["dark"] = res.layers["dark"][cov]
    d["safe"] = pair.truth["hazard"][cov] < 1.0
    if needs_view:
        d["safe_view"] = view_raster_safe(pair, cov, scene)
    d["fp_px"] = np.float32(res.info["footprint_px"])
    d["shape"] = np.asarray(cov.shape)
    out.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(out, **d)
    return d


def footprint_truth(pair_dir: str) -> bool:
    """Whether the pair's frame-0 slope and roughness truth was taken on a footprint raster finer than its view
    raster (``RENDER_VERSION`` 3, docs/scenes.md "Ground-truth accuracy" item 6)."""
    from studies.evaluate import footprint_truth_cell

    try:
        view = json.loads((Path(pair_dir) / "pair.json").read_text())["render"][0]
    except (OSError, ValueError, KeyError, IndexError, TypeError):
        return False
    return isinstance(view, dict) and footprint_truth_cell(view) is not None


def view_raster_safe(pair: Any, cov: np.ndarray, scene: str | None = None) -> np.ndarray:
    """The covered pixels' truth (safe) by the view-raster rule, the renders' truth before stop 67: the 3 m plane
    fitted on the render's own view raster (``studies.evaluate.recorded_truth_planes`` without the footprint
    cell), with the stored shadow. The labels ``--fit-truth view`` fits on. ``scene``: the scene spec (a preset
    or a .toml path) where pair.json names only the scene (a case of ``bench/scenes/``)."""
    from ground_sim.scene import load_scene
    from ground_sim.truth import hazard_layers
    from studies.evaluate import _scene_of, recorded_truth_planes
    from studies.multiframe import world_of

    view = {k: v for k, v in pair.meta["render"][0].items() if k != "truth_cell_m"}
    spec, seed = _scene_of(pair.meta, scene, None)
    if spec is None:
        raise SystemExit(f"fit_psafe: {pair.meta.get('label')}: the pair names no scene to draw the truth from")
    world = world_of(pair)
    ok = cov & np.isfinite(world[..., 0]) & np.isfinite(world[..., 1])
    hz = np.ones(cov.shape, np.float32)  # a covered pixel without true ground is not safe (as gt_hazard NaN)
    planes = recorded_truth_planes(
        load_scene(spec, seed), view, world[..., 0][ok], world[..., 1][ok], Z=world[..., 2][ok]
    )
    if planes is None:
        raise SystemExit(f"fit_psafe: {pair.meta.get('label')}: its render record does not hold its view raster")
    hz[ok] = hazard_layers(*planes, np.asarray(pair.truth["shadow"], bool)[ok])
    return hz[cov] < 1.0


def fit_labelled(rows: list[dict[str, Any]], fit_truth: str) -> list[dict[str, Any]]:
    """``rows`` with the labels the trees are fitted on: ``view`` takes each pair's view-raster truth where its
    render took a finer one (``safe_view``), ``footprint`` the stored truth. Scores always read the stored truth."""
    if fit_truth == "footprint":
        return rows
    return [{**r, "safe": r["safe_view"]} if "safe_view" in r else r for r in rows]


def layers_code() -> str:
    """The fingerprint of the code that makes the layers: flight_sw's Python and C source (not its model
    files: the layers are made with ``psafe_model="gaussian"``, so a refitted model leaves them valid)."""
    from studies.executor import code_fingerprint

    return code_fingerprint(["flight_sw"], suffixes=(".py", ".c"))


def claim_layers(layers_dir: Path, pipeline: dict[str, Any]) -> str | None:
    """Stamp ``layers_dir`` with the code and the ``--set-param`` overrides its layers are made with, or say
    (one line) why its cached layers cannot be used: another code's DEM or other settings. Stop 34's trees
    were fitted on layers made before that stop's band rule changed the DEM, and the stale layers went on
    being used until stop 41 (docs/benchmarks/pipeline.md), so cached layers are trusted only with this stamp."""
    stamp = layers_dir / "pipeline.json"  # the overrides the cached layers were made with
    code = layers_dir / "code.txt"  # and the code that made them
    cached = any(layers_dir.glob("*.npz"))
    if stamp.is_file() and json.loads(stamp.read_text()) != pipeline:
        return f"{layers_dir} holds layers made with {stamp.read_text().strip()}, not {json.dumps(pipeline)}"
    if cached and not (stamp.is_file() and code.is_file()):
        return f"{layers_dir} holds layers of unknown settings or code; give a --layers of their own"
    if cached and code.read_text().strip() != layers_code():
        return (
            f"{layers_dir} holds layers made by other flight_sw code ({code.read_text().strip()}, this code "
            f"{layers_code()}); give a --layers of their own"
        )
    layers_dir.mkdir(parents=True, exist_ok=True)
    stamp.write_text(json.dumps(pipeline) + "\n")
    code.write_text(layers_code() + "\n")
    return None


def load_all(
    seeds: list[int],
    cases: list[str],
    cache: Path,
    layers: Path,
    raster: str = DEFAULT_RASTER,
    set_param: tuple[str, ...] = (),
    image_px: int | None = None,
) -> list[dict[str, Any]]:
    from eval_flight import CASES, case_key, render_case

    rows = []
    for c in cases:
        for s in seeds:
            for e in render_case(c, s, cache, raster=raster, image_px=image_px):
                name = f"{c}_s{s}_{e['altitude_m']}"
                key = case_key(c, s, raster=raster, image_px=image_px)
                spec = CASES[c][1]
                scene = spec if spec.endswith(".toml") else None  # pair.json names such a scene, not its file
                d = pair_layers(e["pair_dir"], layers / f"{key}_{e['altitude_m']}.npz", set_param, scene)
                if "shape" not in d:
                    from protocol.pairdir import read_pair

                    d["shape"] = np.asarray(read_pair(e["pair_dir"]).images[0].shape[:2])
                rows.append({"name": name, "case": c, "seed": s, "alt": e["altitude_m"], **d})
    return rows


def load_library(
    roots: list[str], layers: Path, raster: str = DEFAULT_RASTER, set_param: tuple[str, ...] = ()
) -> list[dict[str, Any]]:
    """Every pair of ``raster`` under ``roots`` (a ``hazard-hil landings --cache`` of library scenes), as rows
    of its scene: the library's scenes, suns and terrain beside the eval cases. A held-out scene seed is refused."""
    from eval_flight import library_pairs

    from ground_sim.seeds import TUNING_SEEDS

    rows = []
    for root in roots:
        for e in library_pairs(Path(root), raster):
            where, seed = e["pair_dir"], e["seed"]
            if seed not in TUNING_SEEDS:
                raise SystemExit(f"fit_psafe: {where} has scene seed {seed}, not a tuning seed: refusing it")
            d = pair_layers(where, layers / f"library_{Path(where).name}.npz", set_param)
            name = f"{e['case']}_{e['scenario']}_s{e['seed']}_{e['altitude_m']}"
            rows.append({"name": name, "case": f"library:{e['case']}", "seed": e["seed"], "alt": e["altitude_m"], **d})
    return rows


# bin edges per feature (a value equal to an edge goes to the upper bin; NaN contributes nothing)
DEFAULT_EDGES: dict[str, tuple[float, ...]] = {
    "a": (0.2, 0.4, 0.6, 0.8, 1.0, 1.25, 1.5, 2.0, 3.0),
    "u": (0.1, 0.2, 0.3, 0.5, 0.8, 1.2, 2.0),
    "rough": (0.25, 0.5, 0.75, 1.0, 1.5),
    "rho": (-0.4, -0.25, -0.15, -0.1, -0.05, 0.05, 0.1, 0.15, 0.25, 0.4),
    "arho": (0.03, 0.05, 0.08, 0.12, 0.2),
    "nbad": (0.01, 0.05, 0.1, 0.2, 0.4),
    "nbad_w": (0.01, 0.03, 0.07, 0.15),
    "nwall": (0.05, 0.1, 0.2, 0.35, 0.5, 0.7),
    "nwall_w": (0.1, 0.2, 0.3, 0.4),
    "amean": (0.3, 0.5, 0.7, 1.0, 1.5),
    "nknown": (0.3, 0.6, 0.9),
    "scale": (0.0, 1.0, 2.0, 3.0, 4.0),
    "gbad": (0.005, 0.01, 0.02, 0.04, 0.08),
}
# the binned model's 1-D features (flight_sw.psafe.PsafeModel)
ADDITIVE = ("rough", "rho", "arho", "nbad", "nbad_w", "nwall", "nwall_w", "amean", "nknown", "scale", "gbad")
MONOTONE_DECREASING = ("rough", "nbad", "nbad_w")  # P(safe) never grows with these (both models)


def _pava_decreasing(w: np.ndarray, cnt: np.ndarray) -> np.ndarray:
    """Weighted least-squares projection of ``w`` onto non-increasing sequences (pool adjacent violators)."""
    vals: list[float] = []
    wts: list[float] = []
    lens: list[int] = []
    for x, c in zip(w.tolist(), np.maximum(cnt, 1e-9).tolist(), strict=True):
        vals.append(x)
        wts.append(c)
        lens.append(1)
        while len(vals) > 1 and vals[-2] < vals[-1]:
            v2, c2, l2 = vals.pop(), wts.pop(), lens.pop()
            vals[-1] = (vals[-1] * wts[-1] + v2 * c2) / (wts[-1] + c2)
            wts[-1] += c2
            lens[-1] += l2
    return np.repeat(np.asarray(vals), lens)


def _design(feats: Mapping[str, np.ndarray], edges: Mapping[str, Sequence[float]]) -> tuple[np.ndarray, list[str]]:
    """One-hot design matrix (1-D features in, rows = points) and the column groups' names."""
    a, u = np.asarray(feats["a"]), np.asarray(feats["u"])
    n = a.size
    known = np.isfinite(a) & np.isfinite(u)
    na, nu = len(edges["a"]) + 1, len(edges["u"]) + 1
    cols = [(~known).astype(np.float32)[:, None]]
    groups = ["nodem"]
    oh = np.zeros((n, na * nu), np.float32)
    idx = np.digitize(np.where(known, a, 0), edges["a"]) * nu + np.digitize(np.where(known, u, 0), edges["u"])
    oh[np.arange(n), idx] = 1.0
    oh[~known] = 0.0
    cols.append(oh)
    groups += ["au"] * (na * nu)
    for f in ADDITIVE:
        x = np.asarray(feats[f])
        ok = np.isfinite(x)
        m = len(edges[f]) + 1
        o = np.zeros((n, m), np.float32)
        o[np.arange(n), np.digitize(np.where(ok, x, 0), edges[f])] = 1.0
        o[~ok] = 0.0
        cols.append(o)
        groups += [f] * m
    cols.append(np.ones((n, 1), np.float32))
    groups.append("bias")
    return np.concatenate(cols, axis=1), groups


def fit_gam(
    feats: Mapping[str, np.ndarray],
    safe: np.ndarray,
    seeds: Sequence[int],
    *,
    edges: Mapping[str, Sequence[float]] | None = None,
    ridge: float = 1.0,
    iters: int = 40,
    info: Mapping[str, Any] | None = None,
) -> psafe.PsafeModel:
    """Fit the model to 1-D feature arrays and truth labels ``safe`` (bool) by ridge-regularised IRLS.

    ``seeds`` are recorded in the model (``fitted_on``); the caller checks they are tuning seeds
    (:func:`fit_rows`: flight_sw does not import ground_sim).
    """
    E = {k: tuple(float(x) for x in v) for k, v in (edges or DEFAULT_EDGES).items()}
    X, groups = _design(feats, E)
    y = np.asarray(safe, np.float64).ravel()
    if X.shape[0] != y.size or y.size == 0:
        raise ValueError("psafe fit: features and labels differ in length or are empty")
    w = np.zeros(X.shape[1])
    reg = ridge * np.ones(X.shape[1])
    reg[-1] = 1e-6  # the bias is not shrunk
    for _ in range(iters):
        z = X @ w
        p = 1.0 / (1.0 + np.exp(-np.clip(z, -30, 30)))
        g = X.T @ (p - y) + reg * w
        H = (X * (p * (1.0 - p))[:, None]).T @ X + np.diag(reg)
        step = np.linalg.solve(H, g)
        w -= step
        if np.abs(step).max() < 1e-5:
            break
    cnt = X.sum(axis=0)
    grp = np.asarray(groups)
    na, nu = len(E["a"]) + 1, len(E["u"]) + 1
    T = w[grp == "au"].reshape(na, nu)
    Tc = cnt[grp == "au"].reshape(na, nu)
    for j in range(nu):  # P(safe) does not grow with the estimated slope at a given uncertainty
        T[:, j] = _pava_decreasing(T[:, j], Tc[:, j])
    weights: dict[str, tuple[float, ...]] = {}
    for f in ADDITIVE:
        sel = grp == f
        wf, cf = w[sel], cnt[sel]
        if f in MONOTONE_DECREASING:
            wf = _pava_decreasing(wf, cf)
        weights[f] = tuple(float(x) for x in wf)
    return psafe.PsafeModel(
        E,
        tuple(tuple(float(x) for x in row) for row in T),
        weights,
        float(w[grp == "nodem"][0]),
        float(w[-1]),
        tuple(int(s) for s in seeds),
        dict(info or {}),
    )


def fit_trees(
    feats: dict[str, np.ndarray], safe: np.ndarray, seeds: list[int], trees: dict[str, Any], info: dict[str, Any]
) -> Any:
    """Histogram gradient boosting (scikit-learn) on the features, exported as a flight_sw TreeModel."""
    from sklearn.ensemble import HistGradientBoostingClassifier

    from flight_sw.psafe import TreeModel

    monotone = ("a", "a_pc", *MONOTONE_DECREASING)  # P(safe) never grows with the slope either

    names = list(feats)
    X = np.stack([feats[k] for k in names], axis=1).astype(np.float32)
    clf = HistGradientBoostingClassifier(
        max_iter=int(trees["iters"]),
        max_leaf_nodes=int(trees["leaves"]),
        learning_rate=float(trees["lr"]),
        l2_regularization=1.0,
        monotonic_cst=[-1 if k in monotone else 0 for k in names],
        early_stopping=False,
        random_state=0,
    ).fit(X, safe)
    cols: dict[str, list[Any]] = {k: [] for k in ("feature", "missing_left", "threshold", "left", "right", "value")}
    roots = []
    for (pred,) in clf._predictors:  # one tree per iteration (binary log-loss)
        nd = pred.nodes
        off = len(cols["value"])
        roots.append(off)
        leaf = nd["is_leaf"].astype(bool)
        cols["feature"] += np.where(leaf, -1, nd["feature_idx"]).tolist()
        cols["missing_left"] += nd["missing_go_to_left"].astype(int).tolist()
        # the largest float32 <= the threshold: a float32 feature goes left exactly when sklearn sends it left
        t64 = np.where(leaf, 0.0, nd["num_threshold"])
        t32 = t64.astype(np.float32)
        t32 = np.where(t32 > t64, np.nextafter(t32, np.float32(-np.inf)), t32)
        cols["threshold"] += t32.tolist()
        cols["left"] += np.where(leaf, 0, nd["left"] + off).tolist()
        cols["right"] += np.where(leaf, 0, nd["right"] + off).tolist()
        cols["value"] += np.where(leaf, nd["value"], 0.0).tolist()
    doc = {
        "format": "psafe-trees/1",
        "features": names,
        "base": float(np.ravel(clf._baseline_prediction)[0]),
        "roots": roots,
        **cols,
        "fitted_on": seeds,
        "info": {**info, "trees": dict(trees), "sklearn": __import__("sklearn").__version__},
    }
    return TreeModel.from_json(doc)


def fit_rows(
    rows: list[dict[str, Any]],
    per_pair: int,
    ridge: float,
    rng_seed: int = 0,
    trees: dict[str, Any] | None = None,
    names: tuple[str, ...] = ALL_FEATS,
    blank_shading: float = 0.0,
    pipeline: dict[str, Any] | None = None,
) -> Any:
    """Fit on ``per_pair`` points of every row. ``blank_shading``: the share of points whose sun-borne features
    (``SUN_FEATS``) are set to NaN, so the trees also learn the case of an unknown sun (the pipeline gives NaN then).
    ``pipeline``: the fast overrides the layers were made with, recorded in the model's info (the pipeline
    refuses the model where its DEM settings differ: flight_sw.pipeline.MODEL_DEM_PARAMS)."""

    rng = np.random.default_rng(rng_seed)
    parts: dict[str, list[np.ndarray]] = {k: [] for k in (*names, "safe")}
    for r in rows:
        idx = np.flatnonzero(~r["dark"])  # dark shadow is a hard cue, not part of the model
        idx = rng.choice(idx, min(idx.size, per_pair), replace=False)
        for k, v in parts.items():
            v.append(r[k][idx])
    cat = {k: np.concatenate(v) for k, v in parts.items()}
    if blank_shading > 0:
        blank = rng.random(cat["safe"].size) < blank_shading
        for k in SUN_FEATS:
            if k in cat:
                cat[k] = np.where(blank, np.float32(np.nan), cat[k])
    seeds = sorted({int(r["seed"]) for r in rows})
    sizes = sorted({tuple(int(x) for x in r["shape"]) for r in rows})
    info = {
        "pairs": len(rows),
        "cases": list(dict.fromkeys(str(r["case"]) for r in rows)),  # eval_flight.py cases: which scenes
        "points": int(cat["safe"].size),
        "per_pair": per_pair,
        "ridge": ridge,
        "image_px": [list(t) for t in sizes],  # the pipeline falls back to the Gaussian rule on other sizes
        "safe_share": float(cat["safe"].mean()),  # the prior P(safe) holds (fusion counts it once: fusion.py)
    }
    if all("fp_px" in r for r in rows):  # below it the pipeline calls nothing safe: the trees would extrapolate
        info["footprint_px_min"] = math.floor(100 * min(float(r["fp_px"]) for r in rows)) / 100
    if blank_shading > 0 and any(k in cat for k in SUN_FEATS):
        info["blank_shading"] = blank_shading
    if pipeline:
        info["pipeline"] = dict(pipeline)
    if trees:
        return fit_trees({k: cat[k] for k in names}, cat["safe"], seeds, trees, info)
    return fit_gam({k: cat[k] for k in names}, cat["safe"], seeds, ridge=ridge, info=info)


def barred(r: dict[str, Any], a_max: float, cap: str = "a", cap_hi: tuple[float, float] | None = None) -> np.ndarray:
    """The points the call never takes (evidence.classify_calibrated): an estimated slope at or over the cap
    (``cap``, ``cap_hi`` as in :func:`score`), or no elevation."""
    from flight_sw.evidence import cap_slope

    with np.errstate(invalid="ignore"):
        lim = a_max if cap_hi is None else np.where(r["scale"] >= cap_hi[0], cap_hi[1], a_max)
        return (cap_slope(r, cap) >= lim) | ~np.isfinite(r["a"])


def score(
    model: Any,
    r: dict[str, Any],
    budget: float,
    p_min: float,
    a_max: float,
    cap: str = "a",
    cap_hi: tuple[float, float] | None = None,
) -> dict[str, Any]:
    """The FP-budget call on one pair's covered points, as the pipeline makes it (evidence.classify_calibrated).

    ``cap``: the slope the ``a_max`` cap reads: ``a`` (the DEM's), ``a_pc`` (with shading; the DEM's where
    it has none), ``max`` (the larger), or ``nosun``: as ``a_pc`` with every ``a_pc`` unknown (no sun given).
    ``cap_hi = (s0, a_hi)``: where the footprint spans ``2^s0`` px or more (feature ``scale``), the cap is
    ``a_hi`` instead (a footprint of many pixels measures its slope well).
    """
    from flight_sw.psafe import budget_rule

    if cap == "nosun":
        r = {**r, **{k: np.full(r["a"].shape, np.nan, np.float32) for k in SUN_FEATS}}
        cap = "a_pc"
    p = model.predict(r, np.ones(r["safe"].shape, bool))
    p[r["dark"]] = 0.0
    call = budget_rule(np.where(barred(r, a_max, cap, cap_hi), np.nan, p), budget, p_min, n=p.size)
    th = ~r["safe"]
    n = max(1, th.size)
    fp = 100.0 * float((call & th).sum()) / n
    tp = 100.0 * float((call & ~th).sum()) / n
    tn = 100.0 * float((~call & th).sum()) / n
    return {"fp": fp, "cdi": tp + tn, "called": 100.0 * float(call.mean()), "p": p}


def _med(x: list[float]) -> float:
    return statistics.median(x) if x else math.nan


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=list(range(10)))
    ap.add_argument("--cases", nargs="+", default=["vertical", "approach"])
    ap.add_argument("--cache", default="/tmp/flight_eval_cache")
    ap.add_argument("--layers", default="/tmp/flight_psafe_layers")
    ap.add_argument("--per-pair", type=positive_int, default=15000, help="points sampled per pair for the fit")
    ap.add_argument("--ridge", type=float, default=1.0)
    ap.add_argument("--cv", action="store_true", help="leave-fold-out cross-validation of the budget")
    ap.add_argument("--folds", type=bounded_int(2, 100), default=5)
    ap.add_argument(
        "--repeats",
        type=int,
        default=1,
        help="CV: also repeat it over this many fold partitions (seeded shuffles of the seeds; the first is the "
        "plain one) and print each budget's worst-pair FP per partition: how much the operating point's rule moves",
    )
    ap.add_argument("--budgets", type=float, nargs="+", default=[0.003, 0.004, 0.005, 0.006])
    ap.add_argument("--p-min", type=float, nargs="+", default=[0.9])
    ap.add_argument(
        "--a-max", type=float, nargs="+", default=[0.6], help="never call an estimated slope >= this x the limit"
    )
    ap.add_argument("--reliability", action="store_true")
    ap.add_argument("--kind", choices=("gam", "trees"), default="gam", help="additive model or boosted trees")
    ap.add_argument("--raster", choices=RASTERS, default=DEFAULT_RASTER, help="the renders' terrain rasters")
    ap.add_argument(
        "--image-size",
        type=int,
        default=None,
        help="the eval cases with a square camera of this many px (thesis FOV; default its 512 px); the model "
        "records the sizes it was fitted on, and the pipeline uses it on those only",
    )
    ap.add_argument("--iters", type=positive_int, default=30, help="trees: boosting iterations (shipped: 30)")
    ap.add_argument("--leaves", type=bounded_int(2, 4096), default=15, help="trees: leaves per tree")
    ap.add_argument("--lr", type=float, default=0.2, help="trees: learning rate (shipped: 0.2)")
    ap.add_argument("--write", type=out_file, help="fit on all the seeds and write the model here")
    ap.add_argument(
        "--call",
        nargs="*",
        default=[],
        metavar="K=V",
        help="with --write: the operating point the CV chose for this model (fp_budget, psafe_min, call_slope_max), "
        "recorded in its info.call; fast calls with it in place of its own (Params.psafe_call)",
    )
    ap.add_argument(
        "--features",
        nargs="+",
        default=list(ALL_FEATS),
        choices=ALL_FEATS,
        help="the model's features (all by default)",
    )
    ap.add_argument(
        "--cap",
        nargs="+",
        default=["a_pc"],
        choices=("a", "a_pc", "max", "nosun"),
        help="CV: which slope the --a-max cap reads (score(); fast reads a_pc)",
    )
    ap.add_argument(
        "--cap-hi",
        nargs="+",
        default=[],
        metavar="S0:A",
        help="CV: also score with the cap at A where the footprint spans 2^S0 px or more (score())",
    )
    ap.add_argument(
        "--blank-shading", type=float, default=0.0, help="share of fit points with a_pc blanked (fit_rows())"
    )
    ap.add_argument(
        "--fit-truth",
        choices=("view", "footprint"),
        default="view",
        help="the labels the trees are fitted on where a render took its slope and roughness truth on a raster "
        "finer than its view raster: the view raster's rule (the shipped trees'; a tuning CV scored on the finer "
        "truth prefers it, docs/benchmarks/pipeline.md stop 68) or the stored footprint-scale truth; CV scores "
        "always read the stored truth",
    )
    ap.add_argument(
        "--library",
        nargs="*",
        default=[],
        help="also fit on every pair in these landing render caches (hazard-hil landings --seed-set tuning --cache)",
    )
    ap.add_argument(
        "--set-param",
        nargs="*",
        default=[],
        metavar="K=V",
        help="make the layers with these overrides of fast (a --layers directory of their own); a written model "
        "records them (info.pipeline) and the pipeline refuses it with other values of the DEM's settings",
    )
    args = ap.parse_args(argv)
    from eval_flight import CASES

    unknown("--cases", args.cases, CASES)  # before any render or layer (render_case: a KeyError after the first)

    import cv2

    cv2.setNumThreads(1)
    from bench_multiframe import preset_with

    from flight_sw.pipeline import PRESETS
    from flight_sw.psafe import CALL_KEYS, checked_call, model_call
    from ground_sim.seeds import TUNING_SEEDS

    try:
        over = preset_with("fast", args.set_param)
    except (ValueError, AttributeError, KeyError) as exc:
        print(f"error: --set-param: {exc}")
        return 2
    pipeline = {k.split("=", 1)[0]: getattr(over, k.split("=", 1)[0]) for k in args.set_param}
    pipeline = {k: v for k, v in pipeline.items() if v != getattr(PRESETS["fast"], k)}
    call: dict[str, float] = {}  # checked before hours of renders and layers, not after
    for item in args.call:
        k, _, v = item.partition("=")
        try:
            if k not in CALL_KEYS:
                raise ValueError
            call[k] = float(v)
        except ValueError:
            print(f"error: --call {item!r}: give K=V with K one of {CALL_KEYS} and V a number")
            return 2
    try:  # the pipeline's bounds too (fp_budget=0.5 or nan passed here, and failed only after the fit)
        checked_call(call)
    except ValueError as exc:
        print(f"error: --call: {exc}")
        return 2
    layers_dir = Path(args.layers)
    refused = claim_layers(layers_dir, pipeline)
    if refused:
        print(f"error: {refused}")
        return 2

    if call and not args.write:
        print("error: --call is recorded in the model --write writes; give --write")
        return 2
    if args.image_size is not None and args.library:
        print("error: --library renders are the thesis camera's 512 px: not with --image-size")
        return 2
    bad = [s for s in args.seeds if s not in TUNING_SEEDS]
    if bad:
        print(f"error: seeds {bad} are not tuning seeds (ground_sim.seeds.TUNING_SEEDS); refusing to fit on them")
        return 2
    names = tuple(args.features)
    trees = {"iters": args.iters, "leaves": args.leaves, "lr": args.lr} if args.kind == "trees" else None
    set_param = tuple(args.set_param)
    rows = load_all(args.seeds, args.cases, Path(args.cache), layers_dir, args.raster, set_param, args.image_size)
    rows += load_library(args.library, layers_dir, args.raster, set_param)
    print(f"{len(rows)} pairs, {sum(r['safe'].size for r in rows)} covered points", flush=True)

    if args.cv or args.reliability:
        his: list[tuple[float, float] | None] = [None] + [
            (float(x.split(":")[0]), float(x.split(":")[1])) for x in args.cap_hi
        ]
        keys = [
            (b, a, pm, c, h)
            for b in args.budgets
            for a in args.a_max
            for pm in args.p_min
            for c in args.cap
            for h in his
        ]
        rel: list[tuple[float, np.ndarray, np.ndarray]] = []
        runs: list[dict[tuple[float, float, float, str, tuple[float, float] | None], list[dict[str, Any]]]] = []
        for rep in range(max(1, args.repeats)):
            # partition 0: seeds i, i + folds, ... (the plain one); later ones: seeded shuffles of the seeds
            order = (
                list(args.seeds) if rep == 0 else [int(x) for x in np.random.default_rng(rep).permutation(args.seeds)]
            )
            folds = [order[i :: args.folds] for i in range(args.folds)]
            res: dict[tuple[float, float, float, str, tuple[float, float] | None], list[dict[str, Any]]] = {
                key: [] for key in keys
            }
            for fold in folds:
                train = fit_labelled([r for r in rows if r["seed"] not in fold], args.fit_truth)
                model = fit_rows(
                    train, args.per_pair, args.ridge, trees=trees, names=names, blank_shading=args.blank_shading
                )
                for r in rows:
                    if r["seed"] not in fold:
                        continue
                    for (b, a_max, pm, cap, ch), out in res.items():
                        s = score(model, r, b, pm, a_max, cap, ch)
                        out.append({"name": r["name"], "case": r["case"], "fp": s["fp"], "cdi": s["cdi"]})
                    if rep == 0:
                        rel.append((float(r["fp_px"]), s["p"], r["safe"]))
            runs.append(res)
            if args.repeats > 1:
                print(f"  partition {rep + 1}/{args.repeats} done", file=sys.stderr, flush=True)
        res = runs[0]
        if args.cv:
            cases = list(dict.fromkeys(r["case"] for r in rows))
            print(
                "\n| FP budget | a_max | cap | p_min | FP % worst / p90 / med | pairs > 1 % | worst pair | CDI % med | "
                + " | ".join(f"{c}: FP worst, CDI med" for c in cases)
                + " |"
            )
            print("|---:|---:|---|---:|---|---:|---|---:|" + "---|" * len(cases))
            for (b, a_max, pm, cap, ch), rs in res.items():
                fps = [x["fp"] for x in rs]
                worst = max(rs, key=lambda x: x["fp"])
                per_case = []
                for c in cases:
                    sel = [x for x in rs if x["case"] == c]
                    per_case.append(f"{max(x['fp'] for x in sel):.2f}, {_med([x['cdi'] for x in sel]):.1f}")
                print(
                    f"| {100 * b:.2f} % | {a_max:g}{'' if ch is None else f' ({ch[1]:g} from 2^{ch[0]:g} px)'} "
                    f"| {cap} | {pm:g} "
                    f"| {max(fps):.2f} / {np.percentile(fps, 90):.2f} / {statistics.median(fps):.2f} "
                    f"| {sum(f > 1.0 for f in fps)}/{len(fps)} | {worst['name']} "
                    f"| {statistics.median(x['cdi'] for x in rs):.1f} | " + " | ".join(per_case) + " |"
                )
        if args.cv and len(runs) > 1:
            print(
                f"\nThe same over {len(runs)} fold partitions (the first is the table's): worst-pair FP % per "
                "partition (and its pair), and the median CDI %"
            )
            print(
                "| FP budget | a_max | cap | p_min | worst-pair FP % per partition | max | pairs > 1 % (max) "
                "| CDI % med |"
            )
            print("|---:|---:|---|---:|---|---:|---:|---:|")
            for key in keys:
                b, a_max, pm, cap, ch = key
                tops = [max(run[key], key=lambda x: x["fp"]) for run in runs]
                worsts = [x["fp"] for x in tops]
                named = ", ".join(f"{x['fp']:.2f} ({x['name']})" for x in tops)
                over = max(sum(x["fp"] > 1.0 for x in run[key]) for run in runs)
                cdis = [statistics.median(x["cdi"] for x in run[key]) for run in runs]
                print(
                    f"| {100 * b:.3f} % | {a_max:g}{'' if ch is None else f' ({ch[1]:g} from 2^{ch[0]:g} px)'} | {cap} "
                    f"| {pm:g} | {named} | {max(worsts):.2f} | {over} "
                    f"| {statistics.median(cdis):.1f} |"
                )
        if args.reliability:
            print("\nReliability (cross-validated): observed safe share per predicted-P(safe) bin, by footprint size")
            bins = [0.0, 0.5, 0.8, 0.9, 0.95, 0.98, 0.99, 0.995, 1.0001]
            print("| footprint px | " + " | ".join(f"{bins[i]:g}-{min(1, bins[i + 1]):g}" for i in range(8)) + " |")
            print("|---|" + "---|" * 8)
            for lo, hi in ((0, 1.5), (1.5, 4), (4, 12), (12, math.inf)):
                in_bin = [(p, y) for f, p, y in rel if lo <= f < hi]
                if not in_bin:
                    continue
                p = np.concatenate([s[0] for s in in_bin])
                y = np.concatenate([s[1] for s in in_bin])
                cells = []
                for i in range(8):
                    m = (p >= bins[i]) & (p < bins[i + 1])
                    cells.append(f"{p[m].mean():.3f}/{y[m].mean():.3f}" if m.sum() > 200 else "-")
                print(f"| {lo:g}-{hi:g} | " + " | ".join(cells) + " |")
            print("(cells: mean predicted / observed safe share)")

    if args.write:
        model = fit_rows(
            fit_labelled(rows, args.fit_truth),
            args.per_pair,
            args.ridge,
            trees=trees,
            names=names,
            blank_shading=args.blank_shading,
            pipeline=pipeline,
        )
        if call:
            model = dataclasses.replace(model, info={**model.info, "call": call})
            model_call(model)  # the bounds the pipeline checks, before anything is written
        indent = None if trees else 1  # the trees' node arrays are long flat lists: one line keeps the file small
        write_out(args.write, json.dumps(model.to_json(), indent=indent) + "\n")
        print(f"wrote {args.write} (fitted on seeds {list(model.fitted_on)})")
    return 0


if __name__ == "__main__":
    run(main)
