"""The scene library: named scenes, their sun, their hazard share and the band it must stay in.

A library scene is a preset (``ground_sim/presets/<name>.toml``) with a ``[library]`` table::

    [library]
    description = "..."
    order = 3                              # listing order
    sun_azimuth_deg = [0.0, 360.0]         # optional: the sun is a scene property, drawn per seed
    sun_elevation_deg = [2.0, 5.0]         #   (absent: the scenario's default sun, DEFAULT_SUN)
    band_pct = [20.0, 60.0]                # hazards in scene: median over seeds at every table altitude
    [library.bands]                        # or one band per scenario
    vertical = [20.0, 45.0]
    [library.targets.vertical]             # or per-altitude targets (the thesis scene, Tables 6.1/6.8)
    altitudes_m = [...]
    hazards_pct = [...]
    tolerance_rel = 0.25                   # band: target x (1 -+ rel) -+ tolerance_abs points
    tolerance_abs = 0.0

*Hazards in scene* is the thesis's Table 6.1/6.8 quantity: the share of frame-0
pixels that see ground also seen by the pair's last frame (the area a DEM can be
made of) and that are unsafe by the ground-truth rules (DESIGN.md: slope >= 15 deg
or roughness >= 0.30 m over the 3 m footprint, or not directly lit). It is
measured from the renderer's own truth (:func:`ground_sim.render.truth_at`: same
raster, same rules, no image) on every second pixel of the covered box, and
stored with a digest of the scene's parameters in ``presets/hazard_shares.json``
(``hazard-hil scenes --measure`` regenerates it).
"""

from __future__ import annotations

import hashlib
import json
import math
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ground_sim.errors import SceneError
from ground_sim.geometry import ground_footprint, project
from ground_sim.hashing import uniform
from ground_sim.scene import PRESET_DIR, Scene, load_scene, preset_names, scene_document
from ground_sim.seeds import describe_seeds
from protocol.pairdir import Camera, Pose, Sun

DEFAULT_SUN = {"vertical": Sun(135.0, 25.0), "approach": Sun(120.0, 25.0)}
FALLBACK_SUN = Sun(135.0, 25.0)
SHARES_PATH = PRESET_DIR / "hazard_shares.json"
SHARES_FORMAT = "hazard-hil-scene-shares/1"
SUN_STREAM = 0x5A11
SCENARIOS = ("vertical", "approach")
MEASURE_STRIDE = 2


@dataclass(frozen=True)
class Target:
    """Per-altitude hazard-share targets (%) and their relative tolerance."""

    altitudes_m: tuple[int, ...]
    hazards_pct: tuple[float, ...]
    tolerance_rel: float
    tolerance_abs: float = 0.0  # percentage points on top of the relative tolerance

    def band(self, altitude_m: int) -> tuple[float, float]:
        v = self.hazards_pct[self.altitudes_m.index(int(altitude_m))]
        return max(0.0, v * (1 - self.tolerance_rel) - self.tolerance_abs), min(
            100.0, v * (1 + self.tolerance_rel) + self.tolerance_abs
        )


@dataclass(frozen=True)
class Entry:
    """A library scene's metadata (its terrain is :func:`ground_sim.scene.load_scene_params`)."""

    name: str
    description: str
    order: int
    sun_azimuth_deg: tuple[float, float] | None
    sun_elevation_deg: tuple[float, float] | None
    band_pct: tuple[float, float] | None
    targets: dict[str, Target] = field(default_factory=dict)
    path: Path = PRESET_DIR
    bands: dict[str, tuple[float, float]] = field(default_factory=dict)

    @property
    def sun_varies(self) -> bool:
        return self.sun_elevation_deg is not None

    def band(self, scenario: str, altitude_m: int) -> tuple[float, float] | None:
        """The documented hazard-share band (%) at a table altitude, or None."""
        t = self.targets.get(scenario)
        if t is not None:  # a table altitude the targets do not list has no band (was a ValueError)
            return t.band(altitude_m) if int(altitude_m) in t.altitudes_m else None
        return self.bands.get(scenario, self.band_pct)

    def sun(self, scenario: str, seed: int) -> Sun:
        """The sun of this scene for ``seed``: drawn from the ranges (a hash of the seed), else the scenario's."""
        if self.sun_elevation_deg is None:
            return DEFAULT_SUN.get(scenario, FALLBACK_SUN)
        az0, az1 = self.sun_azimuth_deg or (135.0, 135.0)
        el0, el1 = self.sun_elevation_deg
        u = uniform(int(seed), SUN_STREAM, zlib.crc32(self.name.encode()), np.array([0, 1]))
        return Sun(float(az0 + u[0] * (az1 - az0)) % 360.0, float(el0 + u[1] * (el1 - el0)))


