"""Score any detector's output directory against a pair's ground truth (``hazard-hil score``).

The flight software's output files are a contract (docs/design.md, "Flight software output directory"):
``hazard.npy`` (required), ``elevation.npy``, ``state.npy`` and the sites of ``result.json`` (optional;
``psafe.npy`` is checked, not scored). Our ``process`` writes them, and so can any other detector. This module
reads them, checks them against the pair,
and scores them by the design's convention (thesis section 2.8, Tables 6.4 and 6.11):

* per pixel, positive = safe; a pixel is *called safe* when ``hazard < 1``. NaN is not called safe:
  TP = safe called safe, FP = unsafe called safe (an undetected hazard, Table 2.1 asks <= 1 %),
  FN = safe not called safe (a false alarm), TN = unsafe not called safe; CDI = TP % + TN %;
* the scored pixels are those of frame 0 whose true ground the last frame sees (from the truth depth and
  the true poses), where the truth is finite. The detector's own NaN does not shrink that area: a pixel it
  left unmapped is scored as not called safe and counted as ``unmapped_pct``. ``evaluate``, the HIL run's grid
  scores and ``bench/eval_flight.py`` score the same area (:func:`ground_sim.gridscore.scored_area`).
* DEM error over the scored pixels where both elevations are finite: mean |error|, median, MAD;
* a site is truly safe when every truth pixel whose true ground (X, Y) lies within the footprint radius
  (1.5 m) of the site is safe (DESIGN.md, :func:`ground_sim.gridscore.judge_site`); a footprint that frame 0
  does not wholly see is not confirmed, and scored as not safe. The first site listed is the top-ranked one.
"""

from __future__ import annotations

import io
import json
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from protocol.errors import InputError, os_error_text
from protocol.pairdir import (
    STATE_OUTSIDE,
    STATE_SAFE,
    STATE_UNKNOWN,
    STATE_UNSAFE,
    PairFormatError,
    file_present,
    named_images,
)
from reports.console import printable
from reports.html import write_atomic

STATE_CODES = (STATE_SAFE, STATE_UNSAFE, STATE_UNKNOWN, STATE_OUTSIDE)  # docs/design.md
FP_LIMIT_PCT = 1.0  # thesis Table 2.1: undetected hazards must stay at or under 1 % of the pixels
# |x|, |y|, |z| of a site (world m): 1000 km is beyond any descent's view
MAX_SITE_COORD_M = 1e6
MAX_RESULT_JSON_BYTES = 16 * 2**20  # a Result's parameters, timings and sites are a few kB


# `score --csv`'s columns, always these and in this order, empty where a pair has no value: a table another tool
# reads needs one schema, whatever files each detector wrote
CSV_COLUMNS = (
    "pair",
    "error",
    "pixels",
    "fp_pct",
    "fn_pct",
    "tp_pct",
    "tn_pct",
    "cdi_pct",
    "hazards_detected_pct",
    "safe_recognised_pct",
    "hazards_in_scene_pct",
    "unmapped_pct",
    "state_safe_pct",
    "state_unsafe_pct",
    "state_unknown_pct",
    "dem_mean_abs_m",
    "dem_median_m",
    "dem_mad_m",
    "dem_coverage_pct",
    "sites",
    "sites_truly_safe",
    "sites_unconfirmed",
    "top_site_truly_safe",
    "top_site_confirmed",
    "pair_dir",
    "output_dir",
    "figure",
    "truth",
    "pair_error",
)


# `score --json` rows also carry these (the CSV leaves them out); every row has every key, null where a pair has no
# value: a consumer reading row["dem_mean_abs_m"] got a KeyError on a detector without elevation.npy
JSON_ONLY_KEYS = ("truth_poses", "truth_note", "sites_unknown")


def json_row(row: dict[str, Any]) -> dict[str, Any]:
    """``row`` with :data:`CSV_COLUMNS` and :data:`JSON_ONLY_KEYS` in that order, None where it has no value."""
    keys = (*CSV_COLUMNS, *JSON_ONLY_KEYS)
    return {k: row.get(k) for k in keys} | {k: v for k, v in row.items() if k not in keys}


class ScoreError(InputError):
    """An output directory or pair that cannot be scored (one line, says which file and why)."""


