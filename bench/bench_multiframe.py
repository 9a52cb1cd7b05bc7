"""Multi-frame descents (issue 10): per-frame cost, and accuracy against the best pair alone.

    .venv/bin/python bench/bench_multiframe.py speed --runs 7                       # CPU s per added frame
    .venv/bin/python bench/bench_multiframe.py accuracy --set tuning --n-seeds 8    # tune
    .venv/bin/python bench/bench_multiframe.py accuracy --set held-out --n-seeds 10 --json /tmp/mf.json

``speed``: CPU time (``time.thread_time``, one thread, medians of ``--runs``) of
``run_pipeline_multi`` on the first 2, 3, ... N frames of one rendered descent; the cost of an
added frame is the slope of a least-squares line through those medians (and each step's
difference). ``accuracy``: for each scene seed a descent with frames at ``--altitudes``
(default 300 250 200 150 m) is rendered into ``--cache``; every policy runs on it and is scored
in frame 0's pixels against frame 0's ground truth, all on the same pixels: those the widest
pair (frames 0 and -1) covers. Policies:

* ``pair 0-k``: :func:`flight_sw.pipeline.run_pipeline` on frames 0 and k; ``best pair`` is the
  one of them with the highest CDI on that descent (chosen with the truth: an upper bound for
  any pair);
* ``multi``: one multi-baseline run on all frames (:func:`flight_sw.pipeline.run_pipeline_multi`);
* ``fused ...``: several runs over the descent, each a (reference, later frames) set, fused on the
  world grid in time order (:mod:`flight_sw.fusion`); the map is read at frame 0's pixels
  (their true ground points). ``window L``: as frame k arrives, one run with reference
  ``max(0, k - L)`` and every frame after it up to k; ``refs->last``: when the last frame
  arrives, one run per earlier reference with all frames after it.

Scores: pixel FP / FN / CDI (``ground_sim.scoring.confusion``; unknown counts as unsafe), DEM
mean |error| and DEM coverage (share of the scored pixels with an elevation). Seeds come from
``ground_sim.seeds``: tune on ``tuning``, quote ``held-out``; the worst case is given beside the
median.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import statistics
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from _cli import out_file, positive_int, run, write_out  # noqa: E402

DEFAULT_ALTITUDES = (300.0, 250.0, 200.0, 150.0)
SCENE = {"vertical": "default", "approach": "approach"}


# ----------------------------------------------------------------------------------------------- rendering
def descent_poses(case: str, altitudes: list[float]) -> list[Any]:
    """Frames of a built-in scenario at these altitudes (vertical: nadir above the site; approach: on the
    45 deg path toward the site, 49 deg off nadir above 300 m and 40 deg at and below, as its pairs)."""
    from ground_sim import trajectory as tr
    from ground_sim.geometry import look_rotation
    from protocol.pairdir import Pose

    if hasattr(tr, "frames_at"):
        return list(tr.frames_at(case, altitudes).poses)
    if case == "vertical":
        s0 = float(max(tr.VERTICAL_UPPER[0], altitudes[0]))
        return [Pose(np.array([0.0, 0.0, h]), look_rotation(0.0), tr._time(s0, h)) for h in altitudes]
    s0 = tr.APPROACH_PAIRS[0][0] * math.sqrt(2)
    return [
        Pose(np.array([0.0, -h, h]), look_rotation(40.0 if h <= 300.0 else 49.0, 0.0), tr._time(s0, h * math.sqrt(2)))
        for h in altitudes
    ]


def render_descent(case: str, seed: int, altitudes: list[float], cache: Path) -> Path:
    """Render (or reuse) one multi-frame pair directory; ground truth is frame 0's."""
    from ground_sim.descent import DEFAULT_SUN
    from ground_sim.render import RENDER_VERSION, render_view
    from ground_sim.render_cache import render_fingerprints, reusable
    from ground_sim.scene import Scene, load_scene_params
    from protocol.pairdir import Camera, Pair, write_pair_atomic

    label = "_".join(f"{a:g}" for a in altitudes)
    out = cache / f"{case}_{label}_s{seed}"
    params = load_scene_params(SCENE[case])
    # else none there, or a stale one, now removed; renders from before the fingerprints are trusted (said)
    if reusable(out, scene=params, trust_unrecorded=True):
        return out
    poses = descent_poses(case, altitudes)
    scene = Scene(params, seed)
    sun = DEFAULT_SUN[case]
    cam = Camera.thesis()
    views = [
        render_view(scene, cam, p, sun, seed=seed * 7919 + 104729 * k + 17, hazard_truth=k == 0)
        for k, p in enumerate(poses)
    ]
    truth = {k: getattr(views[0], k) for k in ("elevation", "depth", "shadow", "hazard")}
    meta = {
        "scenario": case,
        "label": label.replace("_", "/"),
        "scene": scene.params.name,
        "scene_seed": seed,
        "render_version": RENDER_VERSION,
        **render_fingerprints(scene.params),
    }
    meta["true_frames"] = [p.to_dict(f"i{k + 1}.png") for k, p in enumerate(poses)]
    pair = Pair(cam, tuple(poses), tuple(v.image for v in views), sun, truth, meta)
    return write_pair_atomic(out, pair)


