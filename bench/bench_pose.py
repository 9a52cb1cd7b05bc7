"""Benchmark the relative pose refinement (flight_sw/pose_refine.py, issue #10): cost and pose-error sensitivity.

    .venv/bin/python bench/bench_pose.py [--seed-set held-out|tuning] [--n-seeds 2] [--samples 20]
        [--altitudes 125 150 250 300] [--kinds altitude attitude] [--cache DIR] [--out DIR] [--timing-runs 7]

(a) Cost: ``refine_pair`` per approach pair on one pinned core, OpenCV single-threaded; CPU
    (``time.thread_time``) and wall medians over repeats, and the ``fast`` pipeline with and without it.
(b) Sensitivity (thesis sec 6.3, Tables 6.12-6.19): the approach pairs of ``--n-seeds`` scene seeds of
    the chosen set, the pose errors of ``studies.evaluate.sample_pose_error`` (altitude: dh1, dh2 ~
    U(+-0.5 m); attitude: equal pitch on both frames, the thesis's six levels -0.15..+0.15 deg; not in
    the thesis, ``frame2``: frame 2's attitude alone off by 0.5 deg about a random axis), and
    per sample these variants of the poses handed to the ``fast`` pipeline:

    ``off``     the perturbed (reported) poses, no refinement (what the thesis measured)
    ``on``      refined from the images, scale from the reported baseline
    ``on_alt``  refined, scale from a laser altimeter on both frames (true slant range + ``--alt-noise-m``)
    ``oracle``  frame 0's reported pose, the TRUE relative pose, the reported baseline length: what a
                perfect two-view refinement anchored on frame 0 would leave (the unobservable part)
    ``oracle_alt`` the TRUE relative pose and baseline length (a perfect altimeter's scale), placed by
                least squares on both reported positions: the best an altimeter could add

    All variants run the ``fast`` preset with its own refinement switched off (each brings its poses).
    DEM error increase relative to perfect knowledge (true poses, no refinement), in percent, for the
    mean |error| and the MAD (median absolute deviation, blind to a common datum shift), plus
    ``detrended``: mean |error| after removing the least-squares plane ``a + b X + c Y`` of the error
    (blind to a datum shift and a tilt - what two images can observe at all).

Rows go to ``<out>/pose_rows.csv``; the summary is printed as markdown. Tune only on ``--seed-set tuning``.
"""

from __future__ import annotations

import argparse
import csv
import math
import os
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from _cli import InputError, out_dir, positive_int, run  # noqa: E402

VARIANTS = ("off", "on", "on_alt", "oracle", "oracle_alt")


def pin_one_core() -> None:
    cv2.setNumThreads(1)
    if hasattr(os, "sched_setaffinity"):
        cpus = sorted(os.sched_getaffinity(0))
        os.sched_setaffinity(0, {cpus[-1]})


def slant_ranges(pair, true1, true2) -> tuple[float, float]:
    """True laser-altimeter readings: camera z-depth of the ground on each optical axis.

    Frame 0: ``gt_depth_i1`` at the principal point (bilinear). Frame 1: the i1 pixel
    whose true ground point projects onto camera 2's principal point (a Newton step on the
    projection of i1's true ground points), and that point's camera-2 depth.
    """
    from studies.evaluate import backproject_depth

    cam = pair.camera
    depth = pair.truth["depth"].astype(np.float32)
    r1 = float(cv2.getRectSubPix(depth, (1, 1), (cam.cx, cam.cy))[0, 0])
    X = backproject_depth(cam, true1, depth.astype(np.float64))
    Xc = (X - true2.position) @ true2.R.T
    u = cam.fx * Xc[..., 0] / Xc[..., 2] + cam.cx
    v = cam.fy * Xc[..., 1] / Xc[..., 2] + cam.cy
    d2 = (u - cam.cx) ** 2 + (v - cam.cy) ** 2
    r0, c0 = np.unravel_index(int(np.argmin(d2)), d2.shape)
    r = min(max(int(r0), 1), d2.shape[0] - 2)
    c = min(max(int(c0), 1), d2.shape[1] - 2)
    J = np.array(
        [[(u[r, c + 1] - u[r, c - 1]) / 2, (u[r + 1, c] - u[r - 1, c]) / 2],
         [(v[r, c + 1] - v[r, c - 1]) / 2, (v[r + 1, c] - v[r - 1, c]) / 2]]
    )  # fmt: skip
    dc, dr = np.linalg.solve(J, [cam.cx - u[r, c], cam.cy - v[r, c]])
    z2 = Xc[..., 2].astype(np.float32)
    r2 = float(cv2.getRectSubPix(z2, (1, 1), (c + dc, r + dr))[0, 0])
    return r1, r2


