"""Fusion over the descent (issue 10): one world-grid map that every new result refines.

Each pipeline result is a :class:`flight_sw.mapping.HazardGrid` on its own world grid (its cell
is the reference image's ground sample distance, so lower results are finer). The fused map
holds, per cell of its own grid, the log-odds that the cell is safe (a binary Bayes filter, as in
occupancy-grid mapping: Moravec & Elfes 1985, Thrun et al. *Probabilistic Robotics* ch. 9, with
the discounting below)::

    l_i  = logit(P_i(safe)), clipped to [-l_max, +l_max]     (the result's own evidence)
    l_i  = -l_unsafe                                        where the result makes a hazard call (below)
    l_0  = max(0, logit(prior_p))                           (the prior every P_i holds)
    e    = L - l_0                                          (what earlier results added to the prior)
    L   <- l_i + c(e)                                       (the first result to map a cell: L = l_i)
    c(e) = w e    if e > 0
           w_a e  if e <= 0 and no hazard call has entered the cell
           e      otherwise
    L    = l_0 where no result has had evidence yet         (mapped, but nothing measured: the prior)

**The newest result enters whole.** Lower results are finer and see hazards a higher, coarser one
blurred away (a 3 m footprint spans 2 cells at 500 m and 10 at 100 m), so the map takes each new
result's P(safe) as it is, and adds what the earlier results said beyond the prior: their
evidence for and against it discounted by ``w`` and ``w_a`` (``weight``, ``weight_against``, both
0.3), and a hazard call's evidence whole (a hazard stays a hazard). Successive results share frames
and terrain-dependent errors (a crater wall one result's DEM smooths, the next one's smooths too),
so summing their evidence as if independent (``w = 1``) overstates it, either way round. A map of
one result holds that result's P(safe), but its calls are the rule's below: a cell the result called safe
by its own decision (its pixels' calls) at a P(safe) under ``p_min`` (the mean of its pixels' P) is not
safe on the map. So a descent's first fused Result calls less safe than its pair alone: 2 % of the
safe cells on two snapdragon801 approach pairs at 256 px, CDI 44.0 against 45.2 %, FP 0.03 against 0.05 %
(QA of stop 74).

**Hazard calls and soft unsafe calls.** The pipeline calls a point unsafe for a hazard cue (dark
shadow, rock, wall: P(safe) 0) or where its measured P(safe) is below 0.5 (more likely a hazard
than not). A grid cell's unsafe call is a *hazard call* where the cell's P(safe) is below
``hard_unsafe_p`` (0.05, or unknown) and enters at ``-l_unsafe``; above it the call is *soft*: it
enters as its own P(safe), evidence like any other. Either way the map says what the newest result
that measured the cell said: a cell that result called unsafe is unsafe (``vetoed``), whatever the
evidence sums to. Until 2026-12-03 every unsafe call entered at ``-l_unsafe`` and earlier evidence
against "safe" was carried whole (``hard_unsafe_p = 1``, ``w_a = 1``). A P(safe) of 0.3 from a
coarse, high pair then weighed more than four results 99.9 % sure of the same ground, and on the
tuning streams (docs/benchmarks/multiframe.md, stop 39) fusion left the thesis vertical's Results
0.9 points of CDI below the pair alone (median; 8.2 at worst), with the same FP as now.

**The prior is counted once.** A calibrated P(safe) (:mod:`flight_sw.psafe`) is a posterior: it
already holds the prior share of safe ground, ``logit(P_i) = l_0 + evidence_i``. Adding
posteriors would count that prior once per result: with 81 % safe ground (the share the model was
fitted on) two results that know nothing about a cell would call it 95 % safe. So only
``e = L - l_0`` is carried (Bayes' rule for conditionally independent observations; ``prior_p =
0.5``, ``l_0 = 0``, suits the flat-prior Gaussian P(safe) of :mod:`flight_sw.evidence`). ``l_0`` is
never below 0: a prior for "unsafe" is not added back, which keeps the rule for hazards below.

**No elevation, no evidence.** Where a result has no elevation its P(safe) is only a context prior;
it leaves the cell's evidence as it was, unless the result calls the cell unsafe (a hard cue: dark
shadow). Either way round the prior did harm: added to "safe", the demo showed FP 10 % after an
image-only result; taken against it (the trees give 0.08-0.13 on an image-only pair), one
image-only result at the top of a snapdragon801 approach descent left the fused map of the
full-level pairs below it almost nothing safe (CDI 8 % against 66 % alone, docs/hil.md, stop 32).

**Coarse results.** A result that stopped at the coarse level (a half-resolution DEM over coarse planes: in
one HIL vertical descent its fused map's DEM error was 0.96-1.35 m, against 0.46-0.66 m at the full level)
does not replace what a full-level result measured. Where one has had evidence, the cell keeps that
evidence, its call and its elevation, and the coarse result adds its own evidence against "safe" whole::

    L <- max(L + min(0, l_i - l_0),  l_i + carried)        (a coarse result, where a full one has had evidence)

An unsafe call enters as from any result. Where the coarse result alone says more for "safe", or no
full-level result has had evidence, it enters as any result does. The hazard bound below still holds:
both terms of the max satisfy it. Measured on HIL-like streams with coarse results (tuning seeds,
docs/benchmarks/multiframe.md, stop 33): with "newest enters whole" a coarse Result left the approach's fused
map 9 points of CDI below what the same pair gave the map as an image-only Result.

**Accumulated evidence needs a higher bar, and a call.** A cell the newest result that measured it
did not call safe by its own decision (the pipeline's P floor, slope cap and FP budget) becomes safe
only once the fused P(safe) reaches ``p_accumulate`` *and* at least ``accumulate_calls`` earlier
results called it safe by their own decisions; a cell the newest result called safe needs ``p_min``.
Each result's call is where its safeguards act. On the tuning 4-frame approach descents (seeds 0-9),
the cells that no result called safe but whose summed evidence passed ``p_accumulate`` were 1.4 %
hazards (0.8-2.2 % per descent), against 0.35 % for those an earlier result had called
(docs/benchmarks/multiframe.md, stop 29). Evidence summed over results must not overrule every
result's own refusal. ``accumulate_calls = 0`` is the rule before that. The fused state
(``T = logit(p_min)``, ``n_c`` the results that called the cell safe)::

    safe     L >= T  and  (called safe by the newest result that measured it
                           or  (L >= logit(p_accumulate)  and  n_c >= accumulate_calls))
    unsafe   L <= -(l_max + T)  or  called unsafe by the newest result that measured it
    unknown  otherwise          outside   never mapped

The unsafe bound lies beyond what one result's P(safe) can say (``|l_i| <= l_max``): a cell is
unsafe after a hazard call, or when several results agree that it is very likely unsafe.

**The rule for hazards.** ``c(e) <= max(e, 0)``, and ``c(e) <= e`` once a hazard call has entered
the cell. So by induction ``L - l_0 <= S - n_u (l_unsafe + l_0)``, where ``n_u`` counts the hazard
calls and ``S = sum_j max(0, l_j - l_0)`` the *other* results' evidence for "safe" beyond the prior
(with ``w_a = 1``, ``c(e) <= e`` always, and the bound holds for their net evidence as well). A cell
that results called hazardous ``n_u`` times is called safe again only once ``S`` reaches ``T - l_0 +
n_u (l_unsafe + l_0)`` (:func:`overturn_margin`), however the results are ordered. A soft unsafe call
is evidence like any other: one later result 99.9 % sure can clear a cell one earlier result gave
P(safe) 0.3. With the calibrated settings (``p_min = 0.97``, ``prior_p = 0.806``, ``l_max =
logit(0.999) = 6.9``, ``l_unsafe = 2 l_max``): 17.3 for one unsafe call, i.e. at least four later
results each 99.9 % sure; with the defaults (``p_min = 0.9``, ``prior_p = 0.5``): 16.0, three such
results. No single newer result can overturn a hazard (``l_unsafe > l_max + T``, checked).

**Measured** (docs/benchmarks/multiframe.md): with the calibrated P(safe) the earlier rule (every
later result added ``w l_i``, posteriors summed) gave fused FP up to 4.7 % on held-out 4-frame
descents where the best single pair had 0.15 %, and up to 3.7 % (13 of 320 Results over 1 %) on
HIL-like streams of a scenario's pairs fused in order where each pair alone stayed <= 0.43 %. The
settings (``w = 0.3``, ``l_max = logit(0.999)``, ``p_accumulate = 0.995``) were chosen on tuning
seeds 0-9 of both benchmarks.

**Extent and resampling.** With ``extent="newest"`` (the flight default) the fused map after a
result lies on that result's own grid: the lander's current view at its current resolution, so
the map, the Result message and the time to fuse stay the size of one result while the evidence
of every earlier result that saw those cells is kept. With ``extent="union"`` the map covers
every result's extent, cell-aligned at the finer of its current cell and the new result's, but
never so fine that it exceeds ``max_cells`` (memory is bounded before it is spent; the newest
result's own grid is bounded the same way). Evidence moves between grids conservatively: a
coarse cell that is resampled onto a finer grid gives every finer cell its log-odds (a hazard
anywhere in a coarse cell stays a hazard in all of its parts); finer cells that fall into one
coarser cell give it their minimum (the least safe part decides), and the most unsafe calls and
hazard calls any of them holds. Elevations are taken from
the newest result that measured the cell. A hazard call the newest grid leaves out (a divert, or a pair
whose map is narrower than the one before) is kept as a world point, up to :data:`MAX_KEPT_HAZARDS`
(the oldest go first, and counted: ``kept_dropped``), and put back into the first later grid that covers it,
into every cell inside its old cell as a move would (:func:`_put_back`): with ``"newest"`` a hazard
outside one grid was dropped, and a later result back over it called it safe alone (review of stop 64).
A result's gap fills (:attr:`HazardGrid.dem` where it has no
match: the DEM carried into dark shadow) are only reported, where no result matched the cell (the newest
fill); they are no evidence, and the sites on the fused map do not read them.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from protocol.pairdir import STATE_OUTSIDE, STATE_SAFE, STATE_UNKNOWN, STATE_UNSAFE

from .mapping import HazardGrid
from .psafe import load_model


@dataclass(frozen=True)
class FusionParams:
    """Knobs of the fusion rule (module doc; chosen on tuning seeds 0-9 with the calibrated P(safe))."""

    weight: float = 0.3  # w: the share of earlier evidence for "safe" carried into each new result
    l_max: float = math.log(999.0)  # largest |log-odds| one result's P(safe) contributes (P = 0.999)
    l_unsafe: float = 2.0 * math.log(999.0)  # log-odds against "safe" of an unsafe call (2 l_max)
    p_min: float = 0.9  # fused safe when P(safe) >= this; unsafe when P(safe) <= 1 - this
    extent: str = "newest"  # "newest": the map follows the newest result's grid; "union": all results' extents
    max_cells: int = 2_000_000  # the fused map never holds more cells than this
    prior_p: float = 0.5  # the P(safe) a result's posterior holds with no evidence (counted once)
    p_accumulate: float = 0.995  # a cell the newest measuring result did not call safe needs P(safe) >= this
    accumulate_calls: int = 1  # ... and at least this many earlier results that called it safe (0: no such bar)
    weight_against: float = 0.3  # the share of earlier evidence against "safe" carried where no hazard call entered
    hard_unsafe_p: float = 0.05  # an unsafe call with P(safe) below this enters at -l_unsafe; others are soft (1: none)

    def validate(self) -> None:
        for name in ("weight", "weight_against", "l_max", "l_unsafe"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"fusion: {name} must be a positive number, got {v!r}")
        if not (self.weight <= 1 and self.weight_against <= 1):
            raise ValueError(
                f"fusion: weight and weight_against must be at most 1, got {self.weight!r}, {self.weight_against!r}"
            )
        if not 0.5 < self.p_min < 1:
            raise ValueError(f"fusion: p_min must be in (0.5, 1), got {self.p_min!r}")
        if not self.l_unsafe > self.l_max + logit_threshold(self.p_min):
            raise ValueError("fusion: l_unsafe must exceed l_max + logit(p_min) (an unsafe call must read unsafe)")
        if not 0 < self.prior_p < 1:
            raise ValueError(f"fusion: prior_p must be in (0, 1), got {self.prior_p!r}")
        if not 0 <= self.p_accumulate < 1:
            raise ValueError(f"fusion: p_accumulate must be in [0, 1), got {self.p_accumulate!r}")
        if not 0 < self.hard_unsafe_p <= 1:
            raise ValueError(f"fusion: hard_unsafe_p must be in (0, 1], got {self.hard_unsafe_p!r}")
        if not (isinstance(self.accumulate_calls, int) and 0 <= self.accumulate_calls <= 255):
            raise ValueError(f"fusion: accumulate_calls must be an integer in [0, 255], got {self.accumulate_calls!r}")
        if self.extent not in ("newest", "union"):
            raise ValueError(f"fusion: extent must be 'newest' or 'union', got {self.extent!r}")
        if not (isinstance(self.max_cells, int) and self.max_cells >= 1):
            raise ValueError(f"fusion: max_cells must be a positive integer, got {self.max_cells!r}")


@dataclass
class FusedMap:
    """The fused evidence on a regular world grid (rows toward -Y, as :class:`HazardGrid`)."""

    logodds: np.ndarray  # float32 (rows, cols): accumulated evidence for "safe"
    seen: np.ndarray  # uint8 (rows, cols): how many results mapped the cell (0: never, i.e. outside)
    elevation: np.ndarray  # float32 (rows, cols): newest measured elevation, NaN if none
    called: np.ndarray  # uint8 (rows, cols): 1 if the newest result with evidence there called the cell safe
    calls: np.ndarray  # uint8 (rows, cols): how many results with evidence there called the cell safe
    origin_xy: tuple[float, float]  # world x, y of the centre of cell [0, 0]
    cell_m: float
    results: int = 0  # results fused so far
    # uint8 (rows, cols): 1 where a full-level result has had evidence (module doc, "Coarse results"); None: nowhere
    full: np.ndarray | None = None
    # uint8 (rows, cols): 1 if the newest result with evidence there called the cell unsafe; None: nowhere
    vetoed: np.ndarray | None = None
    # uint8 (rows, cols): how many hazard calls (an unsafe call at -l_unsafe) entered the cell; None: none anywhere
    hazards: np.ndarray | None = None
    # float32 (rows, cols): the newest gap-fill elevation (HazardGrid.dem where no match), reported where no
    # result matched the cell; None: no result had fills
    fills: np.ndarray | None = None
    # float64 (N, 5): world x, y, hazard calls, log-odds and cell size of hazard-call cells the map's grid has left
    # (module doc, "Extent and resampling"), put back when a later grid covers them; None: none
    kept: np.ndarray | None = None
    kept_dropped: int = 0  # kept points dropped, the oldest first, to stay within MAX_KEPT_HAZARDS

    @property
    def shape(self) -> tuple[int, int]:
        return (int(self.logodds.shape[0]), int(self.logodds.shape[1]))


def logit_threshold(p_min: float) -> float:
    """``T = logit(p_min)``: the log-odds a cell needs to be called safe."""
    return math.log(p_min / (1.0 - p_min))


def params_for(pipeline_params: Mapping[str, Any], info: Mapping[str, Any], base: FusionParams) -> FusionParams:
    """``base`` set to decide as the pipeline run that made a result (``PipelineResult.params`` / ``.info``):
    its P(safe) floor, and with the calibrated P(safe) in effect the model's prior (``info["psafe_safe_share"]``:
    the share of safe points the model that called it was fitted on); the Gaussian P(safe) has a flat prior."""
    # the floor the result was called with: its model's own (info.psafe_call, a 256 px camera's) or the params'
    p_min = float((info.get("psafe_call") or {}).get("psafe_min", pipeline_params.get("psafe_min", base.p_min)))
    if pipeline_params.get("psafe_model") != "calibrated" or "psafe_fallback" in info:
        return replace(base, p_min=p_min, prior_p=0.5)
    share = info.get("psafe_safe_share")  # the model that called it (one per image size: psafe.model_for_image)
    if share is None:  # a result from before that record: the model file its params name
        share = load_model(str(pipeline_params.get("psafe_model_path") or "") or None).info.get("safe_share", 0.5)
    return replace(base, p_min=p_min, prior_p=float(share))


def prior_logodds(params: FusionParams) -> float:
    """``l_0 = max(0, logit(prior_p))``: the prior a later result's log-odds hold, removed before adding."""
    return max(0.0, logit_threshold(params.prior_p))


