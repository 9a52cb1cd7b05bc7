"""Benchmark: does the work scale over the cores? Rendering a descent and `evaluate`, 1 vs N workers.

Each configuration runs in a fresh Python process (so thread settings and imports are those of a real
run), ``--repeat`` times; we report the median wall time, the machine's load average around the runs,
and the speed-up ratio of medians. Cases:

* ``render``: the vertical descent (8 pairs, 16 frames of 512x512) with ``render_scenario``:
  - ``before``: one process, each pair's two frames one after the other with OpenCV/BLAS free to use
    every core (what `render` did before this change: no frame sharing, no pool);
  - ``workers=1``: one single-threaded process (the 11 distinct poses; shared frames rendered once);
  - ``workers=N``: N single-threaded processes.
* ``evaluate``: ``hazard-hil evaluate --scenario vertical --preset fast --seeds 2`` from an empty
  directory (render + pipeline + scoring + report), ``--workers 1`` vs ``--workers N``.

Usage: ``.venv/bin/python bench/bench_parallel.py [--repeat 3] [--workers 2] [--only render,evaluate]
[--out docs/benchmarks/parallel.md]``
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _cli import InputError, out_file, positive_int, run, unknown, write_out
from pages import write_page

from protocol.errors import comma_items

ROOT = Path(__file__).resolve().parents[1]
PY = sys.executable
CASES = ("render", "evaluate")  # --only

RENDER_BEFORE = """
import time, tempfile
from pathlib import Path
from ground_sim.descent import assemble_pair
from ground_sim.library import scene_sun
from ground_sim.render import render_view
from ground_sim.scene import load_scene
from ground_sim.trajectory import load_trajectory
from protocol.pairdir import write_pair
t0 = time.perf_counter(); c0 = time.process_time()
sc = load_scene("thesis", 1000, "vertical")
sun = scene_sun("thesis", "vertical", 1000)
with tempfile.TemporaryDirectory() as d:
    for spec in load_trajectory("vertical"):
        views = [render_view(sc, spec.camera, p, sun, noise=False) for p in spec.poses]
        write_pair(Path(d) / spec.label.replace("/", "_"), assemble_pair(sc, spec, sun, views, seed=1000))
print(time.perf_counter() - t0, time.process_time() - c0)
"""

RENDER_POOL = """
import time, sys, tempfile
from ground_sim.descent import render_scenario
if __name__ == "__main__":
    t0 = time.perf_counter(); c0 = time.process_time()
    with tempfile.TemporaryDirectory() as d:
        render_scenario("vertical", d, seed=1000, progress=False, workers={workers})
    print(time.perf_counter() - t0, time.process_time() - c0)
