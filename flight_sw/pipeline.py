"""The hazard-detection pipeline (thesis Fig. 4.2) as one call: images + poses in, DEM + hazards out.

Stages: validate -> rocks, shadow, coverage (image-only hazards) -> coarse DEM
(half-resolution sweep) -> full DEM -> georeferencing -> world grid -> slope,
roughness -> hazard -> sites. Anytime: with a deadline, the sweeps check the
clock every few planes and stop ``mapping_reserve_s`` before it; the result is
then built from the best level reached (``image_only`` < ``coarse`` < ``full``)
and flagged ``degraded``. Ground truth is never an input.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from protocol.pairdir import Camera, Pose

from .confidence import elevation_uncertainty, reject_uncertain
from .gapfill import fill_small_gaps
from .georef import backproject
from .mapping import (
    HazardGrid,
    combine,
    grid_extent,
    grid_xy,
    ground_sample_distance,
    image_to_grid_coords,
    pull,
    sample_grid,
    three_state,
)
from .rocks import rock_mask
from .shading import local_shadow_mask, relative_brightness, shading_mask
from .shadow import shadow_mask
from .sites import Site, select_sites
from .slope import plane_fit, roughness
from .sweep import coverage_mask, planes_uniform_disparity, planes_uniform_dz, scaled_camera, sweep_dem
from .validate import FlightInputError, check_inputs
from .warping import area_sigma

LEVELS = ("image_only", "coarse", "full")


@dataclass(frozen=True)
class Params:
    """Pipeline knobs. ``PRESETS`` holds the two reference settings."""

    name: str = "custom"
    half_window: int = 6  # correlation window (2W+1)^2 (sec 4.3); capped by window_px
    cap_window_to_overlap: bool = True  # keep the window <= 1/4 of the overlap (tiny sensors), see window_px
    cost: str = "sad"  # "sad" | "ssd" (eq. 3.13/3.14)
    plane_spacing: str = "disparity"  # "dz": uniform metres; "disparity": uniform i2 pixels at the edge
    dz_m: float = 0.15  # plane step for "dz"
    disparity_step_px: float = 0.5  # largest i2-pixel move between planes for "disparity"
    prefilter: bool = True  # low-pass i2 to i1's pixel footprint before warping
    coarse_to_fine: bool = True  # narrow the full-resolution range to the coarse DEM's
    reject_rel_uncertainty: float = 0.0  # drop matches with u > this x median u (confidence.py); 0: off
    sharp_curvature: float = 0.2  # ... but keep matches whose cost-curve curvature is at least this
    shading_sigma_px: float = 10.0  # local-mean scale of the photometric cues (shading.py), at least ...
    shading_sigma_footprints: float = 3.0  # ... this many lander footprints (in i1 px at the image centre)
    shadow_dark_rel: float = 0.0  # > 0: shadow also needs rho < -this (shading.py); 0: eq. 4.9 only
    shading_limit: float = 0.0  # > 0: |rho| > this is a hazard (steep-wall cue); 0: off
    fill_gap_px: int = 0  # fill DEM gaps narrower than ~this (i1 px) before the slope fit
    fill_min_frac: float = 0.3  # ... where this share of the (2r+1)^2 neighbourhood is valid
    coarse_half_window: int = 4
    coarse_range_pct: float = 0.5  # fine range: this .. 100-this percentile of the coarse DEM, padded
    coarse_step_px: float = 0.5  # at half resolution
    relief_margin_frac: float = 0.06  # sweep range: +- max(min_m, frac * altitude) around Z = 0
    relief_margin_min_m: float = 10.0
    mask_rocks: bool = True  # rock pixels excluded from correlation, NaN elevation (sec 4.2)
    rock_k: float = 11.0  # eq. 4.8
    rock_dilate_px: int = 2
    harris_alpha: float = 0.04
    footprint_m: float = 3.0  # lander footprint (Table 2.1)
    slope_limit_deg: float = 15.0
    hazard_margin_px: float = 0.0  # keep-out margin around DEM hazards, i1 px / grid cells (mapping.combine)
    rough_limit_m: float = 0.30
    cell_m: float | None = None  # world grid cell; None: median GSD of i1 over the covered area
    n_sites: int = 5
    mapping_reserve_s: float = 0.03  # sweeps stop this long before the deadline
    check_every: int = 4  # planes between clock checks

    def validate(self) -> None:
        if self.half_window < 1 or self.coarse_half_window < 1:
            raise FlightInputError("params: half_window must be >= 1")
        if self.cost not in ("sad", "ssd"):
            raise FlightInputError(f"params: cost must be 'sad' or 'ssd', got {self.cost!r}")
        if self.plane_spacing not in ("dz", "disparity"):
            raise FlightInputError(f"params: plane_spacing must be 'dz' or 'disparity', got {self.plane_spacing!r}")
        for name in (
            "dz_m",
            "disparity_step_px",
            "coarse_step_px",
            "footprint_m",
            "slope_limit_deg",
            "rough_limit_m",
            "relief_margin_min_m",
        ):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise FlightInputError(f"params: {name} must be a positive number, got {v!r}")
        if not (math.isfinite(self.hazard_margin_px) and 0 <= self.hazard_margin_px <= 50):
            raise FlightInputError(f"params: hazard_margin_px must be in [0, 50], got {self.hazard_margin_px!r}")
        if self.cell_m is not None and not (math.isfinite(self.cell_m) and self.cell_m > 0):
            raise FlightInputError(f"params: cell_m must be positive, got {self.cell_m!r}")


def window_px(half_window: int, overlap_px: int, cap: bool = True) -> int:
    """Half-window actually used: ``W``, capped so the window spans at most a quarter of the overlap.

    The thesis tuned 17x17 on 512 px images (sec 4.3), where i2 overlaps i1 on
    ~256 px. On a tiny sensor (a 96 px pair overlaps on ~46 px) a 17 px window and
    its border would leave almost nothing, so ``2W + 1 <= overlap / 4`` (min W = 2).
    Unchanged for 256 px images and up.
    """
    if not cap:
        return int(half_window)
    return int(min(half_window, max(2, int((overlap_px / 4.0 - 1.0) / 2.0))))


PRESETS: dict[str, Params] = {
    # fast: SSD + 17x17 window, chosen on ground_sim seed-0 pairs and confirmed on seed-1 pairs
    # (docs/benchmarks/pipeline.md); with i2 prefiltered and rocks masked, SSD's outlier sensitivity
    # (the thesis's reason for SAD, sec 4.2) no longer dominates.
    # Confidence rejection, photometric cues and gap filling (issue #6): tuned on approach/vertical
    # seeds 0-1, seed 2 held out (docs/benchmarks/pipeline.md).
    # A 1 px keep-out margin around slope/roughness hazards (issue #6 follow-up): approach 300 m
    # seed 0 FP 1.23 -> 0.86 % for 5-15 points more false alarms (docs/benchmarks/pipeline.md).
    "fast": Params(
        name="fast",
        half_window=10,
        cost="ssd",
        reject_rel_uncertainty=1.5,
        shadow_dark_rel=0.1,
        shading_limit=0.15,
        fill_gap_px=8,
        hazard_margin_px=1.0,
    ),
    "thesis": Params(
        name="thesis", half_window=8, plane_spacing="dz", dz_m=0.15, prefilter=False, coarse_to_fine=False
    ),
}


@dataclass
class PipelineResult:
    """Everything the pipeline produced. Image-plane arrays are HxW in i1's pixels."""

    elevation: np.ndarray  # float32 world Z, NaN where not recovered
    hazard: np.ndarray  # float32 in [0, 1], NaN outside the area both images cover
    slope_deg: np.ndarray  # float32
    roughness_m: np.ndarray  # float32
    rock_mask: np.ndarray  # bool
    shadow_mask: np.ndarray  # bool
    covered: np.ndarray  # bool: seen by both images
    world_xy: np.ndarray  # float32 HxWx2 world X, Y of each pixel
    grid: HazardGrid
    sites: list[Site]
    timings: dict[str, dict[str, float]]
    degraded: bool
    level: str
    valid_fraction: float
    params: dict[str, Any]
    info: dict[str, Any] = field(default_factory=dict)
    # uint8 HxW, protocol.pairdir.STATE_* (safe/unsafe/unknown/outside); derived from hazard when not given
    state: np.ndarray = field(default_factory=lambda: np.empty(0, np.uint8))
    psafe: np.ndarray = field(default_factory=lambda: np.empty(0, np.float32))  # float32 HxW P(safe), NaN outside
    sigma: np.ndarray | None = None  # float32 HxW elevation standard uncertainty (m), NaN where unknown

    def __post_init__(self) -> None:
        if self.state.size != self.hazard.size or self.psafe.size != self.hazard.size:
            self.state, self.psafe = three_state(self.hazard, self.elevation)


