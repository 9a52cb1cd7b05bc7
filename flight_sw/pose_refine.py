"""Relative pose refinement before the sweep (issue #10; thesis ch. 8; Xiong, Olson & Matthies 2005).

The sweep needs the epipolar geometry to a fraction of a pixel; navigation knows
it to ~0.1 deg (several pixels). This block estimates the motion between the
two descent images from the images themselves and hands the sweep a pose pair
that agrees with them. Arrays in, arrays out; no I/O, no ground truth.

1. **Guided matching.** i2 is low-passed to i1's footprint and warped onto i1
   through the navigation's homography of the reference plane ``Z = 0``
   (H&Z eq. 13.2, :mod:`flight_sw.homography`); that removes the ~2x scale
   change, so a binary detector works. ORB (Rublee et al. 2011; or SIFT,
   Lowe 2004) matches in the overlap with Lowe's ratio test and a mutual
   check; a RANSAC homography of those matches absorbs the navigation error.
   Corners (Shi & Tomasi 1994) are then tracked by Lucas-Kanade with a
   forward-backward check (Kalal et al. 2010) for sub-pixel matches, which
   are mapped back to i2's pixels. LK sees both images high-passed
   (minus a Gaussian local mean): it assumes constant brightness, and two
   views at different ranges and emission angles differ smoothly in it.
2. **Model selection and outliers.** RANSAC fits both an essential matrix
   and a homography; Torr's GRIC (1998),
   ``GRIC = sum min(e_i^2 / s^2, 2 (r - d)) + ln(r) d n + ln(r n) k``
   (``r = 4``; H: ``d = 2, k = 8``; E: ``d = 3, k = 5``), says which explains the
   matches (descent terrain is nearly planar: typically H). The winner's
   inliers go on.
3. **Nonlinear refinement (MAP).** Over the two attitudes ``R1, R2`` and the
   world baseline direction ``b`` (8 unknowns), Levenberg-Marquardt (H&Z A6.2)
   minimises robust (Cauchy) Sampson errors (H&Z eq. 11.9) of
   ``F = K^-T [t]x R21 K^-1`` with ``R21 = R2 R1^T``, ``t = -R2 b``, plus Gaussian
   navigation priors (world axes): frame 1's attitude error ``e1`` (sd ``s_c``),
   the error frame 2 adds to it ``e2 - e1`` (sd ``s_r``), and the baseline
   direction of the reported positions (sd ``sqrt(2) s_p / L``, ``L`` the
   baseline). Why priors: with a 30 deg field of view and motion along the
   optical axis, a rotation about an axis across the view and a tilt of the
   baseline move the image almost alike, so two views alone leave a
   ~0.05-0.2 deg valley that tilts the DEM; and the absolute attitude of the
   pair is not in the images at all, only in the navigation's attitude and,
   across the baseline, in its positions (docs/benchmarks/pose.md).
4. **Scale and datum.** Images cannot observe them. The baseline length is
   the reported baseline projected on ``b``; frame 0's reported position is
   kept (the datum). Optionally (``use_altimeter``), a laser-altimeter slant
   range along an optical axis over the reconstructed axis depth gives a
   second length ``L_a``; the two are combined by inverse variance,
   ``L = (L_n / s_n^2 + L_a / s_a^2) / (1 / s_n^2 + 1 / s_a^2)`` with
   ``s_n = sqrt(2) s_p`` and ``s_a = altimeter_rel_sigma L_a``, and both reported
   positions are fitted by least squares (halving the datum variance). Off by
   default: with exact navigation the sparse axis depth costs accuracy on low
   pairs, and no altimeter can observe the datum (docs/benchmarks/pose.md).
5. **Degeneracy.** Too few matches or inliers, poor spread, too little
   parallax after removing the rotation (pure rotation, identical frames),
   a correction beyond the plausible, a large residual, no convergence, or a
   relative rotation the images do not pin down (posterior sd above
   ``max_rel_rot_sd_deg``: a near-planar scene in a narrow field of view, where
   a rotation and a baseline-direction change move the plane's image alike),
   or a ground the fit triangulates (median inlier height) more than
   ``max(max_ground_gap_m, max_ground_gap_frac r)`` from where frame 1's
   altimeter reads it (an image from another altitude: the poses alone cannot
   see a scale; checked after the degeneracy reasons, which it does not
   override): the navigation poses are returned unchanged with
   ``refined = False``, the reason, and a ``verdict`` for the callers.
6. **Confounded nadir pairs.** With too little depth variation over the
   matches (``min_depth_spread``: a lateral change of the baseline moves points
   by ~1/depth, a rotation does not, so on a near-nadir view of flat ground the
   two are confounded and a free fit follows tiny matching biases - 0.05-0.4
   deg from exact poses) the relative rotation is held at navigation about the
   two axes across the view (``held_rel_att_sigma_deg``; its roll about frame 1's
   optical axis, which no baseline change mimics, keeps the free fit's prior:
   ``held_axis_free``) and the baseline direction takes the image
   motion: any such split maps the ground plane alike, and the ground's
   mapping is what the sweep needs. If that moves the ground's image by less
   than ``min_held_change_px``, navigation is kept.

Steps 1 and 3 live in :mod:`flight_sw.guided_match` and :mod:`flight_sw.pose_map`, the geometry they share in
:mod:`flight_sw.twoview`; this module holds the knobs, the checks and verdicts, and the descent's chain of fits.
"""

from __future__ import annotations

import hashlib
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from protocol.pairdir import Camera, Pose
from reports.console import apart, past

from .guided_match import apply_h, corners_in, descriptor_matches, gray8, highpass, prewarp, shift_h, track
from .homography import plane_homography
from .pose_map import MotionState, map_refine
from .rangefind import altimeter_ground, prior_range
from .twoview import (
    angle_between_deg,
    axis_depth,
    gric,
    homography_sampson_px,
    relative_pose,
    rot_log,
    rotation_angle_deg,
    sampson_px,
    triangulate_depths,
)
from .validate import FlightInputError
from .warping import area_sigma

DETECTORS = ("orb", "sift", "akaze")

# What a refinement's outcome says about the navigation pose (``info["verdict"]``, beside the human ``reason``);
# the pipeline and `process` decide by it, never by the reason's words.
REFINED = "refined"  # the images refined the pose
KEPT = "kept"  # the images agree with navigation within a fraction of a pixel on the ground: kept as it is
DEGENERATE = "degenerate"  # matched, but the geometry cannot fix the pose (little parallax or depth, no convergence)
# by the navigation poses the images hardly share ground: geometry, not a fault (a clean 100 m frame of a 1000 m
# descent), so the pose stays unchecked, and nothing in the images is against it
NO_OVERLAP = "no_overlap"
# too few matches in what they share: a small overlap again, or a blank image; unchecked
FEW_MATCHES = "few_matches"
# texture enough, and it matches nothing consistent: another image, or a pose far from the one declared
UNMATCHED = "unmatched"
# the images matched, and the correction they ask for is beyond the navigation's error envelope (a 30 m lateral
# error at 300 m asked for 4.4 deg and gave a 37 m DEM error with no word): the pose is wrong, or the frames are
# not the pair they claim to be. Clean pairs hardly reach it (docs/benchmarks/pose.md: a polar low sun did)
DISAGREES = "disagrees"
SKIPPED = "skipped"  # not tried: the deadline left no time for it
# its image is an earlier frame's, pixel for pixel (a camera that sent an image again): evidence at any image size,
# where a fit's verdict counts only from CHECK_MIN_SIDE (a 128 px pair of one image twice got no word; QA of stop 71)
REPEATED = "repeated"
VERDICTS = (REFINED, KEPT, DEGENERATE, NO_OVERLAP, FEW_MATCHES, UNMATCHED, DISAGREES, SKIPPED, REPEATED)
# px: below it even clean pairs fail the refinement's checks (measured at 96 and 128 px), so a fallback says nothing
CHECK_MIN_SIDE = 256


