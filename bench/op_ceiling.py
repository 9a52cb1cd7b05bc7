"""How much CDI the P(safe) ranking holds, and how much the operating point's rule gives away (tuning seeds only).

    .venv/bin/python bench/op_ceiling.py --library /tmp/tuning_landing_renders --layers /tmp/flight_psafe_layers

The trees are fitted and scored as ``bench/fit_psafe.py --cv`` does (5 folds of the tuning seeds, the shipped
tree settings), so every pair's P(safe) comes from trees that never saw its seed. Per pair, then:

* ``rule``: the shipped call (slope cap ``a_pc < 0.4``, P floor 0.97, FP budget 0.175 %), its CDI and FP;
* ``ceiling``: the best cut of the same ranking with the truth: the covered points called safe in decreasing
  P(safe) for as long as the pair's true FP stays within 0.25 / 0.5 / 0.9 % of them, with and without the cap.
  No rule can do better with this ranking; a rule that knew each pair's FP curve would reach it;
* ``ratio``: the pair's true FP over the FP its P(safe) expects at the rule's call, and how it correlates with
  pair-level quantities the flight software could compute (a rule that scales the budget per pair needs one);
* ``per scenario``: the rule with a budget of its own for approach (oblique) pairs, the vertical ones at 0.175 %.

Medians over the pairs of each group (the library scenes together), CDI in % of the covered points.
"""

from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from _cli import InputError, check_dir, note_cache_dir, positive_int, run  # noqa: E402
from eval_flight import CASES  # noqa: E402

CUTS = (0.25, 0.5, 0.9)  # the ceiling's FP limits, % of the covered points
TREES = {"iters": 45, "leaves": 31, "lr": 0.15}  # fast's trees (flight_sw/psafe_model.json info)


def out_of_fold(rows: list[dict[str, Any]], seeds: list[int], folds: int) -> list[np.ndarray]:
    """Each row's P(safe) (dark shadow 0) from trees fitted on the other folds' seeds (fit_psafe's CV split)."""
    from fit_psafe import ALL_FEATS, fit_labelled, fit_rows

    out: list[np.ndarray] = [np.empty(0, np.float32)] * len(rows)
    for k in range(folds):
        fold = seeds[k::folds]
        train = fit_labelled([r for r in rows if r["seed"] not in fold], "view")  # the shipped trees' labels
        model = fit_rows(train, 2000, 1.0, trees=TREES, names=ALL_FEATS, blank_shading=0.25)
        for i, r in enumerate(rows):
            if r["seed"] in fold:
                p = model.predict(r, np.ones(r["safe"].shape, bool))
                p[r["dark"]] = 0.0
                out[i] = p
        print(f"  fold {k + 1}/{folds} fitted", file=sys.stderr, flush=True)
    return out


def scores(call: np.ndarray, safe: np.ndarray) -> tuple[float, float]:
    """(FP %, CDI %) of a call over the covered points."""
    n = max(1, safe.size)
    return 100.0 * float((call & ~safe).sum()) / n, 100.0 * float((call & safe).sum() + (~call & ~safe).sum()) / n


def ceiling(p: np.ndarray, safe: np.ndarray, allowed: np.ndarray, fp_pct: float) -> float:
    """CDI % of the best truth cut of the ranking ``p`` over ``allowed`` with FP within ``fp_pct``."""
    order = np.argsort(-np.where(allowed, p, -1.0), kind="stable")
    order = order[allowed[order]]
    hz = ~safe
    fp, tp = np.cumsum(hz[order]), np.cumsum(safe[order])
    k = int(np.searchsorted(fp, fp_pct / 100.0 * safe.size, side="right"))
    called_tp, called_fp = (int(tp[k - 1]), int(fp[k - 1])) if k else (0, 0)
    return 100.0 * (called_tp + int(hz.sum()) - called_fp) / max(1, safe.size)


