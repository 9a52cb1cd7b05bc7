"""Plane-sweep matching cost as a volume: one slab per (reference, other) image pair, summable over frames.

For each plane ``z_k`` the plane-induced homography (eq. 3.8, :mod:`flight_sw.homography`)
warps the other image onto the reference's pixels (reverse bilinear warp, eq. 4.1-4.3), and
the per-pixel cost is a small-support zero-mean SAD::

    C_k(x) = mean_{y in N_r(x)} | (I_1(y) - mu_1(y)) - (I_2k(y) - mu_2k(y)) |,   mu = (2m+1)^2 box mean

with ``N_r`` a ``(2r+1)^2`` square (r = 2: 5x5, Hirschmueller 2008 uses a pixelwise cost; a
small window makes the cost robust to sensor noise while keeping edges, the aggregation does
the rest). The local mean removal makes it insensitive to the brightness change between two
views of the same facet (the lunar photometric function depends on the view angle).

Costs are stored as ``uint16`` (``COST_SCALE`` per grey level, saturated at ``COST_MAX``) in a
``(D, h, w)`` slab over a region of interest of the reference image; ``valid`` marks the
(plane, pixel) entries with at least ``min_support`` of their support inside the other image (a
bilinear sample that touches the image's edge counts as outside). Several frames against the
same reference and planes are combined plane by plane by :func:`multi_cost_slab` (a weighted mean
over the frames that saw each entry; Okutomi & Kanade 1993's sum of costs over baselines,
normalised so that the overlap-edge band where only some frames see a plane is not penalised), so
only the combined slab is stored, and then handed to the aggregation (:mod:`flight_sw.sgm`).
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from protocol.pairdir import Camera, Pose

from .homography import homography_parts
from .sweep import coverage_mask
from .warping import warp_to_i1

COST_SCALE = 8.0  # uint16 units per grey level of mean absolute difference
COST_MAX = 2047  # saturation: 256 grey levels; keeps SGM sums of 8 paths inside int16
# Warped samples that read outside the other image. NaN, not a large sentinel: a bilinear sample in the
# last half pixel of the image blends its edge with the border value, and a blend of a -1e4 sentinel with
# a 1/32 weight passed a "> sentinel / 2" test as a grey level of about -170 (edge 150). Near the overlap edge that
# polluted the local mean and made the true plane's cost the worst one (tuning approach 2400/1200: DEM
# error 3-5 m in a 6 px band, against 1.3-1.5 m inside). NaN survives any blend, so "finite" is "inside".
_OUTSIDE = float("nan")


@dataclass
class CostSlab:
    """Matching costs of a set of planes over ``roi = (x0, y0, w, h)`` of the reference image."""

    cost: np.ndarray  # uint16 (D, h, w); entries that are not valid hold COST_MAX
    valid: np.ndarray  # bool (D, h, w): the support mapped inside the other image for this plane
    planes: np.ndarray  # float64 (D,) ascending elevations
    roi: tuple[int, int, int, int]
    complete: bool = True  # False: a deadline stopped it (the slab is then unusable)
    # multi-frame: float32 (h, w), per pixel the largest sum of info_f over the frames that saw one plane
    info: np.ndarray | None = None


def zero_mean(img: np.ndarray, mean_radius: int) -> np.ndarray:
    """``I - box_mean(I)`` over a ``(2m+1)^2`` square (float32)."""
    k = 2 * int(mean_radius) + 1
    return img - cv2.blur(img, (k, k), borderType=cv2.BORDER_REPLICATE)


def local_contrast(img: np.ndarray, radius: int) -> np.ndarray:
    """Grey-level standard deviation over the ``(2r+1)^2`` square around each pixel (float32)."""
    k = 2 * int(radius) + 1
    a = np.asarray(img, np.float32)
    m = cv2.blur(a, (k, k), borderType=cv2.BORDER_REPLICATE)
    m2 = cv2.blur(a * a, (k, k), borderType=cv2.BORDER_REPLICATE)
    return np.sqrt(np.maximum(m2 - m * m, 0.0)).astype(np.float32)


class _PlaneCost:
    """One (reference, other) pair's per-plane cost over ``roi``: the loop body of :func:`cost_slab`."""

    def __init__(
        self,
        ref: np.ndarray,
        other: np.ndarray,
        camera: Camera,
        pose_ref: Pose,
        pose_other: Pose,
        roi: tuple[int, int, int, int],
        radius: int,
        mean_radius: int,
        prefilter_sigma: float,
        ignore: np.ndarray | None,
        min_support: float,
    ) -> None:
        x0, y0, w, h = roi
        src: np.ndarray = np.asarray(other, np.float32)
        if prefilter_sigma > 0:
            src = cv2.GaussianBlur(src, (0, 0), prefilter_sigma, borderType=cv2.BORDER_REPLICATE)
        self.src = src
        self.roi = roi
        self.a = zero_mean(np.ascontiguousarray(ref[y0 : y0 + h, x0 : x0 + w], dtype=np.float32), mean_radius)
        self.A, self.B, self.cz = homography_parts(camera, pose_ref, pose_other)
        self.k = 2 * int(radius) + 1
        self.km = 2 * int(mean_radius) + 1
        self.keep = None if ignore is None else ~np.asarray(ignore, bool)[y0 : y0 + h, x0 : x0 + w]
        self.min_support = min_support
        self.diff = np.empty((h, w), np.float32)

    def __call__(self, z: float) -> tuple[np.ndarray, np.ndarray]:
        """Scaled, saturated cost (float32) and its valid mask (bool) for the plane ``Z = z``."""
        k, km, diff = self.k, self.km, self.diff
        warped = warp_to_i1(self.src, self.A - self.B / (self.cz - z), self.roi, _OUTSIDE)
        seen = np.isfinite(warped)
        inside = seen.astype(np.float32)
        np.copyto(warped, 0.0, where=~seen)
        # partial supports at the edge of the other image: means and sums over the samples it has
        n_m = cv2.blur(inside, (km, km), borderType=cv2.BORDER_REPLICATE)
        mu = cv2.blur(warped, (km, km), borderType=cv2.BORDER_REPLICATE) / np.maximum(n_m, 1e-6)
        cv2.absdiff(self.a, warped - mu, dst=diff)
        np.multiply(diff, inside, out=diff)
        n_c = cv2.blur(inside, (k, k), borderType=cv2.BORDER_REPLICATE)
        c = cv2.blur(diff, (k, k), borderType=cv2.BORDER_REPLICATE) / np.maximum(n_c, 1e-6)
        np.multiply(c, COST_SCALE, out=c)
        np.minimum(c, COST_MAX, out=c)
        ok = (inside > 0) & (n_c >= self.min_support) & (n_m >= self.min_support)
        if self.keep is not None:
            ok &= self.keep
        return c, ok


