"""Multi-frame descents against the best pair (issue 10): ``hazard-hil evaluate --multi-frame``.

A descent of N frames (default 300, 250, 200, 150 m: the issue's example) is rendered as one pair
directory (:func:`ground_sim.trajectory.frames_at`, ground truth of frame 0). On it:

* ``pair 0-k``: the pipeline on frames 0 and k alone; ``best pair`` is the one with the highest CDI on
  that descent, **chosen with the truth** (an upper bound for any single pair);
* ``multi``: one multi-baseline run on every frame (Okutomi & Kanade 1993;
  :func:`flight_sw.pipeline.run_pipeline_multi`);
* ``fused ...``: several runs over the descent, each a (reference, later frames) set, fused in time
  order on the world grid (:mod:`flight_sw.fusion`, settings as the flight process takes them:
  :func:`flight_sw.fusion.params_for`). ``window L``: as frame k arrives, one run with reference
  ``max(0, k - L)`` and the frames after it up to k; ``refs->last``: when the last frame arrives, one
  run per earlier reference with every frame after it, fused in time order of their references (the
  shortest run, reference N-2, enters last and decides where it measured); ``refs->last, widest last``
  (bench only): the same runs fused the other way round, so that the run on every frame with frame 0 as
  its reference decides. All the runs exist once the last frame has arrived, so either order is open to a
  lander; the time order did better on the held-out thesis-scene descents (docs/benchmarks/multiframe.md,
  stop 39).

Every policy is scored in frame 0's pixels against frame 0's truth, on the same pixels: DESIGN.md's covered
area of the widest pair, frame 0's pixels whose true ground frame N-1 sees
(:func:`ground_sim.gridscore.scored_area`, as ``score`` takes it; until stop 65 the pixels the widest pair's
run covered). Pixel FP / FN / CDI (:func:`ground_sim.scoring.confusion`; unknown counts as unsafe), DEM mean
|error| and coverage. World-grid results (fused maps) are read at each pixel's true ground point. Timing is
CPU seconds (``time.thread_time``).
"""

from __future__ import annotations

import math
import statistics
import time
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from ground_sim.render import DEFAULT_RASTER
from reports.jsondoc import json_text

DEFAULT_FRAMES = (300.0, 250.0, 200.0, 150.0)
POLICIES = ("multi", "fused refs->last", "fused window 2")


# ----------------------------------------------------------------------------------------------- rendering
def render_descent(
    scenario: str,
    seed: int,
    cache_dir: str | Path,
    frames: Sequence[float] = DEFAULT_FRAMES,
    *,
    camera_px: int | None = None,
    scene: str | None = None,
    max_cells: int | None = None,
    raster: str = DEFAULT_RASTER,
) -> Path:
    """Render (or reuse) one multi-frame pair directory of the scenario's scene under its sun."""
    from ground_sim import library, trajectory
    from ground_sim.descent import default_scene, render_pair
    from ground_sim.render import MAX_CELLS
    from ground_sim.render_cache import reusable
    from ground_sim.scene import load_scene, load_scene_params
    from protocol.pairdir import Camera, write_pair_atomic
    from studies.evaluate import camera_for, render_tag

    cam = camera_for(camera_px) or Camera.thesis()
    spec = trajectory.frames_at(scenario, [float(a) for a in frames], cam)
    scene_spec = scene or default_scene(scenario)
    params = load_scene_params(scene_spec, scenario)
    tag = params.spec.replace(":", "-")
    label = "_".join(f"{a:g}" for a in frames)
    out = Path(cache_dir) / f"{scenario}_{tag}_s{seed}_{cam.width}px{render_tag(max_cells, raster)}" / f"frames_{label}"
    # else none there, or a stale one (another renderer, render code or scene parameters), now removed
    if reusable(out, scene=params):
        return out
    sc = load_scene(scene_spec, seed, scenario)
    sun = library.scene_sun(scene_spec, scenario, seed)
    pair = render_pair(sc, spec, sun, seed=seed, max_cells=max_cells or MAX_CELLS, raster=raster)
    return write_pair_atomic(out, pair)


# ----------------------------------------------------------------------------------------------- scoring
def world_of(pair: Any) -> np.ndarray:
    """True world X, Y, Z (H x W x 3) of frame 0's pixels from the truth depth and frame 0's true pose."""
    from studies.evaluate import backproject_depth, true_poses

    return backproject_depth(pair.camera, true_poses(pair)[0], pair.truth["depth"].astype(np.float64))


def pixel_world(pair: Any) -> tuple[np.ndarray, np.ndarray]:
    """True world X, Y of frame 0's pixels (true pose where the directory records it, true elevation)."""
    from flight_sw.georef import backproject
    from protocol.pairdir import true_poses

    return backproject(pair.camera, true_poses(pair)[0], pair.truth["elevation"].astype(np.float64))