@dataclass(frozen=True)
class DetectorOutput:
    """What a detector wrote for one pair: maps in frame 0's pixels and its ranked sites (world x, y, z)."""

    hazard: np.ndarray
    elevation: np.ndarray | None
    state: np.ndarray | None
    sites_xyz: np.ndarray  # (N, 3), N may be 0; the first is the top-ranked site
    # why no site is known, when the output cannot say (no result.json, or one without "sites"): an interrupted
    # `process` was scored as "no site", as if its detector had found none (QA of stop 66)
    sites_unknown: str | None = None


def _load(path: Path, shape: tuple[int, int]) -> np.ndarray:
    """The array in ``path``, read only once its header says it has ``shape`` (memory bounded before it is spent:
    a file claiming a huge array is refused from its header)."""
    from protocol.pairdir import PairFormatError, open_npy

    try:
        a = open_npy(path)
    except PairFormatError as exc:
        raise ScoreError(str(exc)) from None
    if a.shape != shape:
        got = getattr(a, "shape", type(a).__name__)
        raise ScoreError(f"{path}: must be {shape[0]}x{shape[1]} (frame 0's pixels), got {got}")
    if a.dtype.itemsize > 8:
        raise ScoreError(f"{path}: dtype {a.dtype} is not a map's")
    return np.array(a)


def _float32(a: np.ndarray) -> bool:
    """float32 in either byte order (a MATLAB or Java writer's ``>f4`` is DESIGN.md's float32 too)."""
    return a.dtype.kind == "f" and a.dtype.itemsize == 4


def _cast_hint(a: np.ndarray) -> str:
    """How to write a float map of another width as DESIGN.md's float32: numpy's default float64 was refused with
    the rule alone (QA of stop 78)."""
    return "; save it with np.save(path, a.astype(np.float32))" if a.dtype.kind == "f" else ""


def _check_state(path: Path, state: np.ndarray, hazard: np.ndarray) -> None:
    """``state.npy`` must agree with ``hazard.npy`` pixel by pixel (DESIGN.md): 255 exactly where the hazard is
    NaN, 0 (safe) exactly where it is < 1, 1 or 2 (unsafe, unknown) where it is >= 1. The first disagreement is
    named with its direction and count."""
    outside, nan = state == STATE_OUTSIDE, np.isnan(hazard)
    safe, called = state == STATE_SAFE, ~nan & (np.nan_to_num(hazard, nan=1.0) < 1.0)
    for n, what in (
        (np.count_nonzero(outside & ~nan), "255 (outside) where hazard.npy has a value"),
        (np.count_nonzero(~outside & nan), "a code other than 255 (outside) where hazard.npy is NaN"),
        (np.count_nonzero(safe & ~called & ~nan), "0 (safe) where hazard.npy is >= 1"),
        (np.count_nonzero(~safe & ~outside & called), "1 or 2 (not safe) where hazard.npy is < 1 (called safe)"),
    ):
        if n:
            raise ScoreError(f"{path}: says {what} on {n} pixels; the two files must agree")


@dataclass(frozen=True)
class Job:
    """One pair to score: its directory, the detector's output directory, and where the sites come from."""

    label: str
    pair_dir: Path
    out_dir: Path
    sites: list | None = None  # an HIL run's record carries them (None: result.json in out_dir, if any)
    missing: str | None = None  # why there is no output to read (an HIL pair that ended in an error)
    hint: str = ""  # said after the output's error: where the output may be instead


