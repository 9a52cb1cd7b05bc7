"""Uncertainty-aware hazard evidence: slope and roughness judged against their uncertainty, three states.

Footprint plane (thesis eq. 4.11/4.12) by weighted least squares with weights ``w = 1 / sigma_z^2``
(box sums of ``w, wx, wy, wz, wx^2, wxy, wy^2, wxz, wyz``; O(1) per cell)::

    [cxx cxy] [p]   [cxz]
    [cxy cyy] [q] = [cyz]     (w-weighted centred moments),   g = |(p, q)|  (m per cell)

:func:`weighted_plane_fit` also returns the textbook covariance ``rho / sum(w) [cxx cxy; cxy cyy]^-1``
of ``(p, q)``, but it assumes independent elevation errors: on ground_sim's tuning pairs the SGM
DEM's errors are correlated over many pixels, and the textbook slope uncertainty was off by 0.1x
to 4.5x depending on how many cells a footprint spans. The flight pipeline therefore uses the
empirical scales (calibrated on ``ground_sim.seeds.TUNING_SEEDS``, docs/benchmarks/pipeline.md)::

    sigma_g = a_g * mean_footprint(sigma_z) * cell / footprint     sigma_r = a_r * sigma_z

Per point, with ``Phi`` the normal CDF, ``G = tan(15 deg) * cell`` and the hazard limits of
Table 2.1::

    P(safe) = Phi((G - g) / sigma_g) * Phi((0.30 - r) / sigma_r)
    unsafe   if  g - k sigma_g > G  or  r - k sigma_r > 0.30  (or an image cue: shadow, wall, rock)
    safe     if  P(safe) >= p_min  and no image cue
    unknown  otherwise (also: no elevation, or a footprint with too few measured points)

so a hazard is only declared on evidence beyond ``k`` standard uncertainties, and ground is only
called safe when it is safe with probability ``p_min``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import cv2
import numpy as np

from protocol.pairdir import STATE_OUTSIDE, STATE_SAFE, STATE_UNKNOWN, STATE_UNSAFE

from .psafe import Model, budget_rule
from .slope import footprint_cells


def _box(a: np.ndarray, n: int, out: np.ndarray | None = None) -> np.ndarray:
    return cv2.boxFilter(a, cv2.CV_64F, (n, n), dst=out, normalize=False, borderType=cv2.BORDER_CONSTANT)


@dataclass
class PlaneFit:
    """Per-cell weighted footprint plane (float32 arrays, NaN where not determined)."""

    slope_deg: np.ndarray
    grad: np.ndarray  # |(p, q)| in metres per cell
    grad_sigma: np.ndarray  # standard uncertainty of grad (m per cell)
    z_plane: np.ndarray  # plane at the cell centre
    z_plane_sigma: np.ndarray
    # the footprint plane's gradient along the grid's columns / rows (m per cell; NaN where not determined)
    p: np.ndarray
    q: np.ndarray


def _plane_products(z: np.ndarray, sigma: np.ndarray) -> tuple[np.ndarray, list[np.ndarray], np.ndarray, np.ndarray]:
    """``(okz, [w, wx, wy, wz, wx^2, wxy, wy^2, wxz, wyz], xx, yy)``: what the box sums of a footprint run over."""
    z = np.asarray(z, np.float64)
    h, w = z.shape
    wt = np.array(sigma, np.float64)  # becomes the weight 1 / sigma^2 in place
    okz = np.isfinite(z) & np.isfinite(wt) & (wt > 0)
    wt *= wt
    np.divide(1.0, wt, out=wt, where=okz)
    wt[~okz] = 0.0
    wz = np.where(okz, z, 0.0)
    wz *= wt  # w z = wt * z (multiplication commutes exactly)
    # coordinates relative to the grid centre keep the moments well conditioned
    xx = (np.arange(w, dtype=np.float64) - w / 2.0)[None, :]
    yy = (np.arange(h, dtype=np.float64) - h / 2.0)[:, None]
    wx, wy = wt * xx, wt * yy
    return okz, [wt, wx, wy, wz, wx * xx, wx * yy, wy * yy, wz * xx, wz * yy], xx, yy


def _fit_from_products(
    okz: np.ndarray,
    prods: list[np.ndarray],
    xx: np.ndarray,
    yy: np.ndarray,
    n: int,
    cell_m: float,
    min_fraction: float,
    rho: float,
    with_cov: bool,
) -> PlaneFit:
    # Each product is replaced by its box sum, and each box sum by what is derived from it, in the same
    # operation order as the formulas (the same floats): an oblique approach grid of 170 k cells peaked at
    # 56 MiB with a new array per term. The products are consumed (cv2's box filter runs in place exactly).
    h, w = okz.shape
    enough = _box(okz.astype(np.float64), n) >= min_fraction * n * n
    s1, sx, sy, sz, sxx, sxy, syy, sxz, syz = (_box(a, n, out=a) for a in prods)
    nan = np.float32(np.nan)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = np.divide(1.0, s1, out=s1)
        mx, my, mz = (np.multiply(v, inv, out=v) for v in (sx, sy, sz))
        # weighted centred moments (means of w-weighted products): c_ab = s_ab / s1 - m_a m_b
        for s_ab, m_a, m_b in ((sxx, mx, mx), (sxy, mx, my), (syy, my, my), (sxz, mx, mz), (syz, my, mz)):
            np.multiply(s_ab, inv, out=s_ab)
            np.subtract(s_ab, m_a * m_b, out=s_ab)
        cxx, cxy, cyy, cxz, cyz = sxx, sxy, syy, sxz, syz
        det = cxx * cyy
        det -= cxy * cxy
        enough &= det > 1e-6
        idet = np.divide(1.0, det, out=det)
        p = cxz * cyy
        p -= cyz * cxy
        p *= idet
        q = cyz * cxx
        q -= cxz * cxy
        q *= idet
        del cxz, cyz, sxz, syz
        dx, dy = np.subtract(xx, mx, out=mx), np.subtract(yy, my, out=my)  # the means are not needed after
        zc = p * dx
        zc += mz  # mz + p dx: addition commutes exactly
        zc += q * dy
        g = np.hypot(p, q)
        ok = enough & np.isfinite(zc)
        gsig = zsig = np.full((h, w), nan, np.float32)
        if with_cov:
            # Cov(p, q) = (sum w * centred moment matrix)^-1 * rho
            f = rho * inv * idet
            vpp, vqq, vpq = f * cyy, f * cxx, -f * cxy
            gvar = np.where(g > 1e-12, (p * p * vpp + q * q * vqq + 2 * p * q * vpq) / (g * g), 0.5 * (vpp + vqq))
            # plane value at the cell: Var = rho/s1 + d^T Cov d, d = offset of the cell from the weighted centroid
            zvar = rho * inv + dx * dx * vpp + dy * dy * vqq + 2 * dx * dy * vpq
            gsig = np.where(ok, np.sqrt(np.maximum(gvar, 0.0)), nan).astype(np.float32)
            zsig = np.where(ok, np.sqrt(np.maximum(zvar, 0.0)), nan).astype(np.float32)
    g32 = np.where(ok, g, nan).astype(np.float32)
    slope = np.degrees(np.arctan(g32 / np.float32(cell_m))).astype(np.float32)
    pq = [np.where(ok, v, nan).astype(np.float32) for v in (p, q)]
    return PlaneFit(slope, g32, gsig, np.where(ok, zc, nan).astype(np.float32), zsig, pq[0], pq[1])


def weighted_plane_fit(
    z: np.ndarray,
    sigma: np.ndarray,
    cell_m: float,
    footprint_m: float = 3.0,
    min_fraction: float = 0.5,
    rho: float = 1.0,
    with_cov: bool = True,
) -> PlaneFit:
    """Weighted LSQ plane over the footprint around every cell (module doc); ``sigma`` in metres.

    ``with_cov=False`` skips the textbook uncertainties (``grad_sigma``, ``z_plane_sigma`` are NaN).
    """
    okz, prods, xx, yy = _plane_products(z, sigma)
    n = footprint_cells(footprint_m, cell_m)
    return _fit_from_products(okz, prods, xx, yy, n, cell_m, min_fraction, rho, with_cov)


def steeper_plane_fit(
    z: np.ndarray,
    sigma: np.ndarray,
    cell_m: float,
    footprint_m: float,
    wide_m: float,
    min_fraction: float = 0.5,
) -> PlaneFit:
    """The footprint plane of :func:`weighted_plane_fit` (``with_cov=False``), with its slope replaced by
    the plane's over ``wide_m`` where that one is steeper (or the footprint's is undetermined).

    SGM over horizontal planes can terrace a steep crater wall into flat steps about a footprint
    wide; the slope over a few footprints still sees the wall. ``z_plane`` stays the footprint's.
    Each fit boxes its own per-cell products in place: recomputing them (a few products per cell) is
    cheaper than holding nine float64 grids through both fits, where an approach pair's memory peaks.
    """
    n = footprint_cells(footprint_m, cell_m)
    fit = _fit_from_products(*_plane_products(z, sigma), n, cell_m, min_fraction, 1.0, False)
    if wide_m <= footprint_m:
        return fit
    n_w = footprint_cells(wide_m, cell_m)
    wide = _fit_from_products(*_plane_products(z, sigma), n_w, cell_m, min_fraction, 1.0, False)
    steeper = np.isfinite(wide.grad) & ~(wide.grad <= fit.grad)
    fit.grad = np.where(steeper, wide.grad, fit.grad).astype(np.float32)
    fit.slope_deg = np.where(steeper, wide.slope_deg, fit.slope_deg).astype(np.float32)
    return fit


def footprint_mean(a: np.ndarray, n: int) -> np.ndarray:
    """Mean of the finite values of ``a`` over the ``n x n`` square around each cell (NaN if none)."""
    ok = np.isfinite(a)
    s = _box(np.where(ok, a, 0.0).astype(np.float64), n)
    c = _box(ok.astype(np.float64), n)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(c > 0, s / c, np.nan).astype(np.float32)


def norm_cdf(x: np.ndarray) -> np.ndarray:
    """Standard normal CDF (float32) via erf."""
    x = np.asarray(x, np.float32)
    return (0.5 * (1.0 + _erf(x * np.float32(1.0 / math.sqrt(2.0))))).astype(np.float32)


def _erf(x: np.ndarray) -> np.ndarray:
    # Abramowitz & Stegun 7.1.26 (|error| < 1.5e-7): numpy has no vectorised erf
    s = np.sign(x)
    a = np.abs(x)
    t = 1.0 / (1.0 + 0.3275911 * a)
    poly = ((((1.061405429 * t - 1.453152027) * t + 1.421413741) * t - 0.284496736) * t + 0.254829592) * t
    y = 1.0 - poly * np.exp(-a * a)
    return s * y


@dataclass
class Evidence:
    state: np.ndarray  # uint8, protocol.pairdir.STATE_*
    psafe: np.ndarray  # float32, NaN outside
    hazard: np.ndarray  # float32 in [0, 1], NaN outside; unknown and unsafe are 1 (DESIGN.md)


def classify(
    grad: np.ndarray,
    grad_sigma: np.ndarray,
    rough: np.ndarray,
    rough_sigma: np.ndarray,
    cues: np.ndarray,
    covered: np.ndarray,
    cell_m: float | np.ndarray,
    *,
    slope_limit_deg: float = 15.0,
    rough_limit_m: float = 0.30,
    k: float = 2.0,
    p_min: float = 0.9,
    prior: float = 0.5,
) -> Evidence:
    """Three states, P(safe) and the DESIGN.md hazard map from the layers (module doc).

    ``grad`` (m per cell) and ``cell_m`` give the slope; ``cues`` (bool) are image evidence of a
    hazard (shadow, wall, rock). NaN slope or roughness is no evidence: unknown, with P(safe) =
    ``prior`` unless a cue says unsafe. ``k = 0`` and ``p_min = 0`` ignore the uncertainty (a
    point is then unsafe exactly when its estimate crosses a limit).
    """
    G = np.float32(math.tan(math.radians(slope_limit_deg))) * np.asarray(cell_m, np.float32)
    g = np.asarray(grad, np.float32)
    sg = np.maximum(np.asarray(grad_sigma, np.float32), 1e-6)
    r = np.asarray(rough, np.float32)
    sr = np.maximum(np.asarray(rough_sigma, np.float32), 1e-6)
    known = np.isfinite(g) & np.isfinite(r) & np.isfinite(sg) & np.isfinite(sr)
    with np.errstate(invalid="ignore"):
        p = norm_cdf((G - g) / sg) * norm_cdf((rough_limit_m - r) / sr)
        bad = known & ((g - k * sg > G) | (r - k * sr > rough_limit_m))
        if k <= 0 and p_min <= 0:  # no uncertainty: the estimate decides
            bad = known & ((g >= G) | (r >= rough_limit_m))
            good = known & ~bad
        else:
            good = known & ~bad & (p >= p_min)
    cue = np.asarray(cues, bool)
    cov = np.asarray(covered, bool)
    state = np.full(g.shape, STATE_UNKNOWN, np.uint8)
    state[good] = STATE_SAFE
    state[bad | cue] = STATE_UNSAFE
    state[~cov] = STATE_OUTSIDE
    psafe = np.where(known, p, np.float32(prior)).astype(np.float32)
    psafe[bad | cue] = np.minimum(psafe[bad | cue], 0.0)
    psafe[~cov] = np.nan
    with np.errstate(invalid="ignore"):
        h = np.maximum(g / G, r / np.float32(rough_limit_m))
    hazard = np.where(state == STATE_SAFE, np.minimum(h, np.float32(0.999)), np.float32(1.0)).astype(np.float32)
    hazard[~cov] = np.nan
    return Evidence(state, psafe, hazard)


def widen_unsafe(ev: Evidence, margin_px: float) -> Evidence:
    """Keep-out margin: every covered point within ``margin_px`` of an unsafe one becomes unsafe."""
    r = int(math.floor(margin_px))
    if r <= 0:
        return ev
    yy, xx = np.mgrid[-r : r + 1, -r : r + 1]
    disk = ((xx * xx + yy * yy) <= margin_px * margin_px + 1e-9).astype(np.uint8)
    near = cv2.dilate((ev.state == STATE_UNSAFE).astype(np.uint8), disk).astype(bool)
    grow = near & (ev.state != STATE_OUTSIDE)
    state = ev.state.copy()
    state[grow] = STATE_UNSAFE
    psafe = ev.psafe.copy()
    psafe[grow] = 0.0
    hazard = ev.hazard.copy()
    hazard[grow] = 1.0
    return Evidence(state, psafe, hazard)


CAP_SLOPES = ("a", "a_pc", "max")


def cap_slope(feats: Mapping[str, np.ndarray], which: str = "a") -> np.ndarray:
    """The slope ratio the call's cap reads: ``a`` (the DEM's footprint slope over the limit), ``a_pc``
    (its sun-ward part read from the shading, :mod:`flight_sw.photoclinometry`) or ``max`` of the two.
    Where ``a_pc`` is unknown (no sun given, no lit footprint) the DEM's ``a`` stands in."""
    a = np.asarray(feats["a"], np.float32)
    if which == "a":
        return a
    if which not in CAP_SLOPES:
        raise ValueError(f"cap slope must be one of {CAP_SLOPES}, got {which!r}")
    pc = np.asarray(feats["a_pc"], np.float32) if "a_pc" in feats else np.full(a.shape, np.nan, np.float32)
    pc = np.where(np.isfinite(pc), pc, a)
    return pc if which == "a_pc" else np.fmax(a, pc)


