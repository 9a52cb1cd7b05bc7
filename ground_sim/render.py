"""Render a view of a scene with ground truth (pinhole camera, DESIGN.md conventions).

Pipeline per frame:
1. bound the view: border rays against planes at the terrain's min/max height give the
   footprint (the thesis's trapezoid, Fig. 6.9, for a tilted camera), padded by the 3 m
   hazard disk and extended toward the sun so off-screen terrain can cast shadows;
2. evaluate the scene on a world raster of cell ``GSD_min / supersample`` (band-limited
   to 2 cells: terrain-level anti-aliasing), but of at most ``max_cells`` cells (default
   ``MAX_CELLS``, for speed): a larger window gets a coarser cell, and then finer detail is
   in neither the image nor the truth, and two views of the same ground see different
   detail (``info["raster_cell_over_target"]`` says by how much; docs/scenes.md);
3. ray-cast every sub-pixel ray (``supersample^2`` per pixel) and every pixel-centre ray:
   a coarse pass (every 4th pixel) gives a conservative start, then a fine march and a
   regula-falsi refinement on the bilinear surface (correct occlusion);
4. shade with lunar-Lambert (normals from raster gradients) x cast-shadow visibility
   from a horizon sweep; box-downsample the sub-pixels; seeded sensor noise; 8 bit;
5. truth from pixel-centre rays: elevation, camera z-depth, shadow (< half the pixel
   lit), hazard (slope/roughness of the true surface + shadow; the plane over the 3 m disk is
   fitted on the view raster when it holds the disk, else on a world-aligned raster of 0.5 m,
   :func:`ground_sim.truth.footprint_cell` and :func:`~ground_sim.truth.footprint_planes`; the cell
   used is ``info["truth_cell_m"]``), and the altimeter range
   (the ray along the optical axis, ``t`` of its hit: the slant range a laser altimeter
   would measure).

:func:`truth_at` computes the same truth for chosen pixels only, on a raster limited
to a pixel box (same cell, grid aligned with the full view's): the scene library uses
it to measure hazard shares without rendering images.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from ground_sim.errors import RenderError
from ground_sim.geometry import border_rays, ground_footprint, pixel_rays, sky_problem
from ground_sim.heightfield import Raster, intersect
from ground_sim.scene import Scene
from ground_sim.shading import lunar_lambert, sensor, shadow_level
from ground_sim.truth import FOOTPRINT_M, footprint_cell, footprint_planes, hazard_layers, plane_fit, plane_fit_factor
from protocol.errors import InputError
from protocol.pairdir import SUN_AZIMUTH_LIMIT_DEG, Camera, Pose, Sun

# Bump when a change alters what is rendered (images or truth) for the same inputs: render caches
# (ground_sim/render_cache.py) then draw their pairs again. tests/test_render_cache.py pins a small
# render's bytes to this number, so the change cannot land without the bump.
RENDER_VERSION = 3  # 2: shadow edges centred on a caster level without the point itself (stop 24); 3: slope and
# roughness truth on rasters of at most ground_sim.truth.TRUTH_CELL_M (stop 67)
MAX_CELLS = 1_000_000
RASTERS = ("view", "tiles")
# every view at its GSD/supersample from rasters per image tile: "view" (one capped raster per view) draws
# 512 px views 1.2-4.2x coarser and the two views of a pair see different detail (docs/scenes.md, item 4)
DEFAULT_RASTER = "tiles"
MAX_CELLS_LIMIT = 16_000_000  # a render process peaked at 1.0-1.7 GB with it (docs/scenes.md): refused above
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
    altimeter_m: float = math.nan  # slant range along the optical axis to the true ground
    exposure: float = 1.0  # DN per unit radiance (sensor gain for this scene and sun)


def _check_pose(camera: Camera, pose: Pose) -> None:
    try:
        camera.validate()
        pose.validate("render pose")
    except InputError as exc:
        raise RenderError(str(exc)) from None


def check_max_cells(max_cells: int) -> None:
    """Refuse a raster-size bound that is not an integer in [10 000, ``MAX_CELLS_LIMIT``] (memory is bounded first)."""
    if isinstance(max_cells, bool) or not isinstance(max_cells, int) or not 10_000 <= max_cells <= MAX_CELLS_LIMIT:
        raise RenderError(f"--max-raster-cells must be an integer in [10000, {MAX_CELLS_LIMIT}], got {max_cells!r}")


def check_raster(raster: str) -> None:
    """Refuse an unknown raster layout (``"view"``: one raster per view; ``"tiles"``: one per image tile)."""
    if raster not in RASTERS:
        raise RenderError(f"raster must be one of {', '.join(RASTERS)}, got {raster!r}")


def check_sun(sun: Sun, where: str = "sun") -> None:
    """Refuse a sun that the renderer cannot draw or that the pair's reader would refuse (one line)."""
    for what, v in (("azimuth", sun.azimuth_deg), ("elevation", sun.elevation_deg)):
        if not math.isfinite(v):
            raise RenderError(f"{where}: {what} must be a finite number of degrees, got {v}")
    if not -SUN_AZIMUTH_LIMIT_DEG <= sun.azimuth_deg <= SUN_AZIMUTH_LIMIT_DEG:
        lim = SUN_AZIMUTH_LIMIT_DEG
        raise RenderError(f"{where}: azimuth must be in [{-lim:g}, {lim:g}] deg, got {sun.azimuth_deg:g}")
    if not 0.0 < sun.elevation_deg <= 90.0:
        raise RenderError(f"{where}: elevation must be in (0, 90] deg, got {sun.elevation_deg:g}")