def overturn_margin(params: FusionParams, times_unsafe: int = 1) -> float:
    """The least sum of ``max(0, l_j - l_0)`` over the *other* results before a cell given ``times_unsafe``
    hazard calls can be called safe (module doc): ``T - l_0 + n_u (l_unsafe + l_0)``."""
    l0 = prior_logodds(params)
    return logit_threshold(params.p_min) - l0 + times_unsafe * (params.l_unsafe + l0)


def result_logodds(grid: HazardGrid, params: FusionParams) -> np.ndarray:
    """Per-cell evidence ``l_i`` of one result (module doc): float32, NaN where it mapped nothing or has
    no evidence (no elevation and no call against "safe")."""
    ps = np.asarray(grid.psafe, np.float64)
    st = np.asarray(grid.state)
    lo = 1.0 / (1.0 + math.exp(params.l_max))
    p = np.clip(np.where(np.isfinite(ps), ps, 0.5), lo, 1.0 - lo)
    out = np.log(p / (1.0 - p))
    # no elevation, no evidence: a calibrated P(safe) there is only a context prior (module doc)
    out[~np.isfinite(np.asarray(grid.elevation, np.float64))] = np.nan
    # a hazard call enters beyond anything a P(safe) can say; a soft one (a P(safe) that only leans unsafe) as itself
    out[(st == STATE_UNSAFE) & ~(ps >= params.hard_unsafe_p)] = -params.l_unsafe
    out[(st == STATE_OUTSIDE) | ~((st == STATE_SAFE) | (st == STATE_UNSAFE) | (st == STATE_UNKNOWN))] = np.nan
    return out.astype(np.float32)


