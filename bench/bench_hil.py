"""HIL latency per processor budget: end-to-end descents over the budget's own link.

For each budget, streams the same rendered pairs (vertical scenario, 512 px)
through ground -> link -> supervisor -> emulated flight processor and reports
the end-to-end latency (the deadline's: last frame sent -> whole Result held at the ground, docs/hil.md)
p50/p95/max beside the flight latency (last frame in -> Result out), deadline hit rate, the
level reached, the achieved CPU fraction and the line time of frames and
results. Writes ``docs/benchmarks/hil.md``. The pairs and runs go to a temporary directory
(``/tmp/bench_hil_*``), removed at the end unless ``--keep``.

    .venv/bin/python bench/bench_hil.py [--budgets host,snapdragon801,rad750,gr740] [--pairs 600/300,300/150]
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from _cli import InputError, out_path, run, unknown  # noqa: E402
from pages import write_page  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--budgets", default="host,snapdragon801,rad750,gr740")
    ap.add_argument("--pairs", default="600/300,300/150,200/100")
    ap.add_argument("--scenario", default="vertical")
    ap.add_argument("--out", type=out_path, default=ROOT / "docs" / "benchmarks" / "hil.md")
    ap.add_argument("--keep", action="store_true", help="keep the temporary directory of pairs and runs (named)")
    args = ap.parse_args(argv)

    from ground_sim.trajectory import load_trajectory
    from hil_server.budgets import get_budget
    from protocol.errors import comma_items

    # every name checked before the temporary directory is made and the pairs are rendered
    budgets = comma_items(args.budgets, "--budgets") or [""]  # "" is no budget's name either
    for name in budgets:
        get_budget(name)
    pairs = comma_items(args.pairs, "--pairs")
    labels = [s.label for s in load_trajectory(args.scenario)]
    if not pairs:
        raise InputError(f"--pairs: name at least one of {', '.join(labels)}")
    unknown("--pairs", pairs, labels)
    args.budgets, args.pairs = ",".join(budgets), ",".join(pairs)  # as checked (spaces around commas dropped)

    work = Path(tempfile.mkdtemp(prefix="bench_hil_"))
    try:
        return bench(args, work)
    finally:
        if args.keep:
            print(f"bench_hil: kept {work}", file=sys.stderr)
        else:
            shutil.rmtree(work, ignore_errors=True)


def bench(args: argparse.Namespace, work: Path) -> int:
    """Render the pairs into ``work``, run each budget's descent there and write the table."""
    from ground_sim.descent import render_scenario
    from hil_server.budgets import get_budget, load_calibration
    from hil_server.run import LATE_SIGNAL, RunConfig, run_descent
    from protocol.plan import plan_note

    pairs = args.pairs.split(",")
    manifest = render_scenario(args.scenario, work / "pairs", pairs=pairs, progress=True) / "manifest.json"
    cal = load_calibration()
    rows = []
    for name in args.budgets.split(","):
        b = get_budget(name)
        t0 = time.monotonic()
        s = run_descent(
            RunConfig(scenario=args.scenario, link=b.link, budget=name, out=work / name, manifest=manifest),
            log=lambda m: print(m, file=sys.stderr),
        )
        stop = s.get("interrupted_by") or s.get(LATE_SIGNAL)
        if stop:  # a Ctrl-C, also one while the summary was written (returned, not raised): no more budgets
            raise SystemExit(f"bench_hil: stopped by signal {stop} during budget {name}; no table written")
        recs = [r for r in s["records"] if r["status"] == "result"]
        rows.append(
            {
                "budget": name,
                "link": b.link + (f" {b.baud:,} baud" if b.link == "serial" and b.baud else ""),
                "fraction": s["cpu_fraction"],
                "deadline": s["deadline_s"],
                "pairs": s["pairs"],
                "results": s["results"],
                "errors": s["errors"],
                "hit": s["deadline_hit_rate"],
                "p50": s["e2e_latency_p50_s"],
                "p95": s["e2e_latency_p95_s"],
                "max": s["e2e_latency_max_s"],
                "flight50": s["flight_latency_p50_s"],
                "levels": ", ".join(r["level"] for r in recs) or "-",  # in descent order
                # why each degraded pair stopped where it did (the flight's plan telemetry)
                "why": [f"{r['label']}: {w}" for r in recs if (w := plan_note(r.get("plan"), r.get("skipped")))],
                "achieved": statistics.median([r["cpu_fraction"] for r in recs]) if recs else float("nan"),
                "frames_link": statistics.median([r["link_s"] for r in recs]) if recs else float("nan"),
                "result_link": statistics.median([r["link"].get("result_link_s", 0.0) for r in recs])
                if recs
                else float("nan"),
                "wall": time.monotonic() - t0,
            }
        )
        print(json.dumps(rows[-1]), file=sys.stderr)

    lines = [
        "# HIL latency per processor budget",
        "",
        f"Measured {time.strftime('%Y-%m-%d')}: `{args.scenario}` pairs {', '.join(pairs)} at 512x512, `fast` preset, "
        f"lockstep pacing. Host calibration: "
        + (f"{cal.units_per_s:.1f} reference units/s ({cal.cpu_model})" if cal else "none (anchor assumed)")
        + ".",
        "",
        "End to end = the deadline's latency (docs/hil.md): the ground finished sending the last frame -> the",
        "ground holds the whole Result; flight = last frame in -> Result out of the flight process; the result's",
        "own line time is the `result link` column. Achieved = the flight process's CPU time over the wall",
        "time it could run while a pair was outstanding (median over pairs).",
        "",
        "Reproduce: `.venv/bin/python bench/bench_hil.py`",
        "",
        "| budget | link | duty | deadline s | results | hit rate | end to end p50 / p95 / max s | flight p50 s "
        "| levels | achieved "
        "| frames link s | result link s |",
        "|---|---|---:|---:|---:|---:|---|---:|---|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(
            f"| {r['budget']} | {r['link']} | {r['fraction']:.4f} | {r['deadline']:g} | "
            f"{r['results']}/{r['pairs']} | {100 * r['hit']:.0f} % | {r['p50']:.2f} / {r['p95']:.2f} / "
            f"{r['max']:.2f} | {r['flight50']:.2f} | {r['levels']} | {r['achieved']:.3f} | {r['frames_link']:.2f} | "
            f"{r['result_link']:.2f} |"
        )
    why = [f"- {r['budget']} {w}" for r in rows for w in r["why"]]
    if why:
        lines += ["", "Why the degraded pairs stopped where they did (the flight's plan telemetry):", "", *why]
    print("\n".join(lines))
    print(write_page(args.out, "\n".join(lines), "bench_hil.py"))
    return 0


if __name__ == "__main__":
    run(main)
