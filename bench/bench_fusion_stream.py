"""Fusion over a whole descent as the HIL streams it (issue 10): each Result fused, against the pair alone.

    .venv/bin/python bench/bench_fusion_stream.py --set tuning --n-seeds 10       # choose the fusion knobs
    .venv/bin/python bench/bench_fusion_stream.py --set held-out --n-seeds 6      # report
    .venv/bin/python bench/bench_fusion_stream.py --set tuning --fusion weight=0.5 p_accumulate=0.99

For each case of ``bench/eval_flight.py`` (``--cases``; the default scene and the library's thesis scene,
vertical and approach) and scene seed, the case's pairs are taken from the highest to the lowest, as the
ground streams a descent. Each pair runs through the ``fast`` pipeline and its grid is fused into the map of
the pairs before it (:mod:`flight_sw.fusion`, with the settings the flight process uses:
``fusion.params_for``, then ``--fusion`` overrides). Every Result is scored where the ground scores it: at
its own pair's reference pixels, against that pair's truth, on the pixels the pair covers
(``studies.multiframe.score_grid``: a world-grid state read at each pixel's true ground point; unknown and
outside count as not safe). "alone" is the pair's own grid, what a Result reports without fusion.

Per case: pixel FP % (median / worst, Results over 1 %), CDI % (median), and the change fusion makes per
Result (FP: largest increase and how many Results rise by more than 0.1 points; CDI: median and smallest),
and the CPU time of fusing each Result and reading out its map (median; one thread).
Seeds come from ``ground_sim.seeds``: tune on ``tuning``, quote ``held-out``; worst cases beside medians.
Pipeline grids are cached per stream in ``--grids`` so that fusion settings can be compared quickly, keyed by
the case, seed, settings, the render cache and the code of flight_sw, ground_sim and protocol.

``--levels`` runs the stream's pairs at the given levels, position by position (cycled), as a slow
flight processor delivers them: ``image_only`` (the nominal-slowdown trick of the tests: reserves that
outgrow the deadline), ``coarse`` (the full-resolution DEM reported incomplete, as when the deadline
stops its sweep), ``full``. The snapdragon801 approach descent of docs/hil.md (stop 32) delivered
``image_only,image_only,coarse,full,full,coarse,coarse,full``.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import hashlib
import json
import math
import os
import pickle
import statistics
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from _cli import out_file, positive_int, run, write_out  # noqa: E402

DEFAULT_CASES = ("vertical", "approach", "thesis_vertical", "thesis_approach")


LEVELS = ("image_only", "coarse", "full")


@contextlib.contextmanager
def dense_incomplete(on: bool) -> Iterator[None]:
    """While ``on``: the pipeline's full-resolution DEM comes back incomplete, so a pair stops at ``coarse``."""
    import flight_sw.pipeline as pl

    real = pl.dense_dem
    if on:
        pl.dense_dem = lambda *a, **k: dataclasses.replace(real(*a, **k), complete=False)  # type: ignore[assignment]
    try:
        yield
    finally:
        pl.dense_dem = real


def grids_file(
    grids: Path, key: str, cache: Path, levels: tuple[str, ...] = ("full",), set_param: tuple[str, ...] = ()
) -> Path:
    """Where one stream's pipeline grids are kept: a name per case and seed (``key``), level pattern, setting, render
    cache and code, so that no other run's grids stand in for them."""
    from studies.executor import code_fingerprint

    tag = "" if set(levels) == {"full"} else "-" + "-".join(x[0] for x in levels)  # i / c / f per position
    tag += "".join(f"-{kv}" for kv in set_param)  # a variant's grids never stand in for another's
    # nor another code's or model's: a refitted P(safe) model changes every grid (stop 41); nor another render's:
    # the grids of one --cache stood in for another's, and a changed renderer's pairs were never rendered (QA 74)
    where = hashlib.sha256(str(cache.resolve()).encode()).hexdigest()[:8]
    tag += f"-{code_fingerprint(['flight_sw', 'ground_sim', 'protocol'])}-{where}"
    return grids / f"{key}{tag}.pkl"