def repeat_reason(j: int) -> str:
    """The reason of a :data:`REPEATED` verdict: the frame's image is frame ``j``'s."""
    return f"its image is frame {j}'s, pixel for pixel: the same image twice (a camera that sent an image again)"


def unchecked(verdict: str, side: int) -> bool:
    """True when a frame's ``verdict`` means its pose is unchecked or contradicted by the images
    (:data:`NO_OVERLAP`, :data:`FEW_MATCHES`, :data:`UNMATCHED`, :data:`DISAGREES`), on images of at least
    :data:`CHECK_MIN_SIDE` px a side, or its image repeats an earlier frame's (:data:`REPEATED`, any size)."""
    checked = side >= CHECK_MIN_SIDE and verdict in (NO_OVERLAP, FEW_MATCHES, UNMATCHED, DISAGREES)
    return verdict == REPEATED or checked


def contradicted(verdict: str, side: int) -> bool:
    """True when a frame's ``verdict`` is evidence against it (:data:`UNMATCHED`, :data:`DISAGREES`), on images
    of at least :data:`CHECK_MIN_SIDE` px a side, or :data:`REPEATED` at any size: such a frame is left out of a
    multi-frame sweep."""
    return verdict == REPEATED or (side >= CHECK_MIN_SIDE and verdict in (UNMATCHED, DISAGREES))


@dataclass(frozen=True)
class RefineParams:
    """Knobs of the pose refinement. Navigation sigmas are the declared accuracy, not tuned on results."""

    detector: str = "orb"  # coarse matcher on the pre-warped pair: "orb" | "sift" | "akaze" (OpenCV < 5)
    n_features: int = 500  # detector budget per image (only a homography is needed)
    ratio: float = 0.8  # Lowe's ratio test
    coarse_ransac_px: float = 3.0  # residual-homography RANSAC threshold on the pre-warped pair (i1 px)
    max_prewarp_shift_px: float = 60.0  # images vs navigation beyond this (i1 px): refuse (~3.5 deg at 512 px)
    n_corners: int = 500  # Shi-Tomasi corners tracked for the fine matches
    corner_quality: float = 0.001
    track_window: int = 15  # Lucas-Kanade window (px)
    track_levels: int = 1  # pyramid levels above the base
    track_passes: int = 3  # tracking passes; each re-warps i2 through the homography of the previous matches
    fb_max_px: float = 0.5  # forward-backward disagreement that drops a track
    # LK runs on both images minus their Gaussian local mean (this sigma, px; 0 = raw): the two views see the
    # ground under different emission angles and exposures, and brightness that differs smoothly biased the
    # tracks (tuning seeds 0-4, 40 approach pairs, exact poses: relative rotation off 0.038 deg median,
    # 0.062 max, raw; 0.024 / 0.040 deg with sigma 2; 1-4 px alike)
    track_highpass_sigma: float = 2.0
    ransac_px: float = 1.5  # E / H RANSAC threshold (px)
    cauchy_k: float = 2.5  # robust loss scale, in units of the matching noise
    sigma_px_min: float = 0.05  # floor on the matching noise that weighs the images against navigation
    nav_att_sigma_deg: float = 0.25  # frame-1 attitude error, shared by frame 2 (alignment, star tracker)
    nav_rel_att_sigma_deg: float = 0.25  # frame-2 attitude error on top of frame 1's (accrued between them)
    nav_pos_sigma_m: float = 0.5  # position error of each frame, per axis
    use_altimeter: bool = False  # scale from altimeter ranges where given, weighed against the navigation's
    # relative sd of the altimeter's baseline length (the range against the tracks' plane at the optical axis):
    # 0.085 % rms on tuning approach pairs with exact poses (seeds 0-5, 125-1200 m); 0: the altimeter alone
    altimeter_rel_sigma: float = 0.001
    min_inliers: int = 40
    min_spread: float = 0.4  # share of the overlap's 4x4 cells holding an inlier
    min_parallax_px: float = 2.0  # median rotation-compensated motion (i2 px): below it, translation is unobservable
    # ... but where the navigation poses predict more than this many times that (a repeated image: 0.00 px against
    # ~30 px on a 512 px 300/250 pair), the images contradict the poses: `unmatched`, not `degenerate`
    nav_parallax_factor: float = 4.0
    max_rotation_deg: float = 2.0  # a larger correction of either attitude is refused
    max_direction_deg: float = 5.0  # a larger change of the baseline direction is refused
    max_rms_px: float = 1.0  # inlier Sampson RMS above this: refused
    # posterior sd (rms over the 3 axes) of the relative rotation above this: the images do not pin it down
    # (near-planar scene seen along the baseline, narrow field of view) - refused; 0.15 deg already costs 15x
    max_rel_rot_sd_deg: float = 0.1
    # inlier depth spread (p90 - p10) / median below this: a rotation and a baseline-direction change are
    # confounded (near-nadir view of near-flat ground) - refused. Tuning seeds 0-2: vertical 0.007-0.047
    # (relative rotation off 0.05-0.41 deg from exact poses), approach 0.16-0.30 (off 0.004-0.040 deg)
    min_depth_spread: float = 0.1
    # ... and then, instead of refusing, the relative rotation is held at navigation with this prior sd
    # (deg; 0 = refuse as before) and the baseline direction takes the image motion. Tuning landing
    # campaign, vertical pairs under navigation errors: DEM mean |error| 2.65 -> 0.47 m median
    # (docs/benchmarks/pose.md, "Nadir pairs")
    held_rel_att_sigma_deg: float = 0.03
    # ... about the two axes across the view only: the rotation about frame 1's optical axis keeps the free fit's
    # prior (nav_rel_att_sigma_deg), since a roll turns the image and no baseline change does that
    held_axis_free: bool = True
    # ... unless that moves the ground's image by less than this (px): the held fit maps the ground to
    # ~0.4 px of the truth from poses 2.7 px off, and moves exact poses by 0.05-0.20 px (tuning renders'
    # vertical pairs, p10-p90), so a smaller correction is not evidence and navigation is kept
    min_held_change_px: float = 0.5
    # ... and a fit that corrects either attitude (any fit), or the baseline direction (a held one), by more than
    # this many sds of the navigation's declared accuracy (nav_att_sigma_deg; sqrt(2) nav_pos_sigma_m / baseline)
    # is refused:
    # holding the relative rotation, the fit pours a relative rotation error into a common tilt and a baseline
    # change, and the DEM follows. A 3 deg pitch of a 300/150 pair's last frame came out as 1.34 deg of both
    # attitudes and 1.56 deg of direction, "ok", with a DEM 2.7 m off (stop 59's QA); 0.3 deg as 0.12-0.25 and
    # 0.13-0.29 deg. 3 sd keeps the 0.5 deg envelope inside
    max_correction_sd: float = 3.0
    # the ground the fit triangulates (median inlier height) may lie this far from where frame 1's altimeter reads
    # it: max(m, frac x its range). Beyond, the images scale the scene unlike the positions say: a frame's image
    # from another altitude (two images swapped in a descent put it 150-200 m off, 16-25 % of the range, and were
    # swept unsaid, DEMs 29-42 m off; stop 59's QA), a position or the reading wrong. Clean renders (323 QA
    # directories and descents, 6 scenes, 256 and 512 px, 394 fits; stop 60): at most 4.7 % (a deep crater's
    # rim against the floor its altimeter reads, 1200 m) but a 2-deg sun at 100 m (12 %, refused already)
    max_ground_gap_m: float = 10.0
    max_ground_gap_frac: float = 0.08
    max_iterations: int = 30

    def ground_gap_limit(self, range_m: float) -> float:
        """How far a fit's ground may lie from the reference ground ``range_m`` below frame 0 (module doc, 5)."""
        return max(self.max_ground_gap_m, self.max_ground_gap_frac * range_m)

    def validate(self) -> None:
        if self.detector not in DETECTORS:
            raise FlightInputError(f"pose refinement: detector must be one of {DETECTORS}, got {self.detector!r}")
        if self.detector == "akaze" and not hasattr(cv2, "AKAZE_create"):
            raise FlightInputError("pose refinement: this OpenCV build has no AKAZE (OpenCV 5 moved it to contrib)")
        for name in (
            "ratio",
            "coarse_ransac_px",
            "max_prewarp_shift_px",
            "corner_quality",
            "fb_max_px",
            "ransac_px",
            "cauchy_k",
            "sigma_px_min",
            "nav_att_sigma_deg",
            "nav_rel_att_sigma_deg",
            "nav_pos_sigma_m",
            "min_parallax_px",
            "nav_parallax_factor",
            "max_rotation_deg",
            "max_direction_deg",
            "max_rms_px",
            "max_rel_rot_sd_deg",
            "min_depth_spread",
            "min_held_change_px",
            "max_correction_sd",
            "max_ground_gap_m",
            "max_ground_gap_frac",
        ):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise FlightInputError(f"pose refinement: {name} must be a positive number, got {v!r}")
        for name in ("n_features", "n_corners", "track_window", "track_passes", "min_inliers", "max_iterations"):
            v = getattr(self, name)
            if not (isinstance(v, int) and v >= 1):
                raise FlightInputError(f"pose refinement: {name} must be a positive integer, got {v!r}")
        a = self.altimeter_rel_sigma
        if not (isinstance(a, (int, float)) and math.isfinite(a) and 0 <= a < 1):
            raise FlightInputError(f"pose refinement: altimeter_rel_sigma must be in [0, 1), got {a!r}")
        held = self.held_rel_att_sigma_deg
        if not (isinstance(held, (int, float)) and math.isfinite(held) and held >= 0):
            raise FlightInputError(f"pose refinement: held_rel_att_sigma_deg must be a number >= 0, got {held!r}")
        hp = self.track_highpass_sigma
        if not (isinstance(hp, (int, float)) and math.isfinite(hp) and hp >= 0):
            raise FlightInputError(f"pose refinement: track_highpass_sigma must be a number >= 0, got {hp!r}")
        if not 0 <= self.track_levels <= 5 or not 0 < self.min_spread <= 1 or not self.ratio < 1:
            raise FlightInputError("pose refinement: need track_levels 0..5, 0 < min_spread <= 1, ratio < 1")