def frame2_error(seed: int, index: int) -> dict:
    """Not a thesis study: frame 2's attitude alone off by 0.5 deg about a random axis (pitch, yaw, roll)."""
    rng = np.random.default_rng([0xF2, seed, index])
    a = rng.normal(size=3)
    a *= 0.5 / np.linalg.norm(a)
    return {"frames": [{}, {"pitch_deg": float(a[0]), "yaw_deg": float(a[1]), "roll_deg": float(a[2])}]}


def cam2_error(index: int) -> dict:
    """Issue #10's independent-scene case: camera 2's attitude off by 0.15 deg pitch, 0.10 roll, 0.05 yaw
    (frame 0 and the positions exact); even samples with these signs, odd ones with all signs flipped."""
    s = 1.0 if index % 2 == 0 else -1.0
    return {"frames": [{}, {"pitch_deg": 0.15 * s, "roll_deg": 0.10 * s, "yaw_deg": 0.05 * s}]}


def oracle_poses(rep1, rep2, true1, true2):
    """Frame 0 as reported, the true relative pose, the reported baseline length."""
    from protocol.pairdir import Pose

    R21 = true2.R @ true1.R.T
    b_cam1 = true1.R @ (true2.position - true1.position)
    b_cam1 /= np.linalg.norm(b_cam1)
    L = float(np.linalg.norm(rep2.position - rep1.position))
    return rep1, Pose(rep1.position + L * (rep1.R.T @ b_cam1), R21 @ rep1.R, rep2.time_s)


def oracle_alt_poses(rep1, rep2, true1, true2):
    """The true relative pose and baseline length (what images plus a perfect altimeter could give), placed
    by least squares on both reported positions: the datum error becomes the mean of the two altitude errors."""
    from protocol.pairdir import Pose

    R21 = true2.R @ true1.R.T
    b = rep1.R.T @ (true1.R @ (true2.position - true1.position))  # true baseline, in frame 0's reported axes
    C1 = (rep1.position + rep2.position - b) / 2.0
    return Pose(C1, rep1.R, rep1.time_s), Pose(C1 + b, R21 @ rep1.R, rep2.time_s)


def dem_metrics(res, truth_elev: np.ndarray, world_xy: np.ndarray) -> dict[str, float]:
    from ground_sim import scoring

    d = scoring.dem_error_stats(res.elevation, truth_elev, res.covered)
    e = (res.elevation - truth_elev).astype(np.float64)
    ok = res.covered & np.isfinite(e)
    detr = math.nan
    if ok.sum() > 10:
        A = np.c_[np.ones(int(ok.sum())), world_xy[ok]]
        coef, *_ = np.linalg.lstsq(A, e[ok], rcond=None)
        detr = float(np.mean(np.abs(e[ok] - A @ coef)))
    return {
        "mean_abs": d["mean_abs"],
        "median": d["median"],  # signed: the datum shift
        "mad": d["mad"],
        "detrended": detr,
        "valid": res.valid_fraction,
    }