def _pair(v: Any, where: str) -> tuple[float, float] | None:
    if v is None:
        return None
    if not (isinstance(v, list) and len(v) == 2 and all(isinstance(x, (int, float)) for x in v) and v[0] <= v[1]):
        raise SceneError(f"{where}: expected [lo, hi], got {v!r}")
    return float(v[0]), float(v[1])


def parse_entry(doc: dict[str, Any], name: str, path: Path) -> Entry | None:
    lib = doc.get("library")
    if lib is None:
        return None
    where = f"scene {name} [library]"
    targets = {}
    for scen, t in lib.get("targets", {}).items():
        try:
            alts = tuple(int(a) for a in t["altitudes_m"])
            pct = tuple(float(x) for x in t["hazards_pct"])
            tol = float(t.get("tolerance_rel", 0.25))
            tol_abs = float(t.get("tolerance_abs", 0.0))
        except (KeyError, TypeError, ValueError) as exc:
            raise SceneError(f"{where}.targets.{scen}: need altitudes_m, hazards_pct ({exc})") from None
        if len(alts) != len(pct) or not 0 < tol < 1 or tol_abs < 0:
            raise SceneError(f"{where}.targets.{scen}: altitudes and values must pair up, 0 < tolerance_rel < 1")
        targets[str(scen)] = Target(alts, pct, tol, tol_abs)
    bands = {str(k): _pair(v, f"{where}.bands.{k}") for k, v in lib.get("bands", {}).items()}
    el = _pair(lib.get("sun_elevation_deg"), f"{where}.sun_elevation_deg")
    if el is not None and not 0 < el[0] <= el[1] <= 90:
        raise SceneError(f"{where}.sun_elevation_deg must lie in (0, 90]")
    return Entry(
        name,
        str(lib.get("description", "")),
        int(lib.get("order", 99)),
        _pair(lib.get("sun_azimuth_deg"), f"{where}.sun_azimuth_deg"),
        el,
        _pair(lib.get("band_pct"), f"{where}.band_pct"),
        targets,
        path,
        {k: v for k, v in bands.items() if v is not None},
    )


def entries() -> list[Entry]:
    """Every library scene, in listing order."""
    out = []
    for name in preset_names():
        doc, stem, path = scene_document(name)
        e = parse_entry(doc, stem, path)
        if e is not None:
            out.append(e)
    return sorted(out, key=lambda e: (e.order, e.name))


def entry(spec: str | Scene | None) -> Entry | None:
    """The library entry of a scene spec (``thesis``, ``thesis:approach``, a Scene), or None if not a library scene."""
    if spec is None:
        return None
    name = spec.params.name if isinstance(spec, Scene) else str(spec).split(":", 1)[0]
    if name not in preset_names():
        return None
    doc, stem, path = scene_document(name)
    return parse_entry(doc, stem, path)


def scene_sun(spec: str | Scene | None, scenario: str, seed: int) -> Sun:
    """The sun a scene is rendered under: the library scene's own (per seed) or the scenario's default."""
    e = entry(spec)
    if e is not None:
        return e.sun(scenario, seed)
    return DEFAULT_SUN.get(scenario, FALLBACK_SUN)


