"""Footprint slope from shading and stereo together: the sun-ward tilt from i1's brightness, the rest from the DEM.

**Why.** At 300-1000 m the SGM DEM's slope over a 3 m footprint of 3-10 px is noisy (3.5-4 deg median
error on tuning pairs), while the footprint's brightness fixes its incidence angle much better: on the
tuning `thesis` vertical pairs a brightness-derived incidence is within 2-3 deg (median) of the truth.
The brightness only sees the tilt *toward the sun*; the tilt across the sun is second order in it, so
that component comes from the DEM. This is the stereo + shape-from-shading split of planetary
photogrammetry (McEwen 1991, Icarus 92, 298, first-order photoclinometry; Alexandrov & Beyer 2018,
Earth and Space Science 5, 652, shape-from-shading anchored on a stereo DEM), reduced to one
footprint-scale equation per pixel.

**Model.** Lambert's law (lunar-Lambert's ``cos i`` term, which dominates near a nadir view): the
footprint-mean brightness is ``I = k cos i``, with ``k`` the albedo times the camera and phase terms.
``k`` varies slowly: it is estimated over a scale ``s`` much wider than the footprint (8 footprints,
16-64 px in ``fast``), where the DEM is trusted, as the ratio of the lit image to the DEM's own shading::

    k = G_s * (w I) / G_s * (w cos i_DEM),        cos i_meas = I_fp / k

(``w``: lit pixels with an elevation; ``G_s`` a Gaussian, O(1) per pixel). With the ground gradient
``g = (dz/dX, dz/dY)`` split into ``a`` along the sun's horizontal direction ``h`` and ``b`` across it,
and the sun vector ``s = (s_h h, s_z)``, the facet normal ``(-g, 1) / |(-g, 1)|`` gives::

    cos i = (s_z - a s_h) / sqrt(1 + a^2 + b^2)

which, for the DEM's ``b`` and the measured ``cos i = c``, is the quadratic in ``a``::

    (c^2 - s_h^2) a^2 + 2 s_z s_h a + c^2 (1 + b^2) - s_z^2 = 0

Of its roots, the one facing the sun (``s_z - a s_h >= 0``) nearest the DEM's ``a`` is kept; where no
root is real (a facet brighter than any tilt could make it, i.e. albedo), the brightest tilt is used.
The fused footprint gradient is ``|(a, b)|``. It ignores albedo detail below ``s`` (read as tilt), the
emission-angle term and interreflection; the P(safe) model (psafe.py) weighs it beside the DEM's own
slope, so a bias from those is calibrated on tuning seeds, not trusted.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from .shading import wide_blur


def incidence_cosine(gx: np.ndarray, gy: np.ndarray, sun: np.ndarray) -> np.ndarray:
    """``cos i`` of the facet with world gradient ``(gx, gy) = (dz/dX, dz/dY)`` under the unit sun vector
    (``protocol.pairdir.Sun.direction()``), float32."""
    gx = np.asarray(gx, np.float32)
    gy = np.asarray(gy, np.float32)
    sx, sy, sz = (np.float32(v) for v in sun)
    return ((sz - gx * sx - gy * sy) / np.sqrt(1.0 + gx * gx + gy * gy)).astype(np.float32)


def measured_incidence(
    img: np.ndarray,
    cos_i_dem: np.ndarray,
    lit: np.ndarray,
    footprint_px: float,
    gain_sigma_px: float,
) -> np.ndarray:
    """``cos i`` of each footprint from the image: ``I_fp / k`` with the slow gain ``k`` of the module doc.

    ``cos_i_dem``: the DEM's own incidence per pixel (NaN where none); ``lit``: pixels that are neither
    dark shadow nor without an elevation. ``I_fp`` is the box mean of the lit image over the footprint
    (``footprint_px`` wide, at least 1 px). NaN where nothing lit is near.
    """
    I = np.asarray(img, np.float32)
    w = (np.asarray(lit, bool) & np.isfinite(cos_i_dem)).astype(np.float32)
    n = max(1, int(round(float(footprint_px)))) | 1
    s = float(gain_sigma_px)
    num = wide_blur(I * w, s)
    den = wide_blur(np.where(w > 0, cos_i_dem, 0.0).astype(np.float32), s)
    fp_num = cv2.blur(I * w, (n, n), borderType=cv2.BORDER_REFLECT)
    fp_den = cv2.blur(w, (n, n), borderType=cv2.BORDER_REFLECT)
    with np.errstate(divide="ignore", invalid="ignore"):
        k = num / den
        c = (fp_num / fp_den) / k
    ok = (den > 1e-3) & (fp_den > 0.25) & np.isfinite(c) & (k > 0)
    return np.where(ok, np.clip(c, 0.0, 1.0), np.nan).astype(np.float32)


def _split_on(
    gx: np.ndarray, gy: np.ndarray, cos_i: np.ndarray, sun: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(ok, a, b)``: the points where every input is finite, and the split of the module doc on them (1-D)."""
    sx, sy, sz = (float(v) for v in sun)
    sh = math.hypot(sx, sy)
    # the sun at the zenith: brightness tells the tilt, not its direction; any split of the DEM's will do
    hx, hy = (sx / sh, sy / sh) if sh >= 1e-6 else (1.0, 0.0)
    gx = np.asarray(gx, np.float32)
    gy = np.asarray(gy, np.float32)
    c = np.asarray(cos_i, np.float32)
    ok = np.isfinite(gx) & np.isfinite(gy) & np.isfinite(c)
    x, y, c = gx[ok], gy[ok], c[ok]
    a_dem = x * np.float32(hx) + y * np.float32(hy)
    b = y * np.float32(hx) - x * np.float32(hy)
    c2 = c * c
    A = c2 - np.float32(sh * sh)
    B = np.float32(2.0 * sz * sh)
    C = c2 * (1.0 + b * b) - np.float32(sz * sz)
    disc = B * B - 4.0 * A * C
    with np.errstate(divide="ignore", invalid="ignore"):
        root = np.sqrt(np.maximum(disc, 0.0))
        linear = np.abs(A) < 1e-6
        r1 = np.where(linear, -C / B, (-B + root) / (2.0 * A))
        r2 = np.where(linear, r1, (-B - root) / (2.0 * A))
    facing1 = sz - r1 * sh >= 0
    facing2 = sz - r2 * sh >= 0
    pick1 = facing1 & (~facing2 | (np.abs(r1 - a_dem) <= np.abs(r2 - a_dem)))
    a = np.where(pick1, r1, np.where(facing2, r2, a_dem))
    # no real root: brighter than any tilt makes it; the brightest tilt, -s_h (1 + b^2) / s_z
    a = np.where(disc < 0, np.float32(-sh / max(sz, 1e-6)) * (1.0 + b * b), a)
    return ok, a, b


