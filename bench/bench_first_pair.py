"""The first pair of a fresh flight process against its steady cost: does the boot warm-up pay?

    .venv/bin/python bench/bench_first_pair.py [--pair DIR] [--starts 3] [--modes cold settle warm]

Each start is a fresh Python process pinned to one CPU (OpenCV single-threaded, as the flight
process runs) that imports the pipeline, optionally prepares itself (``settle``:
``flight_sw.warmup.settle_allocator``; ``warm``: ``boot_warm_up``, what the flight process does at
boot; ``warm+heap``: also ``prefault_heap`` for the camera, what it does when the Config arrives),
then runs the same pair three times. Reported per mode: the first run's CPU over the median
of the other two, median and worst over the starts. Without ``--pair`` the seeded synthetic 512 px
pair of ``bench_pipeline.py``.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

from _cli import InputError, positive_int, run

ROOT = Path(__file__).resolve().parents[1]

CHILD = r"""
import json, sys, time
import cv2
cv2.setNumThreads(1)
sys.path[:0] = [{root!r}, {bench!r}, {tests!r}]
from flight_sw.pipeline import PRESETS, run_pipeline
mode, pair_dir = sys.argv[1], sys.argv[2]
if pair_dir:
    from protocol.pairdir import read_pair
    p = read_pair(pair_dir)
    args = (p.images[0], p.images[-1], p.poses[0], p.poses[-1], p.camera)
else:
    from bench_pipeline import synthetic_pair
    cam, p1, p2, i1, i2, _ = synthetic_pair(512)
    args = (i1, i2, p1, p2, cam)
boot = 0.0
if mode == "settle":
    from flight_sw.warmup import settle_allocator
    settle_allocator()
elif mode in ("warm", "warm+heap"):
    from flight_sw.warmup import boot_warm_up, heap_mib_for, prefault_heap
    boot = boot_warm_up(PRESETS["fast"])["cpu_s"]
    if mode == "warm+heap":  # what the flight process adds when the Config names the camera
        c0 = time.thread_time()
        prefault_heap(heap_mib_for(args[4].width, args[4].height))
        boot += time.thread_time() - c0
cpu = []
for _ in range(3):
    c0 = time.thread_time()
    run_pipeline(*args, preset=PRESETS["fast"])
    cpu.append(time.thread_time() - c0)
print(json.dumps({{"cpu": cpu, "boot": boot}}))
"""


def one_start(mode: str, pair: str, cpu: int) -> dict:
    code = CHILD.format(root=str(ROOT), bench=str(ROOT / "bench"), tests=str(ROOT / "tests"))
    cmd = ["taskset", "-c", str(cpu), sys.executable, "-c", code, mode, pair]
    out = subprocess.run(cmd, capture_output=True, text=True, env={**os.environ, "OMP_NUM_THREADS": "1"})
    if out.returncode:  # its last line (the exception), not the inline script in a CalledProcessError
        why = (out.stderr.strip().splitlines() or [f"exit status {out.returncode}"])[-1]
        raise SystemExit(f"bench_first_pair: a {mode} start failed: {why}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pair", default="", help="a pair directory (default: the synthetic 512 px pair)")
    ap.add_argument("--starts", type=positive_int, default=3, help="fresh processes per mode")
    modes = ["cold", "settle", "warm", "warm+heap"]
    ap.add_argument("--modes", nargs="+", default=modes, choices=modes)
    cpus = sorted(os.sched_getaffinity(0))  # the CPUs this process may run on (taskset refuses any other)
    ap.add_argument("--cpu", type=int, default=cpus[-1], help=f"the CPU to pin to (default {cpus[-1]})")
    args = ap.parse_args(argv)
    if args.cpu not in cpus:  # taskset's own refusal came after the first start
        raise InputError(f"--cpu {args.cpu}: no such CPU here; choose from {', '.join(map(str, cpus))}")
    if args.pair:  # a pair the children cannot read: said here, in one line, before any start
        from protocol.pairdir import read_pair

        read_pair(args.pair)
    print("| mode | starts | first / steady CPU: median | worst | first ms (median) | steady ms (median) | boot ms |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    for mode in args.modes:
        runs = []
        for i in range(args.starts):
            print(f"  {mode} start {i + 1}/{args.starts}", file=sys.stderr, flush=True)
            runs.append(one_start(mode, args.pair, args.cpu))
        ratios = [r["cpu"][0] / statistics.median(r["cpu"][1:]) for r in runs]
        first = statistics.median(r["cpu"][0] for r in runs)
        steady = statistics.median(statistics.median(r["cpu"][1:]) for r in runs)
        boot = statistics.median(r["boot"] for r in runs)
        print(
            f"| {mode} | {len(runs)} | {statistics.median(ratios):.2f}x | {max(ratios):.2f}x | "
            f"{1e3 * first:.0f} | {1e3 * steady:.0f} | {1e3 * boot:.0f} |",
        )
    return 0


if __name__ == "__main__":
    run(main)
