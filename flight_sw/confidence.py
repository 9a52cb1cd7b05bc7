"""Match confidence from the shape of the cost curve: reject elevations the sweep cannot pin down.

Around the winning plane ``k`` the cost is a parabola (eq. 3.15) whose
normalised curvature is ``kappa = (C_{k-1} + C_{k+1} - 2 C_k) / C_k``. If the
cost carries relative noise ``e``, the vertex moves by about ``sqrt(e / kappa)``
plane steps, so the elevation's standard uncertainty is proportional to::

    u = dz_k / sqrt(kappa)           (m; dz_k = local plane spacing)

``u`` is large where the cost curve is flat: little texture, foreshortened or
repeated texture, and pixels whose i2 position barely moves with elevation
(near the epipole, far field of an oblique view). Its scale grows with
altitude (dz_k does), so the test is relative: a pixel is rejected when its
``u`` exceeds ``k`` times the image's median ``u`` - an outlier in
reliability, whatever the altitude.
"""

from __future__ import annotations

import numpy as np


def elevation_uncertainty(elevation: np.ndarray, curvature: np.ndarray, planes: np.ndarray) -> np.ndarray:
    """``u = dz / sqrt(kappa)`` per pixel (float32, NaN where the elevation is NaN; inf for kappa <= 0)."""
    planes = np.asarray(planes, dtype=np.float64)
    z = np.asarray(elevation, dtype=np.float64)
    ok = np.isfinite(z)
    dz = np.full(z.shape, np.nan)
    dz[ok] = np.interp(z[ok], 0.5 * (planes[1:] + planes[:-1]), np.diff(planes))
    k = np.asarray(curvature, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        u = np.where(k > 0, dz / np.sqrt(np.where(k > 0, k, 1.0)), np.inf)
    return np.where(ok, u, np.nan).astype(np.float32)


def reject_uncertain(
    elevation: np.ndarray,
    uncertainty: np.ndarray,
    rel_limit: float,
    curvature: np.ndarray | None = None,
    sharp_curvature: float = np.inf,
) -> np.ndarray:
    """NaN where ``uncertainty > rel_limit * median(uncertainty)`` over the valid pixels; ``rel_limit <= 0``: off.

    Pixels whose cost curve is sharp in absolute terms (``curvature >= sharp_curvature``) are
    always kept: the relative test must not thin out a well-textured image.
    """
    z = np.asarray(elevation, dtype=np.float32)
    ok = np.isfinite(z) & ~np.isnan(uncertainty)
    if rel_limit <= 0 or not ok.any():
        return z.copy()
    limit = rel_limit * float(np.median(uncertainty[ok]))
    keep = ok & (uncertainty <= limit)
    if curvature is not None and np.isfinite(sharp_curvature):
        keep |= ok & (np.nan_to_num(curvature, nan=0.0) >= sharp_curvature)
    return np.where(keep, z, np.float32(np.nan)).astype(np.float32)