DOC_ONLY = ("description", "order", "band_pct", "bands", "targets")  # [library] keys that do not change the scene


def params_digest(name: str) -> str:
    """sha256 of what makes a preset's hazard share: its parsed TOML (comments, layout and the
    [library] documentation keys - description, bands, targets - do not count; the sun does)."""
    doc, _, _ = scene_document(name)
    doc = {**doc, "library": {k: v for k, v in doc.get("library", {}).items() if k not in DOC_ONLY}}
    return hashlib.sha256(json.dumps(doc, sort_keys=True).encode()).hexdigest()[:16]


# --------------------------------------------------------------------------- hazard share
def covered(camera: Camera, other: Pose, world_xyz: np.ndarray) -> np.ndarray:
    """Which true ground points (N x 3) the ``other`` frame sees inside its image (no occlusion test)."""
    u, v, z = project(camera, other, world_xyz)
    return (z > 0) & (u >= -0.5) & (u <= camera.width - 0.5) & (v >= -0.5) & (v <= camera.height - 0.5)


def share_pct(hazard: np.ndarray, cov: np.ndarray) -> float:
    """Hazards in scene (%): unsafe (hazard >= 1) share of the covered pixels."""
    n = int(np.count_nonzero(cov))
    return 100.0 * float(np.count_nonzero(np.asarray(hazard)[cov] >= 1.0)) / n if n else math.nan


def covered_box(camera: Camera, upper: Pose, lower: Pose, relief_m: float = 80.0) -> tuple[int, int, int, int]:
    """Pixel box (u0, v0, u1, v1 exclusive) of frame 0 holding everything the lower frame can see."""
    pts = []
    for z in (-relief_m, relief_m):
        F = ground_footprint(camera, lower, z)
        u, v, _ = project(camera, upper, np.c_[F, np.full(4, z)])
        pts.append(np.c_[u, v])
    P = np.concatenate(pts)
    u0, v0 = (int(max(0, math.floor(x) - 4)) for x in P.min(axis=0))
    u1 = int(min(camera.width, math.ceil(P[:, 0].max()) + 5))
    v1 = int(min(camera.height, math.ceil(P[:, 1].max()) + 5))
    return u0, v0, max(u1, u0 + 1), max(v1, v0 + 1)


def pair_share(
    scene: Scene, camera: Camera, upper: Pose, lower: Pose, sun: Sun, *, stride: int = MEASURE_STRIDE
) -> float:
    """Hazards in scene (%) of a pair, from truth at every ``stride``-th pixel of the covered box."""
    from ground_sim.render import truth_at

    u0, v0, u1, v1 = covered_box(camera, upper, lower)
    vv, uu = np.mgrid[v0:v1:stride, u0:u1:stride]
    tr = truth_at(scene, camera, upper, sun, uu, vv)
    X = np.c_[tr["world_xy"], tr["elevation"]]
    return share_pct(tr["hazard"], covered(camera, lower, X))


def measure_one(spec: str, scenario: str, seed: int, altitude_m: int) -> float:
    """Hazards in scene (%) of library scene ``spec`` on one table pair of a scenario (picklable for pools)."""
    from ground_sim.trajectory import load_trajectory

    specs = {int(round(s.altitude_m)): s for s in load_trajectory(scenario)}
    ps = specs[int(altitude_m)]
    sc = load_scene(spec, seed, scenario)
    return pair_share(sc, ps.camera, ps.poses[0], ps.poses[-1], scene_sun(spec, scenario, seed))


def _measure_jobs(jobs: list[tuple[str, str, int, int]], workers: int | None, progress: bool) -> list[float]:
    """``measure_one`` over ``jobs`` in order, in a pool, with a progress bar on stderr (a full table takes
    about 10 min)."""
    from ground_sim.parallel import pool_map
    from reports.progress import Progress

    bar = Progress(len(jobs), desc="measure", enabled=progress)

    def done(i: int) -> None:
        name, scenario, seed, alt = jobs[i]
        bar.update(label=f"{name} {scenario} {alt} m seed {seed}")

    return pool_map(measure_one, jobs, workers, on_done=done)


