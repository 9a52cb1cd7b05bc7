"""Render a view of a scene with ground truth (pinhole camera, DESIGN.md conventions).

Pipeline per frame:
1. bound the view: border rays against planes at the terrain's min/max height give the
   footprint (the thesis's trapezoid, Fig. 6.9, for a tilted camera), padded by the 3 m
   hazard disk and extended toward the sun so off-screen terrain can cast shadows;
2. evaluate the scene on a world raster of cell ``GSD_min / supersample`` (band-limited
   to 2 cells: terrain-level anti-aliasing; size capped at ``MAX_CELLS``);
3. ray-cast every sub-pixel ray (``supersample^2`` per pixel) and every pixel-centre ray:
   a coarse pass (every 4th pixel) gives a conservative start, then a fine march and a
   regula-falsi refinement on the bilinear surface (correct occlusion);
4. shade with lunar-Lambert (normals from raster gradients) x cast-shadow visibility
   from a horizon sweep; box-downsample the sub-pixels; seeded sensor noise; 8 bit;
5. truth from pixel-centre rays: elevation, camera z-depth, shadow (< half the pixel
   lit), hazard (slope/roughness of the true raster + shadow).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from ground_sim.errors import RenderError
from ground_sim.geometry import boundary_pixels, pixel_rays
from ground_sim.heightfield import Raster, intersect
from ground_sim.scene import Scene
from ground_sim.shading import lunar_lambert, sensor, shadow_level
from ground_sim.truth import FOOTPRINT_M, hazard_layers, plane_fit
from protocol.errors import InputError
from protocol.pairdir import Camera, Pose, Sun

MAX_CELLS = 1_000_000
MIN_RAY_DOWN = 0.05  # |d_z| below this: ray too close to the horizon
COARSE = 4
REFERENCE_DN = 95.0  # DN of flat ground of mean albedo under this sun


@dataclass
class View:
    """A rendered frame and its per-pixel ground truth."""

    image: np.ndarray  # uint8 (H, W)
    elevation: np.ndarray  # float32 world Z seen by each pixel centre
    depth: np.ndarray  # float32 camera z of that point
    shadow: np.ndarray  # bool, pixel not directly lit (majority of its area)
    hazard: np.ndarray  # float32 [0, 1] truth hazard
    world_xy: np.ndarray  # float32 (H, W, 2)
    radiance: np.ndarray  # float32 noise-free radiance factor (before exposure)
    info: dict


def _check_pose(camera: Camera, pose: Pose) -> None:
    try:
        camera.validate()
        pose.validate("render pose")
    except InputError as exc:
        raise RenderError(str(exc)) from None


def _exposure(scene: Scene, sun: Sun) -> float:
    """Fixed gain per sun: flat ground of mean albedo seen at nadir maps to REFERENCE_DN."""
    ci = math.sin(math.radians(sun.elevation_deg))
    ref = lunar_lambert(
        np.array(scene.params.albedo.mean), np.array(ci), np.array(1.0), np.array(90.0 - sun.elevation_deg)
    )
    return REFERENCE_DN / max(float(ref), 1e-6)


def plan_raster(scene: Scene, camera: Camera, pose: Pose, sun: Sun, supersample: int) -> tuple:
    """Raster window (x0, y0, cell, nx, ny) and the coarse height bounds of the view."""
    C = pose.position
    bu, bv = boundary_pixels(camera, 12)
    bu = np.append(bu, camera.cx)
    bv = np.append(bv, camera.cy)
    d = pixel_rays(camera, pose, bu, bv)
    if d[:, 2].max() > -MIN_RAY_DOWN:
        worst = math.degrees(math.asin(min(1.0, d[:, 2].max())))
        raise RenderError(
            f"camera sees the sky or the horizon (a border ray points {worst:+.1f} deg "
            f"from horizontal; need < {-math.degrees(math.asin(MIN_RAY_DOWN)):.1f})"
        )
    # coarse terrain bounds around the approximate footprint
    z_c = float(scene.height(np.array([C[0]]), np.array([C[1]]), 1.0)[0])
    if C[2] <= z_c + 0.5:
        raise RenderError(
            f"camera at Z = {C[2]:.2f} m is below or too close to the terrain (ground Z = {z_c:.2f} m under it)"
        )
    t0 = (C[2] - z_c) / -d[:, 2]
    fx, fy = C[0] + t0 * d[:, 0], C[1] + t0 * d[:, 1]
    span = max(np.ptp(fx), np.ptp(fy), 1.0)
    gx, gy = np.meshgrid(np.linspace(fx.min(), fx.max(), 33), np.linspace(fy.min(), fy.max(), 33))
    hz = scene.height(gx, gy, span / 16)
    pad = 6.0 + 0.5 * max(scene.params.boulders.d_max_m, 1.0) + 0.1 * np.ptp(hz)
    zlo, zhi = float(hz.min()) - pad, float(hz.max()) + pad
    zhi = min(zhi, C[2] - 0.1)
    ts = []
    for z in (zlo, zhi):
        ts.append((C[2] - z) / -d[:, 2])
    pts = np.concatenate([C[:2] + t[:, None] * d[:, :2] for t in ts])
    x0, y0 = pts.min(axis=0) - (FOOTPRINT_M + 1.0)
    x1, y1 = pts.max(axis=0) + (FOOTPRINT_M + 1.0)
    # shadow casters upstream of the sun
    el = math.radians(max(sun.elevation_deg, 1.0))
    ext = min((zhi - zlo) / math.tan(el), 1.5 * max(x1 - x0, y1 - y0))
    az = math.radians(sun.azimuth_deg)
    sx, sy = math.sin(az) * ext, math.cos(az) * ext
    x0, x1 = min(x0, x0 + sx), max(x1, x1 + sx)
    y0, y1 = min(y0, y0 + sy), max(y1, y1 + sy)
    gsd = float(ts[1].min()) / camera.fx
    cell = max(gsd / supersample, math.sqrt((x1 - x0) * (y1 - y0) / MAX_CELLS))
    nx = int(math.ceil((x1 - x0) / cell)) + 1
    ny = int(math.ceil((y1 - y0) / cell)) + 1
    return x0, y0, cell, nx, ny, zlo, zhi, gsd


def render_view(
    scene: Scene, camera: Camera, pose: Pose, sun: Sun, *, seed: int = 0, supersample: int = 2, noise: bool = True
) -> View:
    """Render ``scene`` from ``pose`` under ``sun``; see the module docstring for the method."""
    _check_pose(camera, pose)
    if not (0.0 < sun.elevation_deg <= 90.0) or not math.isfinite(sun.azimuth_deg):
        raise RenderError(f"sun elevation must be in (0, 90] deg, got {sun.elevation_deg}")
    if supersample < 1 or supersample > 8:
        raise RenderError(f"supersample must be 1..8, got {supersample}")
    ss = int(supersample)
    x0, y0, cell, nx, ny, _, _, gsd = plan_raster(scene, camera, pose, sun, ss)
    H, A = scene.raster(x0, y0, cell, nx, ny)
    r = Raster(x0, y0, cell, H)
    zmin, zmax = float(H.min()) - 0.01, float(H.max()) + 0.01  # float32 sampling slack
    C = pose.position
    W, Hh = camera.width, camera.height

    # -- coarse pass: every COARSE-th pixel centre, full march from the top of the terrain
    cu = np.arange(COARSE / 2 - 0.5, W, COARSE)
    cv = np.arange(COARSE / 2 - 0.5, Hh, COARSE)
    CU, CV = np.meshgrid(cu, cv)
    dcoarse = pixel_rays(camera, pose, CU.ravel(), CV.ravel())
    tlo = np.maximum((C[2] - zmax) / -dcoarse[:, 2], 0.0)
    thi = (C[2] - zmin) / -dcoarse[:, 2]
    sin_t = np.sqrt(np.maximum(1 - dcoarse[:, 2] ** 2, 1e-12))
    step = np.minimum(1.0 * cell, 1.0 * cell / sin_t)
    tc, hitc = intersect(r, C, dcoarse, tlo, thi, step, refine=1)
    if not hitc.all():
        raise RenderError("some rays leave the terrain window without hitting the ground")
    zc = C[2] + tc * dcoarse[:, 2]
    tc = tc.reshape(CU.shape)
    zc = zc.reshape(CU.shape)
    # conservative start height per block: max hit height in the 3x3 block neighbourhood + margin
    zstart = cv2.dilate(zc.astype(np.float32), np.ones((3, 3), np.uint8)).astype(np.float64)
    max_feature = 0.6 * scene.params.boulders.d_max_m
    margin = 1.0 + max_feature + 2.0 * COARSE * gsd

    def coarse_start(u: np.ndarray, v: np.ndarray) -> np.ndarray:
        bi = np.clip(np.floor(v / COARSE).astype(np.int64), 0, zstart.shape[0] - 1)
        bj = np.clip(np.floor(u / COARSE).astype(np.int64), 0, zstart.shape[1] - 1)
        return zstart[bi, bj] + margin

    def march(u: np.ndarray, v: np.ndarray, zs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Hits of the rays through pixels (u, v), marched down from heights ``zs``."""
        d = pixel_rays(camera, pose, u, v)
        zs = np.minimum(zs, zmax)
        t0 = np.maximum((C[2] - zs) / -d[:, 2], 0.0)
        t1 = (C[2] - zmin) / -d[:, 2]
        s = np.sqrt(np.maximum(1 - d[:, 2] ** 2, 1e-12))
        stp = np.minimum(3.0 * cell, 1.2 * cell / s)
        t, hit = intersect(r, C, d, t0, t1, stp)
        # rays that started under the surface (margin too small): redo from the top
        z0 = C[2] + t0 * d[:, 2]
        under = (z0 < zmax) & (np.abs(t - t0) < 1e-9)
        if np.any(under):
            iu = np.nonzero(under)[0]
            tt, hh = intersect(
                r,
                C,
                d[iu],
                np.maximum((C[2] - zmax) / -d[iu, 2], 0.0),
                t1[iu],
                np.minimum(1.0 * cell, 1.0 * cell / s[iu]),
            )
            t[iu], hit[iu] = tt, hh
        if not hit.all():
            raise RenderError("some rays leave the terrain window without hitting the ground")
        return d, t

    # -- sub-pixel rays
    off = (np.arange(ss) + 0.5) / ss - 0.5
    su = (np.arange(W)[None, :, None] + off[None, None, :]).reshape(1, W * ss)
    sv = (np.arange(Hh)[:, None, None] + off[None, :, None]).reshape(Hh * ss, 1)
    SU, SV = np.broadcast_arrays(su, sv)
    d, t = march(SU.ravel(), SV.ravel(), coarse_start(SU.ravel(), SV.ravel()))
    X = C + t[:, None] * d
    sun_dir = sun.direction()
    gyy, gxx = np.gradient(H, cell)
    nxr = r.sample_fast(X[:, 0], X[:, 1], (-gxx).astype(np.float32))
    nyr = r.sample_fast(X[:, 0], X[:, 1], (-gyy).astype(np.float32))
    nrm = np.stack([nxr, nyr, np.ones_like(nxr)], axis=1)
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    cos_i = nrm @ sun_dir
    cos_e = -(nrm * d).sum(axis=1)
    phase = np.degrees(np.arccos(np.clip(-(d @ sun_dir), -1.0, 1.0)))
    alb = r.sample_fast(X[:, 0], X[:, 1], A.astype(np.float32))
    S = shadow_level(H, cell, sun.azimuth_deg, sun.elevation_deg)
    level = r.sample_fast(X[:, 0], X[:, 1], (S - r.zref).astype(np.float32)) + r.zref
    soft = cell * math.tan(math.radians(sun.elevation_deg)) + 0.02
    vis = np.clip((X[:, 2] - level) / soft + 1.0, 0.0, 1.0)
    lit = vis * (cos_i > 0)
    rad = lunar_lambert(alb, cos_i, cos_e, phase) * vis + 0.01 * alb  # faint scattered light
    rad = cv2.resize(rad.reshape(Hh * ss, W * ss).astype(np.float32), (W, Hh), interpolation=cv2.INTER_AREA)
    litf = cv2.resize(lit.reshape(Hh * ss, W * ss).astype(np.float32), (W, Hh), interpolation=cv2.INTER_AREA)

    # -- pixel-centre rays for geometric truth; the sub-pixel hits bracket each centre ray, so
    # start it just above the highest sub-pixel hit of its 3x3 pixel neighbourhood (a feature
    # hiding between sub-pixel rays is narrower than ~1 pixel, hence lower than ~0.6 GSD)
    zsub = X[:, 2].reshape(Hh, ss, W, ss).max(axis=(1, 3)).astype(np.float32)
    zpix = cv2.dilate(zsub, np.ones((3, 3), np.uint8)).astype(np.float64).ravel()
    PU, PV = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(Hh, dtype=np.float64))
    dp, tp = march(PU.ravel(), PV.ravel(), zpix + 0.5 + 0.6 * min(scene.params.boulders.d_max_m, 2.0 * gsd))
    Xp = C + tp[:, None] * dp
    depth = tp * (dp @ pose.R[2])
    shadow = litf < 0.5
    a, b, c = plane_fit(H, cell)
    pa = r.sample(Xp[:, 0], Xp[:, 1], a)
    pb = r.sample(Xp[:, 0], Xp[:, 1], b)
    pc = r.sample(Xp[:, 0], Xp[:, 1], c)
    hazard = hazard_layers(Xp[:, 2], pa, pb, pc, shadow.ravel()).reshape(Hh, W)

    rng = np.random.default_rng([int(seed) & 0xFFFFFFFF, 0x5EED]) if noise else None
    image = sensor(rad, _exposure(scene, sun), rng)
    info = {"raster_cell_m": cell, "raster_shape": [ny, nx], "gsd_min_m": gsd, "raster_origin_m": [x0, y0]}
    return View(
        image,
        Xp[:, 2].reshape(Hh, W).astype(np.float32),
        depth.reshape(Hh, W).astype(np.float32),
        shadow,
        hazard,
        Xp[:, :2].reshape(Hh, W, 2).astype(np.float32),
        rad,
        info,
    )