def _check_args(sun: Sun, supersample: int, max_cells: int = MAX_CELLS) -> None:
    if not (0.0 < sun.elevation_deg <= 90.0):
        raise RenderError(f"sun elevation must be in (0, 90] deg, got {sun.elevation_deg}")
    if not math.isfinite(sun.azimuth_deg):
        raise RenderError(f"sun azimuth must be a finite angle in deg, got {sun.azimuth_deg}")
    if supersample < 1 or supersample > 8:
        raise RenderError(f"supersample must be 1..8, got {supersample}")
    check_max_cells(max_cells)


def exposure(scene: Scene, sun: Sun) -> float:
    """Fixed gain per sun: flat ground of mean albedo seen at nadir maps to REFERENCE_DN."""
    ci = math.sin(math.radians(sun.elevation_deg))
    ref = lunar_lambert(
        np.array(scene.params.albedo.mean), np.array(ci), np.array(1.0), np.array(90.0 - sun.elevation_deg)
    )
    return REFERENCE_DN / max(float(ref), 1e-6)


_exposure = exposure  # old private name


@dataclass(frozen=True)
class RasterPlan:
    """World raster window of a view: origin, cell, size; coarse terrain bounds; min GSD."""

    x0: float
    y0: float
    cell: float
    nx: int
    ny: int
    zlo: float
    zhi: float
    gsd: float
    sun_ext_m: float

    def __iter__(self):  # the old tuple interface: x0, y0, cell, nx, ny, zlo, zhi, gsd
        return iter((self.x0, self.y0, self.cell, self.nx, self.ny, self.zlo, self.zhi, self.gsd))


def _footprint_xy(camera: Camera, pose: Pose, u: np.ndarray, v: np.ndarray, zlo: float, zhi: float) -> np.ndarray:
    C = pose.position
    d = pixel_rays(camera, pose, u, v)
    return np.concatenate([C[:2] + ((C[2] - z) / -d[:, 2])[:, None] * d[:, :2] for z in (zlo, zhi)])


def plan_raster(
    scene: Scene,
    camera: Camera,
    pose: Pose,
    sun: Sun,
    supersample: int,
    box: tuple[float, float, float, float] | None = None,
    max_cells: int = MAX_CELLS,
) -> RasterPlan:
    """Raster window (x0, y0, cell, nx, ny) and the coarse height bounds of the view.

    ``box`` = (u0, v0, u1, v1) in pixel-edge coordinates limits the window to what the
    pixels of that box need; cell, height bounds and the sun extension stay those of the
    whole view, and the origin is snapped to the whole view's grid (in steps of the plane
    fit's coarsening) so the rasters agree where they overlap.
    """
    C = pose.position
    d = border_rays(camera, pose)
    sky = sky_problem(d)
    if sky is not None:
        raise RenderError(sky)
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
    ts = [(C[2] - z) / -d[:, 2] for z in (zlo, zhi)]
    pts = np.concatenate([C[:2] + t[:, None] * d[:, :2] for t in ts])
    x0, y0 = pts.min(axis=0) - (FOOTPRINT_M + 1.0)
    x1, y1 = pts.max(axis=0) + (FOOTPRINT_M + 1.0)
    # shadow casters upstream of the sun
    el = math.radians(max(sun.elevation_deg, 1.0))
    ext = min((zhi - zlo) / math.tan(el), 1.5 * max(x1 - x0, y1 - y0))
    az = math.radians(sun.azimuth_deg)
    sx, sy = math.sin(az) * ext, math.cos(az) * ext
    fx0, fx1 = min(x0, x0 + sx), max(x1, x1 + sx)
    fy0, fy1 = min(y0, y0 + sy), max(y1, y1 + sy)
    gsd = float(ts[1].min()) / camera.fx
    cell = max(gsd / supersample, math.sqrt((fx1 - fx0) * (fy1 - fy0) / max_cells))
    if box is not None:
        u0, v0, u1, v1 = box
        s = np.linspace(0.0, 1.0, 12)
        bu = np.concatenate([u0 + s * (u1 - u0), np.full(12, u1), u1 - s * (u1 - u0), np.full(12, u0)])
        bv = np.concatenate([np.full(12, v0), v0 + s * (v1 - v0), np.full(12, v1), v1 - s * (v1 - v0)])
        bp = _footprint_xy(camera, pose, bu, bv, zlo, zhi)
        bx0, by0 = bp.min(axis=0) - (FOOTPRINT_M + 1.0)
        bx1, by1 = bp.max(axis=0) + (FOOTPRINT_M + 1.0)
        bx0, bx1 = min(bx0, bx0 + sx), max(bx1, bx1 + sx)
        by0, by1 = min(by0, by0 + sy), max(by1, by1 + sy)
        snap = cell * plane_fit_factor(cell)
        bx0 = fx0 + math.floor(max(bx0 - fx0, 0.0) / snap) * snap
        by0 = fy0 + math.floor(max(by0 - fy0, 0.0) / snap) * snap
        fx0, fy0, fx1, fy1 = bx0, by0, min(bx1, fx1), min(by1, fy1)
    nx = int(math.ceil((fx1 - fx0) / cell)) + 1
    ny = int(math.ceil((fy1 - fy0) / cell)) + 1
    return RasterPlan(float(fx0), float(fy0), cell, nx, ny, zlo, zhi, gsd, float(ext))