@contextmanager
def _stage(timings: dict[str, dict[str, float]], name: str) -> Iterator[None]:
    w0, c0 = time.perf_counter(), time.thread_time()
    try:
        yield
    finally:
        timings[name] = {"wall_s": time.perf_counter() - w0, "cpu_s": time.thread_time() - c0}


def _resolve(preset: str | Params) -> Params:
    if isinstance(preset, Params):
        p = preset
    elif isinstance(preset, str) and preset in PRESETS:
        p = PRESETS[preset]
    else:
        raise FlightInputError(f"preset must be one of {sorted(PRESETS)} or a Params, got {preset!r}")
    p.validate()
    return p


def _centre_gsd(camera: Camera, pose: Pose) -> float:
    """Ground sample distance (m) at the image centre over the reference plane: slant range / f."""
    d = pose.position[2] / max(1e-9, -pose.R[2, 2])
    return float(max(1e-6, d / camera.fx))


def _gsd_scale(camera: Camera, pose1: Pose, pose2: Pose) -> float:
    """GSD(i2) / GSD(i1) at the image centre over the reference plane (~0.5 for a halved altitude)."""
    d1 = pose1.position[2] / max(1e-9, -pose1.R[2, 2])
    d2 = pose2.position[2] / max(1e-9, -pose2.R[2, 2])
    return float(min(1.0, d2 / d1)) if d1 > 0 and d2 > 0 else 1.0


