"""The hazard-detection pipeline (thesis Fig. 4.2) as one call: images + poses in, DEM + hazards out.

Two flows, chosen by ``Params.dem``:

* ``"sweep"`` (the ``thesis`` reproduction and ``fast_v1``): validate -> rocks, shadow, coverage
  (image-only hazards) -> coarse DEM (half-resolution WTA sweep) -> full DEM (WTA window sweep)
  -> georeferencing -> world grid -> slope, roughness -> hazard = max of the scaled layers -> sites.
* ``"sgm"`` (``fast``, flight v2, issue 9): rocks, dark shadow, wall cue -> ground range from the
  data (:mod:`flight_sw.rangefind`) -> coarse DEM -> dense DEM: cost volume
  (:mod:`flight_sw.costvolume`) + semi-global aggregation (:mod:`flight_sw.sgm`) with a per-pixel
  elevation uncertainty sigma (:mod:`flight_sw.dense`) -> georeferencing -> world grid -> weighted
  footprint planes and three-state evidence with P(safe) (:mod:`flight_sw.evidence`) -> sites on
  known-safe ground ranked by P(safe) (:func:`flight_sw.sites.select_safe_sites`).

Anytime: with a deadline every stage checks the clock; the DEM stages stop
``mapping_reserve_s x time_scale`` before it (``time_scale`` = the emulated processor's slowdown,
so the reserve is in unthrottled seconds; flight v2 scales it with the pixel count, as the stages
after the DEM cost per pixel), an optional stage starts only if its own cost fits before that
reserve, later stages are skipped once it has passed (listed in
``info["skipped"]``, as is a sweep cut short at the deadline); the result is built from the best
level reached (``image_only`` < ``coarse`` < ``full``) and flagged ``degraded``. Ground truth is never an input.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from protocol.messages import SITES_WITHHELD
from protocol.pairdir import (
    STATE_OUTSIDE,
    STATE_SAFE,
    STATE_UNKNOWN,
    STATE_UNSAFE,
    SUN_AZIMUTH_LIMIT_DEG,
    Camera,
    Pose,
    Sun,
)

from .anytime import (
    AFTER_SLOPE_S,
    CASTER_MAX_PX,
    FULL_OVER_COARSE_MIN,
    MAX_GRID_CELLS_PER_PIXEL,
    REF_PIXELS,
    REFINE_S,
    ROCKS_S,
    SHADING_SLOPE_S,
    SHADOW_BASE_S,
    WALL_CUE_S,
    Clock,
    full_dem_fits,
    grid_cells_estimate,
    mapping_cost_s,
)
from .confidence import elevation_uncertainty, reject_uncertain
from .costvolume import local_contrast
from .dense import dense_dem
from .evidence import (
    Evidence,
    below_model_scale,
    classify,
    classify_calibrated,
    footprint_mean,
    grid_evidence,
    hold_unsafe_pixels,
    steeper_plane_fit,
    widen_unsafe,
)
from .gapfill import fill_small_gaps
from .georef import backproject
from .homography import centre_gsd, gsd_scale
from .lowerview import average_where_both, lower_view_dem, read_into_reference
from .mapping import (
    HazardGrid,
    combine,
    from_pyramid,
    grid_extent,
    grid_maps,
    grid_xy,
    ground_sample_distance,
    image_direction,
    image_to_grid_coords,
    pull,
    remap_maps,
    remap_valid,
    remap_with,
    sample_grid,
    three_state,
)
from .multibaseline import multi_baseline_dem
from .noise import blank_frames, noise_sigma, noisy_frames
from .params import PRESETS, Params, dense_params, window_px
from .photoclinometry import incidence_cosine, measured_incidence, shading_gradient
from .pose_refine import (
    CHECK_MIN_SIDE,
    DISAGREES,
    KEPT,
    REFINED,
    REPEATED,
    SKIPPED,
    UNMATCHED,
    contradicted,
    refine_descent,
    repeat_reason,
)
from .psafe import WIDE_PX as PSAFE_WIDE_PX
from .psafe import Model, model_call, model_for_image, not_fitted_text
from .psafe import features as psafe_features
from .rangefind import (
    altimeter_dem_disagreement,
    altimeter_dem_gap,
    altimeter_disagreement,
    find_ground,
    prior_range,
)
from .rocks import rock_mask
from .sgm import kernel as sgm_kernel
from .shading import local_shadow_mask, relative_brightness, rho_at_sun, shading_mask, speck_contrast
from .shadow import caster_distance, dark_shadow, lit_level, shadow_mask
from .sites import Site, no_site_reason, select_safe_sites, select_sites
from .slope import footprint_cells, plane_fit, roughness
from .sweep import (
    SweepResult,
    coverage_mask,
    planes_uniform_disparity,
    planes_uniform_dz,
    scaled_camera,
    sweep_dem,
)
from .validate import FlightInputError, check_frames
from .warping import area_sigma

LEVELS = ("image_only", "coarse", "full")
# Params that change the DEM the P(safe) trees read: a model fitted with other values is refused (_check_model_dem)
MODEL_DEM_PARAMS = ("lower_view_dem",)


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
    # bool HxW: pixels whose elevation is a gap fill (carried from the nearest matches into dark shadow,
    # Params.dark_fill_m), not a match there; None: the back-end does not fill (v1, thesis)
    filled: np.ndarray | None = None
    layers: dict[str, np.ndarray] = field(default_factory=dict)  # evidence features, when Params.keep_layers

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


def _note_started(info: dict[str, Any], stage: str) -> None:
    """``info["plan"][<stage>_started] = 1`` when a DEM stage the plan weighed did start (a planned run only): a
    stage that was then left out was cut at its deadline, not refused by the plan."""
    if "plan" in info:
        info["plan"][f"{stage}_started"] = 1


def _altimeter(altimeter_m: float | Sequence[float] | None) -> float | None:
    """The slant range of i1's altimeter reading (a per-frame sequence's first entry: frame 0's), or None."""
    if altimeter_m is None:
        return None
    vals = [altimeter_m] if isinstance(altimeter_m, (int, float)) else list(altimeter_m)[:1]
    for v in vals:
        try:
            f = float(v)
        except (TypeError, ValueError):
            raise FlightInputError(f"altimeter_m must be a number (m) or None, got {altimeter_m!r}") from None
        if math.isnan(f):
            continue
        if not (math.isfinite(f) and f > 0):  # inf read as "no reading" here and refused by the refinement (stop 75)
            raise FlightInputError(f"altimeter_m must be a positive slant range, got {f}")
        return f
    return None


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
    altimeter_m: float | Sequence[float] | None = None,
    time_scale: float = 1.0,
    after_s: float = 0.0,
    sun_elevation_deg: float | None = None,
    sun_azimuth_deg: float | None = None,
    reserve_measured: float | None = None,
) -> PipelineResult:
    """Hazard detection from two descent images (i1 higher, i2 lower; poses world->camera).

    ``deadline_s`` is a budget in seconds from the call, ``deadline_at`` an absolute
    ``time.monotonic()`` value (the earlier wins); the result is the best
    level reached in time (see module doc). ``altimeter_m`` is i1's altimeter slant range
    (``Pair.altimeter_m``: a per-frame sequence is accepted; NaN = none); the v2 flow centres
    its ground search on it. ``time_scale`` is the emulated processor's slowdown factor
    (1 / CPU fraction): the stage reserves (``mapping_reserve_s``) are unthrottled seconds and
    are multiplied by it (or by the slowdown the first stages really saw, if larger: ``Clock.learn``).
    ``after_s`` is the caller's own work after the pipeline returns (encoding, fusion), in
    unthrottled seconds: it is reserved before the deadline at the same scale. ``sun_elevation_deg``
    (None or NaN = unknown) lets the shading cue be read as under the sun the P(safe) model was fitted
    under (``Params.shading_sun_ref_deg``); with ``sun_azimuth_deg`` too (DESIGN.md's convention) the
    footprint slope is also read from the shading (``Params.shading_slope``, :mod:`flight_sw.photoclinometry`). With
    ``Params.refine_pose`` the poses are first refined from the
    images (:mod:`flight_sw.pose_refine`); its telemetry is ``info["pose_refinement"]``.
    ``reserve_measured`` (wall s per reserved unthrottled s, :func:`measured_reserve_ratio` on the caller's
    previous pairs) plans the reserves from what they really cost instead of ``time_scale`` alone
    (``Clock.reserve_scale``). Raises :class:`FlightInputError` for bad arguments.
    """
    return run_pipeline_multi(
        [i1, i2],
        [pose1, pose2],
        camera,
        preset=preset,
        deadline_s=deadline_s,
        nominal_site_xy=nominal_site_xy,
        deadline_at=deadline_at,
        altimeter_m=altimeter_m,
        time_scale=time_scale,
        after_s=after_s,
        sun_elevation_deg=sun_elevation_deg,
        sun_azimuth_deg=sun_azimuth_deg,
        reserve_measured=reserve_measured,
    )