"""


def _load() -> float:
    return os.getloadavg()[0]


def _children_cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def _run(code: str, env: dict[str, str]) -> tuple[float, float]:
    """(wall, CPU seconds of the case process and every worker it started)."""
    c0 = _children_cpu()
    out = subprocess.run([PY, "-c", code], cwd=ROOT, env=env, capture_output=True, text=True, check=True)
    wall = float(out.stdout.split()[-2])
    return wall, _children_cpu() - c0


def _env(single: bool) -> dict[str, str]:
    env = dict(os.environ)
    for k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        if single:
            env[k] = "1"
        else:
            env.pop(k, None)
    return env


def bench_render(repeat: int, workers: int) -> dict:
    cases = {
        "before (1 process, all threads, 16 frames)": (RENDER_BEFORE, _env(False)),
        "workers=1 (11 distinct frames)": (RENDER_POOL.replace("{workers}", "1"), _env(True)),
        f"workers={workers}": (RENDER_POOL.replace("{workers}", str(workers)), _env(True)),
    }
    return _cases(cases, repeat)


def _cases(cases: dict[str, tuple[str, dict[str, str]]], repeat: int) -> dict:
    res: dict[str, dict] = {}
    for k in range(repeat):  # interleaved, so a load change hits every case alike
        for name, (code, env) in cases.items():
            l0 = _load()
            wall, cpu = _run(code, env)
            r = res.setdefault(name, {"wall": [], "cpu": [], "load": []})
            r["wall"].append(wall)
            r["cpu"].append(cpu)
            r["load"].append((l0 + _load()) / 2)
            print(f"  [{k + 1}/{repeat}] {name}: {wall:.1f} s (load {r['load'][-1]:.2f})", flush=True)
    return res


def bench_evaluate(repeat: int, workers: int) -> dict:
    res: dict[str, dict] = {}
    exe = str(Path(PY).with_name("hazard-hil"))
    for k in range(repeat):
        for w in (1, workers):
            name = f"--workers {w}"
            d = Path(tempfile.mkdtemp(prefix="bench_eval_"))
            l0 = _load()
            c0 = _children_cpu()
            t0 = time.perf_counter()
            subprocess.run(
                [exe, "evaluate", "--scenario", "vertical", "--preset", "fast", "--seeds", "2"]
                + ["--workers", str(w), "--no-progress", "--out", str(d)],
                cwd=ROOT,
                env=_env(False),
                capture_output=True,
                check=True,
            )
            wall = time.perf_counter() - t0
            shutil.rmtree(d, ignore_errors=True)
            r = res.setdefault(name, {"wall": [], "cpu": [], "load": []})
            r["wall"].append(wall)
            r["cpu"].append(_children_cpu() - c0)
            r["load"].append((l0 + _load()) / 2)
            print(f"  [{k + 1}/{repeat}] evaluate {name}: {wall:.1f} s (load {r['load'][-1]:.2f})", flush=True)
    return res


def _table(title: str, res: dict, base: str) -> list[str]:
    med = {k: statistics.median(v["wall"]) for k, v in res.items()}
    lines = [
        f"**{title}**",
        "",
        "| case | median wall s | min s | max s | CPU s, all processes | load avg during | speed-up vs first |",
    ]
    lines.append("|---|---|---|---|---|---|---|")
    for k, v in res.items():
        lines.append(
            f"| {k} | {med[k]:.1f} | {min(v['wall']):.1f} | {max(v['wall']):.1f} | {statistics.median(v['cpu']):.1f} | "
            f"{min(v['load']):.2f}-{max(v['load']):.2f} | {med[base] / med[k]:.2f}x |"
        )
    return lines


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeat", type=positive_int, default=3)
    ap.add_argument("--workers", type=positive_int, default=2)
    ap.add_argument("--only", default=",".join(CASES), help=f"comma-separated: {','.join(CASES)}")
    ap.add_argument(
        "--out",
        type=out_file,
        default=None,
        help="write the tables into this page (its other text kept: bench/pages.py)",
    )
    ap.add_argument("--json", type=out_file, default=None, help="write the raw timings here")
    args = ap.parse_args()
    only = set(comma_items(args.only, "--only"))
    if not only:  # checked before anything runs or is written
        raise InputError(f"--only: name at least one of {', '.join(CASES)}")
    unknown("--only", sorted(only), CASES)
    out: list[str] = [f"Host: {os.cpu_count()} cores, load average at start {_load():.2f}."]
    raw: dict[str, dict] = {}
    if "render" in only:
        print("render: vertical descent, 16 frames 512x512", flush=True)
        raw["render"] = r = bench_render(args.repeat, args.workers)
        names = list(r)
        out += ["", *_table("render the vertical descent (thesis scene, seed 1000)", r, names[0])]
        m1, mn = statistics.median(r[names[1]]["wall"]), statistics.median(r[names[2]]["wall"])
        out.append(f"\nScaling {names[2]} vs workers=1: {m1 / mn:.2f}x.")
    if "evaluate" in only:
        print("evaluate: vertical, fast, 2 seeds, from an empty directory", flush=True)
        raw["evaluate"] = e = bench_evaluate(args.repeat, args.workers)
        out += ["", *_table("hazard-hil evaluate --scenario vertical --preset fast --seeds 2 (cold)", e, "--workers 1")]
    out.append(f"\nLoad average at the end {_load():.2f}.")
    text = "\n".join(out) + "\n"
    print(text)
    if args.out:
        print(write_page(args.out, text, "bench_parallel.py"))
    if args.json:
        write_out(args.json, json.dumps(raw, indent=1) + "\n")


if __name__ == "__main__":
    run(main)
