"""Filling small DEM gaps by normalized convolution (box filters, O(1) per pixel).

A pixel without a recovered elevation gets the mean of the valid elevations in
the ``(2r+1)^2`` square around it::

    z_f(x) = sum_{N(x)} w z / sum_{N(x)} w,     w = 1 where z is valid, else 0

but only where ``sum w >= min_frac (2r+1)^2``: a gap narrower than about the
window (surrounded by measured ground) is interpolated, a large hole stays
NaN and is later mapped unsafe ("unknown is unsafe", mapping.combine). The
filled value is a local mean, so it carries the surrounding slope into the
footprint plane fit (slope.plane_fit) without inventing relief.
"""
from __future__ import annotations

import cv2
import numpy as np


def fill_small_gaps(z: np.ndarray, radius_px: int, min_frac: float = 0.3) -> np.ndarray:
    """``z`` (float, NaN = unknown) with gaps filled where enough of the neighbourhood is known.

    Returns a new float32 array; valid input values are unchanged. ``radius_px <= 0``
    returns a copy.
    """
    z = np.asarray(z, dtype=np.float32)
    out = z.copy()
    if radius_px <= 0:
        return out
    k = 2 * int(radius_px) + 1
    w = np.isfinite(z).astype(np.float32)
    if w.all() or not w.any():
        return out
    num = cv2.boxFilter(np.where(w > 0, z, np.float32(0)), cv2.CV_64F, (k, k), normalize=False,
                        borderType=cv2.BORDER_CONSTANT)
    den = cv2.boxFilter(w, cv2.CV_64F, (k, k), normalize=False, borderType=cv2.BORDER_CONSTANT)
    take = (w == 0) & (den >= max(1.0, min_frac * k * k))
    with np.errstate(divide="ignore", invalid="ignore"):
        out[take] = (num[take] / den[take]).astype(np.float32)
    return out