def measure(
    names: list[str],
    seeds: list[int],
    *,
    scenarios: tuple[str, ...] = SCENARIOS,
    workers: int | None = None,
    progress: bool = False,
) -> dict[str, Any]:
    """Hazard shares of library scenes on every table pair, per seed: the ``hazard_shares.json`` document.

    ``progress`` draws a bar on stderr."""
    from ground_sim.render import RENDER_VERSION
    from ground_sim.trajectory import load_trajectory

    alts = {s: [int(round(p.altitude_m)) for p in load_trajectory(s)] for s in scenarios}
    jobs = [(n, s, seed, a) for n in names for s in scenarios for a in alts[s] for seed in seeds]
    vals = _measure_jobs(jobs, workers, progress)
    res = dict(zip(jobs, vals))
    doc: dict[str, Any] = {"format": SHARES_FORMAT, "seeds": list(seeds), "stride": MEASURE_STRIDE}
    doc["scenes"] = {
        n: {
            "digest": params_digest(n),
            "render_version": RENDER_VERSION,
            "scenarios": {
                s: {str(a): [round(res[(n, s, sd, a)], 3) for sd in seeds] for a in alts[s]} for s in scenarios
            },
        }
        for n in names
    }
    return doc


def load_shares(path: str | Path = SHARES_PATH) -> dict[str, Any]:
    p = Path(path)
    if not p.is_file():
        return {"scenes": {}, "seeds": []}
    try:
        return json.loads(p.read_text())
    except json.JSONDecodeError as exc:
        raise SceneError(f"{p}: unreadable hazard-share table ({exc})") from None


def _is_number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def table_problem(doc: Any) -> str | None:
    """What makes ``doc`` no hazard-share table (None when it is one): the first bad entry, by its path.

    A share is a number or null (a pair without covered ground); NaN, which Python's json reads, counts as null.
    A table without "format" is accepted (older tables); another format is not.
    """
    if not isinstance(doc, dict):
        return f"not a hazard-share table (need an object with 'scenes' and 'seeds'), got {type(doc).__name__}"
    if "format" in doc and doc["format"] != SHARES_FORMAT:
        return f"format must be {SHARES_FORMAT!r}, got {doc['format']!r:.60}"
    seeds, scenes = doc.get("seeds", []), doc.get("scenes", {})
    if not isinstance(seeds, list) or not all(isinstance(s, int) and not isinstance(s, bool) for s in seeds):
        return f"seeds must be a list of integers, got {seeds!r:.60}"
    if not isinstance(scenes, dict):
        return "not a hazard-share table (need an object with 'scenes' and 'seeds')"
    for name, rec in scenes.items():
        if not isinstance(rec, dict):
            return f"scenes.{name} must be an object, got {rec!r:.60}"
        scenarios = rec.get("scenarios", {})
        if not isinstance(scenarios, dict):
            return f"scenes.{name}.scenarios must be an object of scenarios, got {scenarios!r:.60}"
        for scen, per_alt in scenarios.items():
            where = f"scenes.{name}.scenarios.{scen}"
            if not isinstance(per_alt, dict):
                return f"{where} must be an object of altitudes, got {per_alt!r:.60}"
            for alt, vals in per_alt.items():
                if not str(alt).isdigit():
                    return f"{where}: altitude {alt!r:.60} is not a whole number of metres"
                if not isinstance(vals, list) or not vals or not all(v is None or _is_number(v) for v in vals):
                    return f"{where}.{alt} must be a non-empty list of shares (numbers or null), got {vals!r:.60}"
    return None


def finite_shares(vals: list[Any]) -> list[float]:
    """The measured shares of one table entry (null and NaN are pairs without covered ground)."""
    return [float(v) for v in vals if v is not None and math.isfinite(float(v))]