def classify_calibrated(
    model: Model,
    feats: Mapping[str, np.ndarray],
    cues: np.ndarray,
    covered: np.ndarray,
    fp_budget: float,
    p_min: float = 0.0,
    p_unsafe: float = 0.5,
    a_max: float = math.inf,
    a_sigma_k: float = 0.0,
    cap: str = "a",
) -> Evidence:
    """Three states from the calibrated P(safe) (:mod:`flight_sw.psafe`) and the FP-budget rule.

    ``P(safe)`` is the model's at every covered point and 0 on a hard cue (``cues``: dark shadow,
    which is a hazard by definition). Safe = called by :func:`flight_sw.psafe.budget_rule` (in
    decreasing P(safe) while the expected share of undetected hazards stays within ``fp_budget``
    of the covered points, and ``P >= p_min``); a point whose estimated slope is ``>= a_max`` times
    the limit is never called safe (SGM's smoothing flattens footprint-scale walls: a near-limit
    estimate is where the undetected hazards concentrate on tuning pairs), nor is a point without an
    elevation (its P(safe) is a prior from its surroundings; on the held-out deep crater, calling such
    points safe put FP over 1 % at 200-300 m). With ``a_sigma_k = k > 0`` the cap judges the slope
    against its uncertainty instead: a point at or above ``a_max`` stays callable while
    ``a + k u < 1`` (the slope is below the limit by k standard uncertainties; issue 9's "judge slope
    against its uncertainty"), which lets well-measured 6-15 deg ground through at low altitude and
    changes nothing where ``u`` is large. ``cap`` picks the slope the cap reads (:func:`cap_slope`). Unsafe = a cue or,
    where the footprint slope was measured, ``P(safe) < p_unsafe`` (more likely a hazard than not, for
    ``p_unsafe = 0.5``); unknown otherwise. A point without an elevation and without a cue is unknown
    whatever its P(safe): with no slope, the trees' P(safe) is a context prior (0.08-0.13 on the points of an
    image-only pair), not evidence of a hazard (DESIGN.md: unknown = not enough evidence).
    The hazard map keeps DESIGN.md's semantics: a safe point gets ``min(max(a, rough), 0.999)``, the others 1.
    """
    cov = np.asarray(covered, bool)
    cue = np.asarray(cues, bool) & cov
    # a hard cue is P(safe) 0 whatever the model says: the model runs on the other points only
    p = np.zeros(int(np.count_nonzero(cov)), np.float32)
    live = ~cue[cov]
    if live.any():
        p[live] = model.predict(feats, cov & ~cue)
    a = cap_slope(feats, cap)[cov]
    with np.errstate(invalid="ignore"):
        over = a >= a_max
        if a_sigma_k > 0:
            over &= ~(a + np.float32(a_sigma_k) * np.asarray(feats["u"], np.float32)[cov] < 1.0)
        unmeasured = ~np.isfinite(np.asarray(feats["a"], np.float32)[cov])
        # no elevation: never called on context; a cue never, whatever p_min lets the budget take
        barred = over | unmeasured | cue[cov]
    call = budget_rule(np.where(barred, np.float32(np.nan), p), fp_budget, p_min, n=int(cov.sum()))
    psafe = np.full(cov.shape, np.nan, np.float32)
    psafe[cov] = p
    state = np.full(cov.shape, STATE_OUTSIDE, np.uint8)
    st = np.full(p.shape, STATE_UNKNOWN, np.uint8)
    st[call] = STATE_SAFE
    st[(((p < p_unsafe) & ~unmeasured) | cue[cov]) & ~call] = STATE_UNSAFE
    state[cov] = st
    with np.errstate(invalid="ignore"):
        h = np.fmax(np.asarray(feats["a"], np.float32), np.asarray(feats["rough"], np.float32))
    h = np.where(np.isfinite(h), np.clip(h, 0.0, 0.999), np.float32(0.0))
    hazard = np.where(state == STATE_SAFE, h, np.float32(1.0)).astype(np.float32)
    hazard[~cov] = np.nan
    return Evidence(state, psafe, hazard)