def read_output(
    out_dir: str | Path, shape: tuple[int, int], sites: list | None = None, fingerprint: str | None = None
) -> DetectorOutput:
    """The output files of ``out_dir`` for a frame 0 of ``shape`` (rows, cols), checked; :class:`ScoreError`.
    ``sites``: the ranked sites as ``{"x", "y", "z"}`` objects, instead of ``result.json``'s. ``fingerprint``
    (:func:`protocol.pairdir.pair_fingerprint` of the pair scored): a ``result.json`` that records another
    pair's is refused (an output of another pair of the same size was scored without a word)."""
    out = Path(out_dir)
    if not out.is_dir():
        raise ScoreError(f"{out}: no such output directory")

    def present(name: str) -> bool:  # a FIFO or a directory by a file's name is named, not taken for no file
        try:
            return file_present(out / name)
        except PairFormatError as exc:
            raise ScoreError(str(exc)) from None

    if not present("hazard.npy"):
        hil = (
            " (an HIL run saves the image maps only with `run --full-maps`, and only when its flight program sends "
            "them)"
            if sites is not None
            else ""
        )
        raise ScoreError(f"{out}: no hazard.npy (float HxW in [0, 1], NaN outside the covered area){hil}")
    # DESIGN.md's dtypes exactly: other tools read these files as it says they are
    hazard = _load(out / "hazard.npy", shape)
    if not _float32(hazard):
        raise ScoreError(
            f"{out / 'hazard.npy'}: must be float32 (DESIGN.md), got dtype {hazard.dtype}{_cast_hint(hazard)}"
        )
    hazard = hazard.astype(np.float32)  # a big-endian file (>f4) is float32 too
    if np.isinf(hazard).any() or (np.nan_to_num(hazard, nan=0.0) < 0).any() or (hazard > 1.0).any():
        raise ScoreError(
            f"{out / 'hazard.npy'}: values must lie in [0, 1] or be NaN outside the covered area "
            "(an unknown pixel is written as 1.0)"
        )
    elevation = None
    if present("elevation.npy"):
        elevation = _load(out / "elevation.npy", shape)
        if not _float32(elevation):
            raise ScoreError(
                f"{out / 'elevation.npy'}: must be float32 (NaN where not recovered), got dtype {elevation.dtype}"
                f"{_cast_hint(elevation)}"
            )
        elevation = elevation.astype(np.float32)
        if np.isinf(elevation).any():  # scored as "-" without a word; a float32 overflow is no elevation
            raise ScoreError(f"{out / 'elevation.npy'}: holds inf; write NaN where no elevation was recovered")
    state = None
    if present("state.npy"):
        state = _load(out / "state.npy", shape)
        if state.dtype != np.uint8 or not np.isin(state, STATE_CODES).all():
            got = f"dtype {state.dtype}" if state.dtype != np.uint8 else "other values"  # said, as hazard.npy's is
            raise ScoreError(
                f"{out / 'state.npy'}: must be uint8 codes 0 safe, 1 unsafe, 2 unknown, 255 outside; got {got}"
            )
        _check_state(out / "state.npy", state, hazard)
    if present("psafe.npy"):  # not scored, but a file that breaks DESIGN.md's type is named, not passed over
        psafe = _load(out / "psafe.npy", shape)
        if not _float32(psafe):
            raise ScoreError(
                f"{out / 'psafe.npy'}: must be float32 (DESIGN.md), got dtype {psafe.dtype}{_cast_hint(psafe)}"
            )
        if np.isinf(psafe).any() or (np.nan_to_num(psafe, nan=0.0) < 0).any() or (psafe > 1.0).any():
            raise ScoreError(f"{out / 'psafe.npy'}: a probability: values must lie in [0, 1], or be NaN outside")
        holes = int(np.count_nonzero(np.isnan(psafe) & ~np.isnan(hazard)))
        if holes:  # NaN says "outside": inside, a pixel without a probability breaks the file's type (QA of stop 75)
            raise ScoreError(f"{out / 'psafe.npy'}: NaN on {holes} pixels where hazard.npy has a value; give P(safe)")
    xyz = np.zeros((0, 3))
    unknown = None
    if sites is not None:
        xyz = _site_xyz(sites, out / "results.jsonl")
    elif not present("result.json"):
        unknown = "no result.json: its sites are unknown"
    else:
        doc = _read_result(out / "result.json")
        made_from = doc.get("pair_fingerprint") if isinstance(doc, dict) else None
        if fingerprint is not None and isinstance(made_from, str) and made_from != fingerprint:
            where = printable(str(doc.get("pair_dir", "?")), 200)
            raise ScoreError(
                f"{out}: made from another pair ({where}: result.json's pair_fingerprint {printable(made_from, 40)}, "
                f"this pair's {fingerprint}); score it against the pair it was made from"
            )
        if isinstance(doc, dict) and "sites" not in doc:
            unknown = 'result.json names no "sites": its sites are unknown'
        xyz = _site_xyz(doc.get("sites", []) if isinstance(doc, dict) else None, out / "result.json")
    return DetectorOutput(hazard, elevation, state, xyz, unknown)


def _read_result(path: Path) -> Any:
    size = path.stat().st_size
    if size > MAX_RESULT_JSON_BYTES:  # read whole, a 200 MB file took 450 MB: refused from its size
        raise ScoreError(f"{path}: {size} bytes is more than a result.json can be ({MAX_RESULT_JSON_BYTES} bytes)")
    try:
        doc = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise ScoreError(f"{path}: not readable JSON ({exc})") from None
    except RecursionError:  # json's parser recurses once per nested list or object
        raise ScoreError(f"{path}: JSON nested too deeply") from None
    return doc


