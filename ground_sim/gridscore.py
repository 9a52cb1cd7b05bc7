"""Scoring a compact Result (world grids) per pixel of i1, from ground truth (DESIGN.md "Scoring convention").

The flight side returns hazard states on a world grid, not per pixel. To score
them with the thesis's pixel-level metrics, each pixel of i1 is taken to the
ground point it truly sees: ``X = C + z R^T K^-1 [u, v, 1]`` with the *true*
pose of frame 0 (``pair.json`` meta ``true_frames``, else the reported one) and
the true depth ``z`` (``gt_depth_i1.npy``); its true X, Y selects the grid cell
(nearest cell centre; rows toward -Y, :mod:`protocol.grids`). The pixel is
*called safe* when that cell's state is SAFE; unknown, unsafe, OUTSIDE and off
the grid are not called safe. The scored pixels are those whose true ground the
last frame sees, where the truth is finite: the area `hazard-hil score` scores
(DESIGN.md's covered area). Until stop 64 a pixel off the grid or OUTSIDE left
the count, so a Result that mapped less scored a higher CDI (an all-unknown
answer on an 8x8 corner: 69 % against 22 % on the whole grid; QA 64a). The
share of the scored pixels the grid maps is ``mapped_pct``. The same true X, Y
reads the elevation grid for the DEM error (nearest cell of the possibly
decimated grid).

Scores come from :mod:`ground_sim.scoring` (confusion, DEM error statistics).

Landing sites (world X, Y) are judged by the design's site rule on the same true ground points
(:func:`judge_site`): the landing Monte Carlo and the HIL run share it.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ground_sim import scoring
from ground_sim.truth import FOOTPRINT_M
from protocol.grids import cells_at
from protocol.pairdir import STATE_OUTSIDE, STATE_SAFE, STATE_UNKNOWN, Camera, Pose, true_poses


def true_pose_upper(pair: Any) -> Pose:
    """The true pose of frame 0 (:func:`protocol.pairdir.true_poses`)."""
    return true_poses(pair)[0]


def pixel_ground(camera: Camera, pose: Pose, depth: np.ndarray) -> np.ndarray:
    """World points (H, W, 3) of every pixel from its camera z-depth: ``X = C + z R^T K^-1 [u, v, 1]``."""
    h, w = depth.shape
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    d = np.asarray(depth, np.float64)
    rays = np.stack([(u - camera.cx) / camera.fx * d, (v - camera.cy) / camera.fy * d, d], axis=-1)
    return pose.position + rays @ pose.R


def pixel_ground_xy(camera: Camera, pose: Pose, depth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """True world X, Y of every pixel from its camera z-depth (:func:`pixel_ground`)."""
    world = pixel_ground(camera, pose, depth)
    return world[..., 0], world[..., 1]


def states_at_pixels(
    state_grid: np.ndarray, origin_xy: tuple[float, float], cell_m: float, x: np.ndarray, y: np.ndarray
) -> np.ndarray:
    """uint8 state of the grid cell under each pixel's ground point; OUTSIDE off the grid."""
    i, j, ok = cells_at(x, y, origin_xy, cell_m, state_grid.shape)
    out = np.full(x.shape, STATE_OUTSIDE, np.uint8)
    out[ok] = np.asarray(state_grid)[i[ok], j[ok]]
    return out


def values_at_pixels(
    grid: np.ndarray, origin_xy: tuple[float, float], cell_m: float, x: np.ndarray, y: np.ndarray
) -> np.ndarray:
    """float32 value of the grid cell under each pixel's ground point; NaN off the grid."""
    i, j, ok = cells_at(x, y, origin_xy, cell_m, grid.shape)
    out = np.full(x.shape, np.nan, np.float32)
    out[ok] = np.asarray(grid, np.float32)[i[ok], j[ok]]
    return out


def called_map(states: np.ndarray, scored: np.ndarray) -> np.ndarray:
    """Per-pixel hazard-like map for :func:`ground_sim.scoring.confusion`: 0 called safe, 1 not (OUTSIDE and off the
    grid too), NaN not ``scored``."""
    out = np.where(states == STATE_SAFE, 0.0, 1.0).astype(np.float32)
    out[~scored] = np.nan
    return out


