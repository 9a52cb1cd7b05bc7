"""Where the footprint slope's error comes from: the DEM's and the shading's, split along and across the sun.

    .venv/bin/python bench/slope_errors.py --n-seeds 3                                   # tuning seeds 0-2
    .venv/bin/python bench/slope_errors.py --n-seeds 3 --variants base sgm_p2=256 sgm_radius=3
    .venv/bin/python bench/slope_errors.py --n-seeds 10 --ceiling                        # truth only

Each pair of the cases (rendered by ``bench/eval_flight.py`` into ``--cache``, reused) runs through ``fast``
with ``keep_layers`` and its Params overridden by each variant (``k=v,k=v``; ``base`` = none). The truth is
the footprint plane of the true elevation. All slopes are in units of the slope limit (``a = tan(slope) /
tan(15 deg)``, psafe.features). Per pair, medians over the covered pixels:

* ``a``, ``a_pc``: the P(safe) features (the DEM's footprint slope; the same with its sun-ward part read from
  the shading, photoclinometry.py): ``|err|`` against the truth; ``clear < 0.4``: share of clearly safe pixels
  (truth hazard ratio < 0.5) the feature puts under the 0.4x cap (callable at all); ``steep < 0.6``: share of
  truly steep pixels (truth ``a`` > 1) it puts under 0.6x (a wall that looks like gentle ground);
* ``dem along / across``, ``shading along``: the footprint gradient split along the sun's horizontal
  direction and across it (:func:`flight_sw.photoclinometry.sunward_split`), each plane fitted to the pixels of
  a footprint-wide square of i1 (a nadir approximation of the pipeline's ground-grid footprint);
* ``tail``: of the truly steep pixels that ``a_pc`` puts under 0.6x, the share barely steep (truth ``a`` <
  1.25), in a truly steep region of at least 10 footprint areas (``big``), and within a footprint of that
  region's edge (``edge``);
* ``dem err``: mean |elevation error| (m), ``cov``: share of covered pixels with an elevation.

The table gives the median over the pairs of each case and, beside it, the worst pair. ``--ceiling``
instead prints, from the truth alone, the CDI an estimator of the hazard ratio with Gaussian noise ``s``
(ratio units) could reach if it found every hazard and called safe every pixel at least 1.9 s under the
limit (P(safe) >= 0.97): an upper bound for a given precision, not for a given pipeline (its error tails
are heavier). Tune on ``tuning`` seeds.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
from pathlib import Path
from typing import Any

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from _cli import InputError, out_file, positive_int, run, unknown, write_out  # noqa: E402

TAN_LIMIT = math.tan(math.radians(15.0))
CEILING_SIGMAS = (0.0, 0.1, 0.15, 0.2, 0.25, 0.3)
TAIL_BIG_FP = 10.0  # a truly steep region of at least this many footprint areas is "big"
CEILING_K = 1.9  # one-sided 97 %: the P(safe) floor of `fast`
METRICS = (
    "a |err|",
    "a clear<0.4",
    "a steep<0.6",
    "a_pc |err|",
    "a_pc clear<0.4",
    "a_pc steep<0.6",
    "dem along",
    "dem across",
    "shading along",
    "tail a<1.25",
    "tail big",
    "tail edge",
    "dem err m",
    "cov",
)
# the worse end of each metric over pairs (worst case beside the median): smaller is worse for these
WORSE_LOW = ("a clear<0.4", "a_pc clear<0.4", "cov")


def parse_variant(spec: str) -> dict[str, Any]:
    """``base`` -> {}; ``k=v,k=v`` -> Params overrides, each value parsed as its field's type
    (bench_multiframe.preset_with: booleans true/false/1/0, a path stays a string); a bad one ends with one line."""
    if spec == "base":
        return {}
    from bench_multiframe import preset_with

    pairs = spec.split(",")
    bad = [kv for kv in pairs if not kv.partition("=")[2]]
    if bad:
        raise InputError(f"--variants {spec!r}: expected base or k=v,k=v, got {bad[0]!r}")
    try:
        prm = preset_with("fast", pairs)
    except (ValueError, AttributeError, KeyError) as exc:
        raise InputError(f"--variants {spec!r}: {exc}") from None
    return {k: getattr(prm, k) for k in (kv.partition("=")[0] for kv in pairs)}


def window_plane(z: np.ndarray, X: np.ndarray, Y: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares plane ``z = c + p X + q Y`` of the finite ``z`` in each ``k x k`` square: ``(p, q)``.

    Box sums of the centred moments (slope.py's scheme) on world coordinates, NaN where the square holds
    less than half its pixels or they are collinear."""
    ok = np.isfinite(z) & np.isfinite(X) & np.isfinite(Y)
    w = ok.astype(np.float64)
    x0, y0 = float(np.nanmedian(X)), float(np.nanmedian(Y))
    x = np.where(ok, X - x0, 0.0)
    y = np.where(ok, Y - y0, 0.0)
    zz = np.where(ok, z, 0.0).astype(np.float64)

    def box(a: np.ndarray) -> np.ndarray:
        return cv2.boxFilter(a, cv2.CV_64F, (k, k), normalize=False, borderType=cv2.BORDER_CONSTANT)

    n = box(w)
    with np.errstate(invalid="ignore", divide="ignore"):
        mx, my, mz = box(x) / n, box(y) / n, box(zz) / n
        cxx, cxy, cyy = box(x * x) / n - mx * mx, box(x * y) / n - mx * my, box(y * y) / n - my * my
        cxz, cyz = box(x * zz) / n - mx * mz, box(y * zz) / n - my * mz
        det = cxx * cyy - cxy * cxy
        p = (cxz * cyy - cyz * cxy) / det
        q = (cyz * cxx - cxz * cxy) / det
    bad = (n < 0.5 * k * k) | ~(det > 1e-9)
    return np.where(bad, np.nan, p), np.where(bad, np.nan, q)