def plan_tile(
    camera: Camera,
    pose: Pose,
    sun: Sun,
    ss: int,
    view: RasterPlan,
    box: tuple[int, int, int, int],
    reach_m: float,
    max_cells: int,
) -> RasterPlan:
    """Raster of the pixels ``box`` = (u0, v0, u1, v1) (end exclusive) at their own GSD_min / ss.

    The window holds every hit of the box's rays between the view's height bounds, two cells of
    slack, and ``reach_m`` toward the sun (near shadow casters; farther ones come from the view's
    raster). No hazard pad: slope and roughness truth never come from a tile's raster.
    """
    u0, v0, u1, v1 = box
    s = np.linspace(0.0, 1.0, 9)
    a0, b0, a1, b1 = u0 - 0.5, v0 - 0.5, u1 - 0.5, v1 - 0.5
    bu = np.concatenate([a0 + s * (a1 - a0), np.full(9, a1), a1 - s * (a1 - a0), np.full(9, a0)])
    bv = np.concatenate([np.full(9, b0), b0 + s * (b1 - b0), np.full(9, b1), b1 - s * (b1 - b0)])
    gu, gv = np.meshgrid(np.linspace(a0, a1, 5), np.linspace(b0, b1, 5))
    C = pose.position
    d_in = pixel_rays(camera, pose, np.append(gu.ravel(), bu), np.append(gv.ravel(), bv))
    gsd = float(np.min((C[2] - view.zhi) / -d_in[:, 2])) / camera.fx
    pts = _footprint_xy(camera, pose, bu, bv, view.zlo, view.zhi)
    slack = 2.0 * gsd
    x0, y0 = pts.min(axis=0) - slack
    x1, y1 = pts.max(axis=0) + slack
    az = math.radians(sun.azimuth_deg)
    sx, sy = math.sin(az) * reach_m, math.cos(az) * reach_m
    x0, x1 = min(x0, x0 + sx), max(x1, x1 + sx)
    y0, y1 = min(y0, y0 + sy), max(y1, y1 + sy)
    cell = max(gsd / ss, math.sqrt((x1 - x0) * (y1 - y0) / max_cells))
    nx = int(math.ceil((x1 - x0) / cell)) + 1
    ny = int(math.ceil((y1 - y0) / cell)) + 1
    return RasterPlan(float(x0), float(y0), cell, nx, ny, view.zlo, view.zhi, gsd, float(reach_m))


