"""Guided feature matching for the relative pose refinement (:mod:`flight_sw.pose_refine`, step 1).

i2 is warped onto i1 through the navigation's homography of the reference
plane, which removes the descent's ~2x scale change, so a binary detector
(ORB, Rublee et al. 2011; or SIFT, Lowe 2004; AKAZE) matches with Lowe's ratio
test and a mutual check. Shi-Tomasi corners (1994) are then tracked by
pyramidal Lucas-Kanade with a forward-backward check (Kalal et al. 2010) on
high-passed images (``a - G_sigma * a``): LK assumes constant brightness, and
two views at different ranges differ smoothly in it.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import cv2
import numpy as np

from protocol.pairdir import Camera

if TYPE_CHECKING:  # the knobs live with the block that owns them; a runtime import would be circular
    from .pose_refine import RefineParams


def gray8(img: np.ndarray) -> np.ndarray:
    """8-bit copy for the detectors and LK; float images in [0, 1] are taken as 0..255."""
    a = np.asarray(img)
    if a.dtype == np.uint8:
        return a
    f = a.astype(np.float32)
    if f.size and float(f.max()) <= 1.0:
        f = f * 255.0
    return np.clip(np.rint(f), 0, 255).astype(np.uint8)


def _overlap(camera: Camera, H: np.ndarray, margin: int) -> tuple[np.ndarray, tuple[int, int, int, int]]:
    """i1 pixels whose image through ``H`` (i1 -> i2) lies inside i2 by ``margin`` px, and its bounding box."""
    w, h = camera.width, camera.height
    ones = np.full((h, w), 255, np.uint8)
    inside = cv2.warpPerspective(
        ones, H, (w, h), flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_CONSTANT
    )
    if margin > 0:
        inside = cv2.erode(inside, np.ones((2 * margin + 1, 2 * margin + 1), np.uint8))
    x0, y0, w, h = cv2.boundingRect(inside)
    return inside > 0, (int(x0), int(y0), int(w), int(h))


def _warp(src: np.ndarray, H: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """``out[v, u] = src(H [u, v, 1])``, bilinear, border replicated (keeps LK pyramids out of black)."""
    return cv2.warpPerspective(
        src, H, (shape[1], shape[0]), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_REPLICATE
    )


def prewarp(
    b2: np.ndarray, H: np.ndarray, camera: Camera, margin: int
) -> tuple[np.ndarray, tuple[int, int, int, int], np.ndarray]:
    """i2 warped onto i1 through ``H`` over the overlap's bounding box: (mask, roi, image), both ROI-local."""
    mask, roi = _overlap(camera, H, margin)
    x0, y0, w, h = roi
    if w == 0 or h == 0:
        return mask[0:0, 0:0], roi, np.zeros((0, 0), np.uint8)
    return mask[y0 : y0 + h, x0 : x0 + w], roi, _warp(b2, H @ shift_h(x0, y0), (h, w))


def _detector(name: str, n: int) -> Any:
    # the OpenCV 5 type stubs omit the feature factories
    if name == "sift":
        return cv2.SIFT_create(nfeatures=n, contrastThreshold=0.01)  # type: ignore[attr-defined]
    if name == "akaze":
        return cv2.AKAZE_create(threshold=1e-4)  # type: ignore[attr-defined]
    return cv2.ORB_create(  # type: ignore[attr-defined]
        nfeatures=n, scaleFactor=1.2, nlevels=4, edgeThreshold=15, patchSize=15, fastThreshold=5
    )


def _strongest(found: tuple[Any, np.ndarray | None], n: int) -> tuple[Any, np.ndarray | None]:
    """The ``n`` keypoints of highest response. ORB keeps more than ``nfeatures`` when responses tie (a regular
    dot grid gave 8192^2 / 35 of them), and a matcher refuses more than 2^18 rows with an assertion."""
    keys, desc = found
    if desc is None or len(keys) <= n:
        return keys, desc
    keep = np.argsort([-k.response for k in keys], kind="stable")[:n]
    return [keys[i] for i in keep], desc[keep]


