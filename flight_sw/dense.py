"""Dense, edge-preserving DEM: plane-sweep cost volume -> semi-global aggregation -> checks -> sigma.

One call (:func:`dense_dem`) chains :func:`flight_sw.costvolume.cost_slab` (or a slab that the
caller combined over several frames), :func:`flight_sw.sgm.aggregate`,
:func:`flight_sw.sgm.winner` and :func:`flight_sw.sgm.speckle_filter`, then turns the
sub-plane index into an elevation by interpolating the plane list and the plane-step
uncertainty into metres with the local plane spacing (:func:`flight_sw.sgm.plane_sigma`).
Memory: the slab is ``D x h x w`` uint16 plus a bool mask, the aggregation holds one int16
``h x w x D`` copy of the cost and the int16 sum; nothing else of size D (512^2 pairs: ~30 MB).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from protocol.pairdir import Camera, Pose

from .costvolume import CostSlab, cost_slab, valid_interval
from .sgm import DeadlineReached, aggregate, plane_sigma, speckle_filter, winner
from .sweep import coverage_mask


@dataclass(frozen=True)
class DenseParams:
    radius: int = 2  # cost support (2r+1)^2
    mean_radius: int = 3  # local mean removed before the SAD
    p1: int = 16  # SGM penalties, cost units (costvolume.COST_SCALE per grey level)
    p2: int = 128
    p2_g0: float = 4.0  # grey-level step that halves P2
    p2_adapt: bool = True
    paths: int = 8
    uniqueness: float = 0.05
    end_margin: int = 3  # planes: minima this close to a partially seen end of the pixel's interval are dropped
    min_interval_frac: float = 0.8  # a pixel must see at least this share of the planes
    speckle_px: int = 30
    speckle_diff: float = 2.0  # planes
    temperature: float = 4.0  # sigma calibration (sgm.plane_sigma)
    uniq_scale: float = 0.2  # ambiguity weight of a second minimum (sgm.plane_sigma)
    kappa_radius: int = 2
    kappa_floor: float = 0.0  # > 0: a non-convex raw cost curve gets this curvature (large sigma) instead of no match


@dataclass
class DenseDEM:
    elevation: np.ndarray  # float32 HxW, NaN where rejected or not swept
    sigma: np.ndarray  # float32 HxW, metres, NaN where elevation is NaN
    complete: bool
    info: dict[str, Any] = field(default_factory=dict)


def roi_of(camera: Camera, pose1: Pose, pose2: Pose, z_lo: float, z_hi: float) -> tuple[int, int, int, int]:
    """Bounding box of the reference pixels that see the other image for some plane in the range."""
    reach = coverage_mask(camera, pose1, pose2, z_lo, z_hi, mode="any")
    rows, cols = np.flatnonzero(reach.any(axis=1)), np.flatnonzero(reach.any(axis=0))
    if rows.size == 0:
        return 0, 0, 0, 0
    return int(cols[0]), int(rows[0]), int(cols[-1] - cols[0] + 1), int(rows[-1] - rows[0] + 1)


def dem_from_slab(
    slab: CostSlab,
    ref: np.ndarray,
    shape: tuple[int, int],
    dp: DenseParams,
    deadline: float | None = None,
    prior: np.ndarray | None = None,
) -> DenseDEM:
    """Aggregate a (possibly multi-frame) slab and extract the DEM and its uncertainty.

    ``prior`` (elevation, reference size, NaN = none; e.g. the coarse level's DEM) vouches for
    pixels of the overlap-edge band: one that sees only part of the planes is kept when the
    prior's plane lies well inside the part it sees (then its minimum there is a real one).
    """
    H, W = shape
    nan = np.full(shape, np.nan, np.float32)
    x0, y0, w, h = slab.roi
    planes = slab.planes
    D = planes.size
    if not slab.complete:
        return DenseDEM(nan, nan.copy(), False)
    if w == 0 or h == 0 or D < 3:
        return DenseDEM(nan, nan.copy(), True, {"planes": int(D)})
    C = np.ascontiguousarray(slab.cost.transpose(1, 2, 0)).astype(np.int16)
    lo, hi = valid_interval(slab.valid)
    guide = np.asarray(ref, np.float32)[y0 : y0 + h, x0 : x0 + w]
    try:
        S = aggregate(C, guide, dp.p1, dp.p2, dp.p2_g0, dp.paths, dp.p2_adapt, deadline)
    except DeadlineReached:
        return DenseDEM(nan, nan.copy(), False)
    m = winner(S, C, lo, hi, dp.uniqueness, dp.kappa_radius)
    del S, C
    # the overlap-edge band: a pixel that sees only part of the planes is kept only if it sees most of
    # them and its minimum lies well inside them (on tuning pairs the band's matches were 4 m off
    # otherwise: half of them had their true plane outside the part they see)
    em = int(dp.end_margin)
    partial_lo, partial_hi = lo > 0, hi < D - 1
    ok0 = m.ok.copy()
    band = ((hi - lo + 1) < dp.min_interval_frac * D) | (partial_lo & (m.k < lo + em)) | (partial_hi & (m.k > hi - em))
    if prior is not None:
        zp = np.asarray(prior, np.float32)[y0 : y0 + h, x0 : x0 + w]
        with np.errstate(invalid="ignore"):
            kp = np.interp(np.nan_to_num(zp, nan=-1e9), planes, np.arange(D, dtype=np.float64), left=-1e9, right=1e9)
            vouched = np.isfinite(zp) & (kp >= lo + em) & (kp <= hi - em) & (np.abs(m.frac - kp) <= 2.0 * em)
        band &= ~vouched
    m.ok &= ~band
    ok1 = m.ok.copy()
    ok = speckle_filter(m.frac, m.ok, dp.speckle_px, dp.speckle_diff)
    idx = np.arange(D, dtype=np.float64)
    z = np.interp(m.frac.ravel(), idx, planes).reshape(h, w).astype(np.float32)
    dz = np.interp(m.frac.ravel(), 0.5 * (idx[1:] + idx[:-1]), np.diff(planes)).reshape(h, w)
    kappa = np.maximum(m.kappa, dp.kappa_floor) if dp.kappa_floor > 0 else m.kappa
    sig = (plane_sigma(kappa, dp.temperature, m.uniq, m.k2 - m.k, dp.uniq_scale) * dz).astype(np.float32)
    ok &= np.isfinite(sig)
    elev = nan.copy()
    sigma = nan.copy()
    elev[y0 : y0 + h, x0 : x0 + w] = np.where(ok, z, np.nan)
    sigma[y0 : y0 + h, x0 : x0 + w] = np.where(ok, sig, np.nan)
    info = {
        "planes": int(D),
        "roi": [int(v) for v in slab.roi],
        "rejected_ends_unique": float(np.mean(~ok0)),
        "rejected_band": float(np.mean(ok0 & ~ok1)),
        "rejected_speckle": float(np.mean(ok1 & ~ok)),
    }
    return DenseDEM(elev, sigma, True, info)


def dense_dem(
    i1: np.ndarray,
    i2: np.ndarray,
    camera: Camera,
    pose1: Pose,
    pose2: Pose,
    planes: np.ndarray,
    dp: DenseParams,
    *,
    prefilter_sigma: float = 0.0,
    ignore: np.ndarray | None = None,
    deadline: float | None = None,
    prior: np.ndarray | None = None,
) -> DenseDEM:
    """Two-frame dense DEM of i1 over ``planes`` (module doc); ``prior`` see :func:`dem_from_slab`."""
    roi = roi_of(camera, pose1, pose2, float(planes[0]), float(planes[-1]))
    slab = cost_slab(
        i1,
        i2,
        camera,
        pose1,
        pose2,
        planes,
        roi,
        radius=dp.radius,
        mean_radius=dp.mean_radius,
        prefilter_sigma=prefilter_sigma,
        ignore=ignore,
        deadline=deadline,
    )
    return dem_from_slab(slab, i1, i1.shape, dp, deadline, prior)
