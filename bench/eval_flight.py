"""Tuning / evaluation driver for the flight pipeline (issue 9): renders into a cache, prints the tables.

    .venv/bin/python bench/eval_flight.py --set tuning --n-seeds 3                    # tune on seeds 0-2
    .venv/bin/python bench/eval_flight.py --set held-out --n-seeds 4 --json out.json  # report (1000-1003)
    .venv/bin/python bench/eval_flight.py --cases crater lowsun tilted --set held-out --n-seeds 2
    .venv/bin/python bench/eval_flight.py --ablation --set tuning --n-seeds 2         # the ablation table

Cases: ``vertical`` and ``approach`` are the thesis scenarios on the ``default`` and ``approach`` scene
presets; ``crater`` is a vertical descent into ``bench/scenes/deep_crater.toml`` (floor ~50 m below the
datum); ``lowsun`` the vertical scenario under a 10 deg sun; ``tilted`` the approach over ``bench/scenes/tilted.toml``;
``thesis_vertical`` and ``thesis_approach`` the scenarios on the library's ``thesis`` scene with its sun
(the scene ``render``, ``evaluate`` and ``run`` use by default; more hazardous than ``default``).
Renders go to ``--cache`` (default ``/tmp/flight_eval_cache``; a case's directory carries its raster's
tag, ``_tiles`` by default) and are reused. Every pair is scored
against its ground truth with ``studies.evaluate.score_arrays`` (pixel FP/FN/CDI, DEM error) plus the
top-ranked site's footprint (``ground_sim.gridscore.judge_site``, DESIGN.md's rule). Seeds come from
``ground_sim.seeds``: tune on ``tuning``, quote ``held-out``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import statistics
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from _cli import InputError, check_dir, out_file, positive_int, run, unknown, write_out  # noqa: E402

from flight_sw.psafe import model_call, model_for_image  # noqa: E402
from ground_sim.render import DEFAULT_RASTER, RASTERS  # noqa: E402

SCENES = ROOT / "bench" / "scenes"
# case -> (trajectory, scene spec, sun (az, el) or None for the scenario default)
CASES: dict[str, tuple[str, str, tuple[float, float] | None]] = {
    "vertical": ("vertical", "default", None),
    "approach": ("approach", "approach", None),
    "crater": ("vertical", str(SCENES / "deep_crater.toml"), None),
    "lowsun": ("vertical", "default", (135.0, 10.0)),
    "tilted": ("approach", str(SCENES / "tilted.toml"), None),
    # the scenarios on the scene library's `thesis` scene (their default in render/evaluate/run), its sun
    "thesis_vertical": ("vertical", "thesis", None),
    "thesis_approach": ("approach", "thesis", None),
}


def case_key(
    case: str, seed: int, max_cells: int | None = None, raster: str = DEFAULT_RASTER, image_px: int | None = None
) -> str:
    """``<case>_s<seed>`` plus ``studies.evaluate.render_tag`` (``_tiles``, ``_cells<N>``) and ``_px<N>`` for a
    camera other than the thesis's 512 px: renders, P(safe) layers and fusion grids of one raster and camera are
    named apart from another's in any cache directory."""
    from studies.evaluate import THESIS_CAMERA_PX, render_tag

    px = "" if image_px is None or image_px == THESIS_CAMERA_PX else f"_px{image_px}"
    return f"{case}_s{seed}{render_tag(max_cells, raster)}{px}"


def check_altitudes(cases: list[str], altitudes: list[int] | None) -> None:
    """Refuse ``--altitudes`` that would leave a case without a pair or that no case has, naming each case's
    (lower-frame) altitudes: :func:`render_case` keeps only the pairs at those altitudes, silently."""
    from ground_sim import trajectory

    if not altitudes:
        return
    have = {c: sorted({int(round(s.altitude_m)) for s in getattr(trajectory, CASES[c][0])()}) for c in cases}
    listed = "; ".join(f"{c} has {', '.join(map(str, a))}" for c, a in have.items())
    nowhere = sorted({a for a in altitudes if not any(a in h for h in have.values())})
    if nowhere:
        raise InputError(f"--altitudes: no pair at {', '.join(map(str, nowhere))} m ({listed})")
    empty = [c for c, h in have.items() if not set(h) & set(altitudes)]
    if empty:
        raise InputError(f"--altitudes: no pair of {', '.join(empty)} at {', '.join(map(str, altitudes))} m ({listed})")


