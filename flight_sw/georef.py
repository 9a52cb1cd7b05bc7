"""Georeferencing (thesis sec 4.4.3): world X, Y of every i1 pixel from its recovered elevation.

Exact for any attitude: the pixel's ray ``C1 + t R1^T K^-1 (u, v, 1)`` is cut
with the horizontal plane ``Z = z(u, v)``, ``t = (z - C1_z) / d_z``. The
thesis's eq. 4.16/4.17 are the special case of a camera pitched about one axis
(used as a test oracle).
"""

from __future__ import annotations

import numpy as np

from protocol.pairdir import Camera, Pose


def pixel_rays(camera: Camera, pose: Pose) -> np.ndarray:
    """World-frame ray directions (3xHxW, not normalised) of every pixel centre."""
    v, u = np.mgrid[0 : camera.height, 0 : camera.width].astype(np.float64)
    d_cam = np.stack([(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, np.ones_like(u)])
    return np.tensordot(pose.R.T, d_cam, axes=1)


def backproject(camera: Camera, pose: Pose, elevation: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World (X, Y) where each pixel's ray reaches its elevation; NaN where the elevation is NaN
    or the ray does not descend to it."""
    d = pixel_rays(camera, pose)
    C = pose.position
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (np.asarray(elevation, np.float64) - C[2]) / d[2]
    t = np.where(t > 0, t, np.nan)
    return C[0] + t * d[0], C[1] + t * d[1]