@dataclass
class PoseRefinement:
    """Refined poses (the navigation's where ``refined`` is False) and the pose-quality telemetry."""

    pose1: Pose
    pose2: Pose
    refined: bool
    info: dict[str, Any] = field(default_factory=dict)


# --------------------------------------------------------------------------- the block
def _spread(u: np.ndarray, mask: np.ndarray, roi: tuple[int, int, int, int]) -> float:
    """Share of the overlap's 4x4 cells (at least half inside the ROI-local ``mask``) that hold a point."""
    x0, y0, w, h = roi
    if w == 0 or h == 0:
        return 0.0
    cx = np.clip(((u[:, 0] - x0) * 4 / w).astype(int), 0, 3)
    cy = np.clip(((u[:, 1] - y0) * 4 / h).astype(int), 0, 3)
    sub = mask.astype(np.float32)  # ROI-local
    cells = cv2.resize(sub, (4, 4), interpolation=cv2.INTER_AREA) >= 0.5
    hit = np.zeros((4, 4), bool)
    hit[cy, cx] = True
    n = int(cells.sum())
    return float((hit & cells).sum() / n) if n else 0.0


def _fallback(
    pose1: Pose, pose2: Pose, info: dict[str, Any], verdict: str, reason: str, t0: tuple[float, float]
) -> PoseRefinement:
    info.update(
        refined=False,
        verdict=verdict,
        reason=reason,
        wall_s=time.perf_counter() - t0[0],
        cpu_s=time.thread_time() - t0[1],
    )
    return PoseRefinement(pose1, pose2, False, info)


def refine_pair(
    i1: np.ndarray,
    i2: np.ndarray,
    pose1: Pose,
    pose2: Pose,
    camera: Camera,
    *,
    altimeter_m: tuple[float, float] | None = None,
    params: RefineParams | None = None,
) -> PoseRefinement:
    """Refine the reported poses of a descent pair (i1 higher) from the images; see the module doc.

    ``altimeter_m``: slant ranges (m) along each frame's optical axis, NaN where
    there is none. Returns the navigation poses unchanged, with the reason, when
    the geometry is degenerate. Deterministic: same inputs, same output.
    """
    t0 = (time.perf_counter(), time.thread_time())
    p = params or RefineParams()
    p.validate()
    alt = _check_altimeter(altimeter_m)
    info: dict[str, Any] = {"detector": p.detector, "refined": False}
    a1, a2 = gray8(i1), gray8(i2)
    if a1.shape != (camera.height, camera.width) or a2.shape != a1.shape:
        raise FlightInputError(f"pose refinement: images must be {camera.width}x{camera.height}")

    # -- 1. guided matching: pre-warp i2 onto i1 through the navigation's ground-plane homography
    try:
        H_nav = plane_homography(camera, pose1, pose2, 0.0)
    except ValueError as exc:
        return _fallback(pose1, pose2, info, NO_OVERLAP, f"no ground-plane homography ({exc})", t0)
    d1 = pose1.position[2] / max(1e-9, -pose1.R[2, 2])
    d2 = pose2.position[2] / max(1e-9, -pose2.R[2, 2])
    gsd_ratio = float(min(1.0, d2 / d1)) if d1 > 0 and d2 > 0 else 1.0
    sig = area_sigma(gsd_ratio)
    b2 = cv2.GaussianBlur(a2, (0, 0), sig, borderType=cv2.BORDER_REPLICATE) if sig > 0 else a2
    margin = p.track_window // 2 + 2
    mask, roi, w2 = prewarp(b2, H_nav, camera, margin)
    if roi[2] < 4 * p.track_window or roi[3] < 4 * p.track_window:  # small images: a 128 px 2:1 pair shares ~46 px
        return _fallback(
            pose1,
            pose2,
            info,
            NO_OVERLAP,
            f"the images hardly overlap by the navigation poses ({roi[2]}x{roi[3]} px in common, under four "
            f"{p.track_window} px tracking windows a side)",
            t0,
        )
    x0, y0, w, h = roi
    pa, pb = descriptor_matches(a1[y0 : y0 + h, x0 : x0 + w], w2, mask, p.detector, p.n_features, p.ratio)
    info["coarse_matches"] = len(pa)
    H_c = np.eye(3)  # i1 px -> pre-warped i1 px
    info["coarse_inliers"] = 0
    if len(pa) >= 8:
        Hc, inl = cv2.findHomography(pa, pb, cv2.RANSAC, p.coarse_ransac_px, maxIters=2000, confidence=0.999)
        if Hc is not None and inl is not None and int(inl.sum()) >= 8:
            info["coarse_inliers"] = int(inl.sum())
            H_c = shift_h(x0, y0) @ Hc @ shift_h(-x0, -y0)
    # how far the images disagree with navigation, over the overlap's corners
    corners = np.array([[x0, y0], [x0 + w, y0], [x0, y0 + h], [x0 + w, y0 + h]], float)
    shift = float(np.max(np.linalg.norm(apply_h(H_c, corners) - corners, axis=1)))
    info["prewarp_shift_px"] = shift
    if shift > p.max_prewarp_shift_px:
        return _fallback(
            pose1,
            pose2,
            info,
            UNMATCHED,
            f"images disagree with navigation by {shift:.0f} px (> {p.max_prewarp_shift_px:g})",
            t0,
        )
    H_tot = H_nav @ H_c  # i1 px -> i2 px
    hp1 = highpass(a1, p.track_highpass_sigma)
    pts: np.ndarray | None = None
    u1 = u2 = np.zeros((0, 2))
    for k in range(p.track_passes):
        if k > 0:
            # re-warp through the homography fitted to the tracks: LK then measures only the relief
            # parallax, and its translation-only window model is not biased by a residual scale or shear
            if len(u1) < 8:
                break
            Hf, inl_f = cv2.findHomography(u1, u2, cv2.RANSAC, p.coarse_ransac_px, maxIters=2000, confidence=0.999)
            if Hf is None or int(inl_f.sum()) < 8:
                break
            H_tot = Hf / Hf[2, 2]
        if k > 0 or not np.allclose(H_c, np.eye(3)):
            mask, roi, w2 = prewarp(b2, H_tot, camera, margin)
        x0, y0, w, h = roi
        if pts is None:
            mind = max(3.0, math.sqrt(w * h / max(1, p.n_corners)) / 1.5)
            pts = corners_in(a1[y0 : y0 + h, x0 : x0 + w], mask, p, mind) + [x0, y0]
        inside = (pts[:, 0] >= x0) & (pts[:, 0] < x0 + w) & (pts[:, 1] >= y0) & (pts[:, 1] < y0 + h)
        sel = pts[inside]
        sel = sel[mask[(sel[:, 1] - y0).astype(int), (sel[:, 0] - x0).astype(int)]]
        ok, uw = track(hp1[y0 : y0 + h, x0 : x0 + w], highpass(w2, p.track_highpass_sigma), sel - [x0, y0], p)
        u1 = sel[ok]
        u2 = apply_h(H_tot, uw[ok] + [x0, y0]) if ok.any() else np.zeros((0, 2))
    info["tracks"] = len(u1)
    info["corners"] = 0 if pts is None else len(sel)  # tried in the last pass: texture there, and what tracked
    spread_cells = (mask, roi)
    return _refine_matches(u1, u2, pose1, pose2, camera, alt, p, info, t0, spread_cells)


