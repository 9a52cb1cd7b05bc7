"""Scenes: a resolution-independent height function h(x, y) and albedo a(x, y).

A scene = fBm base relief (:mod:`ground_sim.fbm`) + lazily generated craters and
boulders (:mod:`ground_sim.features`) + features placed on request + an albedo
texture. It is described by a preset name (``ground_sim/presets/<name>.toml``) or a
TOML file, and a seed. Everything is a pure function of (parameters, seed, x, y, band
limit): any window, at any resolution, gives the same terrain.

TOML layout (all keys optional; defaults below)::

    [terrain]  rms_relief_m, hurst, max_wavelength_m, micro_rms_m, micro_scale_m, tilt_deg, tilt_azimuth_deg
    [craters]  coef, exponent, d_min_m, d_max_m, degradation, exclude_radius_m, exclude_d_min_m, profile
    [boulders] coef, exponent, d_min_m, d_max_m, rim_density_m2, exclude_radius_m, profile
    [boulder_fields] per_km2, radius_m, coef, exponent   (random fields; boulder sizes from [boulders])
    [albedo]   mean, sigma
    [[feature]] kind = "boulder"|"crater"|"boulder_field", x_m, y_m, diameter_m,
                height_m (boulder) | depth_ratio, degradation (crater) | coef (boulder_field, 0: the section's)
    [library]  metadata of a named scene (read by :mod:`ground_sim.library`, ignored here)
    [variant.<scenario>.<section>]  overrides applied when the scene is loaded for that scenario

``profile = [[r0, f0], [r1, f1], ...]`` multiplies the population's density by a piecewise
linear factor of the distance from the origin (the nominal landing site), see
:class:`ground_sim.features.RadialProfile`. A scene spec ``name:variant`` (e.g.
``thesis:approach``) names a variant explicitly.

Densities are bounded when a scene is loaded, before anything is drawn: no population (times its profile's
peak) may be denser than geometric saturation, ``N(>D) = 1.54 D^-2`` per m^2 (features packed side by side;
the Moon's equilibrium is ~5 % of it), rim boulders of ``d_min_m`` likewise, and boulder fields may overlap
any point at most 10 times on average.
"""

from __future__ import annotations

import math
import os
import tomllib
from dataclasses import dataclass, field, fields, replace
from itertools import pairwise
from pathlib import Path
from typing import Any

import numpy as np

from ground_sim.errors import SceneError
from ground_sim.fbm import FBm
from ground_sim.features import (
    Features,
    PowerLaw,
    RadialProfile,
    boulders_in,
    craters_in,
    field_boulders,
    random_fields,
)
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
    exclude_radius_m: float = 0.0  # keep random craters out of this radius around the origin ...
    exclude_d_min_m: float = 0.0  # ... if at least this wide (smaller ones follow the profile)
    profile: tuple[tuple[float, float], ...] = ()  # density factor vs distance from the origin


@dataclass(frozen=True)
class Boulders:
    coef: float = 3.0e-4  # VIPER default N(>D) = 3e-4 D^-2.482 per m^2
    exponent: float = 2.482
    d_min_m: float = 0.2
    d_max_m: float = 5.0
    rim_density_m2: float = 0.02  # boulders >= d_min per m^2 around fresh craters
    exclude_radius_m: float = 0.0
    profile: tuple[tuple[float, float], ...] = ()


@dataclass(frozen=True)
class BoulderFields:
    """Random boulder fields: disks with their own dense boulder population (sizes from [boulders])."""

    per_km2: float = 0.0
    radius_m: float = 30.0  # mean; each field's radius is uniform in 0.5-1.5 x this
    coef: float = 0.02
    exponent: float = 2.5


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
    coef: float = 0.0
    ranges: tuple[tuple[str, float, float], ...] = ()  # (key, lo, hi): drawn per scene seed

    def resolved(self, seed: int, index: int) -> Placed:
        """This feature with every ranged key drawn uniformly for ``seed`` (a hash: same seed, same value)."""
        if not self.ranges:
            return self
        from ground_sim.hashing import uniform

        vals: dict[str, Any] = {
            k: lo + float(uniform(seed, PLACED_STREAM, index, j)) * (hi - lo)
            for j, (k, lo, hi) in enumerate(self.ranges)
        }
        return replace(self, ranges=(), **vals)


PLACED_STREAM = 11
_RANGED = ("x_m", "y_m", "diameter_m", "height_m", "depth_ratio", "degradation", "coef")


