"""Calibrated P(safe) and the FP-budget decision rule (issue 9 follow-up: CDI without trading FP).

**Why.** The Gaussian evidence model (:func:`flight_sw.evidence.classify`) computes
``P(safe) = Phi((G - g) / sigma_g) Phi((0.30 - r) / sigma_r)``: a likelihood with a *flat* prior
over the true slope. On ground_sim's tuning pairs that is badly calibrated: pixels whose
estimated slope is below 0.4x the limit but whose slope uncertainty exceeds the limit (most
pixels above ~300 m) are truly safe 99 % of the time, while the model gives them 0.5-0.8 and so
leaves them "unknown". Real terrain is mostly flat, hazards cluster (crater walls), and image
shading sees walls that the DEM smooths; the probability has to learn that.

**Model.** A binned logistic additive model (a logistic GAM with piecewise-constant shape
functions), fitted by ridge-regularised Newton/IRLS on ``ground_sim.seeds.TUNING_SEEDS`` only
(``bench/fit_psafe.py``; the seeds it used are stored with the weights)::

    logit P(safe | x) = b + w_nodem [no elevation]
                          + T_au[bin(a), bin(u)]                  (elevation known)
                          + sum_f w_f[bin(x_f)]                   (each other feature f)

with, per point (image pixel of i1, computed by :func:`features`):

* ``a = g / G`` the footprint slope over the limit, ``u = sigma_g / G`` its uncertainty
  (2-D table: the posterior of "slope < limit" depends on both jointly);
* ``a_pc`` the same ratio with the sun-ward part of the footprint gradient read from the
  shading (:mod:`flight_sw.photoclinometry`; trees only, NaN when the sun is not given: the
  trees are fitted with a quarter of the points' ``a_pc`` blanked, so they know that case);
* ``upsun`` the distance, in footprints, to the nearest dark pixel down-sun (``UPSUN_NONE`` if
  none within about a footprint): ground just sun-ward of a shadow is what casts it, a boulder or
  a rim (:func:`flight_sw.shadow.caster_distance`; trees only, NaN with ``a_pc`` when the sun is
  not given);
* ``rough = r / 0.30 m`` (roughness over its limit), ``rho`` the signed relative brightness
  (:mod:`flight_sw.shading`) and ``arho`` its local mean magnitude;
* context - the prior where the evidence at the point is weak: ``nbad`` / ``nbad_w`` the share
  of *confidently unsafe* points (``a - 2u > 1``) within ~3 footprints / 31 px, ``nwall`` /
  ``nwall_w`` the share of strong shading (``|rho| > 0.1``) there, ``amean`` the local mean
  slope ratio and ``nknown`` the share of points with an elevation; ``scale`` = log2 of the
  lander footprint in pixels (the same for the whole image: it lets the prior and the
  calibration differ between a 30 px and a 1 px footprint); ``gbad`` the share of confidently
  unsafe points over the whole image (a scene prior: a crater field is riskier everywhere,
  also where the evidence at the point looks clean). A point with no elevation
  therefore gets ``b + w_nodem + context`` - a calibrated prior from its surroundings, not
  "unknown".

Shape functions that physics says are monotone (``a`` within each ``u`` row, ``rough``,
``nbad``, ``nbad_w``) are projected onto non-increasing sequences (pool-adjacent-violators
weighted by bin counts) after the fit. Dark shadow stays a hard unsafe cue (it is a hazard by
definition, DESIGN.md).

**Decision (Neyman-Pearson style).** With calibrated ``p_i``, calling a set ``S`` safe has
expected undetected-hazard share ``E[FP] = sum_{i in S} (1 - p_i) / N`` (N covered points), and
expected true positives ``sum_{i in S} p_i``; for a budget ``B`` on the first the second is
maximised by taking points in decreasing ``p`` while ``sum (1 - p) <= B N``
(:func:`budget_rule`). The rule adapts per image: on easy ground it calls almost everything,
on a crater field it stops early. A floor ``p >= p_min`` is kept as well. ``B``, the floor
and a slope cap (:func:`flight_sw.evidence.classify_calibrated`) are chosen by
cross-validation over the tuning seeds, worst pair first (``bench/fit_psafe.py --cv``). The
rule is only as good as the calibration: on a scene where the DEM misses hazards the model is
confidently wrong and the budget does not bound that scene's FP (docs/benchmarks/pipeline.md).
"""

from __future__ import annotations