def _aligned_extent(
    boxes: list[tuple[float, float, float, float]], cell: float
) -> tuple[tuple[float, float], tuple[int, int]]:
    """Cell-aligned origin and shape covering world boxes ``(x_min, x_max, y_min, y_max)``."""
    x0 = math.floor(min(b[0] for b in boxes) / cell) * cell
    x1 = math.ceil(max(b[1] for b in boxes) / cell) * cell
    y0 = math.floor(min(b[2] for b in boxes) / cell) * cell
    y1 = math.ceil(max(b[3] for b in boxes) / cell) * cell
    return (x0, y1), (int(round((y1 - y0) / cell)) + 1, int(round((x1 - x0) / cell)) + 1)


def _box(origin: tuple[float, float], shape: tuple[int, int], cell: float) -> tuple[float, float, float, float]:
    """World extent of a grid's cell centres."""
    return origin[0], origin[0] + (shape[1] - 1) * cell, origin[1] - (shape[0] - 1) * cell, origin[1]


def _axis_index(n: int, dst0: float, dst_cell: float, src0: float, src_cell: float, sign: float) -> np.ndarray:
    """Source index nearest each destination cell centre along one axis (``sign`` -1 for rows toward -Y)."""
    centre = dst0 + sign * np.arange(n, dtype=np.float64) * dst_cell
    return np.rint(sign * (centre - src0) / src_cell).astype(np.int64)


