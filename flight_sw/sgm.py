"""Semi-global aggregation of a plane-sweep cost volume (Hirschmueller 2008), planes as disparities.

Along each path direction ``r`` the aggregated cost is (Hirschmueller 2008, eq. 13)::

    L_r(p, k) = C(p, k) + min( L_r(p - r, k),
                               L_r(p - r, k -+ 1) + P1,
                               min_i L_r(p - r, i) + P2(p, r) ) - min_i L_r(p - r, i)

and ``S(p, k) = sum_r L_r(p, k)``. Eight directions: the six vertical and diagonal ones are
swept row by row (a diagonal predecessor is the previous row shifted by one column), the two
horizontal ones column by column, each sweep vectorised over a whole line and all its
directions at once. ``P2`` adapts to the intensity step along the path,
``P2(p, r) = max(P1 + 1, P2_0 / (1 + |I(p) - I(p - r)| / g0))``, so depth may jump at image
edges (eq. 14's ``P2'/|I_p - I_q|`` with a bounded denominator). Costs and sums are ``int16``:
``L <= C_max + P2`` keeps eight paths below 32767.

The winner per pixel is refined with a parabola through ``S(k-1), S(k), S(k+1)`` (eq. 3.15);
a uniqueness test against the best plane outside ``k +- 1``, a test against minima at the
ends of the planes the pixel saw, and a speckle filter (connected regions of similar plane
index smaller than ``speckle_px``, ``cv2.filterSpeckles``) reject matches.

The elevation uncertainty comes from the curvature of the *unaggregated* cost around the
winner, averaged over a small neighbourhood (the aggregation's own curvature is bounded below
by ``P1`` even on blank ground and would hide missing texture)::

    kappa(p) = mean_N(p) (C(k-1) + C(k+1) - 2 C(k)) / 2,    sigma_k = sqrt(T / kappa)   (plane steps)
    sigma_z = sqrt(sigma_k^2 + 1/12) * dz_k                                    (metres, dz_k = local spacing)

i.e. a Gaussian likelihood ``exp(-C / T)`` around the minimum; the temperature ``T`` is a
calibration constant chosen on tuning seeds (docs/benchmarks/pipeline.md) and the 1/12 is the
quantisation floor of the plane grid.
"""

from __future__ import annotations

import ctypes
import functools
import time
from dataclasses import dataclass

import cv2
import numpy as np

from .kernels import load_kernel

_DIRS_ROWS = ((1, 0), (1, 1), (1, -1))  # (drow, dcol) of the step; predecessor is p - r


class DeadlineReached(Exception):
    """The aggregation passed its deadline (the caller falls back to a lower level)."""


def p2_maps(guide: np.ndarray, p1: int, p2: int, g0: float, adapt: bool = True) -> dict[tuple[int, int], np.ndarray]:
    """``P2(p, r)`` (int16, h x w) for the four step directions r (and their opposites share them shifted)."""
    g = np.asarray(guide, np.float32)
    out: dict[tuple[int, int], np.ndarray] = {}
    for dr, dc in ((1, 0), (0, 1), (1, 1), (1, -1)):
        if not adapt:
            m = np.full(g.shape, p2, np.int16)
        else:
            prev = np.roll(g, (dr, dc), axis=(0, 1))  # value at p - r (wraps at the border: unused there)
            step = np.abs(g - prev)
            m = np.maximum(p1 + 1, np.rint(p2 / (1.0 + step / g0))).astype(np.int16)
        out[(dr, dc)] = m
        # the opposite direction's step at p is the same difference seen from p - r: shift back
        out[(-dr, -dc)] = np.roll(m, (-dr, -dc), axis=(0, 1))
    return out


