"""Does the rendered slope/roughness truth miss hazards? Frame 0's truth recomputed on a finer raster (review 66d).

    .venv/bin/python bench/truth_scale.py --cases approach thesis_approach --set held-out --n-seeds 3
    .venv/bin/python bench/truth_scale.py --cases vertical --seeds 1000 --altitudes 50 150 500 --json out.json
    .venv/bin/python bench/truth_scale.py --cases approach --seeds 1000 --altitudes 1200 --relief image

The renderer takes slope and roughness truth (DESIGN.md: LSQ plane over the 3 m lander footprint, unsafe at
>= 15 deg; |z - plane| at the point, unsafe at >= 0.30 m) from its view raster while that holds the disk, else
(since stop 67, ``RENDER_VERSION`` 3) from a world-aligned raster of ``truth_cell_m`` (0.5 m on every 512 px table
view: :func:`ground_sim.truth.footprint_cell`, :func:`~ground_sim.truth.footprint_planes`). Before, on oblique
views from >= 1000 m the view raster's cell was 1.5-3.4 m and the plane fell back to a 3x3 block (a 5-10 m
window). This bench recomputes frame 0's truth per scored pixel from the scene itself on a raster of ``--cell``
(default 0.25 m: how much the stored truth's cell still misses), with the same exact-disk plane, combined with the
pair's true shadow as the renderer does (``hazard_layers``: max of slope/15 deg, roughness/0.30 m, shadow; unsafe
at >= 1), and scores the flight software's hazard map (run as ``bench/eval_flight.py`` runs it, on its render
cache) against both truths over the same scored area (``ground_sim.gridscore.scored_area``).

``--relief image`` band-limits the fine raster to the image's own finest raster (wavelength >= GSD_min, as the
tiles at GSD_min/2 hold) while keeping the fine cell and exact disk: it separates "the plane's window was too
wide" from "relief finer than any pixel".

As a check, the rendered truth is recomputed by the renderer's rule at the same points (:func:`stored_truth`):
``repro %`` is the share of scored pixels where that agrees with the stored ``gt_hazard`` on unsafe/safe.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))
from _cli import out_file, positive_int, run, unknown  # noqa: E402
from eval_flight import CASES, check_altitudes, render_case, run_pair  # noqa: E402

from ground_sim.truth import (  # noqa: E402
    ROUGH_LIMIT_M,
    SLOPE_LIMIT_DEG,
    footprint_planes,
    hazard_layers,
)


def fine_layers(
    scene: Any, X: np.ndarray, Y: np.ndarray, cell: float, min_wavelength: float | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """(z, slope deg, |z - plane| m, raster cells built) at the ground points (X, Y): the renderer's own
    :func:`ground_sim.truth.footprint_planes` on ``scene``'s heights at ``cell``, band-limited to
    ``min_wavelength`` if given."""
    built = [0]

    def heights(x0: float, y0: float, c: float, nx: int, ny: int) -> np.ndarray:
        built[0] += nx * ny
        return scene.height_raster(x0, y0, c, nx, ny, min_wavelength)

    z, a, b, c = footprint_planes(heights, X, Y, cell)
    return z, np.degrees(np.arctan(np.hypot(b, c))), np.abs(z - a), built[0]


def stored_truth(scene: Any, view: dict[str, Any], X: np.ndarray, Y: np.ndarray, shadow: np.ndarray) -> np.ndarray:
    """The rendered slope/roughness truth again at (X, Y) by the renderer's rule
    (:func:`studies.evaluate.recorded_truth_planes`), combined with ``shadow``: the check that the scene and the
    rule are reproduced."""
    from studies.evaluate import recorded_truth_planes

    planes = recorded_truth_planes(scene, view, X, Y)
    if planes is None:
        raise SystemExit("truth_scale: the pair does not record its view raster (render it with this renderer)")
    return hazard_layers(*planes, shadow)


def scene_of(case: str, seed: int) -> Any:
    from ground_sim.scene import Scene, load_scene_params

    traj, spec, _ = CASES[case]
    return Scene(load_scene_params(spec, traj), seed)


def pct(m: np.ndarray, n: int) -> float:
    return 100.0 * float(np.count_nonzero(m)) / max(n, 1)


def measure(entry: dict[str, Any], preset: Any, cell_opt: float, relief: str, scene: Any) -> dict[str, Any]:
    """One pair: both truths over the scored area, and the detector's FP / CDI against each."""
    from ground_sim import scoring
    from ground_sim.gridscore import scored_area
    from protocol.pairdir import read_pair
    from studies.multiframe import world_of

    t0 = time.perf_counter()
    pair = read_pair(entry["pair_dir"])
    view = pair.meta["render"][0]
    vcell, gsd = float(view["raster_cell_m"]), float(view["gsd_min_m"])
    cell = float(cell_opt)
    world = world_of(pair)
    area = scored_area(pair, world)
    N = int(area.sum())
    X, Y = world[..., 0][area], world[..., 1][area]
    shadow = np.asarray(pair.truth["shadow"], bool)[area]
    rend = np.asarray(pair.truth["hazard"], np.float64)[area]
    t1 = time.perf_counter()
    _, slope, rough, built = fine_layers(scene, X, Y, cell, gsd if relief == "image" else None)
    fine_v = np.maximum(
        np.maximum(np.clip(slope / SLOPE_LIMIT_DEG, 0, 1), np.clip(rough / ROUGH_LIMIT_M, 0, 1)), shadow
    )  # hazard_layers' combination, on the fine plane
    t2 = time.perf_counter()
    repro = stored_truth(scene, view, X, Y, shadow)
    t3 = time.perf_counter()
    res = run_pair(pair, preset)
    t4 = time.perf_counter()
    fine = np.full(area.shape, np.nan, np.float32)
    fine[area] = fine_v
    ru, fu = rend >= 1.0, fine_v >= 1.0
    scores = {}
    for name, truth in (("rend", pair.truth["hazard"]), ("fine", fine)):
        c = scoring.confusion(res.hazard, truth, area)
        scores[name] = c
    called = ~scoring.unsafe_estimate(res.hazard)[area]
    to_unsafe = ~ru & fu
    return {
        **entry,
        "view_cell_m": vcell,
        "gsd_min_m": gsd,
        "fine_cell_m": cell,
        "relief": relief,
        "scored_px": N,
        "fine_cells": built,
        "haz_rend": pct(ru, N),
        "haz_fine": pct(fu, N),
        "haz_rend_check": scores["rend"]["hazards_pct"],
        "u2s": pct(ru & ~fu, N),  # rendered unsafe, fine safe
        "s2u": pct(to_unsafe, N),  # rendered safe, fine unsafe
        "s2u_slope": pct(to_unsafe & (slope >= SLOPE_LIMIT_DEG), N),
        "s2u_rough": pct(to_unsafe & (rough >= ROUGH_LIMIT_M), N),
        "s2u_called": pct(to_unsafe & called, N),  # new hazards the detector calls safe: FP the figure misses
        "repro": 100.0 - pct((repro >= 1.0) != ru, N),
        "fp_rend": scores["rend"]["fp"],
        "fp_fine": scores["fine"]["fp"],
        "cdi_rend": scores["rend"]["cdi"],
        "cdi_fine": scores["fine"]["cdi"],
        "t_read_s": t1 - t0,
        "t_fine_s": t2 - t1,
        "t_check_s": t3 - t2,
        "t_flight_s": t4 - t3,
        "t_total_s": t4 - t0,
    }


