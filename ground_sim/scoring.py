"""Scoring a hazard-detection result against ground truth (thesis ch. 6, DESIGN.md).

Pure functions on arrays in the image plane of i1. Nothing here knows about the
flight software; ``hil_server.evaluate`` feeds its outputs in.

Conventions (DESIGN.md "Scoring convention", thesis sec 2.8, Tables 6.4/6.11):

* **positive = safe**. TP safe called safe, TN unsafe called unsafe,
  FP unsafe called safe (undetected hazard, Table 2.1 wants <= 1 %),
  FN safe called unsafe (false alarm). Percentages are of the scored pixels.
* unsafe <=> hazard >= 1.
* An estimated hazard that is NaN inside the covered area means "not assessed";
  a lander must not touch down there, so it counts as **unsafe** (the
  conservative flight choice: a missing estimate can cost TP, never add FP).
* Pixels whose ground truth is NaN, outside ``covered_mask`` or inside
  ``exclude`` are not scored at all.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from protocol.errors import InputError
from protocol.pairdir import Camera, Pose


class ScoringInputError(InputError):
    """Arrays given to a scoring function do not fit together."""


def _same_shape(**arrays: np.ndarray | None) -> tuple[int, ...]:
    shape: tuple[int, ...] | None = None
    first = ""
    for name, arr in arrays.items():
        if arr is None:
            continue
        if np.ndim(arr) != 2:
            raise ScoringInputError(f"{name}: expected a 2-D image-plane array, got shape {np.shape(arr)}")
        if shape is None:
            shape, first = np.shape(arr), name
        elif np.shape(arr) != shape:
            raise ScoringInputError(f"{name}: shape {np.shape(arr)} does not match {first} {shape}")
    if shape is None:
        raise ScoringInputError("no arrays given")
    return shape


def _scored(shape: tuple[int, ...], mask: np.ndarray | None, exclude: np.ndarray | None) -> np.ndarray:
    keep = np.ones(shape, dtype=bool) if mask is None else np.asarray(mask, dtype=bool).copy()
    if exclude is not None:
        keep &= ~np.asarray(exclude, dtype=bool)
    return keep


def error_stats(est: np.ndarray, truth: np.ndarray, mask: np.ndarray | None = None) -> dict[str, float]:
    """Statistics of ``err = est - truth`` over pixels where both are finite (and ``mask``).

    Returns ``mean_abs`` = mean(|err|), ``median`` = median(err) (signed),
    ``mad`` = median(|err - median(err)|) (unscaled median absolute deviation,
    thesis sec 4.3/6.1), ``skewness`` = m3 / m2^1.5 (Fisher-Pearson g1) and
    ``kurtosis`` = m4 / m2^2 - 3 (**excess** kurtosis, 0 for a Gaussian), with
    ``m_k`` the k-th central sample moment, and ``n`` the pixel count. With no
    valid pixel every statistic is NaN and ``n`` is 0.

    Note: the thesis's kurtosis column (Tables 6.3, 6.10) equals its skewness
    minus 3 in every row but Table 6.3's 50 m one (whose skewness repeats Table
    6.2's MAD), so it is not a kurtosis of any definition; ours is not
    comparable to it.
    """
    _same_shape(est=est, truth=truth, mask=mask)
    e = np.asarray(est, dtype=np.float64)
    t = np.asarray(truth, dtype=np.float64)
    keep = _scored(e.shape, mask, None) & np.isfinite(e) & np.isfinite(t)
    err = (e - t)[keep]
    n = int(err.size)
    if n == 0:
        nan = float("nan")
        return {"mean_abs": nan, "median": nan, "mad": nan, "skewness": nan, "kurtosis": nan, "n": 0}
    med = float(np.median(err))
    dev = err - err.mean()
    m2 = float(np.mean(dev * dev))
    if m2 > 0.0:
        skew = float(np.mean(dev**3)) / m2**1.5
        kurt = float(np.mean(dev**4)) / (m2 * m2) - 3.0
    else:
        skew = kurt = float("nan")
    return {
        "mean_abs": float(np.mean(np.abs(err))),
        "median": med,
        "mad": float(np.median(np.abs(err - med))),
        "skewness": skew,
        "kurtosis": kurt,
        "n": n,
    }


def dem_error_stats(est: np.ndarray, truth: np.ndarray, mask: np.ndarray | None = None) -> dict[str, float]:
    """DEM error statistics (Tables 6.2/6.9/6.3/6.10); see :func:`error_stats` for the formulas."""
    return error_stats(est, truth, mask)


def detrended_error(est: np.ndarray, truth: np.ndarray, xy: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Mean |error| left after removing the error's best plane over the ground, in metres.

    ``e = est - truth``; least squares ``e ~ a + b X + c Y`` over the scored pixels (``xy``: HxWx2 true
    world X, Y of each pixel), and the result is ``mean |e - (a + b X + c Y)|``. An error in the
    absolute attitude tilts the whole reconstruction about the camera, and an error in the datum
    (the reported altitude) shifts it (thesis sec 6.3); to first order the plane absorbs both, and
    neither changes a slope or a roughness at the footprint scale. What is left is the shape error a
    hazard detector sees. NaN with fewer than 3 scored pixels.
    """
    _same_shape(est=est, truth=truth, mask=mask)
    w = np.asarray(xy, dtype=np.float64)
    if w.shape != np.shape(est) + (2,):
        raise ValueError(f"xy must be {np.shape(est) + (2,)}, got {w.shape}")
    e = np.asarray(est, dtype=np.float64) - np.asarray(truth, dtype=np.float64)
    keep = _scored(e.shape, mask, None) & np.isfinite(e) & np.isfinite(w).all(axis=-1)
    if np.count_nonzero(keep) < 3:
        return float("nan")
    x, y, z = w[..., 0][keep], w[..., 1][keep], e[keep]
    A = np.c_[np.ones(z.size), x - x.mean(), y - y.mean()]  # centred: a well-conditioned fit
    coef = np.linalg.lstsq(A, z, rcond=None)[0]
    return float(np.mean(np.abs(z - A @ coef)))