_SECTIONS = {
    "terrain": Terrain,
    "craters": Craters,
    "boulders": Boulders,
    "boulder_fields": BoulderFields,
    "albedo": Albedo,
}
_KINDS = ("boulder", "crater", "boulder_field")


@dataclass(frozen=True)
class SceneParams:
    name: str = "custom"
    terrain: Terrain = field(default_factory=Terrain)
    craters: Craters = field(default_factory=Craters)
    boulders: Boulders = field(default_factory=Boulders)
    albedo: Albedo = field(default_factory=Albedo)
    features: tuple[Placed, ...] = ()
    boulder_fields: BoulderFields = field(default_factory=BoulderFields)
    variant: str = ""  # the scenario variant applied ("" = the base scene)

    @property
    def spec(self) -> str:
        """The spec that loads these parameters again: ``name`` or ``name:variant``."""
        return f"{self.name}:{self.variant}" if self.variant else self.name

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {"name": self.name, "variant": self.variant}
        for key in _SECTIONS:
            sec = getattr(self, key)
            out[key] = {f.name: _plain(getattr(sec, f.name)) for f in fields(sec)}
        out["feature"] = [{f.name: _plain(getattr(p, f.name)) for f in fields(p)} for p in self.features]
        return out


def _plain(v: Any) -> Any:
    return [list(k) for k in v] if isinstance(v, tuple) else v


def _profile(v: Any, where: str) -> tuple[tuple[float, float], ...]:
    ok = isinstance(v, list) and len(v) >= 1
    knots: list[tuple[float, float]] = []
    for item in v if ok else []:
        if not (isinstance(item, list) and len(item) == 2 and all(_is_num(x) for x in item)):
            ok = False
            break
        knots.append((float(item[0]), float(item[1])))
    if not ok or any(r < 0 or f < 0 for r, f in knots) or any(b[0] <= a[0] for a, b in pairwise(knots)):
        raise SceneError(f"{where}.profile: expected [[r_m, factor], ...] with r ascending and factors >= 0, got {v!r}")
    if max(f for _, f in knots) <= 0:
        raise SceneError(f"{where}.profile: at least one factor must be > 0")
    return tuple(knots)


def _is_num(v: Any) -> bool:
    return not isinstance(v, bool) and isinstance(v, (int, float)) and math.isfinite(v)


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
        if k == "profile":
            kw[k] = _profile(v, where)
            continue
        if not _is_num(v):
            raise SceneError(f"{where}.{k}: must be a finite number, got {v!r}")
        kw[k] = float(v)
    return cls(**kw)


def apply_variant(doc: dict[str, Any], variant: str | None, name: str = "custom") -> tuple[dict[str, Any], str]:
    """``doc`` with ``[variant.<variant>]`` merged over it (section by section; a variant's
    ``feature`` list replaces the base's), and the variant actually applied ("" if none)."""
    variants = doc.get("variant", {})
    if not isinstance(variants, dict) or not all(isinstance(v, dict) for v in variants.values()):
        raise SceneError(f"scene {name}: [variant.<scenario>] must hold tables")
    base = {k: v for k, v in doc.items() if k != "variant"}
    if not variant or variant not in variants:
        return base, ""
    out = dict(base)
    for key, val in variants[variant].items():
        if isinstance(val, dict) and isinstance(out.get(key), dict):
            out[key] = {**out[key], **val}
        else:
            out[key] = val
    return out, variant


def parse_scene(doc: dict[str, Any], name: str = "custom", variant: str | None = None) -> SceneParams:
    """Validate a scene document (parsed TOML) into :class:`SceneParams`, with ``variant`` applied if it has one."""
    doc, applied = apply_variant(doc, variant, name)
    if not isinstance(doc.get("library", {}), dict):
        raise SceneError(f"scene {name}: [library] must be a table")
    extra = set(doc) - set(_SECTIONS) - {"feature", "name", "library"}
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
        if not isinstance(fd, dict) or fd.get("kind") not in _KINDS:
            raise SceneError(f"scene {name} feature #{i}: kind must be one of {', '.join(_KINDS)}")
        body = {k: v for k, v in fd.items() if k != "kind"}
        for req in ("x_m", "y_m", "diameter_m"):
            if req not in body:
                raise SceneError(f"scene {name} feature #{i}: missing {req}")
        ranges = []
        for k, v in list(body.items()):
            if isinstance(v, list):
                if k not in _RANGED or len(v) != 2 or not all(_is_num(x) for x in v) or not v[0] <= v[1]:
                    raise SceneError(f"scene {name} feature #{i}.{k}: a range must be [lo, hi] with lo <= hi")
                ranges.append((k, float(v[0]), float(v[1])))
                body[k] = 0.5 * (v[0] + v[1])
        p = _section(Placed, {"kind": fd["kind"], **body}, f"scene {name} feature #{i}")
        feats.append(replace(p, ranges=tuple(ranges)))
    params = SceneParams(
        str(doc.get("name", name)),
        secs["terrain"],
        secs["craters"],
        secs["boulders"],
        secs["albedo"],
        tuple(feats),
        secs["boulder_fields"],
        applied,
    )
    _check(params)
    return params