def scored_area(pair: Any, world: np.ndarray) -> np.ndarray:
    """The pixels of frame 0 scored: their true ground (``world``, H x W x 3) is in the last frame's view and the
    truth is finite there (DESIGN.md's covered area; ``hazard-hil score`` scores the same)."""
    from ground_sim.library import covered

    h, w = world.shape[:2]
    seen = covered(pair.camera, true_poses(pair)[-1], world.reshape(-1, 3)).reshape(h, w)
    return seen & np.isfinite(pair.truth["hazard"]) & np.isfinite(pair.truth["depth"])


def score_grids(
    pair: Any,
    state_grid: np.ndarray,
    origin_xy: tuple[float, float],
    cell_m: float,
    elevation: np.ndarray | None = None,
    elevation_origin_xy: tuple[float, float] | None = None,
    elevation_cell_m: float | None = None,
    elevation_filled: np.ndarray | None = None,
) -> tuple[dict[str, float], np.ndarray]:
    """Pixel-level scores of a compact Result against ``pair``'s ground truth; also the per-pixel called map.

    ``elevation`` is the float grid in metres (NaN = none) on its own geometry (the world grid
    decimated by the Result's ``elevation_step``: :func:`protocol.grids.decimated_geometry`);
    ``elevation_filled`` (bool, its shape; optional) marks its gap fills. The scores then also hold
    ``dem_coverage_pct`` (scored pixels with an elevation) and ``dem_filled_pct`` (those whose elevation
    is a fill), both in % of the scored pixels.
    """
    truth = pair.truth
    if "depth" not in truth or "hazard" not in truth:
        raise scoring.ScoringInputError("grid scoring needs ground-truth depth and hazard (gt_depth_i1.npy, ...)")
    world = pixel_ground(pair.camera, true_pose_upper(pair), truth["depth"])
    x, y = world[..., 0], world[..., 1]
    origin = (float(origin_xy[0]), float(origin_xy[1]))
    states = states_at_pixels(state_grid, origin, float(cell_m), x, y)
    scored = scored_area(pair, world)
    called = called_map(states, scored)
    c = scoring.confusion(called, truth["hazard"], scored)
    out = {f"{k}_pct" if k in ("tp", "tn", "fp", "fn", "cdi") else k: float(v) for k, v in c.items()}
    n_scored = max(1, int(scored.sum()))
    out["unknown_pct"] = float(100.0 * np.count_nonzero(scored & (states == STATE_UNKNOWN)) / n_scored)
    out["mapped_pct"] = float(100.0 * np.count_nonzero(scored & (states != STATE_OUTSIDE)) / n_scored)
    if "elevation" in truth and elevation is not None:
        e_origin = origin if elevation_origin_xy is None else elevation_origin_xy
        e_cell = float(cell_m if elevation_cell_m is None else elevation_cell_m)
        est = values_at_pixels(elevation, e_origin, e_cell, x, y)
        out.update({f"dem_{k}": float(v) for k, v in scoring.dem_error_stats(est, truth["elevation"], scored).items()})
        n = max(1, int(scored.sum()))
        has = scored & np.isfinite(est)
        out["dem_coverage_pct"] = float(100.0 * np.count_nonzero(has) / n)
        if elevation_filled is not None:
            if np.shape(elevation_filled) != np.shape(elevation):
                raise scoring.ScoringInputError(
                    f"elevation_filled shape {np.shape(elevation_filled)} != elevation {np.shape(elevation)}"
                )
            fill = values_at_pixels(np.asarray(elevation_filled, np.float32), e_origin, e_cell, x, y) > 0.5
            out["dem_filled_pct"] = float(100.0 * np.count_nonzero(has & fill) / n)
    return out, called