def _update(prev: np.ndarray, cur: np.ndarray, p1: int, p2: np.ndarray, out: np.ndarray, tmp: np.ndarray) -> None:
    """One path step for stacked lines: ``prev``/``cur``/``out`` (..., n, D) int16, ``p2`` (..., n, 1)."""
    m = prev.min(axis=-1, keepdims=True)
    np.copyto(tmp, prev)
    np.add(prev[..., :-1], p1, out=out[..., 1:])
    np.minimum(tmp[..., 1:], out[..., 1:], out=tmp[..., 1:])
    np.add(prev[..., 1:], p1, out=out[..., :-1])
    np.minimum(tmp[..., :-1], out[..., :-1], out=tmp[..., :-1])
    np.minimum(tmp, m + p2, out=tmp)
    np.subtract(tmp, m, out=tmp)
    np.add(cur, tmp, out=out)


@functools.cache
def kernel() -> ctypes.CDLL | None:
    """The compiled kernel (``flight_sw/_sgmc.c``, built by the install), or None if it is not there."""
    lib = load_kernel("flight_sw._sgmc")
    if lib is None:
        return None
    f = lib.sgm_aggregate
    f.restype = ctypes.c_int
    f.argtypes = [ctypes.c_void_p] * 3 + [ctypes.c_int] * 5 + [ctypes.c_void_p]
    return lib


def aggregate(
    cost: np.ndarray,
    guide: np.ndarray,
    p1: int,
    p2: int,
    g0: float = 4.0,
    paths: int = 8,
    adapt: bool = True,
    deadline: float | None = None,
    use_kernel: bool = True,
) -> np.ndarray:
    """``S = sum_r L_r`` (int16, h x w x D) of an int16 cost ``(h, w, D)`` (module doc).

    ``paths``: 8 (all), 4 (horizontal and vertical) or 0 (no aggregation: ``S = C``).
    ``guide`` is the reference image over the same pixels (for the adaptive ``P2``).
    Raises :class:`DeadlineReached` if ``deadline`` (``time.monotonic()``) passes (checked
    between directions by the compiled kernel, every 16 lines by the numpy reference).
    ``use_kernel=False`` forces the numpy reference.
    """
    C = np.ascontiguousarray(cost, dtype=np.int16)
    if paths == 0:
        return C.copy()
    if paths not in (4, 8):
        raise ValueError(f"paths must be 0, 4 or 8, got {paths}")
    if not 0 < p1 < p2 <= 2000 or int(C.max(initial=0)) > 2047:
        raise ValueError(f"need 0 < P1 < P2 <= 2000 and costs <= 2047 (int16 sums), got P1={p1}, P2={p2}")
    h, w, D = C.shape
    if D < 3:
        raise ValueError(f"need at least 3 planes, got {D}")
    P2 = p2_maps(guide, p1, p2, g0, adapt)
    lib = kernel() if use_kernel else None
    if lib is not None:
        dirs8 = [(1, 0), (-1, 0), (0, 1), (0, -1), (1, 1), (-1, -1), (1, -1), (-1, 1)][:paths]
        S = np.zeros((h, w, D), np.int16)
        for r in dirs8:  # one direction per call: the clock is checked between them
            if deadline is not None and time.monotonic() > deadline:
                raise DeadlineReached
            pm = np.ascontiguousarray(P2[r])
            dv = np.array(r, np.int32)
            rc = lib.sgm_aggregate(C.ctypes.data, pm.ctypes.data, dv.ctypes.data, 1, h, w, D, int(p1), S.ctypes.data)
            if rc != 0:
                raise MemoryError("sgm kernel: line buffers could not be allocated")
        return S
    S = np.zeros((h, w, D), np.int16)
    # --- vertical and diagonal paths, swept over rows: downward (+1, dc) and upward (-1, dc)
    dirs = _DIRS_ROWS if paths == 8 else _DIRS_ROWS[:1]
    nd = len(dirs)
    down = [(dr, dc) for dr, dc in dirs]
    up = [(-dr, -dc) for dr, dc in dirs]
    allr = down + up
    p2rows = np.stack([P2[r] for r in allr])  # (2nd, h, w)
    L = np.zeros((2 * nd, w, D), np.int16)
    prev = np.zeros_like(L)
    tmp = np.empty_like(L)
    cur = np.empty_like(L)
    p2line = np.empty((2 * nd, w, 1), np.int16)
    for s in range(h):
        if deadline is not None and s % 16 == 0 and time.monotonic() > deadline:
            raise DeadlineReached
        i_d, i_u = s, h - 1 - s
        cur[:nd] = C[i_d]
        cur[nd:] = C[i_u]
        if s == 0:
            L[:] = cur
        else:
            # predecessor p - r: same column for dc = 0; column j - dc for diagonals; none at the border
            for q, (_dr, dc) in enumerate(allr):
                if dc == 0:
                    prev[q] = L[q]
                elif dc > 0:
                    prev[q, 1:] = L[q, :-1]
                    prev[q, 0] = 0  # no predecessor: L = C
                else:
                    prev[q, :-1] = L[q, 1:]
                    prev[q, -1] = 0
            p2line[:nd, :, 0] = p2rows[:nd, i_d]
            p2line[nd:, :, 0] = p2rows[nd:, i_u]
            _update(prev, cur, p1, p2line, L, tmp)
        S[i_d] += L[:nd].sum(axis=0, dtype=np.int16)
        S[i_u] += L[nd:].sum(axis=0, dtype=np.int16)
    # --- horizontal paths, swept over columns: (0, +1) and (0, -1)
    p2cols = np.stack([P2[(0, 1)], P2[(0, -1)]])  # (2, h, w)
    L2 = np.zeros((2, h, D), np.int16)
    tmp2 = np.empty_like(L2)
    cur2 = np.empty_like(L2)
    prev2 = np.empty_like(L2)
    p2c = np.empty((2, h, 1), np.int16)
    for s in range(w):
        if deadline is not None and s % 16 == 0 and time.monotonic() > deadline:
            raise DeadlineReached
        j_l, j_r = s, w - 1 - s
        cur2[0] = C[:, j_l]
        cur2[1] = C[:, j_r]
        if s == 0:
            L2[:] = cur2
        else:
            np.copyto(prev2, L2)
            p2c[0, :, 0] = p2cols[0, :, j_l]
            p2c[1, :, 0] = p2cols[1, :, j_r]
            _update(prev2, cur2, p1, p2c, L2, tmp2)
        S[:, j_l] += L2[0]
        S[:, j_r] += L2[1]
    return S