def cached_raster(pair_dir: Path) -> str:
    """``"tiles"`` when every view of a rendered pair was drawn from rasters per tile, else ``"view"``."""
    views = json.loads((pair_dir / "pair.json").read_text()).get("render") or [{}]
    return "tiles" if all(isinstance(v, dict) and "raster_tiles" in v for v in views) else "view"


def render_case(
    case: str,
    seed: int,
    cache: Path,
    altitudes: list[int] | None = None,
    max_cells: int | None = None,
    raster: str = DEFAULT_RASTER,
    image_px: int | None = None,
) -> list[dict[str, Any]]:
    """Render (or reuse) every pair of a case for one scene seed (``max_cells``, ``raster``: the terrain raster;
    ``image_px``: a square thesis camera of this size, default the scenario's 512 px)."""
    from ground_sim import trajectory
    from ground_sim.descent import render_pair
    from ground_sim.library import scene_sun
    from ground_sim.render import MAX_CELLS, RENDER_VERSION
    from ground_sim.render_cache import render_version, reusable
    from ground_sim.scene import Scene, load_scene_params
    from protocol.pairdir import Sun, square_camera, write_pair_atomic

    traj, scene_spec, sun = CASES[case]
    specs = getattr(trajectory, traj)(None if image_px is None else square_camera(image_px))
    if altitudes:
        specs = [s for s in specs if int(round(s.altitude_m)) in altitudes]
    out = cache / case_key(case, seed, max_cells, raster, image_px)
    params = load_scene_params(scene_spec, traj)  # the scenario's variant, where the scene has one
    scene = None
    entries = []
    for spec in specs:
        d = out / spec.label.replace("/", "_")
        have = cached_raster(d) if render_version(d) == RENDER_VERSION else raster
        if have != raster:  # an untagged cache of tiled renders from before stop 21: never score it as another
            raise SystemExit(f"eval_flight: {d} holds raster={have} renders, not {raster}: use another --cache")
        # none there, or a stale or damaged one, now removed; a cache from before pairs recorded their scene and
        # render-code fingerprints is trusted, with a warning (hours of renders), and later changes are seen
        if not reusable(d, scene=params, trust_unrecorded=True):
            scene = scene or Scene(params, seed)  # the scenario's variant, where the scene has one
            s = Sun(*sun) if sun else scene_sun(scene, traj, seed)  # a library scene's own sun, else the default
            mc = MAX_CELLS if max_cells is None else max_cells
            write_pair_atomic(d, render_pair(scene, spec, s, seed=seed, max_cells=mc, raster=raster))
        entries.append({"case": case, "seed": seed, "altitude_m": int(round(spec.altitude_m)), "pair_dir": str(d)})
    return entries


def run_pair(pair: Any, preset: Any) -> Any:
    """The pipeline on a pair's widest two frames with its altimeter reading, as the flight process and
    ``hazard-hil evaluate`` run it."""
    from flight_sw.pipeline import run_pipeline

    return run_pipeline(
        pair.images[0],
        pair.images[-1],
        pair.poses[0],
        pair.poses[-1],
        pair.camera,
        preset=preset,
        altimeter_m=pair.altimeter_m,
        sun_elevation_deg=pair.sun.elevation_deg if pair.sun else None,
        sun_azimuth_deg=pair.sun.azimuth_deg if pair.sun else None,
    )