def run_pipeline_multi(
    images: Sequence[np.ndarray],
    poses: Sequence[Pose],
    camera: Camera,
    *,
    preset: str | Params = "fast",
    deadline_s: float | None = None,
    nominal_site_xy: tuple[float, float] = (0.0, 0.0),
    deadline_at: float | None = None,
    altimeter_m: float | Sequence[float] | None = None,
    time_scale: float = 1.0,
    after_s: float = 0.0,
    sun_elevation_deg: float | None = None,
    sun_azimuth_deg: float | None = None,
    reserve_measured: float | None = None,
    frame_numbers: Sequence[int] | None = None,
) -> PipelineResult:
    """Hazard detection from 2-16 descent frames ordered by time (``images[0]`` the highest: the reference).

    Maps are in frame 0's pixels. The ground range and the coarse DEM come from the widest
    pair (frames 0 and -1, as :func:`run_pipeline`); the dense DEM's cost volume combines every
    (frame 0, frame k) pair robustly (multi-baseline plane sweep, :func:`flight_sw.costvolume.multi_cost_slab`,
    ``Params.multi_*``) before the same SGM, sigma and evidence stages. Two frames give exactly
    :func:`run_pipeline`'s result. The v1 flow (``dem="sweep"``) uses frames 0 and -1 only
    (``info["frames_used"]``). With ``refine_pose``, a later frame the images contradict is left out first
    (``info["frames_dropped"]``, the input's numbers), and the widest pair is frame 0 and the last frame kept.
    ``frame_numbers``: what ``info`` and its messages call the frames (default 0 to n - 1), e.g. a directory's
    frames 0 and 3 given as a pair. Other arguments as :func:`run_pipeline`.
    """
    t_start = time.monotonic()
    timings: dict[str, dict[str, float]] = {}
    with _stage(timings, "validate"):
        p = _resolve(preset)
        images, poses = list(images), list(poses)
        check_frames(images, poses, camera)
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
        if not (isinstance(time_scale, (int, float)) and math.isfinite(time_scale) and time_scale > 0):
            raise FlightInputError(f"time_scale must be a positive number, got {time_scale!r}")
        alt_range = _altimeter(altimeter_m)
        alt_frames = _altimeter_frames(altimeter_m, len(images))
        numbers = _frame_numbers(frame_numbers, len(images))
        ends = [t for t in (None if deadline_s is None else t_start + float(deadline_s), deadline_at) if t is not None]
        if not (isinstance(after_s, (int, float)) and math.isfinite(after_s) and after_s >= 0):
            raise FlightInputError(f"after_s must be a non-negative number of seconds, got {after_s!r}")
        sun_e = _sun_elevation(sun_elevation_deg)
        sun_az = _sun_azimuth(sun_azimuth_deg)
        if reserve_measured is not None and not (
            isinstance(reserve_measured, (int, float)) and math.isfinite(reserve_measured) and reserve_measured > 0
        ):
            raise FlightInputError(f"reserve_measured must be a positive number, got {reserve_measured!r}")
        measured = None if reserve_measured is None else float(reserve_measured)
        clock = Clock(min(ends) if ends else None, float(time_scale), float(after_s), measured)
    # a frame far noisier than the others (a sensor fault, a damaged image) is mapped like any other: said
    # (flight_sw.noise; 2 ms a 512 px pair)
    noise = [noise_sigma(im) for im in images]
    noisy, blank = noisy_frames(noise), blank_frames(noise)
    pose_info: dict[str, Any] | None = None
    poses_in = tuple(poses)  # as reported: what the altimeters are checked against
    if p.refine_pose:
        # a pair's refinement cannot stop part-way: the widest pair's must fit before the reserve, the others follow
        # while time allows (refine_descent's stop_by)
        px_scale = images[0].size / REF_PIXELS
        # its features and tracks are fixed counts, its warps scale with the pixels: 0.022-0.026 s per pair at 256
        # px against 0.047-0.049 s at 512 (stop 59), about the square root of the pixel ratio. Scaled with the
        # pixels, a 16-frame 256 px descent planned 0.13 s, took 0.39 s and left a 0.3 s deadline image-only
        pair_s = REFINE_S * math.sqrt(px_scale)
        if clock.ok(p.mapping_reserve_s * px_scale + pair_s):  # the widest pair: the others as time allows
            # the middle frames take at most half the time left before the reserve: the DEM needs the rest (all
            # 15 of a 16-frame descent ran past a 0.3 s deadline and left it image-only)
            end = clock.before(p.mapping_reserve_s * px_scale)
            stop_by = None if end is None else time.monotonic() + 0.5 * (end - time.monotonic())
            with _stage(timings, "pose_refine"):
                poses, pose_info = refine_descent(images, poses, camera, altimeter_m=alt_frames, stop_by=stop_by)
            t = timings["pose_refine"]
            done = sum(1 for f in pose_info.get("frames", ()) if f.get("verdict") != SKIPPED)
            done += int(pose_info.get("chain_fits", 0))  # frames checked again against one above them
            clock.learn(pair_s * max(1, done), t["wall_s"], t["cpu_s"])
        else:
            pose_info = {
                "refined": False,
                "verdict": SKIPPED,
                "reason": "skipped: its cost does not fit before the deadline",
            }
    alt0 = alt_range  # frame 0's reading, for the DEM's check even when the range search does without it
    camera_side = min(camera.width, camera.height)
    dropped = _frames_to_leave_out(pose_info, len(images), camera_side)
    kept = [k for k in range(len(images)) if k not in dropped]  # the input's numbers of the frames swept
    alt_note = ""
    if alt_frames is not None and p.dem == "sgm":  # the v1 flow reads no altimeter: nothing to distrust
        # a frame left out does not outvote frame 0
        alt_note = altimeter_disagreement(
            [poses_in[k] for k in kept], [alt_frames[k] for k in kept], [numbers[k] for k in kept]
        )
        # a frame swept whose images scale the ground unlike frame 0's altimeter (pose_refine's ground gap): the
        # map rests on one of them, wrong. Not under CHECK_MIN_SIDE, where clean fits fail the checks too
        scale = []
        for f in (pose_info or {}).get("frames") or () if camera_side >= CHECK_MIN_SIDE else ():
            k, gap = int(f.get("frame", 0)), f.get("ground_gap_m")
            if f.get("scale_disagrees") and k in kept and gap is not None and f.get("ground_gap_from") != "frames":
                j = int(f.get("against") or 0)  # a frame checked against a frame above it (pose_refine._chain)
                scale.append(
                    f"frame {numbers[k]}'s images put the ground {float(gap):+.0f} m from where frame {numbers[j]}'s "
                    "altimeter reads it (an image from another altitude, or a wrong position or reading)"
                )
        alt_note = "; ".join([alt_note, *scale] if alt_note else scale)
    if alt_note:  # which of them is wrong is unknown: the ground's range is found from the images alone
        alt_range = None
    if dropped:
        images = [im for k, im in enumerate(images) if k not in dropped]
        poses = [ps for k, ps in enumerate(poses) if k not in dropped]
    i1, i2, pose1, pose2 = images[0], images[-1], poses[0], poses[-1]
    if p.dem == "sgm":
        extra = list(zip(images[1:-1], poses[1:-1]))
        sun = Sun(sun_az, sun_e).direction() if sun_e is not None and sun_az is not None else None
        res = _run_v2(i1, i2, pose1, pose2, camera, p, clock, nominal, alt_range, timings, extra, sun_e, sun)
    else:
        res = _run_v1(i1, i2, pose1, pose2, camera, p, clock, nominal, timings)
        if len(numbers) > 2:  # the input's numbers (with the frames left out, if any)
            res.info["frames_used"] = [kept[0], kept[-1]]
    if dropped:  # the input's frame numbers; info.multi_frame lists the swept ones in frames_swept's order
        res.info["frames_dropped"] = dropped
        res.info["frames_swept"] = kept
    if alt0 is not None and p.dem == "sgm" and np.isfinite(res.elevation).any():
        matched = res.elevation if res.filled is None else np.where(res.filled, np.nan, res.elevation)
        # along the axis navigation reports: the beam follows the camera, and a refinement that took an altitude
        # error in as attitude (up to 3 sd) moved the point and halved the gap
        gap, unchecked = altimeter_dem_gap(matched, camera, poses_in[0], alt0, numbers[0])
        res.info["altimeter_dem_gap_m"] = None if math.isnan(gap) else gap
        if unchecked:
            res.info["altimeter_dem_unchecked"] = unchecked
        alt_note = "; ".join(n for n in (alt_note, altimeter_dem_disagreement(gap, alt0, numbers[0])) if n)
    if alt_note:
        res.info["altimeter_disagreement"] = alt_note
        # which sensor is wrong is unknown, and a map two of them disagree on is no ground to land on: said, with
        # no site rather than a bad one (issue 9)
        _withhold_sites(res, alt_note)
    swept = kept if p.dem == "sgm" else [kept[0], kept[-1]]  # the v1 flow sweeps the widest pair only
    doubt = _pose_doubt(pose_info, swept, dropped, numbers, camera_side)
    if doubt and "sites_withheld" not in res.info:
        _withhold_sites(res, doubt)
    res.info["image_noise_dn"] = [round(v, 2) for v in noise]
    for key, ks in (("noisy_frames", noisy), ("blank_frames", blank)):
        if ks:  # the directory's frame numbers, each with its reading and the others'
            res.info[key] = [
                {
                    "frame": numbers[k],
                    "noise_dn": round(noise[k], 2),
                    "others_dn": [round(v, 2) for j, v in enumerate(noise) if j != k],
                }
                for k in ks
            ]
    if pose_info is not None:
        res.info["pose_refinement"] = pose_info
        if "pose_refine" not in timings:
            res.info.setdefault("skipped", []).insert(0, "pose_refine")
    _renumber(res.info, numbers)
    return res


