"""The anytime plan of the flight pipeline: what each stage costs, what is kept in reserve, and the clock.

The pipeline runs against a deadline on a processor of unknown speed (the HIL's emulated budgets, a board).
Stage costs are unthrottled CPU seconds on a reference host at ``REF_PIXELS``; a stage that cannot stop
part-way starts only when its cost, times the slowdown the clock has learned (:class:`Clock`), fits before
the reserve the stages after it need (:func:`reserves`). The mapping reserve follows the pair's size
(:func:`mapping_cost_s`, fitted by ``bench/fit_mapping_cost.py``), and a flight process that has run pairs
plans from what their reserved work really took (:func:`measured_reserve_ratio`). docs/hil.md, "How our
flight software plans for it".
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from protocol.pairdir import Camera, Pose

from .georef import backproject
from .mapping import grid_extent, ground_sample_distance
from .params import Params
from .sweep import scaled_camera

# Flight v2's stage costs for the anytime logic, unthrottled CPU seconds at REF_PIXELS (512^2, this
# host, median of 3): a stage that cannot stop part-way starts only when its cost fits before the reserve.
REF_PIXELS = 512 * 512
MAX_GRID_CELLS_PER_PIXEL = 2.0  # the world grid's bound (an approach view at 512^2 has 0.6 cells per pixel)
# shading wall cue (relative brightness at footprint scale): two Gaussian blurs on copies small enough that
# the cost no longer follows the sigma (shading.wide_blur; it was 0.62 ms per px of sigma, 37 ms at 60 px):
# the whole shadow stage now takes 4-7 ms at 512^2 from 50 to 1200 m (stop 30). The clock learns the real
# slowdown from the stage only when it cost more than that (Clock.learn ignores stages under 5 ms)
WALL_CUE_S = 0.001
SHADOW_BASE_S = 0.004  # the shadow stage without the wall cue
MAX_LEARNED_SCALE = 3.0  # the learned slowdown stays within 3x the supervisor's 1 / CPU fraction
# the most CPU cold caches add to a stage at 1-2 % duty: measured <= 1.4x on rad750 and gr740 over pose
# refinement, the DEM and the shadow stage (HIL telemetry against the same pairs unthrottled, 2026-11-24)
COLD_CACHE_CPU = 0.4
ROCKS_S = 0.03  # Harris rock mask
# the shading slope stage (photoclinometry.py, with the caster search) and what still follows it, the hazard call
# and the sites, at 512^2 on one core: at most 9.1 ms and 46.5 ms on the 64 tuning pairs of
# bench/fit_mapping_cost.py (8.4 and 49 ms held-out; stop 45), about 1.1x kept. Stop 28's 16 and 65 ms had become
# 2x the stages' cost: with the mapping reserve refitted, rad750 skipped the shading slope with 5 s unused
SHADING_SLOPE_S = 0.010
CASTER_MAX_PX = 16  # the caster search's reach (px): shadow.caster_distance costs O(reach) per pixel
AFTER_SLOPE_S = 0.050
# pose refinement, per refined frame pair: 31-39 ms CPU, median 34, on the 32 pairs of tuning seed 0 (one core,
# quiet host, stop 45). It was 0.06 (stop 20's loaded host): a reference above the stage's real cost hides the
# slowdown from Clock.learn, and rad750's reserves were planned at 77x while the mapping ran at 110x
REFINE_S = 0.035
# the full DEM costs at least this many times the coarse one (CPU, 512^2, one core): 3.60 at least, 4.39 p10, 5.16
# median on the 64 tuning pairs of the four eval cases (seeds 0-1); held-out seeds 1000-1001: 3.52, 4.42, 5.19
# (stop 46). Half the least: a full DEM that cannot finish in the time left is not started (gr740 started it with
# 0.7-6.6 s for a 10-18 s sweep and cut it, and its Results came back that much later)
FULL_OVER_COARSE_MIN = 2.0


def full_dem_fits(room_s: float, coarse_wall_s: float | None) -> bool:
    """Whether a full DEM can finish in ``room_s`` (wall s before the mapping reserve), knowing that this pair's
    coarse DEM took ``coarse_wall_s`` (None: no coarse DEM to judge by, so it is tried). The full sweep's cost
    follows the coarse one's at 3.5-8x (``FULL_OVER_COARSE_MIN``), on the same processor and the same pair."""
    return coarse_wall_s is None or room_s >= FULL_OVER_COARSE_MIN * coarse_wall_s