# N(>D) = 1.54 D^-2 per m^2: craters packed rim to rim, "geometric saturation" (Gault 1970; Hartmann 1984). Lunar
# equilibrium is ~5 % of it (Trask's 0.079). A denser population draws what no surface holds, and with it as many
# features as memory lasts: craters.coef = 1e4 took 4.9 GB and ended in a traceback (QA of stop 71)
GEOMETRIC_SATURATION = 1.54


def _over_saturation(name: str, coef: float, exponent: float, d_min: float, d_max: float, peak: float) -> str | None:
    """Why ``N(>D) = peak * coef * D^-exponent`` on [d_min, d_max] is denser than geometric saturation anywhere, or
    None. ``N(>D) D^2`` is monotone in D for a power law, so one of the ends holds its largest value."""
    worst = max(peak * coef * d ** (2.0 - exponent) for d in (d_min, d_max))
    if worst <= GEOMETRIC_SATURATION:
        return None
    limit = min(GEOMETRIC_SATURATION * d ** (exponent - 2.0) for d in (d_min, d_max)) / peak
    return (
        f"{name} {coef:g} is {worst / GEOMETRIC_SATURATION:.3g}x denser than features packed side by side "
        f"(N(>D) = {GEOMETRIC_SATURATION} D^-2 per m^2, geometric saturation): at most {limit:.3g} "
        f"for exponent {exponent:g} on {d_min:g}-{d_max:g} m"
        + (f" and a profile peak of {peak:g}" if peak != 1 else "")
    )


def _check_density(p: SceneParams) -> None:
    """Refuse, before anything is drawn, populations no surface holds (and memory could not)."""
    c, b, bf = p.craters, p.boulders, p.boulder_fields
    peak_c = max((f for _, f in c.profile), default=1.0)
    peak_b = max((f for _, f in b.profile), default=1.0)
    why = [
        _over_saturation("craters.coef", c.coef, c.exponent, c.d_min_m, c.d_max_m, peak_c),
        _over_saturation("boulders.coef", b.coef, b.exponent, b.d_min_m, b.d_max_m, peak_b),
        _over_saturation("boulder_fields.coef", bf.coef, bf.exponent, b.d_min_m, b.d_max_m, 1.0),
    ]
    for i, f in enumerate(p.features):
        if f.kind == "boulder_field":
            hi = max([f.coef] + [v for k, _, v in f.ranges if k == "coef"])
            why.append(_over_saturation(f"feature #{i} coef", hi, bf.exponent, b.d_min_m, b.d_max_m, 1.0))
    if b.rim_density_m2 * b.d_min_m**2 > GEOMETRIC_SATURATION:  # rim boulders are at least d_min wide
        why.append(
            f"boulders.rim_density_m2 {b.rim_density_m2:g} packs boulders of at least {b.d_min_m:g} m denser than "
            f"side by side: at most {GEOMETRIC_SATURATION / b.d_min_m**2:.3g} per m^2"
        )
    cover = bf.per_km2 * 1e-6 * np.pi * bf.radius_m**2
    if cover > MAX_FIELD_COVER:  # each field holds a population of its own: fields over fields multiply it
        why.append(
            f"boulder_fields.per_km2 {bf.per_km2:g} of radius {bf.radius_m:g} m covers the ground {cover:.3g} "
            f"times over: at most {MAX_FIELD_COVER:g} (per_km2 <= "
            f"{MAX_FIELD_COVER / (1e-6 * np.pi * bf.radius_m**2):.3g})"
        )
    for w in why:
        if w is not None:
            raise SceneError(f"scene {p.name}: {w}")