# a detector ranks a few sites; each is judged over the whole image (~1 ms at 512 px): 800 000 of them fit in a
# 16 MiB result.json and took about 10 min to score (QA of stop 66)
MAX_SCORED_SITES = 10_000


def _site_xyz(raw: Any, path: Path) -> np.ndarray:
    if not isinstance(raw, list):
        raise ScoreError(f'{path}: "sites" must be a list of {{"x", "y", "z"}} objects')
    if len(raw) > MAX_SCORED_SITES:
        raise ScoreError(
            f"{path}: {len(raw)} sites is more than a ranked list of landing sites ({MAX_SCORED_SITES} at most)"
        )
    xyz = [_site_point(s, i, path) for i, s in enumerate(raw)]
    return np.array(xyz, float).reshape(-1, 3)


def _site_point(site: Any, i: int, path: Path) -> list[float]:
    """World ``[x, y, z]`` of site ``i`` of ``path``: JSON numbers, finite and within :data:`MAX_SITE_COORD_M`.

    float() would take "1" and true, and an infinite or huge coordinate made the site "NOT safe" with numpy
    warnings instead of an error: a site the detector could not place is the detector's bug, said here.
    """
    if not isinstance(site, dict) or not all(k in site for k in "xyz"):
        # DESIGN.md's sites carry x, y and z (z is not "where known"); protocol.md lets a degraded Result's z be NaN
        raise ScoreError(
            f'{path}: site {i} needs "x", "y" and "z" (world metres, DESIGN.md); "z" may be null or NaN where the '
            "height is unknown (the verdict uses x and y)"
        )
    out = []
    for k in "xyz":
        v = site[k]
        if k == "z" and (v is None or (isinstance(v, float) and math.isnan(v))):
            out.append(math.nan)  # a degraded Result's site may have no height: judged by its x, y alone
            continue
        if not _coord_ok(v):
            got = "a list or object" if isinstance(v, (list, dict)) else repr(v)[:40]
            raise ScoreError(
                f'{path}: site {i}: "{k}" must be a finite number of world metres within '
                f"+-{MAX_SITE_COORD_M:g}, got {got}"
            )
        out.append(float(v))
    return out


def _coord_ok(v: Any) -> bool:
    """A JSON (or numpy) number, not a bool, with ``|v| <= MAX_SITE_COORD_M``."""
    if isinstance(v, int) and not isinstance(v, bool):
        return abs(v) <= MAX_SITE_COORD_M  # exact: a 400-digit int would overflow float()
    if isinstance(v, (float, np.integer, np.floating)):
        return abs(float(v)) <= MAX_SITE_COORD_M  # False for NaN
    return False


def truth_problem(pair: Any, where: str) -> tuple[str | None, str | None]:
    """Completes ``pair.truth`` where DESIGN.md allows (the hazard derived from depth, elevation and shadow) and
    says (note, problem): the derivation's note, and why the pair cannot be scored (None: it can)."""
    from ground_sim.gridscore import complete_truth

    derived = complete_truth(pair)  # DESIGN.md's files without gt_hazard_i1.npy: the rules give it
    if derived and "hazard" not in pair.truth:  # the derivation says why it gave nothing
        return derived, f"{where}: {derived}; give gt_hazard_i1.npy"
    for key in ("depth", "elevation", "hazard"):
        if key not in pair.truth:
            return derived, (
                f"{where}: no ground truth gt_{key}_i1.npy (scoring needs gt_depth_i1.npy and gt_elevation_i1.npy, "
                "and takes gt_hazard_i1.npy, else derives it from those two and gt_shadow_i1.npy): nothing to score "
                "against"
            )
    return derived, None


def pixel_scores(c: dict[str, float]) -> dict[str, Any]:
    """A row's pixel scores from :func:`ground_sim.scoring.confusion`'s counts, under `score`'s column names."""
    return {
        "pixels": c["n"],
        "tp_pct": c["tp"],
        "fp_pct": c["fp"],
        "fn_pct": c["fn"],
        "tn_pct": c["tn"],
        "cdi_pct": c["cdi"],
        "hazards_detected_pct": c["tn_rate"],
        "safe_recognised_pct": c["tp_rate"],
        "hazards_in_scene_pct": c["hazards_pct"],
    }


