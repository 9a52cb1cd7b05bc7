"""Landing Monte Carlo: how often does the top-ranked site turn out truly safe?

ALHAT judged its hazard detection by Monte Carlo runs of thousands of landings;
this is that study for our pipeline. A campaign is ``n`` landings over a list of
library scenes (:mod:`ground_sim.library`), grouped ``per_render`` to a render:

* render group ``g`` flies scene ``scenes[g % S]`` on the next seed of the seed set
  (held-out by default), with an image pair drawn from :data:`LANDING_PAIRS`, the
  scene's sun (drawn from its range where the scene has one, else the scenario's);
* each of its landings draws an aim point (uniform in a disk of
  :data:`AIM_FRACTION` x the lower frame's footprint around the nominal site) and
  navigation errors for both frames (:data:`DEFAULT_POSE_ERROR`); the flight
  pipeline runs on the images with those poses and that aim point, per preset;
* the top-ranked site is judged against ground truth by the DESIGN.md site rule:
  **safe** when every frame-0 truth pixel whose true ground position lies within
  1.5 m (the 3 m footprint's radius) of the site is safe; **unsafe** otherwise (or
  when the footprint reaches the image border, so truth cannot confirm it); **no
  site** when the flight software offers none - its own outcome, never safe.

Every draw is a hash of (campaign key, group, landing), so a campaign is the same
whatever the backend and a rerun resumes (:mod:`studies.executor`). The divert
distance (aim point to site) and whether the aim point itself was safe (the
"blind landing" baseline) are recorded per landing.
"""

from __future__ import annotations

import csv
import hashlib
import io
import json
import math
import re
import signal
import sys
import time
import zlib
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ground_sim.gridscore import judge_site
from ground_sim.render import DEFAULT_RASTER
from ground_sim.seeds import describe_seeds, not_held_out
from protocol.errors import InputError
from protocol.messages import SITES_WITHHELD
from protocol.pairdir import Camera
from reports.html import write_atomic
from reports.jsondoc import json_text
from reports.style import SERIES_COLOURS

LANDING_PAIRS: tuple[tuple[str, str], ...] = (
    ("vertical", "400/200"),
    ("vertical", "300/150"),
    ("vertical", "200/100"),
    ("vertical", "150/75"),
    ("vertical", "100/50"),
    ("approach", "300/150"),
    ("approach", "250/125"),
)
# Navigation knowledge at the final hazard-detection pairs: altimeter + IMU-grade attitude, 1 sigma
# (thesis sec. 6.3 bounds are +-0.5 m and +-0.15 deg; these are about a third of them, per frame).
DEFAULT_POSE_ERROR = "alt_sigma=0.15,pitch_sigma=0.03,roll_yaw=0.03,lateral=0.15,equal_pitch=0"
PER_RENDER = 8
AIM_FRACTION = 0.2
# the report's series colours: neither an outcome's colour nor red
PRESET_COLOURS = {"fast": SERIES_COLOURS[0], "thesis": SERIES_COLOURS[1]}
PRESETS = ("fast", "thesis")
CAMPAIGN_KEY = 0x1A4D
MAX_LANDINGS = 1_000_000  # per campaign: ~3 CPU-days; more is a typo, and its plan would not fit in memory
OUTCOMES = ("safe", "unsafe", "no_site")
Z95 = 1.959963984540054

ROW_COLUMNS = (
    "landing",
    "group",
    "preset",
    "outcome",
    "safe",
    "site_found",
    "scene",
    "scene_seed",
    "seed_set",
    "scenario",
    "pair",
    "altitude_m",
    "sun_azimuth_deg",
    "sun_elevation_deg",
    "aim_x_m",
    "aim_y_m",
    "aim_safe",
    "site_x_m",
    "site_y_m",
    "divert_m",
    "site_truth_px",
    "site_unsafe_px",
    "truth_incomplete",
    "site_rank_margin",
    "no_site_reason",
    "hazards_in_scene_pct",
    "pipeline_s",
    "level",
    "dz1_m",
    "dz2_m",
    "pitch1_deg",
    "pitch2_deg",
    # last, the columns before it in place: false on every row of a campaign stopped before all its renders flew
    "campaign_complete",
)
# beside every P(safe) interval (console, landings.json, page): the landings of one render are not independent
CI_NOTE = (
    "95 % Wilson interval taking the landings as independent draws; the {per_render} aim points of a render share "
    "its terrain, sun and image pair, so the true uncertainty is wider, more so the fewer the renders"
)


class LandingError(InputError):
    """A landing campaign's options or output directory are unusable."""