# scoring, policies and one descent's evaluation live in studies.multiframe (``hazard-hil evaluate --multi-frame``)
def _med(v: list[float]) -> float:
    v = [x for x in v if x is not None and math.isfinite(x)]
    return statistics.median(v) if v else math.nan


def table(per_descent: list[dict[str, Any]], names: list[str], title: str) -> str:
    out = [
        f"\n### {title}\n",
        "| policy | descents | FP % med / worst | FN % med | CDI % med / min | CDI - best pair med / min "
        "| FP - best pair max | DEM err m med | DEM coverage % med / min | CPU s med |",
        "|---|---:|---|---:|---|---|---:|---:|---|---:|",
    ]
    for name in ["best pair", *names]:
        rs = [d["rows"][name] for d in per_descent if name in d["rows"]]
        if not rs:
            continue
        bp = [d["rows"]["best pair"] for d in per_descent if name in d["rows"]]
        dc = [r["cdi"] - b["cdi"] for r, b in zip(rs, bp)]
        df = [r["fp"] - b["fp"] for r, b in zip(rs, bp)]
        out.append(
            f"| {name} | {len(rs)} | {_med([r['fp'] for r in rs]):.2f} / {max(r['fp'] for r in rs):.2f} "
            f"| {_med([r['fn'] for r in rs]):.1f} "
            f"| {_med([r['cdi'] for r in rs]):.1f} / {min(r['cdi'] for r in rs):.1f} "
            f"| {_med(dc):+.1f} / {min(dc):+.1f} | {max(df):+.2f} | {_med([r['dem'] for r in rs]):.3f} "
            f"| {_med([r['coverage'] for r in rs]):.1f} / {min(r['coverage'] for r in rs):.1f} "
            f"| {_med([r.get('cpu_s', math.nan) for r in rs]):.3f} |"
        )
    return "\n".join(out)


# ----------------------------------------------------------------------------------------------- speed
def preset_with(name: str, set_param: list[str] | tuple[str, ...]) -> Any:
    """Preset ``name`` with ``K=V`` overrides, each value parsed as its field's type (booleans: 1/true/0/false)."""
    from flight_sw.pipeline import PRESETS

    preset = PRESETS[name]
    for kv in set_param:
        k, eq, v = kv.partition("=")
        if not eq or not hasattr(preset, k):
            raise ValueError(f"expected K=V with K a field of the preset (flight_sw.pipeline.Params), got {kv!r}")
        cur = getattr(preset, k)
        if isinstance(cur, bool):  # bool("False") is True, and an unknown word must not pass as False
            words = {"1": True, "true": True, "yes": True, "0": False, "false": False, "no": False}
            if v.lower() not in words:
                raise ValueError(f"--set-param {k}: expected true or false, got {v!r}")
            change: dict[str, Any] = {k: words[v.lower()]}  # field k named at run time: no one static type fits
        else:
            kind = float if cur is None else type(cur)  # an unset optional field (cell_m None) takes a number
            change = {k: kind(v)}
        preset = dataclasses.replace(preset, **change)
    return preset


def build_preset(args: argparse.Namespace) -> Any:
    """``--preset`` with the ``--set-param K=V`` overrides; a bad one ends the bench with one line."""
    try:
        return preset_with(args.preset, args.set_param)
    except (ValueError, AttributeError, KeyError) as exc:
        raise SystemExit(f"bench_multiframe: --preset/--set-param: {exc}") from None


def speed(args: argparse.Namespace) -> int:
    from flight_sw.pipeline import run_pipeline_multi
    from protocol.pairdir import read_pair

    preset = build_preset(args)

    d = render_descent(args.case, args.seed, list(args.altitudes), Path(args.cache))
    pair = read_pair(d)
    n = pair.n_frames
    meds = []
    for m in range(2, n + 1):
        idx = [0, *range(1, m - 1), n - 1]  # the widest pair plus the first m - 2 frames between
        times = []
        for _ in range(args.runs):
            c0 = time.thread_time()
            run_pipeline_multi([pair.images[k] for k in idx], [pair.poses[k] for k in idx], pair.camera, preset=preset)
            times.append(time.thread_time() - c0)
        meds.append(statistics.median(times))
        print(f"{m} frames {idx}: CPU median {meds[-1]:.3f} s (runs {', '.join(f'{t:.3f}' for t in times)})")
    ms = np.arange(2, n + 1, dtype=float)
    slope = float(np.polyfit(ms, meds, 1)[0]) if len(meds) > 1 else math.nan
    steps = np.diff(meds)
    print(
        f"per added frame: {slope:.3f} s (least squares), steps {', '.join(f'{s:+.3f}' for s in steps)} s; "
        f"load average {os.getloadavg()[0]:.1f}"
    )
    return 0 if not args.check or slope <= args.check else 1


