"""Fit the mapping reserve's cost model (``flight_sw.anytime.mapping_cost_s``) on tuning pairs; check it held-out.

    taskset -c 1 .venv/bin/python bench/fit_mapping_cost.py --seeds 0 1 --check-seeds 1000 1001

The flight v2 flow keeps, before its DEM sweeps, a reserve for the stages that map the DEM afterwards
(``MAPPING_STAGES``: georef, grid, slope, shading slope, hazard, sites)::

    t = (MAP_IMAGE_S n_image + MAP_COVERED_S n_covered + MAP_CELLS_S n_cells) / REF_PIXELS

with ``n_covered`` the overlap's pixels and ``n_cells`` the world grid's size as the pipeline estimates them
before the DEM exists (:func:`flight_sw.anytime.grid_cells_estimate`). A model above the real cost leaves
the slow budgets' deadlines partly unused (the DEM sweep stops early to keep the reserve); one below it lets
the mapping run past the deadline. Each pair of the given tuning seeds (the four ``bench/eval_flight.py``
cases, rendered into ``--cache``) is run ``--runs`` times through ``fast`` on one core; the median CPU of its
mapping stages is fitted by non-negative least squares on the three counts. The table gives measured /
model per case (median, p90, max) for the shipped constants and for the fit, on the fitted seeds and on
``--check-seeds`` (held-out: never fitted on).
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from _cli import out_dir, positive_int, run  # noqa: E402

CASES = ("vertical", "approach", "thesis_vertical", "thesis_approach")


def measure(run: Callable[[], Any], camera: Any, pose1: Any, runs: int) -> dict[str, Any]:
    """Run the pipeline ``runs`` times (``run()``); the planning counts of the pair and the median CPU s of its
    mapping stages and of every stage."""
    from flight_sw.anytime import MAPPING_STAGES, grid_cells_estimate
    from flight_sw.pipeline import PRESETS

    cpu, res = [], None
    stages: dict[str, list[float]] = {}
    for _ in range(runs):
        res = run()
        cpu.append(sum(float(res.timings[k]["cpu_s"]) for k in MAPPING_STAGES if k in res.timings))
        for k, v in res.timings.items():
            stages.setdefault(k, []).append(float(v["cpu_s"]))
    assert res is not None
    z = float(res.info.get("coverage_z_m", 0.0))
    return {
        "level": res.level,
        "n_image": int(res.covered.size),
        "n_covered": int(np.count_nonzero(res.covered)),
        "n_cells": int(grid_cells_estimate(camera, pose1, res.covered, z, PRESETS["fast"].cell_m)),
        "mapping_cpu_s": statistics.median(cpu),
        "planned_reserve_s": float(res.info.get("mapping_reserve_s", float("nan"))),
        "stage_cpu_s": {k: statistics.median(v) for k, v in stages.items()},
    }


def pair_costs(pair_dir: str, runs: int) -> dict[str, Any]:
    """:func:`measure` on one rendered pair, run as the flight process runs it."""
    from eval_flight import run_pair

    from flight_sw.pipeline import PRESETS
    from protocol.pairdir import read_pair

    pair = read_pair(pair_dir)
    return measure(lambda: run_pair(pair, PRESETS["fast"]), pair.camera, pair.poses[0], runs)


def synthetic_costs(size: int, runs: int) -> dict[str, Any]:
    """:func:`measure` on ``bench/bench_pipeline.py``'s seeded synthetic 600/300 m pair at ``size`` px: the
    rendered pairs are all 512^2, so only these tell the per-image term from the others."""
    from bench_pipeline import synthetic_pair

    from flight_sw.pipeline import run_pipeline

    cam, p1, p2, i1, i2, _ = synthetic_pair(size)

    def run() -> Any:
        return run_pipeline(i1, i2, p1, p2, cam, preset="fast", sun_elevation_deg=25.0, sun_azimuth_deg=135.0)

    return {"case": f"synthetic {size}px", **measure(run, cam, p1, runs)}


def collect(seeds: list[int], cases: list[str], cache: Path, runs: int, out: Path) -> list[dict[str, Any]]:
    """Every pair's costs (cached in ``out``, one JSON line per pair, so a rerun measures only what is new)."""
    from eval_flight import render_case

    done: dict[str, dict[str, Any]] = {}
    if out.is_file():
        for line in out.read_text().splitlines():
            r = json.loads(line)
            if "stage_cpu_s" in r:  # costs from before the per-stage times were kept are measured again
                done[r["pair_dir"]] = r
    rows = []
    todo = [(c, s) for c in cases for s in seeds]
    for i, (c, s) in enumerate(todo, 1):
        entries = render_case(c, s, cache)
        for e in entries:
            if e["pair_dir"] not in done:
                r = {"case": c, "seed": s, "altitude_m": e["altitude_m"], "pair_dir": e["pair_dir"]}
                r.update(pair_costs(e["pair_dir"], runs))
                with out.open("a") as f:
                    f.write(json.dumps(r) + "\n")
                done[e["pair_dir"]] = r
            rows.append(done[e["pair_dir"]])
        print(f"fit_mapping_cost: {c} seed {s} ({i}/{len(todo)}): {len(entries)} pairs", file=sys.stderr, flush=True)
    return rows


def design(rows: list[dict[str, Any]]) -> np.ndarray:
    from flight_sw.anytime import REF_PIXELS

    return np.array([[r["n_image"], r["n_covered"], r["n_cells"]] for r in rows], float) / REF_PIXELS