def refine_from_matches(
    u1: np.ndarray,
    u2: np.ndarray,
    pose1: Pose,
    pose2: Pose,
    camera: Camera,
    *,
    altimeter_m: tuple[float, float] | None = None,
    params: RefineParams | None = None,
) -> PoseRefinement:
    """Steps 2-5 of the module doc on given matches (Nx2 pixels of i1 and i2), e.g. from another matcher."""
    t0 = (time.perf_counter(), time.thread_time())
    p = params or RefineParams()
    p.validate()
    alt = _check_altimeter(altimeter_m)
    u1 = np.asarray(u1, np.float64).reshape(-1, 2)
    u2 = np.asarray(u2, np.float64).reshape(-1, 2)
    if u1.shape != u2.shape:
        raise FlightInputError(f"pose refinement: {len(u1)} points in i1 but {len(u2)} in i2")
    info: dict[str, Any] = {"detector": "given", "refined": False, "tracks": len(u1)}
    x0, y0 = np.floor(u1.min(0)) if len(u1) else (0, 0)
    x1, y1 = np.ceil(u1.max(0)) + 1 if len(u1) else (1, 1)
    roi = (int(x0), int(y0), int(x1 - x0), int(y1 - y0))
    return _refine_matches(u1, u2, pose1, pose2, camera, alt, p, info, t0, (np.ones((roi[3], roi[2]), bool), roi))


def _check_altimeter(altimeter_m: tuple[float, float] | None) -> tuple[float, float]:
    if altimeter_m is None:
        return (math.nan, math.nan)
    try:
        alt = tuple(float(a) for a in altimeter_m)
    except (TypeError, ValueError):
        raise FlightInputError(f"altimeter_m must be two ranges (m) or NaN, got {altimeter_m!r}") from None
    if len(alt) != 2 or any(not (math.isnan(a) or (math.isfinite(a) and a > 0)) for a in alt):
        raise FlightInputError(f"altimeter_m must be two positive ranges (m) or NaN, got {altimeter_m!r}")
    return alt[0], alt[1]


def _ground_change_px(
    camera: Camera,
    nav: tuple[Pose, Pose],
    refined: tuple[Pose, Pose],
    R21: np.ndarray,
    t_unit: np.ndarray,
    L: float,
    x1n: np.ndarray,
    x2n: np.ndarray,
    u1: np.ndarray,
) -> tuple[float, float]:
    """How far the refined poses move the ground's image in i2 against navigation, in pixels, and the ground's
    elevation (m; NaN when too few inliers triangulate).

    The ground is the horizontal plane through the median world height of the triangulated inliers
    (``X = C1 + R1^T z1 x1``); the change is the largest ``|H_ref u - H_nav u|`` over the inliers' i1
    pixels ``u``, with ``H`` the plane's homography (H&Z eq. 13.2) under each pose pair.
    """
    z1 = triangulate_depths(R21, t_unit, x1n, x2n) * L
    ok = np.isfinite(z1) & (z1 > 0)
    if ok.sum() < 3:
        return math.inf, math.nan
    p1 = refined[0]
    zw = p1.position[2] + ((x1n[ok] * z1[ok, None]) @ p1.R)[:, 2]  # R^T x as x @ R
    z_ground = float(np.median(zw))
    try:
        h_ref = plane_homography(camera, refined[0], refined[1], z_ground)
        h_nav = plane_homography(camera, nav[0], nav[1], z_ground)
    except ValueError:
        return math.inf, z_ground
    return float(np.max(np.linalg.norm(apply_h(h_ref, u1) - apply_h(h_nav, u1), axis=1))), z_ground


def _vec_deg(R: np.ndarray) -> list[float]:
    """A small rotation's axis-angle vector (:func:`flight_sw.twoview.rot_log`) in degrees, for telemetry."""
    return [round(math.degrees(float(v)), 5) for v in rot_log(R)]


def _map_solve(
    K: np.ndarray,
    v1: np.ndarray,
    v2: np.ndarray,
    nav: MotionState,
    sigmas: tuple[float, float, float],
    p: RefineParams,
    info: dict[str, Any],
    axis_sigma: float | None = None,
) -> tuple[MotionState, np.ndarray, float]:
    """Step 3 of the module doc: MAP pose from the inlier matches under ``sigmas`` (frame-1 attitude,
    added frame-2 attitude, baseline direction; rad; ``axis_sigma``: the added attitude's about frame 1's
    optical axis, where it differs). Writes the fit's telemetry into ``info``; returns the state, the inlier
    mask and the inliers' depth spread (:func:`_depth_spread`) under it."""
    # matching noise: robust spread of the residuals at the navigation pose's best fit, floored
    s, r, _, _, _ = map_refine(K, v1, v2, nav, sigmas, 1.0, p.cauchy_k, p.max_iterations, axis_sigma=axis_sigma)
    sigma_px = max(p.sigma_px_min, 1.4826 * float(np.median(np.abs(r))))
    s, r, cov, iters, converged = map_refine(
        K, v1, v2, nav, sigmas, sigma_px, p.cauchy_k, p.max_iterations, s, axis_sigma=axis_sigma
    )
    inl = np.abs(r) < max(1.0, 3.0 * sigma_px)
    R21 = s.R2 @ s.R1.T
    R21_nav = nav.R2 @ nav.R1.T
    J_rel = np.c_[-R21, np.eye(3), np.zeros((3, 2))]  # relative-rotation error ~ d2 - R21 d1 (camera-2 axes)
    t_unit = -s.R2 @ s.b
    Ki = np.linalg.inv(K)
    flow = v2 - apply_h(K @ R21 @ Ki, v1)  # motion left after removing the rotation
    info.update(
        inliers=int(inl.sum()),
        iterations=iters,
        converged=converged,
        sigma_px=sigma_px,
        reproj_rms_px=float(np.sqrt(np.mean(r[inl] ** 2))) if inl.any() else None,  # JSON has no inf
        reproj_median_px=float(np.median(np.abs(r[inl]))) if inl.any() else None,
        parallax_px=float(np.median(np.linalg.norm(flow[inl], axis=1))) if inl.any() else 0.0,
        rotation_correction_deg=[rotation_angle_deg(s.R1 @ nav.R1.T), rotation_angle_deg(s.R2 @ nav.R2.T)],
        relative_rotation_correction_deg=rotation_angle_deg(R21 @ R21_nav.T),
        # signed, about each frame's own camera axes x, y, z (R <- exp(w) R): the magnitudes alone could not be
        # checked against a known error's sign (pose QA of stop 75)
        rotation_correction_vec_deg=[_vec_deg(s.R1 @ nav.R1.T), _vec_deg(s.R2 @ nav.R2.T)],
        relative_rotation_correction_vec_deg=_vec_deg(R21 @ R21_nav.T),
        translation_dir_change_deg=angle_between_deg(s.b, nav.b),
        sigma_rel_rot_deg=math.degrees(math.sqrt(max(0.0, float(np.trace(J_rel @ cov @ J_rel.T))))),
        sigma_att1_deg=math.degrees(math.sqrt(max(0.0, float(np.trace(cov[0:3, 0:3]))))),
        sigma_dir_deg=math.degrees(math.sqrt(max(0.0, float(np.trace(cov[6:8, 6:8]))))),
    )
    return s, inl, _depth_spread(R21, t_unit, v1[inl], v2[inl], Ki)