def below_model_scale(ev: Evidence, footprint_px: float, footprint_px_min: float, prior: float) -> Evidence:
    """The calibrated call where the footprint is smaller, in pixels, than the P(safe) model was fitted down to.

    Below ``footprint_px_min`` (recorded with each model by ``bench/fit_psafe.py``) the trees' P(safe) is an
    extrapolation: a 128 px camera at 5000 m (a 0.14 px footprint against 0.19) called 17 points safe at >= 0.99,
    one of them a hazard, and put the top site on it (review of stop 64). There, nothing is evidence for "safe":
    a point called safe becomes unknown, and ``P = min(P, prior)`` (``prior``: the model's share of safe
    training points), since fusion reads a 0.99 as evidence (review of stop 65). Unsafe calls and NaN (not
    covered) stay. At or above the scale ``ev`` is returned as it is.
    """
    if not footprint_px < footprint_px_min:
        return ev
    was = ev.state == STATE_SAFE
    return Evidence(
        np.where(was, STATE_UNKNOWN, ev.state).astype(np.uint8),
        np.minimum(ev.psafe, np.float32(prior)).astype(np.float32),
        np.where(was, np.float32(1.0), ev.hazard).astype(np.float32),
    )


def grid_evidence(
    called: np.ndarray,
    unsafe: np.ndarray,
    psafe: np.ndarray,
    covered: np.ndarray,
    grad: np.ndarray | None,
    cell_m: float,
    rough: np.ndarray | None,
    slope_limit_deg: float = 15.0,
    rough_limit_m: float = 0.30,
    measured: np.ndarray | None = None,
) -> Evidence:
    """Grid states from the image's call, pulled onto the grid: safe where the pixels read were called
    safe (``called``: the caller's share of the bilinear weight, ``Params.grid_call_share``), unsafe where
    most were unsafe; P(safe) is the pulled pixel probability.

    ``measured`` (bool, optional): cells with an elevation. A called cell without one stays unknown:
    the pull can read called pixels around a DEM hole, and a safe cell must have the elevation a site
    is placed at (0.06 % of safe cells on the default-scene held-out pairs before this rule).
    """
    cov = np.asarray(covered, bool)
    state = np.full(cov.shape, STATE_UNKNOWN, np.uint8)
    state[np.asarray(unsafe, bool)] = STATE_UNSAFE
    ok = np.asarray(called, bool)
    if measured is not None:
        ok = ok & np.asarray(measured, bool)
    state[ok] = STATE_SAFE
    state[~cov] = STATE_OUTSIDE
    ps = np.where(cov, np.asarray(psafe, np.float32), np.nan).astype(np.float32)
    h = np.zeros(cov.shape, np.float32)
    G = math.tan(math.radians(slope_limit_deg)) * float(cell_m)
    with np.errstate(invalid="ignore"):
        if grad is not None:
            h = np.fmax(h, np.asarray(grad, np.float32) / np.float32(G))
        if rough is not None:
            h = np.fmax(h, np.asarray(rough, np.float32) / np.float32(rough_limit_m))
    hazard = np.where(state == STATE_SAFE, np.clip(np.nan_to_num(h), 0.0, 0.999), np.float32(1.0)).astype(np.float32)
    hazard[~cov] = np.nan
    return Evidence(state, ps, hazard)


