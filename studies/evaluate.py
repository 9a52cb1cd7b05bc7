"""Evaluation campaigns: the thesis's ch. 6 tables for our pipeline, and the sec 6.3 Monte Carlo.

Flow: render each scenario's pairs once per scene seed into a cache
(:func:`render_cache`), run the flight pipeline on every (pair, preset) and
score it against ground truth (:func:`evaluate_pair`, a pure function of its
arguments so the executor can ship it to Dask workers), collect one metric row
per pair (``metrics.csv``) and summarise per altitude next to the thesis's
values (:func:`summarise`, :func:`comparison`).

The sensitivity study (:func:`sensitivity_tasks`) re-runs the pipeline on the
same rendered images with the *flight* poses perturbed - the images stay true,
only the knowledge of the poses is wrong, as in thesis sec 6.3 - and reports
the DEM error increase relative to perfect knowledge per sample.
"""

from __future__ import annotations

import csv
import math
import sys
import time
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ground_sim.gridscore import judge_site, pixel_ground, scored_area
from ground_sim.render import DEFAULT_RASTER
from protocol.errors import InputError
from protocol.pairdir import THESIS_CAMERA_PX, Camera, PairFormatError, Pose, read_pair
from protocol.pairdir import true_poses as pairdir_true_poses
from reports.html import dropped_note
from reports.plots import ground_step_m

SCENARIOS = ("vertical", "approach")
PRESETS = ("fast", "thesis", "fast_unrefined")  # fast_unrefined: fast without pose refinement
EPIPOLE_BOX_PX = 80  # Table 6.7: 80x80 px around the epipole
FOOTPRINT_M = 3.0  # lander footprint (Table 2.1)
# the packages whose source decides a task's result (studies.executor.code_fingerprint): a saved result
# of other code is computed again (a render task's code is ground_sim.render_cache's render fingerprint)
EVAL_CODE = ("flight_sw", "ground_sim", "protocol", "studies")
# a render cache pair's true slope and roughness, kept by evaluate_pair(keep_truth=True) with the key they were computed
# under (_truth_key)
TRUTH_KEPT = "truth_slope_roughness.npz"
SENSITIVITY_KINDS = ("altitude", "attitude", "lateral", "rollyaw")
ALTITUDE_ERROR_M = 0.5  # sec 6.3.1: uniform in +-0.5 m per pose
ATTITUDE_LEVELS_DEG = (-0.15, -0.10, -0.05, 0.05, 0.10, 0.15)  # Tables 6.16-6.19
LATERAL_ERROR_M = 0.5  # ch. 8 recommendation; same scale as the altitude study
ROLLYAW_ERROR_DEG = 0.15  # ch. 8 recommendation; same scale as the attitude study
SENSITIVITY_ALTITUDES = (125, 150, 250, 300)  # Tables 6.12-6.19 (approach scenario)

METRIC_COLUMNS = (
    "scenario",
    "altitude_m",
    "label",
    "preset",
    "seed",
    "seed_set",
    "scene",
    "pair",
    "dem_mean_abs_m",
    "dem_median_m",
    "dem_mad_m",
    "dem_skewness",
    "dem_kurtosis",
    "dem_n",
    "slope_mean_abs_deg",
    "slope_median_deg",
    "slope_mad_deg",
    "rough_mean_abs_m",
    "rough_median_m",
    "rough_mad_m",
    "hazards_in_scene_pct",
    "fp_pct",
    "fn_pct",
    "tp_pct",
    "tn_pct",
    "hazards_detected_pct",
    "safe_detected_pct",
    "cdi_pct",
    "unmapped_pct",
    "epi_fp_pct",
    "epi_fn_pct",
    "epi_tp_pct",
    "epi_tn_pct",
    "epi_hazards_detected_pct",
    "epi_safe_detected_pct",
    "epi_cdi_pct",
    "site_fp_pct",
    "site_fn_pct",
    "site_tp_pct",
    "site_tn_pct",
    "site_cdi_pct",
    "site_radius_px",
    "chosen_sites",
    "chosen_sites_safe_pct",
    "valid_pct",
    "level",
    "degraded",
    "pipeline_s",
    "camera_px",  # last, the columns before it in place: rows of another run's camera may share the file
)


MAX_SAMPLES = 10_000  # sensitivity samples per seed and altitude (the thesis: 6 levels); more is a typo
# pipeline runs in one sensitivity campaign: each task and its row are held in memory (~2.3 kB), and at ~0.3 s of
# CPU a run this is already ~8 CPU-hours; 100 seeds x 10000 samples asked for 8 M runs and ~18 GB of tasks
MAX_SENSITIVITY_RUNS = 100_000


class EvaluationError(InputError):
    """A scenario, preset, cache or option given to the evaluation is unusable."""


# --------------------------------------------------------------------------- thesis values
@dataclass(frozen=True)
class ThesisValue:
    table: str
    scenario: str
    altitude_m: int
    metric: str
    value: float


def other_camera(camera_px: int | None) -> str:
    """'a 256 px camera, not the thesis's 512 px' for a camera other than the thesis's; '' for its own (or None)."""
    if camera_px is None or camera_px == THESIS_CAMERA_PX:
        return ""
    return f"a {camera_px} px camera, not the thesis's {THESIS_CAMERA_PX} px"


def thesis_csv_path() -> Path:
    return Path(__file__).with_name("data") / "thesis_tables.csv"


def load_thesis(path: str | Path | None = None) -> list[ThesisValue]:
    """The thesis's ch. 6 numbers (``studies/data/thesis_tables.csv``)."""
    p = Path(path) if path is not None else thesis_csv_path()
    try:
        with p.open(newline="") as fh:
            return [
                ThesisValue(r["table"], r["scenario"], int(r["altitude_m"]), r["metric"], float(r["value"]))
                for r in csv.DictReader(fh)
            ]
    except (OSError, KeyError, ValueError) as exc:
        raise EvaluationError(f"{p}: cannot read thesis table CSV ({exc})") from None


def thesis_index(values: Iterable[ThesisValue]) -> dict[tuple[str, str, int, str], float]:
    """(table, scenario, altitude, metric) -> value, plus TN%, TP%, CDI derived from Tables 6.4/6.11.

    The thesis plots TN%, TP% and CDI (Fig. 6.6/6.12) without tabulating them;
    they follow from Table 6.4/6.11 as TN/(TN+FP), TP/(TP+FN), TP+TN (the same
    formulas reproduce its Table 6.7 to 0.01 %). They are stored under the
    pseudo-tables ``"Fig. 6.6"`` / ``"Fig. 6.12"``.
    """
    idx = {(v.table, v.scenario, v.altitude_m, v.metric): v.value for v in values}
    for tab, fig, scen in (("6.4", "Fig. 6.6", "vertical"), ("6.11", "Fig. 6.12", "approach")):
        alts = {k[2] for k in idx if k[0] == tab}
        for a in alts:
            tp, tn, fp, fn = (idx[(tab, scen, a, m)] for m in ("tp_pct", "tn_pct", "fp_pct", "fn_pct"))
            idx[(fig, scen, a, "hazards_detected_pct")] = 100 * tn / (tn + fp)
            idx[(fig, scen, a, "safe_detected_pct")] = 100 * tp / (tp + fn)
            idx[(fig, scen, a, "cdi_pct")] = tp + tn
    return idx