import ctypes
import functools
import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from .kernels import load_kernel

MODEL_PATH = Path(__file__).with_name("psafe_model.json")
# the models shipped, each fitted on one camera size (its ``info.image_px``): the one fitted on an image's size
# calls it (:func:`model_for_image`); on other sizes the calibration does not hold (docs/benchmarks/pipeline.md)
SHIPPED_MODELS = (
    MODEL_PATH,
    MODEL_PATH.with_name("psafe_model_256.json"),
    MODEL_PATH.with_name("psafe_model_128.json"),
)

WIDE_PX = 31  # the wide context window (i1 pixels)
UPSUN_NONE = 4.0  # upsun where no dark pixel lies down-sun within the caster search
WALL_RHO = 0.1  # |rho| above this counts as strong shading in the context features


def _bmean(x: np.ndarray, k: int) -> np.ndarray:
    return cv2.blur(np.asarray(x, np.float32), (k, k), borderType=cv2.BORDER_REPLICATE)


def features(
    grad: np.ndarray,
    grad_sigma: np.ndarray,
    rough: np.ndarray,
    rho: np.ndarray,
    cell_m: float,
    footprint_px: float,
    *,
    slope_limit_deg: float = 15.0,
    rough_limit_m: float = 0.30,
    grad_shading: np.ndarray | None = None,
    caster_px: np.ndarray | None = None,
    speck: np.ndarray | None = None,
) -> dict[str, np.ndarray]:
    """Per-pixel features of the model (module doc), float32 HxW each; NaN = not available.

    ``grad``/``grad_sigma`` in metres per cell of size ``cell_m``, ``rough`` in metres, ``rho``
    the relative brightness, ``footprint_px`` the lander footprint in i1 pixels. ``grad_shading``
    (optional, m per cell): the footprint gradient with its sun-ward part read from the shading
    (:mod:`flight_sw.photoclinometry`); it gives ``a_pc``, NaN when absent. ``caster_px`` (optional): the
    distance to the nearest dark pixel down-sun (:func:`flight_sw.shadow.caster_distance`, ``inf`` = none
    within its reach); it gives ``upsun`` in footprints, ``UPSUN_NONE`` where none, NaN when absent.
    ``speck`` (optional): the pixel-scale brightness range (:func:`flight_sw.shading.speck_contrast`) and
    ``speck_fp`` its footprint mean, NaN when absent.
    """
    G = math.tan(math.radians(slope_limit_deg)) * float(cell_m)
    a = (np.asarray(grad, np.float32) / np.float32(G)).astype(np.float32)
    u = (np.asarray(grad_sigma, np.float32) / np.float32(G)).astype(np.float32)
    known = np.isfinite(a) & np.isfinite(u)
    k = int(2 * round(1.5 * max(1.0, float(footprint_px))) + 1)  # ~3 footprints
    with np.errstate(invalid="ignore"):
        bad = (known & ((a - 2.0 * u) > 1.0)).astype(np.float32)
    r = np.asarray(rho, np.float32)
    wall = (np.abs(r) > WALL_RHO).astype(np.float32)
    kn = known.astype(np.float32)
    s = _bmean(np.where(known, np.minimum(a, 4.0), 0.0), k)
    c = _bmean(kn, k)
    with np.errstate(invalid="ignore", divide="ignore"):
        amean = np.where(c > 0.05, s / c, np.nan).astype(np.float32)
    a_pc = np.full(a.shape, np.nan, np.float32)
    if grad_shading is not None:
        a_pc = (np.asarray(grad_shading, np.float32) / np.float32(G)).astype(np.float32)
    upsun = np.full(a.shape, np.nan, np.float32)
    if caster_px is not None:
        cp = np.asarray(caster_px, np.float32)
        with np.errstate(invalid="ignore"):
            upsun = np.where(np.isinf(cp), np.float32(UPSUN_NONE), cp / np.float32(max(float(footprint_px), 1e-3)))
        upsun = upsun.astype(np.float32)
    sp = np.full(a.shape, np.nan, np.float32) if speck is None else np.asarray(speck, np.float32)
    n_fp = max(1, int(round(float(footprint_px)))) | 1
    return {
        "a": np.where(known, a, np.nan).astype(np.float32),
        "a_pc": a_pc,
        "upsun": upsun,
        "speck": sp,
        "speck_fp": sp if speck is None else _bmean(sp, n_fp),
        "u": np.where(known, u, np.nan).astype(np.float32),
        "rough": (np.asarray(rough, np.float32) / np.float32(rough_limit_m)).astype(np.float32),
        "rho": r,
        "arho": _bmean(np.abs(r), k),
        "nbad": _bmean(bad, k),
        "nbad_w": _bmean(bad, WIDE_PX),
        "nwall": _bmean(wall, k),
        "nwall_w": _bmean(wall, WIDE_PX),
        "amean": amean,
        "nknown": c,
        "scale": np.full(a.shape, math.log2(max(float(footprint_px), 1e-3)), np.float32),
        "gbad": np.full(a.shape, float(bad[known].mean()) if known.any() else np.nan, np.float32),
    }