def resample(
    values: np.ndarray,
    origin: tuple[float, float],
    cell: float,
    dst_origin: tuple[float, float],
    dst_cell: float,
    dst_shape: tuple[int, int],
    fill: float = np.nan,
    pool_min: bool = True,
    pool_max: bool = False,
) -> np.ndarray:
    """Move a grid layer onto another grid conservatively (module doc): every destination cell takes
    the source cell under its centre and, where the source is finer and ``pool_min``, the minimum of
    the source cells whose centres fall in it (NaN = no value, ignored by the minimum); with ``pool_max``
    the maximum instead (a flag that any finer part raised). float32 out.

    Both grids are axis-aligned, so the cell under a centre is a row index times a column index, and
    the source cells of one destination cell are a contiguous block of rows by a contiguous block of
    columns: the minimum is two ``fmin.reduceat`` passes, O(1) per cell without per-cell index arrays."""
    src = np.asarray(values, np.float32)
    return _Move(src.shape, origin, cell, dst_origin, dst_cell, dst_shape)(src, fill, pool_min, pool_max)


class _Move:
    """The indices that move layers of one grid onto another (:func:`resample`), worked out once for all the
    layers of a map."""

    def __init__(
        self,
        src_shape: tuple[int, ...],
        origin: tuple[float, float],
        cell: float,
        dst_origin: tuple[float, float],
        dst_cell: float,
        dst_shape: tuple[int, int],
    ) -> None:
        self.dst_shape = (int(dst_shape[0]), int(dst_shape[1]))
        h, w = int(src_shape[0]), int(src_shape[1])
        self.empty = h * w == 0 or self.dst_shape[0] * self.dst_shape[1] == 0
        self.same = (h, w) == self.dst_shape and tuple(origin) == tuple(dst_origin) and cell == dst_cell
        self.pools = False
        if self.empty or self.same:
            return
        jj = _axis_index(self.dst_shape[1], dst_origin[0], dst_cell, origin[0], cell, 1.0)
        ii = _axis_index(self.dst_shape[0], dst_origin[1], dst_cell, origin[1], cell, -1.0)
        cols, rows = (jj >= 0) & (jj < w), (ii >= 0) & (ii < h)
        self.at_dst = np.ix_(rows, cols)
        self.at_src = np.ix_(ii[rows], jj[cols])
        if cell < dst_cell * (1.0 - 1e-9):  # finer source: several cells per destination
            dj = _axis_index(w, origin[0], cell, dst_origin[0], dst_cell, 1.0)
            di = _axis_index(h, origin[1], cell, dst_origin[1], dst_cell, -1.0)
            cols, rows = (dj >= 0) & (dj < self.dst_shape[1]), (di >= 0) & (di < self.dst_shape[0])
            if cols.any() and rows.any():
                dj, di = dj[cols], di[rows]  # non-decreasing: each destination cell's sources are contiguous
                self.c0 = np.flatnonzero(np.r_[True, dj[1:] != dj[:-1]])
                self.r0 = np.flatnonzero(np.r_[True, di[1:] != di[:-1]])
                self.block = np.ix_(rows, cols)
                self.at_pool = np.ix_(di[self.r0], dj[self.c0])
                self.pools = True

    def __call__(
        self, values: np.ndarray, fill: float = np.nan, pool_min: bool = True, pool_max: bool = False
    ) -> np.ndarray:
        src = np.asarray(values, np.float32)
        if self.same and not self.empty:
            return src.copy()  # the same grid (a result onto its own grid: the flight's "newest" extent)
        out = np.full(self.dst_shape, np.float32(fill), np.float32)
        if self.empty:
            return out
        out[self.at_dst] = src[self.at_src]
        if (pool_min or pool_max) and self.pools:
            op = np.fmax if pool_max else np.fmin
            pooled = op.reduceat(op.reduceat(src[self.block], self.c0, axis=1), self.r0, axis=0)
            out[self.at_pool] = op(out[self.at_pool], pooled)
        return out