def sample_cells(grid: Any, X: np.ndarray, Y: np.ndarray, layer: np.ndarray, fill: float) -> np.ndarray:
    """Nearest cell of a world-grid layer at world points (``fill`` off the grid)."""
    j = np.rint((X - grid.origin_xy[0]) / grid.cell_m)
    i = np.rint((grid.origin_xy[1] - Y) / grid.cell_m)
    h, w = layer.shape
    ok = np.isfinite(i) & np.isfinite(j) & (i >= 0) & (i < h) & (j >= 0) & (j < w)
    out = np.full(X.shape, fill, np.float32)
    out[ok] = layer[i[ok].astype(int), j[ok].astype(int)]
    return out


def score(pair: Any, hazard: np.ndarray, elevation: np.ndarray, mask: np.ndarray) -> dict[str, float]:
    """Pixel FP / FN / CDI, DEM mean |error| and coverage of image maps on ``mask``."""
    from ground_sim import scoring

    c = scoring.confusion(hazard, pair.truth["hazard"], mask)
    err = np.abs(elevation - pair.truth["elevation"])[mask]
    fin = np.isfinite(err)
    return {
        "fp": c["fp"],
        "fn": c["fn"],
        "cdi": c["cdi"],
        "dem": float(err[fin].mean()) if fin.any() else math.nan,
        "coverage": 100.0 * float(fin.mean()) if fin.size else 0.0,
    }


def score_grid(pair: Any, grid: Any, mask: np.ndarray, xy: tuple[np.ndarray, np.ndarray]) -> dict[str, float]:
    """Score a world-grid result at frame 0's pixels: safe cells -> hazard 0, others 1 (DESIGN.md)."""
    from protocol.pairdir import STATE_OUTSIDE, STATE_SAFE

    st = sample_cells(grid, xy[0], xy[1], grid.state.astype(np.float32), float(STATE_OUTSIDE))
    hz = np.where(st == STATE_SAFE, 0.0, 1.0).astype(np.float32)
    hz[st == STATE_OUTSIDE] = np.nan
    ez = sample_cells(grid, xy[0], xy[1], grid.reported_elevation, math.nan)
    return score(pair, hz, ez, mask)


# ----------------------------------------------------------------------------------------------- policies
def window_jobs(n: int, lag: int) -> list[tuple[int, list[int]]]:
    """As frame k = 1..n-1 arrives: reference max(0, k - lag), the frames after it up to k."""
    return [(max(0, k - lag), list(range(max(0, k - lag) + 1, k + 1))) for k in range(1, n)]


def refs_to_last_jobs(n: int) -> list[tuple[int, list[int]]]:
    """When the last frame arrives: one run per earlier reference r with frames r+1 .. n-1."""
    return [(r, list(range(r + 1, n))) for r in range(n - 1)]


def fused_policies(n: int) -> dict[str, list[tuple[int, list[int]]]]:
    return {
        "fused window 2": window_jobs(n, 2),
        "fused window 3": window_jobs(n, 3),
        "fused refs->last": refs_to_last_jobs(n),
        "fused refs->last, widest last": refs_to_last_jobs(n)[::-1],
        "fused refs->last pairs": [(r, [n - 1]) for r in range(n - 1)],
    }


def run_jobs(
    pair: Any,
    jobs: list[tuple[int, list[int]]],
    preset: Any,
    overrides: dict[str, Any] | None = None,
    runs: dict[tuple[int, ...], tuple[Any, float]] | None = None,
) -> tuple[Any, list[Any], float]:
    """Run each (reference, others) set and fuse the results in order: (fused grid, results, CPU s).
    Fusion decides as the flight process does (``fusion.params_for``), then ``overrides``. ``runs``: pipeline
    results (and their CPU s) by frame set, shared between policies that fuse the same runs; the CPU s
    returned counts every run the policy needs, computed here or not."""
    from flight_sw.fusion import FusionParams, fuse, params_for, to_hazard_grid
    from flight_sw.pipeline import run_pipeline_multi

    fm = None
    results = []
    cpu = 0.0
    prm = FusionParams(**(overrides or {}))
    runs = {} if runs is None else runs
    for ref, others in jobs:
        idx = (ref, *others)
        if idx not in runs:
            c0 = time.thread_time()
            res = run_pipeline_multi(
                [pair.images[k] for k in idx],
                [pair.poses[k] for k in idx],
                pair.camera,
                preset=preset,
                sun_elevation_deg=pair.sun.elevation_deg if pair.sun else None,
                sun_azimuth_deg=pair.sun.azimuth_deg if pair.sun else None,
            )
            runs[idx] = (res, time.thread_time() - c0)
        res, run_cpu = runs[idx]
        c0 = time.thread_time()
        prm = replace(params_for(res.params, res.info, FusionParams()), **(overrides or {}))
        fm = fuse(fm, res.grid, prm, level=str(res.level))
        cpu += run_cpu + time.thread_time() - c0
        results.append(res)
    if fm is None:
        raise ValueError("run_jobs: no jobs")
    return to_hazard_grid(fm, prm), results, cpu


