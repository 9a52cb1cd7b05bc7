"""Benchmark: seconds to render one 512x512 frame with ground truth, one core.

Median of N runs per altitude class (nadir 1000/300/100/50 m, oblique 2400/1200/250 m of
the approach scenario), default scene; wall-clock median/min/max and the median CPU time
(time.process_time, less sensitive to other jobs on a shared machine), peak RSS growth, and how much
coarser than GSD/2 the terrain raster is (the raster cap, docs/scenes.md). Usage:
    .venv/bin/python bench/bench_render.py [--repeat 5] [--max-raster-cells N] [--out table.md]
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("MKL_NUM_THREADS", "1")

import argparse
import resource
import statistics
import time

import cv2
import numpy as np
from _cli import out_file, positive_int, run, unknown
from pages import write_page

from ground_sim.geometry import look_rotation
from ground_sim.render import DEFAULT_RASTER, MAX_CELLS, RASTERS, render_view
from ground_sim.scene import load_scene
from protocol.pairdir import Camera, Pose, Sun

CASES = [
    ("nadir 1000 m", (0, 0, 1000), 0.0),
    ("nadir 300 m", (0, 0, 300), 0.0),
    ("nadir 100 m", (0, 0, 100), 0.0),
    ("nadir 50 m", (0, 0, 50), 0.0),
    ("oblique 49deg 2400 m", (0, -2400, 2400), 49.0),
    ("oblique 49deg 1200 m", (0, -1200, 1200), 49.0),
    ("oblique 40deg 250 m", (0, -250, 250), 40.0),
]


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeat", type=positive_int, default=5)
    ap.add_argument(
        "--out",
        type=out_file,
        default=None,
        help="write the table into this page (its other text kept: bench/pages.py)",
    )
    ap.add_argument("--max-raster-cells", type=positive_int, default=MAX_CELLS)
    ap.add_argument("--raster", choices=list(RASTERS), default=DEFAULT_RASTER)
    ap.add_argument("--cases", nargs="*", default=None, help="only these case names (default: all)")
    args = ap.parse_args()
    if args.cases:  # a name that matches none would leave an empty table (names with spaces: quote each)
        unknown("--cases", args.cases, [name for name, _, _ in CASES])
    mc = args.max_raster_cells
    cv2.setNumThreads(1)
    scene = load_scene("default", 0)
    cam = Camera.thesis()
    rows = []
    for name, pos, tilt in CASES:
        if args.cases and name not in args.cases:
            continue
        pose = Pose(np.asarray(pos, dtype=np.float64), look_rotation(tilt))
        rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        render_view(scene, cam, pose, Sun(135, 25), seed=0, max_cells=mc, raster=args.raster)  # warm-up
        rss = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - rss0) / 1024.0  # MiB (peak growth; 0 if lower)
        ts, cs = [], []
        for k in range(args.repeat):
            t0, c0 = time.perf_counter(), time.process_time()
            v = render_view(scene, cam, pose, Sun(135, 25), seed=k, max_cells=mc, raster=args.raster)
            ts.append(time.perf_counter() - t0)
            cs.append(time.process_time() - c0)
        rows.append(
            (
                name,
                statistics.median(ts),
                min(ts),
                max(ts),
                statistics.median(cs),
                v.info["raster_shape"],
                v.info["raster_cell_m"],
                v.info["raster_cell_over_target"],
                rss,
            )
        )
        print(
            f"{name:24s} median {rows[-1][1]:.2f} s  (min {min(ts):.2f}, max {max(ts):.2f}, "
            f"cpu median {rows[-1][4]:.2f}) raster {v.info['raster_shape']} "
            f"cell {v.info['raster_cell_m']:.3f} m = {v.info['raster_cell_over_target']:.2f} x GSD/2, "
            f"peak RSS +{rss:.0f} MiB",
            flush=True,
        )
    if args.out:
        lines = [
            "| case | median s | min s | max s | CPU median s | raster (rows x cols) | cell m | cell / (GSD/2) "
            "| peak RSS growth MiB |",
            "|---|---|---|---|---|---|---|---|---|",
        ]
        lines += [
            f"| {n} | {m:.2f} | {lo:.2f} | {hi:.2f} | {cp:.2f} | {s[0]}x{s[1]} | {c:.3f} | {r:.2f} | {g:.0f} |"
            for n, m, lo, hi, cp, s, c, r, g in rows
        ]
        print(write_page(args.out, "\n".join(lines), "bench_render.py"))


if __name__ == "__main__":
    run(main)