def cost_slab(
    ref: np.ndarray,
    other: np.ndarray,
    camera: Camera,
    pose_ref: Pose,
    pose_other: Pose,
    planes: np.ndarray,
    roi: tuple[int, int, int, int],
    *,
    radius: int = 2,
    mean_radius: int = 3,
    prefilter_sigma: float = 0.0,
    ignore: np.ndarray | None = None,
    deadline: float | None = None,
    check_every: int = 4,
    min_support: float = 0.5,
) -> CostSlab:
    """Cost slab of ``planes`` for one (reference, other) image pair (module doc).

    ``ref`` is the reference image (its pixels index the slab), ``other`` any other frame with
    its pose; ``prefilter_sigma`` low-passes ``other`` to the reference's pixel footprint
    (:func:`flight_sw.warping.area_sigma`). ``ignore`` (bool, reference size) pixels get
    ``valid = False`` on every plane. With a ``deadline`` (``time.monotonic()``) checked every
    ``check_every`` planes, a late slab comes back with ``complete = False``.
    """
    planes = np.asarray(planes, dtype=np.float64)
    x0, y0, w, h = roi
    D = planes.size
    cost = np.full((D, h, w), COST_MAX, np.uint16)
    valid = np.zeros((D, h, w), bool)
    if w <= 0 or h <= 0 or D == 0:
        return CostSlab(cost, valid, planes, roi)
    pc = _PlaneCost(
        ref, other, camera, pose_ref, pose_other, roi, radius, mean_radius, prefilter_sigma, ignore, min_support
    )
    for i, z in enumerate(planes):
        if deadline is not None and i % check_every == 0 and time.monotonic() > deadline:
            return CostSlab(cost, valid, planes, roi, complete=False)
        c, ok = pc(z)
        cost[i] = np.where(ok, c, COST_MAX)
        valid[i] = ok
    return CostSlab(cost, valid, planes, roi)


RULES = ("mean", "drop_worst")


