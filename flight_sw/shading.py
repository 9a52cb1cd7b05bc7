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

The same tilt moves ``rho`` less under a higher sun (``d rho / d t = cot e``: 2.1 per radian at
25 deg, 1.0 at 45 deg), so a model of ``rho`` fitted under one sun misreads another;
:func:`rho_at_sun` re-expresses ``rho`` as the tilt it implies, seen under a reference sun.
"""

from __future__ import annotations

import math

import cv2
import numpy as np


def wide_blur(a: np.ndarray, sigma_px: float, compensate: bool = False) -> np.ndarray:
    """Gaussian blur of ``sigma_px`` (float32); beyond 8 px on a ``d``-times smaller copy (``d`` a power of 2,
    ``sigma / d`` in 4-8 px), so a 64 px blur costs what an 8 px one does.

    ``compensate``: the small copy's blur is ``sqrt(sigma^2 - d^2 / 4) / d`` instead of ``sigma / d``, taking
    out the variance the ``d``-pixel area average (``d^2 / 12``) and the linear upsampling (``d^2 / 6``) add
    (variances of independent kernels add). On a 512 px lunar frame, for sigma 10-50 px, it then differs
    from the full-size blur by 0.7-2e-4 (median) and 0.5-2.3e-3 (max), relative: 2-5x closer than without.
    """
    a = np.asarray(a, np.float32)
    s = float(sigma_px)
    h, w = a.shape
    d = 1 if s <= 8.0 else int(2 ** math.floor(math.log2(s / 4.0)))
    d = max(1, min(d, h // 8, w // 8))
    if d == 1:
        return cv2.GaussianBlur(a, (0, 0), s, borderType=cv2.BORDER_REFLECT)
    small = cv2.resize(a, (max(1, w // d), max(1, h // d)), interpolation=cv2.INTER_AREA)
    s_small = math.sqrt(s * s - d * d / 4.0) / d if compensate else s / d
    small = cv2.GaussianBlur(small, (0, 0), s_small, borderType=cv2.BORDER_REFLECT)
    return cv2.resize(small, (w, h), interpolation=cv2.INTER_LINEAR)


def relative_brightness(
    img: np.ndarray, sigma_px: float = 10.0, fine_sigma_px: float = 1.0, wide: bool = False
) -> np.ndarray:
    """``rho`` (float32): intensity smoothed by ``fine_sigma_px`` over its ``sigma_px`` Gaussian local mean, minus 1.

    The pipeline ties both scales to the lander footprint: ``fine`` averages the texture within a
    facet (footprint / 3), ``sigma_px`` spans a few footprints, so the cue asks about footprint-sized
    facets whatever the altitude. ``wide``: both blurs by :func:`wide_blur` (compensated; exact up to
    8 px), about 1 ms at any sigma instead of 10-15 ms for the 29 px mean of a 300 m frame and
    ~100 ms for the 172 px one of a 50 m frame; off, the exact blurs (the v1 flow's).
    """
    I = np.asarray(img, dtype=np.float32)
    if wide:
        fine = wide_blur(I, float(fine_sigma_px), compensate=True)
        local = wide_blur(I, float(sigma_px), compensate=True)
    else:
        fine = cv2.GaussianBlur(I, (0, 0), float(fine_sigma_px), borderType=cv2.BORDER_REFLECT)
        local = cv2.GaussianBlur(I, (0, 0), float(sigma_px), borderType=cv2.BORDER_REFLECT)
    floor = np.float32(max(1e-6, 1e-3 * float(np.abs(I).max())))
    return (fine / np.maximum(local, floor) - 1.0).astype(np.float32)


def rho_at_sun(rho: np.ndarray, sun_elevation_deg: float, ref_elevation_deg: float) -> np.ndarray:
    """``rho`` measured under a sun ``sun_elevation_deg`` high, as it would read under ``ref_elevation_deg``.

    First-order photoclinometry with Lambert's law (the cos(i) term that dominates lunar-Lambert near
    nadir view; McEwen 1991, Icarus 92, 298): a facet tilted by ``t`` toward the sun, relative to its
    surroundings, is brighter by ``rho = sin(e + t) / sin(e) - 1``. Inverting for the tilt,

        t = asin(clip((1 + rho) sin e, -1, 1)) - e,       rho_ref = sin(e_ref + t) / sin(e_ref) - 1,

    so the map is the identity when ``e = e_ref`` and it leaves the sign of every cue. A facet tilted
    past the sun (``e + t > 90 deg``) darkens again and reads as the smaller tilt. It ignores the
    tilt across the sun (second order) and albedo (read as tilt: a higher sun amplifies albedo
    contrast too). Float32, NaN stays NaN.
    """
    e, e0 = math.radians(float(sun_elevation_deg)), math.radians(float(ref_elevation_deg))
    if not (0.0 < e <= 0.5 * math.pi and 0.0 < e0 < 0.5 * math.pi):
        raise ValueError(f"sun elevations must be in (0, 90] deg, got {sun_elevation_deg!r} and {ref_elevation_deg!r}")
    r = np.asarray(rho, np.float32)
    t = np.arcsin(np.clip((1.0 + r) * np.float32(math.sin(e)), -1.0, 1.0)) - np.float32(e)
    return (np.sin(np.float32(e0) + t) / np.float32(math.sin(e0)) - 1.0).astype(np.float32)


def local_shadow_mask(img: np.ndarray, global_mask: np.ndarray, rho: np.ndarray, dark_rel: float) -> np.ndarray:
    """Eq. 4.9's ``global_mask`` AND locally dark (``rho < -dark_rel``): a shadow is darker than its surroundings."""
    return np.asarray(global_mask, bool) & (rho < -float(dark_rel))


def shading_mask(rho: np.ndarray, limit: float) -> np.ndarray:
    """Facets much brighter or darker than their surroundings (``|rho| > limit``): likely steep."""
    return np.abs(rho) > float(limit)


def speck_contrast(img: np.ndarray, footprint_px: float) -> np.ndarray:
    """Pixel-scale brightness range ``(max_3x3 I - min_3x3 I) / mean_fp I`` (float32): a sunlit face beside its
    own shadow.

    A boulder smaller than the DEM resolves (a few pixels at 100-300 m) shows as a bright face next to a
    dark one. On the tuning boulder-field renders the hazard pixels called safe had a median range of
    0.8-1.6 against 0.13-0.34 for the truly safe ones called safe. ``mean_fp`` is the box mean over the
    footprint (``footprint_px``, at least 3 px), so the cue is relative to the local brightness. O(1) per pixel.
    """
    I = np.asarray(img, np.float32)
    k3 = np.ones((3, 3), np.uint8)
    rng = cv2.dilate(I, k3, borderType=cv2.BORDER_REPLICATE) - cv2.erode(I, k3, borderType=cv2.BORDER_REPLICATE)
    n = max(3, int(round(float(footprint_px)))) | 1
    mean = cv2.blur(I, (n, n), borderType=cv2.BORDER_REPLICATE)
    floor = np.float32(max(1e-6, 1e-3 * float(np.abs(I).max())))
    return (rng / np.maximum(mean, floor)).astype(np.float32)