def _frame_numbers(frame_numbers: Sequence[int] | None, n: int) -> list[int]:
    if frame_numbers is None:
        return list(range(n))
    out = list(frame_numbers)
    if not all(isinstance(k, (int, np.integer)) and not isinstance(k, bool) for k in out):
        raise FlightInputError(f"frame_numbers must be {n} whole numbers, got {frame_numbers!r}")
    out = [int(k) for k in out]
    if len(out) != n or len(set(out)) != n or any(k < 0 for k in out):
        raise FlightInputError(f"frame_numbers must be {n} distinct non-negative numbers, got {frame_numbers!r}")
    return out


def _renumber(info: dict[str, Any], numbers: list[int]) -> None:
    """The pipeline's frame numbers in ``info`` (its input's positions) become ``numbers``: `process
    --widest-pair` gives it a directory's frames 0 and n - 1, whose warnings named frame 3 "frame 1"."""
    if numbers == list(range(len(numbers))):
        return
    for key in ("frames_dropped", "frames_swept", "frames_used"):
        if key in info:
            info[key] = [numbers[k] for k in info[key]]
    pr = info.get("pose_refinement")
    for f in [pr, *(pr.get("frames") or ())] if isinstance(pr, dict) else ():
        for key in ("frame", "against", "repeat_of") if isinstance(f, dict) else ():  # against: pose_refine._chain
            if isinstance(f.get(key), int) and 0 <= f[key] < len(numbers):
                f[key] = numbers[f[key]]
        if isinstance(f, dict) and f.get("verdict") == REPEATED and isinstance(f.get("repeat_of"), int):
            f["reason"] = repeat_reason(f["repeat_of"])  # its words named the input's position


def _pose_doubt(
    pose_info: dict[str, Any] | None, swept: list[int], dropped: list[int], numbers: list[int], side: int
) -> str:
    """Why the poses leave a map no ground to land on ("" when they do not): it rests on a frame the images
    contradict (a pair cannot leave its frame out), or frames were left out and no swept frame confirms frame
    0's pose. ``swept`` and ``dropped`` are input positions, ``numbers`` what the reason calls them."""
    verdicts = _verdicts(pose_info)
    if any(k in swept for k in _contradicted_frames(pose_info, len(numbers), side)):
        # warned, and its sites had been offered all the same (a 3 deg pitch of a 300/150 pair's last frame: FP
        # 2.07 %, top site unsafe)
        why = []
        for verdict, text in (
            (DISAGREES, "whose navigation pose the images contradict"),
            (UNMATCHED, _NO_MATCH.format(ref=numbers[0])),
            (REPEATED, "whose image is an earlier frame's, pixel for pixel"),
        ):
            ks = [str(numbers[k]) for k in swept if verdicts.get(k) == verdict]
            if ks:
                why.append(f"frame{'s' if len(ks) > 1 else ''} {', '.join(ks)}, {text}")
        return f"it rests on {' and on '.join(why)} (info.pose_refinement)"
    if dropped and not [k for k in swept[1:] if verdicts.get(k) in (REFINED, KEPT)]:
        # what is left rests on frame 0 and frames the images could not confirm (not `degenerate`, which comes
        # before the checks that would see a fault), and the frames that could check frame 0 contradicted it:
        # frame 0 pitched 1 deg in a 1000/600/300/100 descent dropped the two frames that see its ground, the map
        # 51-362 m off; frame 0 and 1's images swapped gave 5 sites on a map 89 m low (stop 61's QA)
        left = ", ".join(str(numbers[k]) for k in dropped)
        were = f"frames {left} were" if len(dropped) > 1 else f"frame {left} was"
        ref, theirs = numbers[0], "their poses" if len(dropped) > 1 else "its pose"
        return (
            f"{were} left out (the images do not bear out {theirs} against frame {ref}'s), and no frame left "
            f"confirms frame {ref}'s pose: it may be frame {ref}'s that is wrong (info.pose_refinement)"
        )
    return ""


def _contradicted_frames(pose_info: dict[str, Any] | None, n: int, side: int) -> list[int]:
    """The later frames (1 to ``n - 1``) whose pose the images contradict (:func:`flight_sw.pose_refine.contradicted`:
    matched and inconsistent, not merely a small overlap). A multi-frame sweep leaves them out, where each adds its
    error to every plane's cost (a noise image as the last of four frames, refused by the refinement and swept all
    the same, left the DEM 7.9 m off; 0.34 m without it), unless that would leave frame 0 alone; a map that still
    rests on one offers no site."""
    return sorted(k for k, v in _verdicts(pose_info).items() if 0 < k < n and contradicted(v, side))


# an UNMATCHED frame: texture, and no consistent match where its pose says it overlaps frame 0 (a blank or another
# image, or a pose far off): the images do not bear its pose out, which is not "contradict" (a fit that asks for a
# correction beyond the navigation's accuracy); stop 61's QA found the two said alike
_NO_MATCH = "whose image does not match frame {ref}'s where its navigation pose says"


def _verdicts(pose_info: dict[str, Any] | None) -> dict[int, str]:
    """Each later frame's pose-refinement verdict (``info["frames"]``), by its position in the input."""
    return {int(f.get("frame", 0)): str(f.get("verdict", "")) for f in (pose_info or {}).get("frames") or ()}


def _frames_to_leave_out(pose_info: dict[str, Any] | None, n: int, side: int) -> list[int]:
    """:func:`_contradicted_frames`, unless they are all the later frames: frame 0 is never left alone (then the
    pair stands, with the warning its reason gives, and no site)."""
    bad = _contradicted_frames(pose_info, n, side)
    return bad if len(bad) < n - 1 else []


def _withhold_sites(res: PipelineResult, why: str) -> None:
    """No site on ``res``'s map, and why (``sites_withheld``, which the HIL flight process reads too)."""
    res.sites = []
    res.info["no_site_reason"] = res.info["sites_withheld"] = f"{SITES_WITHHELD}: {why}"


def _degrees_or_none(value: float | None, name: str) -> float | None:
    """``value`` as float degrees, or None when unknown (None or NaN); a non-number is refused."""
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise FlightInputError(f"{name} must be a number of degrees or None, got {value!r}")
    v = float(value)
    return None if math.isnan(v) else v


def _sun_elevation(sun_elevation_deg: float | None) -> float | None:
    """The sun's elevation in degrees, or None when unknown (None or NaN); anything else is refused."""
    e = _degrees_or_none(sun_elevation_deg, "sun_elevation_deg")
    if e is not None and not 0.0 < e <= 90.0:
        raise FlightInputError(f"sun_elevation_deg must be in (0, 90] (the sun above the horizon), got {e!r}")
    return e


def _sun_azimuth(sun_azimuth_deg: float | None) -> float | None:
    """The sun's azimuth in degrees, or None when unknown (None or NaN); anything else is refused."""
    a = _degrees_or_none(sun_azimuth_deg, "sun_azimuth_deg")
    if a is not None and not abs(a) <= SUN_AZIMUTH_LIMIT_DEG:
        lim = SUN_AZIMUTH_LIMIT_DEG
        raise FlightInputError(f"sun_azimuth_deg must be in [{-lim:g}, {lim:g}], got {a!r}")
    return a