def run_pair(
    entry: dict, kinds: list[str], samples: dict[str, int], alt_noise: float, rp, variants: tuple[str, ...] = VARIANTS
) -> list[dict]:
    """All samples of one pair; ``rp``: the RefineParams of the ``on`` variants (the pipeline hook's default)."""
    import dataclasses

    from flight_sw.pipeline import PRESETS, run_pipeline
    from flight_sw.pose_refine import refine_pair
    from protocol.pairdir import read_pair
    from studies.evaluate import backproject_depth, perturb_poses, sample_pose_error, true_poses

    pair = read_pair(entry["pair_dir"])
    cam = pair.camera
    t1, t2 = true_poses(pair)
    i1, i2 = pair.images[0], pair.images[-1]
    truth = pair.truth["elevation"].astype(np.float32)
    wxy = backproject_depth(cam, t1, pair.truth["depth"].astype(np.float64))[..., :2]
    r1, r2 = slant_ranges(pair, t1, t2)
    fast = dataclasses.replace(PRESETS["fast"], refine_pose=False)  # every variant brings its own poses
    alt = int(round(entry["altitude_m"]))
    perfect = dem_metrics(run_pipeline(i1, i2, t1, t2, cam, preset=fast), truth, wxy)
    rows = []
    rp_alt = dataclasses.replace(rp, use_altimeter=True)
    r0 = refine_pair(i1, i2, t1, t2, cam, params=rp)
    res_on = run_pipeline(i1, i2, r0.pose1, r0.pose2, cam, preset=fast)
    base = {"seed": entry["seed"], "altitude_m": alt}
    rows.append({**base, "kind": "none", "sample": -1, "variant": "perfect", **perfect})
    rows.append({**base, "kind": "none", "sample": -1, "variant": "perfect_on", **dem_metrics(res_on, truth, wxy)})
    rng = np.random.default_rng([entry["seed"], alt, 0xA17])
    for kind in kinds:
        for i in range(samples[kind]):
            if kind == "frame2":
                pe = frame2_error(entry["seed"] * 100003 + alt, i)
            elif kind == "cam2":
                pe = cam2_error(i)
            else:
                pe = sample_pose_error(kind, entry["seed"] * 100003 + alt, i)
            f1, f2 = perturb_poses(t1, t2, pe["frames"])
            errs = {f"{k}{j + 1}": v for j, fr in enumerate(pe["frames"]) for k, v in fr.items()}
            alt_m = (r1 + alt_noise * rng.standard_normal(), r2 + alt_noise * rng.standard_normal())
            for variant in variants:
                p1, p2, pr = f1, f2, None
                if variant in ("on", "on_alt"):
                    # the pipeline hook (Params.refine_pose) is exactly this call followed by the sweep
                    use = variant == "on_alt"
                    ref = refine_pair(
                        i1, i2, f1, f2, cam, params=rp_alt if use else rp, altimeter_m=alt_m if use else None
                    )
                    p1, p2, pr = ref.pose1, ref.pose2, ref.info
                elif variant == "oracle":
                    p1, p2 = oracle_poses(f1, f2, t1, t2)
                elif variant == "oracle_alt":
                    p1, p2 = oracle_alt_poses(f1, f2, t1, t2)
                res = run_pipeline(i1, i2, p1, p2, cam, preset=fast)
                m = dem_metrics(res, truth, wxy)
                row = {**base, "kind": kind, "sample": i, "variant": variant, **errs, **m}
                for k in ("mean_abs", "mad", "detrended"):
                    row[f"{k}_rel_pct"] = 100.0 * (m[k] - perfect[k]) / perfect[k]
                if pr:
                    row.update(
                        refined=pr["refined"],
                        reason=pr["reason"],
                        inliers=pr.get("inliers"),
                        refine_cpu_s=pr["cpu_s"],
                        rot_corr_deg=max(pr.get("rotation_correction_deg", [0.0])),
                    )
                rows.append(row)
    return rows


def summarise(rows: list[dict]) -> list[dict]:
    out = []
    keys = sorted({(r["kind"], r["altitude_m"], r["variant"]) for r in rows if r["kind"] != "none"})
    for kind, alt, variant in keys:
        rs = [r for r in rows if (r["kind"], r["altitude_m"], r["variant"]) == (kind, alt, variant)]
        s = {"kind": kind, "altitude_m": alt, "variant": variant, "n": len(rs)}
        for k in ("mean_abs", "mad", "detrended"):
            v = np.array([r[f"{k}_rel_pct"] for r in rs], float)
            s[f"{k}_median"], s[f"{k}_max"] = float(np.median(v)), float(v.max())
        if variant.startswith("on"):
            s["fallbacks"] = sum(1 for r in rs if not r.get("refined", True))
        out.append(s)
    for kind in sorted({r["kind"] for r in rows if r["kind"] != "none"}):
        for variant in VARIANTS:
            rs = [r for r in rows if r["kind"] == kind and r["variant"] == variant]
            if not rs:
                continue
            s = {"kind": kind, "altitude_m": "all", "variant": variant, "n": len(rs)}
            for k in ("mean_abs", "mad", "detrended"):
                v = np.array([r[f"{k}_rel_pct"] for r in rs], float)
                s[f"{k}_median"], s[f"{k}_max"] = float(np.median(v)), float(v.max())
            if variant.startswith("on"):
                s["fallbacks"] = sum(1 for r in rs if not r.get("refined", True))
            out.append(s)
    return out