# Which thesis table holds which of our metrics, per scenario (printed side by side).
COMPARISON_TABLES: dict[str, list[tuple[str, str, str]]] = {
    "vertical": [
        ("6.1", "hazards_in_scene_pct", "hazards in scene %"),
        ("6.2", "dem_mean_abs_m", "DEM mean abs err m"),
        ("6.2", "dem_median_m", "DEM median m"),
        ("6.2", "dem_mad_m", "DEM MAD m"),
        ("6.2", "slope_mean_abs_deg", "slope mean abs err deg"),
        ("6.2", "slope_median_deg", "slope median deg"),
        ("6.2", "slope_mad_deg", "slope MAD deg"),
        ("6.2", "rough_mean_abs_m", "rough mean abs err m"),
        ("6.2", "rough_median_m", "rough median m"),
        ("6.2", "rough_mad_m", "rough MAD m"),
        ("6.3", "dem_skewness", "DEM skewness"),
        ("6.3", "dem_kurtosis", "DEM excess kurtosis (not the thesis's)"),
        ("6.4", "fp_pct", "FP %"),
        ("6.4", "fn_pct", "FN %"),
        ("6.4", "tp_pct", "TP %"),
        ("6.4", "tn_pct", "TN %"),
        ("Fig. 6.6", "hazards_detected_pct", "TN% (hazards found)"),
        ("Fig. 6.6", "safe_detected_pct", "TP% (safe found)"),
        ("Fig. 6.6", "cdi_pct", "CDI %"),
        ("6.7", "epi_fp_pct", "FP % excl. epipole"),
        ("6.7", "epi_fn_pct", "FN % excl. epipole"),
        ("6.7", "epi_tp_pct", "TP % excl. epipole"),
        ("6.7", "epi_tn_pct", "TN % excl. epipole"),
        ("6.7", "epi_safe_detected_pct", "TP% excl. epipole"),
        ("6.7", "epi_hazards_detected_pct", "TN% excl. epipole"),
        ("6.7", "epi_cdi_pct", "CDI % excl. epipole"),
    ],
    "approach": [
        ("6.8", "hazards_in_scene_pct", "hazards in scene %"),
        ("6.9", "dem_mean_abs_m", "DEM mean abs err m"),
        ("6.9", "dem_median_m", "DEM median m"),
        ("6.9", "dem_mad_m", "DEM MAD m"),
        ("6.9", "slope_mean_abs_deg", "slope mean abs err deg"),
        ("6.9", "slope_median_deg", "slope median deg"),
        ("6.9", "slope_mad_deg", "slope MAD deg"),
        ("6.9", "rough_mean_abs_m", "rough mean abs err m"),
        ("6.9", "rough_median_m", "rough median m"),
        ("6.9", "rough_mad_m", "rough MAD m"),
        ("6.10", "dem_skewness", "DEM skewness"),
        ("6.10", "dem_kurtosis", "DEM excess kurtosis (not the thesis's)"),
        ("6.11", "fp_pct", "FP %"),
        ("6.11", "fn_pct", "FN %"),
        ("6.11", "tp_pct", "TP %"),
        ("6.11", "tn_pct", "TN %"),
        ("Fig. 6.12", "hazards_detected_pct", "TN% (hazards found)"),
        ("Fig. 6.12", "safe_detected_pct", "TP% (safe found)"),
        ("Fig. 6.12", "cdi_pct", "CDI %"),
    ],
}
# Metrics of a thesis table whose thesis column measures something else: ours is shown alone, and the table says
# why. The thesis's "kurtosis" equals its skewness minus 3 in every row but one (ground_sim.scoring.dem_error_stats).
NOT_COMPARABLE = {
    "dem_kurtosis": "ours is the excess kurtosis (0 for a normal distribution); the thesis's kurtosis column equals "
    "its skewness minus 3 in every row but Table 6.3's 50 m one (whose skewness repeats Table 6.2's MAD), not a "
    "kurtosis of any definition, so it is not comparable and not shown",
}
# Metrics without a thesis counterpart that we still show per altitude.
EXTRA_METRICS = (
    ("fp_pct_worst", "FP % worst seed"),
    ("cdi_pct_worst", "CDI % worst seed"),
    ("dem_mean_abs_m_worst", "DEM mean abs err m worst seed"),
    ("hazards_in_scene_pct_worst", "hazards in scene % most hazardous seed"),
    ("site_fp_pct", "site FP % (1.5 m radius at the median GSD)"),
    ("site_cdi_pct", "site CDI %"),
    ("chosen_sites_safe_pct", "chosen sites truly safe %"),
    ("chosen_sites_safe_pct_worst", "chosen sites truly safe % worst seed"),
    ("chosen_sites_seeds", "seeds that offered a site"),
    ("valid_pct", "DEM valid %"),
    ("pipeline_s", "pipeline s"),
    ("fn_unmapped_pct", "FN: outside the map %"),
    ("fn_dem_invalid_pct", "FN: DEM not recovered %"),
    ("fn_rock_pct", "FN: rock %"),
    ("fn_slope_pct", "FN: est. slope %"),
    ("fn_rough_pct", "FN: est. rough %"),
    ("fn_shadow_pct", "FN: det. shadow %"),
    ("fn_other_pct", "FN: other %"),
    ("fp_steep_pct", "FP: true slope %"),
    ("fp_rough_pct", "FP: true rough %"),
    ("fp_other_pct", "FP: other (true shadow, or the truth slope/roughness scale) %"),
    ("fp_in_epipole_box_pct", "FP in epipole box %"),
    ("fp_near_threshold_pct", "FP with est. hazard >= 0.8 %"),
)
_THESIS_METRIC = {
    "epi_fp_pct": "fp_pct",
    "epi_fn_pct": "fn_pct",
    "epi_tp_pct": "tp_pct",
    "epi_tn_pct": "tn_pct",
    "epi_safe_detected_pct": "safe_detected_pct",
    "epi_hazards_detected_pct": "hazards_detected_pct",
    "epi_cdi_pct": "cdi_pct",
}


# --------------------------------------------------------------------------- geometry helpers
backproject_depth = pixel_ground  # world points (H, W, 3) of each pixel at its camera z-depth (ground_sim.gridscore)


def project_points(camera: Camera, pose: Pose, X: np.ndarray) -> np.ndarray:
    """(N, 3) world points -> (N, 2) pixel (u, v) in the camera's image."""
    Xc = (np.asarray(X, dtype=np.float64).reshape(-1, 3) - pose.position) @ pose.R.T
    return np.stack([camera.fx * Xc[:, 0] / Xc[:, 2] + camera.cx, camera.fy * Xc[:, 1] / Xc[:, 2] + camera.cy], 1)


def _record_real(v: Any) -> float | None:
    """A finite JSON number from a render record, else None (a bool, a string, a 400-digit integer, NaN)."""
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return None
    try:
        f = float(v)  # a 400-digit integer is valid JSON
    except OverflowError:
        return None
    return f if math.isfinite(f) else None


def _record_num(v: Any) -> float | None:
    """A cell size from a render record: a finite number in (0, 1e4) m, else None."""
    f = _record_real(v)
    return f if f is not None and 0 < f < 1e4 else None


def footprint_truth_cell(view: dict[str, Any]) -> float | None:
    """The cell (m) of the footprint raster the render took its slope and roughness truth on, or None where it took
    them on its view raster: ``truth_cell_m`` finer than ``raster_cell_m`` in the record (``RENDER_VERSION`` 3,
    docs/scenes.md "Ground-truth accuracy" item 6). A record that is not whole reads as None."""
    cell, tcell = _record_num(view.get("raster_cell_m")), _record_num(view.get("truth_cell_m"))
    return tcell if cell is not None and tcell is not None and tcell < cell else None


