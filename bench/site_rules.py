"""Would a site-level rule on P(safe) or clearance have refused the unsafe top sites? (tuning campaigns)

    .venv/bin/python bench/site_rules.py --seed-set tuning --cache DIR [--pose-error none] [--json rows.json]

Flies the `landings` campaign's draws (the same groups, aim points and navigation errors) with `fast`
asking for 12 sites, judges each against ground truth, then replays the choice "the first site whose
footprint's P(safe) (its smallest cell value) is >= t" and "... whose clearance is >= c": safe / unsafe /
no-site counts per threshold. With t = 0 and c = 0 it reproduces the campaign's counts.
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from _cli import note_cache_dir, out_file, run, write_out


def fly(seed_set: str, pose_error: str, cache: str) -> list[dict[str, Any]]:
    from flight_sw.pipeline import PRESETS, run_pipeline
    from ground_sim.library import entries
    from ground_sim.seeds import HELD_OUT_SEEDS, TUNING_SEEDS
    from studies.evaluate import backproject_depth
    from studies.landings import DEFAULT_POSE_ERROR, Campaign, _perturb, group_pair, judge_site, plan_group

    seeds = tuple(TUNING_SEEDS if seed_set == "tuning" else HELD_OUT_SEEDS)
    c = Campaign(
        scenes=tuple(e.name for e in entries()),
        n=1008,
        seeds=seeds,
        seed_set=seed_set,
        pose_error=None if pose_error == "none" else DEFAULT_POSE_ERROR,
    )
    prm = dataclasses.replace(PRESETS["fast"], n_sites=12)
    rows = []
    for g in range(c.n_groups):
        plan = plan_group(c, g)
        spec, pair = group_pair(plan, cache)
        world = backproject_depth(spec.camera, spec.poses[0], pair.truth["depth"].astype(np.float64))[..., :2]
        for ld in plan["landings"]:
            aim = (float(ld["aim"][0]), float(ld["aim"][1]))
            f = _perturb(spec.poses, ld["errors"])
            res = run_pipeline(
                pair.images[0], pair.images[-1], f[0], f[-1], spec.camera, preset=prm, nominal_site_xy=aim,
                altimeter_m=pair.altimeter_m,
            )  # fmt: skip
            sites = [
                (s.p_safe, bool(judge_site((s.x, s.y), world, pair.truth["hazard"])["safe"]), s.clearance_m)
                for s in res.sites
            ]
            rows.append({"scene": plan["scene"], "seed": plan["seed"], "pair": plan["pair"], "sites": sites})
        print(f"group {g + 1}/{c.n_groups}", file=sys.stderr, flush=True)
    return rows


def replay(rows: list[dict[str, Any]], key: int, thresholds: list[float]) -> list[str]:
    out = []
    for t in thresholds:
        n: collections.Counter[str] = collections.Counter()
        for r in rows:
            s = next((s for s in r["sites"] if s[key] >= t), None)
            n["no site" if s is None else ("safe" if s[1] else "unsafe")] += 1
        out.append(f"| {t:g} | {n['safe']} | {n['unsafe']} | {n['no site']} |")
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seed-set", choices=("tuning", "held-out"), default="tuning")
    ap.add_argument(
        "--pose-error", choices=("default", "none"), default="default", help="'none' for perfect navigation knowledge"
    )
    ap.add_argument(
        "--cache", required=True, help="the landings campaign's render cache (filled where it lacks a pair)"
    )
    ap.add_argument("--json", type=out_file, help="write the flown rows here")
    args = ap.parse_args()
    note_cache_dir(args.cache, "--cache")  # one made on demand is said, so that a mistyped path is seen
    rows = fly(args.seed_set, args.pose_error, args.cache)
    if args.json:
        write_out(args.json, json.dumps(rows))
    print("| site P(safe) >= | safe | unsafe | no site |\n|---:|---:|---:|---:|")
    print("\n".join(replay(rows, 0, [0.0, 0.98, 0.99, 0.993, 0.995, 0.997])))
    print("\n| clearance m >= | safe | unsafe | no site |\n|---:|---:|---:|---:|")
    print("\n".join(replay(rows, 2, [0.0, 3.2, 3.5, 4.0, 5.0])))
    return 0


if __name__ == "__main__":
    run(main)