def score_output(
    pair: Any,
    output: DetectorOutput,
    where: str = "the pair",
    figure: str | Path | None = None,
    label: str | None = None,
) -> dict[str, Any]:
    """Pixel, DEM and site scores of ``output`` against ``pair``'s ground truth (see the module doc); ``where``
    names the pair in errors. With ``figure``, a PNG there: frame 0 with the sites (green truly safe, red not,
    black not confirmed), the pixel scores (TP, TN, FP, FN over the scored area) and the true hazard, titled
    ``label`` (default: the file's name without ``_score.png``). ``site_verdicts`` holds each site's verdict
    (True truly safe, False not, None not confirmed: scored as not safe)."""
    from ground_sim import scoring
    from ground_sim.gridscore import judge_site, scored_area, site_verdict
    from reports.plots import ground_step_m
    from studies.evaluate import _site_radius_px, backproject_depth, true_poses

    derived, problem = truth_problem(pair, where)
    if problem:
        raise ScoreError(problem)
    true1, _ = true_poses(pair)  # its errors said here, as evaluate says them
    depth = pair.truth["depth"].astype(np.float64)
    world = backproject_depth(pair.camera, true1, depth)
    gt_h = pair.truth["hazard"].astype(np.float32)
    area = scored_area(pair, world)  # the one definition evaluate and the HIL's grid scores take too
    n = int(np.count_nonzero(area))
    if n == 0:
        for key, arr in (("hazard", gt_h), ("depth", depth)):
            if not np.isfinite(arr).any():  # not a geometry problem: say which file holds nothing
                raise ScoreError(f"{where}: gt_{key}_i1.npy holds no finite value: nothing to score against")
        raise ScoreError(f"{where}: frame 0 and the last frame share no ground: nothing to score")
    safe = gt_h < 1.0
    called = ~scoring.unsafe_estimate(output.hazard)  # hazard < 1; NaN is not called safe
    c = scoring.confusion(output.hazard, gt_h, area)  # the thesis's pixel scores (one definition for every tool)
    m: dict[str, Any] = {
        "truth": "derived" if derived else "gt_hazard_i1.npy",
        "truth_note": derived,
        # DESIGN.md: scoring judges against the true poses; without them the reported ones stand in, and a navigation
        # error in them goes unseen (the sites are placed on the ground through frame 0's pose)
        "truth_poses": "true_frames" if isinstance(pair.meta, dict) and "true_frames" in pair.meta else "reported",
        **pixel_scores(c),
        "unmapped_pct": 100.0 * np.count_nonzero(area & ~np.isfinite(output.hazard)) / n,
    }
    if output.state is not None:
        for code, name in ((STATE_SAFE, "safe"), (STATE_UNSAFE, "unsafe"), (STATE_UNKNOWN, "unknown")):
            m[f"state_{name}_pct"] = 100.0 * np.count_nonzero(area & (output.state == code)) / n
    if output.elevation is not None:
        d = scoring.dem_error_stats(output.elevation, pair.truth["elevation"].astype(np.float32), area)
        m.update({"dem_mean_abs_m": d["mean_abs"], "dem_median_m": d["median"], "dem_mad_m": d["mad"]})
        m["dem_coverage_pct"] = 100.0 * np.count_nonzero(area & np.isfinite(output.elevation)) / n
    m["sites"] = int(output.sites_xyz.shape[0])
    # DESIGN.md's site rule, as the landing Monte Carlo and the HIL judge it: every pixel whose true ground lies
    # within the footprint radius must be safe, and a footprint frame 0 does not wholly see is not confirmed
    judged = [judge_site((x, y), world[..., :2], gt_h) for x, y in output.sites_xyz[:, :2]]
    each = [bool(j["safe"]) for j in judged]
    m["sites_truly_safe"] = int(sum(each))
    m["sites_unconfirmed"] = sum(site_verdict(j) is None for j in judged)
    m["top_site_truly_safe"] = bool(each[0]) if each else None
    m["site_verdicts"] = [site_verdict(j) for j in judged]
    if output.sites_unknown is not None:
        m["sites_unknown"] = output.sites_unknown
    m["top_site_confirmed"] = site_verdict(judged[0]) is not None if judged else None
    if figure is not None:
        radius = _site_radius_px(pair.camera, depth, area)
        gsd = ground_step_m(world[..., :2])
        try:
            _figure(Path(figure), pair.images[0], called, safe, area, gt_h, judged, radius, m, gsd, label)
        except OSError as exc:  # a full disk: the scores stand; exit 1 read as "FP over the limit" (QA of stop 72)
            m["figure_error"] = os_error_text(exc if exc.filename else OSError(exc.errno, exc.strerror, str(figure)))
    return {k: None if isinstance(v, float) and math.isnan(v) else v for k, v in m.items()}


