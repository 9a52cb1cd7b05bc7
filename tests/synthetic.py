"""Synthetic descent pairs for flight_sw tests: a seeded random texture draped on an analytic surface.

Each pixel's ray is intersected with the surface ``z = height(x, y)`` by
fixed-point iteration (exact for planes, converges for slopes well below the
ray's grazing angle), the texture is sampled there bilinearly (cv2.remap), and
pixels are integrated over an ``ss x ss`` sub-pixel grid before 8-bit
quantisation. Everything is deterministic in ``seed``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np

from protocol.pairdir import Camera, Pose

NADIR_R = np.diag([1.0, -1.0, -1.0])  # x right = +X, y down = -Y, optical axis = -Z


def camera_fov30(size: int) -> Camera:
    """Square camera with the thesis's 30 deg field of view."""
    f = (size / 2) / math.tan(math.radians(15.0))
    return Camera(size, size, f, f, (size - 1) / 2, (size - 1) / 2)


def tilted_R(tilt_deg: float, about: str = "x") -> np.ndarray:
    """Nadir camera rotated by ``tilt_deg`` about its own x axis (looks toward -Y) or y axis."""
    t = math.radians(tilt_deg)
    c, s = math.cos(t), math.sin(t)
    rot = np.array([[1, 0, 0], [0, c, -s], [0, s, c]]) if about == "x" else np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    return rot @ NADIR_R