def multi_cost_slab(
    ref: np.ndarray,
    others: Sequence[np.ndarray],
    camera: Camera,
    pose_ref: Pose,
    poses: Sequence[Pose],
    planes: np.ndarray,
    roi: tuple[int, int, int, int],
    *,
    prefilter_sigmas: Sequence[float] | None = None,
    weights: Sequence[float] | None = None,
    info: Sequence[float] | None = None,
    rule: str = "mean",
    gain: float = 1.0,
    truncate: float = 0.0,
    radius: int = 2,
    mean_radius: int = 3,
    ignore: np.ndarray | None = None,
    deadline: float | None = None,
    check_every: int = 4,
    min_support: float = 0.5,
) -> CostSlab:
    """Multi-baseline cost slab: every other frame's cost per plane, combined robustly (Okutomi & Kanade 1993).

    The planes are shared, so each frame's cost is indexed in the same plane (inverse-depth-like)
    coordinate, as in Okutomi & Kanade's SSSD-in-inverse-distance; per (plane, pixel) entry the
    costs ``C_f`` of the frames that saw it (``n`` of them, weights ``w_f``) are combined by ``rule``::

        mean:        sum_f w_f C_f / sum_f w_f
        drop_worst:  the same without the frame of the largest C_f   when n >= 3

    times ``gain``. The combined curvature at the minimum is the mean of the frames' (each
    ``~ s_f^2``, ``s_f`` = frame f's parallax per plane relative to the widest pair); ``gain`` sets
    the data term's weight against the aggregation's smoothness penalties (``gain = N``:
    Okutomi & Kanade's plain sum of costs; ``1``: one pair's scale). Normalising by the frames
    that saw the entry keeps a frame that drops out at the overlap edge from making a false minimum.

    ``drop_worst`` is a streaming form of Kang, Szeliski & Chai (2001)'s best-subset selection: a
    frame that sees an occluder, a shadow edge that moved or a specular change in front of the
    true plane is outvoted instead of averaged in. ``truncate`` (> 0, cost units) caps each
    frame's cost before it is combined (a truncated mean). Each frame is evaluated only on its
    part of ``roi``: where its image can be reached by some plane (:func:`frame_roi`); entries no
    frame saw stay ``COST_MAX`` and invalid. The loop runs planes outer, frames inner, so only
    the combined slab is ever stored. One other frame gives :func:`cost_slab`'s slab bit for bit.
    ``prefilter_sigmas`` are per frame (:func:`flight_sw.warping.area_sigma` of each GSD ratio).
    """
    if rule not in RULES:
        raise ValueError(f"rule must be one of {RULES}, got {rule!r}")
    if not (math.isfinite(gain) and gain > 0):
        raise ValueError(f"gain must be a positive number, got {gain!r}")
    if len(others) != len(poses) or not others:
        raise ValueError("need one pose per other frame, and at least one other frame")
    sig = [0.0] * len(others) if prefilter_sigmas is None else [float(v) for v in prefilter_sigmas]
    if len(sig) != len(others):
        raise ValueError("need one prefilter sigma per other frame")
    wts = [1.0] * len(others) if weights is None else [float(v) for v in weights]
    if len(wts) != len(others) or not all(math.isfinite(v) and v > 0 for v in wts):
        raise ValueError("need one positive weight per other frame")
    inf = [1.0] * len(others) if info is None else [float(v) for v in info]
    if len(inf) != len(others) or not all(math.isfinite(v) and v >= 0 for v in inf):
        raise ValueError("need one non-negative info value per other frame")
    planes = np.asarray(planes, dtype=np.float64)
    x0, y0, w, h = roi
    D = planes.size
    cost = np.full((D, h, w), COST_MAX, np.uint16)
    valid = np.zeros((D, h, w), bool)
    seen_info = np.zeros((h, w), np.float32)
    if w <= 0 or h <= 0 or D == 0:
        return CostSlab(cost, valid, planes, roi, info=seen_info)
    views: list[tuple[_PlaneCost, tuple[slice, slice], np.float32, np.float32]] = []
    for img, pose, sg, wf, nf in zip(others, poses, sig, wts, inf):
        fx0, fy0, fw, fh = frame_roi(camera, pose_ref, pose, float(planes[0]), float(planes[-1]), roi)
        if fw <= 0 or fh <= 0:
            continue
        pc = _PlaneCost(
            ref, img, camera, pose_ref, pose, (fx0, fy0, fw, fh), radius, mean_radius, sg, ignore, min_support
        )
        views.append(
            (pc, (slice(fy0 - y0, fy0 - y0 + fh), slice(fx0 - x0, fx0 - x0 + fw)), np.float32(wf), np.float32(nf))
        )
    total = np.zeros((h, w), np.float32)  # sum of w_f C_f
    wsum = np.zeros((h, w), np.float32)  # sum of w_f
    worst = np.zeros((h, w), np.float32)  # the largest C_f and its weight (drop_worst)
    worst_w = np.zeros((h, w), np.float32)
    count = np.zeros((h, w), np.float32)  # frames that saw the entry
    plane_info = np.zeros((h, w), np.float32)  # sum of their info
    for i, z in enumerate(planes):
        if deadline is not None and i % check_every == 0 and time.monotonic() > deadline:
            return CostSlab(cost, valid, planes, roi, complete=False, info=seen_info)
        for a in (total, wsum, worst, worst_w, count, plane_info):
            a.fill(0.0)
        for pc, (rs, cs), wt, nfo in views:
            c, ok = pc(z)
            if truncate > 0:
                np.minimum(c, np.float32(truncate), out=c)
            okf = ok.astype(np.float32)
            cw = c * okf
            if wt != 1.0:
                okf *= wt
            total[rs, cs] += cw if wt == 1.0 else cw * wt
            wsum[rs, cs] += okf
            count[rs, cs] += ok
            plane_info[rs, cs] += ok * nfo
            if rule == "drop_worst":
                worse = cw > worst[rs, cs]
                worst[rs, cs][worse] = cw[worse]
                worst_w[rs, cs][worse] = wt
        if rule == "drop_worst":
            drop = count >= 3
            total -= worst * worst_w * drop
            wsum -= worst_w * drop
        seen = count > 0
        mean = total / np.where(wsum > 0, wsum, np.float32(1.0))
        if gain != 1.0:
            np.minimum(mean * np.float32(gain), COST_MAX, out=mean)
        cost[i] = np.where(seen, mean, COST_MAX)
        valid[i] = seen
        np.maximum(seen_info, plane_info, out=seen_info)
    return CostSlab(cost, valid, planes, roi, info=seen_info)