def score_pair(pair_dir: str, preset: Any) -> dict[str, Any]:
    """Run the pipeline on one rendered pair; pixel scores, DEM error, coverage, top-site safety, CPU time."""
    from ground_sim.gridscore import judge_site, scored_area, site_verdict
    from protocol.pairdir import read_pair
    from studies.evaluate import _site_radius_px, score_arrays
    from studies.multiframe import world_of

    pair = read_pair(pair_dir)
    c0 = time.thread_time()
    res = run_pair(pair, preset)
    cpu = time.thread_time() - c0
    causes: dict[str, float] = {}
    if preset.dem == "sgm":  # the same pixels again, keeping the evidence layers (not timed)
        lay = run_pair(pair, dataclasses.replace(preset, keep_layers=True))
        causes = error_causes(lay.layers, lay.state, lay.elevation, pair.truth["hazard"], res.covered)
    tz = pair.truth["elevation"].astype(np.float32)
    world = world_of(pair)
    # DESIGN.md's covered area, as `score` takes it (frame-0 pixels whose true ground the last frame sees); the
    # pipeline's own `covered` left out its unmapped rim, and figures before stop 65 were scored over that
    area = scored_area(pair, world)
    radius = _site_radius_px(pair.camera, pair.truth["depth"], area)
    est = {"elevation": res.elevation, "hazard": res.hazard, "slope_deg": None, "roughness_m": None}
    truth = {"elevation": tz, "hazard": pair.truth["hazard"]}
    box = np.zeros(tz.shape, bool)
    m = score_arrays(est, truth, covered=area, epipole_box=box, site_radius_px=radius)
    top, top_unseen = math.nan, 0
    if res.sites:  # DESIGN.md's rule: every pixel whose true ground lies in the footprint, which frame 0 must hold
        j = judge_site((res.sites[0].x, res.sites[0].y), world[..., :2], pair.truth["hazard"])
        top, top_unseen = 100.0 * j["safe"], int(site_verdict(j) is None)
    st = res.state[res.covered]
    return {
        "fp": m["fp_pct"],
        "fn": m["fn_pct"],
        "cdi": m["cdi_pct"],
        "dem": m["dem_mean_abs_m"],
        "valid": 100.0 * res.valid_fraction,
        # the DEM's coverage of the true overlap (issue 9's "covers >= 90 % of the overlap"); "valid" is of its own
        "dem_cov": 100.0 * float(np.isfinite(res.elevation[area]).mean()) if area.any() else math.nan,
        "filled": 100.0 * float(res.info.get("dem_filled_fraction", 0.0)),  # of "valid": gap fills, not matches
        "unknown": 100.0 * float(np.mean(st == 2)) if st.size else math.nan,
        "n_sites": len(res.sites),
        "top_safe": top,
        "top_unseen": top_unseen,  # its footprint leaves frame 0 (not confirmed, so not safe)
        "no_site": res.info.get("no_site_reason", ""),
        "cpu_s": cpu,
        "level": res.level,
        **causes,
    }


# why a pixel is where it is, in priority order (the first that applies); see error_causes
CAUSES = ("shadow", "no_dem", "over_limit", "uncertain", "near_limit", "shading", "other")
CLEAR_RATIO = 0.5  # a truth hazard ratio (max of slope, roughness, ... over their limits) below this: clearly safe


def error_causes(
    layers: dict[str, np.ndarray],
    state: np.ndarray,
    elevation: np.ndarray,
    hazard_true: np.ndarray,
    covered: np.ndarray,
) -> dict[str, float]:
    """FN and FP pixels (% of the covered pixels) by the first cause that applies:

    ``shadow`` dark-shadow cue; ``no_dem`` no elevation; ``over_limit`` estimated slope or
    roughness over its limit (a >= 1 or rough >= 1); ``uncertain`` slope uncertainty >= the
    limit (u >= 1); ``near_limit`` estimated slope 0.6-1x the limit; ``shading`` strong shading
    at or around the pixel (|rho| > 0.1 or > 20 % of the 3-footprint neighbourhood); ``other``
    (the call ran out of budget / P(safe) too low for none of the above). For FP the same
    classes say what the evidence looked like where a hazard was called safe.
    """
    cov = np.asarray(covered, bool)
    n = max(1, int(cov.sum()))
    th = np.asarray(hazard_true)[cov] >= 1.0
    called = np.asarray(state)[cov] == 0
    clear = np.asarray(hazard_true)[cov] < CLEAR_RATIO  # clearly safe: every hazard under half its limit
    cls = cause_classes(layers, elevation, cov)
    out: dict[str, float] = {}
    for i, name in enumerate(CAUSES):
        m = cls == i
        out[f"fn_{name}"] = 100.0 * float((m & ~called & ~th).sum()) / n
        out[f"fn_{name}_clear"] = 100.0 * float((m & ~called & clear).sum()) / n
        out[f"fp_{name}"] = 100.0 * float((m & called & th).sum()) / n
    return out