def judge_site(
    site_xy: tuple[float, float], world_xy: np.ndarray, hazard: np.ndarray, radius_m: float = FOOTPRINT_M / 2
) -> dict[str, Any]:
    """DESIGN.md site rule on frame-0 truth: safe iff every pixel whose true ground (X, Y) lies within
    ``radius_m`` of the site has hazard < 1. A footprint that falls between pixel centres (ground sampled
    coarser than the footprint) is judged by the pixel whose ground cell holds it (:func:`_cell_holding`).
    A footprint that holds no pixel (off the image), reaches past the image's edge on a side whose border pixels it
    holds (part of it unseen; on a grid sheared strongly enough a footprint can cross an edge between border
    centres unseen by this test, as by the one before stop 75), holds a
    pixel whose truth is unknown (NaN: a derived truth where too little ground was seen) or whose pixels touch
    one without a ground point (NaN depth: where it lies is unknown) cannot be confirmed and is judged unsafe
    (:func:`site_verdict`: not confirmed, unless a pixel of it is truly unsafe).

    ``world_xy`` is (H, W, 2), each pixel's true ground X, Y (:func:`pixel_ground_xy`). Also returns ``uv``,
    the pixel whose ground is nearest the site (None for a site that is not a finite point), to draw it."""
    X, Y = world_xy[..., 0], world_xy[..., 1]
    sx, sy = float(site_xy[0]), float(site_xy[1])
    if not (np.isfinite(sx) and np.isfinite(sy)):
        return {"safe": False, "n_px": 0, "n_unsafe": 0, "incomplete": True, "uv": None}
    d2 = (X - sx) ** 2 + (Y - sy) ** 2
    near = d2 <= radius_m * radius_m
    if not near.any():
        near = _cell_holding(world_xy, d2)
    n = int(np.count_nonzero(near))
    unknown = near & np.isnan(hazard)  # truth that cannot say (a derived one, where too little ground is seen)
    unsafe = int(np.count_nonzero(near & ~unknown & ~(hazard < 1.0)))
    partial = _past_the_border(world_xy, near, sx, sy, radius_m) or bool(unknown.any())
    if n:
        # a pixel without a ground point (NaN depth) has no place in the world, so it is never "near": one beside
        # the footprint's pixels may hide part of it. A rock's pixels with NaN depth left a site over it judged
        # clear (review of stop 66); such a footprint is not confirmed
        vs, us = np.nonzero(near)
        ring = world_xy[max(0, vs.min() - 1) : vs.max() + 2, max(0, us.min() - 1) : us.max() + 2]
        partial = partial or not bool(np.isfinite(ring).all())
    uv = None
    if n:  # the footprint is on the image: the pixel whose ground is nearest its centre
        v, u = np.unravel_index(int(np.nanargmin(d2)), d2.shape)
        uv = (int(u), int(v))
    return {
        "safe": n > 0 and unsafe == 0 and not partial,
        "n_px": n,
        "n_unsafe": unsafe,
        "incomplete": partial or n == 0,
        "uv": uv,
    }


def _past_the_border(world_xy: np.ndarray, near: np.ndarray, sx: float, sy: float, radius_m: float) -> bool:
    """Whether the footprint may reach past the image, on the sides whose border pixels it holds.

    The image ends half a pixel past its border pixels' centres: on the ground, ``e = w_b + (w_b - w_i) / 2``
    with ``w_b`` a border pixel's ground and ``w_i`` its inward neighbour's. The footprint is wholly seen when
    the site lies more than ``radius_m`` from that edge line. The edge is known at samples ``s`` apart, and the
    nearest sample is at most ``s / 2`` along the line from the foot of the perpendicular, so the distance to
    the line is at least ``sqrt(d^2 - s^2 / 4)`` (``d`` the nearest sample's distance). A footprint touching a
    border pixel's centre was called unconfirmed although it ended a tenth of a pixel inside (QA of stop 75).
    An edge without a ground point (NaN) may hide anything: reached."""
    h, w = near.shape
    sides = []
    if near[0].any():
        sides.append((world_xy[0], world_xy[min(1, h - 1)]))
    if near[-1].any():
        sides.append((world_xy[-1], world_xy[max(h - 2, 0)]))
    if near[:, 0].any():
        sides.append((world_xy[:, 0], world_xy[:, min(1, w - 1)]))
    if near[:, -1].any():
        sides.append((world_xy[:, -1], world_xy[:, max(w - 2, 0)]))
    for border, inner in sides:
        if h < 2 or w < 2:
            return True  # a line of pixels has no inward neighbour to size its edge by
        edge = border.astype(np.float64) + 0.5 * (border.astype(np.float64) - inner)
        if not np.isfinite(edge).all():
            return True
        step = float(np.hypot(*np.diff(edge, axis=0).T).max()) if len(edge) > 1 else 0.0
        d2 = float(np.min((edge[:, 0] - sx) ** 2 + (edge[:, 1] - sy) ** 2))
        if d2 - step * step / 4 < radius_m * radius_m:
            return True
    return False