def evaluate_descent(
    pair_dir: str | Path, preset: Any, which: Sequence[str] = POLICIES, overrides: dict[str, Any] | None = None
) -> dict[str, dict[str, float]]:
    """Every pair (0, k), the best of them, and the policies in ``which``, scored alike (module doc)."""
    from flight_sw.pipeline import run_pipeline, run_pipeline_multi
    from ground_sim.gridscore import scored_area
    from protocol.pairdir import read_pair

    pair = read_pair(pair_dir)
    n = pair.n_frames
    sun_e = pair.sun.elevation_deg if pair.sun else None
    sun_az = pair.sun.azimuth_deg if pair.sun else None
    xy = pixel_world(pair)
    rows: dict[str, dict[str, float]] = {}
    results = {}
    for k in range(n - 1, 0, -1):
        c0 = time.thread_time()
        results[k] = run_pipeline(
            pair.images[0],
            pair.images[k],
            pair.poses[0],
            pair.poses[k],
            pair.camera,
            preset=preset,
            sun_elevation_deg=sun_e,
            sun_azimuth_deg=sun_az,
        )
        results[k].info["cpu_s"] = time.thread_time() - c0
    mask = scored_area(pair, world_of(pair))  # the widest pair's true overlap, whatever a run maps of it
    for k in range(1, n):
        res = results[k]
        rows[f"pair 0-{k}"] = {**score(pair, res.hazard, res.elevation, mask), "cpu_s": res.info["cpu_s"]}
        rows[f"pair 0-{k} (grid)"] = score_grid(pair, res.grid, mask, xy)
    best = max(range(1, n), key=lambda k: rows[f"pair 0-{k}"]["cdi"])
    rows["best pair"] = {**rows[f"pair 0-{best}"], "k": best}
    if "multi" in which:
        c0 = time.thread_time()
        res = run_pipeline_multi(
            list(pair.images),
            list(pair.poses),
            pair.camera,
            preset=preset,
            sun_elevation_deg=sun_e,
            sun_azimuth_deg=sun_az,
        )
        rows["multi"] = {**score(pair, res.hazard, res.elevation, mask), "cpu_s": time.thread_time() - c0}
    runs: dict[tuple[int, ...], tuple[Any, float]] = {}  # the refs->last orders fuse the same runs
    for name, jobs in fused_policies(n).items():
        if name in which:
            g, _, cpu = run_jobs(pair, jobs, preset, overrides, runs)
            rows[name] = {**score_grid(pair, g, mask, xy), "cpu_s": cpu, "runs": len(jobs)}
    return rows


def _med(v: Sequence[float]) -> float:
    w = [x for x in v if x is not None and math.isfinite(x)]
    return statistics.median(w) if w else math.nan


def summary_rows(per_descent: Sequence[dict[str, Any]], names: Sequence[str]) -> list[dict[str, Any]]:
    """One row per policy: medians and worst cases over descents, and the change against the best pair."""
    out = []
    for name in ["best pair", *names]:
        rs = [d["rows"][name] for d in per_descent if name in d["rows"]]
        if not rs:
            continue
        bp = [d["rows"]["best pair"] for d in per_descent if name in d["rows"]]
        dc = [r["cdi"] - b["cdi"] for r, b in zip(rs, bp, strict=True)]
        df = [r["fp"] - b["fp"] for r, b in zip(rs, bp, strict=True)]
        out.append(
            {
                "policy": name,
                "descents": len(rs),
                "fp_med": _med([r["fp"] for r in rs]),
                "fp_worst": max(r["fp"] for r in rs),
                "cdi_med": _med([r["cdi"] for r in rs]),
                "cdi_min": min(r["cdi"] for r in rs),
                "dcdi_med": _med(dc),
                "dcdi_min": min(dc),
                "dfp_max": max(df),
                "dem_med": _med([r["dem"] for r in rs]),
                "coverage_med": _med([r["coverage"] for r in rs]),
                "coverage_min": min(r["coverage"] for r in rs),
                "cpu_med": _med([r.get("cpu_s", math.nan) for r in rs]),
            }
        )
    return out