def sunward_split(gx: np.ndarray, gy: np.ndarray, cos_i: np.ndarray, sun: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The footprint gradient split along the sun's horizontal direction: ``(a, b)`` in m per m, float32.

    ``a`` (toward the sun) is the root of the module doc's quadratic for the measured incidence ``cos_i``;
    ``b`` (across the sun, ``h`` turned +90 deg) is the DEM's ``(gx, gy)`` projected on it. NaN where any
    input is. Solved in float32 on the points where it is defined only.
    """
    ok, a, b = _split_on(gx, gy, cos_i, sun)
    out_a = np.full(ok.shape, np.nan, np.float32)
    out_b = np.full(ok.shape, np.nan, np.float32)
    out_a[ok] = a
    out_b[ok] = b
    return out_a, out_b


def shading_gradient(gx: np.ndarray, gy: np.ndarray, cos_i: np.ndarray, sun: np.ndarray) -> np.ndarray:
    """Footprint gradient magnitude ``|(a, b)|`` (m per m): ``a`` (toward the sun) from ``cos_i``, ``b`` from the DEM.

    ``gx, gy``: the DEM's world gradient; ``cos_i``: the measured incidence; ``sun``: unit vector (its
    elevation must be above 0). NaN where any input is (:func:`sunward_split`). The flight path: one output
    image, the norm taken on the defined points only.
    """
    ok, a, b = _split_on(gx, gy, cos_i, sun)
    out = np.full(ok.shape, np.nan, np.float32)
    out[ok] = np.hypot(a, b)
    return out
