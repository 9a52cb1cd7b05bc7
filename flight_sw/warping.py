"""Image warping (thesis sec 4.2, eq. 4.1-4.3): resample i2 onto i1's pixel grid.

Reverse mapping: each i1 pixel ``x1`` reads ``I2(H x1)`` with bilinear
interpolation. The lower image i2 is sampled about twice as finely as i1, so
before warping it is optionally low-passed and decimated to i1's sampling
(``prefilter_levels`` Gaussian-pyramid steps); the homography is then composed
with the decimation ``u' = u / 2^L`` (cv2.pyrDown keeps pixel 2j at j).
"""

from __future__ import annotations

import math

import cv2
import numpy as np


def prefilter_levels(scale: float) -> int:
    """Pyramid levels that bring i2 to i1's sampling; ``scale`` = GSD(i2) / GSD(i1) (~0.5)."""
    if not scale > 0:
        raise ValueError(f"scale must be positive, got {scale}")
    return max(0, int(round(math.log2(1.0 / scale))))


def prefilter(img: np.ndarray, levels: int) -> tuple[np.ndarray, np.ndarray]:
    """Low-pass and decimate ``levels`` times; return the float32 image and the 3x3 map S: full -> reduced."""
    out: np.ndarray = img.astype(np.float32)
    for _ in range(levels):
        out = cv2.pyrDown(out)
    s = 0.5**levels
    return out, np.diag([s, s, 1.0])


MAX_AREA_SIGMA = 64.0  # i2 pixels: a GSD ratio of 1/220 (a 2:1 descent pair needs 0.5)


def area_sigma(scale: float) -> float:
    """Gaussian sigma (i2 pixels) that turns i2's pixel integration into i1's.

    An i1 pixel integrates a box ``1/scale`` i2 pixels wide, an i2 pixel a box
    1 wide; matching second moments gives ``sigma^2 = (1/scale^2 - 1) / 12``,
    at most ``MAX_AREA_SIGMA`` (a camera 10^7 times farther asked OpenCV for a
    kernel it could not allocate; past a few hundred pixels nothing is left to match).
    """
    if not 0 < scale <= 1:
        return 0.0
    return min(math.sqrt((1.0 / scale**2 - 1.0) / 12.0), MAX_AREA_SIGMA)


def area_prefilter(img: np.ndarray, scale: float) -> np.ndarray:
    """Blur i2 (float32, full resolution) so its footprint matches i1's pixels (see :func:`area_sigma`)."""
    out: np.ndarray = img.astype(np.float32)
    sigma = area_sigma(scale)
    if sigma > 0:
        out = cv2.GaussianBlur(out, (0, 0), sigma, borderType=cv2.BORDER_REPLICATE)
    return out


def warp_to_i1(src: np.ndarray, H: np.ndarray, roi: tuple[int, int, int, int], border_value: float = 0.0) -> np.ndarray:
    """Bilinear reverse warp: ``out[r, c] = src(H [c + x0, r + y0, 1])`` over ``roi = (x0, y0, w, h)``.

    Samples falling outside ``src`` take ``border_value``. ``H`` maps i1 pixels to
    ``src`` pixels (compose with the prefilter map first).
    """
    x0, y0, w, h = roi
    T = np.array([[1.0, 0.0, x0], [0.0, 1.0, y0], [0.0, 0.0, 1.0]])
    return cv2.warpPerspective(
        src,
        H @ T,
        (w, h),
        flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=float(border_value),
    )


def bilinear_sample(img: np.ndarray, u: np.ndarray, v: np.ndarray, fill: float = np.nan) -> np.ndarray:
    """Reference bilinear interpolation (eq. 4.3) in plain numpy; ``fill`` outside the image."""
    img = np.asarray(img, dtype=np.float64)
    h, w = img.shape
    u0 = np.floor(u).astype(np.int64)
    v0 = np.floor(v).astype(np.int64)
    fu, fv = u - u0, v - v0
    inside = (u >= 0) & (v >= 0) & (u <= w - 1) & (v <= h - 1)
    u0c, v0c = np.clip(u0, 0, w - 1), np.clip(v0, 0, h - 1)
    u1c, v1c = np.clip(u0 + 1, 0, w - 1), np.clip(v0 + 1, 0, h - 1)
    val = (
        (1 - fu) * (1 - fv) * img[v0c, u0c]
        + fu * (1 - fv) * img[v0c, u1c]
        + (1 - fu) * fv * img[v1c, u0c]
        + fu * fv * img[v1c, u1c]
    )
    return np.where(inside, val, fill)