def _fits_image(info: Mapping[str, Any], shape: tuple[int, ...]) -> bool:
    sizes = info.get("image_px")
    return not sizes or [int(shape[0]), int(shape[1])] in [[int(a), int(b)] for a, b in sizes]


@dataclass(frozen=True)
class PsafeModel:
    """Weights of the binned logistic model (module doc); ``fitted_on`` = the scene seeds used."""

    edges: Mapping[str, Sequence[float]]
    table_au: Sequence[Sequence[float]]  # (len(edges["a"]) + 1) x (len(edges["u"]) + 1)
    weights: Mapping[str, Sequence[float]]  # per additive feature: len(edges[f]) + 1
    w_nodem: float
    bias: float
    fitted_on: tuple[int, ...] = ()
    info: Mapping[str, Any] = field(default_factory=dict)

    def logit(self, feats: Mapping[str, np.ndarray], mask: np.ndarray | None = None) -> np.ndarray:
        """``logit P(safe)`` at the points of ``mask`` (all points if None), float32 1-D."""

        def take(name: str) -> np.ndarray:
            v = np.asarray(feats[name], np.float32)
            return v[mask] if mask is not None else v.ravel()

        a, u = take("a"), take("u")
        known = np.isfinite(a) & np.isfinite(u)
        z = np.full(a.shape, np.float32(self.bias), np.float32)
        T = np.asarray(self.table_au, np.float32)
        ia = np.digitize(np.where(known, a, 0.0), np.asarray(self.edges["a"]))
        iu = np.digitize(np.where(known, u, 0.0), np.asarray(self.edges["u"]))
        z += np.where(known, T[ia, iu], np.float32(self.w_nodem))
        for name in self.weights:
            x = take(name)
            w = np.asarray(self.weights[name], np.float32)
            ok = np.isfinite(x)
            i = np.digitize(np.where(ok, x, 0.0), np.asarray(self.edges[name]))
            z += np.where(ok, w[i], np.float32(0.0))
        return z

    def fits_image(self, shape: tuple[int, ...]) -> bool:
        """True when the model was fitted on images of this (rows, cols) size (``info["image_px"]``, a list of
        [rows, cols]); a model without the record is taken to fit any size."""
        return _fits_image(self.info, shape)

    def predict(self, feats: Mapping[str, np.ndarray], mask: np.ndarray | None = None) -> np.ndarray:
        """P(safe) (float32) at the points of ``mask`` (1-D), or over the whole array when ``mask`` is None."""
        z = self.logit(feats, mask)
        p = (1.0 / (1.0 + np.exp(-np.clip(z, -30.0, 30.0)))).astype(np.float32)
        if mask is None:
            return p.reshape(np.asarray(feats["a"]).shape)
        return p

    def to_json(self) -> dict[str, Any]:
        return {
            "format": "psafe-gam/1",
            "edges": {k: [float(x) for x in v] for k, v in self.edges.items()},
            "table_au": [[round(float(x), 6) for x in row] for row in self.table_au],
            "weights": {k: [round(float(x), 6) for x in v] for k, v in self.weights.items()},
            "w_nodem": round(float(self.w_nodem), 6),
            "bias": round(float(self.bias), 6),
            "fitted_on": [int(s) for s in self.fitted_on],
            "info": dict(self.info),
        }

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> PsafeModel:
        if d.get("format") != "psafe-gam/1":
            raise ValueError(f"not a psafe-gam/1 model: {d.get('format')!r}")
        edges = {k: tuple(float(x) for x in v) for k, v in d["edges"].items()}
        weights = {k: tuple(float(x) for x in v) for k, v in d["weights"].items()}
        table = tuple(tuple(float(x) for x in row) for row in d["table_au"])
        if len(table) != len(edges["a"]) + 1 or any(len(r) != len(edges["u"]) + 1 for r in table):
            raise ValueError("psafe model: table_au does not match the a/u bin edges")
        for k, w in weights.items():
            if len(w) != len(edges[k]) + 1:
                raise ValueError(f"psafe model: {k} has {len(w)} weights for {len(edges[k])} edges")
        return cls(
            edges,
            table,
            weights,
            float(d["w_nodem"]),
            float(d["bias"]),
            tuple(d.get("fitted_on", ())),
            d.get("info", {}),
        )