def datum_fit(rows: list[dict]) -> list[dict]:
    """Altitude study: least squares ``median signed DEM error - perfect's = c1 dh1 + c2 dh2 + c0`` per variant.

    A datum the images cannot see follows the reported altitudes: ``c1 = 1`` means the DEM rides
    up and down with frame 0's altitude error.
    """
    perf = {(r["seed"], r["altitude_m"]): r["median"] for r in rows if r["variant"] == "perfect"}
    out = []
    for variant in VARIANTS:
        rs = [r for r in rows if r["kind"] == "altitude" and r["variant"] == variant]
        if len(rs) < 4:
            continue
        A = np.array([[r.get("dz_m1", 0.0), r.get("dz_m2", 0.0), 1.0] for r in rs])
        y = np.array([r["median"] - perf[(r["seed"], r["altitude_m"])] for r in rs])
        ok = np.isfinite(y)
        c, *_ = np.linalg.lstsq(A[ok], y[ok], rcond=None)
        resid = y[ok] - A[ok] @ c
        out.append(
            {
                "variant": variant,
                "c1 (dh1)": round(float(c[0]), 2),
                "c2 (dh2)": round(float(c[1]), 2),
                "c0 m": round(float(c[2]), 3),
                "residual sd m": round(float(resid.std()), 3),
            }
        )
    return out


def markdown(rows: list[dict]) -> str:
    if not rows:
        return ""
    cols = list(dict.fromkeys(k for r in rows for k in r))
    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for r in rows:
        cells = []
        for c in cols:
            v = r.get(c, "")
            cells.append(f"{v:+.1f}" if isinstance(v, float) and c.endswith(("_median", "_max")) else str(v))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def timing(entries: list[dict], runs: int) -> list[dict]:
    import dataclasses

    from flight_sw.pipeline import PRESETS, run_pipeline
    from flight_sw.pose_refine import refine_pair
    from protocol.pairdir import read_pair
    from studies.evaluate import perturb_poses, sample_pose_error, true_poses

    out = []
    fast, fast_on = (dataclasses.replace(PRESETS["fast"], refine_pose=v) for v in (False, True))
    for e in entries:
        pair = read_pair(e["pair_dir"])
        t1, t2 = true_poses(pair)
        f1, f2 = perturb_poses(t1, t2, sample_pose_error("attitude", 0, 0)["frames"])
        i1, i2 = pair.images[0], pair.images[-1]
        refine_pair(i1, i2, f1, f2, pair.camera)  # warm-up
        cpu, wall, p_off, p_on = [], [], [], []
        for _ in range(runs):
            r = refine_pair(i1, i2, f1, f2, pair.camera)
            cpu.append(r.info["cpu_s"])
            wall.append(r.info["wall_s"])
            c0 = time.thread_time()
            run_pipeline(i1, i2, f1, f2, pair.camera, preset=fast)
            p_off.append(time.thread_time() - c0)
            c0 = time.thread_time()
            run_pipeline(i1, i2, f1, f2, pair.camera, preset=fast_on)
            p_on.append(time.thread_time() - c0)
        out.append(
            {
                "pair": f"approach s{e['seed']} {Path(e['pair_dir']).name}",
                "refine_cpu_ms": round(1e3 * statistics.median(cpu), 1),
                "refine_wall_ms": round(1e3 * statistics.median(wall), 1),
                "pipeline_cpu_ms_off": round(1e3 * statistics.median(p_off), 1),
                "pipeline_cpu_ms_on": round(1e3 * statistics.median(p_on), 1),
                "inliers": r.info.get("inliers"),
                "refined": r.refined,
            }
        )
    return out