def unsafe_estimate(hazard_est: np.ndarray) -> np.ndarray:
    """Estimated unsafe map: ``hazard >= 1`` or NaN (not assessed counts as unsafe)."""
    h = np.asarray(hazard_est, dtype=np.float64)
    return ~(h < 1.0)  # NaN compares False, so it lands on the unsafe side


def _counts(est_unsafe: np.ndarray, true_unsafe: np.ndarray, keep: np.ndarray) -> dict[str, float]:
    n = int(np.count_nonzero(keep))
    eu, tu = est_unsafe[keep], true_unsafe[keep]
    tp = int(np.count_nonzero(~eu & ~tu))
    tn = int(np.count_nonzero(eu & tu))
    fp = int(np.count_nonzero(~eu & tu))
    fn = int(np.count_nonzero(eu & ~tu))

    def pct(a: int, b: int) -> float:
        return 100.0 * a / b if b else float("nan")

    return {
        "tp": pct(tp, n),
        "tn": pct(tn, n),
        "fp": pct(fp, n),
        "fn": pct(fn, n),
        "tn_rate": pct(tn, tn + fp),
        "tp_rate": pct(tp, tp + fn),
        "cdi": pct(tp + tn, n),
        "hazards_pct": pct(tn + fp, n),
        "n": n,
    }


def confusion(
    hazard_est: np.ndarray, hazard_true: np.ndarray, covered_mask: np.ndarray | None, exclude: np.ndarray | None = None
) -> dict[str, float]:
    """Pixel-level detection probabilities (thesis Tables 6.4/6.11, Fig. 6.6/6.12), in percent.

    ``tp, tn, fp, fn`` are shares of the scored pixels (covered, not excluded,
    finite truth); ``tn_rate`` = TN/(TN+FP) (hazards detected, TN%),
    ``tp_rate`` = TP/(TP+FN) (safe sites detected, TP%), ``cdi`` = TP+TN,
    ``hazards_pct`` = true hazards in the scored area (Tables 6.1/6.8), ``n`` =
    scored pixel count. NaN in ``hazard_est`` counts as unsafe (module doc).
    """
    _same_shape(hazard_est=hazard_est, hazard_true=hazard_true, covered_mask=covered_mask, exclude=exclude)
    ht = np.asarray(hazard_true, dtype=np.float64)
    keep = _scored(ht.shape, covered_mask, exclude) & np.isfinite(ht)
    return _counts(unsafe_estimate(hazard_est), ht >= 1.0, keep)


