"""Landing campaigns with one site-selection parameter at several values (how `fast`'s site guard
on relief, 14 m, its site margin and the grid's share of called pixels were chosen).

    .venv/bin/python bench/bench_site_guard.py --seed-set tuning --thresholds 0 12 14 [--pose-error none]
    .venv/bin/python bench/bench_site_guard.py --seed-set tuning --param site_margin_m --thresholds 0.5 1 1.5
    .venv/bin/python bench/bench_site_guard.py --seed-set tuning --param grid_call_share --thresholds 0.999 0.5

Flies the `hazard-hil landings` campaign (the same draws: scenes, seeds, aim points, navigation
errors; ``studies.landings``) with ``PipelineParams.<param>`` (default ``site_relief_max_m``, 0 = no
guard) set to each value and prints safe / unsafe / no-site counts and the unsafe landings. Tune on
``--seed-set tuning`` (seeds 0-9); quote ``held-out``. Renders are cached in ``--cache`` and shared
with any campaign of the same draws.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import multiprocessing as mp
import sys
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from _cli import out_file, positive_int, run, write_out  # noqa: E402

from studies import landings as L  # noqa: E402

PARAMS = ("site_relief_max_m", "site_margin_m", "grid_call_share", "site_reach_cells", "grid_elev_finite")


def _fly(args: tuple[L.Campaign, int, str, float, str]) -> list[dict[str, Any]]:
    camp, g, name, value, cache = args
    from flight_sw import pipeline as P

    # forked workers: the preset is patched in this process only
    fields: dict[str, Any] = {name: value}
    P.PRESETS["fast"] = dataclasses.replace(P.PRESETS["fast"], **fields)
    rows: list[dict[str, Any]] = L.land_group(L.plan_group(camp, g), ["fast"], cache)["rows"]
    return rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seed-set", choices=("tuning", "held-out"), default="tuning")
    ap.add_argument("--seeds", type=int, default=0, help="first N seeds of the set (default: all of it)")
    ap.add_argument("--n", type=positive_int, default=1008, help="landings per campaign")
    ap.add_argument("--pose-error", default=L.DEFAULT_POSE_ERROR, help="PoseError syntax, or 'none'")
    ap.add_argument("--param", choices=PARAMS, default=PARAMS[0], help="the fast preset's field to vary")
    ap.add_argument(
        "--thresholds",
        type=float,
        nargs="+",
        default=[0.0, 12.0, 14.0],
        help="its values (m, or a share)",
    )
    ap.add_argument("--cache", default=str(ROOT / "out" / "landing_renders"))
    ap.add_argument("--workers", type=positive_int, default=2)
    ap.add_argument("--json", type=out_file, help="write every campaign's rows here")
    a = ap.parse_args()
    from ground_sim import library
    from ground_sim.seeds import SEED_SETS

    seeds = SEED_SETS[a.seed_set][: a.seeds or None]
    pe = None if a.pose_error.lower() == "none" else a.pose_error
    camp = L.Campaign(tuple(e.name for e in library.entries()), a.n, seeds, a.seed_set, pose_error=pe)
    print(f"{camp.n_landings} landings, {camp.n_groups} renders, {a.seed_set} seeds {seeds[0]}-{seeds[-1]}")
    out: dict[str, list[dict[str, Any]]] = {}
    for t in a.thresholds:
        jobs = [(camp, g, a.param, t, a.cache) for g in range(camp.n_groups)]
        with mp.get_context("fork").Pool(a.workers) as pool:
            rows = [r for rs in pool.imap(_fly, jobs) for r in rs]
        out[f"{t:g}"] = rows
        k = {o: sum(r["outcome"] == o for r in rows) for o in ("safe", "unsafe", "no_site")}
        print(f"{a.param} {t:g}: safe {k['safe']}, unsafe {k['unsafe']}, no site {k['no_site']}")
        for r in rows:
            if r["outcome"] == "unsafe":
                where = f"{r['scene']} seed {r['scene_seed']} {r['scenario']} {r['pair']}"
                print(f"    unsafe: {where} landing {r['landing']}")
    if a.json:
        write_out(a.json, json.dumps(out))
    return 0


if __name__ == "__main__":
    run(main)
