"""Run every benchmark script in bench/ in turn (``make bench``).

Runs each ``bench_*.py`` bare (its defaults), one after the other, with its exit status and wall time. Each
prints its own table; only three also write a page under ``docs/benchmarks/``: ``bench_hil.py`` (hil.md),
``bench_budget_speed.py`` (budget_speed.md) and ``bench_throttle.py`` (throttle.md). The other pages there are
not written by ``make bench`` (``bench_render.py`` and ``bench_parallel.py`` write their table to a file only
when given ``--out``; several scripts keep renders or rows of their own under /tmp or out/ to reuse).
docs/BENCHMARKS.md collects the headline numbers.
Pass names to run a subset: ``python bench/run_all.py pipeline render``.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path

from _cli import run, unknown

HERE = Path(__file__).resolve().parent


def main(argv: list[str] | None = None) -> int:
    scripts = {s.stem.removeprefix("bench_"): s for s in sorted(HERE.glob("bench_*.py"))}
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("names", nargs="*", metavar="NAME", help=f"run only these (default: all): {', '.join(scripts)}")
    args = ap.parse_args(argv)
    unknown("NAME", args.names, scripts)  # before any script runs
    failed = []
    for name, script in scripts.items():
        if args.names and name not in args.names:
            continue
        print(f"\n=== {script.name}", flush=True)
        t0 = time.perf_counter()
        rc = subprocess.call([sys.executable, str(script)], cwd=HERE.parent)
        print(f"=== {script.name}: exit {rc} in {time.perf_counter() - t0:.1f} s", flush=True)
        if rc:
            failed.append(script.name)
    if failed:
        print("failed: " + ", ".join(failed), file=sys.stderr)
    return 1 if failed else 0


if __name__ == "__main__":
    run(main)