def _altimeter_frames(altimeter_m: float | Sequence[float] | None, n: int) -> list[float] | None:
    """Per-frame altimeter ranges for pose_refine (NaN = none); a single number is frame 0's."""
    if altimeter_m is None:
        return None
    if isinstance(altimeter_m, (int, float)):
        return [float(altimeter_m)] + [math.nan] * (n - 1)
    seq = [math.nan if a is None else float(a) for a in altimeter_m]
    if any(not (math.isnan(a) or (math.isfinite(a) and a > 0)) for a in seq):  # as every path reads them
        raise FlightInputError(f"altimeter_m must be positive slant ranges (m), NaN where none, got {altimeter_m!r}")
    if len(seq) == 1:  # i1's reading only
        return seq + [math.nan] * (n - 1)
    if len(seq) != n:
        raise FlightInputError(f"altimeter_m: {len(seq)} readings for {n} frames (one per frame, NaN: none)")
    return seq


def _finish(timings: dict[str, dict[str, float]]) -> None:
    timings["total"] = {
        "wall_s": sum(t["wall_s"] for t in timings.values()),
        "cpu_s": sum(t["cpu_s"] for t in timings.values()),
    }


def _overlapping(covered: np.ndarray, z: float, other: str = "the other frame") -> np.ndarray:
    """``covered``, or a clear error when the frames share no ground (the world grid would be empty); ``other``
    names the frames compared with the reference ("the other frame" was ambiguous of four; QA 74)."""
    if not np.any(covered):
        raise FlightInputError(
            f"the frames do not overlap: no pixel of the reference frame sees ground at Z = {z:.1f} m that "
            f"{other} sees (check the poses)"
        )
    return covered


def _mapping_reserve(p: Params, camera: Camera, pose1: Pose, covered: np.ndarray, z: float, n_image: int) -> float:
    """``p.mapping_reserve_margin x mapping_cost_s`` of a pair whose overlap is ``covered`` at ``Z = z``."""
    cells = grid_cells_estimate(camera, pose1, covered, z, p.cell_m)
    return p.mapping_reserve_margin * mapping_cost_s(n_image, int(np.count_nonzero(covered)), cells)


def _ground_grid(
    camera: Camera,
    pose1: Pose,
    X: np.ndarray,
    Y: np.ndarray,
    z_fill: np.ndarray,
    z_ref: float,
    covered: np.ndarray,
    cell_m: float | None,
) -> tuple[float, tuple[float, float], tuple[int, int], np.ndarray, np.ndarray, np.ndarray]:
    """The world grid over the covered ground: ``(cell, origin, shape, gu, gv, g_cov)``, ``gu, gv``
    where each cell falls in i1 and ``g_cov`` the cells both images see.

    ``cell_m`` None: i1's median GSD over the covered area (over the whole image if that gives no cell).
    The grid never holds more than ``MAX_GRID_CELLS_PER_PIXEL`` cells per i1 pixel: a view that reaches
    toward the horizon covers kilometres of ground (a 128 px camera tilted 80 deg asked for 16 GiB of grid
    indices), so its cell grows until the grid fits (memory bounded before it is spent).
    """
    cell = cell_m or ground_sample_distance(X, Y, covered, 50.0)
    if not math.isfinite(cell) or cell <= 0:
        cell = ground_sample_distance(X, Y, np.ones(covered.shape, bool))
    cx, cy = np.where(covered, X, np.nan), np.where(covered, Y, np.nan)
    origin, shape = grid_extent(cx, cy, cell)
    cap = MAX_GRID_CELLS_PER_PIXEL * covered.size
    while shape[0] * shape[1] > cap:
        cell *= 1.01 * math.sqrt(shape[0] * shape[1] / cap)
        origin, shape = grid_extent(cx, cy, cell)
    GX, GY = grid_xy(shape, origin, cell)
    gu, gv = image_to_grid_coords(camera, pose1, z_fill, GX, GY, z_ref)
    g_cov = pull(covered.astype(np.float32), gu, gv) > 0.999
    return cell, origin, shape, gu, gv, g_cov


def _result(
    p: Params,
    level: str,
    timings: dict[str, dict[str, float]],
    info: dict[str, Any],
    grid: HazardGrid,
    sites: list[Site],
    elevation: np.ndarray,
    hazard: np.ndarray,
    slope_img: np.ndarray,
    rough_img: np.ndarray,
    rocks: np.ndarray,
    shadow: np.ndarray,
    covered: np.ndarray,
    world_xy: np.ndarray,
    **three_state: Any,
) -> PipelineResult:
    """The back-ends' common ending: close the timings and pack what they made into a PipelineResult.

    ``three_state``: v2's ``state``, ``psafe``, ``sigma`` and ``layers``; without them (v1) the
    result derives its state from the hazard.
    """
    _finish(timings)
    n_cov = int(covered.sum())
    valid = float(np.isfinite(elevation[covered]).sum() / n_cov) if n_cov else 0.0
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
        level != "full" or bool(info["skipped"]),
        level,
        valid,
        dataclasses.asdict(p),
        info,
        **three_state,
    )


