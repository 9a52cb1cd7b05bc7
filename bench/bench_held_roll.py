"""Nadir pairs: the held fit's rotation about the optical axis (flight_sw/pose_refine.py, held_axis_free).

    .venv/bin/python bench/bench_held_roll.py --seed-set tuning --n-seeds 4 [--altitudes 150 300] [--camera-px 512]

On the vertical descent's pairs (near-nadir: the refinement holds the relative rotation, docs/benchmarks/pose.md
"Nadir pairs"), frame 2's reported attitude is perturbed: exact (``none``), the landing campaign's navigation
errors (``nav``: 0.03 deg per axis per frame, 0.15 m per axis; seeded per pair and draw), a roll about frame 2's
optical axis of +-0.3 and +-0.5 deg (``roll``), and the issue's camera-2 case (``cam2``: 0.15 pitch, 0.10 roll,
0.05 yaw deg, both signs). Each is refined with the held prior on all three axes (``held_axis_free=0``, before
stop 75) and with the optical axis spared (``1``), and the ``fast`` sweep runs on the refined poses (its own
refinement off). Printed per kind and variant: verdicts, the relative rotation left against the truth (deg) and
the DEM mean |error| (m), medians and worst. Tune on ``--seed-set tuning`` only.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from _cli import positive_int, run  # noqa: E402


def _errors(kind: str, seed: int, alt: int) -> list[list[dict[str, float]]]:
    if kind == "none":
        return [[{}, {}]]
    if kind == "roll":
        return [[{}, {"roll_deg": r}] for r in (0.3, -0.3, 0.5, -0.5)]
    if kind == "cam2":
        return [[{}, {"pitch_deg": 0.15 * s, "roll_deg": 0.10 * s, "yaw_deg": 0.05 * s}] for s in (1.0, -1.0)]
    rng = np.random.default_rng([seed, alt, 0x4E41])  # nav: the landing campaign's per-frame sds
    out = []
    for _ in range(4):
        fr = []
        for _k in range(2):
            a = rng.normal(0.0, 0.03, 3)
            p = rng.normal(0.0, 0.15, 3)
            fr.append({"pitch_deg": a[0], "roll_deg": a[1], "yaw_deg": a[2], "dx_m": p[0], "dy_m": p[1], "dz_m": p[2]})
        out.append(fr)
    return out


def main(argv: list[str] | None = None) -> int:
    from bench_pose import dem_metrics, pin_one_core

    from flight_sw.pipeline import PRESETS, run_pipeline
    from flight_sw.pose_refine import RefineParams, refine_pair
    from flight_sw.twoview import rotation_angle_deg
    from ground_sim.seeds import SEED_SETS
    from protocol.pairdir import read_pair
    from studies.evaluate import backproject_depth, perturb_poses, render_cache, true_poses

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seed-set", choices=sorted(SEED_SETS), default="tuning")
    ap.add_argument("--n-seeds", type=positive_int, default=4)
    ap.add_argument("--altitudes", type=int, nargs="+", default=[150, 300])
    ap.add_argument("--camera-px", type=positive_int, default=512)
    ap.add_argument(
        "--kinds", nargs="+", default=["none", "nav", "roll", "cam2"], choices=["none", "nav", "roll", "cam2"]
    )
    ap.add_argument("--cache", type=Path, default=ROOT / "out" / "bench_pose" / "cache")
    a = ap.parse_args(argv)
    pin_one_core()
    fast = dataclasses.replace(PRESETS["fast"], refine_pose=False)
    variants = {"held 3 axes": RefineParams(held_axis_free=False), "optical axis spared": RefineParams()}
    rows = []
    for seed in SEED_SETS[a.seed_set][: a.n_seeds]:
        for e in render_cache("vertical", seed, a.cache, camera_px=a.camera_px, altitudes=a.altitudes):
            pair = read_pair(e["pair_dir"])
            cam, (t1, t2) = pair.camera, true_poses(pair)
            i1, i2 = pair.images[0], pair.images[-1]
            truth = pair.truth["elevation"].astype(np.float32)
            wxy = backproject_depth(cam, t1, pair.truth["depth"].astype(np.float64))[..., :2]
            R21_true = t2.R @ t1.R.T
            for kind in a.kinds:
                for fr in _errors(kind, seed, int(e["altitude_m"])):
                    f1, f2 = perturb_poses(t1, t2, fr)
                    for name, rp in variants.items():
                        ref = refine_pair(i1, i2, f1, f2, cam, params=rp)
                        rot_left = rotation_angle_deg((ref.pose2.R @ ref.pose1.R.T) @ R21_true.T)
                        m = dem_metrics(run_pipeline(i1, i2, ref.pose1, ref.pose2, cam, preset=fast), truth, wxy)
                        rows.append({"kind": kind, "variant": name, "verdict": ref.info.get("verdict"),
                                     "left_deg": rot_left, "dem_m": m["mean_abs"]})  # fmt: skip
            print(f"  seed {seed} {e['label']} done", file=sys.stderr, flush=True)
    print(f"## held fit on nadir pairs ({a.seed_set} seeds, {a.camera_px} px, altitudes {a.altitudes})\n")
    print(
        "| pose error | variant | n | verdicts | rotation left deg: median / worst | DEM mean abs m: median / worst |"
    )
    print("|---|---|---:|---|---|---|")
    for kind in a.kinds:
        for name in variants:
            rs = [r for r in rows if r["kind"] == kind and r["variant"] == name]
            verdicts = ", ".join(
                f"{v} {sum(r['verdict'] == v for r in rs)}" for v in sorted({r["verdict"] for r in rs})
            )
            left = [r["left_deg"] for r in rs]
            dem = [r["dem_m"] for r in rs if math.isfinite(r["dem_m"])]
            print(f"| {kind} | {name} | {len(rs)} | {verdicts} | {np.median(left):.3f} / {max(left):.3f} | "
                  f"{np.median(dem):.3f} / {max(dem):.3f} |")  # fmt: skip
    return 0


if __name__ == "__main__":
    run(main)