def stream_results(
    case: str,
    seed: int,
    cache: Path,
    grids: Path,
    levels: tuple[str, ...] = ("full",),
    set_param: tuple[str, ...] = (),
) -> list[dict[str, Any]]:
    """The case's pairs, highest first, each with its pipeline grid at ``levels[k % len]`` (cached in ``grids``),
    from ``fast`` with the ``set_param`` (``K=V``) overrides."""
    from bench_multiframe import preset_with
    from eval_flight import case_key, render_case

    from flight_sw.pipeline import run_pipeline
    from ground_sim.gridscore import scored_area
    from protocol.pairdir import read_pair
    from studies.multiframe import world_of

    preset = preset_with("fast", set_param)
    f = grids_file(grids, case_key(case, seed), cache, levels, set_param)
    if f.is_file():
        return list(pickle.loads(f.read_bytes()))
    out = []
    for k, e in enumerate(sorted(render_case(case, seed, cache), key=lambda e: -e["altitude_m"])):
        pair = read_pair(Path(e["pair_dir"]))
        want = levels[k % len(levels)]
        slow = {"deadline_s": 10.0, "time_scale": 1e5} if want == "image_only" else {}
        with dense_incomplete(want == "coarse"):
            r = run_pipeline(  # with the sun, as a HIL Frame carries it (the shading slope needs its azimuth)
                pair.images[0],
                pair.images[-1],
                pair.poses[0],
                pair.poses[-1],
                pair.camera,
                preset=preset,
                sun_elevation_deg=pair.sun.elevation_deg if pair.sun else None,
                sun_azimuth_deg=pair.sun.azimuth_deg if pair.sun else None,
                **slow,  # type: ignore[arg-type]
            )
        if r.level != want:
            raise RuntimeError(f"{e['pair_dir']}: asked for level {want}, the pipeline gave {r.level}")
        mask = scored_area(pair, world_of(pair))  # DESIGN.md's covered area, as `score` takes it (stop 65)
        out.append({"dir": e["pair_dir"], "alt": e["altitude_m"], "grid": r.grid, "params": r.params,
                    "info": r.info, "mask": mask, "level": r.level})  # fmt: skip
    grids.mkdir(parents=True, exist_ok=True)
    tmp = f.with_name(f"{f.name}.partial{os.getpid()}")  # concurrent runs never share a temporary file
    tmp.write_bytes(pickle.dumps(out))
    tmp.replace(f)
    return out


def score_stream(results: list[dict[str, Any]], overrides: dict[str, Any]) -> list[dict[str, float]]:
    """Fuse the stream in order; per Result the pair alone and the fused map, scored at that pair."""
    from flight_sw.fusion import FusionParams, fuse, params_for, to_hazard_grid
    from protocol.pairdir import read_pair
    from studies.multiframe import pixel_world, score_grid

    fm = None
    rows = []
    for r in results:
        pair = read_pair(Path(r["dir"]))
        xy = pixel_world(pair)
        prm = dataclasses.replace(params_for(r["params"], r["info"], FusionParams()), **overrides)
        t0 = time.thread_time()  # what the flight process spends per Result on the map
        fm = fuse(fm, r["grid"], prm, level=r.get("level", "full"))
        fused_grid = to_hazard_grid(fm, prm)
        fuse_ms = 1000.0 * (time.thread_time() - t0)
        alone = score_grid(pair, r["grid"], r["mask"], xy)
        fused = score_grid(pair, fused_grid, r["mask"], xy)
        rows.append({"alt": r["alt"], "level": r.get("level", "full"), "fp": alone["fp"], "cdi": alone["cdi"],
                     "fp_f": fused["fp"], "cdi_f": fused["cdi"], "fuse_ms": fuse_ms})  # fmt: skip
    return rows


def summary(rows: list[dict[str, float]]) -> dict[str, float]:
    dfp = [r["fp_f"] - r["fp"] for r in rows]
    dcdi = [r["cdi_f"] - r["cdi"] for r in rows]
    dcdi_full = [r["cdi_f"] - r["cdi"] for r in rows if r.get("level", "full") == "full"] or [math.nan]
    return {
        "results": len(rows),
        "fp_med": statistics.median(r["fp"] for r in rows),
        "fp_worst": max(r["fp"] for r in rows),
        "fp_over1": sum(r["fp"] > 1.0 for r in rows),
        "cdi_med": statistics.median(r["cdi"] for r in rows),
        "fp_f_med": statistics.median(r["fp_f"] for r in rows),
        "fp_f_worst": max(r["fp_f"] for r in rows),
        "fp_f_over1": sum(r["fp_f"] > 1.0 for r in rows),
        "cdi_f_med": statistics.median(r["cdi_f"] for r in rows),
        "dfp_max": max(dfp),
        "dfp_over01": sum(d > 0.1 for d in dfp),
        "dcdi_med": statistics.median(dcdi),
        "dcdi_min": min(dcdi),
        "full": sum(r.get("level", "full") == "full" for r in rows),
        "dcdi_full_med": statistics.median(dcdi_full),
        "dcdi_full_min": min(dcdi_full),
        "fuse_ms_med": statistics.median(r.get("fuse_ms", math.nan) for r in rows),
    }