# the files `score` reads, by name: a --csv or --json on one of them destroyed it (ground truth included)
_READ_NAMES = frozenset({"pair.json", "result.json", "manifest.json", "results.jsonl"})


def check_not_an_input(path: Path, jobs: list[Job], pairs: Path, outputs: Path, option: str) -> None:
    """Refuse a file ``score`` writes (``option``) that is one of the files it reads: a pair's images as its
    pair.json names them (in subdirectories too, with any extension), a pair's or an output's ``.npy``, image or
    JSON, the descent's manifest or an HIL run's records. A new file of one's own beside them is fine."""
    target = path.resolve()
    if not target.exists():
        return
    pair_dirs = {j.pair_dir.resolve() for j in jobs}
    read_dirs = {j.out_dir.resolve() for j in jobs} | {pairs.resolve(), outputs.resolve()} | pair_dirs
    read = target.suffix in (".npy", ".png") or target.name in _READ_NAMES
    named = {img for d in pair_dirs for img in named_images(d)}  # in subdirectories too, any extension
    if (target.parent in read_dirs and read) or target in named:
        raise ScoreError(f"{option} {path} is one of the files this scoring reads: it would be overwritten")


def _records(path: Path) -> list[dict]:
    """An HIL run's records (``received/results.jsonl``), in order; :class:`ScoreError` when it is not one."""
    from ground_sim.results_file import read_results

    try:
        return read_results(path)
    except UnicodeDecodeError as exc:  # a ValueError whose text does not name the file
        raise ScoreError(f"{path}: not an HIL run's records ({exc})") from None
    except ValueError as exc:  # read_results names the file and the line
        raise ScoreError(f"not an HIL run's records: {exc}") from None
    except OSError as exc:
        raise ScoreError(f"{path}: not an HIL run's records ({exc.strerror or exc})") from None


def pair_jobs(pairs: str | Path, outputs: str | Path) -> list[Job]:
    """The pairs to score:

    * one pair directory (``pair.json``) and its output directory;
    * a rendered descent (``manifest.json``) and a directory with one output directory per pair, named as the
      pair directory is (``OUTPUTS/600_300`` for ``PAIRS/600_300``);
    * a rendered descent and an HIL run's ``received/`` (``results.jsonl``): each pair's record names its
      directory and carries its sites; the image maps are there with ``run --full-maps``.
    """
    from protocol.pairdir import read_manifest

    p, o = Path(pairs), Path(outputs)
    if p.name in ("manifest.json", "pair.json") and p.is_file():  # the file `run --manifest` takes: its directory
        p = p.parent
    if not o.is_dir():  # a mistyped path: usage, not a detector that wrote nothing for every pair
        raise ScoreError(f"{o}: {'not a directory' if o.exists() else 'no such directory'} (OUTPUTS)")
    if (p / "pair.json").exists():  # a FIFO or a directory by that name: read_pair says which
        # one pair of an HIL run's received/: its sites are in the run's record, not in a result.json (scored as
        # "no site" when the Result had one, stop 59's QA)
        ran = o.parent / "results.jsonl"
        if not (o / "result.json").exists() and ran.is_file():
            try:
                runs = _records(ran)
            except ScoreError:  # a file of that name that is no HIL run's: the directory is scored as it is
                runs = []
            mine = [r for r in runs if Path(str(r.get("out_dir", r.get("pair_id", "")))).name == o.name]
            if mine and mine[-1].get("status") == "result":
                return [Job(p.name, p, o, sites=mine[-1].get("sites") or [])]
        return [Job(p.name, p, o, hint=_one_level_down(o, p.name))]
    if not (p / "manifest.json").is_file():
        raise ScoreError(f"{p}: neither a pair directory (pair.json) nor a rendered descent (manifest.json)")
    entries = read_manifest(p / "manifest.json")["pairs"]
    seen: dict[str, int] = {}
    for i, e in enumerate(entries):  # one pair scored twice weighed twice in the medians (QA of stop 66)
        # outputs are named by the pair directory's last part: a/p1 and b/p1 would share one (review of stop 66)
        keys = {
            f"dir {(p / e['path']).resolve().as_posix()}": "names the same pair directory",
            f"label {e.get('label', e['path'])}": "has the same label",
            f"name {Path(e['path']).name}": "has the same directory name (its output's name)",
        }
        for key, what in keys.items():
            if key in seen:
                raise ScoreError(f"{p / 'manifest.json'}: pair {i} {what} as pair {seen[key]} ({e['path']!r})")
            seen[key] = i
    if not (o / "results.jsonl").is_file():
        # OUTPUTS one output itself (hazard.npy), given with the descent rather than its pair: said where to look
        hint = (
            f"; {o} is one output itself: give the pair it was made from as PAIRS ({p / entries[0]['path']})"
            if (o / "hazard.npy").is_file() and len(entries) == 1
            else f"; {o} is one output itself: score it against its pair directory, not the descent"
            if (o / "hazard.npy").is_file()
            else ""
        )
        return [
            Job(str(e.get("label", e["path"])), p / e["path"], o / Path(e["path"]).name, hint=hint) for e in entries
        ]
    records = {Path(str(r.get("pair_dir", ""))).name: r for r in _records(o / "results.jsonl")}
    jobs = []
    for e in entries:
        name = Path(e["path"]).name
        label = str(e.get("label", e["path"]))
        r = records.get(name)
        if r is None:
            jobs.append(Job(label, p / e["path"], o / name, missing=f"{o / 'results.jsonl'}: no record of {name}"))
        elif r.get("status") != "result":
            why = f"the run ended this pair as {r.get('code', r.get('status'))}: {r.get('text', '')}"[:300]
            jobs.append(Job(label, p / e["path"], o / name, missing=why))
        else:  # the record's own directory, relative to the run's received/ (the run may have moved)
            jobs.append(
                Job(label, p / e["path"], o / Path(str(r.get("out_dir", name))).name, sites=r.get("sites") or [])
            )
    return jobs