MAX_FIELD_COVER = 10.0  # boulder fields over a point, on average (the boulder-field scene: 1.4)


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
        (
            p.boulder_fields.per_km2 >= 0 and p.boulder_fields.radius_m > 0 and p.boulder_fields.coef >= 0,
            "boulder_fields: per_km2 >= 0, radius_m > 0, coef >= 0",
        ),
        (p.boulder_fields.exponent > 0.5, "boulder_fields.exponent must be > 0.5"),
        (0 < a.mean < 1 and 0 <= a.sigma < a.mean, "albedo: need 0 < mean < 1 and 0 <= sigma < mean"),
    ]
    for ok, msg in checks:
        if not ok:
            raise SceneError(f"scene {p.name}: {msg}")
    _check_density(p)
    for i, f0 in enumerate(p.features):
        ends = [f0] + [replace(f0, **{k: v}) for k, lo, hi in f0.ranges for v in (lo, hi)]  # type: ignore[arg-type]
        for f in ends:  # a ranged key must be valid over its whole range
            if not 0 < f.diameter_m <= 2000:
                raise SceneError(f"scene {p.name} feature #{i}: diameter_m must be in (0, 2000]")
            if f.kind == "boulder" and not 0 < f.height_m <= f.diameter_m * 2:
                raise SceneError(f"scene {p.name} feature #{i}: boulder height_m must be in (0, 2*diameter]")
            if f.coef < 0 or not 0 <= f.degradation <= 1 or f.depth_ratio < 0:
                raise SceneError(
                    f"scene {p.name} feature #{i}: need coef >= 0, 0 <= degradation <= 1, depth_ratio >= 0"
                )


def preset_names() -> list[str]:
    return sorted(p.stem for p in PRESET_DIR.glob("*.toml"))


def split_scene_spec(spec: str | Path) -> tuple[str, str | None]:
    """(preset name or scene file, variant or None) of a scene spec: ``name``, ``name:variant``, a file ending in
    ``.toml`` or naming a directory (``./mine``, ``dir/mine.toml``), or ``file.toml:variant``.

    A spec is a file only when it says so: a file or directory in the working directory named after a preset
    (``render --scene mare --out mare``) made ``mare`` a missing scene file, and an empty file named ``mare`` gave
    the default scene's terrain under the name mare (QA of stop 73)."""
    text = str(spec)
    if ".toml:" in text:
        base, variant = text.rsplit(".toml:", 1)
        return base + ".toml", variant
    if text.endswith(".toml") or "/" in text or os.sep in text:
        return text, None
    name, sep, variant = text.partition(":")
    return name, (variant if sep else None)


def _is_file_spec(base: str) -> bool:
    return base.endswith(".toml") or "/" in base or os.sep in base


def scene_document(spec: str | Path) -> tuple[dict[str, Any], str, Path]:
    """(parsed TOML, name, path) of a preset name or a TOML file (:func:`split_scene_spec`); a spec's variant is
    left out here."""
    base, _ = split_scene_spec(spec)
    if _is_file_spec(base):
        path = Path(base)
        if not path.is_file():
            raise SceneError(f"scene file {path} does not exist")
    else:
        path = PRESET_DIR / f"{base}.toml"
        if not path.is_file():
            raise SceneError(
                f"unknown scene preset {base!r} (presets: {', '.join(preset_names())}; or give a .toml file)"
            )
    try:
        doc = tomllib.loads(path.read_text())
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise SceneError(f"scene file {path}: invalid TOML ({exc})") from None
    return doc, path.stem, path


def load_scene_params(spec: str | Path = "default", scenario: str | None = None) -> SceneParams:
    """Preset name (``ground_sim/presets/<name>.toml``), ``name:variant``, or path to a TOML file.

    ``scenario`` selects the scene's ``[variant.<scenario>]`` if it has one (an explicit
    ``:variant`` in the spec wins).
    """
    _, asked = split_scene_spec(spec)
    doc, name, _ = scene_document(spec)
    variant = scenario
    if asked is not None:
        variant = asked
        if variant not in doc.get("variant", {}):
            have = sorted(doc.get("variant", {}))
            raise SceneError(
                f"scene {name} has no variant {variant!r} "
                + (f"(it has {', '.join(have)})" if have else f"(it has none: give {name} alone)")
            )
    return parse_scene(doc, name, variant)