def cause_classes(layers: dict[str, np.ndarray], elevation: np.ndarray, covered: np.ndarray) -> np.ndarray:
    """Per covered pixel, the index in ``CAUSES`` of the first cause that applies (see :func:`error_causes`)."""
    cov = np.asarray(covered, bool)
    g = {k: np.asarray(v)[cov] for k, v in layers.items()}
    nodem = ~np.isfinite(np.asarray(elevation)[cov]) | ~np.isfinite(g["a"])
    with np.errstate(invalid="ignore"):
        cls = [
            g["dark"].astype(bool),
            nodem,
            (g["a"] >= 1.0) | (g["rough"] >= 1.0),
            g["u"] >= 1.0,
            g["a"] >= 0.6,
            (np.abs(g["rho"]) > 0.1) | (g["nwall"] > 0.2),
        ]
    out = np.full(nodem.shape, len(CAUSES) - 1, np.int8)  # "other"
    for i in range(len(cls) - 1, -1, -1):  # the first that applies wins
        out[cls[i]] = i
    return out


def causes_table(rows: list[dict[str, Any]], title: str) -> str:
    """Median FN share per cause (and the FP share per cause, summed over pairs / pairs) per (case, altitude)."""
    if not rows or "fn_other" not in rows[0]:
        return ""
    out = [
        f"\n### {title}\n",
        "FN (truly safe, not called safe) by cause, median % of the covered pixels; FP column: mean FP % by cause "
        "(the largest two)\n",
        "| case | alt m | FN % | " + " | ".join(CAUSES) + " | FP % mean: where |",
        "|---|---:|---:|" + "---:|" * len(CAUSES) + "---|",
    ]
    keys = sorted({(r["case"], r["altitude_m"]) for r in rows}, key=lambda k: (list(CASES).index(k[0]), k[1]))
    for case, alt in keys:
        rs = [r for r in rows if r["case"] == case and r["altitude_m"] == alt]
        fpc = sorted(((statistics.mean(r[f"fp_{c}"] for r in rs), c) for c in CAUSES), reverse=True)[:2]
        out.append(
            f"| {case} | {alt} | {_med([r['fn'] for r in rs]):.1f} | "
            + " | ".join(f"{_med([r[f'fn_{c}'] for r in rs]):.1f}" for c in CAUSES)
            + f" | {statistics.mean(r['fp'] for r in rs):.2f}: "
            + ", ".join(f"{c} {v:.2f}" for v, c in fpc)
            + " |"
        )
    return "\n".join(out)


def clear_ground_table(rows: list[dict[str, Any]], title: str) -> str:
    """Per case, the mean FN share per cause over its pairs and the part of it on clearly safe ground (truth
    hazard ratio < ``CLEAR_RATIO``): where more evidence, not a better decision rule, would gain CDI."""
    if not rows or "fn_other_clear" not in rows[0]:
        return ""
    out = [
        f"\n### {title}\n",
        f"FN by cause, mean % of the covered pixels over the pairs: all / on clearly safe ground (truth hazard "
        f"ratio < {CLEAR_RATIO})\n",
        "| case | pairs | " + " | ".join(CAUSES) + " |",
        "|---|---:|" + "---|" * len(CAUSES),
    ]
    for case in sorted({r["case"] for r in rows}, key=list(CASES).index):
        rs = [r for r in rows if r["case"] == case]
        cells = [
            f"{statistics.mean(r[f'fn_{c}'] for r in rs):.1f} / {statistics.mean(r[f'fn_{c}_clear'] for r in rs):.1f}"
            for c in CAUSES
        ]
        out.append(f"| {case} | {len(rs)} | " + " | ".join(cells) + " |")
    return "\n".join(out)


def _thesis_dem() -> dict[tuple[str, int], float]:
    from studies.evaluate import load_thesis

    return {
        (v.scenario, v.altitude_m): v.value
        for v in load_thesis()
        if v.metric == "dem_mean_abs_m" and v.table in ("6.2", "6.9")
    }


def _med(v: list[float]) -> float:
    v = [x for x in v if x is not None and math.isfinite(x)]
    return statistics.median(v) if v else math.nan