# what the stages after the DEM (georef, grid, slope, shading slope, hazard call, sites) cost on one core,
# unthrottled s per REF_PIXELS of image, of covered pixels and of world-grid cells: non-negative least squares
# over 64 tuning pairs (seeds 0-1, all four eval cases, 50-1200 m; bench/fit_mapping_cost.py, stop 45). Measured /
# model on 64 held-out pairs, two runs: median 1.01 / 0.98, p90 1.06 / 1.04, max 1.17 / 1.09; synthetic pairs of
# 384-1536 px: 0.59-1.19. Stop 29's constants (0.052, 0.083, 0.170) had become 1.7x the cost
MAP_IMAGE_S = 0.027
MAP_COVERED_S = 0.057
MAP_CELLS_S = 0.103

# the stages the mapping reserve covers: what runs after the DEM (measured_reserve_ratio sums their wall time)
MAPPING_STAGES = ("georef", "grid", "slope", "shading_slope", "hazard", "sites")
# planning from what the reserved work really took on the previous pairs (Clock.reserve_scale): kept x this.
# Demo pairs (snapdragon801 at 21 % duty, 2026-12-02): the mapping stages and the fusion + output took 2.5-3.4 wall s
# per reserved second against the nominal 4.75; planning with the largest of the last pairs x this covers that spread
MEASURED_RESERVE_MARGIN = 1.25


def mapping_cost_s(n_image: int, n_covered: int, n_cells: int) -> float:
    """Modelled CPU s of the stages after the DEM::

        t = (MAP_IMAGE_S n_image + MAP_COVERED_S n_covered + MAP_CELLS_S n_cells) / REF_PIXELS

    Oblique views put up to 2.5x more world-grid cells over the same covered pixels than nadir ones
    (a grid at the median ground sample distance over ground whose far part is coarser), and the slope
    and grid stages cost per cell: 0.11 s on nadir pairs, 0.17-0.20 s on approach pairs at 512^2."""
    return (MAP_IMAGE_S * n_image + MAP_COVERED_S * n_covered + MAP_CELLS_S * n_cells) / REF_PIXELS


def measured_reserve_ratio(
    timings: Mapping[str, Mapping[str, float]],
    info: Mapping[str, Any],
    level: str,
    after_wall_s: float,
    after_s: float,
    pixels: int = REF_PIXELS,
) -> float | None:
    """Wall seconds the reserved work took per unthrottled second reserved for it, on one pair.

    ``ratio = (sum of the MAPPING_STAGES' wall time + after_wall_s) / (info["mapping_reserve_s"] + after_s - s)``:
    the pair's planned mapping reserve and what the caller reserved for its own work after the pipeline
    (``after_wall_s``: what that work took). Only a pair with a DEM (full or coarse: the mapping stages map
    it on the same grid) measures the work its reserve was planned for: None for an image-only pair (its
    mapping stages have no DEM to map and cost a fraction of it), or when the pair planned no mapping reserve
    (the v1 flow of ``thesis``). A pair that skipped a mapping stage measures nothing either, except the
    shading slope alone, the stage a tight plan gives up first: ``s`` is then its reserved cost
    (``SHADING_SLOPE_S`` at ``pixels``), else 0. Without that, slow budgets that skipped it on every pair never
    measured anything and planned every pair at the first pair's margins (gr740, stop 45). The flight
    process passes the recent pairs' largest ratio as ``reserve_measured``.
    """
    mapping = float(info.get("mapping_reserve_s", 0.0))
    skipped = set(info.get("skipped", ())) & set(MAPPING_STAGES)
    if (
        level not in ("full", "coarse")
        or skipped - {"shading_slope"}
        or not (mapping > 0 and after_s >= 0 and after_wall_s >= 0)
    ):
        return None
    reserved = mapping + after_s - (SHADING_SLOPE_S * pixels / REF_PIXELS if skipped else 0.0)
    if reserved <= 0:
        return None
    needed = [k for k in MAPPING_STAGES if k != "shading_slope"]  # no sun, no shading slope: not a degradation
    if any(k not in timings for k in needed):
        return None
    wall = sum(float(timings[k]["wall_s"]) for k in MAPPING_STAGES if k in timings)
    ratio = (wall + after_wall_s) / reserved
    return ratio if math.isfinite(ratio) and ratio > 0 else None


