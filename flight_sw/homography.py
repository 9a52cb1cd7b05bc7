"""Plane-induced homography between the two descent views (thesis sec 3.3, eq. 3.8).

For a plane ``n^T X1 + d = 0`` in camera-1 coordinates and ``X2 = R21 X1 + t21``
(Hartley & Zisserman eq. 13.2, DESIGN.md)::

    x2 ~ K (R21 - t21 n^T / d) K^-1 x1

A horizontal world plane ``Z = h`` has ``n = R1 e_z`` and ``d = C1_z - h``;
with ``R21 = R2 R1^T`` and ``t21 = R2 (C1 - C2)``. For a nadir camera this is
the thesis's eq. 3.8.
"""

from __future__ import annotations

import numpy as np

from protocol.pairdir import Camera, Pose


def homography_parts(camera: Camera, pose1: Pose, pose2: Pose) -> tuple[np.ndarray, np.ndarray, float]:
    """Return ``(A, B, C1_z)`` with ``H(h) = A - B / (C1_z - h)``: the plane-independent parts."""
    K = camera.K
    Kinv = np.linalg.inv(K)
    R21 = pose2.R @ pose1.R.T
    t21 = pose2.R @ (pose1.position - pose2.position)
    n = pose1.R @ np.array([0.0, 0.0, 1.0])
    A = K @ R21 @ Kinv
    B = K @ np.outer(t21, n) @ Kinv
    return A, B, float(pose1.position[2])


def plane_homography(camera: Camera, pose1: Pose, pose2: Pose, elevation: float) -> np.ndarray:
    """3x3 homography mapping i1 pixels (u, v, 1) to i2 pixels for the world plane ``Z = elevation``."""
    A, B, cz = homography_parts(camera, pose1, pose2)
    d = cz - float(elevation)
    if d <= 0:
        raise ValueError(f"plane Z = {elevation} m is not below camera 1 (Z = {cz} m)")
    return A - B / d


def map_points(H: np.ndarray, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Apply a homography to pixel coordinates (vectorised), returning the mapped (u, v)."""
    w = H[2, 0] * u + H[2, 1] * v + H[2, 2]
    return (H[0, 0] * u + H[0, 1] * v + H[0, 2]) / w, (H[1, 0] * u + H[1, 1] * v + H[1, 2]) / w


def centre_gsd(camera: Camera, pose: Pose) -> float:
    """Ground sample distance (m) at the image centre over the reference plane: slant range / f."""
    d = pose.position[2] / max(1e-9, -pose.R[2, 2])
    return float(max(1e-6, d / camera.fx))


def gsd_scale(camera: Camera, pose1: Pose, pose2: Pose) -> float:
    """GSD(i2) / GSD(i1) at the image centre over the reference plane (~0.5 for a halved altitude)."""
    d1 = pose1.position[2] / max(1e-9, -pose1.R[2, 2])
    d2 = pose2.position[2] / max(1e-9, -pose2.R[2, 2])
    return float(min(1.0, d2 / d1)) if d1 > 0 and d2 > 0 else 1.0