def hold_unsafe_pixels(
    grid: Evidence, unsafe: np.ndarray, psafe: np.ndarray, px_maps: tuple[np.ndarray, np.ndarray]
) -> tuple[Evidence, int]:
    """The grid with every cell that holds the ground point of a pixel called unsafe made unsafe; and how many
    cells that changed.

    The grid reads the image bilinearly at its cells' centres (:func:`grid_evidence`), so a cell is unsafe
    only where unsafe pixels carry more than half of its four weights. An unsafe pixel with no cell centre
    within ~0.3 px (a one-pixel shadow or rock; on an oblique view's near field, where cells are wider than
    pixels, any pixel between the centres) left every cell around it safe, and the site search, which reads
    only the grid, could centre a footprint on it. Here each unsafe pixel ``(u, v)`` marks the cell
    ``(round(my[v, u]), round(mx[v, u]))`` its ground falls in (``px_maps``: :func:`flight_sw.mapping.grid_maps`),
    a scatter-max of the pixel call, and that cell's P(safe) becomes ``min(P_cell, P_pixel)``. Along an
    unsafe region's edge the cell holding an unsafe pixel is mostly unsafe already where the grid runs with the
    pixels; where it is turned against them or coarser, the edge can move up to about half a cell into the safe
    side (review of stop 65: 0-1.3 px on synthetic grids turned 30-45 deg; none on the real pairs it tried).
    """
    rows, cols = grid.state.shape
    vs, us = np.nonzero(np.asarray(unsafe, bool))
    gc = np.rint(px_maps[0][vs, us])
    gr = np.rint(px_maps[1][vs, us])
    inside = (gc >= 0) & (gc < cols) & (gr >= 0) & (gr < rows)  # -1e4 where a pixel has no ground point
    flat = gr[inside].astype(np.intp) * cols + gc[inside].astype(np.intp)
    held = grid.state.ravel()[flat] == STATE_SAFE  # the only cells it can change
    if not held.any():
        return grid, 0
    flat = flat[held]
    state = grid.state.copy()
    ps = grid.psafe.copy()
    hazard = grid.hazard.copy()
    np.fmin.at(ps.ravel(), flat, np.asarray(psafe, np.float32)[vs[inside][held], us[inside][held]])
    state.ravel()[flat] = STATE_UNSAFE
    hazard.ravel()[flat] = np.float32(1.0)
    return Evidence(state, ps, hazard), int(np.unique(flat).size)