def merge_conflict(old: dict[str, Any], names: list[str], seeds: list[int]) -> str | None:
    """Why measuring ``names`` on ``seeds`` cannot be merged into ``old`` (None when it can).

    A table is for one seed set: scenes measured on other seeds and not re-measured now would have to go.
    """
    kept = [n for n in old.get("scenes", {}) if n not in names]
    if not kept or old.get("seeds") == list(seeds):
        return None
    was = old.get("seeds") or []
    return (
        f"the table holds {', '.join(kept)} measured on seeds "
        f"{f'{was[0]}-{was[-1]}' if was else '(none)'}; measuring on {seeds[0]}-{seeds[-1]} would drop them "
        f"(measure with --seeds {len(was)}, measure every scene, or write another --table)"
    )


def merge_shares(old: dict[str, Any], new: dict[str, Any]) -> dict[str, Any]:
    """``new``'s scenes replace ``old``'s; the seed list must agree (a table is for one seed set).

    Scenes of ``old`` that ``new`` does not re-measure are never dropped silently: a different seed set
    with such scenes left is a :class:`SceneError` (check :func:`merge_conflict` before measuring)."""
    why = merge_conflict(old, list(new.get("scenes", {})), list(new.get("seeds", [])))
    if why:
        raise SceneError(why)
    if old.get("seeds") != new.get("seeds"):
        return new  # every scene of old is re-measured in new
    out = dict(new)
    out["scenes"] = {**old.get("scenes", {}), **new["scenes"]}
    return out


def check(e: Entry, rec: dict[str, Any] | None) -> list[str]:
    """Problems of a stored measurement: stale digest or renderer, missing, or a median outside the band."""
    from ground_sim.render import RENDER_VERSION

    if rec is None:
        return [f"{e.name}: not measured (run hazard-hil scenes --measure)"]
    out = []
    if rec.get("digest") != params_digest(e.name):
        out.append(f"{e.name}: measured with other parameters (stale; run hazard-hil scenes --measure)")
    if rec.get("render_version", 1) != RENDER_VERSION:  # the truth (shadow edges) is the renderer's
        out.append(
            f"{e.name}: measured with renderer version {rec.get('render_version', 1)}, this is {RENDER_VERSION}"
            " (stale; run hazard-hil scenes --measure)"
        )
    for scen, per_alt in rec.get("scenarios", {}).items():
        for alt, vals in per_alt.items():
            band = e.band(scen, int(alt))
            fin = finite_shares(vals)
            if not fin:
                out.append(f"{e.name} {scen} {alt} m: no finite share measured")
                continue
            med = float(np.median(fin))
            if band is not None and not band[0] <= med <= band[1]:
                out.append(f"{e.name} {scen} {alt} m: median {med:.1f} % outside [{band[0]:.1f}, {band[1]:.1f}]")
    return out


# --------------------------------------------------------------------------- listing
def summary_params(name: str) -> dict[str, Any]:
    """The parameters people compare scenes by (the full set is the preset file)."""
    from ground_sim.scene import load_scene_params

    p = load_scene_params(name)
    t, c, b, bf = p.terrain, p.craters, p.boulders, p.boulder_fields
    kinds: dict[str, int] = {}
    for f in p.features:
        kinds[f.kind] = kinds.get(f.kind, 0) + 1
    return {
        "relief_rms_m": t.rms_relief_m,
        "hurst": t.hurst,
        "craters": f"{c.coef:g} D^-{c.exponent:g}, degradation {c.degradation:g}" + (" x profile" if c.profile else ""),
        "boulders": f"{b.coef:g} D^-{b.exponent:g}" + (" x profile" if b.profile else ""),
        "boulder_fields_per_km2": bf.per_km2,
        "placed": ", ".join(f"{n} {k}" for k, n in kinds.items()) or "none",
        "albedo": p.albedo.mean,
    }