def grid_cells_estimate(camera: Camera, pose: Pose, covered: np.ndarray, z: float, cell_m: float | None) -> int:
    """The world grid's size (cells) before there is a DEM: the pipeline's ``_ground_grid`` rule on the covered
    pixels backprojected to the plane ``Z = z``, every ``2^k``-th pixel (``2^k <= min side / 64``, at most
    8: about 0.2 ms at 512^2); each side gains the ``2^k - 1`` pixels the subsample skips at its far end."""
    cov_full = np.asarray(covered, bool)
    level = int(max(0, min(3, math.floor(math.log2(max(1, min(cov_full.shape) // 64))))))
    step = 1 << level
    cam = scaled_camera(camera, level)
    cov = cov_full[::step, ::step][: cam.height, : cam.width]
    if not cov.any():
        return 0
    X, Y = backproject(cam, pose, np.full((cam.height, cam.width), z, np.float64))
    cell = cell_m or ground_sample_distance(X, Y, cov, 50.0) / step
    if not (math.isfinite(cell) and cell > 0):
        return int(cov.sum()) * step * step
    _, shape = grid_extent(np.where(cov, X, np.nan), np.where(cov, Y, np.nan), cell)
    return int(min((shape[0] + step - 1) * (shape[1] + step - 1), MAX_GRID_CELLS_PER_PIXEL * cov_full.size))


def reserves(p: Params) -> dict[str, tuple[tuple[str, ...], float]]:
    """What each deadline reserve of the v2 flow must cover: its name -> (the timed stages that run
    after its gate, the reserve in unthrottled s at ``REF_PIXELS``). ``bench/bench_pipeline.py
    --check-reserves`` compares them with measured stage times; a reserve shorter than its stages lets a
    tight deadline pass while they still run."""
    return {
        "mapping_reserve_s": (("georef", "grid", "slope", "shading_slope", "hazard", "sites"), p.mapping_reserve_s),
        "SHADING_SLOPE_S + AFTER_SLOPE_S": (("shading_slope", "hazard", "sites"), SHADING_SLOPE_S + AFTER_SLOPE_S),
        "AFTER_SLOPE_S": (("hazard", "sites"), AFTER_SLOPE_S),
    }


def reserve_table(
    p: Params, stage_cpu_s: dict[str, float], pixels: int = REF_PIXELS, mapping_s: float | None = None
) -> list[tuple[str, tuple[str, ...], float, float]]:
    """Each reserve (:func:`reserves`) against the CPU time its stages took on a ``pixels``-pixel pair:
    ``(name, stages, needed s, reserve s)``, the reserve scaled to that pair as the pipeline scales it.
    ``mapping_s``: the mapping reserve the pipeline planned for that pair (``info["mapping_reserve_s"]``,
    from :func:`mapping_cost_s` when ``p.mapping_reserve_margin > 0``) instead of the fixed one."""
    scale = pixels / REF_PIXELS
    return [
        (
            name,
            stages,
            sum(stage_cpu_s.get(k, 0.0) for k in stages),
            mapping_s if (mapping_s is not None and name == "mapping_reserve_s") else reserve * scale,
        )
        for name, (stages, reserve) in reserves(p).items()
    ]


def reserve_shortfalls(
    p: Params, stage_cpu_s: dict[str, float], pixels: int = REF_PIXELS, mapping_s: float | None = None
) -> list[tuple[str, float, float]]:
    """The reserves shorter than their stages (:func:`reserve_table`): ``(name, needed s, reserve s)``."""
    return [(n, need, have) for n, _, need, have in reserve_table(p, stage_cpu_s, pixels, mapping_s) if need > have]


@dataclass
class Clock:
    """The deadline in ``time.monotonic()`` seconds; reserves are unthrottled seconds x :meth:`reserve_scale`.

    ``scale`` is the emulated processor's slowdown (1 / CPU fraction): a reserve that covers the
    mapping stages on this host covers them on a processor ``scale`` times slower. ``measured``, when
    the caller has it, is what the reserved work really took on its previous pairs: wall seconds per
    reserved unthrottled second (:func:`measured_reserve_ratio`), which also holds the host's speed
    against the reference costs the reserves are written in.
    """

    deadline: float | None
    scale: float = 1.0
    after: float = 0.0  # the caller's work after the pipeline returns, unthrottled s (reserved x reserve_scale())
    measured: float | None = None

    def __post_init__(self) -> None:
        self.base = self.scale

    def learn(self, ref_cpu_s: float, wall_s: float, cpu_s: float = 0.0) -> None:
        """Raise ``scale`` to the slowdown a stage of known unthrottled cost really saw (at most
        ``MAX_LEARNED_SCALE`` x the given one). At duty cycles of a few % every stop leaves the caches
        cold, and a busy host steals time: the real slowdown can exceed 1 / CPU fraction by ~2x
        (docs/BENCHMARKS.md, HIL latency per budget), and reserves planned with it would be too short.

        The stage's unthrottled cost is ``max(ref_cpu_s, cpu_s / a)``, ``cpu_s`` its measured CPU time
        and ``a = 1 + COLD_CACHE_CPU * min(1, (base - 1) / 20)`` the CPU inflation cold caches can explain
        (none at full speed, up to 1.4x from 5 % duty down): a stage that costs more on this pair's data,
        or on a process's first call, is not a slowdown. (Taking ``ref_cpu_s`` alone, a shadow stage of
        0.034 s CPU against the 0.014 s reference read as an 8x slowdown on snapdragon801, and the demo's
        200/100 skipped its DEM. With up to 2x, the first pose refinement of a fresh process, 2.1x its
        steady CPU on rad750, read as a 2.2x slowdown and the first pair went image-only.)"""
        allowance = 1.0 + COLD_CACHE_CPU * min(1.0, max(0.0, self.base - 1.0) / 20.0)
        ref = max(ref_cpu_s, cpu_s / allowance)
        if ref > 0.005 and wall_s > 0:
            self.scale = max(self.scale, min(wall_s / ref, MAX_LEARNED_SCALE * self.base))

    def reserve_scale(self) -> float:
        """Wall seconds to keep per unthrottled second of reserve.

        Without a measurement: ``scale``. With one: ``measured x MEASURED_RESERVE_MARGIN``, what the reserved
        work really cost on the previous pairs. The reserves are modelled costs on a reference host with a
        margin, so ``scale`` kept 0.5-0.8 s of a 2 s deadline unused on snapdragon801; and ``scale`` is raised
        by the slowest of two short early stages (pose refinement, shadows: 0.05 s of CPU), whose wall time
        at 21 % duty swung it from 4.75 to 5.5-7.7 on 4 of 8 pairs of one descent and skipped their DEM. The
        reserved work lasts about a second of wall time: its own past cost predicts it better than a spike
        does (docs/hil.md, "How our flight software plans for it").
        """
        if self.measured is None:
            return self.scale
        return self.measured * MEASURED_RESERVE_MARGIN

    def before(self, reserve_s: float) -> float | None:
        """The time by which work must stop to leave ``reserve_s`` (unthrottled) for what follows."""
        return None if self.deadline is None else self.deadline - (reserve_s + self.after) * self.reserve_scale()

    def ok(self, reserve_s: float = 0.0) -> bool:
        """True while ``reserve_s`` (unthrottled) still fits before the deadline."""
        if self.deadline is None:
            return True
        return time.monotonic() + (reserve_s + self.after) * self.reserve_scale() < self.deadline

    def decide(self, info: dict[str, Any], stage: str, reserve_s: float) -> bool:
        """:meth:`ok`, with the figures it was decided on kept in ``info["plan"]`` (wall s, as the flight runs):
        ``<stage>_left_s`` (to the deadline), ``<stage>_need_s`` (kept for the work after the stage),
        and the ``scale`` they were planned at (``measured`` 1 when it is :func:`measured_reserve_ratio`'s).
        A degraded Result's telemetry then says why a stage did not run, not only that it did not."""
        go = self.ok(reserve_s)
        if self.deadline is not None:
            plan = info.setdefault("plan", {})
            plan[f"{stage}_left_s"] = self.deadline - time.monotonic()
            plan[f"{stage}_need_s"] = (reserve_s + self.after) * self.reserve_scale()
            plan["scale"] = self.reserve_scale()
            plan["measured"] = int(self.measured is not None)
        return go