@dataclass
class Match:
    """Winner-take-all result on the aggregated cost, in plane-index units."""

    k: np.ndarray  # int32 h x w winning plane
    frac: np.ndarray  # float32 h x w sub-plane index (k + parabolic offset)
    ok: np.ndarray  # bool h x w: passed the interval-end and uniqueness tests
    uniq: np.ndarray  # float32 h x w: (S2 - S1) / S1, S2 the best plane outside k +- 1
    k2: np.ndarray  # int32 h x w: that competing plane
    kappa: np.ndarray  # float32 h x w: local curvature of the raw cost at the winner (cost units)


UNIQ_STRIP_ELEMENTS = 1 << 20  # cost entries per strip of :func:`winner`'s uniqueness copy (2 MiB)


def winner(
    S: np.ndarray,
    C: np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
    uniqueness: float = 0.0,
    kappa_radius: int = 2,
) -> Match:
    """Winner, sub-plane refinement and checks on ``S`` (h, w, D); ``C`` the raw cost (h, w, D).

    ``lo``/``hi`` are the first/last planes each pixel saw (:func:`flight_sw.costvolume.valid_interval`):
    a minimum on either end is rejected (the true plane may lie beyond; this also removes the
    range ends and the overlap-edge band). ``uniqueness > 0`` rejects ``(S2 - S1) / S1 < uniqueness``.
    """
    h, w, D = S.shape
    k = S.argmin(axis=2).astype(np.int32)
    km = np.clip(k - 1, 0, D - 1)
    kp = np.clip(k + 1, 0, D - 1)
    s0 = np.take_along_axis(S, k[..., None], 2)[..., 0].astype(np.float32)
    sm = np.take_along_axis(S, km[..., None], 2)[..., 0].astype(np.float32)
    sp = np.take_along_axis(S, kp[..., None], 2)[..., 0].astype(np.float32)
    denom = 2.0 * (sm + sp - 2.0 * s0)
    with np.errstate(divide="ignore", invalid="ignore"):
        off = np.where(denom > 0, (sm - sp) / denom, 0.0)
    frac = (k + np.clip(off, -0.5, 0.5)).astype(np.float32)
    ok = (k > lo) & (k < hi) & (lo >= 0)
    # uniqueness: best cost outside k-1..k+1, on a copy of a strip of rows at a time (a whole copy of S
    # was the largest array of the DEM stage: 2 bytes per pixel and plane)
    big = np.int16(np.iinfo(np.int16).max)
    k2 = np.empty((h, w), np.int32)
    s2 = np.empty((h, w), np.float32)
    rows = max(1, UNIQ_STRIP_ELEMENTS // max(1, w * D))
    for r0 in range(0, h, rows):
        r = slice(r0, min(h, r0 + rows))
        S2 = S[r].copy()
        for kk in (km[r], k[r], kp[r]):
            np.put_along_axis(S2, kk[..., None], big, 2)
        k2[r] = S2.argmin(axis=2)
        s2[r] = np.take_along_axis(S2, k2[r][..., None], 2)[..., 0]
    uniq = (s2 - s0) / np.maximum(s0, 1.0)
    if uniqueness > 0:
        ok &= uniq >= uniqueness
    c0 = np.take_along_axis(C, k[..., None], 2)[..., 0].astype(np.float32)
    cm = np.take_along_axis(C, km[..., None], 2)[..., 0].astype(np.float32)
    cp = np.take_along_axis(C, kp[..., None], 2)[..., 0].astype(np.float32)
    curv = 0.5 * (cm + cp - 2.0 * c0)
    kr = 2 * int(kappa_radius) + 1
    kappa = cv2.blur(curv, (kr, kr), borderType=cv2.BORDER_REPLICATE)
    return Match(k, frac, ok, uniq.astype(np.float32), k2, kappa.astype(np.float32))


def speckle_filter(frac: np.ndarray, ok: np.ndarray, max_size: int, max_diff: float = 1.0) -> np.ndarray:
    """``ok`` without connected regions (4-neighbours differing by <= ``max_diff`` planes) below ``max_size`` px."""
    if max_size <= 0:
        return ok
    d = np.where(ok, np.rint(frac * 16.0), -16).astype(np.int16)  # 1/16 plane units, -1 plane = invalid
    cv2.filterSpeckles(d, -16, int(max_size), int(round(max_diff * 16)))
    return ok & (d != -16)


def plane_sigma(
    kappa: np.ndarray,
    temperature: float,
    uniq: np.ndarray | None = None,
    jump: np.ndarray | None = None,
    uniq_scale: float = 0.2,
) -> np.ndarray:
    """Elevation uncertainty in plane steps (inf where the cost curve is not convex)::

        sigma_k^2 = T / kappa + 1/12 + w (k2 - k)^2,   w = max(0, 1 - uniq / uniq_scale)

    The last term is the ambiguity of a second minimum ``k2`` of the aggregated cost whose
    cost is within ``uniq_scale`` (relative) of the winner's: the closer it is, the more its
    distance counts.
    """
    with np.errstate(divide="ignore", invalid="ignore"):
        v = temperature / kappa + 1.0 / 12.0
        if uniq is not None and jump is not None and uniq_scale > 0:
            wgt = np.clip(1.0 - uniq / uniq_scale, 0.0, 1.0)
            v = v + wgt * np.asarray(jump, np.float32) ** 2
        s = np.sqrt(v)
    return np.where(kappa > 0, s, np.inf).astype(np.float32)