def _stats(vals: list[float]) -> dict[str, float | None]:
    """Median, min and max of the finite shares (None when there are none: strict JSON, no NaN)."""
    if not vals:
        return {"median": None, "min": None, "max": None}
    return {"median": float(np.median(vals)), "min": float(np.min(vals)), "max": float(np.max(vals))}


def _cell(stats: dict[str, Any], key: str) -> str:
    """An 11-character listing cell: the median, or the min-max range ("-" when nothing was measured)."""
    if stats["median"] is None:
        return f"{'-':>11}"
    return f"{stats['median']:11.1f}" if key == "median" else f"{stats['min']:5.1f}-{stats['max']:<5.1f}"


def describe(names: list[str], table: dict[str, Any]) -> list[dict[str, Any]]:
    """JSON-able listing: metadata, parameters, stored shares (median, min, max) and bands."""
    known = {e.name: e for e in entries()}
    out = []
    for n in names:
        e = known[n]
        rec = table.get("scenes", {}).get(n)
        shares: dict[str, Any] = {}
        for scen, per_alt in (rec or {}).get("scenarios", {}).items():
            shares[scen] = {
                alt: {**_stats(finite_shares(v)), "band": e.band(scen, int(alt))} for alt, v in per_alt.items()
            }
        sun: Any = (
            {"azimuth_deg": e.sun_azimuth_deg, "elevation_deg": e.sun_elevation_deg}
            if e.sun_varies
            else {s: [DEFAULT_SUN[s].azimuth_deg, DEFAULT_SUN[s].elevation_deg] for s in SCENARIOS}
        )
        out.append(
            {
                "name": n,
                "description": e.description,
                "parameters": summary_params(n),
                "sun": sun,
                "seeds": table.get("seeds", []),
                "hazards_in_scene_pct": shares,
                "problems": check(e, rec),
            }
        )
    return out


def format_listing(names: list[str], table: dict[str, Any]) -> str:
    """The ``hazard-hil scenes`` text: one block per scene."""
    lines = []
    seeds = table.get("seeds", [])
    which = describe_seeds(seeds, "held-out") if seeds else "not measured"  # one seed read "1000-1000"
    for d in describe(names, table):
        p = d["parameters"]
        lines.append(f"{d['name']}: {d['description']}")
        lines.append(
            f"  terrain fBm RMS {p['relief_rms_m']:g} m, Hurst {p['hurst']:g}; craters {p['craters']}; "
            f"boulders {p['boulders']}; boulder fields {p['boulder_fields_per_km2']:g}/km2; placed: {p['placed']}; "
            f"albedo {p['albedo']:g}"
        )
        sun = d["sun"]
        if "azimuth_deg" in sun:
            az, el = sun["azimuth_deg"] or (135.0, 135.0), sun["elevation_deg"]
            lines.append(f"  sun drawn per seed: azimuth {az[0]:g}-{az[1]:g} deg, elevation {el[0]:g}-{el[1]:g} deg")
        else:
            lines.append(
                "  sun: the scenario's ("
                + ", ".join(f"{s} {v[0]:g}/{v[1]:g} deg" for s, v in sun.items())
                + " azimuth/elevation)"
            )
        for scen, per_alt in d["hazards_in_scene_pct"].items():
            alts = sorted(per_alt, key=lambda a: -int(a))
            lines.append(f"  hazards in scene % ({scen}, {which}):")
            lines.append("    altitude m " + "".join(f"{a:>11}" for a in alts))
            lines.append("    median     " + "".join(_cell(per_alt[a], "median") for a in alts))
            lines.append("    range      " + "".join(_cell(per_alt[a], "range") for a in alts))
            if any(per_alt[a]["band"] for a in alts):
                lines.append(
                    "    band       "
                    + "".join(
                        f"{per_alt[a]['band'][0]:5.1f}-{per_alt[a]['band'][1]:<5.1f}"
                        if per_alt[a]["band"]
                        else f"{'-':>11}"
                        for a in alts
                    )
                )
        for prob in d["problems"]:
            lines.append(f"  ! {prob}")
        lines.append("")
    return "\n".join(lines)