def _cell_holding(world_xy: np.ndarray, d2: np.ndarray) -> np.ndarray:
    """The pixel whose ground cell holds a footprint that falls between pixel centres (a ground sample coarser
    than the footprint, 3-5 m at 2000 m on an approach, where no centre lies within 1.5 m and the rule would be
    vacuous): the nearest pixel, when the site lies within half its cell's diagonal. Each side of the cell is
    the shorter step to the pixel's two neighbours on that axis; neighbours whose steps differ by more than 2x
    (a rim hiding ground behind it) or that have no ground (a hole) leave the site unconfirmed, as does a site
    past the last pixel's cell (off the image)."""
    near = np.zeros(d2.shape, bool)
    if not np.isfinite(d2).any():
        return near
    v, u = np.unravel_index(int(np.nanargmin(d2)), d2.shape)
    h, w = d2.shape
    sides = []
    for dv, du in ((0, 1), (1, 0)):
        steps = [
            float(np.hypot(*(world_xy[vv, uu, :2] - world_xy[v, u, :2])))
            for vv, uu in ((v + dv, u + du), (v - dv, u - du))
            if 0 <= vv < h and 0 <= uu < w
        ]
        if not steps or not np.isfinite(steps).all() or max(steps) > 2.0 * min(steps):
            return near
        sides.append(min(steps))
    if d2[v, u] <= 0.25 * (sides[0] ** 2 + sides[1] ** 2):
        near[v, u] = True
    return near


def site_verdict(judged: dict[str, Any]) -> bool | None:
    """A :func:`judge_site` result in one word: True truly clear, False not (an unsafe pixel in the footprint, or
    a wholly seen footprint that is not clear), None not confirmed (the image does not hold the whole footprint
    and sees no hazard in it). Scores count None as not safe; the HIL judges it on another pair, pictures draw it
    black."""
    if judged["safe"]:
        return True
    return None if judged["incomplete"] and judged["n_unsafe"] == 0 else False


def complete_truth(pair: Any) -> str | None:
    """Give ``pair.truth`` a ``hazard`` when the pair has none but DESIGN.md's truth files give one: the rules
    applied to each pixel's true ground point (:func:`ground_sim.truth.hazard_from_points`), its X, Y from
    ``gt_depth`` through frame 0's true pose, its Z from ``gt_elevation``, with ``gt_shadow`` when present.

    Returns a note saying so (for the scores' reader: such a truth sees only the relief the camera resolves),
    None when the pair carries ``gt_hazard_i1.npy`` or lacks the files to derive one. When the files give no
    footprint's hazard at all, ``pair.truth`` is left without one and the note says why (every caller then has
    no truth to score against, as without the files)."""
    truth = pair.truth
    if "hazard" in truth or "depth" not in truth or "elevation" not in truth:
        return None
    from ground_sim.truth import FOOTPRINT_M, hazard_from_points, truth_grid

    points = pixel_ground(pair.camera, true_pose_upper(pair), truth["depth"])
    points[..., 2] = truth["elevation"]
    hazard = hazard_from_points(points, truth.get("shadow"))
    known = float(np.mean(np.isfinite(hazard)))
    if known == 0.0:  # why none could be derived, from what the derivation itself used
        cell = truth_grid(points)[0]
        if not np.isfinite(points).all(axis=-1).any():
            why = "gt_depth_i1.npy and gt_elevation_i1.npy give no pixel a finite ground point"
        elif cell > FOOTPRINT_M / 2:
            why = (
                f"frame 0 samples the ground every {cell:.2g} m (its coarser direction), over half the 3 m "
                "footprint: its slope cannot be told"
            )
        else:
            why = "no 3 m footprint of frame 0 is half seen"
        return f"no gt_hazard_i1.npy, and none can be derived from gt_elevation and gt_depth: {why}"
    truth["hazard"] = hazard
    # the shadow counts too: the note named two of the three files it came from (QA of stop 79)
    files = (
        "gt_elevation, gt_depth and gt_shadow"
        if "shadow" in truth
        else "gt_elevation and gt_depth (no gt_shadow_i1.npy: shadow not counted)"
    )
    return (
        f"no gt_hazard_i1.npy: the true hazard was derived from {files} by DESIGN.md's "
        f"rules at the camera's resolution ({100 * known:.0f} % of frame 0 resolved; docs/design.md)"
    )


def judge_sites(pair: Any, sites_xy: list[tuple[float, float]]) -> list[dict[str, Any]]:
    """:func:`judge_site` for each site, on ``pair``'s truth of frame 0 (its depth and hazard)."""
    truth = pair.truth
    if "depth" not in truth or "hazard" not in truth:
        raise scoring.ScoringInputError("judging sites needs ground-truth depth and hazard (gt_depth_i1.npy, ...)")
    world = np.stack(pixel_ground_xy(pair.camera, true_pose_upper(pair), truth["depth"]), axis=-1)
    return [judge_site(xy, world, truth["hazard"]) for xy in sites_xy]
