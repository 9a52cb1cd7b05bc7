"""Photometric cues from i1 alone: locally dark pixels (shadow) and strong shading (steep walls).

The relative brightness of a pixel against its neighbourhood,

    rho = G_1 * I / G_s * I - 1        (G_s: Gaussian of sigma s pixels, O(1) per pixel)

removes the slow illumination gradient across the image (sun elevation, the
view angle of an oblique frame) that makes the global eq. 4.9 threshold
``(mu + sigma) / 2`` flag whole dim regions as shadow. Under Lambertian
reflectance the brightness of a facet is ``albedo * cos(i)``; tilting it by
``t`` toward (away from) the sun changes ``cos(i)`` by a factor that exceeds
``1 + rho_t`` (falls below ``1 - rho_t``) long before ``t`` reaches the
15 deg slope limit for sun elevations of 20-60 deg, so ``|rho| > rho_t`` marks
crater walls that the window-correlated DEM smooths below the limit (sec 4.3's
window spans ~11 m at 300 m altitude). The threshold is empirical (ground_sim
seeds 0-1, docs/benchmarks/pipeline.md): albedo contrast also moves ``rho``.
"""

from __future__ import annotations

import cv2
import numpy as np


def relative_brightness(img: np.ndarray, sigma_px: float = 10.0, fine_sigma_px: float = 1.0) -> np.ndarray:
    """``rho`` (float32): intensity smoothed by ``fine_sigma_px`` over its ``sigma_px`` Gaussian local mean, minus 1.

    The pipeline ties both scales to the lander footprint: ``fine`` averages the texture within a
    facet (footprint / 3), ``sigma_px`` spans a few footprints, so the cue asks about footprint-sized
    facets whatever the altitude.
    """
    I = np.asarray(img, dtype=np.float32)
    fine = cv2.GaussianBlur(I, (0, 0), float(fine_sigma_px), borderType=cv2.BORDER_REFLECT)
    local = cv2.GaussianBlur(I, (0, 0), float(sigma_px), borderType=cv2.BORDER_REFLECT)
    floor = np.float32(max(1e-6, 1e-3 * float(np.abs(I).max())))
    return (fine / np.maximum(local, floor) - 1.0).astype(np.float32)


def local_shadow_mask(img: np.ndarray, global_mask: np.ndarray, rho: np.ndarray, dark_rel: float) -> np.ndarray:
    """Eq. 4.9's ``global_mask`` AND locally dark (``rho < -dark_rel``): a shadow is darker than its surroundings."""
    return np.asarray(global_mask, bool) & (rho < -float(dark_rel))


def shading_mask(rho: np.ndarray, limit: float) -> np.ndarray:
    """Facets much brighter or darker than their surroundings (``|rho| > limit``): likely steep."""
    return np.abs(rho) > float(limit)