@functools.cache
def tree_kernel() -> ctypes.CDLL | None:
    """The compiled tree kernel (``flight_sw/_treesc.c``, built by the install), or None if it is not there."""
    lib = load_kernel("flight_sw._treesc")
    if lib is None:
        return None
    f = lib.psafe_trees
    f.restype = ctypes.c_int
    f.argtypes = [ctypes.c_void_p, ctypes.c_int64, ctypes.c_int, ctypes.c_int, *[ctypes.c_void_p] * 7, ctypes.c_float]
    f.argtypes = [*f.argtypes, ctypes.c_void_p]  # X n nf trees | roots depth feature missing threshold left value
    return lib


@dataclass(frozen=True)
class TreeModel:
    """Gradient-boosted trees for ``logit P(safe)`` over the same per-point features (format psafe-trees/1).

    ``logit P(safe | x) = base + sum_t value[leaf_t(x)]``: each tree sends a point left when
    ``x[feature] <= threshold`` and to the node's ``missing_left`` side when the feature is NaN (no
    elevation, no shading evidence), as the histogram gradient boosting of Ke et al. 2017 (LightGBM)
    does; fitted by ``bench/fit_psafe.py --kind trees`` (scikit-learn's
    ``HistGradientBoostingClassifier``, log-loss, monotone non-increasing in ``a``, ``rough``,
    ``nbad``, ``nbad_w``) on tuning seeds only. Why trees: the additive model cannot express that the
    same slope estimate means something else beside strong shading, on a crater field or at another
    footprint scale; on the tuning CV the trees call 9-15 more points in 100 safe at the same worst-pair
    FP (docs/benchmarks/pipeline.md). Node arrays are flat over all trees, children indices absolute.
    """

    features: tuple[str, ...]
    base: float
    roots: np.ndarray  # int32 (trees,)
    feature: np.ndarray  # int16 (nodes,), -1 at a leaf
    missing_left: np.ndarray  # uint8
    threshold: np.ndarray  # float32
    left: np.ndarray  # int32
    right: np.ndarray  # int32
    value: np.ndarray  # float32 (the leaf's logit contribution)
    fitted_on: tuple[int, ...] = ()
    info: Mapping[str, Any] = field(default_factory=dict)

    def _matrix(self, feats: Mapping[str, np.ndarray], mask: np.ndarray | None) -> np.ndarray:
        cols = []
        for name in self.features:
            v = np.asarray(feats[name], np.float32)
            cols.append(v[mask] if mask is not None else v.ravel())
        return np.ascontiguousarray(np.stack(cols, axis=1), dtype=np.float32)

    def logit(
        self, feats: Mapping[str, np.ndarray], mask: np.ndarray | None = None, use_kernel: bool = True
    ) -> np.ndarray:
        """``logit P(safe)`` at the points of ``mask`` (all points if None), float32 1-D; the compiled kernel
        when it is there, else the numpy reference (same arithmetic, ~11x slower)."""
        X = self._matrix(feats, mask)
        n = X.shape[0]
        out = np.empty(n, np.float32)
        lib = tree_kernel() if use_kernel else None
        if lib is not None:
            lay = self.kernel_layout
            arrs = (lay["roots"], lay["depth"], lay["feature"], lay["missing_left"], lay["threshold"], lay["left"])
            lib.psafe_trees(X.ctypes.data, n, X.shape[1], self.roots.size, *(a.ctypes.data for a in arrs),
                            lay["value"].ctypes.data, self.base, out.ctypes.data)  # fmt: skip
            return out
        z = np.full(n, np.float32(self.base), np.float32)
        rows = np.arange(n)
        for root in self.roots.tolist():
            k = np.full(n, root, np.int32)
            live = rows[self.feature[k] >= 0]
            while live.size:
                kk = k[live]
                v = X[live, self.feature[kk]]
                go_left = np.where(np.isnan(v), self.missing_left[kk] > 0, v <= self.threshold[kk])
                k[live] = np.where(go_left, self.left[kk], self.right[kk])
                live = live[self.feature[k[live]] >= 0]
            z += self.value[k]
        return z

    def predict(self, feats: Mapping[str, np.ndarray], mask: np.ndarray | None = None) -> np.ndarray:
        """P(safe) (float32) at the points of ``mask`` (1-D), or over the whole array when ``mask`` is None."""
        z = self.logit(feats, mask)
        p = (1.0 / (1.0 + np.exp(-np.clip(z, -30.0, 30.0)))).astype(np.float32)
        return p.reshape(np.asarray(feats[self.features[0]]).shape) if mask is None else p

    @functools.cached_property
    def kernel_layout(self) -> dict[str, np.ndarray]:
        """The compiled kernel's node arrays (``_treesc.c``): per tree breadth-first with adjacent children, leaves
        absorbing (feature 0, threshold +inf, missing side left, left child itself), and each tree's depth."""
        order: list[int] = []
        roots, depth = [], []
        for root in self.roots.tolist():
            base = len(order)
            roots.append(base)
            level, d = [root], 0
            while level:
                nxt: list[int] = []
                for k in level:
                    order.append(k)
                    if self.feature[k] >= 0:
                        nxt += [int(self.left[k]), int(self.right[k])]
                if nxt:
                    d += 1
                level = nxt
            if d > 255:  # the kernel counts a tree's steps in a byte
                raise ValueError(f"psafe trees: a tree {d} levels deep (at most 255)")
            depth.append(d)
        pos = np.empty(self.feature.size, np.int64)
        pos[np.asarray(order)] = np.arange(len(order))
        o = np.asarray(order)
        split = self.feature[o] >= 0
        return {
            "roots": np.asarray(roots, np.int32),
            "depth": np.asarray(depth, np.uint8),
            "feature": np.where(split, self.feature[o], 0).astype(np.int16),
            "missing_left": np.where(split, self.missing_left[o], 1).astype(np.uint8),
            "threshold": np.where(split, self.threshold[o], np.inf).astype(np.float32),
            "left": np.where(split, pos[self.left[o]], np.arange(o.size)).astype(np.int32),
            "value": self.value[o].astype(np.float32),
        }

    def fits_image(self, shape: tuple[int, ...]) -> bool:
        """As :meth:`PsafeModel.fits_image`."""
        return _fits_image(self.info, shape)

    def to_json(self) -> dict[str, Any]:
        return {
            "format": "psafe-trees/1",
            "features": list(self.features),
            "base": float(self.base),
            "roots": self.roots.tolist(),
            "feature": self.feature.tolist(),
            "missing_left": self.missing_left.tolist(),
            "threshold": [float(x) for x in self.threshold.tolist()],
            "left": self.left.tolist(),
            "right": self.right.tolist(),
            "value": self.value.tolist(),
            "fitted_on": [int(s) for s in self.fitted_on],
            "info": dict(self.info),
        }

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> TreeModel:
        if d.get("format") != "psafe-trees/1":
            raise ValueError(f"not a psafe-trees/1 model: {d.get('format')!r}")
        feats = tuple(str(f) for f in d["features"])
        feature = np.asarray(d["feature"], np.int16)
        n = feature.size
        arrs: dict[str, np.ndarray] = {
            "missing_left": np.asarray(d["missing_left"], np.uint8),
            "threshold": np.asarray(d["threshold"], np.float32),
            "left": np.asarray(d["left"], np.int32),
            "right": np.asarray(d["right"], np.int32),
            "value": np.asarray(d["value"], np.float32),
        }
        roots = np.asarray(d["roots"], np.int32)
        if any(a.shape != (n,) for a in arrs.values()) or roots.ndim != 1 or roots.size == 0:
            raise ValueError("psafe trees: node arrays differ in length, or no tree")
        split = feature >= 0
        kids = np.concatenate([arrs["left"][split], arrs["right"][split], roots])
        if (
            np.any(feature >= len(feats))
            or np.any(feature < -1)
            or np.any(kids < 0)
            or np.any(kids >= n)
            or np.any(arrs["left"][split] <= np.flatnonzero(split))
            or np.any(arrs["right"][split] <= np.flatnonzero(split))
        ):
            # children after their parent: the traversal always ends (no cycle reaches the C loop)
            raise ValueError("psafe trees: a node points outside the model, backwards, or at an unknown feature")
        return cls(
            features=feats,
            base=float(d["base"]),
            roots=roots,
            feature=feature,
            fitted_on=tuple(int(x) for x in d.get("fitted_on", ())),
            info=d.get("info", {}),
            **arrs,
        )