class _Caster:
    """The raster of a view and its ray casting: coarse pass, conservative starts, fine march."""

    blocks: tuple[int, int, int, int]
    zstart: np.ndarray
    margin: float
    truth_cell: float | None  # the footprint raster of the slope and roughness truth; None: the view raster
    hazard_truth: bool  # False: no slope and roughness truth (render_view(hazard_truth=False))

    def __init__(
        self,
        scene: Scene,
        camera: Camera,
        pose: Pose,
        sun: Sun,
        ss: int,
        box: tuple[int, int, int, int] | None = None,
        max_cells: int = MAX_CELLS,
        tile_of: _Caster | None = None,
        plan: RasterPlan | None = None,
        hazard_truth: bool = True,
    ) -> None:
        self.scene, self.camera, self.pose, self.sun, self.ss = scene, camera, pose, sun, ss
        self.hazard_truth = hazard_truth if tile_of is None else tile_of.hazard_truth
        W, Hh = camera.width, camera.height
        if tile_of is not None and plan is not None:
            # a tile of a view (render_view(raster="tiles")): its own raster, the view's start heights
            self.blocks = tile_of.blocks
        elif box is None:
            self.blocks = (0, 0, -(-Hh // COARSE), -(-W // COARSE))
            plan = plan_raster(scene, camera, pose, sun, ss, max_cells=max_cells)
        else:
            # pixels of the box plus two coarse blocks around it (the start heights dilate by one block)
            u0, v0, u1, v1 = box
            bi0, bj0 = max(v0 // COARSE - 2, 0), max(u0 // COARSE - 2, 0)
            bi1, bj1 = min(-(-v1 // COARSE) + 2, -(-Hh // COARSE)), min(-(-u1 // COARSE) + 2, -(-W // COARSE))
            self.blocks = (bi0, bj0, bi1, bj1)
            edge = (bj0 * COARSE - 0.5, bi0 * COARSE - 0.5, min(bj1 * COARSE, W) - 0.5, min(bi1 * COARSE, Hh) - 0.5)
            plan = plan_raster(scene, camera, pose, sun, ss, box=edge, max_cells=max_cells)
        assert plan is not None
        self.plan = plan
        self.H, self.A = scene.raster(plan.x0, plan.y0, plan.cell, plan.nx, plan.ny)
        self.r = Raster(plan.x0, plan.y0, plan.cell, self.H)
        self.cell, self.gsd = plan.cell, plan.gsd
        self.zmin, self.zmax = float(self.H.min()) - 0.01, float(self.H.max()) + 0.01  # float32 sampling slack
        self.C = pose.position
        if tile_of is not None:
            # the view's start heights, 1 m higher: fine relief its raster smooths away may rise above them
            self.zstart, self.margin = tile_of.zstart, tile_of.margin + 1.0
            self.truth_cell = tile_of.truth_cell
        else:
            self._coarse()
            # the whole view's ground per pixel (also for a box of it: truth_at takes the view's truth cell)
            corners = ground_footprint(camera, pose, 0.5 * (plan.zlo + plan.zhi))
            x, y = corners[:, 0], corners[:, 1]
            area = 0.5 * abs(float(np.dot(x, np.roll(y, 1)) - np.dot(y, np.roll(x, 1))))
            self.truth_cell = footprint_cell(plan.cell, area / (W * Hh))

    def _coarse(self) -> None:
        """Every COARSE-th pixel centre, full march from the top of the terrain."""
        bi0, bj0, bi1, bj1 = self.blocks
        C, cell = self.C, self.cell
        cu = np.arange(bj0, bj1) * COARSE + COARSE / 2 - 0.5
        cv = np.arange(bi0, bi1) * COARSE + COARSE / 2 - 0.5
        CU, CV = np.meshgrid(cu, cv)
        dcoarse = pixel_rays(self.camera, self.pose, CU.ravel(), CV.ravel())
        tlo = np.maximum((C[2] - self.zmax) / -dcoarse[:, 2], 0.0)
        thi = (C[2] - self.zmin) / -dcoarse[:, 2]
        sin_t = np.sqrt(np.maximum(1 - dcoarse[:, 2] ** 2, 1e-12))
        step = np.minimum(1.0 * cell, 1.0 * cell / sin_t)
        tc, hitc = intersect(self.r, C, dcoarse, tlo, thi, step, refine=1)
        if not hitc.all():
            raise RenderError("some rays leave the terrain window without hitting the ground")
        zc = (C[2] + tc * dcoarse[:, 2]).reshape(CU.shape)
        # conservative start height per block: max hit height in the 3x3 block neighbourhood + margin
        self.zstart = cv2.dilate(zc.astype(np.float32), np.ones((3, 3), np.uint8)).astype(np.float64)
        max_feature = 0.6 * self.scene.params.boulders.d_max_m
        self.margin = 1.0 + max_feature + 2.0 * COARSE * self.gsd

    def coarse_start(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        bi0, bj0, _, _ = self.blocks
        bi = np.clip(np.floor(v / COARSE).astype(np.int64) - bi0, 0, self.zstart.shape[0] - 1)
        bj = np.clip(np.floor(u / COARSE).astype(np.int64) - bj0, 0, self.zstart.shape[1] - 1)
        return self.zstart[bi, bj] + self.margin

    def march(self, u: np.ndarray, v: np.ndarray, zs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Hits of the rays through pixels (u, v), marched down from heights ``zs``."""
        C, cell, r = self.C, self.cell, self.r
        d = pixel_rays(self.camera, self.pose, u, v)
        zs = np.minimum(zs, self.zmax)
        t0 = np.maximum((C[2] - zs) / -d[:, 2], 0.0)
        t1 = (C[2] - self.zmin) / -d[:, 2]
        s = np.sqrt(np.maximum(1 - d[:, 2] ** 2, 1e-12))
        stp = np.minimum(3.0 * cell, 1.2 * cell / s)
        t, hit = intersect(r, C, d, t0, t1, stp)
        # rays that started under the surface (margin too small): redo from the top
        z0 = C[2] + t0 * d[:, 2]
        under = (z0 < self.zmax) & (np.abs(t - t0) < 1e-9)
        if np.any(under):
            iu = np.nonzero(under)[0]
            tt, hh = intersect(
                r,
                C,
                d[iu],
                np.maximum((C[2] - self.zmax) / -d[iu, 2], 0.0),
                t1[iu],
                np.minimum(1.0 * cell, 1.0 * cell / s[iu]),
            )
            t[iu], hit[iu] = tt, hh
        if not hit.all():
            raise RenderError("some rays leave the terrain window without hitting the ground")
        return d, t

    def shadow_level(self) -> np.ndarray:
        # casters from half a cell toward the sun, not the point itself: with it, the level equals the
        # terrain on lit ground and kinks at the shadow's edge, so its interpolation (and the soft edge
        # below) moved the edge by a fraction of the raster cell - which differs 2x between a pair's views
        # (docs/scenes.md, item 5)
        return shadow_level(self.H, self.cell, self.sun.azimuth_deg, self.sun.elevation_deg, min_dist_m=0.5 * self.cell)

    def lit(self, X: np.ndarray, S: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(sun visibility in [0, 1] at hit points X - soft over one cell, centred on the caster level -,
        cos i, surface normals)."""
        r = self.r
        gyy, gxx = np.gradient(self.H, self.cell)
        nxr = r.sample_fast(X[:, 0], X[:, 1], (-gxx).astype(np.float32))
        nyr = r.sample_fast(X[:, 0], X[:, 1], (-gyy).astype(np.float32))
        nrm = np.stack([nxr, nyr, np.ones_like(nxr)], axis=1)
        nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
        cos_i = nrm @ self.sun.direction()
        level = r.sample_fast(X[:, 0], X[:, 1], (S - r.zref).astype(np.float32)) + r.zref
        soft = self.cell * math.tan(math.radians(self.sun.elevation_deg)) + 0.02
        vis = np.clip((X[:, 2] - level) / soft + 0.5, 0.0, 1.0)  # half lit on the geometric edge
        return vis, cos_i, nrm

    def radiance(self, X: np.ndarray, d: np.ndarray, S: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(radiance factor, directly lit share) of the hits X of rays d under shadow levels S (lunar-Lambert)."""
        vis, cos_i, nrm = self.lit(X, S)
        cos_e = -(nrm * d).sum(axis=1)
        phase = np.degrees(np.arccos(np.clip(-(d @ self.sun.direction()), -1.0, 1.0)))
        alb = self.r.sample_fast(X[:, 0], X[:, 1], self.A.astype(np.float32))
        rad = lunar_lambert(alb, cos_i, cos_e, phase) * vis + 0.01 * alb  # faint scattered light
        return rad, vis * (cos_i > 0)

    def centre_start(self, zsub_max: np.ndarray) -> np.ndarray:
        """Start height of pixel-centre rays from the highest sub-pixel hit of each pixel's neighbourhood."""
        return zsub_max + 0.5 + 0.6 * min(self.scene.params.boulders.d_max_m, 2.0 * self.gsd)

    def truth(self, dp: np.ndarray, tp: np.ndarray, shadow: np.ndarray) -> dict[str, np.ndarray]:
        """Elevation, depth, world X/Y and hazard of centre-ray hits (flat arrays)."""
        Xp = self.C + tp[:, None] * dp
        if not self.hazard_truth:
            hazard = np.full(len(Xp), np.nan, np.float32)
        elif self.truth_cell is not None:
            hazard = hazard_layers(*footprint_planes(self.heights, Xp[:, 0], Xp[:, 1], self.truth_cell), shadow)
        else:
            a, b, c = plane_fit(self.H, self.cell)
            r = self.r
            pa = r.sample(Xp[:, 0], Xp[:, 1], a)
            pb = r.sample(Xp[:, 0], Xp[:, 1], b)
            pc = r.sample(Xp[:, 0], Xp[:, 1], c)
            hazard = hazard_layers(Xp[:, 2], pa, pb, pc, shadow)
        return {
            "elevation": Xp[:, 2],
            "depth": tp * (dp @ self.pose.R[2]),
            "world_xy": Xp[:, :2],
            "hazard": hazard,
        }

    def heights(self, x0: float, y0: float, cell: float, nx: int, ny: int) -> np.ndarray:
        """The scene's heights on a raster (:func:`ground_sim.truth.footprint_planes`' source)."""
        return self.scene.height_raster(x0, y0, cell, nx, ny)

    def altimeter(self, zs: float) -> float:
        """Slant range from the camera centre to the ground along the optical axis (principal point ray)."""
        cam = self.camera
        _, t = self.march(np.array([cam.cx]), np.array([cam.cy]), np.array([zs]))
        return float(t[0])


def render_view(
    scene: Scene,
    camera: Camera,
    pose: Pose,
    sun: Sun,
    *,
    seed: int = 0,
    supersample: int = 2,
    noise: bool = True,
    max_cells: int = MAX_CELLS,
    raster: str = DEFAULT_RASTER,
    hazard_truth: bool = True,
) -> View:
    """Render ``scene`` from ``pose`` under ``sun``; see the module docstring for the method.

    ``raster="tiles"`` (the default) draws the image and the geometric truth from rasters per image tile at
    the tile's own GSD/supersample (:func:`_render_tiles`); far shadow casters stay on the view's raster, and
    slope and roughness truth too while it holds the footprint's disk (else a 0.5 m raster; module docstring).
    ``raster="view"`` draws everything from one raster per view, capped at ``max_cells`` (the renders before
    2026-11-25).

    ``hazard_truth=False`` skips the slope and roughness truth, most of a high view's time (a pair's later
    frames, whose truth nothing reads): ``View.hazard`` is then all NaN and ``info["truth_cell_m"]`` None. The
    image and every other truth layer are the same bytes.
    """
    _check_pose(camera, pose)
    _check_args(sun, supersample, max_cells)
    check_raster(raster)
    ss = int(supersample)
    cs = _Caster(scene, camera, pose, sun, ss, max_cells=max_cells, hazard_truth=hazard_truth)
    if raster == "tiles":
        return _render_tiles(cs, seed=seed, noise=noise, max_cells=max_cells)
    C = cs.C
    W, Hh = camera.width, camera.height

    # -- sub-pixel rays
    off = (np.arange(ss) + 0.5) / ss - 0.5
    su = (np.arange(W)[None, :, None] + off[None, None, :]).reshape(1, W * ss)
    sv = (np.arange(Hh)[:, None, None] + off[None, :, None]).reshape(Hh * ss, 1)
    SU, SV = np.broadcast_arrays(su, sv)
    d, t = cs.march(SU.ravel(), SV.ravel(), cs.coarse_start(SU.ravel(), SV.ravel()))
    X = C + t[:, None] * d
    rad, lit = cs.radiance(X, d, cs.shadow_level())
    rad = cv2.resize(rad.reshape(Hh * ss, W * ss).astype(np.float32), (W, Hh), interpolation=cv2.INTER_AREA)
    litf = cv2.resize(lit.reshape(Hh * ss, W * ss).astype(np.float32), (W, Hh), interpolation=cv2.INTER_AREA)

    # -- pixel-centre rays for geometric truth; the sub-pixel hits bracket each centre ray, so
    # start it just above the highest sub-pixel hit of its 3x3 pixel neighbourhood (a feature
    # hiding between sub-pixel rays is narrower than ~1 pixel, hence lower than ~0.6 GSD)
    zsub = X[:, 2].reshape(Hh, ss, W, ss).max(axis=(1, 3)).astype(np.float32)
    zpix = cv2.dilate(zsub, np.ones((3, 3), np.uint8)).astype(np.float64)
    PU, PV = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(Hh, dtype=np.float64))
    dp, tp = cs.march(PU.ravel(), PV.ravel(), cs.centre_start(zpix.ravel()))
    shadow = litf < 0.5
    tr = cs.truth(dp, tp, shadow.ravel())
    # the optical axis meets the image at the principal point: start like its nearest pixel
    iu = int(np.clip(round(camera.cx), 0, W - 1))
    iv = int(np.clip(round(camera.cy), 0, Hh - 1))
    alt_m = cs.altimeter(float(cs.centre_start(zpix[iv, iu])))

    image, gain = _sensor_image(cs, rad, seed, noise)
    # > 1: the raster is this much coarser than GSD_min / supersample (the max_cells cap)
    info = _view_info(cs, alt_m, raster_cell_over_target=cs.plan.cell / (cs.plan.gsd / ss))
    return View(
        image,
        tr["elevation"].reshape(Hh, W).astype(np.float32),
        tr["depth"].reshape(Hh, W).astype(np.float32),
        shadow,
        tr["hazard"].reshape(Hh, W),
        tr["world_xy"].reshape(Hh, W, 2).astype(np.float32),
        rad,
        info,
        alt_m,
        gain,
    )


def _sensor_image(cs: _Caster, rad: np.ndarray, seed: int, noise: bool) -> tuple[np.ndarray, float]:
    """The 8-bit image of a radiance map (the scene's fixed gain; sensor noise of ``seed`` unless ``noise=False``)."""
    rng = np.random.default_rng([int(seed) & 0xFFFFFFFF, 0x5EED]) if noise else None
    gain = exposure(cs.scene, cs.sun)
    return sensor(rad, gain, rng), gain


def _view_info(cs: _Caster, alt_m: float, **extra: Any) -> dict[str, Any]:
    """What a View records about its rendering: the view raster, its GSD, the altimeter range, ``extra``."""
    p = cs.plan
    return {
        "raster_cell_m": p.cell,
        "raster_shape": [p.ny, p.nx],
        "gsd_min_m": p.gsd,
        "raster_cell_over_target": extra.pop("raster_cell_over_target"),
        "raster_origin_m": [p.x0, p.y0],
        # the raster the slope and roughness truth's plane was fitted on (ground_sim.truth.footprint_cell)
        # (None: no slope and roughness truth drawn, render_view(hazard_truth=False))
        "truth_cell_m": None if not cs.hazard_truth else p.cell if cs.truth_cell is None else cs.truth_cell,
        **extra,
        "altimeter_m": alt_m,
    }


def _tile_boxes(cs: _Caster, box: tuple[int, int, int, int], max_cells: int, out: list) -> None:
    """Quad-split ``box`` until its raster reaches GSD/ss within ``max_cells`` (or it is 16 px)."""
    u0, v0, u1, v1 = box
    plan = plan_tile(cs.camera, cs.pose, cs.sun, cs.ss, cs.plan, _grown(box, cs.camera), _reach(cs), max_cells)
    if plan.cell <= 1.001 * plan.gsd / cs.ss or min(u1 - u0, v1 - v0) <= 16:
        out.append((box, plan))
        return
    um, vm = (u0 + u1) // 2, (v0 + v1) // 2
    for b in ((u0, v0, um, vm), (um, v0, u1, vm), (u0, vm, um, v1), (um, vm, u1, v1)):
        _tile_boxes(cs, b, max_cells, out)


def _grown(box: tuple[int, int, int, int], camera: Camera) -> tuple[int, int, int, int]:
    """The box and one pixel around it (the 3x3 start-height neighbourhood of the centre rays)."""
    u0, v0, u1, v1 = box
    return max(u0 - 1, 0), max(v0 - 1, 0), min(u1 + 1, camera.width), min(v1 + 1, camera.height)


def _reach(cs: _Caster) -> float:
    """Shadow casters nearer than this come from the tiles' rasters, farther ones from the view's."""
    return 4.0 * cs.cell


def _render_tiles(cs: _Caster, *, seed: int, noise: bool, max_cells: int) -> View:
    """The image and geometric truth of ``cs``'s view from one raster per tile at the tile's GSD/ss.

    Each tile (a quad-tree split of the image until every tile's raster reaches GSD_min/ss within
    ``max_cells``) is ray cast on its own raster, grown by one pixel so the pixel-centre rays find
    their start heights. Shadows: casters within :func:`_reach` toward the sun from the tile's raster,
    farther ones from the view's (``shadow_level(min_dist_m=...)``). Slope and roughness truth are the
    view raster's at the tile's hits, or :func:`ground_sim.truth.footprint_planes`' at them (``cs.truth_cell``);
    the shadow truth is the tiles' (the sub-pixel lit fraction).
    """
    camera, pose, sun, ss, C = cs.camera, cs.pose, cs.sun, cs.ss, cs.C
    W, Hh = camera.width, camera.height
    tiles: list = []
    _tile_boxes(cs, (0, 0, W, Hh), max_cells, tiles)
    reach = _reach(cs)
    S_far = shadow_level(cs.H, cs.cell, sun.azimuth_deg, sun.elevation_deg, min_dist_m=reach)
    S_far32 = (S_far - cs.r.zref).astype(np.float32)
    # slope and roughness truth: the view raster's when it is fine enough, else one footprint-scale raster after
    # the tiles (footprint_planes over every pixel's ground point: its strips then span the view once)
    truth_cell, view_truth = cs.truth_cell, cs.hazard_truth and cs.truth_cell is None
    a_c, b_c, c_c = plane_fit(cs.H, cs.cell) if view_truth else (None, None, None)
    off = (np.arange(ss) + 0.5) / ss - 0.5
    rad = np.zeros((Hh, W), np.float32)
    litf = np.zeros((Hh, W), np.float32)
    elev = np.zeros((Hh, W))
    depth = np.zeros((Hh, W))
    wxy = np.zeros((Hh, W, 2))
    haz = np.zeros((Hh, W), np.float32) if cs.hazard_truth else np.full((Hh, W), np.nan, np.float32)
    alt_m = math.nan
    worst, cells = 1.0, 0
    iu = int(np.clip(round(camera.cx), 0, W - 1))
    iv = int(np.clip(round(camera.cy), 0, Hh - 1))
    for (u0, v0, u1, v1), plan in tiles:
        g0, h0, g1, h1 = _grown((u0, v0, u1, v1), camera)
        tc = _Caster(cs.scene, camera, pose, sun, ss, tile_of=cs, plan=plan)
        worst = max(worst, plan.cell / (plan.gsd / ss))
        cells += plan.nx * plan.ny
        gw, gh = g1 - g0, h1 - h0
        su = (np.arange(g0, g1)[None, :, None] + off[None, None, :]).reshape(1, gw * ss)
        sv = (np.arange(h0, h1)[:, None, None] + off[None, :, None]).reshape(gh * ss, 1)
        SU, SV = (a.ravel() for a in np.broadcast_arrays(su, sv))
        d, t = tc.march(SU, SV, tc.coarse_start(SU, SV))
        X = C + t[:, None] * d
        nodes_x = plan.x0 + np.arange(plan.nx) * plan.cell
        nodes_y = plan.y0 + np.arange(plan.ny) * plan.cell
        NX, NY = np.meshgrid(nodes_x, nodes_y)
        far = cs.r.sample_fast(NX.ravel(), NY.ravel(), S_far32).reshape(NX.shape) + cs.r.zref
        rd, lit = tc.radiance(X, d, np.maximum(tc.shadow_level(), far))
        rd = cv2.resize(rd.reshape(gh * ss, gw * ss).astype(np.float32), (gw, gh), interpolation=cv2.INTER_AREA)
        lt = cv2.resize(lit.reshape(gh * ss, gw * ss).astype(np.float32), (gw, gh), interpolation=cv2.INTER_AREA)
        zsub = X[:, 2].reshape(gh, ss, gw, ss).max(axis=(1, 3)).astype(np.float32)
        zpix = cv2.dilate(zsub, np.ones((3, 3), np.uint8)).astype(np.float64)
        iy, ix = slice(v0 - h0, v1 - h0), slice(u0 - g0, u1 - g0)
        PU, PV = np.meshgrid(np.arange(u0, u1, dtype=np.float64), np.arange(v0, v1, dtype=np.float64))
        dp, tp = tc.march(PU.ravel(), PV.ravel(), tc.centre_start(zpix[iy, ix].ravel()))
        Xp = C + tp[:, None] * dp
        shp = (v1 - v0, u1 - u0)
        if view_truth:
            zc = cs.r.sample(Xp[:, 0], Xp[:, 1])
            pa, pb, pc = (cs.r.sample(Xp[:, 0], Xp[:, 1], m) for m in (a_c, b_c, c_c))
            haz[v0:v1, u0:u1] = hazard_layers(zc, pa, pb, pc, (lt[iy, ix] < 0.5).ravel()).reshape(shp)
        rad[v0:v1, u0:u1], litf[v0:v1, u0:u1] = rd[iy, ix], lt[iy, ix]
        elev[v0:v1, u0:u1] = Xp[:, 2].reshape(shp)
        depth[v0:v1, u0:u1] = (tp * (dp @ pose.R[2])).reshape(shp)
        wxy[v0:v1, u0:u1] = Xp[:, :2].reshape(shp + (2,))
        if u0 <= iu < u1 and v0 <= iv < v1:
            alt_m = tc.altimeter(float(tc.centre_start(zpix[iv - h0, iu - g0])))
    if cs.hazard_truth and truth_cell is not None:
        planes = footprint_planes(cs.heights, wxy[..., 0].ravel(), wxy[..., 1].ravel(), truth_cell)
        haz = hazard_layers(*planes, (litf < 0.5).ravel()).reshape(Hh, W)
    image, gain = _sensor_image(cs, rad, seed, noise)
    info = _view_info(cs, alt_m, raster_cell_over_target=worst, raster_tiles=len(tiles), raster_tile_cells=cells)
    return View(
        image,
        elev.astype(np.float32),
        depth.astype(np.float32),
        litf < 0.5,
        haz,
        wxy.astype(np.float32),
        rad,
        info,
        alt_m,
        gain,
    )


def noisy_image(view: View, seed: int) -> np.ndarray:
    """The 8-bit image of ``view`` with the sensor noise of ``seed`` (same bytes as ``render_view(seed=seed)``)."""
    return sensor(view.radiance, view.exposure, np.random.default_rng([int(seed) & 0xFFFFFFFF, 0x5EED]))


def truth_at(
    scene: Scene,
    camera: Camera,
    pose: Pose,
    sun: Sun,
    u: np.ndarray,
    v: np.ndarray,
    *,
    supersample: int = 2,
    max_cells: int = MAX_CELLS,
) -> dict[str, np.ndarray]:
    """Ground truth at integer pixel centres (u, v) as :func:`render_view` computes it, without an image.

    This is the ``raster="view"`` truth. A tiled render has the same slope and roughness rule (the view
    raster, or the view's ``truth_cell`` when it is coarser), taken at its own hits, and its own shadows and
    elevations: those see the relief the view raster smooths away.

    The raster covers only the bounding box of the pixels (same cell and grid as the whole
    view's); shadow is the sub-pixel lit fraction < 1/2, as in the render. Centre rays start
    from the conservative coarse bound instead of the neighbouring sub-pixel hits. Returns
    flat arrays ``elevation``, ``depth``, ``world_xy`` (N x 2), ``hazard``, ``shadow``.
    """
    _check_pose(camera, pose)
    _check_args(sun, supersample, max_cells)
    ss = int(supersample)
    u = np.asarray(u, dtype=np.int64).ravel()
    v = np.asarray(v, dtype=np.int64).ravel()
    if u.size == 0 or u.min() < 0 or v.min() < 0 or u.max() >= camera.width or v.max() >= camera.height:
        raise RenderError("truth_at: pixels must lie inside the image")
    box = (int(u.min()), int(v.min()), int(u.max()) + 1, int(v.max()) + 1)
    cs = _Caster(scene, camera, pose, sun, ss, box=box, max_cells=max_cells)
    off = (np.arange(ss) + 0.5) / ss - 0.5
    ou, ov = np.meshgrid(off, off)
    su = (u[:, None] + ou.ravel()[None, :]).ravel()
    sv = (v[:, None] + ov.ravel()[None, :]).ravel()
    d, t = cs.march(su, sv, cs.coarse_start(su, sv))
    X = cs.C + t[:, None] * d
    vis, cos_i, _ = cs.lit(X, cs.shadow_level())
    litf = (vis * (cos_i > 0)).reshape(u.size, ss * ss).mean(axis=1)
    shadow = litf < 0.5
    uf, vf = u.astype(np.float64), v.astype(np.float64)
    dp, tp = cs.march(uf, vf, cs.coarse_start(uf, vf))
    tr = cs.truth(dp, tp, shadow)
    tr["shadow"] = shadow
    return tr
