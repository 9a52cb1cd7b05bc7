"""Plane sweep: DEM recovery by warping i2 through horizontal planes and correlating (thesis sec 3.3, 4.2).

For each elevation ``z_k`` the plane-induced homography ``H_k`` (eq. 3.8,
:func:`plane_homography`) warps i2 onto i1; the window cost (SAD/SSD, eq.
3.13/3.14) is box-filtered and each pixel keeps the plane of lowest cost,
refined with a parabola through its neighbours (eq. 3.15). The cost volume is
never stored: the loop keeps, per pixel, the running best cost, its plane
index, and the costs of the planes just before and after it.

Only the region of i1 that can see i2 (for some plane in the range) is swept.
Samples warped from outside i2 take a value far outside the intensity range,
so planes that leave the image lose; the final validity test is geometric
(the window around a pixel must map inside i2 through every swept plane).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import cv2
import numpy as np

from protocol.pairdir import Camera, Pose

from .correlation import parabolic_offset, pixel_cost, window_sum
from .homography import homography_parts, map_points, plane_homography
from .validate import FlightInputError
from .warping import warp_to_i1

__all__ = [
    "SweepResult",
    "coverage_mask",
    "plane_homography",
    "planes_uniform_disparity",
    "planes_uniform_dz",
    "scaled_camera",
    "sweep_dem",
]

# Out-of-image samples read this value: any difference to it exceeds every in-image difference.
_OUTSIDE = 1000.0


@dataclass
class SweepResult:
    """Outcome of one sweep. ``elevation`` is NaN where not recovered."""

    elevation: np.ndarray  # float32 HxW world Z
    best_cost: np.ndarray  # float32 HxW, NaN where not swept
    planes: np.ndarray  # the elevations swept
    planes_done: int
    complete: bool  # False if the deadline stopped the loop
    roi: tuple[int, int, int, int]
    curvature: np.ndarray | None = None  # float32 HxW (C_{k-1} + C_{k+1} - 2 C_k) / C_k at the best plane
    range_end: np.ndarray | None = None  # bool HxW: the minimum fell on the first or last plane


def scaled_camera(camera: Camera, level: int) -> Camera:
    """Camera of a pyramid level (cv2.pyrDown keeps pixel 2j at j: ``u' = u / 2``)."""
    s = 0.5**level
    return Camera(
        (camera.width + (1 << level) - 1) >> level,
        (camera.height + (1 << level) - 1) >> level,
        camera.fx * s,
        camera.fy * s,
        camera.cx * s,
        camera.cy * s,
    )


def planes_uniform_dz(z_min: float, z_max: float, dz: float) -> np.ndarray:
    """Elevations ``z_min, z_min + dz, ... <= z_max`` (the thesis's uniform step, sec 4.3)."""
    if not dz > 0 or not z_max > z_min:
        raise ValueError(f"need dz > 0 and z_max > z_min, got dz={dz}, range [{z_min}, {z_max}]")
    n = int(np.floor((z_max - z_min) / dz + 1e-9)) + 1
    return z_min + dz * np.arange(n)


def _probe_grid(camera: Camera, n: int = 9) -> tuple[np.ndarray, np.ndarray]:
    u, v = np.meshgrid(np.linspace(0, camera.width - 1, n), np.linspace(0, camera.height - 1, n))
    return u.ravel(), v.ravel()


def planes_uniform_disparity(
    camera: Camera, pose1: Pose, pose2: Pose, z_min: float, z_max: float, step_px: float, scale: float = 1.0
) -> np.ndarray:
    """Elevations spaced so that no covered i1 pixel moves more than ``step_px`` in the warped image
    between adjacent planes.

    The displacement of ``x2 = H(z) x1`` per unit z grows toward the image edge
    (eq. 3.12: disparity ~ d/Z * distance from centre), so a step uniform in
    pixels is non-uniform in metres. ``scale`` converts i2 pixels to the warped
    source's pixels (0.5**levels after prefiltering). Computed on a dense z grid
    over a 9x9 probe grid of i1 pixels that see i2.
    """
    if not step_px > 0 or not z_max > z_min:
        raise ValueError(f"need step_px > 0 and z_max > z_min, got {step_px}, [{z_min}, {z_max}]")
    A, B, cz = homography_parts(camera, pose1, pose2)
    zs = np.linspace(z_min, z_max, 2001)
    u, v = _probe_grid(camera)
    x = np.stack([u, v, np.ones_like(u)])  # 3 x P
    inv_d = (1.0 / (cz - zs))[:, None, None]  # Z x 1 x 1
    h = (A @ x)[None] - inv_d * (B @ x)[None]  # Z x 3 x P, H(z) = A - B / d(z)
    pos = h[:, :2] / h[:, 2:3]
    mid = pos[zs.size // 2]
    seen = (mid[0] >= 0) & (mid[0] <= camera.width - 1) & (mid[1] >= 0) & (mid[1] <= camera.height - 1)
    if not seen.any():
        seen[:] = True
    step = np.hypot(*np.diff(pos[:, :, seen], axis=0).transpose(1, 0, 2)).max(axis=1) * scale
    arc = np.concatenate([[0.0], np.cumsum(step)])
    if not np.all(np.isfinite(arc)):
        raise FlightInputError("the poses and camera give no finite image motion between planes (check them)")
    n = max(3, int(np.ceil(arc[-1] / step_px)) + 1)  # a sweep needs three planes, however short the baseline
    return np.interp(np.linspace(0.0, arc[-1], n), arc, zs)


def _inside(
    camera: Camera,
    H: np.ndarray,
    u: np.ndarray,
    v: np.ndarray,
    z_map: np.ndarray | None = None,
    parts: tuple | None = None,
) -> np.ndarray:
    if z_map is None:
        u2, v2 = map_points(H, u, v)
    else:  # per-pixel plane: H(z) = A - B / (C1z - z)
        assert parts is not None
        A, B, cz = parts
        inv_d = 1.0 / (cz - z_map)
        hu = (A[0, 0] - B[0, 0] * inv_d) * u + (A[0, 1] - B[0, 1] * inv_d) * v + (A[0, 2] - B[0, 2] * inv_d)
        hv = (A[1, 0] - B[1, 0] * inv_d) * u + (A[1, 1] - B[1, 1] * inv_d) * v + (A[1, 2] - B[1, 2] * inv_d)
        hw = (A[2, 0] - B[2, 0] * inv_d) * u + (A[2, 1] - B[2, 1] * inv_d) * v + (A[2, 2] - B[2, 2] * inv_d)
        u2, v2 = hu / hw, hv / hw
    return (u2 >= 0) & (u2 <= camera.width - 1) & (v2 >= 0) & (v2 <= camera.height - 1)


def _inside_polygon(camera: Camera, H: np.ndarray) -> np.ndarray:
    """i1 pixels that ``H`` maps inside i2: the convex quadrilateral ``H^-1`` (i2 rectangle), rasterised."""
    w, h = camera.width, camera.height
    corners = np.array([[0, 0, 1], [w - 1, 0, 1], [w - 1, h - 1, 1], [0, h - 1, 1]], dtype=np.float64).T
    q = np.linalg.inv(H) @ corners
    mask: np.ndarray = np.zeros((h, w), np.uint8)
    if np.all(q[2] > 0) or np.all(q[2] < 0):
        pts = np.round(16 * (q[:2] / q[2]).T).astype(np.int64)
        pts = np.clip(pts, -(1 << 24), 1 << 24).astype(np.int32)  # far-away corners: keep fixed point sane
        cv2.fillConvexPoly(mask, pts, 1, lineType=cv2.LINE_8, shift=4)
        mask = cv2.erode(mask, np.ones((3, 3), np.uint8))  # the fill includes edge-touching pixels
    else:  # the quadrilateral wraps through infinity: fall back to the per-pixel test
        v, u = np.mgrid[0:h, 0:w].astype(np.float64)
        return _inside(camera, H, u, v)
    return mask.astype(bool)


def coverage_mask(
    camera: Camera, pose1: Pose, pose2: Pose, z_lo: float, z_hi: float | None = None, mode: str = "all"
) -> np.ndarray:
    """i1 pixels that map inside i2 for the planes ``z_lo`` and ``z_hi``.

    A pixel's image in i2 moves along a straight epipolar segment as z varies and
    the image is convex, so inside at both ends means inside for every plane in
    between (``mode="all"``); ``mode="any"`` is the union. Each mask is the
    rasterised quadrilateral ``H^-1`` (i2's rectangle), not a per-pixel test.
    """
    a = _inside_polygon(camera, plane_homography(camera, pose1, pose2, z_lo))
    if z_hi is None or z_hi == z_lo:
        return a
    b = _inside_polygon(camera, plane_homography(camera, pose1, pose2, z_hi))
    return (a & b) if mode == "all" else (a | b)


def _roi(mask: np.ndarray, pad: int) -> tuple[int, int, int, int]:
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    if rows.size == 0:
        return 0, 0, 0, 0
    h, w = mask.shape
    y0, y1 = max(0, rows[0] - pad), min(h, rows[-1] + 1 + pad)
    x0, x1 = max(0, cols[0] - pad), min(w, cols[-1] + 1 + pad)
    return int(x0), int(y0), int(x1 - x0), int(y1 - y0)


def sweep_dem(
    i1: np.ndarray,
    i2: np.ndarray,
    camera: Camera,
    pose1: Pose,
    pose2: Pose,
    planes: np.ndarray,
    *,
    half_window: int = 8,
    cost: str = "sad",
    prefilter_sigma: float = 0.0,
    ignore: np.ndarray | None = None,
    deadline: float | None = None,
    check_every: int = 4,
    end_erosion: int | None = None,
) -> SweepResult:
    """Sweep ``planes`` (ascending elevations) and return the per-pixel elevation of i1.

    ``prefilter_sigma`` (i2 pixels, see :func:`flight_sw.warping.area_sigma`) low-passes
    i2 before warping. ``ignore`` (bool HxW, e.g. the rock mask) pixels contribute nothing to any
    window and get NaN (thesis sec 4.2). ``deadline`` is a ``time.monotonic()``
    value checked every ``check_every`` planes; if it passes, the sweep stops
    with ``complete=False`` and an all-NaN elevation. Pixels within ``end_erosion``
    (default W) of a range-end minimum are rejected.
    """
    planes = np.asarray(planes, dtype=np.float64)
    H_img, W_img = i1.shape
    nan_img = np.full(i1.shape, np.nan, np.float32)
    if planes.size < 3 or np.any(np.diff(planes) <= 0):
        raise ValueError("planes must be >= 3 strictly increasing elevations")
    W = int(half_window)
    reach = coverage_mask(camera, pose1, pose2, planes[0], planes[-1], mode="any")
    roi = _roi(reach, W)
    x0, y0, rw, rh = roi
    if rw <= 2 * W or rh <= 2 * W:
        return SweepResult(nan_img, nan_img.copy(), planes, 0, True, roi)
    src: np.ndarray = i2.astype(np.float32)
    if prefilter_sigma > 0:  # low-pass i2 to i1's pixel footprint (warping.area_sigma)
        src = cv2.GaussianBlur(src, (0, 0), prefilter_sigma, borderType=cv2.BORDER_REPLICATE)
    a = np.ascontiguousarray(i1[y0 : y0 + rh, x0 : x0 + rw], dtype=np.float32)
    keep = None
    if ignore is not None and ignore.any():
        keep = (~ignore[y0 : y0 + rh, x0 : x0 + rw]).astype(np.float32)
    A, B, cz = homography_parts(camera, pose1, pose2)
    shape = (rh, rw)
    best = np.full(shape, np.inf, np.float32)
    best_k = np.full(shape, -1, np.int32)
    c_before = np.zeros(shape, np.float32)
    c_after = np.zeros(shape, np.float32)
    prev = np.zeros(shape, np.float32)
    cur = np.empty(shape, np.float32)
    diff = np.empty(shape, np.float32)
    better = np.empty(shape, bool)
    done = 0
    for k, z in enumerate(planes):
        if deadline is not None and k % check_every == 0 and time.monotonic() > deadline:
            return SweepResult(nan_img, nan_img.copy(), planes, done, False, roi)
        warped = warp_to_i1(src, A - B / (cz - z), roi, _OUTSIDE)
        pixel_cost(a, warped, cost, out=diff)
        if keep is not None:
            np.multiply(diff, keep, out=diff)
        window_sum(diff, W, out=cur)
        if k > 0:
            np.copyto(c_after, cur, where=(best_k == k - 1))
        np.less(cur, best, out=better)
        np.copyto(best, cur, where=better)
        np.copyto(best_k, k, where=better)
        np.copyto(c_before, prev, where=better)
        prev, cur = cur, prev
        done += 1
    n = planes.size
    interior = (best_k > 0) & (best_k < n - 1)
    frac = best_k + parabolic_offset(c_before, best, c_after)
    z_roi = np.interp(frac.ravel(), np.arange(n), planes).reshape(shape).astype(np.float32)
    # Valid only where the whole window maps inside i2 for EVERY swept plane: near the edge of
    # i2's view, out-of-image samples penalise some planes, which would bias the choice.
    seen = coverage_mask(camera, pose1, pose2, planes[0], planes[-1], mode="all")[y0 : y0 + rh, x0 : x0 + rw]
    # A minimum on the first or last plane means no interior minimum (ambiguous or out of range);
    # window neighbours share most of that window, so they are rejected too (window-sized erosion).
    box = np.ones((2 * W + 1, 2 * W + 1), np.uint8)
    ok = cv2.erode(seen.astype(np.uint8), box, borderType=cv2.BORDER_CONSTANT, borderValue=0).astype(bool)
    E = W if end_erosion is None else int(end_erosion)
    ok &= cv2.erode(
        interior.astype(np.uint8), np.ones((2 * E + 1, 2 * E + 1), np.uint8), borderType=cv2.BORDER_REPLICATE
    ).astype(bool)
    if keep is not None:
        ok &= keep > 0
    elev = nan_img.copy()
    elev[y0 : y0 + rh, x0 : x0 + rw] = np.where(ok, z_roi, np.nan)
    bc = nan_img.copy()
    bc[y0 : y0 + rh, x0 : x0 + rw] = np.where(ok, best, np.nan)
    curv = nan_img.copy()
    with np.errstate(divide="ignore", invalid="ignore"):
        curv[y0 : y0 + rh, x0 : x0 + rw] = (c_before + c_after - 2 * best) / np.maximum(best, 1e-6)
    ends = np.zeros(i1.shape, bool)
    ends[y0 : y0 + rh, x0 : x0 + rw] = ~interior
    return SweepResult(elev, bc, planes, done, True, roi, curv, ends)
