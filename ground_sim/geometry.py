"""Camera geometry: pixel rays, attitude construction, view footprint."""

from __future__ import annotations

import math

import numpy as np

from protocol.pairdir import Camera, Pose


def look_rotation(off_nadir_deg: float, heading_deg: float = 0.0) -> np.ndarray:
    """World->camera R for a camera tilted ``off_nadir_deg`` from nadir toward the heading.

    Heading is the horizontal direction of the tilt, clockwise from +Y (like the sun
    azimuth). Image x (right) stays horizontal: ``x = f x Z``; ``z = cos(t) (-Z) + sin(t) f``;
    ``y = z x x`` (down in the image, toward the near field). At 0 deg the image top is the heading.
    """
    t, h = math.radians(off_nadir_deg), math.radians(heading_deg)
    f = np.array([math.sin(h), math.cos(h), 0.0])
    x = np.cross(f, [0.0, 0.0, 1.0])
    z = math.cos(t) * np.array([0.0, 0.0, -1.0]) + math.sin(t) * f
    y = np.cross(z, x)
    return np.stack([x, y, z])


def pixel_rays(camera: Camera, pose: Pose, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Unit world ray directions (..., 3) through pixel coordinates (u, v)."""
    dc = np.stack([(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, np.ones(np.shape(u))], axis=-1)
    d = dc @ pose.R  # R^T applied to row vectors: camera -> world
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def boundary_pixels(camera: Camera, n: int = 16) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates along the image border (outer pixel edges)."""
    w, h = camera.width - 0.5, camera.height - 0.5
    s = np.linspace(0.0, 1.0, n)
    u = np.concatenate([-0.5 + s * (w + 0.5), np.full(n, w), w - s * (w + 0.5), np.full(n, -0.5)])
    v = np.concatenate([np.full(n, -0.5), -0.5 + s * (h + 0.5), np.full(n, h), h - s * (h + 0.5)])
    return u, v


def project(camera: Camera, pose: Pose, X: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Project world points (..., 3) -> (u, v, z_cam)."""
    Xc = (X - pose.position) @ pose.R.T
    z = Xc[..., 2]
    return camera.fx * Xc[..., 0] / z + camera.cx, camera.fy * Xc[..., 1] / z + camera.cy, z


def ground_footprint(camera: Camera, pose: Pose, z: float = 0.0) -> np.ndarray:
    """Corners (4x2) where the image corner rays meet the plane Z = z (thesis Fig. 6.9 trapezoid)."""
    u = np.array([-0.5, camera.width - 0.5, camera.width - 0.5, -0.5])
    v = np.array([-0.5, -0.5, camera.height - 0.5, camera.height - 0.5])
    d = pixel_rays(camera, pose, u, v)
    t = (z - pose.position[2]) / d[:, 2]
    return pose.position[:2] + t[:, None] * d[:, :2]


MIN_RAY_DOWN = 0.05  # |d_z| below this: a ray too close to the horizon to meet the ground


def border_rays(camera: Camera, pose: Pose) -> np.ndarray:
    """World directions (N x 3) of rays through the image border (12 per side) and its centre."""
    bu, bv = boundary_pixels(camera, 12)
    return pixel_rays(camera, pose, np.append(bu, camera.cx), np.append(bv, camera.cy))


def sky_problem(rays: np.ndarray) -> str | None:
    """Why a view whose :func:`border_rays` are ``rays`` cannot be rendered because some of it sees the sky or the
    horizon (a ray pointing less than asin(:data:`MIN_RAY_DOWN`) below the horizontal), or None. Checked where a
    trajectory is read, so that the error names its pair and frame, and again by the renderer."""
    d = np.asarray(rays)
    if d[:, 2].max() <= -MIN_RAY_DOWN:
        return None
    worst = math.degrees(math.asin(min(1.0, float(d[:, 2].max()))))
    return (
        f"camera sees the sky or the horizon (a border ray points {worst:+.1f} deg "
        f"from horizontal; need < {-math.degrees(math.asin(MIN_RAY_DOWN)):.1f})"
    )