def _share(x: np.ndarray, sel: np.ndarray) -> float:
    sel = sel & np.isfinite(x)
    return float(np.mean(x[sel])) if sel.any() else math.nan


def _med_abs(x: np.ndarray, sel: np.ndarray) -> float:
    sel = sel & np.isfinite(x)
    return float(np.median(np.abs(x[sel]))) if sel.any() else math.nan


def pair_metrics(pair_dir: str, over: dict[str, Any]) -> dict[str, float]:
    """The module doc's metrics of one rendered pair under one variant."""
    from eval_flight import run_pair

    from flight_sw.georef import backproject
    from flight_sw.photoclinometry import incidence_cosine, measured_incidence, sunward_split
    from flight_sw.pipeline import PRESETS
    from protocol.pairdir import read_pair

    pair = read_pair(pair_dir)
    res = run_pair(pair, dataclasses.replace(PRESETS["fast"], keep_layers=True, **over))
    gt = pair.truth["elevation"].astype(np.float64)
    hz = pair.truth["hazard"]
    z = res.elevation.astype(np.float64)
    fp = float(res.info["footprint_px"])
    k = max(3, int(2 * round(fp / 2) + 1))
    X, Y = backproject(pair.camera, pair.poses[0], np.where(np.isfinite(z), z, gt))
    pt, qt = window_plane(gt, X, Y, k)
    pd, qd = window_plane(z, X, Y, k)
    a_true = np.hypot(pt, qt) / TAN_LIMIT
    cov = res.covered & np.isfinite(a_true)
    clear, steep = cov & (hz < 0.5), cov & (a_true > 1.0)
    out: dict[str, float] = {}
    for f in ("a", "a_pc"):
        a = res.layers[f]
        out[f"{f} |err|"] = _med_abs(a - a_true, cov)
        out[f"{f} clear<0.4"] = _share(np.where(np.isfinite(a), a < 0.4, np.nan), clear)
        out[f"{f} steep<0.6"] = _share(np.where(np.isfinite(a), a < 0.6, np.nan), steep)
    # the tail: truly steep points a_pc calls gentle. How steep, in how large a steep region, how near its edge
    tail = steep & (res.layers["a_pc"] < 0.6)
    if tail.any():
        _, lab, stats, _ = cv2.connectedComponentsWithStats(steep.view(np.uint8), connectivity=8)
        big = stats[lab, cv2.CC_STAT_AREA] >= TAIL_BIG_FP * fp * fp
        inner = cv2.erode(steep.view(np.uint8), np.ones((k, k), np.uint8)).view(bool)
        out["tail a<1.25"] = float(np.mean(a_true[tail] < 1.25))
        out["tail big"] = float(np.mean(big[tail]))
        out["tail edge"] = float(np.mean(~inner[tail]))
    lit = cov & ~res.layers["dark"]
    if pair.sun is not None:
        sun = pair.sun.direction()
        ci = incidence_cosine(pd.astype(np.float32), qd.astype(np.float32), sun)
        seen = ~res.layers["dark"] & np.isfinite(z)
        c = measured_incidence(pair.images[0], ci, seen, fp, min(64.0, max(16.0, 8.0 * fp)))
        sh = math.hypot(float(sun[0]), float(sun[1]))
        hx, hy = (float(sun[0]) / sh, float(sun[1]) / sh) if sh > 1e-6 else (1.0, 0.0)
        a_t, b_t = pt * hx + qt * hy, qt * hx - pt * hy
        a_d, b_d = pd * hx + qd * hy, qd * hx - pd * hy
        a_s, _ = sunward_split(pd, qd, c, sun)
        out["dem along"] = _med_abs((a_d - a_t) / TAN_LIMIT, lit)
        out["dem across"] = _med_abs((b_d - b_t) / TAN_LIMIT, lit)
        out["shading along"] = _med_abs((a_s - a_t) / TAN_LIMIT, lit)
    e = np.abs(res.elevation - gt)[res.covered & np.isfinite(res.elevation)]
    out["dem err m"] = float(e.mean()) if e.size else math.nan
    out["cov"] = float(np.isfinite(res.elevation)[res.covered].mean()) if res.covered.any() else math.nan
    return out