def load_scene(spec: str | Path | Scene = "default", seed: int = 0, scenario: str | None = None) -> Scene:
    """Load a scene preset or TOML file with a seed (and the scenario's variant, if the scene has one)."""
    if isinstance(spec, Scene):
        return spec
    return Scene(load_scene_params(spec, scenario), int(seed))


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
        c, b, bf = params.craters, params.boulders, params.boulder_fields
        self._crater_sfd = PowerLaw(c.coef, c.exponent, c.d_min_m, c.d_max_m)
        self._boulder_sfd = PowerLaw(b.coef, b.exponent, b.d_min_m, b.d_max_m)
        self._crater_profile = RadialProfile(c.profile) if c.profile else None
        self._boulder_profile = RadialProfile(b.profile) if b.profile else None
        self._field_sfd = PowerLaw(bf.coef, bf.exponent, b.d_min_m, b.d_max_m)
        self.placed = tuple(f.resolved(self.seed, i) for i, f in enumerate(params.features))
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
        cr = craters_in(
            self.seed, self._crater_sfd, bbox, 1.5 * max(min_size, 0.0), p.craters.degradation, self._crater_profile
        )
        if p.craters.exclude_radius_m > 0:
            cr = cr.select(
                (np.hypot(cr.x, cr.y) - cr.reach > p.craters.exclude_radius_m) | (cr.d < p.craters.exclude_d_min_m)
            )
        pc = [f for f in self.placed if f.kind == "crater"]
        placed_cr = Features(
            np.array([f.x_m for f in pc]),
            np.array([f.y_m for f in pc]),
            np.array([f.diameter_m for f in pc]),
            np.array([f.depth_ratio * f.diameter_m for f in pc]),
            np.array([f.degradation for f in pc]),
            "crater",
        )
        # placed craters shed rim boulders like random ones
        rim_src = Features.concat([cr, placed_cr], "crater") if pc else cr
        bl = boulders_in(
            self.seed,
            self._boulder_sfd,
            bbox,
            max(0.5 * min_size, 0.0),
            rim_src.select(rim_src.d >= 8.0),
            p.boulders.rim_density_m2,
            self._boulder_profile,
        )
        if p.boulders.exclude_radius_m > 0:
            bl = bl.select(np.hypot(bl.x, bl.y) - bl.reach > p.boulders.exclude_radius_m)
        bl = Features.concat([bl, self._field_boulders(bbox, max(0.5 * min_size, 0.0))], "boulder")
        pb = [f for f in self.placed if f.kind == "boulder"]
        if pc:
            cr = Features.concat([cr, placed_cr], "crater")
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

    def _field_boulders(self, bbox: tuple[float, float, float, float], d_min: float) -> Features:
        """Boulders of the random fields and of the placed ``boulder_field`` features."""
        p = self.params
        bf = p.boulder_fields
        parts = []
        if bf.per_km2 > 0 and bf.coef > 0:
            fx, fy, fr, keys = random_fields(self.seed, bf.per_km2, bf.radius_m, bbox)
            parts.append(field_boulders(self.seed, self._field_sfd, fx, fy, fr, keys, bbox, d_min))
        b = p.boulders
        for i, f in enumerate(self.placed):
            if f.kind != "boulder_field":
                continue
            sfd = PowerLaw(f.coef or bf.coef, bf.exponent, b.d_min_m, b.d_max_m)
            key = np.array([-1 - i], np.int64)  # placed fields: negative keys, random ones are >= 0
            one = np.array([f.x_m]), np.array([f.y_m]), np.array([0.5 * f.diameter_m])
            parts.append(field_boulders(self.seed, sfd, *one, key, bbox, d_min))
        return Features.concat(parts, "boulder")

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
        h, rel = self._height_raster(x0, y0, cell, nx, ny, min_wavelength, albedo=True)
        assert rel is not None
        mw = 2.0 * cell if min_wavelength is None else float(min_wavelength)
        xs = x0 + np.arange(nx) * cell
        ys = y0 + np.arange(ny) * cell
        a = self._albedo(None, None, mw, rel, self._albedo_fbm.raster(xs, ys, max(mw, 2.0)))
        return h, a

    def height_raster(
        self, x0: float, y0: float, cell: float, nx: int, ny: int, min_wavelength: float | None = None
    ) -> np.ndarray:
        """The height of :meth:`raster` alone (the same bytes, without the albedo's cost)."""
        return self._height_raster(x0, y0, cell, nx, ny, min_wavelength, albedo=False)[0]

    def _height_raster(
        self, x0: float, y0: float, cell: float, nx: int, ny: int, min_wavelength: float | None, *, albedo: bool
    ) -> tuple[np.ndarray, np.ndarray | None]:
        mw = 2.0 * cell if min_wavelength is None else float(min_wavelength)
        xs = x0 + np.arange(nx) * cell
        ys = y0 + np.arange(ny) * cell
        h = self._fbm.raster(xs, ys, mw) + self._plane[0] * xs[None, :] + self._plane[1] * ys[:, None]
        rel = np.zeros_like(h) if albedo else None
        cr, bl = self.features((xs[0], ys[0], xs[-1], ys[-1]), mw)
        for f in (cr, bl):
            stamp_raster(f, x0, y0, cell, nx, ny, h, rel)
        return h, rel
