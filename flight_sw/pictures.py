"""PNG pictures of pipeline outputs for people (the CLI's only use of ground truth is here)."""

from __future__ import annotations

import cv2
import numpy as np

# BGR colours of the confusion map (positive = safe, DESIGN.md scoring convention)
CONFUSION_COLOURS = {"TP": (80, 200, 80), "TN": (160, 160, 160), "FP": (40, 40, 230), "FN": (40, 210, 230)}


def colour_map(
    values: np.ndarray, lo: float | None = None, hi: float | None = None, cmap: int = cv2.COLORMAP_VIRIDIS
) -> np.ndarray:
    """BGR uint8 picture of a float layer scaled ``lo..hi`` (default: 1st-99th percentile); NaN is black."""
    v = np.asarray(values, np.float64)
    ok = np.isfinite(v)
    if not ok.any():
        return np.zeros(v.shape + (3,), np.uint8)
    lo = float(np.percentile(v[ok], 1)) if lo is None else lo
    hi = float(np.percentile(v[ok], 99)) if hi is None else hi
    g = np.clip((np.where(ok, v, lo) - lo) / max(hi - lo, 1e-12), 0, 1)
    img = cv2.applyColorMap((g * 255).astype(np.uint8), cmap)
    img[~ok] = 0
    return img


def confusion(hazard: np.ndarray, truth_hazard: np.ndarray) -> dict[str, np.ndarray]:
    """Masks TP/TN/FP/FN where both maps are known; safe means hazard < 1."""
    both = np.isfinite(hazard) & np.isfinite(truth_hazard)
    called_safe, is_safe = hazard < 1, truth_hazard < 1
    return {
        "TP": both & called_safe & is_safe,
        "TN": both & ~called_safe & ~is_safe,
        "FP": both & called_safe & ~is_safe,
        "FN": both & ~called_safe & is_safe,
    }


def confusion_picture(masks: dict[str, np.ndarray]) -> np.ndarray:
    shape = next(iter(masks.values())).shape
    img = np.zeros(shape + (3,), np.uint8)
    for name, m in masks.items():
        img[m] = CONFUSION_COLOURS[name]
    return img