def table(rows: list[dict[str, Any]], title: str) -> str:
    """Markdown table per (case, altitude): coverage min/median, DEM error vs 0.5x thesis, FP worst/median,
    FN and CDI median, top-site safety, CPU time."""
    thesis = _thesis_dem()
    out = [
        f"\n### {title}\n",
        "| case | alt m | pairs | DEM valid % min / med | DEM err m med / worst | 0.5x thesis m | FP % med / worst "
        "| FN % med | CDI % med / min | unknown % med | top site safe | no site | CPU s med |",
        "|---|---:|---:|---|---|---:|---|---:|---|---:|---:|---:|---:|",
    ]
    keys = sorted({(r["case"], r["altitude_m"]) for r in rows}, key=lambda k: (list(CASES).index(k[0]), k[1]))
    for case, alt in keys:
        rs = [r for r in rows if r["case"] == case and r["altitude_m"] == alt]
        th = thesis.get((CASES[case][0], alt), math.nan)
        tops = [r["top_safe"] for r in rs if math.isfinite(r["top_safe"])]
        out.append(
            f"| {case} | {alt} | {len(rs)} | {min(r['valid'] for r in rs):.1f} / {_med([r['valid'] for r in rs]):.1f} "
            f"| {_med([r['dem'] for r in rs]):.3f} / {max(r['dem'] for r in rs):.3f} | {0.5 * th:.3f} "
            f"| {_med([r['fp'] for r in rs]):.2f} / {max(r['fp'] for r in rs):.2f} | {_med([r['fn'] for r in rs]):.1f} "
            f"| {_med([r['cdi'] for r in rs]):.1f} / {min(r['cdi'] for r in rs):.1f} "
            f"| {_med([r['unknown'] for r in rs]):.1f} | {sum(t >= 100 for t in tops)}/{len(tops)} "
            f"| {sum(1 for r in rs if r['n_sites'] == 0)} | {_med([r['cpu_s'] for r in rs]):.3f} |"
        )
    tops = [r["top_safe"] for r in rows if math.isfinite(r["top_safe"])]
    out.append(
        f"\nall: {len(rows)} pairs, FP worst {max(r['fp'] for r in rows):.2f} %, median CDI "
        f"{_med([r['cdi'] for r in rows]):.1f} %, DEM valid min {min(r['valid'] for r in rows):.1f} % "
        f"(matched, without gap fills: {min(r['valid'] - r.get('filled', 0.0) for r in rows):.1f} %; of the true "
        f"overlap: {min(r.get('dem_cov', math.nan) for r in rows):.1f} %), top site "
        f"truly safe {sum(t >= 100 for t in tops)}/{len(tops)} ({sum(r.get('top_unseen', 0) for r in rows)} "
        f"not confirmed: footprint off frame 0), no site {sum(1 for r in rows if r['n_sites'] == 0)}, "
        f"CPU median {_med([r['cpu_s'] for r in rows]):.3f} s"
    )
    return "\n".join(out)


def library_pairs(root: Path, raster: str = DEFAULT_RASTER) -> list[dict[str, Any]]:
    """Every pair of ``raster`` in a landing render cache (``hazard-hil landings --cache``), as eval entries of
    its library scene: the issue's "and on the scene library" criteria, pair by pair."""
    out = []
    for pj in sorted(root.glob("*/pair.json")):
        if cached_raster(pj.parent) != raster:
            continue
        meta = json.loads(pj.read_text())
        out.append(
            {
                "case": str(meta.get("scene", "?")),
                "scenario": str(meta.get("scenario", "?")),
                "seed": int(meta.get("scene_seed", -1)),
                "altitude_m": int(round(float(meta.get("altitude_m", 0)))),
                "pair_dir": str(pj.parent),
            }
        )
    if not out:
        raise SystemExit(f"eval_flight: no rendered pair (*/pair.json) of raster {raster} in {root}")
    return out


def library_table(rows: list[dict[str, Any]], title: str) -> str:
    """Markdown table per library scene: pixel FP worst and pairs over 1 %, CDI, DEM coverage, top site."""
    out = [
        f"\n### {title}\n",
        "| scene | pairs | FP % worst | pairs FP > 1 % | FP % med | CDI % med / min | DEM valid % min "
        "| top site safe |",
        "|---|---:|---:|---:|---:|---|---:|---:|",
    ]
    groups = sorted({r["case"] for r in rows}) + ["all"]
    for g in groups:
        rs = rows if g == "all" else [r for r in rows if r["case"] == g]
        tops = [r["top_safe"] for r in rs if math.isfinite(r["top_safe"])]
        out.append(
            f"| {g} | {len(rs)} | {max(r['fp'] for r in rs):.2f} | {sum(r['fp'] > 1.0 for r in rs)} "
            f"| {_med([r['fp'] for r in rs]):.2f} "
            f"| {_med([r['cdi'] for r in rs]):.1f} / {min(r['cdi'] for r in rs):.1f} "
            f"| {min(r['valid'] for r in rs):.1f} | {sum(t >= 100 for t in tops)}/{len(tops)} |"
        )
    return "\n".join(out)