Model = PsafeModel | TreeModel


@functools.lru_cache(maxsize=4)
def load_model(path: str | None = None) -> Model:
    """The model shipped with the package (``flight_sw/psafe_model.json``) or one at ``path``
    (format ``psafe-gam/1`` or ``psafe-trees/1``)."""
    p = Path(path) if path else MODEL_PATH
    d = json.loads(p.read_text())
    return TreeModel.from_json(d) if d.get("format") == "psafe-trees/1" else PsafeModel.from_json(d)


def model_for_image(path: str | None, shape: tuple[int, ...]) -> tuple[Model, str] | None:
    """The P(safe) model that calls images of ``shape`` (rows, cols) and its file: the one at ``path`` when
    given, else the first of :data:`SHIPPED_MODELS` fitted on that size; ``None`` when that model (or every
    shipped one) was fitted on other sizes."""
    for f in [Path(path)] if path else [m for m in SHIPPED_MODELS if m.is_file()]:
        model = load_model(str(f))
        if model.fits_image(shape):
            return model, str(f)
    return None


def not_fitted_text(shape: tuple[int, ...]) -> str:
    """Why images of ``shape`` (rows, cols) get the Gaussian rule: no model was fitted on that size
    (:func:`model_for_image` gave None). `process` warns with it and `run` says it in its summary."""
    return f"calibrated P(safe) not fitted for {shape[1]}x{shape[0]} images"


