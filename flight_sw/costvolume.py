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
(plane, pixel) entries whose whole support sampled inside the other image. Slabs of several
frames against the same reference and planes are combined by :func:`combine` (mean over the
frames that saw each entry; Okutomi & Kanade 1993's sum of costs over baselines, normalised
so that the overlap-edge band where only some frames see a plane is not penalised) and then
handed to the aggregation (:mod:`flight_sw.sgm`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import cv2
import numpy as np

from protocol.pairdir import Camera, Pose

from .homography import homography_parts
from .warping import warp_to_i1

COST_SCALE = 8.0  # uint16 units per grey level of mean absolute difference
COST_MAX = 2047  # saturation: 256 grey levels; keeps SGM sums of 8 paths inside int16
_OUTSIDE = -1.0e4  # warped samples from outside the other image


@dataclass
class CostSlab:
    """Matching costs of a set of planes over ``roi = (x0, y0, w, h)`` of the reference image."""

    cost: np.ndarray  # uint16 (D, h, w); entries that are not valid hold COST_MAX
    valid: np.ndarray  # bool (D, h, w): the support mapped inside the other image for this plane
    planes: np.ndarray  # float64 (D,) ascending elevations
    roi: tuple[int, int, int, int]
    complete: bool = True  # False: a deadline stopped it (the slab is then unusable)


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
    src: np.ndarray = np.asarray(other, np.float32)
    if prefilter_sigma > 0:
        src = cv2.GaussianBlur(src, (0, 0), prefilter_sigma, borderType=cv2.BORDER_REPLICATE)
    a = zero_mean(np.ascontiguousarray(ref[y0 : y0 + h, x0 : x0 + w], dtype=np.float32), mean_radius)
    A, B, cz = homography_parts(camera, pose_ref, pose_other)
    k = 2 * int(radius) + 1
    km = 2 * int(mean_radius) + 1
    keep = None if ignore is None else ~np.asarray(ignore, bool)[y0 : y0 + h, x0 : x0 + w]
    diff = np.empty((h, w), np.float32)
    for i, z in enumerate(planes):
        if deadline is not None and i % check_every == 0 and time.monotonic() > deadline:
            return CostSlab(cost, valid, planes, roi, complete=False)
        warped = warp_to_i1(src, A - B / (cz - z), roi, _OUTSIDE)
        inside = (warped > _OUTSIDE * 0.5).astype(np.float32)
        np.multiply(warped, inside, out=warped)
        # partial supports at the edge of the other image: means and sums over the samples it has
        n_m = cv2.blur(inside, (km, km), borderType=cv2.BORDER_REPLICATE)
        mu = cv2.blur(warped, (km, km), borderType=cv2.BORDER_REPLICATE) / np.maximum(n_m, 1e-6)
        cv2.absdiff(a, warped - mu, dst=diff)
        np.multiply(diff, inside, out=diff)
        n_c = cv2.blur(inside, (k, k), borderType=cv2.BORDER_REPLICATE)
        c = cv2.blur(diff, (k, k), borderType=cv2.BORDER_REPLICATE) / np.maximum(n_c, 1e-6)
        np.multiply(c, COST_SCALE, out=c)
        np.minimum(c, COST_MAX, out=c)
        ok = (inside > 0) & (n_c >= min_support) & (n_m >= min_support)
        if keep is not None:
            ok &= keep
        cost[i] = np.where(ok, c, COST_MAX)
        valid[i] = ok
    return CostSlab(cost, valid, planes, roi)


def combine(slabs: list[CostSlab]) -> CostSlab:
    """Mean cost over the slabs that saw each (plane, pixel) entry (same planes and roi required).

    ``sum_f valid_f C_f / sum_f valid_f``; entries no frame saw stay ``COST_MAX`` and invalid.
    One slab is returned unchanged.
    """
    if not slabs:
        raise ValueError("combine needs at least one slab")
    if len(slabs) == 1:
        return slabs[0]
    ref = slabs[0]
    for s in slabs[1:]:
        if s.roi != ref.roi or s.planes.shape != ref.planes.shape or not np.allclose(s.planes, ref.planes):
            raise ValueError("slabs must share planes and roi")
    total = np.zeros(ref.cost.shape, np.uint32)
    count = np.zeros(ref.cost.shape, np.uint8)
    for s in slabs:
        total += np.where(s.valid, s.cost, 0).astype(np.uint32)
        count += s.valid
    valid = count > 0
    mean = np.where(valid, total // np.maximum(count, 1), COST_MAX).astype(np.uint16)
    return CostSlab(mean, valid, ref.planes, ref.roi, all(s.complete for s in slabs))


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
