"""Illumination: cast shadows by a horizon sweep, lunar-Lambert reflectance, sensor model."""

from __future__ import annotations

import math

import cv2
import numpy as np


def shadow_level(
    H: np.ndarray, cell: float, azimuth_deg: float, elevation_deg: float, min_dist_m: float = 0.0
) -> np.ndarray:
    """Lowest lit height per raster cell: ``S(p) = max_{s>=0} h(p + s*u_sun) - s*tan(el)``.

    A point at height z is directly lit iff ``z >= S`` (``S = h`` on lit ground). Computed by
    rotating the raster so the sun lies toward -column, then a running maximum per row of
    ``h + j*cell*tan(el)`` (O(N), vectorised over rows), and rotating back.
    Raster rows are +Y, columns +X; azimuth is clockwise from +Y.
    ``min_dist_m > 0`` keeps only casters at least that far toward the sun (``s >= min_dist_m``),
    without the point itself: the far part of a two-level shadow (near casters from a finer raster).
    """
    ny, nx = H.shape
    az = math.radians(azimuth_deg)
    tan_el = math.tan(math.radians(max(elevation_deg, 0.05)))
    su = np.array([math.sin(az), math.cos(az)])  # toward the sun in (col, row)
    au = -su  # rotated +col axis: away from the sun
    av = np.array([-au[1], au[0]])
    diag = int(math.ceil(math.hypot(nx, ny))) + 2
    c_src = np.array([(nx - 1) / 2, (ny - 1) / 2])
    c_dst = np.array([(diag - 1) / 2, (diag - 1) / 2])
    # src = c_src + (u - cu) * au + (v - cv) * av   (dst -> src map)
    M = np.array(
        [
            [au[0], av[0], c_src[0] - au[0] * c_dst[0] - av[0] * c_dst[1]],
            [au[1], av[1], c_src[1] - au[1] * c_dst[0] - av[1] * c_dst[1]],
        ]
    )
    low = float(H.min()) - 1e4
    zref = float(H.mean())
    Hr = cv2.warpAffine(
        (H - zref).astype(np.float32),
        M,
        (diag, diag),
        flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=low - zref,
    )
    ramp = (np.arange(diag, dtype=np.float64) * cell * tan_el)[None, :]
    acc = np.maximum.accumulate(Hr + ramp, axis=1)
    n0 = int(math.ceil(min_dist_m / cell)) if min_dist_m > 0 else 0
    if n0 > 0:
        acc = np.concatenate([np.full((diag, min(n0, diag)), low - zref), acc[:, : max(diag - n0, 0)]], axis=1)
    S = acc - ramp
    back = cv2.warpAffine(S.astype(np.float32), M, (nx, ny), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    if n0 > 0:
        return np.maximum(back.astype(np.float64) + zref, low)
    return np.maximum(back.astype(np.float64) + zref, H)


def lommel_l(phase_deg: np.ndarray) -> np.ndarray:
    """McEwen's lunar-Lambert limb parameter L(alpha), clamped to [0, 1] (scenes.md sec. 3)."""
    a = phase_deg
    return np.clip(1.0 - 0.019 * a + 2.42e-4 * a**2 - 1.46e-6 * a**3, 0.0, 1.0)


def lunar_lambert(albedo: np.ndarray, cos_i: np.ndarray, cos_e: np.ndarray, phase_deg: np.ndarray) -> np.ndarray:
    """Radiance factor ``A cos(i) [(1 - L) + 2 L / (cos i + cos e)]`` (McEwen lunar-Lambert); 0 if cos i <= 0."""
    L = lommel_l(phase_deg)
    ci = np.clip(cos_i, 0.0, None)
    ce = np.clip(cos_e, 1e-3, None)
    return albedo * ci * ((1.0 - L) + 2.0 * L / (ci + ce))


def sensor(
    radiance: np.ndarray,
    exposure: float,
    rng: np.random.Generator | None,
    read_noise_dn: float = 0.6,
    shot_gain: float = 0.02,
) -> np.ndarray:
    """8-bit image: ``DN = exposure * radiance`` + Gaussian read and shot noise (var = r^2 + g*DN)."""
    dn = exposure * radiance
    if rng is not None:
        dn = dn + rng.standard_normal(dn.shape) * np.sqrt(read_noise_dn**2 + shot_gain * np.maximum(dn, 0))
    return np.clip(np.rint(dn), 0, 255).astype(np.uint8)