def parallax_px(
    camera: Camera, pose_ref: Pose, pose: Pose, z_lo: float, z_hi: float, roi: tuple[int, int, int, int], n: int = 9
) -> float:
    """Median image motion, in reference pixels, of a reference pixel's match in ``pose``'s image from
    plane ``z_lo`` to ``z_hi`` (0 if no probe is seen): how much depth signal the frame carries.

    Over an ``n x n`` probe grid of ``roi``, the match moves by ``|x(z_hi) - x(z_lo)|`` frame pixels;
    dividing by the local scale ``sqrt(|det J|)`` of the mid-plane homography (frame pixels per
    reference pixel) puts every frame on the reference's pixel scale.
    """
    x0, y0, w, h = roi
    if w <= 0 or h <= 0:
        return 0.0
    ug, vg = np.meshgrid(np.linspace(x0, x0 + w - 1, n), np.linspace(y0, y0 + h - 1, n))
    u, v = ug.ravel(), vg.ravel()
    A, B, cz = homography_parts(camera, pose_ref, pose)

    def mapped(z: float) -> tuple[np.ndarray, np.ndarray]:
        H = A - B / (cz - z)
        q = H @ np.stack([u, v, np.ones_like(u)])
        return q[0] / q[2], q[1] / q[2]

    z_mid = 0.5 * (z_lo + z_hi)
    ua, va = mapped(z_lo)
    ub, vb = mapped(z_hi)
    um, vm = mapped(z_mid)
    # local scale: the mid-plane homography's Jacobian by finite differences (1 px steps)
    Hm = A - B / (cz - z_mid)

    def at(du: float, dv: float) -> tuple[np.ndarray, np.ndarray]:
        q = Hm @ np.stack([u + du, v + dv, np.ones_like(u)])
        return q[0] / q[2], q[1] / q[2]

    (ux, vx), (uy, vy) = at(1.0, 0.0), at(0.0, 1.0)
    det = np.abs((ux - um) * (vy - vm) - (uy - um) * (vx - vm))
    seen = (um >= 0) & (um <= camera.width - 1) & (vm >= 0) & (vm <= camera.height - 1) & (det > 1e-12)
    if not seen.any():
        return 0.0
    move = np.hypot(ub - ua, vb - va) / np.sqrt(np.where(seen, det, 1.0))
    return float(np.median(move[seen]))


def frame_roi(
    camera: Camera, pose_ref: Pose, pose: Pose, z_lo: float, z_hi: float, within: tuple[int, int, int, int]
) -> tuple[int, int, int, int]:
    """The part of ``within`` (a reference-image box) whose pixels see ``pose``'s image for some plane."""
    reach = coverage_mask(camera, pose_ref, pose, z_lo, z_hi, mode="any")
    x0, y0, w, h = within
    sub = reach[y0 : y0 + h, x0 : x0 + w]
    rows, cols = np.flatnonzero(sub.any(axis=1)), np.flatnonzero(sub.any(axis=0))
    if rows.size == 0:
        return x0, y0, 0, 0
    return int(x0 + cols[0]), int(y0 + rows[0]), int(cols[-1] - cols[0] + 1), int(rows[-1] - rows[0] + 1)


def valid_interval(valid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel, the first and last plane index its support saw (``-1, -1`` if none).

    The image of a pixel in the other view moves along a straight epipolar segment as the
    plane moves and the image is convex, so the planes it sees form one interval.
    """
    D = valid.shape[0]
    anyv = valid.any(axis=0)
    lo = np.where(anyv, valid.argmax(axis=0), -1).astype(np.int32)
    hi = np.where(anyv, D - 1 - valid[::-1].argmax(axis=0), -1).astype(np.int32)
    return lo, hi