def ratio_table(rows: list[dict[str, Any]], coef: np.ndarray, label: str) -> list[str]:
    """measured / model per case: median, p90, max."""
    X, y = design(rows), np.array([r["mapping_cpu_s"] for r in rows])
    ratio = y / (X @ coef)
    lines = []
    for c in [*CASES, *sorted({r["case"] for r in rows} - set(CASES)), "all"]:
        sel = np.array([c in ("all", r["case"]) for r in rows])
        if sel.any():
            q = ratio[sel]
            lines.append(
                f"| {label} | {c} | {sel.sum()} | {np.median(q):.2f} | {np.percentile(q, 90):.2f} | {q.max():.2f} |"
            )
    return lines


def stage_table(rows: list[dict[str, Any]]) -> str:
    """The pipeline's fixed stage costs (``REFINE_S``, the shadow stage, the gates after the slope fit) against
    the CPU the stages took on ``rows``, scaled to 512^2 as the pipeline scales them: median, p90, max."""
    from flight_sw.anytime import AFTER_SLOPE_S, REF_PIXELS, REFINE_S, SHADING_SLOPE_S, SHADOW_BASE_S, WALL_CUE_S

    groups = {
        "pose_refine": (("pose_refine",), REFINE_S),
        "shadow": (("shadow",), SHADOW_BASE_S + WALL_CUE_S),
        "shading_slope": (("shading_slope",), SHADING_SLOPE_S),
        "hazard + sites": (("hazard", "sites"), AFTER_SLOPE_S),
    }
    lines = ["| stage(s) | constant s | measured CPU s median | p90 | max |", "|---|---:|---:|---:|---:|"]
    for name, (keys, const) in groups.items():
        v = np.array([sum(r["stage_cpu_s"].get(k, 0.0) for k in keys) * REF_PIXELS / r["n_image"] for r in rows])
        lines.append(f"| {name} | {const:.4f} | {np.median(v):.4f} | {np.percentile(v, 90):.4f} | {v.max():.4f} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    from scipy.optimize import nnls

    from flight_sw.anytime import MAP_CELLS_S, MAP_COVERED_S, MAP_IMAGE_S
    from ground_sim.seeds import HELD_OUT_SEEDS, TUNING_SEEDS

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1], help="tuning seeds to fit on")
    ap.add_argument("--check-seeds", type=int, nargs="*", default=[], help="held-out seeds to check the fit on")
    ap.add_argument("--cases", nargs="+", default=list(CASES), choices=CASES)
    ap.add_argument("--runs", type=positive_int, default=3)
    ap.add_argument("--sizes", type=int, nargs="*", default=[], help="also check synthetic pairs of these sizes (px)")
    ap.add_argument("--cache", default="/tmp/flight_eval_cache")
    ap.add_argument(
        "--out", type=out_dir, default="out/fit_mapping_cost", help="per-pair costs (JSON lines) are kept here"
    )
    args = ap.parse_args(argv)
    bad = [s for s in args.seeds if s not in TUNING_SEEDS]
    if bad:
        ap.error(f"--seeds {bad}: not tuning seeds ({TUNING_SEEDS[0]}-{TUNING_SEEDS[-1]}); fit on tuning seeds only")
    bad = [s for s in args.check_seeds if s not in HELD_OUT_SEEDS]
    if bad:
        ap.error(f"--check-seeds {bad}: not held-out seeds")
    try:
        import cv2

        cv2.setNumThreads(1)
    except ImportError:
        pass
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    cache = Path(args.cache)
    fit_rows = collect(args.seeds, args.cases, cache, args.runs, out / "costs.jsonl")
    X, y = design(fit_rows), np.array([r["mapping_cpu_s"] for r in fit_rows])
    coef, _ = nnls(X, y)
    shipped = np.array([MAP_IMAGE_S, MAP_COVERED_S, MAP_CELLS_S])
    print(f"pairs fitted: {len(fit_rows)} (seeds {args.seeds})")
    print(f"shipped: MAP_IMAGE_S={shipped[0]:.3f} MAP_COVERED_S={shipped[1]:.3f} MAP_CELLS_S={shipped[2]:.3f}")
    print(f"fit:     MAP_IMAGE_S={coef[0]:.3f} MAP_COVERED_S={coef[1]:.3f} MAP_CELLS_S={coef[2]:.3f}")
    print()
    print("| model | case | pairs | measured / model median | p90 | max |")
    print("|---|---|---:|---:|---:|---:|")
    lines = ratio_table(fit_rows, shipped, "shipped, fitted seeds") + ratio_table(fit_rows, coef, "fit, fitted seeds")
    if args.check_seeds:
        check = collect(args.check_seeds, args.cases, cache, args.runs, out / "costs.jsonl")
        lines += ratio_table(check, shipped, "shipped, held-out") + ratio_table(check, coef, "fit, held-out")
    if args.sizes:
        synth = [synthetic_costs(n, args.runs) for n in args.sizes]
        lines += ratio_table(synth, shipped, "shipped, synthetic") + ratio_table(synth, coef, "fit, synthetic")
    print("\n".join(lines))
    print()
    print(stage_table(fit_rows))
    (out / "fit.json").write_text(
        json.dumps({"seeds": args.seeds, "coef": coef.tolist(), "shipped": shipped.tolist()}, indent=1) + "\n"
    )
    return 0


if __name__ == "__main__":
    run(main)