@dataclass
class Texture:
    """Albedo on a regular world grid: ``img[r, c]`` at ``x = x0 + c*cell, y = y0 + r*cell``."""

    img: np.ndarray
    x0: float
    y0: float
    cell: float

    @classmethod
    def random(
        cls,
        half_extent_m: float,
        cell: float,
        seed: int,
        blur_cells: float = 1.2,
        spots_per_km2: float = 0.0,
        spot_m: float = 1.5,
    ) -> Texture:
        """Smooth random albedo; optional bright/black spot pairs mimic sunlit boulders and their shadows
        (intensity only - no relief), the high-contrast features behind the thesis's squared pattern."""
        rng = np.random.default_rng(seed)
        n = int(math.ceil(2 * half_extent_m / cell)) + 1
        fine = cv2.GaussianBlur(rng.standard_normal((n, n)).astype(np.float32), (0, 0), blur_cells)
        coarse = cv2.GaussianBlur(rng.standard_normal((n, n)).astype(np.float32), (0, 0), 8 * blur_cells)
        t = fine / fine.std() + 0.7 * coarse / coarse.std()
        t = np.clip(128 + 40 * t, 5, 250).astype(np.float32)
        k = int(rng.poisson(spots_per_km2 * (2 * half_extent_m / 1000.0) ** 2))
        r = max(1, int(round(spot_m / cell / 2)))
        for ci, cj in rng.integers(2 * r, n - 4 * r, size=(k, 2)):
            t[ci - r : ci + r, cj - r : cj + r] = 255.0
            t[ci + r : ci + 3 * r, cj - r : cj + r] = 0.0
        return cls(t, -half_extent_m, -half_extent_m, cell)

    def sample(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        mx = ((x - self.x0) / self.cell).astype(np.float32)
        my = ((y - self.y0) / self.cell).astype(np.float32)
        return cv2.remap(self.img, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)


def ray_surface(
    camera: Camera, pose: Pose, height: Callable, u: np.ndarray, v: np.ndarray, iters: int = 30
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """World (X, Y, Z) where the rays of pixels (u, v) meet ``Z = height(X, Y)``."""
    d_cam = np.stack([(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, np.ones_like(u)])
    d = np.tensordot(pose.R.T, d_cam, axes=1)
    C = pose.position
    t = (0.0 - C[2]) / d[2]
    for _ in range(iters):
        x, y = C[0] + t * d[0], C[1] + t * d[1]
        t = (height(x, y) - C[2]) / d[2]
    return C[0] + t * d[0], C[1] + t * d[1], C[2] + t * d[2]


def render(camera: Camera, pose: Pose, height: Callable, tex: Texture, ss: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Render an 8-bit image and the true elevation per pixel (at pixel centres)."""
    acc = np.zeros((camera.height, camera.width), np.float64)
    v, u = np.mgrid[0 : camera.height, 0 : camera.width].astype(np.float64)
    offs = (np.arange(ss) + 0.5) / ss - 0.5
    for dv in offs:
        for du in offs:
            x, y, _ = ray_surface(camera, pose, height, u + du, v + dv)
            acc += tex.sample(x, y)
    img = np.clip(np.rint(acc / ss**2), 0, 255).astype(np.uint8)
    _, _, z = ray_surface(camera, pose, height, u, v)
    return img, z.astype(np.float32)


def plane(z0: float) -> Callable:
    return lambda x, y: np.full_like(x, z0)


def roof(slope_deg: float, z0: float = 0.0) -> Callable:
    """A ridge along Y: ``z = z0 - tan(slope) |x|``."""
    g = math.tan(math.radians(slope_deg))
    return lambda x, y: z0 - g * np.abs(x)


def crater(radius: float, depth: float, cx: float = 0.0, cy: float = 0.0) -> Callable:
    """A paraboloid bowl of the given rim radius and depth on the plane z = 0."""
    return lambda x, y: -depth * np.clip(1 - ((x - cx) ** 2 + (y - cy) ** 2) / radius**2, 0, None)


def make_pair(
    size: int,
    alt1: float,
    alt2: float,
    height: Callable,
    seed: int = 0,
    R: np.ndarray = NADIR_R,
    offset2: tuple[float, float] = (0.0, 0.0),
    spots_per_km2: float = 0.0,
):
    """Camera, poses, images and true elevation of i1 for a vertical descent alt1 -> alt2."""
    cam = camera_fov30(size)
    p1 = Pose(np.array([0.0, 0.0, alt1]), R)
    p2 = Pose(np.array([offset2[0], offset2[1], alt2]), R, 10.0)  # later: frames are ordered by time
    gsd2 = alt2 / cam.fx
    half = alt1 * 0.6 + 10
    tex = Texture.random(half, gsd2 / 1.5, seed, spots_per_km2=spots_per_km2, spot_m=3 * gsd2)
    i1, z1 = render(cam, p1, height, tex)
    i2, _ = render(cam, p2, height, tex)
    return cam, p1, p2, i1, i2, z1


def flattened_wall_grid(origin_xy: tuple[float, float] = (0.0, 0.0)):
    """A 160 x 160 HazardGrid (0.5 m cells) whose every cell is measured safe (P 0.99): a plateau at 0 m,
    a 20 m wall that the DEM flattened into a 2 m ramp (columns 76-79, its top at column 76), a floor at
    -20 m. What SGM makes of a crater wall (flight_sw.sites.local_relief)."""
    from flight_sw.mapping import HazardGrid
    from protocol.pairdir import STATE_SAFE

    n = 160
    z = np.zeros((n, n), np.float32)
    z[:, 80:] = -20.0
    z[:, 76:80] = np.linspace(-4.0, -16.0, 4, dtype=np.float32)
    st = np.full((n, n), STATE_SAFE, np.uint8)
    return HazardGrid(np.zeros((n, n), np.float32), z, origin_xy, 0.5, st, np.full((n, n), 0.99, np.float32))


def frames_of(pair_id: str, seq0: int, pose_img: list) -> list:
    """The Frames a ground sends for ``pose_img`` [(pose, image), ...] (frame_index 0 first), seqs from ``seq0``."""
    from protocol.messages import Frame

    return [
        Frame(
            seq=seq0 + k,
            capture_time_s=float(k),
            position_m=tuple(float(v) for v in pose.position),
            R_world_to_cam=np.asarray(pose.R, "<f8"),
            altimeter_m=float("nan"),
            image=img,
            pair_id=pair_id,
            frame_index=k,
        )
        for k, (pose, img) in enumerate(pose_img)
    ]