@dataclass(frozen=True)
class Campaign:
    """Everything that defines a campaign's draws (``n`` only decides how many groups run)."""

    scenes: tuple[str, ...]
    n: int
    seeds: tuple[int, ...]
    seed_set: str
    presets: tuple[str, ...] = ("fast",)
    per_render: int = PER_RENDER
    pose_error: str | None = DEFAULT_POSE_ERROR
    camera_px: int | None = None
    raster: str = DEFAULT_RASTER  # ground_sim's terrain rasters: "tiles" renders every view at its GSD/2

    def __post_init__(self) -> None:
        from ground_sim import library
        from ground_sim.errors import RenderError
        from ground_sim.render import check_raster

        try:
            check_raster(self.raster)
        except RenderError as exc:
            raise LandingError(f"--raster: {exc}") from None

        known = {e.name for e in library.entries()}
        bad = [s for s in self.scenes if s not in known]
        if not self.scenes or bad:
            raise LandingError(
                f"--scenes: not library scenes: {bad or 'none given'} (library: {', '.join(sorted(known))})"
            )
        if len(set(self.scenes)) != len(self.scenes):
            raise LandingError(f"--scenes: each scene once, got {list(self.scenes)}")
        if self.n < 1 or self.per_render < 1:
            raise LandingError(f"need --n >= 1 and --per-render >= 1, got {self.n} and {self.per_render}")
        if self.n > MAX_LANDINGS or self.per_render > MAX_LANDINGS:
            raise LandingError(
                f"need --n and --per-render <= {MAX_LANDINGS} (a landing is a pipeline run of about 0.3 s, its plan "
                f"held in memory), got {self.n} and {self.per_render}"
            )
        if self.per_render > max(self.n, PER_RENDER):  # n is rounded up to whole renders: 1 landing became 1e6
            raise LandingError(
                f"--per-render {self.per_render} is more than the {self.n} landings asked for (--n): the landings are "
                f"rounded up to whole renders, so at most max(--n, {PER_RENDER}) aim points may share one"
            )
        if not self.seeds:
            raise LandingError("no scene seeds")
        bad_p = [p for p in self.presets if p not in PRESETS]
        if not self.presets or bad_p:
            raise LandingError(f"presets must be among {PRESETS}, got {list(self.presets)}")
        if self.pose_error:
            from ground_sim.pose_error import PoseError

            PoseError.parse(self.pose_error)  # fail early on a bad spec

    @property
    def n_groups(self) -> int:
        """Renders: ``n`` in whole renders of ``per_render``, rounded up to a multiple of the scenes (render g flies
        scene g mod S): 8 landings over the six library scenes flew one render of one scene, and the campaign's
        P(safe landing) was said over all six; 7 renders over 6 scenes counted one twice."""
        renders = -(-self.n // self.per_render)
        return -(-renders // len(self.scenes)) * len(self.scenes)

    @property
    def n_landings(self) -> int:
        """Landings actually flown: whole groups (``n`` rounded up to whole renders, and to every scene alike)."""
        return self.n_groups * self.per_render

    def identity(self) -> dict[str, Any]:
        """The settings a resumed campaign must share (all but ``n``)."""
        d = asdict(self)
        d.pop("n")
        d["scenes"] = list(self.scenes)
        d["seeds"] = list(self.seeds)
        d["presets"] = list(self.presets)
        if d["raster"] == "view":  # campaigns from before the choice existed resume unchanged
            d.pop("raster")
        return d


# a campaign whose top sites are unsafe at most this often is marked ok on its page (issue 9: the top site truly
# safe on >= 98 % of pairs)
UNSAFE_SITE_OK = 0.02


# --------------------------------------------------------------------------- draws


def _rng(*keys: int) -> np.random.Generator:
    return np.random.default_rng([CAMPAIGN_KEY, *[int(k) & 0xFFFFFFFF for k in keys]])


@dataclass(frozen=True)
class PlanContext:
    """What every group of a campaign draws from, read once (the library's scene files, the landing pairs'
    trajectories, the navigation errors): read per group, planning 125 000 groups took 4 minutes unannounced."""

    entries: dict[str, Any]  # scene -> its library entry (or None)
    aim_radius_m: dict[tuple[str, str], float]  # (scenario, pair label) -> aim-point disc radius
    pose_error: Any  # ground_sim.pose_error.PoseError or None

    @classmethod
    def of(cls, c: Campaign) -> PlanContext:
        from ground_sim import library
        from ground_sim.pose_error import PoseError
        from ground_sim.trajectory import load_trajectory

        radii = {}
        for scenario, label in LANDING_PAIRS:
            spec = next(s for s in load_trajectory(scenario) if s.label == label)
            radii[scenario, label] = AIM_FRACTION * _footprint_width(spec.camera, spec.poses[-1])
        pe = PoseError.parse(c.pose_error) if c.pose_error else None
        return cls({scene: library.entry(scene) for scene in c.scenes}, radii, pe)


def plan_group(c: Campaign, g: int, ctx: PlanContext | None = None) -> dict[str, Any]:
    """The draws of render group ``g``: scene, seed, pair, sun, and per landing an aim point and pose errors;
    ``ctx`` (:meth:`PlanContext.of`, read here when not given) is the same for every group of ``c``."""
    from ground_sim import library

    ctx = ctx or PlanContext.of(c)
    scene = c.scenes[g % len(c.scenes)]
    seed = c.seeds[(g // len(c.scenes)) % len(c.seeds)]
    rng = _rng(g, zlib.crc32(scene.encode()))
    scenario, label = LANDING_PAIRS[int(rng.integers(len(LANDING_PAIRS)))]
    e = ctx.entries[scene]
    if e is not None and e.sun_varies:
        az0, az1 = e.sun_azimuth_deg or (135.0, 135.0)
        el0, el1 = e.sun_elevation_deg or (25.0, 25.0)
        sun = [float(rng.uniform(az0, az1)) % 360.0, float(rng.uniform(el0, el1))]
    else:
        s = library.DEFAULT_SUN[scenario]
        sun = [s.azimuth_deg, s.elevation_deg]
    radius, pe = ctx.aim_radius_m[scenario, label], ctx.pose_error
    landings = []
    for j in range(c.per_render):
        lr = _rng(g, j, 0xA1)
        r, th = radius * math.sqrt(lr.uniform()), lr.uniform(0.0, 2.0 * math.pi)
        deltas = [d.to_dict() for d in pe.sample(lr)] if pe is not None else [{}, {}]
        landings.append(
            {"landing": g * c.per_render + j, "aim": [r * math.sin(th), r * math.cos(th)], "errors": deltas}
        )
    return {
        "group": g,
        "scene": scene,
        "seed": seed,
        "seed_set": c.seed_set,
        "scenario": scenario,
        "pair": label,
        "sun": sun,
        "camera_px": c.camera_px,
        "raster": c.raster,
        "landings": landings,
    }


def _footprint_width(camera: Any, pose: Any) -> float:
    """Narrowest edge of a frame's ground footprint on Z = 0 (m)."""
    from ground_sim.geometry import ground_footprint

    F = ground_footprint(camera, pose)
    return float(min(np.linalg.norm(F[1] - F[0]), np.linalg.norm(F[2] - F[3]), np.linalg.norm(F[3] - F[0])))


# --------------------------------------------------------------------------- judging
def group_pair(plan: dict[str, Any], cache_dir: str | None = None) -> tuple[Any, Any]:
    """(spec, pair) of a render group: rendered, or read from ``cache_dir`` where an earlier campaign left it.

    The cache key is everything the render depends on (scene, seed, scenario, pair, sun, camera) but the scene's
    parameters and the render code, which the pair records and :func:`ground_sim.render_cache.reusable` checks;
    campaigns that differ only in aim points, navigation errors or presets share their renders."""

    from ground_sim.descent import render_pair
    from ground_sim.render_cache import reusable
    from ground_sim.scene import load_scene, load_scene_params
    from ground_sim.trajectory import load_trajectory
    from protocol.pairdir import Sun, read_pair, write_pair_atomic
    from studies.evaluate import camera_for

    scenario = plan["scenario"]
    spec = next(s for s in load_trajectory(scenario, camera_for(plan["camera_px"])) if s.label == plan["pair"])
    sun = Sun(*plan["sun"])
    raster = plan.get("raster", "view")
    if cache_dir is None:
        sc = load_scene(plan["scene"], plan["seed"], scenario)
        return spec, render_pair(sc, spec, sun, seed=plan["seed"], raster=raster)
    key = (
        f"{plan['scene']}_{scenario}_{plan['pair'].replace('/', '-')}_s{plan['seed']}"
        f"_sun{sun.azimuth_deg:.4f}-{sun.elevation_deg:.4f}_{plan['camera_px'] or 512}px"
        + ("" if raster == "view" else f"_{raster}")
    )
    d = Path(cache_dir) / key
    # none there, or a stale one (another renderer, render code or scene parameters: the key names the scene
    # only), now removed
    if not reusable(d, scene=load_scene_params(plan["scene"], scenario)):
        sc = load_scene(plan["scene"], plan["seed"], scenario)
        # a concurrent writer's copy is kept
        write_pair_atomic(d, render_pair(sc, spec, sun, seed=plan["seed"], raster=raster))
    return spec, read_pair(d)


REFUSED_REASON = "the flight software refused its navigation inputs (see refused_because)"


def land_group(plan: dict[str, Any], presets: list[str], cache_dir: str | None = None) -> dict[str, Any]:
    """Render one group's pair and fly every landing of it with every preset (a pure function: any backend).

    Truth is read from the pair as written (float32 depth backprojected with the true pose), so a cached
    and a fresh render give the same rows."""
    from flight_sw.pipeline import run_pipeline
    from flight_sw.validate import FlightInputError
    from ground_sim.library import covered, share_pct
    from studies.evaluate import backproject_depth

    scenario = plan["scenario"]
    spec, pair = group_pair(plan, cache_dir)
    hazard = pair.truth["hazard"]
    X = backproject_depth(spec.camera, spec.poses[0], pair.truth["depth"].astype(np.float64))
    world = X[..., :2]
    X[..., 2] = pair.truth["elevation"]
    share = share_pct(hazard, covered(spec.camera, spec.poses[-1], X.reshape(-1, 3)).reshape(hazard.shape))
    rows = []
    for ld in plan["landings"]:
        aim = (float(ld["aim"][0]), float(ld["aim"][1]))
        aim_j = judge_site(aim, world, hazard)
        fly = _perturb(spec.poses, ld["errors"])
        for preset in presets:
            t0 = time.process_time()
            try:
                res = run_pipeline(
                    pair.images[0],
                    pair.images[-1],
                    fly[0],
                    fly[-1],
                    spec.camera,
                    preset=preset,
                    nominal_site_xy=aim,
                    altimeter_m=pair.altimeter_m,  # the reading the flight process gets in HIL runs
                    sun_elevation_deg=pair.sun.elevation_deg if pair.sun else None,
                    sun_azimuth_deg=pair.sun.azimuth_deg if pair.sun else None,
                )
            except FlightInputError as exc:
                # navigation data the flight software refuses (a pose error that puts frame 2 above frame 1): the
                # lander gets no map and no site, as under the HIL; it failed the whole group, and so the campaign
                res, refused = None, str(exc)
            cpu = time.process_time() - t0
            row: dict[str, Any] = {
                "landing": ld["landing"],
                "group": plan["group"],
                "preset": preset,
                "scene": plan["scene"],
                "scene_seed": plan["seed"],
                "seed_set": plan["seed_set"],
                "scenario": scenario,
                "pair": plan["pair"],
                "altitude_m": float(spec.altitude_m),
                "sun_azimuth_deg": plan["sun"][0],
                "sun_elevation_deg": plan["sun"][1],
                "aim_x_m": aim[0],
                "aim_y_m": aim[1],
                "aim_safe": bool(aim_j["safe"]),
                "hazards_in_scene_pct": share,
                "pipeline_s": cpu,
                "level": res.level if res is not None else "refused",
                "no_site_reason": (
                    REFUSED_REASON if res is None else str(res.info.get("no_site_reason", "")) if not res.sites else ""
                ),
            }
            if res is None:
                row["refused_because"] = refused
            for k, d in enumerate(ld["errors"][:2]):
                row[f"dz{k + 1}_m"] = float(d.get("dz_m", 0.0))
                row[f"pitch{k + 1}_deg"] = float(d.get("pitch_deg", 0.0))
            if res is not None and res.sites:
                top = res.sites[0]
                j = judge_site((top.x, top.y), world, hazard)
                row.update(
                    {
                        "outcome": "safe" if j["safe"] else "unsafe",
                        "safe": bool(j["safe"]),
                        "site_found": True,
                        "site_x_m": float(top.x),
                        "site_y_m": float(top.y),
                        "divert_m": float(math.hypot(top.x - aim[0], top.y - aim[1])),
                        "site_truth_px": j["n_px"],
                        "site_unsafe_px": j["n_unsafe"],
                        "truth_incomplete": bool(j["incomplete"]),
                        "site_rank_margin": float(top.margin),
                    }
                )
            else:
                row.update({"outcome": "no_site", "safe": False, "site_found": False})
            rows.append(row)
    return {"rows": rows}


def _perturb(poses: tuple[Any, ...], errors: list[dict[str, float]]) -> list[Any]:
    """Poses as navigation reports them: ``PoseDelta(**errors[k]).apply(poses[k])``."""
    from ground_sim.pose_error import PoseDelta

    return [PoseDelta(**e).apply(p) if e else p for p, e in zip(poses, errors)]


# --------------------------------------------------------------------------- statistics
def wilson(k: int, n: int, z: float = Z95) -> tuple[float, float]:
    """Wilson score interval of a binomial proportion k/n (Wilson 1927): centre
    ``(p + z^2/2n) / (1 + z^2/n)``, half-width ``z sqrt(p(1-p)/n + z^2/4n^2) / (1 + z^2/n)``."""
    if n <= 0:
        return (math.nan, math.nan)
    if not 0 <= k <= n:
        raise ValueError(f"wilson: need 0 <= k <= n, got k={k}, n={n}")
    p = k / n
    den = 1.0 + z * z / n
    centre = (p + z * z / (2 * n)) / den
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / den
    # exact at the boundaries (k = 0 or n): centre - half is 0 or 1 only up to rounding, which could put
    # the proportion itself outside its interval
    lo = 0.0 if k == 0 else max(0.0, centre - half)
    hi = 1.0 if k == n else min(1.0, centre + half)
    return (lo, hi)


def stats(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """P(safe) with its Wilson 95 % interval, P(no site), P(unsafe), divert percentiles, blind baseline."""
    n = len(rows)
    k = {o: sum(1 for r in rows if r["outcome"] == o) for o in OUTCOMES}
    div = np.array([r["divert_m"] for r in rows if r.get("site_found")], float)
    aim = sum(1 for r in rows if r.get("aim_safe"))
    pct = {f"p{q}": (float(np.percentile(div, q)) if div.size else None) for q in (50, 90, 99)}
    return {
        "n": n,
        "n_safe": k["safe"],
        "n_unsafe": k["unsafe"],
        "n_no_site": k["no_site"],
        "p_safe": k["safe"] / n if n else None,
        "p_safe_ci95": list(wilson(k["safe"], n)) if n else None,
        "p_unsafe": k["unsafe"] / n if n else None,
        "p_no_site": k["no_site"] / n if n else None,
        "p_no_site_ci95": list(wilson(k["no_site"], n)) if n else None,
        "divert_m": {
            **pct,
            "max": float(div.max()) if div.size else None,
            "mean": float(div.mean()) if div.size else None,
        },
        "p_aim_safe": aim / n if n else None,
        "p_aim_safe_ci95": list(wilson(aim, n)) if n else None,
    }


def no_site_reasons(rows: list[dict[str, Any]]) -> dict[str, int]:
    """Landings without a site, counted by the flight software's reason (its leading clause: the figures
    in brackets differ per landing; a withheld map's reason is cut at its first figure, as frame numbers and
    metres differ too), most frequent first."""
    counts: dict[str, int] = {}
    for r in rows:
        if r["outcome"] == "no_site":
            why = str(r.get("no_site_reason") or "").split(" (")[0].strip() or "no reason given"
            if why.startswith(SITES_WITHHELD):  # "... frame 0's optical axis +17.5 m from ...": one group, not one each
                why = re.split(r"[+-]?\d", why, maxsplit=1)[0].rstrip(" :,") + " ..."
            counts[why] = counts.get(why, 0) + 1
    return dict(sorted(counts.items(), key=lambda kv: (-kv[1], kv[0])))


def summarise(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Statistics per preset, overall and per scene (and per preset x pair), and why no site was offered."""
    out: dict[str, Any] = {"per_preset": {}, "per_scene": {}, "per_pair": {}, "no_site_reasons": {}}
    presets = sorted({r["preset"] for r in rows}, key=lambda p: PRESETS.index(p) if p in PRESETS else 9)
    for p in presets:
        rp = [r for r in rows if r["preset"] == p]
        out["per_preset"][p] = stats(rp)
        out["no_site_reasons"][p] = no_site_reasons(rp)
        for s in sorted({r["scene"] for r in rp}):
            out["per_scene"].setdefault(s, {})[p] = stats([r for r in rp if r["scene"] == s])
        for key in sorted({f"{r['scenario']} {r['pair']}" for r in rp}):
            out["per_pair"].setdefault(key, {})[p] = stats([r for r in rp if f"{r['scenario']} {r['pair']}" == key])
    out["overall"] = {p: out["per_preset"][p] for p in presets}
    return out


# --------------------------------------------------------------------------- campaign
def claim_out_dir(c: Campaign, out_dir: str | Path) -> Path:
    """Create ``out_dir`` for campaign ``c``; refuse one that holds a campaign with other settings."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    cfg = out / "campaign.json"
    if cfg.is_file():
        try:
            old = json.loads(cfg.read_text())
        except json.JSONDecodeError:
            old = None
        if old is not None and old != c.identity():
            new = c.identity()
            keys = sorted(set(old) | set(new)) if isinstance(old, dict) else []
            differ = [
                f"{k} {old.get(k)!r:.40} there, {new.get(k)!r:.40} here" for k in keys if old.get(k) != new.get(k)
            ]
            raise LandingError(
                f"{out} holds a campaign with other settings ({cfg}"
                + (f": {'; '.join(differ[:3])}" if differ else "")
                + "); use another --out or the same options"
            )
    cfg.write_text(json.dumps(c.identity(), indent=1) + "\n")
    return out


def campaign_key(c: Campaign) -> str:
    """A short digest of the campaign's identity (:meth:`Campaign.identity`): what its saved landings depend on."""
    text = json.dumps(c.identity(), sort_keys=True, separators=(",", ":"))
    return "campaign-" + hashlib.sha256(text.encode()).hexdigest()[:16]


PLAN_NOTE_GROUPS = 10_000  # planning this many render groups takes seconds: said before it starts


def run_campaign(
    c: Campaign,
    out_dir: str | Path,
    *,
    scheduler: Any = None,
    workers: int | None = None,
    progress: bool = True,
    cache_dir: str | Path | None = None,
    figures: bool = True,
) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """Fly the campaign (resuming ``out_dir/runs/landings.jsonl``); write CSV, JSON and the page.

    ``cache_dir`` keeps the rendered pairs for later campaigns (render once, fly many times). ``figures``: the
    page draws its figures (off: ``--no-figures``, the tables alone). Returns (rows, summary)."""
    from protocol.pairdir import THESIS_CAMERA_PX
    from studies.evaluate import EVAL_CODE
    from studies.executor import PAIR_BYTES_PER_PX, CampaignError, Task, code_fingerprint, load_results, run_tasks

    out = claim_out_dir(c, out_dir)
    cache = None if cache_dir is None else str(Path(cache_dir).resolve())
    ctx = PlanContext.of(c)
    if progress and c.n_groups >= PLAN_NOTE_GROUPS:  # a million landings planned for a minute without a word (QA 74)
        print(f"landings: planning {c.n_groups} renders of {c.n_landings} landings", file=sys.stderr, flush=True)
    tasks = [
        Task(f"g{g:05d}", {"plan": plan_group(c, g, ctx), "presets": list(c.presets), "cache_dir": cache})
        for g in range(c.n_groups)
    ]
    t0 = time.time()
    code = code_fingerprint(EVAL_CODE)
    # the task ids (g00000, ...) say nothing of the campaign: a record is reused only by the campaign that made it,
    # whatever campaign.json says (a lost or edited one let another campaign's landings pass as this one's)
    inputs = campaign_key(c)
    log = out / "runs" / "landings.jsonl"
    try:
        res = run_tasks(
            land_group,
            tasks,
            log,
            scheduler=scheduler,
            workers=workers,
            progress=progress,
            desc=f"landings ({c.per_render} per render)",
            code=code,
            inputs=inputs,
            # a kept render per group (none kept without a cache)
            disk=None if cache is None else (cache, int(PAIR_BYTES_PER_PX * (c.camera_px or THESIS_CAMERA_PX) ** 2)),
        )
    except (KeyboardInterrupt, CampaignError) as exc:
        # a partial summary of the renders that finished, marked incomplete, then the interruption goes on
        saved = load_results(log, code, inputs)
        part = [r for t in tasks if t.id in saved for r in saved[t.id]["rows"]]
        # the signal by name, as the console says it ("stopped by SIGTERM"); a Ctrl-C is "interrupted"
        signum = getattr(exc, "signum", None)
        why = (
            (f"stopped by {signal.Signals(signum).name}" if signum else "interrupted")
            if isinstance(exc, KeyboardInterrupt)
            else str(exc)
        )
        _write_summary(c, out, part, time.time() - t0, complete=False, reason=why, figures=figures)
        raise
    rows = [r for t in tasks for r in res[t.id]["rows"]]
    summary = _write_summary(c, out, rows, time.time() - t0, complete=True, figures=figures)
    return rows, summary


def _write_summary(
    c: Campaign,
    out: Path,
    rows: list[dict[str, Any]],
    wall: float,
    *,
    complete: bool,
    reason: str = "",
    figures: bool = True,
) -> dict[str, Any]:
    """``landings.csv``, ``landings.json`` (``complete`` false, with the reason, when renders are missing)
    and the page; a partial campaign's statistics cover only the landings flown."""
    summary = summarise(rows)
    summary["campaign"] = {**c.identity(), "n": c.n, "n_landings": c.n_landings, "n_renders": c.n_groups}
    summary["complete"] = complete
    summary["n_landings_flown"] = len({r["landing"] for r in rows})
    if not complete:
        summary["incomplete_reason"] = reason
    summary["seeds_used"] = sorted({int(r["scene_seed"]) for r in rows})
    # the camera the landings saw: the campaign's camera_px is null for the scenarios' own (QA of stop 73)
    summary["camera_px_used"] = c.camera_px or Camera.thesis().width
    summary["ci95_note"] = CI_NOTE.format(per_render=c.per_render)  # travels with the numbers (QA 65b L3)
    summary["wall_s_this_run"] = wall
    # each file whole or not at all: a signal in the last instant must not leave a truncated landings.json
    write_rows(rows, out / "landings.csv", complete=complete)
    write_atomic(out / "landings.json", json_text(summary))
    if rows:
        write_report(out, rows, summary, figures=figures)
    return summary


def write_rows(rows: list[dict[str, Any]], path: Path, *, complete: bool = True) -> Path:
    """``landings.csv``: a row per landing and preset, each saying whether its campaign is complete (a partial
    campaign's file could not be told from a whole one's, and a comment line would break CSV readers)."""
    cols = list(ROW_COLUMNS) + sorted({k for r in rows for k in r} - set(ROW_COLUMNS))
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=cols, extrasaction="ignore", lineterminator="\n")
    w.writeheader()
    for r in sorted(rows, key=lambda r: (r["landing"], r["preset"])):
        w.writerow({k: _cell(r.get(k)) for k in cols} | {"campaign_complete": str(complete).lower()})
    return write_atomic(path, buf.getvalue())


def _cell(v: Any) -> Any:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return ""
    if isinstance(v, float):
        return f"{v:.6g}"
    return v


# --------------------------------------------------------------------------- report
PLOT_NAMES = ("p_safe_by_scene.png", "outcomes.png", "divert_cdf.png")  # _plots' files, in its order


def _plots(out: Path, rows: list[dict[str, Any]], summary: dict[str, Any]) -> list[tuple[str, str]]:
    """The page's figures: P(safe) per scene with Wilson bars and the blind baseline; outcomes; divert CDF. A
    partial campaign's are titled INCOMPLETE: a figure is shown and passed on without its page."""
    from reports.plots import _plt, save
    from reports.style import FALSE_ALARM, MISSED, SAFE, UNKNOWN

    plt = _plt()
    mark = "" if summary.get("complete") is not False else "INCOMPLETE: "
    presets = list(summary["per_preset"])
    scenes = list(summary["per_scene"])
    files = []
    fig, ax = plt.subplots(figsize=(9.5, 3.6))
    w = 0.8 / (len(presets) + 1)
    x = np.arange(len(scenes))
    for i, p in enumerate(presets + ["blind"]):
        if p == "blind":
            st = [summary["per_scene"][s][presets[0]] for s in scenes]
            val = [s["p_aim_safe"] for s in st]
            ci = [s["p_aim_safe_ci95"] for s in st]
            colour = UNKNOWN
        else:
            st = [summary["per_scene"][s][p] for s in scenes]
            val = [s["p_safe"] for s in st]
            ci = [s["p_safe_ci95"] for s in st]
            colour = PRESET_COLOURS.get(p, SERIES_COLOURS[0])  # not the outcome colours (orange is "no site")
        err = np.clip(np.array([[v - c[0] for v, c in zip(val, ci)], [c[1] - v for v, c in zip(val, ci)]]), 0, None)
        bars = ax.bar(
            x + (i - len(presets) / 2) * w,
            val,
            w,
            yerr=err,
            capsize=3,
            label=p if p != "blind" else "aim point (blind)",
            color=colour,
        )
        # each bar says its value: a P(safe) of 0 drew no bar at all, only a whisker no one could place
        ax.bar_label(bars, labels=[f"{v:.2f}" for v in val], fontsize=7, padding=1)
    ax.set_xticks(x, scenes, rotation=15)
    ax.set_ylim(0, 1.05)
    ax.set_ylabel("P(safe landing)")
    ax.set_title(f"{mark}top-ranked site truly safe (95 % Wilson interval); grey: landing blind at the aim point")
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.0, 1.0), frameon=False)  # beside: it hid a bar (QA 64b)
    fig.tight_layout()
    files.append((save(fig, out / PLOT_NAMES[0]).name, "P(safe landing) per scene and preset"))

    fig, axes = plt.subplots(1, len(presets), figsize=(4.2 * len(presets), 3.4), squeeze=False)
    colours = {"safe": SAFE, "unsafe": MISSED, "no_site": FALSE_ALARM}
    for ax, p in zip(axes[0], presets):
        bottom = np.zeros(len(scenes))
        for o in OUTCOMES:
            v = np.array(
                [summary["per_scene"][s][p][f"n_{o}"] / max(1, summary["per_scene"][s][p]["n"]) for s in scenes]
            )
            ax.bar(scenes, v, bottom=bottom, color=colours[o], label=o.replace("_", " "))
            bottom += v
        ax.set_title(f"{mark}outcomes, preset {p}")
        ax.set_ylabel("share of the scene's landings")
        ax.set_ylim(0, 1.0)
        ax.tick_params(axis="x", rotation=30, labelsize=8)
        ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.0, 1.0), frameon=False)  # beside, not over a bar
    fig.tight_layout()
    files.append((save(fig, out / PLOT_NAMES[1]).name, "outcome shares per scene: safe, unsafe site, no site"))

    fig, ax = plt.subplots(figsize=(5.5, 3.4))
    for p in presets:
        d = np.sort([r["divert_m"] for r in rows if r["preset"] == p and r.get("site_found")])
        if d.size:  # an empirical CDF is a step function
            ax.step(
                np.r_[0.0, d],
                np.r_[0.0, np.arange(1, d.size + 1) / d.size],
                where="post",
                label=f"{p} ({d.size})",
                color=PRESET_COLOURS.get(p),
            )
        else:  # say so rather than leave the preset out without a word
            ax.plot([], [], " ", label=f"{p}: no site on any landing")
    ax.set_xlim(left=0)
    ax.set_ylim(0, 1.02)
    ax.set_title(f"{mark}how far the chosen site is from the aim point")
    ax.set_xlabel("divert distance from the aim point [m]")
    ax.set_ylabel("share of landings with a site")
    ax.legend(fontsize=8, title="preset (landings with a site)", title_fontsize=7)
    fig.tight_layout()
    files.append((save(fig, out / PLOT_NAMES[2]).name, "cumulative divert distance"))
    return files


def counted(n: int, noun: str) -> str:
    """``1 render``, ``2 renders``: a count and its noun, plural but for one."""
    return f"{n} {noun}{'' if n == 1 else 's'}"


def write_report(out: Path, rows: list[dict[str, Any]], summary: dict[str, Any], *, figures: bool = True) -> Path:
    """``out/report/index.html``: headline P(safe) per preset, a table per scene, the figures (one page; without
    ``figures`` the page says they were not drawn)."""
    from reports.html import (
        NO_FIGURES_NOTE,
        Column,
        Figure,
        Headline,
        Section,
        Table,
        drop_pictures,
        dropped_note,
        file_links,
        write_page,
    )

    rep = out / "report"
    rep.mkdir(parents=True, exist_ok=True)
    figs = _plots(rep, rows, summary) if figures else []
    if not figures and (gone := drop_pictures(rep / name for name in PLOT_NAMES)):
        print(dropped_note("landings", len(gone), rep), file=sys.stderr, flush=True)
    camp = summary["campaign"]
    seeds = summary.get("seeds_used") or camp["seeds"]
    partial = summary.get("complete") is False
    # in the title and each headline, not only below them (QA 65b L2)
    so_far = f"{summary.get('n_landings_flown')} of {camp['n_landings']} landings flown" if partial else ""
    head = []
    for p, st in summary["per_preset"].items():
        lo, hi = st["p_safe_ci95"]
        label = f"P(safe landing), {p}" + (f", INCOMPLETE: {so_far}" if partial else "")
        head.append(Headline("p_safe", f"{st['p_safe']:.3f} [{lo:.3f}, {hi:.3f}]", label=label))
        # the figure a lander fears most, beside it: a site offered that is not clear (a landing with no site is
        # not safe either, but it is no crash); the page showed it only deep in the table (QA of stop 72)
        pu = st.get("p_unsafe")
        if pu is not None:
            status = "ok" if pu <= UNSAFE_SITE_OK else "bad"
            head.append(Headline("p_unsafe", pu, status, f"P(unsafe site), {p}"))
    table_rows = []
    for s, per in summary["per_scene"].items():
        # which pairs the scene was flown at: two scenes side by side may have been flown at other altitudes
        flown = ", ".join(sorted({f"{r['scenario']} {r['pair']}" for r in rows if r["scene"] == s}))
        for p, st in per.items():
            table_rows.append(
                {
                    "scene": s,
                    "pairs": flown,
                    "preset": p,
                    "n": st["n"],
                    "p_safe": st["p_safe"],
                    "p_safe_ci95": f"{st['p_safe_ci95'][0]:.3f}-{st['p_safe_ci95'][1]:.3f}",
                    "p_no_site": st["p_no_site"],
                    "p_unsafe": st["p_unsafe"],
                    "p_aim_safe": st["p_aim_safe"],
                    "divert_m": st["divert_m"]["p50"],
                }
            )
    cols = [
        Column("scene", "scene"),
        Column("pairs", "pairs flown"),
        Column("preset", "preset"),
        Column("n", "landings", term="n_landings"),
        Column("p_safe"),
        Column("p_safe_ci95"),
        Column("p_no_site"),
        Column("p_unsafe"),
        Column("p_aim_safe"),
        Column("divert_m", "median divert [m]"),
    ]
    planned = f"{counted(camp['n_landings'], 'landing')} ({counted(camp['n_renders'], 'render')}, "
    from studies.evaluate import other_camera

    other = other_camera(camp.get("camera_px"))
    camera = f"; {other}: not its setup" if other else ""
    intro = (
        (f"{summary['n_landings_flown']} of {planned}" if partial else planned)
        + f"{counted(camp['per_render'], 'aim point')} each) over "
        f"{', '.join(camp['scenes'])}; {describe_seeds(seeds, camp['seed_set'])}; pose errors "
        f"{camp['pose_error'] or 'none'}{camera}. A landing is safe when every ground-truth pixel within 1.5 m of "
        "the top-ranked site is safe; no site is its own outcome and is not safe. The intervals: "
        + summary.get("ci95_note", CI_NOTE.format(per_render=camp["per_render"]))
        + "."
    )
    warning = not_held_out(seeds, camp["seed_set"])
    if warning:
        intro = f"WARNING: {warning}. " + intro
    if partial:
        intro = (
            f"INCOMPLETE ({summary.get('incomplete_reason') or 'stopped'}): only {summary['n_landings_flown']} of "
            f"{camp['n_landings']} landings were flown, and every figure below covers those alone; rerun the same "
            "command to finish the campaign. " + intro
        )
    why_rows = [
        {"preset": p, "reason": why, "n": k, "share": k / summary["per_preset"][p]["n"]}
        for p, reasons in summary.get("no_site_reasons", {}).items()
        for why, k in reasons.items()
    ]
    why_cols = [
        Column("preset", "preset"),
        Column("reason", "why the flight software offered no site"),
        Column("n", "landings", term="n_landings"),  # "n" alone is the glossary's Monte Carlo "samples"
        Column("share", "share of the preset's landings"),
    ]
    sections = [
        Section("Per scene", [intro], [Table(cols, table_rows)]),
        # a heading over nothing when every landing had a site
        *([Section("Why no site", [], [Table(why_cols, why_rows)])] if why_rows else []),
        Section("Figures", [] if figures else [NO_FIGURES_NOTE], [], [Figure(f, cap) for f, cap in figs]),
    ]
    links = file_links(
        rep,
        [
            ("../landings.csv", "a row per landing and preset: the draws, the site and its verdict"),
            ("../landings.json", "the figures of this page"),
        ],
    )
    if links:
        sections.append(Section("Files", links=links))
    title = "hazard-hil landings: " + (
        f"INCOMPLETE landing Monte Carlo ({so_far})" if partial else "landing Monte Carlo"
    )
    return write_page(rep / "index.html", title, sections, headline=head, legends=())