MAX_KEPT_HAZARDS = 65536  # hazard-call cells kept off the map's grid: 2 MiB


def _left_out(fm: FusedMap, origin: tuple[float, float], shape: tuple[int, int], cell: float) -> np.ndarray:
    """World x, y, hazard calls, log-odds and cell size (N x 5, float64) of the map's hazard-call cells whose centres
    the grid ``origin``, ``shape``, ``cell`` does not hold (the cells a move drops). Per axis: both grids are
    axis-aligned."""
    if fm.hazards is None or not fm.hazards.size:
        return np.zeros((0, 5), np.float64)
    rows, cols = fm.shape
    x = fm.origin_xy[0] + np.arange(cols) * fm.cell_m
    y = fm.origin_xy[1] - np.arange(rows) * fm.cell_m
    jn, i_n = np.rint((x - origin[0]) / cell), np.rint((origin[1] - y) / cell)
    held = ((i_n >= 0) & (i_n < shape[0]))[:, None] & ((jn >= 0) & (jn < shape[1]))[None, :]
    i, j = np.nonzero((fm.hazards > 0) & ~held)
    size = np.full(i.size, fm.cell_m)
    return np.column_stack([x[j], y[i], fm.hazards[i, j], fm.logodds[i, j], size]).astype(np.float64)


MAX_KEPT_RASTER = 1 << 22  # cells of one kept group's raster (20 MiB): past it, a group is put back by its centres