def _med(v: list[float]) -> float:
    return statistics.median(v) if v else math.nan


def table(rows: list[dict[str, Any]]) -> str:
    """Per (case, altitude): medians over the seeds, and the worst seed of each column (largest FP / flips, lowest
    CDI, each on its own)."""
    out = [
        "| case | alt pair | seeds | view cell m | fine cell m | hazards % rend / fine | flips % u->s / s->u "
        "| s->u % worst | FP % rend / fine (med) | FP % rend / fine (worst) | CDI % rend / fine (med) "
        "| CDI % rend / fine (worst) | repro % min | s / pair med / max |",
        "|---|---|---:|---:|---:|---|---|---:|---|---|---|---|---:|---|",
    ]
    keys = sorted({(r["case"], r["altitude_m"]) for r in rows}, key=lambda k: (list(CASES).index(k[0]), k[1]))
    for case, alt in keys:
        rs = [r for r in rows if r["case"] == case and r["altitude_m"] == alt]
        m = {k: _med([r[k] for r in rs]) for k in rs[0] if isinstance(rs[0][k], float)}
        w = {k: max(r[k] for r in rs) for k in ("fp_rend", "fp_fine", "s2u", "t_total_s")}
        out.append(
            f"| {case} | {2 * alt}/{alt} | {len(rs)} | {m['view_cell_m']:.2f} | {m['fine_cell_m']:.2f} "
            f"| {m['haz_rend']:.1f} / {m['haz_fine']:.1f} | {m['u2s']:.2f} / {m['s2u']:.2f} | {w['s2u']:.2f} "
            f"| {m['fp_rend']:.2f} / {m['fp_fine']:.2f} | {w['fp_rend']:.2f} / {w['fp_fine']:.2f} "
            f"| {m['cdi_rend']:.1f} / {m['cdi_fine']:.1f} "
            f"| {min(r['cdi_rend'] for r in rs):.1f} / {min(r['cdi_fine'] for r in rs):.1f} "
            f"| {min(r['repro'] for r in rs):.1f} | {m['t_total_s']:.1f} / {w['t_total_s']:.1f} |"
        )
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", nargs="+", default=["approach", "thesis_approach"], choices=list(CASES))
    ap.add_argument("--set", choices=("tuning", "held-out"), default="held-out")
    ap.add_argument("--n-seeds", type=positive_int, default=3)
    ap.add_argument("--seeds", type=int, nargs="*", help="explicit seeds (overrides --set/--n-seeds)")
    ap.add_argument("--altitudes", type=int, nargs="*", help="only these (lower-frame) altitudes")
    ap.add_argument("--preset", default="fast")
    ap.add_argument("--cell", type=float, default=0.25, help="fine raster cell m (default 0.25)")
    ap.add_argument(
        "--relief",
        choices=("fine", "image"),
        default="fine",
        help="fine: all relief the fine raster holds; image: band-limited to the image's finest raster (GSD_min)",
    )
    ap.add_argument("--cache", default="/tmp/flight_eval_cache")
    ap.add_argument("--json", type=out_file, help="write the rows here (JSON lines, appended per pair)")
    ap.add_argument("--from-json", nargs="+", metavar="FILE", help="print the table of these rows; run nothing")
    args = ap.parse_args(argv)
    if args.from_json:
        print(table([json.loads(ln) for f in args.from_json for ln in Path(f).read_text().splitlines() if ln]))
        return 0

    from flight_sw.pipeline import PRESETS

    unknown("--preset", [args.preset], PRESETS)
    check_altitudes(args.cases, args.altitudes)  # one that matches no pair would leave an empty table
    cv2.setNumThreads(1)
    from bench_multiframe import preset_with

    from ground_sim.seeds import HELD_OUT_SEEDS, TUNING_SEEDS

    seeds = args.seeds or list((TUNING_SEEDS if args.set == "tuning" else HELD_OUT_SEEDS)[: args.n_seeds])
    preset = preset_with(args.preset, [])
    cache = Path(args.cache)
    rows = []
    for case in args.cases:
        for seed in seeds:
            scene = scene_of(case, seed)
            for e in render_case(case, seed, cache, args.altitudes):
                r = measure(e, preset, args.cell, args.relief, scene)
                rows.append(r)
                print(
                    f"{case} s{seed} {2 * r['altitude_m']}/{r['altitude_m']}: cell {r['view_cell_m']:.2f} -> "
                    f"{r['fine_cell_m']:.2f} m, haz {r['haz_rend']:.1f}/{r['haz_fine']:.1f} %, flips "
                    f"{r['u2s']:.2f}/{r['s2u']:.2f} % (slope {r['s2u_slope']:.2f}, rough {r['s2u_rough']:.2f}), "
                    f"FP {r['fp_rend']:.2f}/{r['fp_fine']:.2f} %, CDI {r['cdi_rend']:.1f}/{r['cdi_fine']:.1f} %, "
                    f"repro {r['repro']:.1f} %, {r['fine_cells'] / 1e6:.1f} Mcells, {r['t_total_s']:.1f} s "
                    f"(fine {r['t_fine_s']:.1f}, flight {r['t_flight_s']:.1f})",
                    file=sys.stderr,
                    flush=True,
                )
                if args.json:
                    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
                    with open(args.json, "a") as fh:
                        fh.write(json.dumps(r, default=float) + "\n")
    print(table(rows))
    return 0


if __name__ == "__main__":
    run(main)