def run_pipeline(
    i1: np.ndarray,
    i2: np.ndarray,
    pose1: Pose,
    pose2: Pose,
    camera: Camera,
    *,
    preset: str | Params = "fast",
    deadline_s: float | None = None,
    nominal_site_xy: tuple[float, float] = (0.0, 0.0),
    deadline_at: float | None = None,
) -> PipelineResult:
    """Hazard detection from two descent images (i1 higher, i2 lower; poses world->camera).

    ``deadline_s`` is a budget in seconds from the call, ``deadline_at`` an absolute
    ``time.monotonic()`` value (the earlier wins); the result is the best
    level reached in time (see module doc). Raises :class:`FlightInputError`
    for bad arguments.
    """
    t_start = time.monotonic()
    timings: dict[str, dict[str, float]] = {}
    with _stage(timings, "validate"):
        p = _resolve(preset)
        check_inputs(i1, i2, pose1, pose2, camera)
        if deadline_s is not None and not (isinstance(deadline_s, (int, float)) and math.isfinite(deadline_s)):
            raise FlightInputError(f"deadline_s must be a finite number of seconds, got {deadline_s!r}")
        try:
            nominal = (float(nominal_site_xy[0]), float(nominal_site_xy[1]))
        except (TypeError, ValueError, IndexError):
            raise FlightInputError(f"nominal_site_xy must be (x, y), got {nominal_site_xy!r}") from None
        if not all(math.isfinite(v) for v in nominal):
            raise FlightInputError(f"nominal_site_xy must be finite, got {nominal_site_xy!r}")
        if deadline_at is not None and not (isinstance(deadline_at, (int, float)) and math.isfinite(deadline_at)):
            raise FlightInputError(f"deadline_at must be a finite time.monotonic() value, got {deadline_at!r}")
        ends = [t for t in (None if deadline_s is None else t_start + float(deadline_s), deadline_at) if t is not None]
        deadline = min(ends) if ends else None
        sweep_deadline = None if deadline is None else deadline - p.mapping_reserve_s
        a1 = np.ascontiguousarray(i1, dtype=np.float32)
        a2 = np.ascontiguousarray(i2, dtype=np.float32)
        alt = float(pose1.position[2])
        margin = max(p.relief_margin_min_m, p.relief_margin_frac * alt)
        z_lo, z_hi = -margin, min(margin, float(pose2.position[2]) * 0.5)
        scale = _gsd_scale(camera, pose1, pose2)
        sigma = area_sigma(scale) if p.prefilter else 0.0
    info: dict[str, Any] = {"sweep_range_m": [z_lo, z_hi], "gsd_ratio": scale}

    with _stage(timings, "rocks"):
        rocks = rock_mask(i1, p.rock_k, p.harris_alpha, p.rock_dilate_px)
    with _stage(timings, "shadow"):
        shadow = shadow_mask(i1)
        shading = np.zeros(i1.shape, bool)
        if p.shadow_dark_rel > 0 or p.shading_limit > 0:
            fp_px = p.footprint_m / _centre_gsd(camera, pose1)
            rho = relative_brightness(
                i1, max(p.shading_sigma_px, p.shading_sigma_footprints * fp_px), max(1.0, fp_px / 3.0)
            )
            if p.shadow_dark_rel > 0:
                shadow = local_shadow_mask(i1, shadow, rho, p.shadow_dark_rel)
            if p.shading_limit > 0:
                shading = shading_mask(rho, p.shading_limit)
    with _stage(timings, "coverage"):
        covered = coverage_mask(camera, pose1, pose2, 0.0)
        rows, cols = np.flatnonzero(covered.any(axis=1)), np.flatnonzero(covered.any(axis=0))
        overlap = min(rows[-1] - rows[0] + 1, cols[-1] - cols[0] + 1) if rows.size else 0
        W_full = window_px(p.half_window, overlap, p.cap_window_to_overlap)
        W_coarse = window_px(p.coarse_half_window, overlap // 2, p.cap_window_to_overlap)
        info["half_window_px"], info["coarse_half_window_px"] = W_full, W_coarse
    level = "image_only"
    elevation = np.full(i1.shape, np.nan, np.float32)

    with _stage(timings, "coarse_dem"):
        cam_c = scaled_camera(camera, 1)
        c1, c2 = cv2.pyrDown(a1), cv2.pyrDown(a2)
        rock_c = cv2.resize(
            rocks.astype(np.uint8), (cam_c.width, cam_c.height), interpolation=cv2.INTER_NEAREST
        ).astype(bool)
        planes_c = planes_uniform_disparity(cam_c, pose1, pose2, z_lo, z_hi, p.coarse_step_px)
        res_c = sweep_dem(
            c1,
            c2,
            cam_c,
            pose1,
            pose2,
            planes_c,
            half_window=W_coarse,
            cost=p.cost,
            prefilter_sigma=sigma,
            ignore=rock_c if p.mask_rocks else None,
            deadline=sweep_deadline,
            check_every=p.check_every,
        )
        info["coarse_planes"] = int(planes_c.size)
        if res_c.complete and res_c.curvature is not None and p.reject_rel_uncertainty > 0:
            # outliers would widen the fine range
            u_c = elevation_uncertainty(res_c.elevation, res_c.curvature, res_c.planes)
            res_c.elevation = reject_uncertain(
                res_c.elevation, u_c, p.reject_rel_uncertainty, res_c.curvature, p.sharp_curvature
            )
        n_coarse = int(np.isfinite(res_c.elevation).sum())
        if res_c.complete and n_coarse > 0:
            coarse = cv2.resize(res_c.elevation, (camera.width, camera.height), interpolation=cv2.INTER_LINEAR)
            elevation = np.where(rocks & p.mask_rocks, np.nan, coarse).astype(np.float32)
            level = "coarse"

    with _stage(timings, "full_dem"):
        # tiny images can leave the half-resolution DEM empty: then sweep the full range
        if res_c.complete:
            f_lo, f_hi = z_lo, z_hi
            if p.coarse_to_fine and n_coarse >= 50:
                pad = 2.0 * float(np.max(np.diff(planes_c)))
                lo, hi = np.nanpercentile(res_c.elevation, [p.coarse_range_pct, 100.0 - p.coarse_range_pct])
                f_lo, f_hi = max(z_lo, float(lo) - pad), min(z_hi, float(hi) + pad)
            if p.plane_spacing == "dz":
                planes = planes_uniform_dz(f_lo, f_hi, p.dz_m)
            else:
                planes = planes_uniform_disparity(camera, pose1, pose2, f_lo, f_hi, p.disparity_step_px)
            info["full_planes"] = int(planes.size)
            info["full_range_m"] = [f_lo, f_hi]
            res_f = sweep_dem(
                a1,
                a2,
                camera,
                pose1,
                pose2,
                planes,
                half_window=W_full,
                cost=p.cost,
                prefilter_sigma=sigma,
                ignore=rocks if p.mask_rocks else None,
                deadline=sweep_deadline,
                check_every=p.check_every,
            )
            info["full_planes_done"] = res_f.planes_done
            if res_f.complete:
                elevation = res_f.elevation
                if p.reject_rel_uncertainty > 0 and res_f.curvature is not None:
                    u = elevation_uncertainty(elevation, res_f.curvature, res_f.planes)
                    elevation = reject_uncertain(
                        elevation, u, p.reject_rel_uncertainty, res_f.curvature, p.sharp_curvature
                    )
                level = "full"

    with _stage(timings, "gap_fill"):
        # hazard mapping uses the gap-filled DEM; the returned elevation stays measured-only
        have_dem = level != "image_only"
        elev_map = fill_small_gaps(elevation, p.fill_gap_px, p.fill_min_frac) if have_dem else elevation
        info["filled_fraction"] = float(
            (np.isfinite(elev_map) & ~np.isfinite(elevation) & covered).sum() / max(1, int(covered.sum()))
        )

    with _stage(timings, "georef"):
        z_ref = float(np.nanmedian(elevation)) if have_dem and np.isfinite(elevation).any() else 0.0
        z_fill = np.where(np.isfinite(elev_map), elev_map, np.float32(z_ref))
        X, Y = backproject(camera, pose1, z_fill)
        world_xy = np.stack([X, Y], axis=-1).astype(np.float32)

    with _stage(timings, "grid"):
        cell = p.cell_m or ground_sample_distance(X, Y, covered, 50.0)
        if not math.isfinite(cell) or cell <= 0:
            cell = ground_sample_distance(X, Y, np.ones(covered.shape, bool))
        origin, shape = grid_extent(np.where(covered, X, np.nan), np.where(covered, Y, np.nan), cell)
        GX, GY = grid_xy(shape, origin, cell)
        gu, gv = image_to_grid_coords(camera, pose1, z_fill, GX, GY, z_ref)
        g_cov = pull(covered.astype(np.float32), gu, gv) > 0.999
        g_elev = pull(elev_map, gu, gv) if have_dem else np.full(shape, np.nan, np.float32)
        g_rock = pull(rocks.astype(np.float32), gu, gv) > 0
        g_shadow = pull((shadow | shading).astype(np.float32), gu, gv) > 0.5

    with _stage(timings, "slope"):
        g_slope: np.ndarray | None = None
        g_rough: np.ndarray | None = None
        if have_dem:
            g_slope, g_plane = plane_fit(g_elev, cell, p.footprint_m)
            g_rough = roughness(g_elev, g_plane)
            slope_img = sample_grid(g_slope, origin, cell, X, Y)
            rough_img = roughness(elev_map, sample_grid(g_plane, origin, cell, X, Y))
        else:
            slope_img = np.full(i1.shape, np.nan, np.float32)
            rough_img = np.full(i1.shape, np.nan, np.float32)

    with _stage(timings, "hazard"):
        hazard = combine(
            slope_img if have_dem else None,
            rough_img,
            shadow | shading,
            rocks,
            covered,
            p.slope_limit_deg,
            p.rough_limit_m,
            p.hazard_margin_px,
        )
        # the grid cell is i1's median GSD, so the same count of pixels and cells is the same margin
        g_haz = combine(
            g_slope, g_rough, g_shadow, g_rock, g_cov, p.slope_limit_deg, p.rough_limit_m, p.hazard_margin_px
        )
        grid = HazardGrid(g_haz, np.where(g_cov, g_elev, np.nan).astype(np.float32), origin, float(cell))

    with _stage(timings, "sites"):
        sites = select_sites(grid, p.footprint_m, nominal, p.n_sites)

    timings["total"] = {
        "wall_s": sum(t["wall_s"] for t in timings.values()),
        "cpu_s": sum(t["cpu_s"] for t in timings.values()),
    }
    n_cov = int(covered.sum())
    valid = float(np.isfinite(elevation[covered]).sum() / n_cov) if n_cov else 0.0
    params = dataclasses.asdict(p)
    return PipelineResult(
        elevation.astype(np.float32),
        hazard,
        slope_img.astype(np.float32),
        rough_img.astype(np.float32),
        rocks,
        shadow,
        covered,
        world_xy,
        grid,
        sites,
        timings,
        level != "full",
        level,
        valid,
        params,
        info,
    )