def detectors(entries: list[dict]) -> list[dict]:
    """Which detector, and is the pre-warp needed: raw-image matching + RANSAC E against the guided pipeline.

    ``raw``: detect and match on the original pair (2x scale change), essential matrix by RANSAC,
    ``cv2.recoverPose``. ``guided``: the refinement with that detector for the coarse homography.
    Errors are of the relative rotation against the truth; the navigation input carries a 0.3 deg
    attitude error on frame 2 and the thesis's positions (exact).
    """
    import dataclasses

    from flight_sw.guided_match import descriptor_matches
    from flight_sw.pose_refine import RefineParams, refine_pair
    from flight_sw.twoview import relative_pose, rot_exp
    from flight_sw.twoview import rotation_angle_deg as ang
    from protocol.pairdir import Pose, read_pair
    from studies.evaluate import true_poses

    out = []
    for e in entries:
        pair = read_pair(e["pair_dir"])
        t1, t2 = true_poses(pair)
        i1, i2 = pair.images[0], pair.images[-1]
        K = pair.camera.K
        Rt, _ = relative_pose(t1, t2)
        nav2 = Pose(t2.position, rot_exp(np.radians(0.3) * np.array([0.6, 0.8, 0.0])) @ t2.R, t2.time_s)
        for det in ("orb", "sift"):
            c0 = time.thread_time()
            full = np.ones(i1.shape, bool)
            pa, pb = descriptor_matches(i1, i2, full, det, 2000, 0.8)
            E, inl = cv2.findEssentialMat(pa, pb, K, cv2.RANSAC, 0.999, 1.0) if len(pa) >= 5 else (None, None)
            raw_err, raw_inl = math.nan, 0
            if E is not None and inl is not None and E.shape == (3, 3):
                _, R, _, _ = cv2.recoverPose(E, pa, pb, K, mask=inl.copy())
                raw_err, raw_inl = ang(R @ Rt.T), int(inl.sum())
            raw_ms = 1e3 * (time.thread_time() - c0)
            rp = dataclasses.replace(RefineParams(), detector=det)
            r = refine_pair(i1, i2, t1, nav2, pair.camera, params=rp)
            Rg, _ = relative_pose(r.pose1, r.pose2)
            out.append(
                {
                    "pair": f"s{e['seed']} {Path(e['pair_dir']).name}",
                    "detector": det,
                    "raw_matches": len(pa),
                    "raw_inliers": raw_inl,
                    "raw_rot_err_deg": round(raw_err, 3),
                    "raw_cpu_ms": round(raw_ms, 1),
                    "guided_coarse_inliers": r.info.get("coarse_inliers"),
                    "guided_inliers": r.info.get("inliers"),
                    "guided_rot_err_deg": round(ang(Rg @ Rt.T), 4),
                    "guided_cpu_ms": round(1e3 * r.info["cpu_s"], 1),
                }
            )
    return out


def _rotation_cases(i1, i2, t1, t2, cam, configs: dict, axes: np.ndarray, deg: float) -> dict[str, list[float]]:
    from flight_sw.pose_refine import refine_pair
    from flight_sw.twoview import relative_pose, rot_exp
    from flight_sw.twoview import rotation_angle_deg as ang
    from protocol.pairdir import Pose

    Rt, _ = relative_pose(t1, t2)
    out: dict[str, list[float]] = {name: [] for name in configs}
    for ax in axes:
        nav2 = Pose(t2.position, rot_exp(np.radians(deg) * ax) @ t2.R, t2.time_s)
        for name, rp in configs.items():
            r = refine_pair(i1, i2, t1, nav2, cam, params=rp)
            R, _ = relative_pose(r.pose1, r.pose2)
            out[name].append(ang(R @ Rt.T) if r.refined else math.nan)
    return out