def table(per_case: dict[str, dict[str, float]]) -> str:
    out = [
        "| case | Results | alone: FP % med / worst (> 1 %) | alone: CDI % med | fused: FP % med / worst (> 1 %) "
        "| fused: CDI % med | FP change: max (Results > +0.1) | CDI change: med / min "
        "| full-level Results: CDI change med / min | fuse + map CPU ms med |",
        "|---|---:|---|---:|---|---:|---|---|---|---:|",
    ]
    for case, s in per_case.items():
        out.append(
            f"| {case} | {s['results']} | {s['fp_med']:.2f} / {s['fp_worst']:.2f} ({s['fp_over1']}) "
            f"| {s['cdi_med']:.1f} | {s['fp_f_med']:.2f} / {s['fp_f_worst']:.2f} ({s['fp_f_over1']}) "
            f"| {s['cdi_f_med']:.1f} | {s['dfp_max']:+.2f} ({s['dfp_over01']}) "
            f"| {s['dcdi_med']:+.1f} / {s['dcdi_min']:+.1f} "
            f"| {s['dcdi_full_med']:+.1f} / {s['dcdi_full_min']:+.1f} ({s['full']}) | {s['fuse_ms_med']:.1f} |"
        )
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--set", choices=("tuning", "held-out"), default="tuning")
    ap.add_argument("--n-seeds", type=positive_int, default=6)
    ap.add_argument("--cases", nargs="+", default=list(DEFAULT_CASES))
    ap.add_argument("--cache", default="/tmp/flight_eval_cache", help="rendered pairs (shared with eval_flight)")
    ap.add_argument("--grids", help="cached pipeline grids per stream (default: CACHE_fusion_grids)")
    ap.add_argument("--fusion", nargs="*", default=[], metavar="K=V", help="FusionParams fields to override")
    ap.add_argument("--json", type=out_file, help="write per-Result rows and the summary here")
    ap.add_argument("--levels", default="full", help="comma list of pipeline levels per stream position, cycled")
    ap.add_argument("--set-param", nargs="*", default=[], metavar="K=V", help="fields of the fast preset to override")
    args = ap.parse_args(argv)
    levels = tuple(x.strip() for x in args.levels.split(","))
    if not levels or any(x not in LEVELS for x in levels):
        ap.error(f"--levels: each must be one of {LEVELS}, got {args.levels!r}")

    from eval_flight import CASES

    from flight_sw.fusion import FusionParams
    from ground_sim.seeds import HELD_OUT_SEEDS, TUNING_SEEDS

    bad = [c for c in args.cases if c not in CASES]
    if bad:
        ap.error(f"unknown case(s) {bad}; known: {sorted(CASES)}")
    from bench_multiframe import fusion_overrides, preset_with

    try:  # a bad --fusion ends here with one line, not after the first stream's renders
        overrides = fusion_overrides(args.fusion)
        FusionParams(**overrides).validate()
    except ValueError as exc:
        ap.error(f"--fusion: {exc}")
    try:  # and so does a bad --set-param
        preset_with("fast", args.set_param)
    except (ValueError, AttributeError) as exc:
        ap.error(f"--set-param: {exc}")
    seeds = list((TUNING_SEEDS if args.set == "tuning" else HELD_OUT_SEEDS)[: args.n_seeds])
    streams = [(c, s) for c in args.cases for s in seeds]
    rows: dict[str, list[dict[str, float]]] = {c: [] for c in args.cases}
    t0 = time.perf_counter()
    for k, (case, seed) in enumerate(streams, 1):
        res = stream_results(
            case,
            seed,
            Path(args.cache),
            Path(args.grids or f"{args.cache.rstrip('/')}_fusion_grids"),
            levels,
            tuple(args.set_param),
        )
        rows[case] += [{"seed": seed, **r} for r in score_stream(res, overrides)]
        print(f"[{k}/{len(streams)}] {case} seed {seed}: {len(res)} pairs ({time.perf_counter() - t0:.0f} s)",
              file=sys.stderr, flush=True)  # fmt: skip
    per_case = {c: summary(r) for c, r in rows.items() if r}
    per_case["all"] = summary([x for r in rows.values() for x in r])
    print(f"\nFusion over streamed descents, {args.set} seeds {seeds}, levels {','.join(levels)}, "
          f"overrides {overrides or 'none'}, fast {' '.join(args.set_param) or 'as shipped'}\n")  # fmt: skip
    print(table(per_case))
    if args.json:
        write_out(args.json, json.dumps({"seeds": seeds, "overrides": overrides, "summary": per_case,
                                               "rows": rows}, indent=1))  # fmt: skip
    return 0


if __name__ == "__main__":
    run(main)