CALL_KEYS = ("fp_budget", "psafe_min", "call_slope_max")


def model_call(model: Model) -> dict[str, float]:
    """The operating point a model records (``info["call"]``: any of :data:`CALL_KEYS`, chosen by the tuning CV
    of ``bench/fit_psafe.py`` for that model), ``{}`` when it records none. A value outside the pipeline's own
    bounds (``Params.validate``) is refused: a model file that would call everything safe must not load."""
    return checked_call(model.info.get("call") or {})


def checked_call(call: object) -> dict[str, float]:
    """An operating point (:data:`CALL_KEYS` to numbers) within the pipeline's own bounds, as floats;
    ``ValueError`` naming what is wrong (``bench/fit_psafe.py --call`` checks it before it fits)."""
    if not isinstance(call, Mapping) or set(call) - set(CALL_KEYS):
        raise ValueError(f"P(safe) model: info.call must hold only {CALL_KEYS}, got {call!r}")
    out = {k: float(v) for k, v in call.items()}
    if not (0 <= out.get("fp_budget", 0) <= 0.2 and 0 <= out.get("psafe_min", 0) < 1):
        raise ValueError(f"P(safe) model: info.call out of bounds: {out!r}")
    if not out.get("call_slope_max", 1.0) > 0:
        raise ValueError(f"P(safe) model: info.call call_slope_max must be positive: {out!r}")
    return out


def budget_rule(p: np.ndarray, budget: float, p_min: float = 0.0, n: int | None = None) -> np.ndarray:
    """Points called safe: in decreasing ``p`` while ``sum(1 - p) <= budget * n`` and ``p >= p_min``.

    ``p`` is 1-D (NaN = never called); ``n`` the count the budget is a share of (default: the
    finite points). Exact up to ties within 1e-4 of ``1 - p``, which are resolved conservatively
    (a bin of equal values is taken whole or not at all): O(N), no sort.
    """
    p = np.asarray(p, np.float32)
    ok = np.isfinite(p) & (p >= p_min)
    if n is None:
        n = int(np.isfinite(p).sum())
    out = np.zeros(p.shape, bool)
    if n == 0 or budget <= 0 or not ok.any():
        return out
    q = np.clip(1.0 - p[ok], 0.0, 1.0)
    nb = 10001
    b = np.minimum((q * (nb - 1)).astype(np.int64), nb - 1)
    cum = np.cumsum(np.bincount(b, weights=q, minlength=nb))
    last = int(np.searchsorted(cum, budget * n, side="right")) - 1  # the last whole bin within the budget
    if last < 0:
        return out
    out[np.flatnonzero(ok)[b <= last]] = True
    return out