def rotation_recovery(entries: list[dict], n_axes: int = 4, deg: float = 0.3) -> list[dict]:
    """Relative rotation left after refining a ``deg`` attitude error of frame 2 (random axes, positions exact).

    ``frame2``: navigation declares frame 1's attitude and both positions known (the test's setting);
    ``default``: the default priors. Pairs: ground_sim approach pairs of ``entries`` and three
    approach-geometry pairs from the exact-geometry renderer of tests/synthetic.py (256 px).
    """
    sys.path.insert(0, str(ROOT / "tests"))
    from synthetic import Texture, camera_fov30, crater, render, tilted_R

    from flight_sw.pose_refine import RefineParams
    from protocol.pairdir import Pose, read_pair
    from studies.evaluate import true_poses

    configs = {
        "frame2": RefineParams(nav_att_sigma_deg=0.001, nav_pos_sigma_m=0.01, nav_rel_att_sigma_deg=0.5),
        "default": RefineParams(),
    }
    rng = np.random.default_rng(7)
    groups: dict[str, dict[str, list[float]]] = {}
    for e in entries:
        pair = read_pair(e["pair_dir"])
        t1, t2 = true_poses(pair)
        axes = rng.normal(size=(n_axes, 3))
        axes /= np.linalg.norm(axes, axis=1, keepdims=True)
        res = _rotation_cases(pair.images[0], pair.images[-1], t1, t2, pair.camera, configs, axes, deg)
        g = groups.setdefault(f"ground_sim {pair.camera.width} px", {k: [] for k in configs})
        for k, v in res.items():
            g[k] += v
    cam = camera_fov30(256)
    R = tilted_R(49.0)
    t1, t2 = Pose(np.array([0.0, 300.0, 300.0]), R), Pose(np.array([0.0, 150.0, 150.0]), R)
    for seed in range(3):
        tex = Texture.random(600.0, 150.0 / cam.fx, seed, blur_cells=2.0)
        hf = lambda x, y, s=seed: crater(40, 6, 10 * s, 0)(x, y) + crater(25, 4, 30, -60)(x, y)  # noqa: E731
        i1, _ = render(cam, t1, hf, tex, ss=2)
        i2, _ = render(cam, t2, hf, tex, ss=2)
        axes = rng.normal(size=(n_axes, 3))
        axes /= np.linalg.norm(axes, axis=1, keepdims=True)
        res = _rotation_cases(i1, i2, t1, t2, cam, configs, axes, deg)
        g = groups.setdefault("exact renderer 256 px", {k: [] for k in configs})
        for k, v in res.items():
            g[k] += v
    out = []
    for name, g in groups.items():
        for k, v in g.items():
            a = np.array(v)
            out.append(
                {
                    "imagery": name,
                    "priors": k,
                    "cases": len(a),
                    "fallbacks": int(np.isnan(a).sum()),
                    "median_deg": round(float(np.nanmedian(a)), 4),
                    "p90_deg": round(float(np.nanpercentile(a, 90)), 4),
                    "max_deg": round(float(np.nanmax(a)), 4),
                    "share_le_0.01_deg": f"{100 * float(np.mean(a <= 0.01)):.0f} %",
                }
            )
    return out


