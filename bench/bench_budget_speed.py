"""Does an emulated budget run our flight pipeline at the speed it stands for? -> docs/benchmarks/budget_speed.md.

    .venv/bin/python bench/bench_budget_speed.py [--budgets rad750 gr740] [--runs 2] [--uncompensated] [--out F]

A budget stands for ``share = cpu_dmips / host_dmips`` of one host core (hil_server/budgets.py), so a pair whose
`fast` pipeline takes C CPU-seconds at full speed should take ``C / share`` of wall time on it. One probe process,
pinned to the emulated core, warms up at full speed, times ``--runs`` pipelines at full speed, then as many under
the throttle at the budget's duty cycle (:class:`hil_server.procemu.Throttle`; the start-up is not throttled, so a
gr740 run does not spend a minute importing). ``slow = wall / (C / share)``: 1.0 is the budget's speed exactly,
above 1 the emulated processor is slower than the budget. ``--uncompensated`` also runs each budget at
``duty = share`` (the rule before stop 47, which ignored that a throttled CPU-second does less work).
The pair is bench_pipeline.py's seeded synthetic 512x512 pair.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from _cli import out_file_or_empty, positive_int, run  # noqa: E402
from pages import write_page  # noqa: E402

from hil_server.budgets import get_budget, load_calibration  # noqa: E402
from hil_server.procemu import Throttle, start_at_full_speed  # noqa: E402

PROBE = """
import json, sys, time
sys.path[:0] = [{root!r}, {root!r} + "/bench", {root!r} + "/tests"]
import cv2
cv2.setNumThreads(1)
from flight_sw.warmup import settle_allocator
settle_allocator()
from bench_pipeline import synthetic_pair
from flight_sw.pipeline import run_pipeline
cam, p1, p2, i1, i2, _ = synthetic_pair(512)
sun = dict(sun_azimuth_deg=135.0, sun_elevation_deg=25.0)
run_pipeline(i1, i2, p1, p2, cam, preset="fast", **sun)
print("ready", flush=True)
for _ in sys.stdin:
    w, c = time.monotonic(), time.process_time()
    run_pipeline(i1, i2, p1, p2, cam, preset="fast", **sun)
    print(json.dumps([time.process_time() - c, time.monotonic() - w]), flush=True)
"""


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--budgets", nargs="+", default=["snapdragon801", "rad750", "gr740"])
    ap.add_argument("--runs", type=positive_int, default=2)
    ap.add_argument("--uncompensated", action="store_true", help="also run at duty = share (the old rule)")
    ap.add_argument(
        "--out",
        type=out_file_or_empty,
        default=str(ROOT / "docs" / "benchmarks" / "budget_speed.md"),
        help="'' to print only",
    )
    args = ap.parse_args(argv)
    for name in args.budgets:  # every name, before the probe starts
        get_budget(name)
    cal = load_calibration()
    if cal is None or not cal.throttle_efficiency:
        print("this host has no throttle efficiency on record: run `hazard-hil calibrate` first", file=sys.stderr)
        return 2
    load = os.getloadavg()[0]
    popen = start_at_full_speed(
        [sys.executable, "-c", PROBE.format(root=str(ROOT))], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
    )
    assert popen.stdin is not None and popen.stdout is not None
    stdin, stdout = popen.stdin, popen.stdout

    def runs(n: int) -> list[tuple[float, float]]:
        out = []
        for _ in range(n):
            stdin.write("go\n")
            stdin.flush()
            cpu, wall = json.loads(stdout.readline())
            out.append((cpu, wall))
        return out

    rows = []
    try:
        if stdout.readline().strip() != "ready":
            raise RuntimeError("the pipeline probe did not start")
        for name in args.budgets:
            duty = get_budget(name).duty(cal)
            modes = [("compensated", duty.applied)] + ([("duty = share", duty.effective)] if args.uncompensated else [])
            for mode, applied in modes:
                t0 = time.monotonic()
                full = runs(args.runs)
                with Throttle(popen, applied):
                    thr = runs(args.runs)
                full += runs(args.runs)
                c_full = statistics.median(c for c, _ in full)
                c_thr = statistics.median(c for c, _ in thr)
                w_thr = statistics.median(w for _, w in thr)
                want = c_full / duty.effective
                rows.append((name, mode, duty.effective, applied, c_full, c_thr, w_thr, want, w_thr / want))
                print(
                    f"{name} {mode}: duty {applied:.4f} for a share of {duty.effective:.4f}: pipeline {c_full:.3f} s "
                    f"CPU at full speed, {c_thr:.3f} s throttled, wall {w_thr:.1f} s against {want:.1f} s -> "
                    f"slow x{w_thr / want:.2f} ({time.monotonic() - t0:.0f} s)",
                    flush=True,
                )
    finally:
        popen.kill()
        popen.wait()
    eff = ", ".join(f"{e:.2f} at {f:g}" for f, e in cal.throttle_efficiency)
    lines = [
        "# A budget's speed on our flight pipeline",
        "",
        f"Measured {time.strftime('%Y-%m-%d')} on {cal.cpu_model} ({os.cpu_count()} cores, load average at start "
        f"{load:.2f}), calibrated {cal.measured_at}: {cal.units_per_s:.1f} reference units/s, throttle efficiency "
        f"eta {eff}. Command: `.venv/bin/python bench/bench_budget_speed.py --runs {args.runs}"
        f"{' --uncompensated' if args.uncompensated else ''}`.",
        "",
        "A budget stands for a share `cpu_dmips / host_dmips` of one host core, so a pair whose `fast` pipeline "
        "takes C CPU-seconds at full speed should take C / share of wall time on it. One probe process on the "
        "emulated core warms up at full speed and runs the pipeline on the synthetic 512x512 pair of "
        "`bench_pipeline.py`, "
        f"{args.runs} times at full speed, {args.runs} times throttled at the budget's duty cycle, and "
        f"{args.runs} times at full speed again (medians). `duty = share` is the rule before stop 47; "
        "`compensated` raises the duty until `f eta(f) = share` (`hil_server.budgets.Budget.duty`, "
        "[throttle.md](throttle.md) section 5).",
        "",
        "| budget | duty rule | share of a core | duty applied | pipeline CPU s, full speed | CPU s, throttled "
        "| wall s | wall s the budget means | slower than the budget |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for name, mode, share, applied, c_full, c_thr, w_thr, want, slow in rows:
        lines.append(
            f"| {name} | {mode} | {share:.4f} | {applied:.4f} | {c_full:.3f} | {c_thr:.3f} | {w_thr:.1f} | "
            f"{want:.1f} | x{slow:.2f} |"
        )
    lines += [
        "",
        "Above x1 the emulated processor is slower than the budget, below x1 faster. eta is measured on the "
        "reference workload (`hil_server/calibrate.py`), the yardstick for any flight program (`--flight-cmd`); our "
        "pipeline may lose more or less than it to a throttled slice.",
        "",
    ]
    print("\n".join(lines))
    if args.out:
        print(write_page(args.out, "\n".join(lines), "bench_budget_speed.py"))
        print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    run(main)
