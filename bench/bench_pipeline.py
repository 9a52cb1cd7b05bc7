"""Benchmark the flight pipeline on one core: median stage times, peak memory growth, DEM accuracy.

    .venv/bin/python bench/bench_pipeline.py [--pair DIR] [--size 512] [--runs 7] [--presets fast thesis]

Without ``--pair`` it renders a seeded synthetic 600 m -> 300 m vertical pair
(textured terrain with craters, tests/synthetic.py). OpenCV runs single-threaded
and the process is pinned to one CPU. Timings are medians over ``--runs``. The pipeline is told a sun
(``--sun``, or the pair's), as HIL frames tell it, so the shading-slope stage is timed too.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
import tracemalloc
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

from _cli import out_file, positive_int, run, unknown, write_out  # noqa: E402


def synthetic_pair(size: int, seed: int = 0, spots_per_km2: float = 2000.0):
    from synthetic import make_pair

    craters = [(-40.0, 25.0, 30.0, 6.0), (35.0, -20.0, 18.0, 3.5), (5.0, 5.0, 8.0, 1.2), (-10.0, -45.0, 45.0, 8.0)]

    def height(x, y):
        z = 0.02 * x - 0.015 * y
        for cx, cy, r, d in craters:
            z = z - d * np.clip(1 - ((x - cx) ** 2 + (y - cy) ** 2) / r**2, 0, None)
        return z

    cam, p1, p2, i1, i2, z = make_pair(size, 600.0, 300.0, height, seed=seed, spots_per_km2=spots_per_km2)
    return cam, p1, p2, i1, i2, z


def rss_mb() -> float:
    import psutil

    return psutil.Process().memory_info().rss / 2**20


class RssSampler:
    """Peak RSS over a block, sampled every millisecond from a thread (catches OpenCV's own buffers)."""

    def __enter__(self):
        import threading

        self.base = self.peak = rss_mb()
        self._stop = threading.Event()

        def loop():
            while not self._stop.is_set():
                self.peak = max(self.peak, rss_mb())
                self._stop.wait(0.001)

        self._t = threading.Thread(target=loop, daemon=True)
        self._t.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._t.join()
        self.peak = max(self.peak, rss_mb())


def ablation(i1, i2, p1, p2, cam, z) -> dict:
    """DEM error of preset variants; the >1 m tail measures the thesis's "squared pattern" blobs."""
    import dataclasses

    from flight_sw.pipeline import PRESETS, run_pipeline

    variants = {}
    for base in ("thesis", "fast"):
        for cost in ("ssd", "sad"):
            for pre in (False, True):
                for mask in (False, True):
                    variants[f"{base} {cost} prefilter={int(pre)} rocks_masked={int(mask)}"] = dataclasses.replace(
                        PRESETS[base], cost=cost, prefilter=pre, mask_rocks=mask
                    )
    for w in (4, 5, 8):
        variants[f"fast W={w}"] = dataclasses.replace(PRESETS["fast"], half_window=w)
    variants["fast step=0.25px"] = dataclasses.replace(PRESETS["fast"], disparity_step_px=0.25)
    variants["fast no coarse-to-fine"] = dataclasses.replace(PRESETS["fast"], coarse_to_fine=False)
    out = {}
    print("\nablation (one run each)")
    for name, prm in variants.items():
        t0 = time.perf_counter()
        res = run_pipeline(i1, i2, p1, p2, cam, preset=prm)
        dt = time.perf_counter() - t0
        e = res.elevation - z
        ok = np.isfinite(e)
        row = {
            "wall_s": dt,
            "mean_abs_m": float(np.abs(e[ok]).mean()),
            "p99_abs_m": float(np.percentile(np.abs(e[ok]), 99)),
            "frac_gt_1m": float((np.abs(e[ok]) > 1.0).mean()),
            "valid": res.valid_fraction,
        }
        out[name] = row
        print(
            f"  {name:45s} {dt:6.3f} s  mean|e| {row['mean_abs_m']:.3f} m  p99 {row['p99_abs_m']:.2f} m  "
            f">1m {row['frac_gt_1m']:.2%}  valid {row['valid']:.1%}"
        )
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--pair", help="pair directory (default: synthetic)")
    ap.add_argument("--size", type=positive_int, default=512)
    ap.add_argument("--runs", type=positive_int, default=7)
    ap.add_argument("--presets", nargs="+", default=["fast", "fast_v1", "thesis"])
    ap.add_argument("--json", type=out_file, help="write the summary here")
    ap.add_argument(
        "--sun",
        nargs=2,
        type=float,
        default=[135.0, 25.0],
        metavar=("AZ", "EL"),
        help="sun azimuth and elevation (deg) the pipeline is told, as HIL frames carry them (default 135 25; "
        "a --pair's own sun wins)",
    )
    ap.add_argument(
        "--ablation",
        action="store_true",
        help="also compare prefilter / rock masking / SAD vs SSD / window (DEM error only)",
    )
    ap.add_argument(
        "--check-reserves",
        action="store_true",
        help="exit 1 when a v2 preset's deadline reserve (flight_sw.anytime.reserve_table) is shorter than the "
        "median CPU time of the stages it must cover",
    )
    args = ap.parse_args(argv)
    from flight_sw.anytime import reserve_table
    from flight_sw.pipeline import PRESETS, run_pipeline

    unknown("--presets", args.presets, PRESETS)  # before the warm-up and every other preset's runs

    cv2.setNumThreads(1)
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[0]})

    if args.pair:
        from protocol.pairdir import read_pair

        pair = read_pair(args.pair)
        cam, (p1, p2), (i1, i2) = pair.camera, pair.poses, pair.images
        z = pair.truth.get("elevation")
        source = args.pair
        if pair.sun is not None:
            args.sun = [pair.sun.azimuth_deg, pair.sun.elevation_deg]
    else:
        cam, p1, p2, i1, i2, z = synthetic_pair(args.size)
        source = f"synthetic {args.size}px 600->300 m"
    sun = {"sun_azimuth_deg": args.sun[0], "sun_elevation_deg": args.sun[1]}
    run_pipeline(i1, i2, p1, p2, cam, preset="fast", **sun)  # warm-up (imports, allocator)
    summary = {"source": source, "runs": args.runs, "sun": args.sun, "presets": {}}
    short_any = False
    for preset in args.presets:
        walls, res = [], None
        stages: dict[str, list[tuple[float, float]]] = {}
        for _ in range(args.runs):
            t0 = time.perf_counter()
            res = run_pipeline(i1, i2, p1, p2, cam, preset=preset, **sun)
            walls.append(time.perf_counter() - t0)
            for k, v in res.timings.items():
                stages.setdefault(k, []).append((v["wall_s"], v["cpu_s"]))
        # memory on a separate run: tracemalloc slows allocation and would skew the timings
        res = None
        tracemalloc.start()
        with RssSampler() as mem:
            res = run_pipeline(i1, i2, p1, p2, cam, preset=preset, **sun)
        traced = tracemalloc.get_traced_memory()[1] / 2**20
        tracemalloc.stop()
        row = {
            "median_cpu_s": statistics.median(c for _, c in stages["total"]),
            "median_wall_s": statistics.median(walls),
            "min_wall_s": min(walls),
            "max_wall_s": max(walls),
            "stages": {
                k: {"wall_s": statistics.median(a for a, _ in v), "cpu_s": statistics.median(b for _, b in v)}
                for k, v in stages.items()
            },
            "peak_rss_growth_mb": mem.peak - mem.base,
            "peak_numpy_alloc_mb": traced,
            "level": res.level,
            "valid_fraction": res.valid_fraction,
            "info": res.info,
        }
        if z is not None:
            e = res.elevation - z
            ok = np.isfinite(e)
            row["dem_mean_abs_m"] = float(np.abs(e[ok]).mean())
            row["dem_median_m"] = float(np.median(e[ok]))
        summary["presets"][preset] = row
        print(
            f"{preset:7s} median {row['median_wall_s']:.3f} s wall, {row['median_cpu_s']:.3f} s CPU "
            f"(wall min {row['min_wall_s']:.3f}, max "
            f"{row['max_wall_s']:.3f}), peak RSS growth {row['peak_rss_growth_mb']:.1f} MB "
            f"(numpy peak {row['peak_numpy_alloc_mb']:.1f} MB), valid "
            f"{row['valid_fraction']:.1%}"
            + (f", DEM mean |err| {row['dem_mean_abs_m']:.3f} m" if z is not None else "")
        )
        for k, v in row["stages"].items():
            print(f"    {k:11s} wall {v['wall_s'] * 1e3:8.1f} ms   cpu {v['cpu_s'] * 1e3:8.1f} ms")
        if PRESETS[preset].dem == "sgm":
            cpu = {k: v["cpu_s"] for k, v in row["stages"].items()}
            row["reserves"] = {}
            planned = row["info"].get("mapping_reserve_s")  # the pair's own modelled mapping reserve, if any
            for name, covers, need, have in reserve_table(PRESETS[preset], cpu, i1.size, planned):
                short = need > have
                row["reserves"][name] = {"needed_s": need, "reserve_s": have, "short": short}
                print(
                    f"    reserve {name}: {have * 1e3:.1f} ms for {need * 1e3:.1f} ms of "
                    f"{' + '.join(covers)}" + ("  SHORT" if short else "")
                )
                short_any = short_any or short
    if args.ablation and z is not None:
        summary["ablation"] = ablation(i1, i2, p1, p2, cam, z)
    if args.json:
        write_out(args.json, json.dumps(summary, indent=1, default=float) + "\n")
    if args.check_reserves and short_any:
        print("a deadline reserve is shorter than the stages it covers (flight_sw.anytime.reserves)", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    run(main)