def main(argv: list[str] | None = None) -> int:
    from ground_sim.seeds import SEED_SETS
    from studies.evaluate import render_cache

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seed-set", choices=sorted(SEED_SETS), default="held-out")
    ap.add_argument("--n-seeds", type=positive_int, default=2, help="first N seeds of the set")
    ap.add_argument(
        "--samples", type=positive_int, default=20, help="altitude samples per pair (attitude: the 6 levels)"
    )
    ap.add_argument("--altitudes", type=int, nargs="+", default=[125, 150, 250, 300])
    kinds = ["altitude", "attitude", "frame2", "cam2"]
    ap.add_argument("--kinds", nargs="+", default=["altitude", "attitude"], choices=kinds)
    ap.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    ap.add_argument("--cam2-samples", type=positive_int, default=2, help="cam2 kind: samples (alternating signs)")
    ap.add_argument("--alt-noise-m", type=float, default=0.0, help="Gaussian noise of the simulated altimeter")
    ap.add_argument("--cache", type=Path, default=Path("out/bench_pose/cache"))
    ap.add_argument("--out", type=out_dir, default=Path("out/bench_pose"))
    ap.add_argument("--timing-runs", type=positive_int, default=7)
    ap.add_argument("--skip-timing", action="store_true")
    ap.add_argument("--skip-sensitivity", action="store_true")
    ap.add_argument("--detectors", action="store_true", help="also compare ORB and SIFT, raw and guided")
    ap.add_argument("--rotation", action="store_true", help="also measure the recovery of a 0.3 deg rotation error")
    ap.add_argument("--refine", default="", help="RefineParams overrides for the sensitivity, e.g. nav_pos_sigma_m=0.3")
    a = ap.parse_args(argv)
    from flight_sw.pose_refine import RefineParams

    conv: dict[type, Callable[[str], object]] = {
        bool: lambda v: v.lower() in ("1", "true", "yes"),
        int: int,
        float: float,
        str: str,
    }
    try:  # each value parsed as its own field's type (the fields are named at run time: no one static type fits)
        over = dict(kv.split("=", 1) for kv in a.refine.split(",") if kv)
        fields: dict[str, Any] = {k: conv[type(getattr(RefineParams(), k))](v) for k, v in over.items()}
        rp = RefineParams(**fields)
    except (ValueError, TypeError, AttributeError, KeyError) as exc:
        raise InputError(f"--refine {a.refine!r}: expected K=V,... with K a field of RefineParams ({exc})") from None
    pin_one_core()
    seeds = list(SEED_SETS[a.seed_set][: a.n_seeds])
    entries = [{**e, "seed": s} for s in seeds for e in render_cache("approach", s, a.cache, altitudes=a.altitudes)]
    a.out.mkdir(parents=True, exist_ok=True)
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else math.nan
    if not a.skip_timing:
        t = timing(entries[: len(a.altitudes)], a.timing_runs)
        print(f"## cost per pair (one core, medians of {a.timing_runs}; host load {load:.1f})\n")
        print(markdown(t) + "\n", flush=True)
    if a.rotation:
        print(f"## rotation recovery (seeds {seeds}; 0.3 deg on frame 2 about random axes)\n")
        print(markdown(rotation_recovery(entries)) + "\n", flush=True)
    if a.detectors:
        print(f"## detectors (seeds {seeds}, 0.3 deg attitude error on frame 2)\n")
        print(markdown(detectors(entries)) + "\n", flush=True)
    if a.skip_sensitivity:
        return 0
    samples = {"altitude": a.samples, "attitude": 6, "frame2": 6, "cam2": a.cam2_samples}
    rows: list[dict] = []
    t0 = time.perf_counter()
    for k, e in enumerate(entries):
        rows += run_pair(e, a.kinds, samples, a.alt_noise_m, rp, tuple(a.variants))
        print(f"  pair {k + 1}/{len(entries)} done ({time.perf_counter() - t0:.0f} s)", file=sys.stderr, flush=True)
    cols = list(dict.fromkeys(k for r in rows for k in r))
    with (a.out / "pose_rows.csv").open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=cols, lineterminator="\n")
        w.writeheader()
        w.writerows(rows)
    ref = [r for r in rows if r["variant"] in ("perfect", "perfect_on")]
    pm = {}
    for v in ("perfect", "perfect_on"):
        rr = [r for r in ref if r["variant"] == v]
        pm[v] = {k: round(float(np.median([r[k] for r in rr])), 3) for k in ("mean_abs", "mad", "detrended")}
    print(f"## sensitivity ({a.seed_set} seeds {seeds}, fast preset, % increase over perfect knowledge)\n")
    print(f"refinement parameters: {a.refine or 'defaults'}\n")
    print(f"perfect knowledge, median over pairs (m): {pm['perfect']}; refined from true poses: {pm['perfect_on']}\n")
    per = {(r["seed"], r["altitude_m"]): r for r in ref if r["variant"] == "perfect"}
    for metric in ("mean_abs", "mad"):
        ch = [
            100.0 * (r[metric] / per[(r["seed"], r["altitude_m"])][metric] - 1)
            for r in ref
            if r["variant"] == "perfect_on"
        ]
        print(
            f"refining the true poses changes {metric} by {min(ch):+.0f} / {np.median(ch):+.0f} / {max(ch):+.0f} %"
            " (min / median / max over pairs)"
        )
    print()
    print(markdown(summarise(rows)))
    if "altitude" in a.kinds:
        print("\n## datum: median signed DEM error against the reported altitude errors (altitude study)\n")
        print(markdown(datum_fit(rows)))
    print(f"\nrows: {a.out / 'pose_rows.csv'}")
    return 0


if __name__ == "__main__":
    run(main)