# bytes per pixel and frame read_pair may hold while it decodes (a 16-bit RGB PNG: 6 B, and its grey copy), and per
# pixel of the truth layers (float32 elevation, depth, hazard, shadow and their checks)
READ_BYTES_PER_FRAME_PX = 10
READ_BYTES_PER_TRUTH_PX = 32


def check_read_memory(pair_dir: Path) -> None:
    """Refuse, from pair.json alone, a pair whose frames and truth would not fit in the memory this process can
    spend: ``score`` decodes every frame, and 16 frames of 4096^2 16-bit RGB took 2.2 GB and 15 s to say "no ground
    truth" (QA of stop 66). A pair.json that cannot be read this way is left to ``read_pair``, which says why."""
    from flight_sw.validate import memory_room
    from protocol.pairdir import declared_size

    size = declared_size(pair_dir)
    if size is None or min(size[:2]) <= 0:
        return
    w, h, n = size
    need = w * h * (n * READ_BYTES_PER_FRAME_PX + READ_BYTES_PER_TRUTH_PX)
    room, what = memory_room()
    if need > room:
        raise ScoreError(
            f"{pair_dir}: {w}x{h} px x {n} frames needs ~{need / 2**20:.0f} MiB to read, but only "
            f"{room / 2**20:.0f} MiB {what}"
        )


def _one_level_down(o: Path, name: str) -> str:
    """For ``score PAIR OUTPUTS`` with OUTPUTS one level too high (the per-pair directories' parent): where the
    output is, said after the "no hazard.npy" error; "" when OUTPUTS holds one itself or its ``name`` holds none."""
    if (o / "hazard.npy").exists() or not (o / name / "hazard.npy").is_file():
        return ""
    return f"; {o / name} holds one: give that as OUTPUTS"


def stray_outputs(
    pairs: str | Path, outputs: str | Path, jobs: list[Job], ours: Sequence[Path | None] = ()
) -> list[str]:
    """The directories in OUTPUTS that no pair of the descent reads (a typo, ``600-300`` for ``600_300``), which
    were skipped without a word; [] when PAIRS is one pair or OUTPUTS an HIL run's records (the run names its
    own directories). ``ours``: directories the command writes (``--figures``), not strays."""
    p, o = Path(pairs), Path(outputs)
    if (p / "pair.json").exists() or (o / "results.jsonl").is_file():
        return []
    read = {j.out_dir.name for j in jobs}
    mine = {Path(d).resolve() for d in ours if d is not None}
    try:
        return sorted(
            d.name
            for d in o.iterdir()
            if d.is_dir() and d.name not in read and not d.name.startswith(".") and d.resolve() not in mine
        )
    except OSError:  # a directory that cannot be listed: the pairs' own errors say what is missing
        return []