def recorded_truth_planes(
    scene: Any,
    view: dict[str, Any],
    X: np.ndarray,
    Y: np.ndarray,
    max_cells: int = 4_000_000,
    Z: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
    """The renderer's footprint planes again at ground points (X, Y): ``(z, a, b, c)`` of ``z = a + b dx + c dy``.

    ``view`` is the render's record of the view (pair.json ``render[k]``, ``ground_sim.render._view_info``). Where
    ``truth_cell_m`` (one of ``ground_sim.truth.TRUTH_CELLS_M``) is finer than ``raster_cell_m``, the planes are
    :func:`ground_sim.truth.footprint_planes` on that cell; else they are :func:`ground_sim.truth.plane_fit` on the
    recorded view raster (its origin and shape, with its coarsening and fallback), sampled bilinearly. ``z`` is
    that raster's height, except for a render drawn from one raster per view (no ``raster_tiles`` in the record),
    which took the pixel's own hit: ``Z``, the points' true elevations. This is the rule the hazard truth was drawn
    with (docs/scenes.md, "Ground-truth accuracy" item 6). None when the record is not a whole one, the raster
    would exceed ``max_cells`` or does not hold the points (a pair from elsewhere).
    """
    from ground_sim.truth import TRUTH_CELLS_M, bilinear_inside, footprint_planes, plane_fit

    cell = _record_num(view.get("raster_cell_m"))
    origin, shape = view.get("raster_origin_m"), view.get("raster_shape")
    x0, y0 = (_record_real(o) for o in origin) if isinstance(origin, list) and len(origin) == 2 else (None, None)
    if cell is None or x0 is None or y0 is None:
        return None
    tcell = footprint_truth_cell(view)
    if tcell is not None:
        # a cell the renderer takes, never another: memory and time follow the ground over cell^2
        return footprint_planes(scene.height_raster, X, Y, tcell) if tcell in TRUTH_CELLS_M else None
    if not (isinstance(shape, list) and len(shape) == 2 and all(isinstance(n, (int, np.integer)) for n in shape)):
        return None
    ny, nx = int(shape[0]), int(shape[1])
    gx, gy = (X - x0) / cell, (Y - y0) / cell
    inside = gx.min() >= 0 and gy.min() >= 0 and gx.max() <= nx - 1 and gy.max() <= ny - 1
    if min(nx, ny) < 2 or nx * ny > max_cells or not inside:
        return None
    H = scene.height_raster(x0, y0, cell, nx, ny)
    a, b, c = plane_fit(H, cell)
    gx, gy = np.clip(gx, 0.0, nx - 1.000001), np.clip(gy, 0.0, ny - 1.000001)
    z, pa, pb, pc = (bilinear_inside(m, gx, gy) for m in (H, a, b, c))
    if "raster_tiles" not in view and Z is not None:
        z = np.asarray(Z, np.float64)
    return z, pa, pb, pc


def truth_slope_roughness(
    scene: Any,
    world: np.ndarray,
    cell_m: float,
    max_cells: int = 4_000_000,
    view: dict[str, Any] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """True slope (deg) and roughness (m) at each pixel's true ground point: slope = atan(|(b, c)|) and
    roughness = |z - a| of the least-squares plane ``z = a + b dx + c dy`` over the 3 m footprint
    (``ground_sim.truth``, DESIGN.md "Hazard definitions").

    With ``view`` (the render's record of frame 0) the planes are the renderer's own (:func:`recorded_truth_planes`),
    the ones the hazard truth was drawn with. Otherwise (a pair rendered elsewhere) the scene is rastered at
    ``cell_m`` over the pixels' ground, coarser if that would exceed ``max_cells``, and the plane is sampled
    bilinearly at the points, ``z`` being the pixels' own elevation.
    """
    import cv2

    from ground_sim.truth import plane_fit

    X, Y, Z = world[..., 0], world[..., 1], world[..., 2]
    ok = np.isfinite(X) & np.isfinite(Y)
    slope = np.full(X.shape, np.nan, np.float32)
    rough = np.full(X.shape, np.nan, np.float32)
    if not ok.any():
        return slope, rough
    planes = recorded_truth_planes(scene, view, X[ok], Y[ok], max_cells, Z[ok]) if view is not None else None
    if planes is not None:
        z, a, b, c = planes
        slope[ok] = np.degrees(np.arctan(np.hypot(b, c)))
        rough[ok] = np.abs(z - a)
        return slope, rough
    pad = FOOTPRINT_M + 2 * cell_m
    x0, x1 = float(X[ok].min()) - pad, float(X[ok].max()) + pad
    y0, y1 = float(Y[ok].min()) - pad, float(Y[ok].max()) + pad
    cell = max(cell_m, math.sqrt((x1 - x0) * (y1 - y0) / max_cells))
    nx, ny = int(math.ceil((x1 - x0) / cell)) + 1, int(math.ceil((y1 - y0) / cell)) + 1
    H = scene.height_raster(x0, y0, cell, nx, ny)
    a, b, c = plane_fit(H.astype(np.float64), cell, FOOTPRINT_M)
    s = np.degrees(np.arctan(np.hypot(b, c))).astype(np.float32)
    mu = ((np.where(ok, X, x0) - x0) / cell).astype(np.float32)
    mv = ((np.where(ok, Y, y0) - y0) / cell).astype(np.float32)
    s = cv2.remap(s, mu, mv, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    zp = cv2.remap(a.astype(np.float32), mu, mv, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    r = np.abs(Z.astype(np.float32) - zp)
    return np.where(ok, s, np.nan).astype(np.float32), np.where(ok, r, np.nan).astype(np.float32)


# --------------------------------------------------------------------------- scoring one result
def score_arrays(
    est: dict[str, np.ndarray],
    truth: dict[str, np.ndarray],
    *,
    covered: np.ndarray,
    epipole_box: np.ndarray,
    site_radius_px: float,
) -> dict[str, float]:
    """Flat metric dict from estimated and true image-plane layers (keys as in :data:`METRIC_COLUMNS`).

    ``est``: elevation, hazard, slope_deg, roughness_m. ``truth``: elevation,
    hazard and optionally slope_deg, roughness_m. DEM, slope and roughness
    errors use every covered pixel where both values are finite (the flight
    software leaves rock pixels NaN, like the thesis's sec 4.2 omission).
    """
    from ground_sim import scoring

    m: dict[str, Any] = {}
    d = scoring.dem_error_stats(est["elevation"], truth["elevation"], covered)
    m.update(
        {
            "dem_mean_abs_m": d["mean_abs"],
            "dem_median_m": d["median"],
            "dem_mad_m": d["mad"],
            "dem_skewness": d["skewness"],
            "dem_kurtosis": d["kurtosis"],
            "dem_n": d["n"],
        }
    )
    for key, name, unit in (("slope_deg", "slope", "deg"), ("roughness_m", "rough", "m")):
        if truth.get(key) is not None and est.get(key) is not None:
            s = scoring.error_stats(est[key], truth[key], covered)
        else:
            s = {"mean_abs": math.nan, "median": math.nan, "mad": math.nan}
        m.update(
            {
                f"{name}_mean_abs_{unit}": s["mean_abs"],
                f"{name}_median_{unit}": s["median"],
                f"{name}_mad_{unit}": s["mad"],
            }
        )
    c = scoring.confusion(est["hazard"], truth["hazard"], covered)
    e = scoring.confusion(est["hazard"], truth["hazard"], covered, exclude=epipole_box)
    s = scoring.site_scores(est["hazard"], truth["hazard"], covered, site_radius_px)
    m["hazards_in_scene_pct"] = c["hazards_pct"]  # evaluate_pair's area is the true overlap: the scene's share
    m["hazards_in_scored_pct"] = c["hazards_pct"]  # the same since every pixel of it is scored; a CSV column kept
    for prefix, src in (("", c), ("epi_", e)):
        m.update(
            {
                f"{prefix}fp_pct": src["fp"],
                f"{prefix}fn_pct": src["fn"],
                f"{prefix}tp_pct": src["tp"],
                f"{prefix}tn_pct": src["tn"],
                f"{prefix}hazards_detected_pct": src["tn_rate"],
                f"{prefix}safe_detected_pct": src["tp_rate"],
                f"{prefix}cdi_pct": src["cdi"],
            }
        )
    m.update(
        {
            "site_fp_pct": s["fp"],
            "site_fn_pct": s["fn"],
            "site_tp_pct": s["tp"],
            "site_tn_pct": s["tn"],
            "site_cdi_pct": s["cdi"],
            "site_radius_px": s["radius_px"],
        }
    )
    return m


def error_causes(
    est: dict[str, np.ndarray],
    truth: dict[str, np.ndarray],
    *,
    covered: np.ndarray,
    rocks: np.ndarray,
    shadow: np.ndarray,
    epipole_box: np.ndarray,
) -> dict[str, float]:
    """Where the FP and FN pixels come from, in % of the scored pixels (so they add up to fp_pct / fn_pct).

    FN (false alarms) by the first estimated cause in the order: outside the map
    (the detector left the pixel NaN: the scored area is the true overlap), DEM not
    recovered (hazard forced to 1, not a rock), detected rock, estimated slope
    >= 15 deg, estimated roughness >= 0.30 m, detected shadow. FP (undetected
    hazards) by the first true cause: slope >= 15 deg, roughness >= 0.30 m,
    true shadow - with the share inside the epipole box and the share where the
    estimate was close (hazard >= 0.8) reported on top.
    """
    from ground_sim.scoring import unsafe_estimate

    ht = np.asarray(truth["hazard"], dtype=np.float64)
    keep = np.asarray(covered, bool) & np.isfinite(ht)
    n = max(1, int(keep.sum()))
    eu, tu = unsafe_estimate(est["hazard"]), ht >= 1.0
    fn, fp = keep & eu & ~tu, keep & ~eu & tu
    out: dict[str, float] = {}
    left = fn.copy()
    for name, cause in (
        ("unmapped", ~np.isfinite(np.asarray(est["hazard"], np.float64))),
        ("dem_invalid", ~np.isfinite(est["elevation"]) & ~rocks),
        ("rock", rocks),
        ("slope", np.nan_to_num(est["slope_deg"]) >= 15.0),
        ("rough", np.nan_to_num(est["roughness_m"]) >= 0.30),
        ("shadow", shadow),
    ):
        hit = left & cause
        out[f"fn_{name}_pct"] = 100.0 * hit.sum() / n
        left &= ~hit
    out["fn_other_pct"] = 100.0 * left.sum() / n
    left = fp.copy()
    tslope, trough = truth.get("slope_deg"), truth.get("roughness_m")
    if tslope is not None and trough is not None:
        for name, cause in (("steep", np.nan_to_num(tslope) >= 15.0), ("rough", np.nan_to_num(trough) >= 0.30)):
            hit = left & cause
            out[f"fp_{name}_pct"] = 100.0 * hit.sum() / n
            left &= ~hit
        out["fp_other_pct"] = 100.0 * left.sum() / n
    out["fp_in_epipole_box_pct"] = 100.0 * (fp & epipole_box).sum() / n
    out["fp_near_threshold_pct"] = 100.0 * (fp & (np.nan_to_num(est["hazard"]) >= 0.8)).sum() / n
    return out


def _site_radius_px(camera: Camera, depth: np.ndarray, covered: np.ndarray) -> float:
    """Footprint radius in i1 pixels: 1.5 m over the median ground sample distance (depth / f).

    One radius for the whole image: on an oblique view the 3 m footprint spans fewer pixels in the far field and
    more in the near, and the ground sample along the tilt is longer than across it (depth / (f cos tilt)), so
    there the disk holds about 3.2 x 4.9 m at 500/250 m and 7.7 x 11.6 m at 2400/1200 m (review of stop 66).
    The site-level figure that judges a whole 3 m footprint in world coordinates is the landing sites' (DESIGN.md,
    :func:`ground_sim.gridscore.judge_site`)."""
    z = depth[covered & np.isfinite(depth)]
    if z.size == 0:
        return 1.0
    gsd = float(np.median(z)) / camera.fx
    return max(1.0, 0.5 * FOOTPRINT_M / gsd)


def evaluate_pair(
    pair_dir: str,
    preset: str = "fast",
    *,
    pose_error: dict[str, Any] | None = None,
    maps_path: str | None = None,
    epipole_box_px: int | None = None,
    scene: str | None = None,
    scene_seed: int | None = None,
    truth_slope: bool = True,
    figures_dir: str | None = None,
    figure_stem: str | None = None,
    keep_truth: bool = False,
) -> dict[str, Any]:
    """Run the pipeline on one pair directory and score it against its ground truth.

    ``pose_error`` perturbs the poses handed to the flight software (keys of
    :func:`perturb_poses`); the images and the truth stay those of the true
    poses. ``scene``/``scene_seed`` (defaults: the pair's meta) rebuild the
    terrain for the true slope/roughness; without them (or with
    ``truth_slope=False``, as the sensitivity study does) those errors are NaN.
    ``maps_path`` saves the layers for figures (``.npz``); with ``figures_dir`` the
    figures themselves are drawn here, in the worker (``<figure_stem>_dem.png`` etc.), so
    the report does not redraw them serially. ``epipole_box_px`` (default 80 px scaled by
    width/512) is the Table 6.7 exclusion square. ``keep_truth`` keeps the true slope and roughness in the pair's
    directory (:data:`TRUTH_KEPT`, a render cache's pair), keyed by what they are computed from and the code that
    computes them (:func:`_truth_key`): another preset, or a later run on the same render, reads them instead of
    computing them again (the scene rastered at the renderer's footprint cell: 8 s of a 2400 m pair's 9 s).
    Returns the flat metric dict plus ``timings``.
    """
    from flight_sw.pipeline import run_pipeline
    from ground_sim import scoring

    pair = read_pair(pair_dir)
    for key in ("elevation", "hazard", "depth"):
        if key not in pair.truth:
            raise EvaluationError(f"{pair_dir}: no ground truth {key!r} (gt_{key}_i1.npy)")
    true1, true2 = true_poses(pair)
    fly1, fly2 = pair.poses[0], pair.poses[-1]
    if pose_error:
        fly1, fly2 = perturb_poses(true1, true2, pose_error["frames"])
    t0 = time.perf_counter()
    # the altimeter reading the flight process gets in HIL runs (flight v2 centres its ground search on it)
    res = run_pipeline(
        pair.images[0],
        pair.images[-1],
        fly1,
        fly2,
        pair.camera,
        preset=preset,
        altimeter_m=pair.altimeter_m,
        sun_elevation_deg=pair.sun.elevation_deg if pair.sun else None,  # as the Frames carry it
        sun_azimuth_deg=pair.sun.azimuth_deg if pair.sun else None,
    )
    wall = time.perf_counter() - t0

    truth_elev = pair.truth["elevation"].astype(np.float32)
    world = backproject_depth(pair.camera, true1, pair.truth["depth"].astype(np.float64))
    world[..., 2] = truth_elev
    truth: dict[str, np.ndarray] = {"elevation": truth_elev, "hazard": pair.truth["hazard"]}
    # DESIGN.md's covered area, as `score` and the HIL's grid scores take it: frame-0 pixels whose true ground the
    # last frame sees. The detector's own `covered` left out its unmapped rim (2-6.5 % of the overlap), which
    # scored a map up to 2.5 CDI points above `score`'s figure for the same map (QA of stop 65)
    area = scored_area(pair, world)
    scene_spec, seed = _scene_of(pair.meta, scene, scene_seed)
    radius = _site_radius_px(pair.camera, pair.truth["depth"], area)
    if scene_spec is not None and truth_slope:
        from ground_sim.scene import load_scene

        gsd = float(np.nanmedian(pair.truth["depth"])) / pair.camera.fx
        views = pair.meta.get("render")
        # the renderer's own planes, where the pair records its render (QA 67c: a cell of the GSD disagreed with
        # the hazard truth on a third of a small camera's high view)
        view = views[0] if isinstance(views, list) and views and isinstance(views[0], dict) else None
        kept_as = _truth_key(pair_dir, scene_spec, seed, gsd, world) if keep_truth else None
        got = _load_truth(pair_dir, kept_as, truth_elev.shape) if kept_as else None
        if got is None:
            got = truth_slope_roughness(load_scene(scene_spec, seed), world, max(gsd, 0.02), view=view)
            if kept_as:
                _save_truth(pair_dir, kept_as, got)
        truth["slope_deg"], truth["roughness_m"] = got
    epi = scoring.epipole_px(pair.camera, true1, true2)
    if epipole_box_px is None:  # the thesis's 80 px at 512 px, scaled with the camera
        epipole_box_px = max(1, round(EPIPOLE_BOX_PX * pair.camera.width / THESIS_CAMERA_PX))
    box = scoring.box_mask(truth_elev.shape, epi, epipole_box_px)
    est = {"elevation": res.elevation, "hazard": res.hazard, "slope_deg": res.slope_deg, "roughness_m": res.roughness_m}
    m: dict[str, Any] = score_arrays(est, truth, covered=area, epipole_box=box, site_radius_px=radius)
    m["unmapped_pct"] = 100.0 * float(np.count_nonzero(area & ~np.isfinite(res.hazard))) / max(1, int(area.sum()))
    # the shape error alone: what a tilt (absolute attitude) and a datum shift (altitude) leave out
    m["dem_detrended_mean_abs_m"] = scoring.detrended_error(res.elevation, truth_elev, world[..., :2], area)
    # DESIGN.md's site rule (ground_sim.gridscore.judge_site), as `score`, the landings and the HIL judge a site
    safe_sites = [judge_site((s.x, s.y), world[..., :2], pair.truth["hazard"])["safe"] for s in res.sites]
    ch = {"n": len(safe_sites), "safe_pct": 100.0 * float(np.mean(safe_sites)) if safe_sites else math.nan}
    m.update(error_causes(est, truth, covered=area, rocks=res.rock_mask, shadow=res.shadow_mask, epipole_box=box))
    m.update(
        {
            "chosen_sites": ch["n"],
            "chosen_sites_safe_pct": ch["safe_pct"],
            "valid_pct": 100.0 * res.valid_fraction,
            "level": res.level,
            "degraded": bool(res.degraded),
            "pipeline_s": wall,
            "timings": {k: round(v["wall_s"], 4) for k, v in res.timings.items()},
            "epipole_uv": list(epi) if epi is not None else None,
        }
    )
    if maps_path:
        import io

        from reports.html import write_atomic

        buf = (
            io.BytesIO()
        )  # written whole or not at all: a stop or a full disk mid-write left a torn npz (QA of stop 72)
        np.savez_compressed(
            buf,
            image=pair.images[0],
            m_per_px=np.float64(ground_step_m(world[..., :2]) or np.nan),  # the pictures' scale bar
            est_elevation=res.elevation,
            true_elevation=truth_elev,
            est_hazard=res.hazard,
            true_hazard=pair.truth["hazard"].astype(np.float32),
            est_slope=res.slope_deg,
            true_slope=truth.get("slope_deg", np.full_like(truth_elev, np.nan)),
            est_rough=res.roughness_m,
            true_rough=truth.get("roughness_m", np.full_like(truth_elev, np.nan)),
            covered=res.covered,
            scored=area,  # the true overlap the scores are over: the pictures' percentages are too
            epipole_box=box,
            rocks=res.rock_mask,
            est_shadow=res.shadow_mask,
            true_shadow=pair.truth.get("shadow", np.zeros(truth_elev.shape, bool)),
        )
        write_atomic(maps_path, buf.getvalue())
        if figures_dir:
            from studies.report import figures_from_maps

            files = figures_from_maps(maps_path, figures_dir, figure_stem or Path(maps_path).stem)
            m["figures"] = [f.name for f in files]
    return {k: (None if isinstance(v, float) and math.isnan(v) else v) for k, v in m.items()}


def _truth_key(pair_dir: str, scene_spec: str, seed: int, gsd: float, world: np.ndarray) -> str:
    """SHA-256 (32 hex digits) of everything :func:`truth_slope_roughness` reads in :func:`evaluate_pair`: the scene
    and its seed, the pair's record (its render views), the ground cell and the pixels' true ground points, and of
    the code that computes them (ground_sim's render and truth code, and this package)."""
    import hashlib

    from ground_sim.render_cache import render_code_fingerprint
    from studies.executor import code_fingerprint

    code = f"{render_code_fingerprint()}-{code_fingerprint(('studies',))}"
    h = hashlib.sha256(f"{code}\0{scene_spec}\0{seed}\0{gsd!r}\0".encode())
    h.update((Path(pair_dir) / "pair.json").read_bytes())
    h.update(np.ascontiguousarray(world, np.float64).tobytes())
    return h.hexdigest()[:32]


def _load_truth(pair_dir: str, key: str, shape: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray] | None:
    """The layers :func:`_save_truth` kept in ``pair_dir`` under ``key``, or None: none kept, kept under another key
    (the render, its record or the code changed), not whole, or not float32 of ``shape``."""
    import zipfile

    try:
        with np.load(Path(pair_dir) / TRUTH_KEPT, allow_pickle=False) as z:
            if str(z["key"]) != key:
                return None
            slope, rough = z["slope_deg"], z["roughness_m"]
    except (OSError, KeyError, ValueError, EOFError, zipfile.BadZipFile):  # absent, or cut off by a stopped worker
        return None
    if any(a.shape != shape or a.dtype != np.float32 for a in (slope, rough)):
        return None
    return slope, rough


def _save_truth(pair_dir: str, key: str, layers: tuple[np.ndarray, np.ndarray]) -> None:
    """Keep the true slope and roughness in ``pair_dir`` under ``key``, in place of what was kept there; written whole
    or not at all (a rename), as another worker may read it at once."""
    import os
    import tempfile

    d = Path(pair_dir)
    try:
        fd, name = tempfile.mkstemp(prefix=f".{TRUTH_KEPT}.", suffix=".tmp", dir=d)  # unique on a shared disk too
    except OSError:  # a cache this process may read and not write: computed again next time
        return
    try:
        with os.fdopen(fd, "wb") as f:
            np.savez(f, key=np.str_(key), slope_deg=layers[0], roughness_m=layers[1])
        os.replace(name, d / TRUTH_KEPT)
    except OSError:  # a full disk, say
        Path(name).unlink(missing_ok=True)


def _scene_of(meta: dict[str, Any], scene: str | None, seed: int | None) -> tuple[str | None, int]:
    spec = scene if scene is not None else meta.get("scene_spec", meta.get("scene"))
    s = seed if seed is not None else meta.get("scene_seed", 0)
    return (str(spec) if isinstance(spec, str) and spec else None), int(s or 0)


def true_poses(pair: Any) -> tuple[Pose, Pose]:
    """True poses of frames 0 and -1 (:func:`protocol.pairdir.true_poses`)."""
    try:
        every = pairdir_true_poses(pair)
    except PairFormatError as exc:
        raise EvaluationError(str(exc)) from None
    return every[0], every[-1]


# --------------------------------------------------------------------------- pose perturbation
def perturb_poses(pose1: Pose, pose2: Pose, frames: list[dict[str, float]]) -> tuple[Pose, Pose]:
    """Poses as believed by the flight software: ``ground_sim.pose_error.PoseDelta(**frames[k]).apply``.

    PoseDelta fields: dz_m, dx_m, dy_m (centre offsets), pitch_deg (about the
    camera x axis: the plane of the surface normal and the optical axis, thesis
    sec 6.3.2), roll_deg (camera z), yaw_deg (camera y).
    """
    from ground_sim.pose_error import PoseDelta

    if len(frames) != 2:
        raise EvaluationError(f"pose error needs one delta per frame, got {len(frames)}")
    try:
        d1, d2 = PoseDelta(**frames[0]), PoseDelta(**frames[1])
    except TypeError as exc:
        raise EvaluationError(f"pose error: {exc}") from None
    return d1.apply(pose1), d2.apply(pose2)


def sample_pose_error(kind: str, seed: int, index: int) -> dict[str, Any]:
    """Deterministic pose error for sample ``index`` of a campaign (seeded by kind, scene seed, index).

    altitude: dh1, dh2 ~ U(-0.5, 0.5) m (sec 6.3.1). attitude: the first six
    samples are the thesis's levels -0.15..+0.15 deg (Tables 6.16-6.19), later
    ones U(-0.15, 0.15) deg, equal on both poses (sec 6.3.2). lateral: dx, dy
    per pose ~ U(-0.5, 0.5) m. rollyaw: roll, yaw ~ U(-0.15, 0.15) deg, equal on both poses.
    """
    if kind not in SENSITIVITY_KINDS:
        raise EvaluationError(f"sensitivity kind must be one of {SENSITIVITY_KINDS}, got {kind!r}")
    rng = np.random.default_rng([SENSITIVITY_KINDS.index(kind), int(seed), int(index)])
    if kind == "altitude":
        d = rng.uniform(-ALTITUDE_ERROR_M, ALTITUDE_ERROR_M, 2)
        return {"frames": [{"dz_m": float(d[0])}, {"dz_m": float(d[1])}]}
    if kind == "attitude":
        a = ATTITUDE_LEVELS_DEG[index] if index < len(ATTITUDE_LEVELS_DEG) else float(rng.uniform(-0.15, 0.15))
        return {"frames": [{"pitch_deg": a}, {"pitch_deg": a}]}
    if kind == "lateral":
        d = rng.uniform(-LATERAL_ERROR_M, LATERAL_ERROR_M, 4)
        return {"frames": [{"dx_m": float(d[0]), "dy_m": float(d[1])}, {"dx_m": float(d[2]), "dy_m": float(d[3])}]}
    d = rng.uniform(-ROLLYAW_ERROR_DEG, ROLLYAW_ERROR_DEG, 2)
    return {"frames": [{"roll_deg": float(d[0]), "yaw_deg": float(d[1])}] * 2}


# --------------------------------------------------------------------------- rendering cache
def camera_for(size_px: int | None) -> Camera | None:
    """A square camera with the thesis camera's 30 deg field of view (None: the thesis camera itself)."""
    if size_px is None or size_px == THESIS_CAMERA_PX:
        return None
    if size_px < 32:
        raise EvaluationError(f"camera size must be >= 32 px, got {size_px}")
    return Camera.thesis(size_px)  # the same 30 deg FOV


def render_cache(
    scenario: str,
    seed: int,
    cache_dir: str | Path,
    *,
    camera_px: int | None = None,
    altitudes: Iterable[int] | None = None,
    progress: bool = False,
    scene: str | None = None,
    max_cells: int | None = None,
    raster: str = DEFAULT_RASTER,
) -> list[dict[str, Any]]:
    """Render (or reuse) the scenario's pairs for one scene seed; return [{label, altitude_m, pair_dir}].

    Pairs are rendered with ``ground_sim`` from the true trajectory (no pose
    error: the sensitivity study perturbs the flight's pose knowledge instead)
    on ``scene`` (default: the scenario's, :func:`scenario_scene`) under the
    scene's sun, into ``cache_dir/<scenario>_<scene>_s<seed>_<px>px/<label>/``;
    a pair directory that already holds ``pair.json`` is reused, so presets and
    samples share one rendering.
    """
    from ground_sim import library, trajectory
    from ground_sim.descent import render_pair
    from ground_sim.render import MAX_CELLS
    from ground_sim.render_cache import reusable
    from ground_sim.scene import load_scene, load_scene_params
    from protocol.pairdir import write_pair_atomic

    if scenario not in SCENARIOS:
        raise EvaluationError(f"scenario must be one of {SCENARIOS}, got {scenario!r}")
    specs = getattr(trajectory, scenario)(camera_for(camera_px))
    if altitudes is not None:
        want = {int(a) for a in altitudes}
        have = [int(round(s.altitude_m)) for s in specs]
        if not want <= set(have):
            raise EvaluationError(
                f"scenario {scenario}: no pair at altitude(s) {sorted(want - set(have))} m (it has {sorted(have)})"
            )
        specs = [s for s in specs if int(round(s.altitude_m)) in want]
    scene_spec = scene or scenario_scene(scenario)
    params = load_scene_params(scene_spec, scenario)
    tag = params.spec.replace(":", "-")
    out = Path(cache_dir) / f"{scenario}_{tag}_s{seed}_{camera_px or THESIS_CAMERA_PX}px{render_tag(max_cells, raster)}"
    sc = None
    entries = []
    for k, spec in enumerate(specs):
        d = out / spec.label.replace("/", "_")
        # none there, or a stale one (another renderer, render code or scene parameters), now removed
        if not reusable(d, scene=params):
            if sc is None:
                sc = load_scene(scene_spec, seed, scenario)
            if progress:
                print(f"render {scenario} seed {seed}: {spec.label} ({k + 1}/{len(specs)})", flush=True)
            sun = library.scene_sun(scene_spec, scenario, seed)
            # atomic: an interrupted render never leaves a half-written pair, a concurrent one is kept
            write_pair_atomic(d, render_pair(sc, spec, sun, seed=seed, max_cells=max_cells or MAX_CELLS, raster=raster))
        entries.append({"label": spec.label, "altitude_m": float(spec.altitude_m), "pair_dir": str(d)})
    return entries


def render_tag(max_cells: int | None, raster: str = DEFAULT_RASTER) -> str:
    """Suffix of cache directories and task ids for every terrain raster but the capped one-per-view raster
    at ``MAX_CELLS`` (the renders differ). Tiled renders, the default, carry ``_tiles``: the untagged
    caches and task ids of the capped renders made before stop 21 stay theirs, never taken for tiled ones."""
    from ground_sim.errors import RenderError
    from ground_sim.render import MAX_CELLS, check_max_cells, check_raster

    try:
        check_raster(raster)
        if max_cells is not None:
            check_max_cells(max_cells)
    except RenderError as exc:
        raise EvaluationError(str(exc)) from None
    tag = "" if max_cells is None or max_cells == MAX_CELLS else f"_cells{max_cells}"
    return tag + ("" if raster == "view" else f"_{raster}")


def task_inputs(camera_px: int | None, renders: str | None = None) -> str:
    """What a scoring task's result depends on beyond its id (``run_tasks(inputs=...)``): a rerun into the same
    ``--out`` with another ``--camera-px`` scores its own renders instead of reusing the other camera's results
    (the ids, which name scenario, preset, seed, altitude and raster, leave the camera out); ``renders``
    (:func:`render_identity`) likewise for renders drawn from other scene parameters or render code."""
    text = f"camera_px={camera_px or THESIS_CAMERA_PX}"
    return text if renders is None else f"{text}, renders {renders}"


def render_identity(scenario: str, scene: str | None = None) -> str:
    """The render code and scene-parameter fingerprints (:mod:`ground_sim.render_cache`) of a scenario's renders:
    the task ids and cache keys name the scene, not what it holds, so a preset edited under the same name, or
    the render or truth code changed, would have reused the old renders and their scores."""
    from ground_sim.render_cache import render_code_fingerprint, scene_fingerprint
    from ground_sim.scene import load_scene_params

    params = load_scene_params(scene or scenario_scene(scenario), scenario)
    return f"{render_code_fingerprint()}-{scene_fingerprint(params)}"


def scenario_scene(scenario: str) -> str:
    """Scene preset per scenario (:func:`ground_sim.descent.default_scene`, as ``render`` and ``run`` use)."""
    from ground_sim.descent import default_scene

    return default_scene(scenario)


# --------------------------------------------------------------------------- campaigns
def _render_task(
    scenario: str,
    seed: int,
    cache_dir: str,
    camera_px: int | None,
    altitude: int,
    scene: str | None = None,
    max_cells: int | None = None,
    raster: str = DEFAULT_RASTER,
) -> dict[str, Any]:
    return render_cache(
        scenario,
        seed,
        cache_dir,
        camera_px=camera_px,
        altitudes=[altitude],
        scene=scene,
        max_cells=max_cells,
        raster=raster,
    )[0]


def _check_choice(name: str, values: Iterable[Any], allowed: Iterable[Any]) -> list[Any]:
    vals, ok = list(values), list(allowed)
    bad = [v for v in vals if v not in ok]
    if bad or not vals:
        raise EvaluationError(f"{name} must be among {ok}, got {vals}")
    return vals


def render_all(
    scenario: str,
    seeds: Iterable[int],
    cache_dir: str | Path,
    *,
    camera_px: int | None = None,
    altitudes: Iterable[int] | None = None,
    scheduler: Any = None,
    workers: int | None = None,
    progress: bool = True,
    run_dir: str | Path | None = None,
    scene: str | None = None,
    pool: Any = None,
    max_cells: int | None = None,
    raster: str = DEFAULT_RASTER,
) -> list[dict[str, Any]]:
    """Render every (seed, pair) in parallel through the executor; entries carry ``seed``."""
    from ground_sim import trajectory
    from ground_sim.render_cache import reusable
    from ground_sim.scene import load_scene_params
    from studies.executor import PAIR_BYTES_PER_PX, Task, run_tasks

    have = sorted(int(round(s.altitude_m)) for s in getattr(trajectory, scenario)(None))
    alts = have if altitudes is None else sorted({int(a) for a in altitudes})
    if not set(alts) <= set(have) or not alts:
        raise EvaluationError(
            f"scenario {scenario}: no pair at altitude(s) {sorted(set(alts) - set(have))} m (it has {have})"
        )
    seeds = [int(s) for s in seeds]
    tag = (scene or scenario_scene(scenario)).replace(":", "-")
    identity = render_identity(scenario, scene)
    scene_params = load_scene_params(scene or scenario_scene(scenario), scenario)
    tasks = [
        Task(
            f"{scenario}-{tag}-s{s}-{camera_px or THESIS_CAMERA_PX}px-{a}{render_tag(max_cells, raster)}",
            {
                "scenario": scenario,
                "seed": s,
                "cache_dir": str(cache_dir),
                "camera_px": camera_px,
                "altitude": a,
                "scene": scene,
                "max_cells": max_cells,
                "raster": raster,
            },
        )
        for s in seeds
        for a in alts
    ]
    run_dir = Path(run_dir) if run_dir is not None else Path(cache_dir)
    res = run_tasks(
        _render_task,
        tasks,
        run_dir / "render.jsonl",
        scheduler=scheduler,
        workers=workers,
        progress=progress,
        desc=f"render {scenario}",
        pool=pool,
        # what decides the renders, not all of ground_sim: "computing them again" is then said only when the
        # cached renders are drawn again (render_cache, reusable), not when an unrelated module changed
        code=identity,
        disk=(cache_dir, int(PAIR_BYTES_PER_PX * (camera_px or THESIS_CAMERA_PX) ** 2)),
    )
    out = []
    cache = Path(cache_dir).resolve()
    for t in tasks:
        pair_dir = Path(res[t.id]["pair_dir"])
        # cache wiped since the log was written, or the log copied with its --out: a copy read the original's pairs;
        # or damaged since (removed and said by reusable): every rerun failed on it, "rerun to retry" (stop 63's QA)
        here = (pair_dir / "pair.json").is_file() and pair_dir.resolve().is_relative_to(cache)
        if not here or not reusable(pair_dir, scene=scene_params):
            res[t.id] = _render_task(**t.kwargs)
        out.append({**res[t.id], "seed": t.kwargs["seed"]})
    return out


def evaluate_scenario(
    scenario: str,
    out_dir: str | Path,
    *,
    presets: Iterable[str] = ("fast",),
    seeds: Iterable[int] = (0,),
    cache_dir: str | Path | None = None,
    camera_px: int | None = None,
    altitudes: Iterable[int] | None = None,
    scheduler: Any = None,
    workers: int | None = None,
    progress: bool = True,
    maps_seeds: int = 1,
    scene: str | None = None,
    max_cells: int | None = None,
    raster: str = DEFAULT_RASTER,
    figures: bool = True,
) -> list[dict[str, Any]]:
    """Render, run and score a scenario for every preset and seed; write ``metrics.csv``; return the rows.

    One row per (preset, seed, pair), columns :data:`METRIC_COLUMNS` (with the
    scene and the seed set each seed belongs to). Finished pairs are logged to
    ``out_dir/runs/evaluate.jsonl`` so a rerun resumes. The layers of the first
    ``maps_seeds`` seeds are kept in ``out_dir/maps``, and the first preset's
    figures of them are drawn by the workers into ``out_dir/report`` (not without ``figures``: the maps are kept,
    and a later run's page draws them). Rendering and evaluation share one pool of single-threaded processes.
    """
    from ground_sim.seeds import seed_set_of
    from studies.executor import Task, code_fingerprint, local_pool, run_tasks

    _check_choice("scenario", [scenario], SCENARIOS)
    presets = _check_choice("preset", presets, PRESETS)
    seeds = [int(s) for s in seeds]
    out = Path(out_dir)
    cache = Path(cache_dir) if cache_dir is not None else out / "cache"
    scene_spec = scene or scenario_scene(scenario)
    n_alts = len(list(altitudes)) if altitudes is not None else 8
    with local_pool(1 if scheduler else workers, len(seeds) * n_alts * len(presets)) as pool:
        pairs = render_all(
            scenario,
            seeds,
            cache,
            camera_px=camera_px,
            altitudes=altitudes,
            scheduler=scheduler,
            workers=workers,
            progress=progress,
            run_dir=out / "runs",
            scene=scene,
            pool=pool,
            max_cells=max_cells,
            raster=raster,
        )
        tasks: list[Any] = []
        info: dict[str, dict[str, Any]] = {}
        stems: set[str] = set()  # the map figures this run's page has, drawn or (--no-figures) not
        for preset in presets:
            for e in pairs:
                alt = int(round(e["altitude_m"]))
                tid = f"{scenario}-{preset}-s{e['seed']}-{alt}{render_tag(max_cells, raster)}"
                # the true slope and roughness are kept with the render: computed for the first preset of the first
                # run, read by the others
                kw: dict[str, Any] = {
                    "pair_dir": e["pair_dir"],
                    "preset": preset,
                    "maps_path": None,
                    "keep_truth": True,
                }
                if e["seed"] in seeds[:maps_seeds]:
                    kw["maps_path"] = str(out / "maps" / f"{tid}.npz")
                    if preset == presets[0]:
                        stems.add(f"{scenario}_{alt}m")
                    if preset == presets[0] and figures:
                        kw["figures_dir"] = str(out / "report")
                        kw["figure_stem"] = f"{scenario}_{alt}m"
                tasks.append(Task(tid, kw))
                info[tid] = {
                    "scenario": scenario,
                    "altitude_m": alt,
                    "label": e["label"],
                    "preset": preset,
                    "seed": e["seed"],
                    "seed_set": seed_set_of(e["seed"]),
                    "scene": scene_spec,
                    "pair": e["pair_dir"],
                    "camera_px": camera_px or THESIS_CAMERA_PX,  # as the sensitivity CSV states it
                }
        maps = {Path(t.kwargs["maps_path"]).name for t in tasks if t.kwargs["maps_path"]}
        retired = retire_page(out, scenario)
        if retired:  # before any figure changes: an interrupted or failed run left the old page over new figures
            print(
                f"evaluate: removed the earlier {scenario} page ({', '.join(p.name for p in retired)}) from "
                f"{out / 'report'}: "
                + ("this run's figures replace its figures, and " if figures else "")
                + "this run writes it when it finishes",
                file=sys.stderr,
                flush=True,
            )
        gone, undrawn = prune_other_runs(out, scenario, maps, stems, figures=figures)
        if gone:  # said with --no-progress too: scripts are where a silent deletion hurts
            print(
                f"evaluate: removed {_count(gone)} of {scenario} that an earlier run with other settings left in {out}",
                file=sys.stderr,
                flush=True,
            )
        if undrawn:  # an earlier run's, with the same settings: the page says none were drawn, so none may stay
            said = dropped_note("evaluate", len(undrawn), out / "report", f" of {scenario}")
            print(said, file=sys.stderr, flush=True)
        res = run_tasks(
            evaluate_pair,
            tasks,
            out / "runs" / "evaluate.jsonl",
            scheduler=scheduler,
            workers=workers,
            progress=progress,
            desc=f"evaluate {scenario}",
            pool=pool,
            code=code_fingerprint(EVAL_CODE),
            inputs=task_inputs(camera_px, render_identity(scenario, scene)),
            # a saved result whose maps are gone (pruned above, or deleted) is scored again to draw them
            redo=[t.id for t in tasks if t.kwargs["maps_path"] and not Path(t.kwargs["maps_path"]).is_file()],
        )
    rows = [{**info[t.id], **res[t.id]} for t in tasks]
    # another scenario evaluated into the same --out keeps its rows (they were overwritten, without a word)
    others = (
        [r for r in read_metrics_csv(out / "metrics.csv") if r.get("scenario") != scenario]
        if (out / "metrics.csv").is_file()
        else []
    )
    write_metrics_csv(others + rows, out / "metrics.csv")
    return rows


def retire_page(out: Path, scenario: str) -> list[Path]:
    """Remove ``scenario``'s page (``report/index.html`` when it is evaluate's page of ``scenario``) and its
    ``tables_<scenario>.md``, and return them: this run deletes and redraws the scenario's figures as its tasks
    finish, so a run stopped or failed before its report left the old page and tables, presented as complete,
    over a mix of old and new figures, some missing (QA 65b M1). The page of another study or scenario is kept:
    none of its figures change until this run writes its own page. ``metrics.csv`` stays: its rows name their
    seeds and presets and match the maps of the run that wrote them."""
    from reports.html import page_title

    rep = out / "report"
    mine = [rep / f"tables_{scenario}.md"]
    if (page_title(rep / "index.html") or "").startswith(f"hazard-hil evaluate: {scenario} scenario"):
        mine.append(rep / "index.html")
    gone = [p for p in mine if p.is_file()]
    for p in gone:
        p.unlink()
    return gone


def prune_other_runs(
    out: Path, scenario: str, maps: set[str], stems: set[str], *, figures: bool = True
) -> tuple[list[Path], list[Path]]:
    """Remove ``scenario``'s maps (``out/maps``) and figures (``out/report``) that this run will not write: an
    earlier run into ``out`` with other seeds, altitudes or presets left them, and the report took the first map
    of an altitude it found, another seed's among them. ``maps``: this run's map file names; ``stems``: the
    stems of its page's map figures. The figures of this run's stems go too (redrawn: their names hold no preset
    or seed), and so do its charts (``<scenario>_detection.png`` ...) when it draws none (``figures`` False). Other
    scenarios' files, and every other file, are kept. Returns what an earlier run with other settings left, and
    the figures of this run's page that it draws none of (``--no-figures``)."""
    import re

    from studies.report import FIGURE_KINDS

    figure = re.compile(rf"^({re.escape(scenario)}_\d+m)_({'|'.join(FIGURE_KINDS)})\.png$")
    gone = [p for p in sorted((out / "maps").glob(f"{scenario}-*.npz")) if p.name not in maps]
    drawn = {p: m[1] for p in sorted((out / "report").glob(f"{scenario}_*.png")) if (m := figure.match(p.name))}
    gone += [p for p, stem in drawn.items() if stem not in stems]
    undrawn = [] if figures else [p for p in sorted((out / "report").glob(f"{scenario}_*.png")) if p not in gone]
    # this run's own stems too, unsaid when redrawn: a name says no preset or seed, so an earlier run's first preset
    # could pass for this one's; the workers, or the report from this run's maps, draw them again
    for p in [*gone, *drawn, *undrawn]:
        p.unlink(missing_ok=True)
    return gone, undrawn


def _count(paths: list[Path]) -> str:
    """``3 maps and 2 figures``: what a list of removed files holds, by kind."""
    n_maps = sum(p.suffix == ".npz" for p in paths)
    n_figs = len(paths) - n_maps
    parts = [f"{n} {w}{'s' * (n != 1)}" for n, w in ((n_maps, "map"), (n_figs, "figure")) if n]
    return " and ".join(parts)


def write_metrics_csv(rows: list[dict[str, Any]], path: str | Path) -> Path:
    """``metrics.csv``: :data:`METRIC_COLUMNS` first, then any other scalar keys; empty cell = not available."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    extra = sorted(
        {k for r in rows for k, v in r.items() if k not in METRIC_COLUMNS and not isinstance(v, (dict, list))}
    )
    cols = list(METRIC_COLUMNS) + extra
    with p.open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=cols, extrasaction="ignore", lineterminator="\n")
        w.writeheader()
        for r in rows:
            w.writerow({k: _fmt_csv(r.get(k)) for k in cols})
    return p


def _fmt_csv(v: Any) -> Any:
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return ""
    if isinstance(v, float):
        return f"{v:.6g}"
    return v


def read_metrics_csv(path: str | Path) -> list[dict[str, Any]]:
    """Rows of a ``metrics.csv`` with numbers parsed (empty -> None)."""

    def conv(v: str) -> Any:
        if v == "":
            return None
        try:
            f = float(v)
        except ValueError:
            return {"True": True, "False": False}.get(v, v)
        return int(f) if f.is_integer() and "." not in v and "e" not in v.lower() else f

    with Path(path).open(newline="") as fh:
        return [{k: conv(v) for k, v in r.items()} for r in csv.DictReader(fh)]


# The worst seed beside the median (brief: quote held-out results with their worst case): max or min.
WORST = {
    "fp_pct": max,
    "cdi_pct": min,
    "hazards_in_scene_pct": max,
    "chosen_sites_safe_pct": min,
    "dem_mean_abs_m": max,  # the figure most set beside the thesis's: its worst seed too (stop 57's studies QA)
}


def summarise(rows: Iterable[dict[str, Any]]) -> dict[tuple[str, str, int], dict[str, float]]:
    """(scenario, preset, altitude) -> median over seeds of every numeric metric (plus ``n_seeds``),
    and ``<metric>_worst`` for the metrics of :data:`WORST`. A metric is the median of the seeds that have it:
    the chosen sites' share only of those that offered a site, so their count goes beside it
    (``chosen_sites_seeds``; a median of 3 of 5 seeds read as all 5's: QA of stop 75)."""
    groups: dict[tuple[str, str, int], list[dict[str, Any]]] = {}
    for r in rows:
        groups.setdefault((r["scenario"], r["preset"], int(r["altitude_m"])), []).append(r)
    out = {}
    for key, rs in sorted(groups.items()):
        agg: dict[str, float] = {"n_seeds": float(len(rs))}
        offered = [r.get("chosen_sites_safe_pct") for r in rs]
        agg["chosen_sites_seeds"] = sum(isinstance(v, (int, float)) and math.isfinite(v) for v in offered)  # "2"
        for k in rs[0]:
            vals = [r.get(k) for r in rs]
            nums = [
                float(v)
                for v in vals
                if isinstance(v, (int, float)) and not isinstance(v, bool) and v is not None and math.isfinite(float(v))
            ]
            if nums and k not in ("altitude_m", "seed"):
                agg[k] = float(np.median(nums))
                if k in WORST:
                    agg[f"{k}_worst"] = float(WORST[k](nums))
        out[key] = agg
    return out


def comparison(
    summary: dict[tuple[str, str, int], dict[str, float]],
    scenario: str,
    thesis: dict[tuple[str, str, int, str], float] | None = None,
) -> list[dict[str, Any]]:
    """Side-by-side cells: one dict per (thesis table, metric, altitude) with ``thesis`` and ours per preset."""
    idx = thesis if thesis is not None else thesis_index(load_thesis())
    presets = sorted(
        {k[1] for k in summary if k[0] == scenario}, key=lambda p: PRESETS.index(p) if p in PRESETS else 99
    )
    alts = sorted({k[2] for k in summary if k[0] == scenario})
    cells = []
    for table, metric, label in COMPARISON_TABLES[scenario]:
        tmetric = _THESIS_METRIC.get(metric, metric)
        for a in alts:
            tv = None if metric in NOT_COMPARABLE else idx.get((table, scenario, a, tmetric))
            ours = {p: summary.get((scenario, p, a), {}).get(metric) for p in presets}
            cells.append(
                {
                    "table": table,
                    "metric": metric,
                    "label": label,
                    "altitude_m": a,
                    "thesis": tv,
                    **{f"ours_{p}": v for p, v in ours.items()},
                }
            )
    for metric, label in EXTRA_METRICS:
        for a in alts:
            ours = {p: summary.get((scenario, p, a), {}).get(metric) for p in presets}
            cells.append(
                {
                    "table": "-",
                    "metric": metric,
                    "label": label,
                    "altitude_m": a,
                    "thesis": None,
                    **{f"ours_{p}": v for p, v in ours.items()},
                }
            )
    return cells


# --------------------------------------------------------------------------- sensitivity
def sensitivity_campaign(
    kind: str,
    out_dir: str | Path,
    *,
    samples: int = 20,
    seeds: Iterable[int] = (0, 1),
    presets: Iterable[str] = ("thesis", "fast"),
    cache_dir: str | Path | None = None,
    camera_px: int | None = None,
    altitudes: Iterable[int] = SENSITIVITY_ALTITUDES,
    scheduler: Any = None,
    workers: int | None = None,
    progress: bool = True,
    max_cells: int | None = None,
    raster: str = DEFAULT_RASTER,
) -> list[dict[str, Any]]:
    """Thesis sec 6.3 Monte Carlo on the approach scenario; one row per (preset, seed, altitude, sample).

    Every (preset, seed, altitude) also runs once with perfect pose knowledge
    (sample ``-1``); ``dem_mean_rel_pct`` etc. are the increase of each
    sample's DEM error over that reference, in percent (Tables 6.12-6.19).
    Results go to ``out_dir/runs/sensitivity-<kind>.jsonl`` (resumable) and
    ``out_dir/sensitivity_<kind>.csv``.
    """
    from ground_sim.seeds import seed_set_of
    from studies.executor import Task, code_fingerprint, run_tasks

    _check_choice("kind", [kind], SENSITIVITY_KINDS)
    presets = _check_choice("preset", presets, PRESETS)
    if not (isinstance(samples, int) and 1 <= samples <= MAX_SAMPLES):
        raise EvaluationError(
            f"samples must be an integer in [1, {MAX_SAMPLES}] (each is a pipeline run per seed, altitude and "
            f"preset, its task held in memory), got {samples!r}"
        )
    seeds = [int(s) for s in seeds]
    altitudes = list(altitudes)
    runs = len(presets) * len(seeds) * len(altitudes) * (samples + 1)
    if runs > MAX_SENSITIVITY_RUNS:  # said before the renders, not after them as the memory runs out
        raise EvaluationError(
            f"{runs} pipeline runs ({len(presets)} preset(s) x {len(seeds)} seed(s) x {len(altitudes)} altitude(s) "
            f"x ({samples} samples + 1 reference)) is over {MAX_SENSITIVITY_RUNS}: use fewer --samples or --seeds, "
            "or split the study over several --out directories"
        )
    out = Path(out_dir)
    cache = Path(cache_dir) if cache_dir is not None else out / "cache"
    pairs = render_all(
        "approach",
        seeds,
        cache,
        camera_px=camera_px,
        altitudes=altitudes,
        scheduler=scheduler,
        workers=workers,
        progress=progress,
        run_dir=out / "runs",
        max_cells=max_cells,
        raster=raster,
    )
    tasks: list[Any] = []
    info: dict[str, dict[str, Any]] = {}
    tag = render_tag(max_cells, raster)
    for preset in presets:
        for e in pairs:
            alt = int(round(e["altitude_m"]))
            for i in range(-1, samples):
                pe = None if i < 0 else sample_pose_error(kind, e["seed"] * 100003 + alt, i)
                tid = f"{kind}-{preset}-s{e['seed']}-{alt}-{'ref' if i < 0 else i}{tag}"
                tasks.append(
                    Task(tid, {"pair_dir": e["pair_dir"], "preset": preset, "pose_error": pe, "truth_slope": False})
                )
                info[tid] = {
                    "kind": kind,
                    "preset": preset,
                    "seed": e["seed"],
                    "altitude_m": alt,
                    "sample": i,
                    **_flat_error(pe),
                }
    res = run_tasks(
        evaluate_pair,
        tasks,
        out / "runs" / f"sensitivity-{kind}.jsonl",
        scheduler=scheduler,
        workers=workers,
        progress=progress,
        desc=f"sensitivity {kind}",
        code=code_fingerprint(EVAL_CODE),
        inputs=task_inputs(camera_px, render_identity("approach")),
    )
    rows = []
    for t in tasks:
        meta = info[t.id]
        ref = res[f"{kind}-{meta['preset']}-s{meta['seed']}-{meta['altitude_m']}-ref{tag}"]
        r = res[t.id]
        row = {
            **meta,
            "seed_set": seed_set_of(meta["seed"]),  # held-out or tuning, in the file itself
            **{
                k: r.get(k)
                for k in (
                    "dem_mean_abs_m",
                    "dem_median_m",
                    "dem_mad_m",
                    "dem_detrended_mean_abs_m",
                    "fp_pct",
                    "cdi_pct",
                    "valid_pct",
                    "pipeline_s",
                )
            },
        }
        for k, name in (
            ("dem_mean_abs_m", "dem_mean_rel_pct"),
            ("dem_mad_m", "dem_mad_rel_pct"),
            ("dem_detrended_mean_abs_m", "dem_detrended_rel_pct"),
        ):
            a, b = r.get(k), ref.get(k)
            row[name] = 100.0 * (a - b) / b if a is not None and b else None
        # last, the columns before it in place for readers: the kinds studied into one --out share its page, and
        # may come from runs with other cameras (the seeds are in the rows already)
        row["camera_px"] = camera_px or THESIS_CAMERA_PX
        rows.append(row)
    _write_rows(rows, out / f"sensitivity_{kind}.csv")
    return rows


def _flat_error(pe: dict[str, Any] | None) -> dict[str, float]:
    out = {f"{k}{j + 1}": 0.0 for j in range(2) for k in ("dz_m", "dx_m", "dy_m", "pitch_deg", "roll_deg", "yaw_deg")}
    for j, fr in enumerate((pe or {}).get("frames", [])):
        for k, v in fr.items():
            out[f"{k}{j + 1}"] = float(v)
    return out


def _write_rows(rows: list[dict[str, Any]], path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    cols = list(rows[0]) if rows else []
    with path.open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=cols, lineterminator="\n")
        w.writeheader()
        for r in rows:
            w.writerow({k: _fmt_csv(r.get(k)) for k in cols})


def thesis_sensitivity(kind: str, altitude_m: int) -> dict[str, float | None]:
    """The thesis's own figures for one sensitivity row (Tables 6.12-6.19, approach pairs at 125-300 m): for
    ``altitude`` the median over its 20 samples of the relative DEM mean-error increase (``sNN.dem_mean_rel_pct``),
    for ``attitude`` that increase at each of its six pitch levels and their median (None at an altitude it did not
    study); {} for the other kinds, which it did not study. It drew its samples one way, we another (module doc):
    medians, not sample by sample."""
    idx = thesis_index(load_thesis())
    pre = {"altitude": "s", "attitude": "dev"}.get(kind)
    vals = {
        m: v
        for (t, sc, a, m), v in idx.items()
        if sc == "approach" and a == altitude_m and t.startswith("6.1") and m.endswith(".dem_mean_rel_pct")
        and pre is not None and m.startswith(pre)
    }  # fmt: skip
    if pre is None:
        return {}
    # the same keys on every row of a kind (None where the thesis has no such altitude): one table, one header
    out: dict[str, float | None] = {"thesis_median_rel_pct": float(np.median(list(vals.values()))) if vals else None}
    if kind == "attitude":
        for lv in ATTITUDE_LEVELS_DEG:
            out[f"thesis_rel_pct@{lv:+.2f}"] = vals.get(f"dev{lv:+.2f}.dem_mean_rel_pct")
    return out


def sensitivity_summary(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per (kind, preset, altitude): medians of the relative DEM error increase and the share within +15 %,
    with the thesis's own figure beside it where it studied that kind and altitude (:func:`thesis_sensitivity`).

    For ``altitude`` the samples are also split like the thesis's Fig. 6.13
    reading: near the diagonal (|dh1 - dh2| <= 0.15 m, both poses off by about
    the same) vs off it (|dh1 - dh2| > 0.3 m). For ``attitude`` the
    six thesis levels are reported one by one.
    """
    groups: dict[tuple[str, str, int], list[dict[str, Any]]] = {}
    no_dem: dict[tuple[str, str, int], int] = {}
    for r in rows:
        if r["sample"] < 0:
            continue
        key = (r["kind"], r["preset"], int(r["altitude_m"]))
        no_dem[key] = no_dem.get(key, 0) + (r.get("dem_mean_rel_pct") is None)
        if r.get("dem_mean_rel_pct") is not None:
            groups.setdefault(key, []).append(r)
    lost = sorted(k for k, v in no_dem.items() if v and k not in groups)
    if lost:  # every sample without a DEM error: say so rather than leave the row out
        print(f"note: sensitivity: no sample of {lost} has a DEM error to compare", file=sys.stderr, flush=True)
    out = []
    for (kind, preset, alt), rs in sorted(groups.items()):
        rel = np.array([r["dem_mean_rel_pct"] for r in rs], float)
        det = np.array([np.nan if r.get("dem_detrended_rel_pct") is None else r["dem_detrended_rel_pct"] for r in rs])
        s: dict[str, Any] = {
            "kind": kind,
            "preset": preset,
            "altitude_m": alt,
            "n": len(rs),
            # samples left out of the statistics: no DEM (or none in the perfect-knowledge reference)
            "n_no_dem": no_dem.get((kind, preset, alt), 0),
            "median_rel_pct": float(np.median(rel)),
            "max_rel_pct": float(rel.max()),
            "within_15pct": float(np.mean(rel <= 15.0) * 100),
            # the same after removing the error's best plane (tilt + datum: scoring.detrended_error)
            "detrended_median_rel_pct": float(np.median(det)) if np.isfinite(det).all() else None,
            "detrended_max_rel_pct": float(det.max()) if np.isfinite(det).all() else None,
        }
        if kind == "altitude":
            d = np.array([abs(r["dz_m1"] - r["dz_m2"]) for r in rs])
            near, far = rel[d <= 0.15], rel[d > 0.3]
            s["near_diag_median_rel_pct"] = float(np.median(near)) if near.size else None
            s["off_diag_median_rel_pct"] = float(np.median(far)) if far.size else None
        if kind == "attitude":
            for lv in ATTITUDE_LEVELS_DEG:
                sel = rel[np.isclose([r["pitch_deg1"] for r in rs], lv)]
                s[f"rel_pct@{lv:+.2f}"] = float(np.median(sel)) if sel.size else None
        s.update(thesis_sensitivity(kind, alt))
        out.append(s)
    return out