def _nav_parallax_px(camera: Camera, pose1: Pose, pose2: Pose, altimeter_m: float, u1: np.ndarray) -> float:
    """The motion the navigation's baseline adds to the rotation's at ``u1`` (i1 px), as the ground would show
    it: the median of ``|H_g u - H_inf u|``, with ``H_g`` the ground plane's homography and ``H_inf = K R21 K^-1``
    the infinite one (Hartley & Zisserman 2004, ch. 13, the homography a plane induces: ``H_g = K (R - t n^T / d)
    K^-1``). The ground is frame 0's altimeter ground; without an altimeter, the deepest the range search looks
    (:func:`flight_sw.rangefind.prior_range`), which predicts the least: at the datum, a clean pair over ground
    260 m below it was called a repeat (stop 62's review). 0 where no plane homography exists."""
    z = altimeter_ground(pose1, altimeter_m) if math.isfinite(altimeter_m) else prior_range(pose1, pose2, None)[0]
    try:
        H_g = plane_homography(camera, pose1, pose2, z)
    except ValueError:
        return 0.0
    R21, _ = relative_pose(pose1, pose2)
    K = camera.K
    H_inf = K @ R21 @ np.linalg.inv(K)
    if len(u1) == 0:
        return 0.0
    return float(np.median(np.linalg.norm(apply_h(H_g, u1) - apply_h(H_inf, u1), axis=1)))


def _depth_spread(R21: np.ndarray, t21: np.ndarray, v1: np.ndarray, v2: np.ndarray, Ki: np.ndarray) -> float:
    """``(p90 - p10) / median`` of the matches' triangulated camera-1 depths under ``(R21, t21)``.

    Scale-free: a lateral baseline change moves points by ~1/depth, a rotation does not depend on
    depth, so only depth variation tells them apart. 0 with fewer than 3 usable depths."""
    n = len(v1)
    if n < 3:
        return 0.0
    x1n, x2n = np.c_[v1, np.ones(n)] @ Ki.T, np.c_[v2, np.ones(n)] @ Ki.T
    zd = triangulate_depths(R21, t21, x1n, x2n)
    zd = zd[np.isfinite(zd) & (zd > 0)]
    if zd.size < 3:
        return 0.0
    p10, p50, p90 = np.percentile(zd, [10, 50, 90])
    return float((p90 - p10) / p50) if p50 > 0 else 0.0


