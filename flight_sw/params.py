"""The pipeline's knobs (:class:`Params`) and its named settings (:data:`PRESETS`).

``fast`` is flight v2 (issue 9), tuned on ``ground_sim.seeds.TUNING_SEEDS`` (docs/benchmarks/pipeline.md,
bench/eval_flight.py); ``thesis`` is the thesis's own setting (sec 4.3, 6.1); ``fast_v1``, ``fast_gaussian``
and ``fast_unrefined`` are kept for the ablations. :func:`window_px` caps the correlation window on small
sensors. Every setting is validated (:meth:`Params.validate`) before a run.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

from .costvolume import RULES
from .dense import DenseParams
from .evidence import CAP_SLOPES
from .validate import FlightInputError


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
    # > 0: under a sun higher than this (deg), rho is read as under this sun (shading.rho_at_sun); 0: off
    shading_sun_ref_deg: float = 0.0
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
    mapping_reserve_s: float = 0.03  # sweeps stop this long (unthrottled s, x time_scale) before the deadline
    # > 0 (v2 flow): from the range search on, that reserve is this margin x mapping_cost_s of the pair's
    # image, covered pixels and world-grid cells instead of mapping_reserve_s x its pixels
    mapping_reserve_margin: float = 0.0
    check_every: int = 4  # planes between clock checks
    # ---- flight v2 (issue 9); dem="sweep" is the v1 / thesis flow and ignores these
    dem: str = "sweep"  # "sweep": WTA window sweep (v1, thesis); "sgm": cost volume + semi-global aggregation
    range_search: bool = False  # find the ground (rangefind.py) instead of +- relief_margin around Z = 0
    range_below_frac: float = 0.6  # wide prior: [-below * h1, min(above * h1, 0.3 h2)]
    range_above_frac: float = 0.2
    sgm_radius: int = 2  # cost support (2r+1)^2 (costvolume.py)
    sgm_mean_radius: int = 3
    sgm_p1: int = 16
    sgm_p2: int = 128
    sgm_p2_g0: float = 4.0
    p2_gradient_adapt: bool = True
    sgm_paths: int = 8  # 8, 4 or 0 (no aggregation)
    uniqueness: float = 0.05
    speckle_px: int = 30
    end_margin: int = 1  # planes: minima this close to a partially seen end of a pixel's plane interval are dropped
    min_interval_frac: float = 0.5  # pixels must see at least this share of the planes
    sigma_temperature: float = 4.0  # sigma calibration (sgm.plane_sigma)
    kappa_floor: float = 0.0  # > 0: keep matches with a non-convex raw cost curve at this curvature (sgm.py)
    sigma_uniq_scale: float = 0.2  # ambiguity weight of a second minimum (sgm.plane_sigma)
    max_planes: int = 64  # full-resolution planes; the disparity step grows to stay under it ...
    min_planes: int = 24  # ... and shrinks to reach this many
    slope_sigma_gain: float = 1.0  # slope uncertainty = gain * mean footprint sigma / footprint (evidence.py)
    rough_sigma_gain: float = 0.2  # roughness uncertainty = gain * sigma
    sigma_k: float = 2.0  # unsafe only beyond k sigma of a limit
    psafe_min: float = 0.9  # safe only with P(safe) >= this
    shadow_dark_frac: float = 0.0  # > 0: shadow = I < frac * median(I) (replaces eq. 4.9 in the v2 flow)
    # > 0: ... unless shadow covers most of the image (a polar sun a few degrees up), where the median is a
    # shadow's brightness: the lit ground's median is used then (shadow.lit_level, this = the class ratio)
    shadow_mode_ratio: float = 0.0
    # > 0: the shadow hazard cue's own threshold (x the lit level), above shadow_dark_frac, which stays the
    # matching mask's: a boulder's shadow a pixel or two wide is partly lit (0.2-0.36 of the median on tuning
    # renders) and is a hazard, but its pixels still carry texture to match
    shadow_cue_frac: float = 0.0
    rocks_as_hazard: bool = True  # Harris rocks are an unsafe cue
    mask_shadow: bool = False  # v2: dark-shadow pixels get no elevation (no texture to match)
    texture_min: float = 0.0  # > 0: pixels whose support has a grey-level std below this get no elevation
    # > 0: those unmatched pixels (dark, blank) within this many metres of a match get the aggregation's
    # elevation and a sigma growing dark_fill_slope per metre (dense.gap_fill_sigma). The DEM reports them;
    # the hazard stage reads matches only (an interpolated elevation is no evidence for "safe")
    dark_fill_m: float = 0.0
    dark_fill_slope: float = 0.6
    wide_slope_factor: float = 0.0  # > 1: slope = max(footprint slope, slope over this many footprints)
    # the footprint slope read from the shading too (photoclinometry.py), a P(safe) feature, when the sun's
    # azimuth and elevation are known; its brightness gain is fitted over this many footprints (16-64 px)
    shading_slope: bool = False
    shading_gain_footprints: float = 8.0
    site_margin_m: float = 0.5  # known-safe margin around a site's footprint
    site_reach_cells: float = 0.0  # ... and this many grid cells more (0.5: every cell the disk reaches into)
    site_relief_max_m: float = 0.0  # > 0: no site where the DEM spans more than this ...
    site_relief_window_m: float = 30.0  # ... in a square this wide around it (sites.local_relief)
    refine_pose: bool = False  # refine the relative pose from the images first (pose_refine.py, issue #10)
    # a second DEM with the lower frame as the reference, averaged with the first where both matched (lowerview.py).
    # A pair where it was not averaged in (no time for it, or a coarse DEM) is called with the P(safe) model and
    # FP budget fitted on the first DEM alone: the fallback ones ("" = the shipped model)
    lower_view_dem: bool = False
    lower_view_fallback_model: str = ""
    lower_view_fallback_budget: float = 0.00175
    # ---- multi-frame (issue 10): frames between the reference and the widest-baseline frame (v2 flow only)
    multi_rule: str = "mean"  # costvolume.multi_cost_slab: "mean" | "drop_worst" across frames
    multi_cost_gain: float = 1.0  # combined cost x this (data term vs SGM penalties); N = Okutomi & Kanade's sum
    multi_weight_exp: float = 2.0  # frame weight = (its parallax / the widest frame's)^exp; 0: equal weights
    multi_truncate: float = 0.0  # > 0: cap each frame's cost at this (cost units) before combining
    multi_extent: str = "widest"  # map where the widest pair sees ("widest") or where any frame does ("union")
    multi_sigma_gamma: float = 0.3  # sigma / I^(gamma/2), I = sum_f (parallax_f / widest)^2 over the frames seen
    # "gaussian": P(safe) = Phi(..) Phi(..), safe at psafe_min (evidence.classify); "calibrated": the binned
    # logistic model fitted on tuning seeds (psafe.py) and the FP-budget rule (safe while sum(1 - p) <= budget N)
    psafe_model: str = "gaussian"
    fp_budget: float = 0.005  # "calibrated": expected share of undetected hazards among the covered points
    psafe_unsafe: float = 0.5  # "calibrated": unsafe below this P(safe), unknown between it and the call
    call_slope_max: float = math.inf  # "calibrated": never call safe an estimated slope >= this x the limit
    call_slope_sigma_k: float = 0.0  # > 0: the cap spares a slope below the limit by this many sigmas (off)
    call_slope_feature: str = "a"  # the slope the cap reads: "a" (DEM), "a_pc" (shading), "max" (evidence.cap_slope)
    psafe_model_path: str = ""  # "calibrated": a model file other than flight_sw/psafe_model.json
    # "calibrated": "model" calls with the operating point the model records (info.call: fp_budget, psafe_min,
    # call_slope_max, chosen by the tuning CV for that model; psafe.model_call) where it records one, and with
    # these params where it does not (the 512 px model); "params": always with these params
    psafe_call: str = "model"
    # "calibrated": a grid cell is called safe when more than this share of the bilinear weight of the i1
    # pixels it reads was called safe (unsafe: more than half was called unsafe). 0.999 (all of them, until
    # stop 38) eroded the safe ground by half a pixel all round: read back at the pixels, the grid's CDI was
    # 5-6 points (median) under the pixel map's on the tuning descents (docs/benchmarks/pipeline.md)
    grid_call_share: float = 0.5
    # every cell that holds the ground point of a pixel called unsafe is unsafe (evidence.hold_unsafe_pixels):
    # the bilinear pull alone lost a one-pixel hazard with no cell centre near it, and the site search reads
    # only the grid (review of stop 64). False: the pull alone, as before
    grid_hold_unsafe: bool = True
    # the grid's elevation (what it reports, and what a safe cell needs) read from a cell's finite neighbours
    # (mapping.remap_valid); False: NaN beside any DEM hole, as the slope fit reads it
    grid_elev_finite: bool = True
    # the grid reports the DEM's gap fills too (dark_fill_m), as the pixel map does (HazardGrid.dem): without
    # them the fused 4-frame maps' DEM coverage was 2-3 points under the pixel maps'. The evidence and the
    # sites still read matched elevations only (HazardGrid.elevation)
    grid_dem_filled: bool = True
    keep_layers: bool = False  # keep the evidence features in PipelineResult.layers (tuning, bench/eval_flight.py)

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
        if self.dem not in ("sweep", "sgm"):
            raise FlightInputError(f"params: dem must be 'sweep' or 'sgm', got {self.dem!r}")
        if self.sgm_paths not in (0, 4, 8):
            raise FlightInputError(f"params: sgm_paths must be 0, 4 or 8, got {self.sgm_paths!r}")
        if not 0 < self.sgm_p1 < self.sgm_p2 <= 2000:
            raise FlightInputError(f"params: need 0 < sgm_p1 < sgm_p2 <= 2000, got {self.sgm_p1}, {self.sgm_p2}")
        if not 3 <= self.min_planes <= self.max_planes <= 256:
            raise FlightInputError(
                f"params: need 3 <= min_planes <= max_planes <= 256, got {self.min_planes!r}, {self.max_planes!r}"
            )
        if self.sgm_radius < 0 or self.sgm_mean_radius < 1:
            raise FlightInputError("params: sgm_radius must be >= 0 and sgm_mean_radius >= 1")
        if self.multi_rule not in RULES:
            raise FlightInputError(f"params: multi_rule must be one of {RULES}, got {self.multi_rule!r}")
        if not (math.isfinite(self.multi_cost_gain) and self.multi_cost_gain > 0):
            raise FlightInputError(f"params: multi_cost_gain must be a positive number, got {self.multi_cost_gain!r}")
        if self.multi_extent not in ("widest", "union"):
            raise FlightInputError(f"params: multi_extent must be 'widest' or 'union', got {self.multi_extent!r}")
        if not (0 <= self.psafe_min < 1 and self.sigma_k >= 0):
            raise FlightInputError("params: need 0 <= psafe_min < 1 and sigma_k >= 0")
        if self.psafe_model not in ("gaussian", "calibrated"):
            raise FlightInputError(f"params: psafe_model must be 'gaussian' or 'calibrated', got {self.psafe_model!r}")
        if self.psafe_call not in ("model", "params"):
            raise FlightInputError(f"params: psafe_call must be 'model' or 'params', got {self.psafe_call!r}")
        for name in ("fp_budget", "lower_view_fallback_budget"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and 0 <= v <= 0.2):
                raise FlightInputError(f"params: {name} must be in [0, 0.2], got {v!r}")
        if not (math.isfinite(self.grid_call_share) and 0 < self.grid_call_share < 1):
            raise FlightInputError(f"params: grid_call_share must be in (0, 1), got {self.grid_call_share!r}")
        if not (self.call_slope_max > 0):
            raise FlightInputError(f"params: call_slope_max must be positive, got {self.call_slope_max!r}")
        if not (math.isfinite(self.shading_sun_ref_deg) and 0 <= self.shading_sun_ref_deg < 90):
            raise FlightInputError(f"params: shading_sun_ref_deg must be in [0, 90), got {self.shading_sun_ref_deg!r}")
        if self.call_slope_feature not in CAP_SLOPES:
            raise FlightInputError(
                f"params: call_slope_feature must be one of {CAP_SLOPES}, got {self.call_slope_feature!r}"
            )
        if not (math.isfinite(self.call_slope_sigma_k) and self.call_slope_sigma_k >= 0):
            raise FlightInputError(f"params: call_slope_sigma_k must be >= 0, got {self.call_slope_sigma_k!r}")
        if not (math.isfinite(self.psafe_unsafe) and 0 <= self.psafe_unsafe <= 1):
            raise FlightInputError(f"params: psafe_unsafe must be in [0, 1], got {self.psafe_unsafe!r}")
        for name in (
            "sigma_temperature",
            "slope_sigma_gain",
            "rough_sigma_gain",
            "kappa_floor",
            "texture_min",
            "dark_fill_m",
            "dark_fill_slope",
            "wide_slope_factor",
            "site_margin_m",
            "site_reach_cells",
            "site_relief_max_m",
            "site_relief_window_m",
            "shading_gain_footprints",
            "shadow_dark_frac",
            "shadow_mode_ratio",
            "shadow_cue_frac",
            "mapping_reserve_s",
            "mapping_reserve_margin",
            "multi_truncate",
            "multi_weight_exp",
            "multi_sigma_gamma",
        ):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise FlightInputError(f"params: {name} must be a non-negative number, got {v!r}")


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


# fast_v1 (issue 6): SSD + 21x21 window, chosen on ground_sim seed-0 pairs and confirmed on seed-1 pairs
# (docs/benchmarks/pipeline.md); with i2 prefiltered and rocks masked, SSD's outlier sensitivity
# (the thesis's reason for SAD, sec 4.2) no longer dominates. Confidence rejection, photometric cues and
# gap filling (issue #6); a 1 px keep-out margin around slope/roughness hazards.
_FAST_V1 = Params(
    name="fast_v1",
    half_window=10,
    cost="ssd",
    reject_rel_uncertainty=1.5,
    shadow_dark_rel=0.1,
    shading_limit=0.15,
    fill_gap_px=8,
    hazard_margin_px=1.0,
)

PRESETS: dict[str, Params] = {
    # fast = flight v2 (issue 9): ground range from the data, cost volume + 8-path SGM, sigma per pixel,
    # uncertainty-aware three-state hazards, sites on known-safe ground. Tuned on ground_sim.seeds.TUNING_SEEDS
    # (docs/benchmarks/pipeline.md, bench/eval_flight.py).
    "fast": dataclasses.replace(
        _FAST_V1,
        name="fast",
        dem="sgm",
        range_search=True,
        mask_rocks=False,  # rocks are not masked out of the matching ...
        rocks_as_hazard=False,  # ... nor a hazard cue: the ablation shows no FP gain for 0.7 CDI points
        coarse_range_pct=2.0,
        reject_rel_uncertainty=1.5,  # coarse level and range search only
        fill_gap_px=0,
        hazard_margin_px=0.0,
        shadow_dark_frac=0.2,
        # boulder shadows a pixel or two wide were the unsafe pixel of most unsafe tuning landing sites once
        # the renders centred their penumbrae (RENDER_VERSION 2): tuning campaign 24 -> 0 unsafe landings
        # (docs/benchmarks/pipeline.md, stop 25); 0.35 -> 0.4 with the shading slope (stop 26), whose flatter
        # footprints let 1 px boulder shadows at 0.37-0.39x through: tuning campaign 3 -> 0 unsafe (0.38: 1)
        shadow_cue_frac=0.4,
        # a shadow majority is told by its dark/bright class ratio: 7-66 on the tuning library renders that
        # have one (polar-low-sun, a deep-crater floor), 1.2-1.5 where Otsu splits a lit image
        # (docs/benchmarks/pipeline.md, "The scene library pixel by pixel, and shadow under a polar sun")
        shadow_mode_ratio=4.0,
        shading_limit=0.1,
        # every pair the P(safe) model was fitted on had a 25 deg sun; a higher sun shades a wall less and
        # its rho is read as under 25 deg. Never mapped downward: under a low sun the map would weaken the
        # shading cue where Lambert's first order no longer holds (docs/benchmarks/pipeline.md, stop 24)
        shading_sun_ref_deg=25.0,
        # georef + grid + slope + shading_slope + hazard + sites at 512^2, one core: 0.065-0.116 s CPU on 128
        # tuning and held-out pairs (bench/fit_mapping_cost.py, stop 45), + 20 %: the reserve before the pose
        # refinement. From the range search on, the pair's own modelled cost + 25 % (mapping_cost_s)
        mapping_reserve_s=0.14,
        mapping_reserve_margin=1.25,
        sgm_p1=16,
        sgm_p2=128,
        uniqueness=0.0,  # ambiguity goes into sigma (sgm.plane_sigma) instead of rejecting the match
        kappa_floor=0.05,
        mask_shadow=True,
        texture_min=1.0,
        # the DEM carried up to 1 m into dark shadow from the nearest match (tuning seeds 0-9, nadir pairs
        # 50-500 m: pairs under 90 % coverage 51 -> 10 of 160, the worst altitude's median DEM error 0.42 ->
        # 0.48x the thesis's; 0.5 m: 16 pairs, 0.45x; 1.5 m: 8, 0.49x; docs/benchmarks/pipeline.md, stop 28)
        dark_fill_m=1.0,
        sigma_temperature=0.1,
        slope_sigma_gain=0.9,
        wide_slope_factor=3.0,
        rough_sigma_gain=0.15,
        sigma_k=2.0,
        max_planes=48,
        # 1 m of known-safe ground around the footprint. Tuning landing campaigns (seeds 0-9, 1008 landings,
        # bench/bench_site_guard.py --param site_margin_m; docs/benchmarks/pipeline.md, stop 30), safe / unsafe
        # with navigation errors: 1.5 m 511 / 0, 1 m 604 / 2, 0.75 m 627 / 2, 0.5 m 647 / 3; with perfect
        # navigation 496 / 0, 592 / 0, 636 / 4, 653 / 3. 1.5 m dated from before the relief guard below,
        # when 0.5 m put 2 of 6 tuning crater top sites on terraced wall steps at the edge of the map
        site_margin_m=1.0,
        # stop 38: the grid takes the pixels' call (grid_call_share 0.5; it had eroded the safe ground by half a
        # pixel), so a site's disk now holds every cell it reaches into. Tuning landing campaigns, safe / unsafe:
        # with navigation errors 599 / 4 (eroded grid) -> 603 / 4 (0 cells: 613 / 4); perfect navigation
        # 594 / 6 -> 602 / 6 (610 / 6). 0 cells put one held-out top site on a 1-pixel hazard at 2400 m
        site_reach_cells=0.5,
        # no site in a 30 m square whose DEM spans > 14 m: SGM flattens crater walls, and a flattened wall
        # reads as flat, certain ground. Tuning landing campaigns (seeds 0-9, 126 renders x 8 aim points,
        # docs/benchmarks/pipeline.md): unsafe top sites 12 -> 4 with perfect navigation (no safe one lost),
        # 8 -> 5 with navigation errors (2 of 272 safe ones lost); 12 m lost 4 safe ones for the same gain
        site_relief_max_m=14.0,
        # relative pose refinement before the sweep (issue #10; docs/benchmarks/pose.md)
        refine_pose=True,
        # calibrated P(safe) (boosted trees, psafe.TreeModel) and the FP-budget call (bench/fit_psafe.py --kind
        # trees on tuning seeds 0-9 of the default and thesis scenes; operating point by 5-fold CV, worst pair FP
        # first, then CDI: 0.3 % / 0.4x / 0.97 -> FP worst 0.63 %, CDI 44.3 %; the additive model's 0.2 % gave
        # 0.78 % and 36.2 %)
        psafe_model="calibrated",
        # stop 27: 0.3 -> 0.2 % with the caster and speck features (shadow.caster_distance,
        # shading.speck_contrast) and larger trees (45 x 31 leaves): tuning CV FP worst 1.58 -> 0.95 %, no pair
        # over 1 % (was 1 of 443), CDI 59.5 -> 59.8 % (docs/benchmarks/pipeline.md, stop 27). Stop 34: the trees
        # refitted on the DEM without the overlap edge's border samples; 0.2 % gave 1 of 443 pairs over 1 %
        # (1.03 %), 0.175 % none (0.96 %, CDI 60.0 %), by the same rule. Stop 41: the trees refitted on the DEM
        # that ships (stop 34's band rule had come after the fit); over five fold partitions 0.175 % keeps every
        # pair under 1 % (worst 0.98 %, CDI 60.3 %) and 0.2 % does not (1.09 %)
        fp_budget=0.00175,
        psafe_min=0.97,
        call_slope_max=0.4,
        # the footprint slope read from the shading as well (photoclinometry.py), a tree feature, and the cap
        # reads it; the trees fitted on the 123 tuning library renders too. Tuning CV (same budget, cap, floor):
        # CDI 55.5 -> 59.5 %, 1 of 443 pairs over 1 % FP (a library boulder field; fitted on the eval pairs
        # alone, 2 of the 123 library renders; docs/benchmarks/pipeline.md, stop 26). No sun: the cap reads a
        shading_slope=True,
        call_slope_feature="a_pc",
    ),
    # the issue-6 fast preset, kept for the ablation (bench/eval_flight.py --ablation)
    "fast_v1": _FAST_V1,
    "thesis": Params(
        name="thesis", half_window=8, plane_spacing="dz", dz_m=0.15, prefilter=False, coarse_to_fine=False
    ),
}
# flight v2 as merged for issue 9 (Gaussian P(safe), safe at P >= 0.9), kept for comparison
PRESETS["fast_gaussian"] = dataclasses.replace(
    PRESETS["fast"],
    name="fast_gaussian",
    psafe_model="gaussian",
    psafe_min=0.9,
    fp_budget=0.005,
    call_slope_max=math.inf,
    shading_sun_ref_deg=0.0,
)

# fast with the navigation poses as given: the A/B of the pose refinement (hazard-hil sensitivity --preset refine)
PRESETS["fast_unrefined"] = dataclasses.replace(PRESETS["fast"], name="fast_unrefined", refine_pose=False)


def dense_params(p: Params) -> DenseParams:
    """The dense-matching knobs of a preset (:class:`flight_sw.dense.DenseParams`)."""
    return DenseParams(
        radius=p.sgm_radius,
        mean_radius=p.sgm_mean_radius,
        p1=p.sgm_p1,
        p2=p.sgm_p2,
        p2_g0=p.sgm_p2_g0,
        p2_adapt=p.p2_gradient_adapt,
        paths=p.sgm_paths,
        uniqueness=p.uniqueness,
        speckle_px=p.speckle_px,
        temperature=p.sigma_temperature,
        kappa_floor=p.kappa_floor,
        uniq_scale=p.sigma_uniq_scale,
        end_margin=p.end_margin,
        min_interval_frac=p.min_interval_frac,
        fill_max_m=p.dark_fill_m,
        fill_slope=p.dark_fill_slope,
    )