def summary(rows: list[dict[str, Any]]) -> dict[str, float]:
    tops = [r["top_safe"] for r in rows if math.isfinite(r["top_safe"])]
    return {
        "pairs": len(rows),
        "valid_min": min(r["valid"] for r in rows),
        "valid_med": _med([r["valid"] for r in rows]),
        "dem_med": _med([r["dem"] for r in rows]),
        "fp_med": _med([r["fp"] for r in rows]),
        "fp_max": max(r["fp"] for r in rows),
        "fn_med": _med([r["fn"] for r in rows]),
        "cdi_med": _med([r["cdi"] for r in rows]),
        "top_safe": sum(t >= 100 for t in tops),
        "top_n": len(tops),
        "cpu_med": _med([r["cpu_s"] for r in rows]),
    }


def ablation_variants() -> dict[str, Any]:
    """Each v2 change switched off (or back to v1) on its own; see docs/benchmarks/pipeline.md."""
    from flight_sw.pipeline import PRESETS

    f = PRESETS["fast"]
    r = dataclasses.replace
    return {
        "fast (v2)": f,
        "v1 (issue 6 fast)": PRESETS["fast_v1"],
        "no SGM (WTA on the small-window cost)": r(f, sgm_paths=0),
        "SGM 4 paths": r(f, sgm_paths=4),
        "constant P2 (no gradient adaptation)": r(f, p2_gradient_adapt=False),
        "uniqueness check 0.05 (reject instead of sigma)": r(f, uniqueness=0.05),
        "no speckle filter": r(f, speckle_px=0),
        "no uncertainty in hazards (k = 0, sigma ignored)": r(f, sigma_k=0.0, psafe_min=0.0),
        "no wide-scale slope (footprint slope only)": r(f, wide_slope_factor=0.0),
        "shadow pixels matched (no dark mask in the cost)": r(f, mask_shadow=False),
        "P1/P2 = 2/96 (weak smoothing)": r(f, sgm_p1=2, sgm_p2=96),
        "P1/P2 = 8/128": r(f, sgm_p1=8, sgm_p2=128),
        "non-convex raw cost = no match (kappa floor 0)": r(f, kappa_floor=0.0),
        "wall cue at 0.15 (v1's)": r(f, shading_limit=0.15),
        "P(safe) >= 0.8": r(f, psafe_min=0.8),
        "no wall cue": r(f, shading_limit=0.0),
        "with the Harris rock cue": r(f, rocks_as_hazard=True),
        "with keep-out margin 1 px": r(f, hazard_margin_px=1.0),
        "fixed sweep range (v1 +-max(10 m, 6 %))": r(f, range_search=False),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--set", choices=("tuning", "held-out"), default="tuning")
    ap.add_argument("--n-seeds", type=positive_int, default=2, help="first N seeds of the set")
    ap.add_argument("--seeds", type=int, nargs="*", help="explicit seeds (overrides --set/--n-seeds)")
    ap.add_argument("--cases", nargs="+", default=["vertical", "approach"], choices=list(CASES))
    ap.add_argument("--altitudes", type=int, nargs="*", help="only these (lower-frame) altitudes")
    ap.add_argument("--presets", nargs="+", default=["fast"])
    ap.add_argument("--set-param", nargs="*", default=[], metavar="K=V", help="override fields of the preset")
    ap.add_argument("--ablation", action="store_true", help="run the ablation variants instead of --presets")
    ap.add_argument("--cache", default="/tmp/flight_eval_cache")
    ap.add_argument(
        "--max-raster-cells",
        type=positive_int,
        default=None,
        help="render with this raster cap (docs/scenes.md); use a cache of its own, renders are reused by path",
    )
    ap.add_argument("--raster", choices=list(RASTERS), default=DEFAULT_RASTER, help="terrain rasters (docs/scenes.md)")
    ap.add_argument(
        "--image-size",
        type=positive_int,
        default=None,
        help="a square camera of this many px with the thesis camera's field of view (default: its 512 px)",
    )
    ap.add_argument("--render-only", action="store_true")
    ap.add_argument("--json", type=out_file, help="write all rows here")
    ap.add_argument("--causes", action="store_true", help="also print the FN/FP breakdown by cause (v2 presets)")
    ap.add_argument(
        "--library",
        metavar="DIR",
        help="score every pair of this landing render cache (hazard-hil landings --cache) instead of --cases",
    )
    args = ap.parse_args(argv)
    from flight_sw.pipeline import PRESETS

    # every argument checked before anything is rendered or scored
    if args.library:
        check_dir(args.library, "--library")
    else:
        check_altitudes(args.cases, args.altitudes)
    if not args.ablation:
        unknown("--presets", args.presets, PRESETS)

    import cv2

    cv2.setNumThreads(1)
    from ground_sim.seeds import HELD_OUT_SEEDS, TUNING_SEEDS

    seeds = args.seeds or list((TUNING_SEEDS if args.set == "tuning" else HELD_OUT_SEEDS)[: args.n_seeds])
    cache = Path(args.cache)
    mc = args.max_raster_cells
    if args.ablation:
        variants = ablation_variants()
    else:
        variants = {}
        from bench_multiframe import preset_with

        for p in args.presets:
            try:  # a bad key or value ends the bench with one line (booleans: true/false/1/0/yes/no)
                prm = preset_with(p, args.set_param)
            except (ValueError, AttributeError, KeyError) as exc:
                raise InputError(f"--presets/--set-param: {exc}") from None
            variants[p + ("" if not args.set_param else " " + " ".join(args.set_param))] = prm
            swept = [
                k
                for k in ("fp_budget", "psafe_min", "call_slope_max")
                if any(x.startswith(k + "=") for x in args.set_param)
            ]
            size = args.image_size or 512
            fitted = model_for_image(prm.psafe_model_path or None, (size, size)) if swept else None
            if fitted is not None and prm.psafe_call == "model" and model_call(fitted[0]):
                # that model records its own operating point, which replaces these (Params.psafe_call)
                said = ", ".join(swept)
                print(f"note: {said} set, but {Path(fitted[1]).name}'s own operating point replaces them: add "
                      "psafe_call=params to sweep them", file=sys.stderr)  # fmt: skip
    if args.library:
        pairs = library_pairs(Path(args.library), args.raster)
        seeds = sorted({e["seed"] for e in pairs})
    else:
        pairs = [
            e
            for c in args.cases
            for s in seeds
            for e in render_case(c, s, cache, args.altitudes, mc, args.raster, args.image_size)
        ]
    if args.render_only:
        print(f"{len(pairs)} pairs in {cache}")
        return 0
    all_rows: dict[str, list[dict[str, Any]]] = {}
    for name, prm in variants.items():
        rows = []
        for e in pairs:
            r = score_pair(e["pair_dir"], prm)
            rows.append({**e, **r})
        all_rows[name] = rows
        print((library_table if args.library else table)(rows, f"{name} - seeds {seeds}"), flush=True)
        if args.causes and not args.library:
            print(causes_table(rows, f"{name} - where the FN and FP pixels are"), flush=True)
            print(clear_ground_table(rows, f"{name} - the FN on clearly safe ground"), flush=True)
    if args.ablation:
        print("\n| variant | DEM valid % min / med | FP % med / worst | FN % med | CDI % med | top site safe | CPU s |")
        print("|---|---|---|---:|---:|---:|---:|")
        for name, rows in all_rows.items():
            s = summary(rows)
            print(
                f"| {name} | {s['valid_min']:.1f} / {s['valid_med']:.1f} | {s['fp_med']:.2f} / {s['fp_max']:.2f} "
                f"| {s['fn_med']:.1f} | {s['cdi_med']:.1f} | {s['top_safe']}/{s['top_n']} | {s['cpu_med']:.3f} |"
            )
    if args.json:
        write_out(args.json, json.dumps(all_rows, indent=1, default=float) + "\n")
    return 0


if __name__ == "__main__":
    run(main)