def group(r: dict[str, Any]) -> str:
    return "library" if str(r["case"]).startswith("library") else str(r["case"])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=list(range(10)))
    ap.add_argument(
        "--cases", nargs="+", default=["vertical", "approach", "thesis_vertical", "thesis_approach"], choices=CASES
    )
    ap.add_argument("--cache", default="/tmp/flight_eval_cache", help="eval_flight's renders (made on first use)")
    ap.add_argument("--layers", default="/tmp/flight_psafe_layers", help="fit_psafe's layers (made on first use)")
    ap.add_argument("--library", nargs="*", default=[], help="tuning landing render caches (fit_psafe --library)")
    ap.add_argument("--folds", type=positive_int, default=5)
    ap.add_argument("--budget", type=float, default=0.00175)
    ap.add_argument("--approach-budgets", type=float, nargs="*", default=[0.00175, 0.002, 0.0025, 0.003])
    args = ap.parse_args(argv)
    from ground_sim.seeds import TUNING_SEEDS

    if any(s not in TUNING_SEEDS for s in args.seeds):
        raise InputError(f"--seeds must be tuning seeds ({TUNING_SEEDS[0]}-{TUNING_SEEDS[-1]}, ground_sim.seeds)")
    for lib in args.library:  # inputs that must exist, before the cases are rendered and their layers made
        check_dir(lib, "--library")
    note_cache_dir(args.cache, "--cache")  # caches made on demand: said, so that a mistyped path is seen
    note_cache_dir(args.layers, "--layers")

    import cv2

    cv2.setNumThreads(1)
    from fit_psafe import barred, claim_layers, load_all, load_library

    from flight_sw.psafe import budget_rule

    refused = claim_layers(Path(args.layers), {})
    if refused:
        print(f"error: {refused}")
        return 2
    rows = load_all(args.seeds, args.cases, Path(args.cache), Path(args.layers))
    rows += load_library(args.library, Path(args.layers))
    print(f"{len(rows)} pairs", file=sys.stderr, flush=True)
    ps = out_of_fold(rows, list(args.seeds), args.folds)

    per: dict[str, list[list[float]]] = {}
    ratio: list[float] = []
    pair_q: dict[str, list[float]] = {"called": [], "sigma_u": [], "dem_vs_shading": [], "footprint_px": []}
    scen: list[tuple[bool, np.ndarray, np.ndarray]] = []
    for r, p in zip(rows, ps, strict=True):
        safe = r["safe"]
        cap = ~barred(r, 0.4, "a_pc") & ~r["dark"]  # what the rule may call (dark shadow is a hazard cue)
        measured = np.isfinite(r["a"]) & ~r["dark"]
        call = budget_rule(np.where(cap, p, np.nan), args.budget, 0.97, n=p.size)
        fp, cdi = scores(call, safe)
        row = [cdi, fp]
        row += [ceiling(p, safe, cap, c) for c in CUTS] + [ceiling(p, safe, measured, c) for c in CUTS]
        per.setdefault(group(r), []).append(row)
        per.setdefault("all", []).append(row)
        expected = 100.0 * float((1.0 - p[call]).sum()) / max(1, p.size)
        ratio.append((fp + 0.01) / (expected + 0.01))
        both = np.isfinite(r["a"]) & np.isfinite(r["a_pc"])
        pair_q["called"].append(100.0 * float(call.mean()))
        pair_q["sigma_u"].append(float(np.nanmedian(r["u"])) if np.isfinite(r["u"]).any() else np.nan)
        pair_q["dem_vs_shading"].append(float(np.median(np.abs(r["a"] - r["a_pc"])[both])) if both.any() else np.nan)
        pair_q["footprint_px"].append(float(r["fp_px"]))
        scen.append(("approach" in str(r["name"]), p, cap))

    print(f"\nrule: cap a_pc < 0.4, P >= 0.97, budget {100 * args.budget:.3f} %; ceiling: the best truth cut of the "
          "same out-of-fold ranking")  # fmt: skip
    head = " | ".join(f"FP <= {c:g} %" for c in CUTS)
    print(f"| group | pairs | rule: CDI % med, FP % worst | ceiling with the cap: {head} | without: {head} |")
    print("|---|---:|---|" + "---:|" * (2 * len(CUTS)))
    for g, rs in per.items():
        a = np.asarray(rs)
        cells = " | ".join(f"{statistics.median(a[:, i]):.1f}" for i in range(2, 2 + 2 * len(CUTS)))
        print(f"| {g} | {len(rs)} | {statistics.median(a[:, 0]):.1f}, {a[:, 1].max():.2f} | {cells} |")

    lr = np.log(np.asarray(ratio))
    q = {k: float(np.percentile(ratio, v)) for k, v in (("p10", 10), ("median", 50), ("p90", 90), ("max", 100))}
    print("\ntrue / expected FP at the rule's call: " + ", ".join(f"{k} {v:.2f}" for k, v in q.items()))
    print("correlation of its log with:")
    for k, v in pair_q.items():
        x = np.asarray(v)
        ok = np.isfinite(x)
        print(f"  {k}: {np.corrcoef(x[ok], lr[ok])[0, 1]:+.2f}")

    print(f"\nper scenario: vertical pairs at {100 * args.budget:.3f} %, approach pairs at")
    print("| approach budget | FP % worst | CDI % med | approach: FP worst, CDI med |")
    print("|---:|---:|---:|---|")
    for b in args.approach_budgets:
        res = []
        for (oblique, p, cap), r in zip(scen, rows, strict=True):
            call = budget_rule(np.where(cap, p, np.nan), b if oblique else args.budget, 0.97, n=p.size)
            res.append((oblique, *scores(call, r["safe"])))
        fps = [x[1] for x in res]
        ap_fp = [x[1] for x in res if x[0]]
        ap_cdi = [x[2] for x in res if x[0]]
        print(f"| {100 * b:.3f} % | {max(fps):.2f} | {statistics.median(x[2] for x in res):.1f} "
              f"| {max(ap_fp):.2f}, {statistics.median(ap_cdi):.1f} |")  # fmt: skip
    return 0


if __name__ == "__main__":
    run(main)