def _run_v1(
    i1: np.ndarray,
    i2: np.ndarray,
    pose1: Pose,
    pose2: Pose,
    camera: Camera,
    p: Params,
    clock: Clock,
    nominal: tuple[float, float],
    timings: dict[str, dict[str, float]],
) -> PipelineResult:
    """The thesis / issue-6 flow: window-correlation WTA sweeps, hazard = max of scaled layers."""
    with _stage(timings, "prepare"):
        sweep_deadline = clock.before(p.mapping_reserve_s)
        a1 = np.ascontiguousarray(i1, dtype=np.float32)
        a2 = np.ascontiguousarray(i2, dtype=np.float32)
        alt = float(pose1.position[2])
        margin = max(p.relief_margin_min_m, p.relief_margin_frac * alt)
        z_lo, z_hi = -margin, min(margin, float(pose2.position[2]) * 0.5)
        scale = gsd_scale(camera, pose1, pose2)
        sigma = area_sigma(scale) if p.prefilter else 0.0
    info: dict[str, Any] = {"sweep_range_m": [z_lo, z_hi], "gsd_ratio": scale, "skipped": []}

    with _stage(timings, "rocks"):
        rocks = rock_mask(i1, p.rock_k, p.harris_alpha, p.rock_dilate_px)
    with _stage(timings, "shadow"):
        shadow = shadow_mask(i1)
        shading = np.zeros(i1.shape, bool)
        if (p.shadow_dark_rel > 0 or p.shading_limit > 0) and clock.ok(p.mapping_reserve_s):
            fp_px = p.footprint_m / centre_gsd(camera, pose1)
            rho = relative_brightness(
                i1, max(p.shading_sigma_px, p.shading_sigma_footprints * fp_px), max(1.0, fp_px / 3.0)
            )
            if p.shadow_dark_rel > 0:
                shadow = local_shadow_mask(i1, shadow, rho, p.shadow_dark_rel)
            if p.shading_limit > 0:
                shading = shading_mask(rho, p.shading_limit)
        elif p.shadow_dark_rel > 0 or p.shading_limit > 0:
            info["skipped"].append("photometric_cues")
    with _stage(timings, "coverage"):
        covered = _overlapping(coverage_mask(camera, pose1, pose2, 0.0), 0.0)
        rows, cols = np.flatnonzero(covered.any(axis=1)), np.flatnonzero(covered.any(axis=0))
        overlap = min(rows[-1] - rows[0] + 1, cols[-1] - cols[0] + 1) if rows.size else 0
        W_full = window_px(p.half_window, overlap, p.cap_window_to_overlap)
        W_coarse = window_px(p.coarse_half_window, overlap // 2, p.cap_window_to_overlap)
        info["half_window_px"], info["coarse_half_window_px"] = W_full, W_coarse
    level = "image_only"
    elevation = np.full(i1.shape, np.nan, np.float32)
    res_c: SweepResult | None = None
    n_coarse = 0

    with _stage(timings, "coarse_dem"):
        if clock.decide(info, "coarse_dem", p.mapping_reserve_s):
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
            elif not res_c.complete:  # started, cut at the deadline: left out as much as a stage never started
                info["skipped"].append("coarse_dem")
        else:
            info["skipped"].append("coarse_dem")

    with _stage(timings, "full_dem"):
        # tiny images can leave the half-resolution DEM empty: then sweep the full range
        if res_c is not None and res_c.complete and clock.decide(info, "full_dem", p.mapping_reserve_s):
            f_lo, f_hi = z_lo, z_hi
            if p.coarse_to_fine and n_coarse >= 50:
                pad = 2.0 * float(np.max(np.diff(res_c.planes)))
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
            else:  # cut at the deadline
                info["skipped"].append("full_dem")
        else:  # no time left, or no coarse DEM to narrow it from
            info["skipped"].append("full_dem")

    with _stage(timings, "gap_fill"):
        # hazard mapping uses the gap-filled DEM; the returned elevation stays measured-only
        have_dem = level != "image_only"
        elev_map = elevation
        if have_dem and p.fill_gap_px > 0 and clock.ok():
            elev_map = fill_small_gaps(elevation, p.fill_gap_px, p.fill_min_frac)
        info["filled_fraction"] = float(
            (np.isfinite(elev_map) & ~np.isfinite(elevation) & covered).sum() / max(1, int(covered.sum()))
        )

    with _stage(timings, "georef"):
        z_ref = float(np.nanmedian(elevation)) if have_dem and np.isfinite(elevation).any() else 0.0
        z_fill = np.where(np.isfinite(elev_map), elev_map, np.float32(z_ref))
        X, Y = backproject(camera, pose1, z_fill)
        world_xy = np.stack([X, Y], axis=-1).astype(np.float32)

    with _stage(timings, "grid"):
        cell, origin, shape, gu, gv, g_cov = _ground_grid(camera, pose1, X, Y, z_fill, z_ref, covered, p.cell_m)
        g_elev = pull(elev_map, gu, gv) if have_dem else np.full(shape, np.nan, np.float32)
        g_rock = pull(rocks.astype(np.float32), gu, gv) > 0
        g_shadow = pull((shadow | shading).astype(np.float32), gu, gv) > 0.5

    with _stage(timings, "slope"):
        g_slope: np.ndarray | None = None
        g_rough: np.ndarray | None = None
        if have_dem and not clock.ok():
            have_dem = False  # past the deadline: map the image cues only
            info["skipped"].append("slope")
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
        # a cell with no elevation is not known safe: at the image-only level the cues alone left it safe, and the
        # site search offered sites with no elevation on them (QA of stop 66)
        g_haz = np.where(g_cov & ~np.isfinite(g_elev), np.float32(1.0), g_haz).astype(np.float32)
        grid = HazardGrid(g_haz, np.where(g_cov, g_elev, np.nan).astype(np.float32), origin, float(cell))

    with _stage(timings, "sites"):
        if clock.ok():
            sites = select_sites(grid, p.footprint_m, nominal, p.n_sites)
            if not sites and p.n_sites > 0:  # say why, as the v2 back-end does
                info["no_site_reason"] = no_site_reason(grid, p.footprint_m)
        else:
            sites = []
            info["skipped"].append("sites")
            info["no_site_reason"] = "deadline reached before site selection"

    # the states follow the DEM the hazards were mapped on: a small gap filled for the mapping is called as the map
    # calls it (state.npy said unknown where hazard.npy said safe, and `score` refused the pair)
    state, psafe = three_state(hazard, elev_map)
    # DESIGN.md: an unknown pixel is written as 1.0 (not called safe); the image-only level wrote 0 there, which
    # `score` refused as a state/hazard mismatch (QA of stop 66)
    hazard = np.where(state == STATE_UNKNOWN, np.float32(1.0), hazard).astype(np.float32)
    maps = (elevation, hazard, slope_img, rough_img, rocks, shadow, covered, world_xy)
    return _result(p, level, timings, info, grid, sites, *maps, state=state, psafe=psafe)


def _crop_box(mask: np.ndarray, pad: int) -> tuple[slice, slice]:
    """Slices of the bounding box of ``mask`` grown by ``pad`` pixels (the whole array if it is empty)."""
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    if rows.size == 0:
        return slice(0, mask.shape[0]), slice(0, mask.shape[1])
    h, w = mask.shape
    return (
        slice(max(0, int(rows[0]) - pad), min(h, int(rows[-1]) + pad + 1)),
        slice(max(0, int(cols[0]) - pad), min(w, int(cols[-1]) + pad + 1)),
    )


def _uncrop(a: np.ndarray, cs: tuple[slice, slice], shape: tuple[int, ...], fill: float = np.nan) -> np.ndarray:
    out = np.full(shape, fill, a.dtype)
    out[cs] = a
    return out


def _bounded_planes(
    camera: Camera, pose1: Pose, pose2: Pose, z_lo: float, z_hi: float, step_px: float, n_min: int, n_max: int
) -> np.ndarray:
    """Planes uniform in disparity (``step_px``), the step adjusted so that ``n_min <= D <= n_max``:
    a bounded cost volume over a wide range, enough planes for the sub-plane fit over a narrow one."""
    planes = planes_uniform_disparity(camera, pose1, pose2, z_lo, z_hi, step_px)
    for _ in range(12):
        if planes.size > n_max:
            step_px *= 1.25 * planes.size / n_max
        elif planes.size < n_min:
            step_px *= 0.9 * planes.size / n_min
        else:
            break
        planes = planes_uniform_disparity(camera, pose1, pose2, z_lo, z_hi, step_px)
    return planes


def _check_model_dem(p: Params, shape: tuple[int, ...] = (512, 512)) -> None:
    """The calibrated P(safe) holds only for the DEM its trees were fitted on: a model records the pipeline
    settings that change that DEM (``info["pipeline"]``, from ``bench/fit_psafe.py --set-param``; absent: the
    defaults), and a run with other settings is refused rather than mapped with a miscalibrated P(safe).
    ``shape``: the images', which pick the shipped model (:func:`flight_sw.psafe.model_for_image`).
    With ``lower_view_dem`` the fallback model (:func:`_without_lower_view`) is checked too."""
    runs = [p] + ([_without_lower_view(p)] if p.lower_view_dem else [])
    for q in runs:
        got = model_for_image(q.psafe_model_path or None, shape)
        if got is None:  # not fitted on this size: the Gaussian rule stands in, and no DEM setting matters
            continue
        fitted = got[0].info.get("pipeline", {})
        for name in MODEL_DEM_PARAMS:
            want = fitted.get(name, getattr(PRESETS["fast"], name))
            if getattr(q, name) != want:
                which = "psafe_model_path" if q is p else "lower_view_fallback_model"
                raise FlightInputError(
                    f"params: {name}={getattr(q, name)!r}, but the P(safe) model ({which}) was fitted with "
                    f"{name}={want!r}; fit one on this DEM (bench/fit_psafe.py --set-param {name}=... --write M)"
                )


def _model_and_call(p: Params, shape: tuple[int, ...], info: dict[str, Any]) -> tuple[tuple[Model, str] | None, Params]:
    """The P(safe) model that calls images of ``shape`` under ``p`` (:func:`flight_sw.psafe.model_for_image`; None:
    none fits) and ``p`` with that model's own operating point where it records one and ``p.psafe_call`` is
    "model". ``info`` gets the model's prior (``psafe_safe_share``, which fusion takes out once) and the point
    used (``psafe_call``), or, when none fits, why the Gaussian rule calls it (``psafe_fallback``)."""
    fitted = model_for_image(p.psafe_model_path or None, shape)
    info.pop("psafe_call", None)
    if fitted is None:
        # outside the image sizes the models were fitted on (the 512 px trees on a 128 px camera: FP 1.6-5 % vs
        # 0-3 %), the calibration does not hold: the caller falls back to the Gaussian rule, at the preset's floor
        info.pop("psafe_safe_share", None)
        info["psafe_fallback"] = not_fitted_text(shape)
        return None, p
    info["psafe_safe_share"] = float(fitted[0].info.get("safe_share", 0.5))
    own = model_call(fitted[0]) if p.psafe_call == "model" else {}
    if own:  # the operating point the CV chose for this model (a 256 px camera's): said, and used
        info["psafe_call"] = own
        p = dataclasses.replace(
            p,
            fp_budget=own.get("fp_budget", p.fp_budget),
            psafe_min=own.get("psafe_min", p.psafe_min),
            call_slope_max=own.get("call_slope_max", p.call_slope_max),
        )
    return fitted, p


def _without_lower_view(p: Params) -> Params:
    """``p`` as a pair without the lower view's DEM is called: the fallback P(safe) model and FP budget."""
    return dataclasses.replace(
        p, lower_view_dem=False, psafe_model_path=p.lower_view_fallback_model, fp_budget=p.lower_view_fallback_budget
    )


def _matching_mask(img: np.ndarray, p: Params) -> np.ndarray:
    """The pixels of a reference image with nothing to match, as the first DEM's ``ignore``: dark shadow
    (below ``shadow_dark_frac`` of the image's lit level) and blank support (``texture_min``)."""
    out = np.zeros(img.shape, bool)
    if p.mask_shadow and p.shadow_dark_frac > 0:
        out |= img < np.float32(p.shadow_dark_frac * lit_level(img, p.shadow_mode_ratio))
    if p.texture_min > 0:
        out |= local_contrast(img, p.sgm_radius + p.sgm_mean_radius) < p.texture_min
    return out


def _run_v2(
    i1: np.ndarray,
    i2: np.ndarray,
    pose1: Pose,
    pose2: Pose,
    camera: Camera,
    p: Params,
    clock: Clock,
    nominal: tuple[float, float],
    alt_range: float | None,
    timings: dict[str, dict[str, float]],
    extra: Sequence[tuple[np.ndarray, Pose]] = (),
    sun_e: float | None = None,
    sun: np.ndarray | None = None,
) -> PipelineResult:
    """Flight v2 (issue 9): ground range from the data, dense SGM DEM with sigma, three-state evidence.

    ``extra``: the frames between i1 and i2 (issue 10); they join the dense DEM's cost volume.
    ``sun_e``: the sun's elevation (deg), None if unknown; ``sun``: the unit vector toward it, None if
    its azimuth is unknown too.
    """
    px_scale = i1.size / REF_PIXELS  # what follows the DEM costs per pixel: so does its reserve
    reserve = p.mapping_reserve_s * px_scale
    if p.mapping_reserve_margin > 0:  # this pair's own mapping cost; the datum's overlap until the ground is found
        reserve = _mapping_reserve(p, camera, pose1, coverage_mask(camera, pose1, pose2, 0.0), 0.0, i1.size)
    with _stage(timings, "prepare"):
        a1 = np.ascontiguousarray(i1, dtype=np.float32)
        a2 = np.ascontiguousarray(i2, dtype=np.float32)
        scale = gsd_scale(camera, pose1, pose2)
        sigma_pf = area_sigma(scale) if p.prefilter else 0.0
    info: dict[str, Any] = {"gsd_ratio": scale, "skipped": [], "sgm_kernel": "c" if sgm_kernel() else "numpy"}

    with _stage(timings, "rocks"):
        rocks = np.zeros(i1.shape, bool)
        if (p.rocks_as_hazard or p.mask_rocks) and clock.ok(reserve + ROCKS_S * px_scale):
            rocks = rock_mask(i1, p.rock_k, p.harris_alpha, p.rock_dilate_px)
        elif p.rocks_as_hazard or p.mask_rocks:
            info["skipped"].append("rocks")
    with _stage(timings, "shadow"):
        if p.shadow_dark_frac > 0:
            lit = lit_level(a1, p.shadow_mode_ratio)  # the median unless shadow is the majority
            info["shadow_lit_level"] = lit
            dark, shadow = dark_shadow(a1, lit, p.shadow_dark_frac, p.shadow_cue_frac)
        else:
            dark = shadow = shadow_mask(i1)
        wall = np.zeros(i1.shape, bool)
        fp_px = p.footprint_m / centre_gsd(camera, pose1)
        info["footprint_px"] = fp_px
        calibrated = p.psafe_model == "calibrated"
        p_asked = p  # before a model's own operating point: what a lower view's fallback starts from
        fitted = None
        if calibrated:
            _check_model_dem(p, i1.shape)
            fitted, p = _model_and_call(p, i1.shape, info)
            calibrated = fitted is not None
        rho = np.full(i1.shape, np.nan, np.float32)  # calibrated model: NaN = no shading evidence
        need_rho = p.shading_limit > 0 or calibrated or p.keep_layers
        rho_sigma = max(p.shading_sigma_px, p.shading_sigma_footprints * fp_px)
        if need_rho and clock.ok(reserve + WALL_CUE_S * px_scale):
            rho = relative_brightness(i1, rho_sigma, max(1.0, fp_px / 3.0), wide=True)
            sun_ref = p.shading_sun_ref_deg
            read_as = sun_e
            if sun_ref > 0 and sun_e is not None and sun_e > sun_ref:
                rho, read_as = rho_at_sun(rho, sun_e, sun_ref), sun_ref
            info["shading_sun"] = {"elevation_deg": sun_e, "read_as_deg": read_as}
            if p.shading_limit > 0 and not calibrated:  # the calibrated model weighs rho itself
                wall = shading_mask(rho, p.shading_limit)
        elif need_rho:
            info["skipped"].append("wall_cue")
    if "wall_cue" not in info["skipped"]:
        # the stage's unthrottled cost must be the one it has: a reference below it reads as a slowdown (a fixed
        # 14 ms read a 200/100 pair's 29 ms as 2x and left rad750 image-only), one above it hides a real one
        ref = (SHADOW_BASE_S + (WALL_CUE_S if need_rho else 0.0)) * px_scale
        clock.learn(ref, timings["shadow"]["wall_s"], timings["shadow"]["cpu_s"])

    with _stage(timings, "range"):
        if p.range_search:
            z_lo, z_hi, source = prior_range(
                pose1, pose2, alt_range, below_frac=p.range_below_frac, above_frac=p.range_above_frac
            )
            gr = None
            if clock.ok(reserve):
                gr = find_ground(
                    a1, a2, camera, pose1, pose2, z_lo, z_hi, source=source, deadline=clock.before(reserve)
                )
                z_lo, z_hi = gr.z_lo, gr.z_hi
                info["range_search"] = {
                    "prior_m": list(gr.prior),
                    "source": gr.source,
                    "found": gr.found,
                    "planes": gr.planes,
                    "median_z_m": gr.median_z,
                }
            else:
                info["skipped"].append("range")
            if gr is not None and gr.found:
                z_mid = gr.median_z
            else:  # nothing found: the datum if the prior holds it
                z_mid = 0.0 if z_lo < 0.0 < z_hi else 0.5 * (z_lo + z_hi)
        else:
            margin = max(p.relief_margin_min_m, p.relief_margin_frac * float(pose1.position[2]))
            z_lo, z_hi = -margin, min(margin, float(pose2.position[2]) * 0.5)
            z_mid = 0.0
        info["sweep_range_m"] = [z_lo, z_hi]

    with _stage(timings, "coverage"):
        # the overlap on the ground that was found (a crater floor 50 m down overlaps elsewhere than Z = 0)
        covered = coverage_mask(camera, pose1, pose2, z_mid)
        if extra and p.multi_extent == "union":
            for _, pose_k in extra:
                covered |= coverage_mask(camera, pose1, pose_k, z_mid)
        if not extra:
            other = "the other frame"
        elif p.multi_extent == "union":
            other = "the last frame used, nor any frame between,"
        else:
            other = "the last frame used"
        covered = _overlapping(covered, z_mid, other)
        rows, cols = np.flatnonzero(covered.any(axis=1)), np.flatnonzero(covered.any(axis=0))
        overlap = min(rows[-1] - rows[0] + 1, cols[-1] - cols[0] + 1) if rows.size else 0
        W_coarse = window_px(p.coarse_half_window, overlap // 2, p.cap_window_to_overlap)
        info["coarse_half_window_px"] = W_coarse
        info["coverage_z_m"] = z_mid
        if p.mapping_reserve_margin > 0:
            reserve = _mapping_reserve(p, camera, pose1, covered, z_mid, i1.size)
        info["mapping_reserve_s"] = reserve

    level = "image_only"
    elevation = np.full(i1.shape, np.nan, np.float32)
    sigma = np.full(i1.shape, np.nan, np.float32)
    f_lo, f_hi = z_lo, z_hi
    with _stage(timings, "coarse_dem"):
        if clock.decide(info, "coarse_dem", reserve):
            _note_started(info, "coarse_dem")
            cam_c = scaled_camera(camera, 1)
            planes_c = planes_uniform_disparity(cam_c, pose1, pose2, z_lo, z_hi, p.coarse_step_px)
            res_c = sweep_dem(
                cv2.pyrDown(a1),
                cv2.pyrDown(a2),
                cam_c,
                pose1,
                pose2,
                planes_c,
                half_window=W_coarse,
                cost=p.cost,
                prefilter_sigma=sigma_pf,
                deadline=clock.before(reserve),
                check_every=p.check_every,
            )
            info["coarse_planes"] = int(planes_c.size)
            if res_c.complete and res_c.curvature is not None:
                u_c = elevation_uncertainty(res_c.elevation, res_c.curvature, res_c.planes)
                rel, sharp = p.reject_rel_uncertainty, p.sharp_curvature
                ez = reject_uncertain(res_c.elevation, u_c, rel, res_c.curvature, sharp)
                n_c = int(np.isfinite(ez).sum())
                if n_c > 0:
                    size = (camera.width, camera.height)
                    elevation = from_pyramid(ez, size)
                    u_full = np.where(np.isfinite(ez), u_c, np.nan).astype(np.float32)
                    sigma = from_pyramid(u_full, size)
                    del u_full
                    elevation[~np.isfinite(sigma)] = np.nan
                    level = "coarse"
                if n_c >= 50:  # coarse-to-fine: the full-resolution range
                    pad = 2.0 * float(np.max(np.diff(planes_c)))
                    lo, hi = np.nanpercentile(ez, [p.coarse_range_pct, 100.0 - p.coarse_range_pct])
                    f_lo, f_hi = max(z_lo, float(lo) - pad), min(z_hi, float(hi) + pad)
            elif not res_c.complete:  # started, cut at the deadline: left out as much as a stage never started
                info["skipped"].append("coarse_dem")
        else:
            info["skipped"].append("coarse_dem")

    # the DEM's filled pixels and their values: reported, but the hazard stage reads the matches only
    dem_fill: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
    with _stage(timings, "full_dem"):
        # no match where there is nothing to match: dark shadow (and rocks, if masked)
        ignore = (dark if p.mask_shadow else np.zeros(i1.shape, bool)) | (rocks if p.mask_rocks else False)
        if p.texture_min > 0:  # blank support: nothing to match (its cost curve is flat, whatever SGM says)
            ignore |= local_contrast(a1, p.sgm_radius + p.sgm_mean_radius) < p.texture_min
        go = clock.decide(info, "full_dem", reserve) and f_hi > f_lo
        stop_by = clock.before(reserve)
        if go and stop_by is not None and level == "coarse":
            coarse_wall = timings["coarse_dem"]["wall_s"]
            info["plan"]["full_dem_min_s"] = FULL_OVER_COARSE_MIN * coarse_wall
            go = full_dem_fits(stop_by - time.monotonic(), coarse_wall)
        if go:
            _note_started(info, "full_dem")
            planes = _bounded_planes(camera, pose1, pose2, f_lo, f_hi, p.disparity_step_px, p.min_planes, p.max_planes)
            info["full_planes"] = int(planes.size)
            info["full_range_m"] = [f_lo, f_hi]
            prior = elevation if level == "coarse" else None
            if extra:
                dem = multi_baseline_dem(
                    a1, a2, pose1, pose2, extra, camera, planes, p, ignore, clock, prior, info, reserve
                )
            else:
                dem = dense_dem(
                    a1,
                    a2,
                    camera,
                    pose1,
                    pose2,
                    planes,
                    dense_params(p),
                    prefilter_sigma=sigma_pf,
                    ignore=ignore,
                    deadline=clock.before(reserve),
                    prior=prior,
                    gsd_m=centre_gsd(camera, pose1),
                )
            info["dense"] = dem.info
            if dem.complete:
                elevation, sigma, level = dem.elevation, dem.sigma, "full"
                if dem.filled is not None:  # set aside, not copied: two images less through the hazard stage
                    dem_fill = (dem.filled, elevation[dem.filled], sigma[dem.filled])
                    elevation[dem.filled] = np.nan
                    sigma[dem.filled] = np.nan
            else:  # cut at the deadline
                info["skipped"].append("full_dem")
            del dem, prior
        else:
            info["skipped"].append("full_dem")
    if p.lower_view_dem and level == "full":
        # the second sweep covers all of i2: about the first's wall time x (i2's pixels / the first's swept box).
        # Started only if that fits before the mapping reserve, so a tight deadline does not pay for a sweep that
        # would be cut off (on snapdragon801 it was, on 7 of 8 pairs, after 19-69 ms of CPU each)
        roi = (info.get("dense") or {}).get("roi") or [0, 0, i1.shape[1], i1.shape[0]]
        expect = timings["full_dem"]["wall_s"] * a2.size / max(1, int(roi[2]) * int(roi[3]))
        stop_by = clock.before(reserve)
        with _stage(timings, "lower_dem"):
            if stop_by is None or time.monotonic() + expect < stop_by:
                # i2 is the lowest frame (extra frames lie between): its planes uniform in i1's disparity
                planes_2 = _bounded_planes(
                    camera, pose2, pose1, f_lo, f_hi, p.disparity_step_px, p.min_planes, p.max_planes
                )
                ignore2 = _matching_mask(a2, p)
                z2, info["lower_view"] = lower_view_dem(
                    a1,
                    a2,
                    camera,
                    pose1,
                    pose2,
                    planes_2,
                    dense_params(p),
                    area_sigma_px=sigma_pf,
                    ignore2=ignore2,
                    deadline=clock.before(reserve),
                )
                if z2 is not None:
                    z_mid_dem = float(np.nanmedian(elevation)) if np.isfinite(elevation).any() else z_mid
                    z_start = np.where(np.isfinite(elevation), elevation, np.float32(z_mid_dem))
                    z2_1 = read_into_reference(z2, camera, pose1, pose2, z_start)
                    elevation, both = average_where_both(elevation, z2_1)
                    info["lower_view"]["averaged"] = float(both.mean())
                del z2, ignore2
            else:
                info["skipped"].append("lower_dem")
    if p.lower_view_dem and "averaged" not in info.get("lower_view", {}):
        # no lower view in this DEM: the P(safe) trees fitted on the first DEM alone call it, with their own
        # prior and operating point (picked again: the model resolved above was the lower view's)
        p = _without_lower_view(p_asked)
        if fitted is not None:
            fitted, p = _model_and_call(p, i1.shape, info)
            calibrated = fitted is not None
            if not calibrated and p.shading_limit > 0 and "wall_cue" not in info["skipped"]:
                # now called by the Gaussian rule, which needs the wall cue the calibrated path left out (review
                # of stop 63: ~500 px a pair called safe that `fast` calls unsafe)
                wall = shading_mask(rho, p.shading_limit)
        info["lower_view_fallback"] = f"no lower view in the {level} DEM: P(safe) model and budget of the first DEM"
    del a2  # nothing after the DEM reads the second image

    have_dem = level != "image_only"
    with _stage(timings, "georef"):
        z_ref = float(np.nanmedian(elevation)) if have_dem and np.isfinite(elevation).any() else z_mid
        z_fill = np.where(np.isfinite(elevation), elevation, np.float32(z_ref))
        X, Y = backproject(camera, pose1, z_fill)
        world_xy = np.stack([X, Y], axis=-1).astype(np.float32)

    with _stage(timings, "grid"):
        cell, origin, shape, gu, gv, g_cov = _ground_grid(camera, pose1, X, Y, z_fill, z_ref, covered, p.cell_m)
        g_maps = remap_maps(gu, gv)  # the cells' i1 pixels and the pixels' cells, each read many times
        px_maps = grid_maps(origin, cell, X, Y)
        g_elev = remap_with(elevation, g_maps) if have_dem else np.full(shape, np.nan, np.float32)
        g_seen = remap_valid(elevation, g_maps) if have_dem and p.grid_elev_finite else g_elev
        g_dem = None
        if have_dem and p.grid_dem_filled and dem_fill is not None:
            z_rep = elevation.copy()  # one image, for the moment of this read
            z_rep[dem_fill[0]] = dem_fill[1]
            g_dem = remap_valid(z_rep, g_maps) if p.grid_elev_finite else remap_with(z_rep, g_maps)
            g_dem = np.where(np.isfinite(g_seen), g_seen, g_dem)  # a match beats a fill beside it
            del z_rep
        g_sig = remap_with(sigma, g_maps) if have_dem else np.full(shape, np.nan, np.float32)
        cues = shadow | wall | (rocks if p.rocks_as_hazard else False)
        g_cue = remap_with(cues.astype(np.float32), g_maps) > 0.25
        # the shading stage's ground point, taken now: the float64 X, Y (4 MiB at 512^2) and the grid's
        # float64 pixel maps are not held through the slope fits, where the pair's memory peaks
        ground = None
        if have_dem and sun is not None and (p.shading_slope or p.keep_layers) and covered.any():
            ground = (float(np.nanmedian(X[covered])), float(np.nanmedian(Y[covered])))
        del X, Y, z_fill, gu, gv

    with _stage(timings, "slope"):
        if have_dem and not clock.ok():
            have_dem = False  # past the deadline: the image cues are all the evidence there is
            info["skipped"].append("slope")
        if have_dem:
            # the steeper of the footprint's plane and a few footprints' (SGM can terrace a steep wall)
            fit = steeper_plane_fit(g_elev, g_sig, cell, p.footprint_m, p.wide_slope_factor * p.footprint_m)
            # uncertainty of the footprint-scale quantities, calibrated on tuning seeds (evidence.py):
            # slope from the footprint's mean sigma, roughness from the point's sigma
            g_sbar = footprint_mean(g_sig, footprint_cells(p.footprint_m, cell))
            g_gsig = (p.slope_sigma_gain * g_sbar * cell / p.footprint_m).astype(np.float32)
            g_rough = np.abs(g_elev - fit.z_plane)
            g_rsig = (p.rough_sigma_gain * g_sig).astype(np.float32)
            slope_img = remap_with(fit.slope_deg, px_maps)
            grad_img = remap_with(fit.grad, px_maps)
            gsig_img = remap_with(g_gsig, px_maps)
            rough_img = np.abs(elevation - remap_with(fit.z_plane, px_maps))
            rsig_img = (p.rough_sigma_gain * sigma).astype(np.float32)
        else:
            slope_img = grad_img = gsig_img = rough_img = rsig_img = np.full(i1.shape, np.nan, np.float32)
            fit = None

    pc_img: np.ndarray | None = None
    caster_img: np.ndarray | None = None
    if fit is not None and sun is not None and (p.shading_slope or p.keep_layers):
        if not clock.ok((SHADING_SLOPE_S + AFTER_SLOPE_S) * px_scale):
            info["skipped"].append("shading_slope")  # a_pc NaN: the trees' no-sun case, the cap reads a
        else:
            with _stage(timings, "shading_slope"):
                # grid columns run along +X, rows along -Y: the world gradient of the footprint plane
                gx = remap_with(fit.p, px_maps) / np.float32(cell)
                gy = -remap_with(fit.q, px_maps) / np.float32(cell)
                seen = ~dark & np.isfinite(elevation)  # lit and matched: what the brightness gain is fitted on
                c_meas = measured_incidence(
                    a1,
                    incidence_cosine(gx, gy, sun),
                    seen,
                    fp_px,
                    min(64.0, max(16.0, p.shading_gain_footprints * fp_px)),
                )
                pc_img = np.where(covered & seen, shading_gradient(gx, gy, c_meas, sun), np.nan).astype(np.float32)
                pc_img *= np.float32(cell)  # m per cell, as grad_img
                del gx, gy, c_meas, seen
                # what casts each shadow lies sun-ward of it, within about a footprint (a boulder, a rim)
                toward = None
                if ground is not None:
                    toward = image_direction(camera, pose1, ground, (float(sun[0]), float(sun[1])), z_ref)
                if toward is not None:
                    reach = int(min(CASTER_MAX_PX, max(2, round(fp_px))))
                    caster_img = caster_distance(shadow, toward, reach)
    if pc_img is None or caster_img is None:  # NaN: no sun known (the trees' no-sun case, as a_pc)
        nan_img = np.full(i1.shape, np.nan, np.float32)  # made only when needed: an image each at 1024^2
        pc_img = nan_img if pc_img is None else pc_img
        caster_img = nan_img if caster_img is None else caster_img

    with _stage(timings, "hazard"):
        kw = {
            "slope_limit_deg": p.slope_limit_deg,
            "rough_limit_m": p.rough_limit_m,
            "k": p.sigma_k,
            "p_min": p.psafe_min,
        }
        layers: dict[str, np.ndarray] = {}
        if calibrated or p.keep_layers:
            # on the covered bounding box (+ the widest context window): same values, a quarter of the work
            cs = _crop_box(covered, PSAFE_WIDE_PX // 2 + 1)
            feats = psafe_features(
                grad_img[cs],
                gsig_img[cs],
                rough_img[cs],
                rho[cs],
                cell,
                fp_px,
                slope_limit_deg=p.slope_limit_deg,
                rough_limit_m=p.rough_limit_m,
                grad_shading=pc_img[cs],
                caster_px=caster_img[cs],
                speck=speck_contrast(a1[cs], fp_px),
            )
            if p.keep_layers:
                layers = {k: _uncrop(v, cs, i1.shape) for k, v in feats.items()}
                layers["dark"] = shadow
        if fitted is not None:
            # calibrated P(safe) per pixel and the FP-budget call (psafe.py); the grid takes the pixels' call
            model = fitted[0]
            ev_c = classify_calibrated(
                model,
                feats,
                (shadow | (rocks if p.rocks_as_hazard else False))[cs],
                covered[cs],
                p.fp_budget,
                p.psafe_min,
                p.psafe_unsafe,
                p.call_slope_max,
                p.call_slope_sigma_k,
                p.call_slope_feature,
            )
            fp_min = float(model.info.get("footprint_px_min", 0.0))
            if fp_px < fp_min:  # the trees' P(safe) would be an extrapolation there: nothing is called safe
                ev_c = below_model_scale(ev_c, fp_px, fp_min, float(model.info.get("safe_share", 0.5)))
                info["psafe_beyond_scale"] = (
                    f"the {p.footprint_m:g} m footprint is {fp_px:.2f} px here, below the {fp_min:g} px the P(safe) "
                    "model was fitted down to: nothing is called safe"
                )
            ev = Evidence(
                _uncrop(ev_c.state, cs, i1.shape, STATE_OUTSIDE),
                _uncrop(ev_c.psafe, cs, i1.shape),
                _uncrop(ev_c.hazard, cs, i1.shape),
            )
            g_call = remap_with((ev.state == STATE_SAFE).astype(np.float32), g_maps) > p.grid_call_share
            g_ps = remap_with(np.nan_to_num(ev.psafe, nan=0.0), g_maps)
            g_bad = remap_with((ev.state == STATE_UNSAFE).astype(np.float32), g_maps) > 0.5
            gev = grid_evidence(
                g_call,
                g_bad,
                g_ps,
                g_cov,
                fit.grad if fit is not None else None,
                cell,
                g_rough if fit is not None else None,
                p.slope_limit_deg,
                p.rough_limit_m,
                measured=np.isfinite(g_seen),
            )
            del feats, ev_c, g_call, g_ps, g_bad
        else:
            ev = classify(grad_img, gsig_img, rough_img, rsig_img, cues, covered, cell, **kw)
            if fit is not None:
                gev = classify(fit.grad, g_gsig, g_rough, g_rsig, g_cue, g_cov, cell, **kw)
            else:
                nan_g = np.full(shape, np.nan, np.float32)
                gev = classify(nan_g, nan_g, nan_g, nan_g, g_cue, g_cov, cell, **kw)
        if p.grid_hold_unsafe:
            gev, info["grid_held_unsafe"] = hold_unsafe_pixels(gev, ev.state == STATE_UNSAFE, ev.psafe, px_maps)
        if p.hazard_margin_px > 0:
            ev = widen_unsafe(ev, p.hazard_margin_px)
            gev = widen_unsafe(gev, p.hazard_margin_px)
        grid = HazardGrid(
            gev.hazard,
            np.where(g_cov, g_seen, np.nan).astype(np.float32),
            origin,
            float(cell),
            gev.state,
            gev.psafe,
            None if g_dem is None else np.where(g_cov, g_dem, np.nan).astype(np.float32),
        )
    # what the site search does not read, dropped before it: 512^2 approach pairs peaked there at 69 MiB
    del fit, gev, grad_img, gsig_img, rsig_img, pc_img, caster_img, px_maps, g_maps

    with _stage(timings, "sites"):
        if clock.ok():
            sites, reason = select_safe_sites(
                grid,
                p.footprint_m,
                nominal,
                p.n_sites,
                p.site_margin_m,
                relief_max_m=p.site_relief_max_m,
                relief_window_m=p.site_relief_window_m,
                reach_cells=p.site_reach_cells,
            )
        else:
            sites, reason = [], "deadline reached before site selection"
            info["skipped"].append("sites")
        if not sites:
            beyond = info.get("psafe_beyond_scale")
            info["no_site_reason"] = f"{beyond} ({reason})" if beyond else reason

    info["unknown_fraction"] = float(np.mean(ev.state[covered] == STATE_UNKNOWN)) if covered.any() else 0.0
    filled = np.zeros(elevation.shape, bool)
    if dem_fill is not None:
        filled, z_filled, s_filled = dem_fill
        elevation[filled] = z_filled
        sigma[filled] = s_filled
        filled &= np.isfinite(elevation)
    # the share of the covered pixels whose reported elevation is a fill: the DEM's coverage counts them
    info["dem_filled_fraction"] = float(np.count_nonzero(filled & covered) / max(1, int(covered.sum())))
    return _result(
        p,
        level,
        timings,
        info,
        grid,
        sites,
        elevation,
        ev.hazard,
        slope_img,
        rough_img,
        rocks,
        shadow,
        covered,
        world_xy,
        state=ev.state,
        psafe=ev.psafe,
        sigma=np.where(np.isfinite(elevation), sigma, np.nan).astype(np.float32),
        filled=filled,
        layers=layers,
    )