def fusion_overrides(items: list[str]) -> dict[str, Any]:
    """``K=V`` strings as FusionParams fields, each value parsed as its field's type (``extent=union``)."""
    from flight_sw.fusion import FusionParams

    defaults = {f.name: getattr(FusionParams(), f.name) for f in dataclasses.fields(FusionParams)}
    out: dict[str, Any] = {}
    for kv in items:
        k, sep, v = kv.partition("=")
        if not sep or k not in defaults:
            raise ValueError(f"expected K=V with K one of {', '.join(defaults)}, got {kv!r}")
        out[k] = type(defaults[k])(v)  # ValueError for a non-number where a number belongs
    return out


def accuracy(args: argparse.Namespace) -> int:
    from flight_sw.fusion import FusionParams
    from ground_sim.seeds import HELD_OUT_SEEDS, TUNING_SEEDS
    from studies.multiframe import evaluate_descent, fused_policies

    seeds = args.seeds or list((TUNING_SEEDS if args.set == "tuning" else HELD_OUT_SEEDS)[: args.n_seeds])
    preset = build_preset(args)
    try:
        overrides = fusion_overrides(args.fusion)
        FusionParams(**overrides).validate()  # a bad --fusion fails here, not after the first render
    except ValueError as exc:
        print(f"bench_multiframe: --fusion: {exc}", file=sys.stderr)
        return 2
    known = ["multi", *fused_policies(len(args.altitudes))]
    which = known if args.policies is None else args.policies
    unknown = [w for w in which if w not in known]
    if unknown:  # an unknown name would be skipped without a word
        print(f"bench_multiframe: --policies: unknown {unknown!r}; one of {', '.join(known)}", file=sys.stderr)
        return 2
    cache = Path(args.cache)
    per: list[dict[str, Any]] = []
    for case in args.cases:
        for s in seeds:
            d = render_descent(case, s, list(args.altitudes), cache)
            rows = evaluate_descent(d, preset, which, overrides)
            per.append({"case": case, "seed": s, "dir": str(d), "rows": rows})
            print(
                f"{case} seed {s}: best pair 0-{rows['best pair']['k']} CDI {rows['best pair']['cdi']:.1f} FP "
                f"{rows['best pair']['fp']:.2f}; "
                + "; ".join(f"{w} CDI {rows[w]['cdi']:.1f} FP {rows[w]['fp']:.2f}" for w in which if w in rows),
                flush=True,
            )
    alts = "/".join(f"{a:g}" for a in args.altitudes)
    for case in args.cases:
        print(table([d for d in per if d["case"] == case], which, f"{case} {alts} m, seeds {seeds}"))
    print(table(per, which, f"all cases, seeds {seeds}"))
    if args.json:
        write_out(args.json, json.dumps(per, indent=1, default=float) + "\n")
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    for name in ("speed", "accuracy"):
        p = sub.add_parser(name)
        p.add_argument("--altitudes", type=float, nargs="+", default=list(DEFAULT_ALTITUDES))
        p.add_argument("--cache", default="/tmp/multiframe_cache")
        p.add_argument("--preset", default="fast")
        p.add_argument("--set-param", nargs="*", default=[], metavar="K=V", help="Params fields, e.g. refine_pose=0")
        if name == "speed":
            p.add_argument("--case", default="vertical", choices=list(SCENE))
            p.add_argument("--seed", type=int, default=0)
            p.add_argument("--runs", type=positive_int, default=5)
            p.add_argument("--check", type=float, default=None, help="exit 1 if the per-frame cost exceeds this (s)")
        else:
            p.add_argument("--set", choices=("tuning", "held-out"), default="tuning")
            p.add_argument("--n-seeds", type=positive_int, default=4)
            p.add_argument("--seeds", type=int, nargs="*")
            p.add_argument("--cases", nargs="+", default=list(SCENE), choices=list(SCENE))
            p.add_argument("--fusion", nargs="*", default=[], metavar="K=V", help="FusionParams fields")
            p.add_argument("--policies", nargs="*", default=None)
            p.add_argument("--json", type=out_file)
    argv = sys.argv[1:] if argv is None else argv
    args = ap.parse_args(argv or ["speed"])  # bare (``make bench``): the per-frame cost, ~30 s
    import cv2

    cv2.setNumThreads(1)
    return speed(args) if args.cmd == "speed" else accuracy(args)


if __name__ == "__main__":
    run(main)