def summary_markdown(summary: Sequence[dict[str, Any]]) -> str:
    lines = [
        "| policy | descents | FP % med / worst | CDI % med / min | CDI - best pair med / min | FP - best pair max "
        "| DEM err m med | DEM coverage % med / min | CPU s med |",
        "|---|---:|---|---|---|---:|---:|---|---:|",
    ]
    for s in summary:
        lines.append(
            f"| {s['policy']} | {s['descents']} | {s['fp_med']:.2f} / {s['fp_worst']:.2f} "
            f"| {s['cdi_med']:.1f} / {s['cdi_min']:.1f} | {s['dcdi_med']:+.1f} / {s['dcdi_min']:+.1f} "
            f"| {s['dfp_max']:+.2f} | {s['dem_med']:.3f} | {s['coverage_med']:.1f} / {s['coverage_min']:.1f} "
            f"| {s['cpu_med']:.3f} |"
        )
    return "\n".join(lines) + "\n"


def descent_task(
    scenario: str,
    seed: int,
    cache: str,
    frames: list[float],
    camera_px: int | None,
    preset: str,
    which: list[str],
    max_cells: int | None,
    raster: str,
) -> dict[str, Any]:
    """One seed's descent rendered (or reused) and scored: a task of :func:`evaluate_multiframe`."""
    from flight_sw.pipeline import PRESETS

    d = render_descent(scenario, seed, cache, frames, camera_px=camera_px, max_cells=max_cells, raster=raster)
    rows = evaluate_descent(d, PRESETS[preset], which)
    return {"scenario": scenario, "seed": seed, "frames": list(frames), "dir": str(d), "rows": rows}


def evaluate_multiframe(
    scenario: str,
    out_dir: str | Path,
    seeds: Sequence[int],
    *,
    frames: Sequence[float] = DEFAULT_FRAMES,
    cache_dir: str | Path | None = None,
    camera_px: int | None = None,
    preset: str = "fast",
    which: Sequence[str] = POLICIES,
    progress: Callable[[str], None] | None = None,
    max_cells: int | None = None,
    raster: str = DEFAULT_RASTER,
    scheduler: Any = None,
) -> list[dict[str, Any]]:
    """Render and score one descent per seed; write ``multiframe_<scenario>.json`` and the summary table
    ``report/multiframe_<scenario>.md`` under ``out_dir``; return the per-descent records.

    Each seed is a task of :func:`studies.executor.run_tasks` saved in ``runs/multiframe.jsonl``: an
    interrupted evaluation resumes from the descents it scored (one descent is 1-2 min of CPU). Locally the
    descents run one after another in this process; ``scheduler`` (a Dask address or client) spreads them
    over the cluster's workers."""

    from studies.evaluate import EVAL_CODE, render_identity, render_tag, task_inputs
    from studies.executor import Task, code_fingerprint, run_tasks

    out = Path(out_dir)
    cache = Path(cache_dir) if cache_dir is not None else out / "cache"
    alts = "-".join(f"{a:g}" for a in frames)
    kw: dict[str, Any] = {
        "cache": str(cache),
        "frames": [float(a) for a in frames],
        "camera_px": camera_px,
        "preset": preset,
    }
    kw |= {"which": list(which), "max_cells": max_cells, "raster": raster, "scenario": scenario}
    tag = f"{'+'.join(which)}{render_tag(max_cells, raster)}"
    tasks = [Task(f"mf-{scenario}-{preset}-s{seed}-{alts}-{tag}", {**kw, "seed": int(seed)}) for seed in seeds]
    t0 = time.perf_counter()
    res = run_tasks(
        descent_task,
        tasks,
        out / "runs" / "multiframe.jsonl",
        scheduler=scheduler,
        workers=1,  # locally one descent holds four 512 px frames and their cost volumes: one at a time
        progress=progress is not None,
        desc=f"multi-frame {scenario}",
        code=code_fingerprint(EVAL_CODE),
        inputs=task_inputs(camera_px, render_identity(scenario)),
    )
    per = [res[t.id] for t in tasks]
    for i, rec in enumerate(per, 1):
        if progress:
            rows = rec["rows"]
            bp = rows["best pair"]
            progress(
                f"multi-frame {scenario} seed {rec['seed']} ({i}/{len(seeds)}, {time.perf_counter() - t0:.0f} s): "
                f"best pair 0-{bp['k']} CDI {bp['cdi']:.1f} FP {bp['fp']:.2f}; "
                + "; ".join(f"{w} CDI {rows[w]['cdi']:.1f} FP {rows[w]['fp']:.2f}" for w in which if w in rows)
            )
    (out / "report").mkdir(parents=True, exist_ok=True)
    (out / f"multiframe_{scenario}.json").write_text(json_text(per))
    (out / "report" / f"multiframe_{scenario}.md").write_text(summary_markdown(summary_rows(per, list(which))))
    return per