def _refine_matches(
    u1: np.ndarray,
    u2: np.ndarray,
    pose1: Pose,
    pose2: Pose,
    camera: Camera,
    alt: tuple[float, float],
    p: RefineParams,
    info: dict[str, Any],
    t0: tuple[float, float],
    spread_cells: tuple[np.ndarray, tuple[int, int, int, int]],
) -> PoseRefinement:
    K = camera.K
    mask, roi = spread_cells
    base = pose2.position - pose1.position
    L_nav = float(np.linalg.norm(base))
    if not L_nav > 1e-6:
        return _fallback(
            pose1, pose2, info, DEGENERATE, "navigation reports no baseline: translation direction undefined", t0
        )
    if len(u1) < p.min_inliers:
        tried = int(info.get("corners", 0))
        if tried >= 2 * p.min_inliers:  # texture enough in the overlap, and it does not follow: another image
            why = f"the images do not track: {len(u1)} of {tried} corners (< {p.min_inliers})"
            return _fallback(pose1, pose2, info, UNMATCHED, why, t0)
        return _fallback(pose1, pose2, info, FEW_MATCHES, f"too few matches ({len(u1)} < {p.min_inliers})", t0)

    # -- 2. model selection (GRIC) and outliers
    E, inl_e = cv2.findEssentialMat(u1, u2, K, cv2.RANSAC, 0.999, p.ransac_px)
    Hm, inl_h = cv2.findHomography(u1, u2, cv2.RANSAC, p.ransac_px, maxIters=2000, confidence=0.999)
    if E is None or Hm is None or E.shape != (3, 3):
        return _fallback(pose1, pose2, info, UNMATCHED, "RANSAC found no model (degenerate matches)", t0)
    Ki = np.linalg.inv(K)
    e_err = np.abs(sampson_px(Ki.T @ E @ Ki, u1, u2))
    h_err = homography_sampson_px(Hm, u1, u2)
    ie, ih = inl_e.ravel() > 0, inl_h.ravel() > 0
    sigma_model = max(0.05, 1.4826 * float(np.median(np.abs(e_err[ie])))) if ie.any() else 1.0
    g_e, g_h = gric(e_err, sigma_model, 3, 5), gric(h_err, sigma_model, 2, 8)
    model = "H" if g_h <= g_e else "E"
    keep = ih if model == "H" else ie
    info.update(model=model, gric_e=g_e, gric_h=g_h, ransac_inliers=int(keep.sum()))
    if keep.sum() < p.min_inliers:
        return _fallback(
            pose1, pose2, info, UNMATCHED, f"too few RANSAC inliers ({int(keep.sum())} < {p.min_inliers})", t0
        )
    v1, v2 = u1[keep], u2[keep]

    # -- 3. MAP refinement of R1, R2 and the baseline direction
    nav = MotionState(pose1.R, pose2.R, base / L_nav)
    s_att, s_dir = math.radians(p.nav_att_sigma_deg), math.sqrt(2.0) * p.nav_pos_sigma_m / L_nav
    # confounded nadir pairs (module doc, step 6): judged first under the navigation's geometry, so such
    # a pair costs one solve; again after the free fit in the rare case it finds the depths flatter
    can_hold = p.held_rel_att_sigma_deg > 0
    s_held = math.radians(p.held_rel_att_sigma_deg)
    spread_nav = _depth_spread(*relative_pose(pose1, pose2), v1, v2, Ki)
    held = can_hold and spread_nav < p.min_depth_spread
    s_free = math.radians(p.nav_rel_att_sigma_deg)
    s_rel = s_held if held else s_free
    # held: only the axes across the view are confounded with the baseline; a roll about the optical axis turns
    # the image, which no baseline change does (a 0.5 deg roll was kept as "navigation agrees"; QA of stop 75)
    s_axis = s_free if p.held_axis_free else None
    s, inl, spread = _map_solve(K, v1, v2, nav, (s_att, s_rel, s_dir), p, info, s_axis if held else None)
    if can_hold and not held and spread < p.min_depth_spread:
        s, inl, _ = _map_solve(K, v1, v2, nav, (s_att, s_held, s_dir), p, info, s_axis)
        held = True
    info.update(depth_spread=spread, depth_spread_nav=spread_nav, relative_rotation_held=held)
    info["spread"] = _spread(v1[inl], mask, roi)
    R21 = s.R2 @ s.R1.T
    t_unit = -s.R2 @ s.b
    x1n, x2n = np.c_[v1[inl], np.ones(int(inl.sum()))] @ Ki.T, np.c_[v2[inl], np.ones(int(inl.sum()))] @ Ki.T
    parallax = float(info["parallax_px"])
    rms = info["reproj_rms_px"] if info["reproj_rms_px"] is not None else math.inf

    # -- 4. scale and datum
    L_rep = float(s.b @ base)  # the reported baseline projected on the refined direction
    scales = []
    if p.use_altimeter and (math.isfinite(alt[0]) or math.isfinite(alt[1])):
        z1 = triangulate_depths(R21, t_unit, x1n, x2n)  # camera-1 depths for a unit baseline
        if math.isfinite(alt[0]):
            za = axis_depth(x1n, z1)
            if math.isfinite(za):
                scales.append(alt[0] / za)
        if math.isfinite(alt[1]):
            X2 = (x1n * z1[:, None]) @ R21.T + t_unit  # the same points in camera 2
            za = axis_depth(X2 / X2[:, 2:3], X2[:, 2])
            if math.isfinite(za):
                scales.append(alt[1] / za)
        L_alt = float(np.mean(scales)) if scales else math.nan
        info["altimeter_scale"] = L_alt / L_nav
        s_nav = math.sqrt(2.0) * p.nav_pos_sigma_m
        s_alt = p.altimeter_rel_sigma * abs(L_alt) if math.isfinite(L_alt) else math.nan
        # beyond 3 sigma of the two lengths' difference the altimeter scale is not believed (NaN too)
        if not abs(L_alt - L_rep) <= 3.0 * math.hypot(s_nav, s_alt):
            info["altimeter_ignored"] = f"altimeter baseline {L_alt:.2f} m vs reported {L_rep:.2f} m"
            scales = []
    if scales:
        if p.altimeter_rel_sigma > 0:  # inverse-variance mean of the two lengths (module doc, step 4)
            w_nav, w_alt = 1.0 / s_nav**2, 1.0 / s_alt**2
            L = (w_nav * L_rep + w_alt * L_alt) / (w_nav + w_alt)
            info["altimeter_weight"] = w_alt / (w_nav + w_alt)
        else:
            L = L_alt
        C1 = (pose1.position + pose2.position - L * s.b) / 2.0  # least squares on both reported positions
        info["scale_source"] = "altimeter"
    else:
        L = L_rep
        C1 = pose1.position.copy()
        info["scale_source"] = "navigation"
    C2 = C1 + L * s.b
    info.update(
        scale=L / L_nav,
        baseline_m=L,
        position_change_m=[float(np.linalg.norm(C1 - pose1.position)), float(np.linalg.norm(C2 - pose2.position))],
    )
    info["ground_change_px"], z_ground = _ground_change_px(
        camera, (pose1, pose2), (Pose(C1, s.R1), Pose(C2, s.R2)), R21, t_unit, L, x1n, x2n, v1[inl]
    )
    info["ground_z_m"] = None if math.isnan(z_ground) else z_ground
    ground_gap, gap_tol = math.nan, math.inf
    if math.isfinite(z_ground) and math.isfinite(alt[0]):
        ground_gap = z_ground - altimeter_ground(pose1, alt[0])
        gap_tol = p.ground_gap_limit(alt[0])
        info["ground_gap_m"] = ground_gap

    # -- 5. degeneracy checks
    reason, verdict = "", DEGENERATE
    if inl.sum() < p.min_inliers:
        reason = f"too few inliers ({int(inl.sum())} < {p.min_inliers})"
        verdict = UNMATCHED
    elif (
        parallax < p.min_parallax_px
        and (expected := _nav_parallax_px(camera, pose1, pose2, alt[0], v1[inl]))
        > p.nav_parallax_factor * p.min_parallax_px
    ):
        # the navigation's baseline would show as parallax the images do not have: a camera that sent its last
        # image again, or an image from where frame 0 was taken (a 300/250 pair with i2 a copy of i1 was refined
        # as `degenerate`, unwarned, its DEM 21 m off and "full"; stop 62's QA H1)
        reason = (
            f"no parallax between the images ({parallax:.2f} px) where the navigation poses predict "
            f"{expected:.0f} px: the same image twice, or frames taken from one place"
        )
        verdict = UNMATCHED
    elif parallax < p.min_parallax_px:  # before convergence: without parallax the translation wanders
        shown = past(parallax, p.min_parallax_px)
        reason = f"too little parallax ({shown} px < {p.min_parallax_px:g}): translation unobservable"
    elif not info["converged"]:
        reason = f"refinement did not converge in {info['iterations']} iterations"
    elif info["spread"] < p.min_spread:
        reason = f"inliers poorly spread over the overlap ({past(info['spread'], p.min_spread)} < {p.min_spread:g})"
    elif max(info["rotation_correction_deg"]) > p.max_rotation_deg:
        shown = past(max(info["rotation_correction_deg"]), p.max_rotation_deg)
        reason = f"attitude correction {shown} deg > {p.max_rotation_deg:g}"
        verdict = DISAGREES
    elif info["translation_dir_change_deg"] > p.max_direction_deg:
        shown = past(info["translation_dir_change_deg"], p.max_direction_deg)
        reason = f"baseline direction change {shown} deg > {p.max_direction_deg:g}"
        verdict = DISAGREES
    elif beyond := _beyond_navigation(info["rotation_correction_deg"], p):
        # held or not: on the approach a lower frame reported 20 m high came out as 1.1-1.7 deg of both attitudes,
        # under the 2 deg limit, and a DEM 40 m off with sites on it (stop 59's QA)
        reason = beyond + (
            " on a near-nadir pair, whose images cannot tell a relative rotation from a baseline change"
            if held
            else ": a position or attitude the images cannot follow"
        )
        verdict = DISAGREES
    elif held and info["translation_dir_change_deg"] > p.max_correction_sd * math.degrees(s_dir):
        turn, sd_limit = apart(info["translation_dir_change_deg"], p.max_correction_sd * math.degrees(s_dir))
        reason = (
            f"baseline direction change {turn} deg > {p.max_correction_sd:g} sd of the navigation's ({sd_limit}) on a "
            "near-nadir pair, whose images cannot tell a relative rotation from a baseline change"
        )
        verdict = DISAGREES
    elif rms > p.max_rms_px:
        reason = f"inlier residual {past(rms, p.max_rms_px)} px > {p.max_rms_px:g}"
        verdict = DISAGREES
    elif info["depth_spread"] < p.min_depth_spread and not held:
        shown = past(info["depth_spread"], p.min_depth_spread, 3)
        reason = (
            f"too little depth variation over the inliers ({shown} < {p.min_depth_spread:g}):"
            " a rotation and a baseline-direction change are confounded (near-nadir view of flat ground)"
        )
    elif info["sigma_rel_rot_deg"] > p.max_rel_rot_sd_deg:
        shown = past(info["sigma_rel_rot_deg"], p.max_rel_rot_sd_deg)
        reason = (
            f"the images do not pin down the relative rotation (posterior sd {shown} deg"
            f" > {p.max_rel_rot_sd_deg:g}): near-degenerate geometry"
        )
    elif not (C2[2] < C1[2] and L > 0):
        reason = "refined geometry puts frame 2 above frame 1"
        verdict = DISAGREES
    elif abs(ground_gap) > gap_tol:
        reason = (
            f"the images put the ground {ground_gap:+.0f} m from where the first frame's altimeter reads it, more "
            f"than {gap_tol:.0f} m"
        )
        verdict = DISAGREES
        info["scale_disagrees"] = True  # the altimeter against the images: a map resting on it offers no site
    elif held and info["ground_change_px"] < p.min_held_change_px:
        reason = (
            f"navigation already maps the ground within {info['ground_change_px']:.2f} px of the held-rotation"
            f" fit (< {p.min_held_change_px:g}): kept"
        )
        verdict = KEPT
    if reason:
        return _fallback(pose1, pose2, info, verdict, reason, t0)
    out1 = Pose(C1, s.R1, pose1.time_s)
    out2 = Pose(C2, s.R2, pose2.time_s)
    info.update(
        refined=True, verdict=REFINED, reason="ok", wall_s=time.perf_counter() - t0[0], cpu_s=time.thread_time() - t0[1]
    )
    return PoseRefinement(out1, out2, True, info)