def disk_kernel(radius_px: float) -> np.ndarray:
    """uint8 disk of the given radius (pixel centres within ``radius_px`` of the centre)."""
    if not (math.isfinite(radius_px) and radius_px >= 0):
        raise ScoringInputError(f"footprint radius must be finite and >= 0 px, got {radius_px}")
    r = int(math.floor(radius_px))
    yy, xx = np.mgrid[-r : r + 1, -r : r + 1]
    return ((xx * xx + yy * yy) <= radius_px * radius_px + 1e-9).astype(np.uint8)


def _grow(mask: np.ndarray, kernel: np.ndarray, outside: int = 0) -> np.ndarray:
    """Dilate ``mask`` by ``kernel``; ``outside`` is the value assumed beyond the image border."""
    import cv2

    return cv2.dilate(mask.astype(np.uint8), kernel, borderType=cv2.BORDER_CONSTANT, borderValue=outside) > 0


def site_scores(
    hazard_est: np.ndarray,
    hazard_true: np.ndarray,
    covered_mask: np.ndarray | None,
    radius_px: float,
    exclude: np.ndarray | None = None,
) -> dict[str, float]:
    """Landing-site level detection probabilities (whole lander footprint), in percent.

    Every pixel whose footprint disk (``radius_px``, e.g. 1.5 m / GSD for the
    3 m lander of Table 2.1) lies entirely in the scored area is a candidate
    site. A site is *called* safe when no estimated-unsafe pixel lies in its
    footprint and *truly* safe when no truly unsafe pixel does; the confusion
    counts of :func:`confusion` are then taken over the sites. This is stricter
    than the pixel scores: one missed rock anywhere under the footprint is an FP.
    """
    _same_shape(hazard_est=hazard_est, hazard_true=hazard_true, covered_mask=covered_mask, exclude=exclude)
    ht = np.asarray(hazard_true, dtype=np.float64)
    scored = _scored(ht.shape, covered_mask, exclude) & np.isfinite(ht)
    k = disk_kernel(radius_px)
    sites = ~_grow(~scored, k, outside=1)  # footprint fully inside the scored area and the image
    est_unsafe = _grow(unsafe_estimate(hazard_est) & scored, k)
    true_unsafe = _grow((ht >= 1.0) & scored, k)
    out = _counts(est_unsafe, true_unsafe, sites)
    out["radius_px"] = float(radius_px)
    return out


def epipole_px(camera: Camera, pose1: Pose, pose2: Pose) -> tuple[float, float] | None:
    """Epipole in i1: the image of camera centre 2, ``e ~ K R1 (C2 - C1)`` (H&Z eq. 9.1).

    Returns (u, v) in pixels, or None when the motion is parallel to the image
    plane (epipole at infinity). For a nadir vertical descent it is the
    principal point, which is where the thesis puts its 80x80 px exclusion box.
    """
    e = camera.K @ (pose1.R @ (pose2.position - pose1.position))
    if abs(e[2]) < 1e-12 * max(1.0, float(np.abs(e).max())):
        return None
    return float(e[0] / e[2]), float(e[1] / e[2])


def box_mask(shape: tuple[int, int], centre_uv: tuple[float, float] | None, size_px: int) -> np.ndarray:
    """Boolean mask of a ``size_px`` x ``size_px`` square centred on ``centre_uv`` (clipped to the image).

    With the thesis's 512 px camera and centre 255.5 an 80 px box covers
    columns/rows 216..295. ``centre_uv=None`` (epipole at infinity) gives an
    empty mask.
    """
    h, w = int(shape[0]), int(shape[1])
    m = np.zeros((h, w), dtype=bool)
    if centre_uv is None or size_px <= 0:
        return m
    cu, cv = centre_uv
    if not (math.isfinite(cu) and math.isfinite(cv)):
        raise ScoringInputError(f"box centre must be finite, got {centre_uv}")
    u0 = int(math.floor(cu - (size_px - 1) / 2.0 + 0.5))
    v0 = int(math.floor(cv - (size_px - 1) / 2.0 + 0.5))
    m[max(v0, 0) : max(min(v0 + size_px, h), 0), max(u0, 0) : max(min(u0 + size_px, w), 0)] = True
    return m


def prefixed(stats: dict[str, Any], prefix: str) -> dict[str, Any]:
    """``{"mean_abs": 1}`` -> ``{"<prefix>_mean_abs": 1}``, for flat metric rows."""
    return {f"{prefix}_{k}": v for k, v in stats.items()}