def _put_back(
    pts: np.ndarray, origin: tuple[float, float], shape: tuple[int, int], cell: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Kept hazard points (:func:`_left_out`'s rows) moved onto a grid as the layers they left are: each group of
    points on one lattice (one source grid's cell size and phase) is rasterised on that lattice and moved with
    :class:`_Move`, so a finer grid gives every cell inside a kept cell its call, and a coarser one pools them.
    Returns the hazard calls (uint8) and log-odds (float32, NaN where none) on the grid, and per point whether its
    cell lies wholly inside the grid (it can go from the kept list)."""
    hz = np.zeros(shape, np.float32)
    lo = np.full(shape, np.nan, np.float32)
    half = pts[:, 4] / 2
    x0, x1, y0, y1 = _box(origin, shape, cell)
    e = cell / 2
    x, y = pts[:, 0], pts[:, 1]
    over = (x + half > x0 - e) & (x - half < x1 + e) & (y + half > y0 - e) & (y - half < y1 + e)
    whole = (x - half >= x0 - e) & (x + half <= x1 + e) & (y - half >= y0 - e) & (y + half <= y1 + e)
    if not over.any():
        return hz.astype(np.uint8), lo, whole
    c = pts[:, 4]
    # one integer per lattice (cell size to the micrometre, phase to 0.1 mm): a 1-D unique, not a row-wise one
    key = (np.rint(c * 1e6).astype(np.int64) << 32) ^ (np.rint((x - c * np.rint(x / c)) * 1e4).astype(np.int64) << 16)
    key ^= np.rint((y - c * np.rint(y / c)) * 1e4).astype(np.int64)
    sel = np.flatnonzero(over)
    groups, which = np.unique(key[sel], return_inverse=True)
    for k in range(len(groups)):
        g = pts[sel if len(groups) == 1 else sel[which.ravel() == k]]
        gc, gx0, gy1 = float(g[0, 4]), float(g[:, 0].min()), float(g[:, 1].max())
        jj = np.rint((g[:, 0] - gx0) / gc).astype(np.intp)
        ii = np.rint((gy1 - g[:, 1]) / gc).astype(np.intp)
        rshape = (int(ii.max()) + 1, int(jj.max()) + 1)
        if rshape[0] * rshape[1] > MAX_KEPT_RASTER:  # scattered far apart: the cell under each centre
            jc = np.rint((g[:, 0] - origin[0]) / cell)
            ic = np.rint((origin[1] - g[:, 1]) / cell)
            ok = (ic >= 0) & (ic < shape[0]) & (jc >= 0) & (jc < shape[1])
            at = (ic[ok].astype(np.intp), jc[ok].astype(np.intp))
            np.maximum.at(hz, at, g[ok, 2].astype(np.float32))
            np.fmin.at(lo, at, g[ok, 3].astype(np.float32))
            continue
        hr = np.zeros(rshape, np.float32)
        np.maximum.at(hr, (ii, jj), g[:, 2].astype(np.float32))
        lr = np.full(rshape, np.nan, np.float32)
        np.fmin.at(lr, (ii, jj), g[:, 3].astype(np.float32))
        mv = _Move(rshape, (gx0, gy1), gc, origin, cell, shape)
        h_on = np.nan_to_num(mv(hr, fill=0.0, pool_max=True))
        hz = np.fmax(hz, h_on)
        lo = np.fmin(lo, np.where(h_on > 0, mv(lr), np.float32(np.nan)))
    return np.minimum(hz, 255).astype(np.uint8), lo, whole


def _regrid(
    fm: FusedMap, origin: tuple[float, float], shape: tuple[int, int], cell: float, prior: float = 0.0
) -> FusedMap:
    """The fused map on another grid (same or different cell), conservatively (module doc). ``prior``: the
    log-odds a cell holds before any evidence (:func:`prior_logodds`), which a never-mapped part of a coarser cell
    brings into its minimum.

    A coarser cell is mapped if any of its parts was (the maximum of ``seen``). With the minimum, one never-mapped
    part (the previous footprint's edge) made it unmapped and wiped its hazard calls, veto and log-odds, so one
    later result 99.9 % sure could call a hazard safe where the rule asks three (review of stop 64). Its log-odds
    are the minimum over its parts, a never-mapped part counting at the prior: evidence against "safe" carries
    whole, evidence for it only where every part holds it."""
    if fm.results == 0:
        return FusedMap(
            np.zeros(shape, np.float32),
            np.zeros(shape, np.uint8),
            np.full(shape, np.nan, np.float32),
            np.zeros(shape, np.uint8),
            np.zeros(shape, np.uint8),
            origin,
            cell,
            0,
        )
    mv = _Move(fm.shape, fm.origin_xy, fm.cell_m, origin, cell, shape)  # the same indices for every layer
    lo = mv(np.where(fm.seen > 0, fm.logodds, np.float32(prior)))
    seen = mv(fm.seen.astype(np.float32), fill=0.0, pool_max=True)
    elev = mv(fm.elevation, pool_min=False)
    # a coarser cell counts as called safe only if all of its finer parts were (the minimum)
    called = mv(fm.called.astype(np.float32), fill=0.0)
    calls = mv(fm.calls.astype(np.float32), fill=0.0)
    seen_u8 = np.where(np.isfinite(seen), seen, 0).astype(np.uint8)
    called_u8 = np.where(np.isfinite(called) & (seen_u8 > 0), called, 0).astype(np.uint8)
    calls_u8 = np.where(np.isfinite(calls) & (seen_u8 > 0), calls, 0).astype(np.uint8)
    full = None
    if fm.full is not None:  # like the call: a coarser cell holds full-level evidence only if all its parts did
        f = mv(fm.full.astype(np.float32), fill=0.0)
        full = np.where(np.isfinite(f) & (seen_u8 > 0), f, 0).astype(np.uint8)
    vetoed = None
    if fm.vetoed is not None:  # unlike the call: a coarser cell is vetoed if any of its finer parts was (the max)
        v = mv(fm.vetoed.astype(np.float32), fill=0.0, pool_max=True)
        vetoed = ((v > 0.5) & (seen_u8 > 0)).astype(np.uint8)
    hazards = None
    if fm.hazards is not None:  # a coarser cell holds as many hazard calls as the most any of its parts holds
        hz = mv(fm.hazards.astype(np.float32), fill=0.0, pool_max=True)
        hazards = np.where(seen_u8 > 0, np.rint(hz), 0).astype(np.uint8)
    fills = None
    if fm.fills is not None:
        fills = mv(fm.fills, pool_min=False)
    logodds = np.where(seen_u8 > 0, np.nan_to_num(lo), 0.0).astype(np.float32)
    # kept points this grid covers are put back; hazard calls it leaves out are kept as points
    kept = None
    if fm.kept is not None:
        h_back, l_back, whole = _put_back(fm.kept, origin, shape, cell)
        back = h_back > 0
        if back.any():
            hazards = np.zeros(shape, np.uint8) if hazards is None else hazards
            hazards = np.maximum(hazards, h_back)
            fresh = back & (seen_u8 == 0)
            logodds = np.where(fresh, np.float32(prior), logodds)  # a cell first mapped here: from the prior
            logodds = np.where(back, np.fmin(logodds, l_back), logodds).astype(np.float32)
            seen_u8 = np.where(back, np.maximum(seen_u8, 1), seen_u8).astype(np.uint8)
        kept = fm.kept[~whole]
    gone = _left_out(fm, origin, shape, cell)
    if gone.size:
        kept = gone if kept is None else np.concatenate([kept, gone])
    dropped = fm.kept_dropped
    if kept is not None:
        dropped += max(0, len(kept) - MAX_KEPT_HAZARDS)
        kept = kept[-MAX_KEPT_HAZARDS:] if kept.size else None  # the newest last: the oldest go first
    return FusedMap(
        logodds,
        seen_u8,
        elev,
        called_u8,
        calls_u8,
        origin,
        cell,
        fm.results,
        full,
        vetoed,
        hazards,
        fills,
        kept,
        dropped,
    )


def empty_map() -> FusedMap:
    """A map before any result: no cells."""
    none = np.zeros((0, 0), np.uint8)
    return FusedMap(np.zeros((0, 0), np.float32), none, np.zeros((0, 0), np.float32), none, none, (0.0, 0.0), 0.0)


def fuse(
    fm: FusedMap | None,
    grid: HazardGrid,
    params: FusionParams | None = None,
    weight: float | None = None,
    level: str = "full",
) -> FusedMap:
    """The fused map after one more result (a new object; ``fm`` is not modified).

    ``weight`` overrides ``params.weight`` for this result (the share of earlier evidence for "safe" it carries).
    ``level`` is the result's anytime level (:data:`flight_sw.pipeline.LEVELS`): where a full-level result's
    evidence stands, a ``coarse`` one adds only its evidence against "safe" (module doc, "Coarse results").
    The map's grid is the result's (``extent="newest"``) or the union of both extents at the finer
    cell (``"union"``), bounded by ``max_cells`` either way.
    """
    prm = params or FusionParams()
    prm.validate()
    w = prm.weight if weight is None else float(weight)
    if not (math.isfinite(w) and 0 < w <= 1):
        raise ValueError(f"fusion: weight must be in (0, 1], got {weight!r}")
    if level not in ("image_only", "coarse", "full"):  # flight_sw.pipeline.LEVELS
        raise ValueError(f"fusion: level must be image_only, coarse or full, got {level!r}")
    fm = fm if fm is not None else empty_map()
    if grid.hazard.size == 0 or not (grid.state != STATE_OUTSIDE).any():
        return replace(fm, results=fm.results + 1)  # arrays are never modified in place
    cell = float(grid.cell_m)
    origin, shape = (
        (float(grid.origin_xy[0]), float(grid.origin_xy[1])),
        (int(grid.hazard.shape[0]), int(grid.hazard.shape[1])),
    )
    if prm.extent == "union" or shape[0] * shape[1] > prm.max_cells:
        boxes = [_box(grid.origin_xy, grid.hazard.shape, grid.cell_m)]
        if prm.extent == "union" and fm.results > 0 and fm.logodds.size:
            boxes.append(_box(fm.origin_xy, fm.shape, fm.cell_m))
            cell = min(cell, fm.cell_m)
        while True:  # the finer cell, unless the map would not fit in max_cells
            origin, shape = _aligned_extent(boxes, cell)
            if shape[0] * shape[1] <= prm.max_cells:
                break
            cell *= math.sqrt(shape[0] * shape[1] / prm.max_cells) * 1.01
    base = _regrid(fm, origin, shape, cell, prior_logodds(prm))
    li = result_logodds(grid, prm)
    mv = _Move(grid.hazard.shape, grid.origin_xy, grid.cell_m, origin, cell, shape)  # every layer of the result
    l_new = mv(li)
    e_new = mv(grid.elevation, pool_min=False)
    st = np.asarray(grid.state)
    mapped = (st == STATE_SAFE) | (st == STATE_UNSAFE) | (st == STATE_UNKNOWN)
    m_new = mv(mapped.astype(np.float32), fill=0.0) > 0.5
    upd = np.isfinite(l_new)  # the result has evidence for the cell
    l0 = np.float32(prior_logodds(prm))
    e = np.where(base.seen > 0, base.logodds - l0, np.float32(0.0))
    carried = np.where(e > 0, np.float32(w) * e, e)  # earlier evidence for "safe" discounted, against it whole
    # ... unless no hazard call ever entered the cell: a P(safe) that leans unsafe is discounted like one that
    # leans safe (the same shared frames and errors), a hazard call never is (module doc, "The rule for hazards")
    had_hazard = base.hazards if base.hazards is not None else np.zeros(shape, np.uint8)
    soft = (e < 0) & (had_hazard == 0)
    carried = np.where(soft, np.float32(prm.weight_against) * e, carried)
    # a cell first mapped without evidence holds the prior (e = 0), not log-odds 0: below a calibrated
    # prior that would read as evidence against "safe" for every later result
    logodds = np.where(upd, np.nan_to_num(l_new) + carried, np.where(base.seen > 0, base.logodds, l0))
    seen = np.minimum(base.seen.astype(np.int32) + (m_new | upd), 255).astype(np.uint8)
    elev = np.where(upd & np.isfinite(e_new), e_new, base.elevation).astype(np.float32)
    fills = base.fills
    if grid.dem is not None:  # the result's gap fills: reported where no result matched the cell
        own = np.where(np.isfinite(np.asarray(grid.elevation)), np.float32(np.nan), grid.dem)
        f_new = mv(own, pool_min=False)
        fills = np.where(np.isfinite(f_new), f_new, np.float32(np.nan) if fills is None else fills)
    # did the newest result with evidence call the cell safe (a coarser map cell: only if all its parts were)
    c_new = mv((st == STATE_SAFE).astype(np.float32))
    c_bool = np.nan_to_num(c_new) > 0.5
    called = np.where(upd, c_bool, base.called > 0).astype(np.uint8)
    # did it call the cell unsafe (a coarser map cell: if any of its parts was)
    u_new = mv((st == STATE_UNSAFE).astype(np.float32), fill=0.0, pool_max=True)
    had_veto = base.vetoed if base.vetoed is not None else np.zeros(shape, np.uint8)
    vetoed = np.where(upd, u_new > 0.5, had_veto > 0)
    calls = np.minimum(base.calls.astype(np.int32) + (upd & c_bool), 255).astype(np.uint8)
    had_full = base.full if base.full is not None else np.zeros(shape, np.uint8)
    if level == "coarse":
        # a coarse DEM (half resolution, coarse planes) does not replace what a full one measured: the
        # cell keeps its evidence, call and elevation, and takes the coarse result's evidence against "safe";
        # an unsafe call (log-odds -l_unsafe, beyond what any P(safe) gives) still enters whole, as a hazard
        keep = upd & (had_full > 0) & (np.nan_to_num(l_new) >= -np.float32(prm.l_max))
        against = np.minimum(np.nan_to_num(l_new) - l0, np.float32(0.0))
        kept = base.logodds + against
        keep &= kept > logodds  # where the coarse result alone says more for "safe", it enters as any result does
        logodds = np.where(keep, kept, logodds)
        elev = np.where(keep & np.isfinite(base.elevation), base.elevation, elev).astype(np.float32)
        called = np.where(keep, base.called, called).astype(np.uint8)
        vetoed = np.where(keep, had_veto > 0, vetoed)
        full = had_full
    else:
        full = (had_full > 0) | (upd & (level == "full"))
    return FusedMap(
        logodds.astype(np.float32),
        seen,
        elev,
        called,
        calls,
        origin,
        cell,
        fm.results + 1,
        full.astype(np.uint8),
        vetoed.astype(np.uint8),
        np.minimum(had_hazard.astype(np.int32) + (upd & (l_new <= -np.float32(prm.l_unsafe))), 255).astype(np.uint8),
        None if fills is None else fills.astype(np.float32),
        base.kept,
        base.kept_dropped,
    )


def fused_state(fm: FusedMap, params: FusionParams | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``(state, psafe)`` of the fused map: STATE_* codes (uint8) and P(safe) (float32, NaN outside)."""
    prm = params or FusionParams()
    T = logit_threshold(prm.p_min)
    lo = fm.logodds
    state = np.full(lo.shape, STATE_UNKNOWN, np.uint8)
    accumulated = (lo >= logit_threshold(max(prm.p_accumulate, prm.p_min))) & (fm.calls >= prm.accumulate_calls)
    state[(lo >= T) & ((fm.called > 0) | accumulated)] = STATE_SAFE
    bound = np.float32(-(prm.l_max + T))
    state[lo <= bound] = STATE_UNSAFE
    if fm.vetoed is not None:  # the newest result that measured the cell called it unsafe: so is the map
        state[fm.vetoed > 0] = STATE_UNSAFE
    state[fm.seen == 0] = STATE_OUTSIDE
    with np.errstate(over="ignore"):
        psafe = (1.0 / (1.0 + np.exp(-lo.astype(np.float64)))).astype(np.float32)
    psafe[fm.seen == 0] = np.nan
    return state, psafe


def to_hazard_grid(fm: FusedMap, params: FusionParams | None = None) -> HazardGrid:
    """The fused map as a :class:`HazardGrid` (for :func:`flight_sw.sites.select_safe_sites` and the Result):
    hazard = 1 - P(safe) on safe cells, 1 on unknown and unsafe ones (DESIGN.md), NaN outside."""
    state, psafe = fused_state(fm, params)
    hazard = np.where(state == STATE_SAFE, 1.0 - psafe, 1.0).astype(np.float32)
    hazard[state == STATE_OUTSIDE] = np.nan
    elev = np.where(state != STATE_OUTSIDE, fm.elevation, np.nan).astype(np.float32)
    dem = None
    if fm.fills is not None:  # a match beats a fill, whichever is newer
        dem = np.where(np.isfinite(elev), elev, np.where(state != STATE_OUTSIDE, fm.fills, np.nan)).astype(np.float32)
    return HazardGrid(hazard, elev, fm.origin_xy, float(fm.cell_m), state, psafe, dem)