def descriptor_matches(
    a: np.ndarray, b: np.ndarray, mask: np.ndarray, detector: str, n: int, ratio: float
) -> tuple[np.ndarray, np.ndarray]:
    """Detector matches ``a -> b`` inside ``mask``: Lowe's ratio test and a mutual (cross) check. Nx2 each."""
    det = _detector(detector, n)
    m8 = mask.astype(np.uint8) * 255
    ka, da = _strongest(det.detectAndCompute(a, m8), n)
    kb, db = _strongest(det.detectAndCompute(b, m8), n)
    if da is None or db is None or len(ka) < 2 or len(kb) < 2:
        return np.zeros((0, 2)), np.zeros((0, 2))
    norm = cv2.NORM_L2 if detector == "sift" else cv2.NORM_HAMMING
    bf = cv2.BFMatcher(norm)
    fwd = bf.knnMatch(da, db, k=2)
    back = {m[0].queryIdx: m[0].trainIdx for m in bf.knnMatch(db, da, k=1) if m}
    pairs = [
        (m[0].queryIdx, m[0].trainIdx)
        for m in fwd
        if len(m) == 2 and m[0].distance < ratio * m[1].distance and back.get(m[0].trainIdx) == m[0].queryIdx
    ]
    if not pairs:
        return np.zeros((0, 2)), np.zeros((0, 2))
    pa = np.array([ka[i].pt for i, _ in pairs], np.float64)
    pb = np.array([kb[j].pt for _, j in pairs], np.float64)
    return pa, pb


def corners_in(a: np.ndarray, mask: np.ndarray, p: RefineParams, min_distance: float) -> np.ndarray:
    """Shi-Tomasi corners of ``a`` inside ``mask`` (Nx2, float64)."""
    pts = cv2.goodFeaturesToTrack(
        a, p.n_corners, p.corner_quality, max(1.0, min_distance), mask=mask.astype(np.uint8) * 255, blockSize=7
    )
    return np.zeros((0, 2)) if pts is None else pts.reshape(-1, 2).astype(np.float64)


def highpass(a: np.ndarray, sigma: float) -> np.ndarray:
    """``128 + 2 (a - G_sigma * a)`` as 8-bit (``a`` itself when ``sigma`` <= 0): brightness that varies
    slowly between two views (exposure, lunar-Lambert emission angle) leaves what LK tracks unchanged."""
    if sigma <= 0:
        return a
    f = a.astype(np.float32)
    g = f - cv2.GaussianBlur(f, (0, 0), sigma, borderType=cv2.BORDER_REPLICATE)
    return np.clip(128.0 + 2.0 * g, 0, 255).astype(np.uint8)


def track(a: np.ndarray, b: np.ndarray, pts: np.ndarray, p: RefineParams) -> tuple[np.ndarray, np.ndarray]:
    """Pyramidal Lucas-Kanade ``a -> b`` of ``pts``; kept (bool mask) where tracking back lands within ``fb_max_px``."""
    if len(pts) == 0:
        return np.zeros(0, bool), np.zeros((0, 2))
    p0 = pts.astype(np.float32).reshape(-1, 1, 2)
    crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01)
    win = (p.track_window, p.track_window)
    lk = {"winSize": win, "maxLevel": p.track_levels, "criteria": crit}
    fwd, st1, _ = cv2.calcOpticalFlowPyrLK(a, b, p0, p0.copy(), **lk)  # type: ignore[call-overload]
    bwd, st2, _ = cv2.calcOpticalFlowPyrLK(b, a, fwd, p0.copy(), **lk)  # type: ignore[call-overload]
    fb = np.linalg.norm((bwd - p0).reshape(-1, 2), axis=1)
    ok = (st1.ravel() == 1) & (st2.ravel() == 1) & (fb < p.fb_max_px)
    return ok, fwd.reshape(-1, 2).astype(np.float64)


def apply_h(H: np.ndarray, u: np.ndarray) -> np.ndarray:
    x = np.c_[u, np.ones(len(u))] @ H.T
    return np.asarray(x[:, :2] / x[:, 2:3])


def shift_h(x: float, y: float) -> np.ndarray:
    return np.array([[1.0, 0.0, x], [0.0, 1.0, y], [0.0, 0.0, 1.0]])