def ceiling(hazard_ratio: np.ndarray) -> list[float]:
    """CDI % reachable with hazard-ratio noise ``s`` (module doc), for each of ``CEILING_SIGMAS``."""
    h = hazard_ratio[np.isfinite(hazard_ratio)]
    if h.size == 0:
        return [math.nan] * len(CEILING_SIGMAS)
    unsafe = float(np.mean(h >= 1.0))
    return [100.0 * (unsafe + float(np.mean(h < 1.0 - CEILING_K * s))) for s in CEILING_SIGMAS]


def main(argv: list[str] | None = None) -> int:
    from eval_flight import CASES, _med, render_case

    from ground_sim.seeds import SEED_SETS

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--set", choices=tuple(SEED_SETS), default="tuning")
    ap.add_argument("--n-seeds", type=positive_int, default=3)
    ap.add_argument("--seeds", type=int, nargs="*")
    ap.add_argument("--cases", nargs="+", default=["vertical", "thesis_vertical", "approach", "thesis_approach"])
    ap.add_argument("--altitudes", type=int, nargs="*", help="lower-frame altitudes (m); default: all of a case's")
    ap.add_argument("--cache", default="/tmp/flight_eval_cache")
    ap.add_argument("--variants", nargs="+", default=["base"], help="base, or Params overrides k=v,k=v")
    ap.add_argument("--ceiling", action="store_true", help="print the truth-only CDI ceiling table instead")
    ap.add_argument("--json", type=out_file, help="write every pair's metrics here")
    args = ap.parse_args(argv)
    unknown("--cases", args.cases, CASES)
    variants = {v: parse_variant(v) for v in args.variants}
    seeds = args.seeds if args.seeds else list(SEED_SETS[args.set][: args.n_seeds])
    cv2.setNumThreads(1)
    pairs = [
        (c, e["pair_dir"])
        for c in args.cases
        for s in seeds
        for e in render_case(c, s, Path(args.cache), args.altitudes)
    ]
    print(f"{len(pairs)} pairs, seeds {seeds}", flush=True)
    if args.ceiling:
        from protocol.pairdir import read_pair

        ceilings = {c: [ceiling(read_pair(d).truth["hazard"]) for cc, d in pairs if cc == c] for c in args.cases}
        print("\n| case | pairs | " + " | ".join(f"s = {s:g}: CDI % med / min" for s in CEILING_SIGMAS) + " |")
        print("|---|---:|" + "---|" * len(CEILING_SIGMAS))
        for c, r in ceilings.items():
            cols = [f"{_med([x[i] for x in r]):.1f} / {min(x[i] for x in r):.1f}" for i in range(len(CEILING_SIGMAS))]
            print(f"| {c} | {len(r)} | " + " | ".join(cols) + " |")
        return 0
    dump: dict[str, list[dict[str, Any]]] = {}
    print("\n(each cell: median over the pairs / the worst pair)")
    print("\n| variant | case | pairs | " + " | ".join(METRICS) + " |")
    print("|---|---|---:|" + "---:|" * len(METRICS))
    for name, over in variants.items():
        rows = []
        for i, (c, d) in enumerate(pairs):
            rows.append({"case": c, "pair_dir": d, **pair_metrics(d, over)})
            print(f"  {name}: {i + 1}/{len(pairs)}", end="\r", file=sys.stderr, flush=True)
        dump[name] = rows
        for c in [*args.cases, "all"]:
            sel = [r for r in rows if c in ("all", r["case"])]
            cells = []
            for m in METRICS:
                v = [x for x in (r.get(m, math.nan) for r in sel) if math.isfinite(x)]
                worst = (min(v) if m in WORSE_LOW else max(v)) if v else math.nan
                cells.append(f"{_med(v):.3f} / {worst:.3f}")
            vals = " | ".join(cells)
            print(f"| {name} | {c} | {len(sel)} | {vals} |", flush=True)
    if args.json:
        write_out(args.json, json.dumps(dump, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    run(main)