def summarise(rows: list[dict[str, Any]], fp_limit_pct: float = FP_LIMIT_PCT) -> dict[str, Any]:
    """Over the scored pairs: worst FP and how many exceed ``fp_limit_pct``, median and lowest CDI, top sites
    truly safe; pairs that could not be scored are counted apart (``failed``)."""
    ok = [r for r in rows if r.get("error") is None]
    fps = [r["fp_pct"] for r in ok]
    cdis = [r["cdi_pct"] for r in ok]
    tops = [r["top_site_truly_safe"] for r in ok if r["top_site_truly_safe"] is not None]
    return {
        "pairs": len(rows),
        "scored": len(ok),
        "failed": len(rows) - len(ok),
        "fp_worst_pct": max(fps) if fps else None,
        "pairs_over_fp_limit": sum(f > fp_limit_pct for f in fps),
        "fp_limit_pct": fp_limit_pct,
        "cdi_median_pct": float(np.median(cdis)) if cdis else None,
        "cdi_lowest_pct": min(cdis) if cdis else None,
        "top_sites": len(tops),
        "top_sites_truly_safe": sum(tops),
        "top_sites_unconfirmed": sum(r.get("top_site_confirmed") is False for r in ok),
        "no_site": sum(r["top_site_truly_safe"] is None and not r.get("sites_unknown") for r in ok),
        "sites_unknown": sum(bool(r.get("sites_unknown")) for r in ok),
        "truth_derived": sum(r.get("truth") == "derived" for r in ok),
    }


def _figure(
    path: Path,
    image: np.ndarray,
    called: np.ndarray,
    safe: np.ndarray,
    area: np.ndarray,
    gt_h: np.ndarray,
    judged: list[dict[str, Any]],
    radius: float,
    m: dict[str, Any],
    m_per_px: float | None = None,
    label: str | None = None,
) -> Path:
    """The picture of one scored pair (see :func:`score_output`); a derived truth (``m["truth"]``) is titled so."""
    from ground_sim.gridscore import site_verdict
    from reports.plots import Panel, Site, confusion_codes, map_figure, save, truth_panel

    # drawn at the pixel whose true ground is nearest the site; black where frame 0 does not hold the footprint
    marks = [
        Site(float(j["uv"][0]), float(j["uv"][1]), radius, i + 1, site_verdict(j))
        for i, j in enumerate(judged)
        if j["uv"] is not None
    ]
    truth_title = (
        "derived true hazard where scored (unsafe: >= 1; white: unknown)"
        if m.get("truth") == "derived"
        else "true hazard where scored (unsafe: >= 1)"
    )
    # NaN (unmapped) pixels are scored as not called safe, so they read as TN/FN: say how many there are
    unmapped = f" ({m['unmapped_pct']:.0f} % unmapped: NaN, not called safe)" if m.get("unmapped_pct") else ""
    panels = [
        Panel("image", image, "frame 0 and the sites", sites=marks),
        Panel("confusion", confusion_codes(called, safe, area), f"pixel scores{unmapped}", sites=marks),
        truth_panel(gt_h, truth_title, scored=area),
    ]
    verdicts = {True: "truly safe", None: "not confirmed (off frame 0, or truth unknown)", False: "NOT safe"}
    if len(judged) > len(marks):
        title_sites = f"; {len(judged) - len(marks)} site(s) off frame 0 not drawn"
    else:
        title_sites = ""
    top = verdicts[site_verdict(judged[0])] if judged else "none"
    title = (
        f"{label or path.name.removesuffix('_score.png')}: FP {m['fp_pct']:.2f} %, CDI {m['cdi_pct']:.1f} %, "
        f"top site {top}{title_sites}"
    )
    return save(map_figure(panels, title, m_per_px=m_per_px), path)


def write_csv(rows: list[dict[str, Any]], path: str | Path) -> Path:
    """One row per pair with :data:`CSV_COLUMNS` (empty cell = no value; booleans as true/false)."""
    import csv

    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)

    def cell(v: Any) -> Any:
        if v is None or (isinstance(v, float) and math.isnan(v)):
            return ""
        if isinstance(v, bool):
            return "true" if v else "false"
        return f"{v:.6g}" if isinstance(v, float) else v

    text = io.StringIO()
    w = csv.writer(text, lineterminator="\n")
    w.writerow(CSV_COLUMNS)
    for r in rows:
        w.writerow([cell(r.get(k)) for k in CSV_COLUMNS])
    # whole or not at all: written in place, a full disk left an empty file, or tore a good earlier one (QA of stop 72)
    return write_atomic(p, text.getvalue())