def _beyond_navigation(corrections_deg: Sequence[float], p: RefineParams) -> str:
    """Why an attitude correction is more than ``p.max_correction_sd`` sds of the navigation's declared error
    of that frame ("" if neither is): frame 1's ``nav_att_sigma_deg``, frame 2's with ``nav_rel_att_sigma_deg``
    on top, ``sqrt(s_att^2 + s_rel^2)``."""
    sds = (p.nav_att_sigma_deg, math.hypot(p.nav_att_sigma_deg, p.nav_rel_att_sigma_deg))
    for k, (c, sd) in enumerate(zip(corrections_deg, sds)):
        limit = p.max_correction_sd * sd
        if c > limit:
            shown, limit_shown = apart(c, limit)
            return (
                f"attitude correction {shown} deg of the pair's {('upper', 'lower')[k]} frame > "
                f"{p.max_correction_sd:g} sd of the navigation's ({limit_shown})"
            )
    return ""


def transfer_relative(ref: Pose, rel_from: Pose, rel_to: Pose) -> Pose:
    """The pose that ``rel_to`` is relative to ``rel_from``, re-attached to ``ref``.

    ``R = (R_to R_from^T) R_ref`` and ``C = C_ref + R_ref^T R_from (C_to - C_from)``: the relative
    rotation and the baseline in the first camera's frame are kept (the pair's geometry), the
    reference frame's pose is replaced. Used to make every frame of a descent agree with one frame 0.
    """
    R = rel_to.R @ rel_from.R.T @ ref.R
    C = ref.position + ref.R.T @ (rel_from.R @ (rel_to.position - rel_from.position))
    return Pose(C, R, rel_to.time_s)


def refine_descent(
    images: Sequence[np.ndarray],
    poses: Sequence[Pose],
    camera: Camera,
    *,
    altimeter_m: Sequence[float] | None = None,
    params: RefineParams | None = None,
    stop_by: float | None = None,
) -> tuple[list[Pose], dict[str, Any]]:
    """Refine 2-16 descent frames against frame 0; returns the poses and the telemetry.

    The widest pair (frames 0 and -1) is refined first (:func:`refine_pair`) and fixes frame 0's
    pose; every other frame k is refined with frame 0 and its relative pose re-attached to that
    frame 0 (:func:`transfer_relative`). A degenerate pair keeps its navigation relative pose
    (re-attached the same way) and says why in ``info["frames"]``. ``info`` is the widest pair's
    telemetry plus ``frames``: per frame k >= 1 ``refined``, ``reason``, ``inliers``,
    ``relative_rotation_correction_deg``.

    ``stop_by`` (``time.monotonic()``): a middle frame is refined only while the widest pair's own cost still
    fits before it; the others keep their navigation relative pose, with the reason "skipped".

    A frame that shares too little ground with frame 0 to be judged is then checked against the nearest frame
    above it that was confirmed (:func:`_chain`; ``against`` in its entry, ``chain_fits`` in ``info``).
    """
    n = len(images)
    if n < 2 or len(poses) != n:
        raise FlightInputError(f"pose refinement: need 2-16 frames with one pose each, got {n} and {len(poses)}")
    alt = [math.nan] * n if altimeter_m is None else [math.nan if a is None else float(a) for a in altimeter_m]
    if len(alt) != n:
        raise FlightInputError(f"pose refinement: altimeter_m has {len(alt)} entries for {n} frames")
    t_wide = time.monotonic()
    wide = refine_pair(images[0], images[-1], poses[0], poses[-1], camera, altimeter_m=(alt[0], alt[-1]), params=params)
    cost = time.monotonic() - t_wide  # what one more pair will take, about
    out = [wide.pose1] + [poses[k] for k in range(1, n - 1)] + [wide.pose2]
    info = dict(wide.info)

    frames = []
    relative = {k: (poses[0], poses[k]) for k in range(1, n - 1)}  # each middle frame's pose relative to frame 0
    for k in range(1, n - 1):
        if stop_by is not None and time.monotonic() + cost > stop_by:
            out[k] = transfer_relative(out[0], poses[0], poses[k])
            why = "skipped: the deadline leaves no time to refine it (its navigation pose is kept)"
            frames.append({"frame": k, "refined": False, "verdict": SKIPPED, "reason": why, "inliers": 0})
            continue
        t_k = time.monotonic()
        r = refine_pair(images[0], images[k], poses[0], poses[k], camera, altimeter_m=(alt[0], alt[k]), params=params)
        # a widest pair that shares too little ground returns in 0.4 ms: a real fit takes 20-45 ms (stop 61's review)
        cost = max(cost, time.monotonic() - t_k)
        relative[k] = (r.pose1, r.pose2)
        out[k] = transfer_relative(out[0], r.pose1, r.pose2)
        frames.append(_summary(r, k))
    frames.append(_summary(wide, n - 1))
    p = params or RefineParams()
    for k, j in repeated_images(images).items():  # before the checks and the chain that read the verdicts
        frames[k - 1].update(
            refined=False,
            verdict=REPEATED,
            repeat_of=j,
            reason=repeat_reason(j),
        )
        _back_to_navigation(k, out, poses, relative)
        if k == n - 1:
            info.update(refined=False, verdict=REPEATED, reason=frames[k - 1]["reason"], repeat_of=j)
    for f in _scale_outliers(frames, poses[0], p):
        _back_to_navigation(f["frame"], out, poses, relative)
        if f["frame"] == n - 1:
            info.update(refined=False, verdict=DISAGREES, reason=f["reason"], scale_disagrees=True)
    # info stays the widest pair's own fit; a last frame checked against a frame above says so in its entry
    info["chain_fits"] = _chain(images, poses, camera, alt, p, stop_by, cost, out, frames)
    info["frames"] = frames
    return out, info


def _back_to_navigation(k: int, out: list[Pose], poses: Sequence[Pose], relative: dict[int, tuple[Pose, Pose]]) -> None:
    """Frame ``k``'s refined pose in ``out`` back to its navigation pose relative to frame 0. The last frame's
    (the widest pair's) fit had fixed frame 0's pose too: then frame 0 and it go back to navigation, and every
    middle frame is re-attached to frame 0 by its own fit (``relative``)."""
    n = len(out)
    if k == n - 1:
        out[0], out[-1] = poses[0], poses[-1]
        for m in range(1, n - 1):
            out[m] = transfer_relative(out[0], *relative[m])
    else:
        out[k] = transfer_relative(out[0], poses[0], poses[k])


