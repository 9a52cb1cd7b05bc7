"""Window correlation costs (thesis sec 3.3.1, eq. 3.13-3.15) via O(1)-per-pixel box filters.

SAD: ``C(x, y) = sum_{window} |I1 - I2k|``;  SSD: ``sum_{window} (I1 - I2k)^2``,
window ``(2W+1)^2``. Box sums accumulate in double inside OpenCV, so a single
huge out-of-image sample does not disturb its neighbours' sums.
"""

from __future__ import annotations

import cv2
import numpy as np

COSTS = ("sad", "ssd")


def pixel_cost(i1: np.ndarray, i2w: np.ndarray, cost: str = "sad", out: np.ndarray | None = None) -> np.ndarray:
    """Per-pixel dissimilarity ``|I1 - I2k|`` (sad) or ``(I1 - I2k)^2`` (ssd), float32."""
    out = cv2.absdiff(i1, i2w, dst=out)
    if cost == "ssd":
        cv2.multiply(out, out, dst=out)
    elif cost != "sad":
        raise ValueError(f"cost must be one of {COSTS}, got {cost!r}")
    return out


def window_sum(img: np.ndarray, half_window: int, out: np.ndarray | None = None) -> np.ndarray:
    """Unnormalised (2W+1)^2 box sum; pixels closer than W to the border are NaN-free but partial
    (replicated border) - callers mask them."""
    k = 2 * half_window + 1
    return cv2.boxFilter(img, -1, (k, k), dst=out, normalize=False, borderType=cv2.BORDER_REPLICATE)


def window_cost(i1: np.ndarray, i2w: np.ndarray, half_window: int, cost: str = "sad") -> np.ndarray:
    """Eq. 3.13/3.14 for every pixel; border pixels (within W of the edge) are NaN."""
    c = window_sum(pixel_cost(np.asarray(i1, np.float32), np.asarray(i2w, np.float32), cost), half_window)
    W = half_window
    if W > 0:
        c[:W], c[-W:], c[:, :W], c[:, -W:] = np.nan, np.nan, np.nan, np.nan
    return c


def parabolic_offset(c_prev: np.ndarray, c_best: np.ndarray, c_next: np.ndarray) -> np.ndarray:
    """Sub-plane offset of the cost minimum from a parabola through three costs (eq. 3.15).

    ``delta = (C_{k-1} - C_{k+1}) / (2 (C_{k-1} + C_{k+1} - 2 C_k))`` in units of the
    plane step, clipped to [-0.5, 0.5]. Eq. 3.15 as printed has the opposite sign
    of the numerator (its planes are ordered by decreasing depth); this is the
    vertex for planes ordered by increasing index. A flat curve gives 0.
    """
    denom = 2.0 * (c_prev + c_next - 2.0 * c_best)
    with np.errstate(divide="ignore", invalid="ignore"):
        d = np.where(denom > 0, (c_prev - c_next) / denom, 0.0)
    return np.clip(d, -0.5, 0.5)
