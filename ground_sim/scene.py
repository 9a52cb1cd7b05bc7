"""Scenes: a resolution-independent height function h(x, y) and albedo a(x, y).

A scene = fBm base relief (:mod:`ground_sim.fbm`) + lazily generated craters and
boulders (:mod:`ground_sim.features`) + features placed on request + an albedo
texture. It is described by a preset name (``ground_sim/presets/<name>.toml``) or a
TOML file, and a seed. Everything is a pure function of (parameters, seed, x, y, band
limit): any window, at any resolution, gives the same terrain.

TOML layout (all keys optional; defaults below)::

    [terrain]  rms_relief_m, hurst, max_wavelength_m, micro_rms_m, micro_scale_m, tilt_deg, tilt_azimuth_deg
    [craters]  coef, exponent, d_min_m, d_max_m, degradation, exclude_radius_m
    [boulders] coef, exponent, d_min_m, d_max_m, rim_density_m2, exclude_radius_m
    [albedo]   mean, sigma
    [[feature]] kind = "boulder"|"crater", x_m, y_m, diameter_m, height_m (boulder) | depth_ratio, degradation (crater)
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np

from ground_sim.errors import SceneError
from ground_sim.fbm import FBm
from ground_sim.features import Features, PowerLaw, boulders_in, craters_in
from ground_sim.stamp import stamp_points, stamp_raster

PRESET_DIR = Path(__file__).with_name("presets")
FINEST_WAVELENGTH_M = 0.02


@dataclass(frozen=True)
class Terrain:
    rms_relief_m: float = 6.0
    hurst: float = 0.76
    max_wavelength_m: float = 2048.0
    micro_rms_m: float = 0.03
    micro_scale_m: float = 4.0
    tilt_deg: float = 0.0
    tilt_azimuth_deg: float = 0.0


@dataclass(frozen=True)
class Craters:
    coef: float = 0.079  # Trask equilibrium N(>D) = 0.079 D^-2 per m^2
    exponent: float = 2.0
    d_min_m: float = 1.0
    d_max_m: float = 400.0
    degradation: float = 0.5
    exclude_radius_m: float = 0.0  # keep random craters out of this radius around the origin


@dataclass(frozen=True)
class Boulders:
    coef: float = 3.0e-4  # VIPER default N(>D) = 3e-4 D^-2.482 per m^2
    exponent: float = 2.482
    d_min_m: float = 0.2
    d_max_m: float = 5.0
    rim_density_m2: float = 0.02  # boulders >= d_min per m^2 around fresh craters
    exclude_radius_m: float = 0.0


@dataclass(frozen=True)
class Albedo:
    mean: float = 0.12
    sigma: float = 0.03


@dataclass(frozen=True)
class Placed:
    kind: str
    x_m: float
    y_m: float
    diameter_m: float
    height_m: float = 0.0
    depth_ratio: float = 0.2
    degradation: float = 0.0


_SECTIONS = {"terrain": Terrain, "craters": Craters, "boulders": Boulders, "albedo": Albedo}


@dataclass(frozen=True)
class SceneParams:
    name: str = "custom"
    terrain: Terrain = field(default_factory=Terrain)
    craters: Craters = field(default_factory=Craters)
    boulders: Boulders = field(default_factory=Boulders)
    albedo: Albedo = field(default_factory=Albedo)
    features: tuple[Placed, ...] = ()

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {"name": self.name}
        for key in _SECTIONS:
            sec = getattr(self, key)
            out[key] = {f.name: getattr(sec, f.name) for f in fields(sec)}
        out["feature"] = [{f.name: getattr(p, f.name) for f in fields(p)} for p in self.features]
        return out


def _section(cls, doc: dict, where: str):
    if not isinstance(doc, dict):
        raise SceneError(f"{where}: must be a table")
    known = {f.name: f for f in fields(cls)}
    kw: dict[str, Any] = {}
    for k, v in doc.items():
        if k not in known:
            raise SceneError(f"{where}: unknown key {k!r} (known: {', '.join(known)})")
        if k == "kind":
            kw[k] = str(v)
            continue
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise SceneError(f"{where}.{k}: must be a finite number, got {v!r}")
        kw[k] = float(v)
    return cls(**kw)


def parse_scene(doc: dict[str, Any], name: str = "custom") -> SceneParams:
    """Validate a scene document (parsed TOML) into :class:`SceneParams`."""
    extra = set(doc) - set(_SECTIONS) - {"feature", "name"}
    if extra:
        raise SceneError(
            f"scene {name}: unknown section(s) {sorted(extra)}; expected {sorted(_SECTIONS) + ['feature']}"
        )
    secs = {k: _section(cls, doc.get(k, {}), f"scene {name} [{k}]") for k, cls in _SECTIONS.items()}
    feats = []
    raw = doc.get("feature", [])
    if not isinstance(raw, list):
        raise SceneError(f"scene {name}: 'feature' must be an array of tables ([[feature]])")
    for i, fd in enumerate(raw):
        if not isinstance(fd, dict) or fd.get("kind") not in ("boulder", "crater"):
            raise SceneError(f"scene {name} feature #{i}: kind must be 'boulder' or 'crater'")
        body = {k: v for k, v in fd.items() if k != "kind"}
        for req in ("x_m", "y_m", "diameter_m"):
            if req not in body:
                raise SceneError(f"scene {name} feature #{i}: missing {req}")
        p = _section(Placed, {"kind": fd["kind"], **body}, f"scene {name} feature #{i}")
        feats.append(Placed(fd["kind"], p.x_m, p.y_m, p.diameter_m, p.height_m, p.depth_ratio, p.degradation))
    params = SceneParams(
        str(doc.get("name", name)), secs["terrain"], secs["craters"], secs["boulders"], secs["albedo"], tuple(feats)
    )
    _check(params)
    return params


def _check(p: SceneParams) -> None:
    t, c, b, a = p.terrain, p.craters, p.boulders, p.albedo
    checks = [
        (t.rms_relief_m >= 0, "terrain.rms_relief_m must be >= 0"),
        (0.0 < t.hurst <= 1.0, "terrain.hurst must be in (0, 1]"),
        (t.max_wavelength_m > 1.0, "terrain.max_wavelength_m must be > 1 m"),
        (t.micro_rms_m >= 0 and t.micro_scale_m > 0, "terrain.micro_rms_m >= 0 and micro_scale_m > 0"),
        (abs(t.tilt_deg) < 45, "terrain.tilt_deg must be within +-45"),
        (c.coef >= 0 and c.exponent > 0.5, "craters.coef >= 0 and craters.exponent > 0.5"),
        (0 < c.d_min_m < c.d_max_m <= 5000, "craters: need 0 < d_min_m < d_max_m <= 5000"),
        (0 < c.degradation < 1, "craters.degradation must be in (0, 1)"),
        (b.coef >= 0 and b.exponent > 0.5, "boulders.coef >= 0 and boulders.exponent > 0.5"),
        (0 < b.d_min_m < b.d_max_m <= 50, "boulders: need 0 < d_min_m < d_max_m <= 50"),
        (b.rim_density_m2 >= 0, "boulders.rim_density_m2 must be >= 0"),
        (0 < a.mean < 1 and 0 <= a.sigma < a.mean, "albedo: need 0 < mean < 1 and 0 <= sigma < mean"),
    ]
    for ok, msg in checks:
        if not ok:
            raise SceneError(f"scene {p.name}: {msg}")
    for i, f in enumerate(p.features):
        if not 0 < f.diameter_m <= 2000:
            raise SceneError(f"scene {p.name} feature #{i}: diameter_m must be in (0, 2000]")
        if f.kind == "boulder" and not 0 < f.height_m <= f.diameter_m * 2:
            raise SceneError(f"scene {p.name} feature #{i}: boulder height_m must be in (0, 2*diameter]")


def load_scene_params(spec: str | Path = "default") -> SceneParams:
    """Preset name (``ground_sim/presets/<name>.toml``) or path to a TOML file."""
    path = Path(spec)
    if path.suffix != ".toml" and not path.exists():
        path = PRESET_DIR / f"{spec}.toml"
        if not path.is_file():
            names = sorted(p.stem for p in PRESET_DIR.glob("*.toml"))
            raise SceneError(f"unknown scene preset {spec!r} (presets: {', '.join(names)}; or give a .toml file)")
    if not path.is_file():
        raise SceneError(f"scene file {path} does not exist")
    try:
        doc = tomllib.loads(path.read_text())
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise SceneError(f"scene file {path}: invalid TOML ({exc})") from None
    return parse_scene(doc, path.stem)


def load_scene(spec: str | Path = "default", seed: int = 0) -> Scene:
    """Load a scene preset or TOML file with a seed."""
    if isinstance(spec, Scene):
        return spec
    return Scene(load_scene_params(spec), int(seed))


class Scene:
    """Height and albedo of a procedural lunar scene (world frame, metres, Z up)."""

    def __init__(self, params: SceneParams, seed: int = 0) -> None:
        self.params = params
        self.seed = int(seed)
        t = params.terrain
        self._fbm = FBm(
            self.seed,
            t.rms_relief_m,
            t.hurst,
            t.max_wavelength_m,
            n_octaves=int(np.ceil(np.log2(t.max_wavelength_m / FINEST_WAVELENGTH_M))) + 1,
            micro_rms_m=t.micro_rms_m,
            micro_scale_m=t.micro_scale_m,
        )
        self._albedo_fbm = FBm(self.seed + 7919, 1.0, 0.5, 512.0, n_octaves=5)
        c, b = params.craters, params.boulders
        self._crater_sfd = PowerLaw(c.coef, c.exponent, c.d_min_m, c.d_max_m)
        self._boulder_sfd = PowerLaw(b.coef, b.exponent, b.d_min_m, b.d_max_m)
        tilt = math.radians(t.tilt_deg)
        az = math.radians(t.tilt_azimuth_deg)
        self._plane = (math.tan(tilt) * math.sin(az), math.tan(tilt) * math.cos(az))

    def __repr__(self) -> str:
        return f"Scene({self.params.name!r}, seed={self.seed})"

    # -- features -----------------------------------------------------------
    def features(self, bbox: tuple[float, float, float, float], min_size: float = 0.0) -> tuple[Features, Features]:
        """(craters, boulders) with diameter >= ``min_size`` that influence ``bbox`` = (x0, y0, x1, y1)."""
        p = self.params
        # craters narrower than ~1.5 band-limit wavelengths are sub-pixel: dropped
        cr = craters_in(self.seed, self._crater_sfd, bbox, 1.5 * max(min_size, 0.0), p.craters.degradation)
        if p.craters.exclude_radius_m > 0:
            cr = cr.select(np.hypot(cr.x, cr.y) - cr.reach > p.craters.exclude_radius_m)
        bl = boulders_in(
            self.seed,
            self._boulder_sfd,
            bbox,
            max(0.5 * min_size, 0.0),
            cr.select(cr.d >= 8.0),
            p.boulders.rim_density_m2,
        )
        if p.boulders.exclude_radius_m > 0:
            bl = bl.select(np.hypot(bl.x, bl.y) - bl.reach > p.boulders.exclude_radius_m)
        pc = [f for f in p.features if f.kind == "crater"]
        pb = [f for f in p.features if f.kind == "boulder"]
        if pc:
            cr = Features.concat(
                [
                    cr,
                    Features(
                        np.array([f.x_m for f in pc]),
                        np.array([f.y_m for f in pc]),
                        np.array([f.diameter_m for f in pc]),
                        np.array([f.depth_ratio * f.diameter_m for f in pc]),
                        np.array([f.degradation for f in pc]),
                        "crater",
                    ),
                ],
                "crater",
            )
        if pb:
            bl = Features.concat(
                [
                    bl,
                    Features(
                        np.array([f.x_m for f in pb]),
                        np.array([f.y_m for f in pb]),
                        np.array([f.diameter_m for f in pb]),
                        np.array([f.height_m for f in pb]),
                        np.zeros(len(pb)),
                        "boulder",
                    ),
                ],
                "boulder",
            )
        return cr, bl

    # -- evaluation ----------------------------------------------------------
    def _base(self, x, y, mw):
        return self._fbm.at(x, y, mw) + self._plane[0] * x + self._plane[1] * y

    def height_albedo(
        self, x: np.ndarray, y: np.ndarray, min_wavelength: float | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Height (world Z) and albedo at scattered points, features >= ``min_wavelength``."""
        x, y = np.broadcast_arrays(np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64))
        if not (np.all(np.isfinite(x)) and np.all(np.isfinite(y))):
            raise SceneError("height: x and y must be finite")
        mw = FINEST_WAVELENGTH_M if min_wavelength is None else float(min_wavelength)
        shape = x.shape
        xf, yf = x.ravel(), y.ravel()
        h = self._base(xf, yf, mw)
        rel = np.zeros_like(h)
        if xf.size:
            cr, bl = self.features((xf.min(), yf.min(), xf.max(), yf.max()), mw)
            for f in (cr, bl):
                dh, da = stamp_points(f, xf, yf)
                h += dh
                rel += da
        a = self._albedo(xf, yf, mw, rel, self._albedo_fbm.at(xf, yf, max(mw, 2.0)))
        return h.reshape(shape), a.reshape(shape)

    def height(self, x: np.ndarray, y: np.ndarray, min_wavelength: float | None = None) -> np.ndarray:
        """World Z (float64, shape of x/y); band-limited to ``min_wavelength`` if given."""
        return self.height_albedo(x, y, min_wavelength)[0]

    def albedo(self, x: np.ndarray, y: np.ndarray, min_wavelength: float | None = None) -> np.ndarray:
        """Normal albedo (lunar-Lambert A) at the points."""
        return self.height_albedo(x, y, min_wavelength)[1]

    def _albedo(self, x, y, mw, rel, noise):
        a = self.params.albedo
        return np.clip(a.mean * (1.0 + rel) + a.sigma * noise, 0.02, 0.6)

    def raster(
        self, x0: float, y0: float, cell: float, nx: int, ny: int, min_wavelength: float | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """(height, albedo) on the grid x = x0 + j*cell, y = y0 + i*cell (row i, column j).

        Identical (to rounding) to :meth:`height_albedo` at the grid points; the default
        band limit is two cells (Nyquist) so the raster holds no aliased detail.
        """
        mw = 2.0 * cell if min_wavelength is None else float(min_wavelength)
        xs = x0 + np.arange(nx) * cell
        ys = y0 + np.arange(ny) * cell
        h = self._fbm.raster(xs, ys, mw) + self._plane[0] * xs[None, :] + self._plane[1] * ys[:, None]
        rel = np.zeros_like(h)
        cr, bl = self.features((xs[0], ys[0], xs[-1], ys[-1]), mw)
        for f in (cr, bl):
            stamp_raster(f, x0, y0, cell, nx, ny, h, rel)
        a = self._albedo(None, None, mw, rel, self._albedo_fbm.raster(xs, ys, max(mw, 2.0)))
        return h, a