def repeated_images(images: Sequence[np.ndarray]) -> dict[int, int]:
    """``{k: j}`` for each frame ``k`` whose image equals an earlier frame ``j``'s pixel for pixel. Two exposures
    never do (sensor noise, the camera moved); a camera that sent its last image again does. Uniform images are
    left out (blank, not repeated: the pipeline's blank-image check names them). A descent's frame 2
    a copy of frame 1 was "kept" against frame 0, unwarned, the DEM 32 m off (stop 62's review): its motion
    from frame 0 is frame 1's, which no fit against frame 0 alone can tell from its own."""
    seen: dict[bytes, int] = {}
    out: dict[int, int] = {}
    for k, im in enumerate(images):
        a = np.ascontiguousarray(im)
        if a.size == 0 or a.min() == a.max():  # a uniform image is blank, said as such: two of them were called
            continue  # "the same image twice, a camera that sent an image again" (pose QA of stop 75)
        h = hashlib.blake2b(str((a.shape, a.dtype.str)).encode(), digest_size=16)
        h.update(a.data.cast("B"))  # the pixels, not copied
        key = h.digest()
        if key in seen:
            out[k] = seen[key]
        else:
            seen[key] = k
    return out


def _summary(r: PoseRefinement, k: int, upper: str = "the reference frame") -> dict[str, Any]:
    """Frame ``k``'s entry in :func:`refine_descent`'s ``info["frames"]``. Its reason names the fit's two frames
    as ``upper`` and "this frame": said under frame k's warning, "the pair's upper frame" read as a fault of
    another frame (stop 61's review)."""
    why = str(r.info.get("reason", "")).replace("the pair's upper frame", upper)
    return {
        "frame": k,
        "refined": r.refined,
        "verdict": r.info.get("verdict", ""),
        "reason": why.replace("the pair's lower frame", "this frame"),
        "inliers": r.info.get("inliers", 0),
        "ground_z_m": r.info.get("ground_z_m"),
        "ground_gap_m": r.info.get("ground_gap_m"),
        "scale_disagrees": bool(r.info.get("scale_disagrees")),
        "relative_rotation_correction_deg": r.info.get("relative_rotation_correction_deg", 0.0),
        "relative_rotation_correction_vec_deg": r.info.get("relative_rotation_correction_vec_deg"),
        "wall_s": r.info.get("wall_s"),
        # a near-nadir fit holds the relative rotation and moves the baseline instead (module doc, 6): a 1 deg
        # pitch read "corrected by 0.10 deg" with the rest of it unsaid (stop 61's QA)
        "relative_rotation_held": bool(r.info.get("relative_rotation_held")),
        "translation_dir_change_deg": r.info.get("translation_dir_change_deg"),
        "ground_change_px": r.info.get("ground_change_px"),
    }


def _chain(
    images: Sequence[np.ndarray],
    poses: Sequence[Pose],
    camera: Camera,
    alt: list[float],
    p: RefineParams,
    stop_by: float | None,
    cost: float,
    out: list[Pose],
    frames: list[dict[str, Any]],
) -> int:
    """Check each frame that shares too little ground with frame 0 (:data:`NO_OVERLAP`, :data:`FEW_MATCHES`)
    against the nearest frame above it whose pose the images confirmed (:data:`REFINED`, :data:`KEPT`); in
    place.

    On a deep descent the frames' footprints shrink with their height: the last frame of a 256 px 1000/600/300
    approach shares 62x52 px with frame 0 and was swept unchecked, so a pitch or position fault in it moved the
    DEM 8-87 m with a note and no warning (stop 60's QA); against the 600 m frame it shares half the image, and
    matches (held-out seed 1031: a 1 deg pitch of it is refined away, DEM 15.3 -> 0.80 m, 0.75 m clean; a 2 deg
    pitch, 30 m across or 20 m up is refused and left out, 18-52 -> 1.01 m).

    A fit that confirms the frame re-attaches its pose to that frame's (:func:`transfer_relative`), so the chain
    ends at frame 0; one that contradicts it (:data:`UNMATCHED`, :data:`DISAGREES`) replaces the frame's verdict,
    and the sweep leaves it out; one that cannot judge it either leaves it as it was. ``against`` names the frame
    it was checked with. Its ground is held to the others' median as in :func:`_scale_outliers`, as frame 0's
    altimeter does not see its ground. Returns the number of fits made (each costs a pair's refinement)."""
    fits_made = 0
    confirmed = {f["frame"]: f for f in frames if f.get("verdict") in (REFINED, KEPT)}
    fits = [float(f["ground_z_m"]) for f in confirmed.values() if f.get("ground_z_m") is not None]
    z_ref = float(np.median(fits)) if fits else math.nan
    for i, f in enumerate(frames):
        k = int(f["frame"])
        anchors = [j for j in confirmed if j < k]
        if f.get("verdict") not in (NO_OVERLAP, FEW_MATCHES) or not anchors:
            continue
        if stop_by is not None and time.monotonic() + cost > stop_by:
            break
        j = max(anchors)
        fits_made += 1
        t_k = time.monotonic()
        r = refine_pair(images[j], images[k], poses[j], poses[k], camera, altimeter_m=(alt[j], alt[k]), params=p)
        cost = max(cost, time.monotonic() - t_k)
        g = {**_summary(r, k, upper="the frame it was checked against"), "against": j}
        verdict = g["verdict"]
        if verdict in (REFINED, KEPT) and g.get("ground_z_m") is not None and math.isfinite(z_ref):
            gap = float(g["ground_z_m"]) - z_ref
            # the scale of frame j's range: the fit triangulates from it (frame 0's allowed a 13 % scale error)
            tol = p.ground_gap_limit(float(poses[j].position[2]) - z_ref)
            if abs(gap) > tol:
                verdict = DISAGREES
                _off_the_others(g, gap, tol)
        if verdict in (REFINED, KEPT):
            out[k] = transfer_relative(out[j], r.pose1, r.pose2)
            confirmed[k] = g
        elif verdict not in (UNMATCHED, DISAGREES):
            continue
        frames[i] = g
    return fits_made


def _scale_outliers(frames: list[dict[str, Any]], pose0: Pose, p: RefineParams) -> list[dict[str, Any]]:
    """Frames whose fit puts the ground off where the others' put it, marked ``disagrees`` (``scale_disagrees``,
    ``ground_gap_m`` from the median) in place and returned.

    Without an altimeter the scale check of :func:`refine_pair` has no reference, and two images swapped in a
    descent came out "kept", the DEM 202 m off with an unsafe site (stop 60's QA). Every (frame 0, frame k) fit
    triangulates the same ground, so with three or more fits a frame more than ``max(max_ground_gap_m,
    max_ground_gap_frac r)`` from their median (``r`` frame 0's height above it) is the odd one. Clean descents
    with three or more fits (40 of stop 59's and 60's QA renders, six scenes, 256 and 512 px): at most 0.69 of that
    limit (a deep-crater approach, the rim against the floor), median 0.01."""
    fits = [f for f in frames if f.get("verdict") in (REFINED, KEPT) and f.get("ground_z_m") is not None]
    if len(fits) < 3:
        return []
    z = float(np.median([float(f["ground_z_m"]) for f in fits]))
    tol = p.ground_gap_limit(float(pose0.position[2]) - z)
    odd = [f for f in fits if abs(float(f["ground_z_m"]) - z) > tol]
    for f in odd:
        _off_the_others(f, float(f["ground_z_m"]) - z, tol)
    return odd


def _off_the_others(entry: dict[str, Any], gap: float, tol: float) -> None:
    """Mark a frame's entry ``disagrees``: its fit puts the ground ``gap`` m from where the other fits put it."""
    entry.update(
        refined=False,
        verdict=DISAGREES,
        scale_disagrees=True,
        ground_gap_m=gap,
        ground_gap_from="frames",  # not the altimeter: the pipeline's altimeter note leaves it out
        reason=f"the images put the ground {gap:+.0f} m from where the other frames' images put it, more than "
        f"{tol:.0f} m",
    )
