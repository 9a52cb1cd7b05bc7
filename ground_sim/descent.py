"""Render descent pairs (2-16 frames each) to pair directories (DESIGN.md format) with ground truth.

Frames are rendered in a pool of single-threaded processes (:mod:`ground_sim.parallel`);
a pose shared by two pairs (the vertical descent's 400 m frame is the lower frame of
800/400 and the upper one of 400/200) is rendered once and given each pair's own sensor
noise, so the bytes do not depend on the pool or on the sharing.
"""

from __future__ import annotations

import json
import sys
import time
import zlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from ground_sim import library
from ground_sim.errors import TrajectoryError
from ground_sim.library import DEFAULT_SUN, covered, share_pct
from ground_sim.pose_error import PoseDelta, PoseError
from ground_sim.render import (
    DEFAULT_RASTER,
    MAX_CELLS,
    RENDER_VERSION,
    View,
    check_max_cells,
    check_raster,
    check_sun,
    noisy_image,
    render_view,
)
from ground_sim.render_cache import render_fingerprints
from ground_sim.scene import Scene, SceneParams, load_scene
from ground_sim.trajectory import (
    MAX_ALTITUDE_M,
    MIN_ALTITUDE_M,
    PairSpec,
    check_distinct_dirs,
    frames_at,
    load_trajectory,
)
from protocol.pairdir import (
    MANIFEST_FORMAT,
    Camera,
    Pair,
    PairFormatError,
    Pose,
    Sun,
    check_altimeter,
    check_sees_ground,
    image_name,
    is_write_leftover,
    write_pair_atomic,
)
from reports.html import write_atomic
from reports.jsondoc import finite_or_null, json_text

__all__ = ["DEFAULT_SUN", "default_scene", "render_pair", "render_scenario", "render_views"]

INLINE_PIXELS = 2 * 512 * 512  # default-worker renders up to this many pixels stay in-process
ALTITUDE_CONVENTION = (
    "altitude_m is the LOWER (last) frame's altitude above the reference plane, as in "
    "thesis Tables 6.1/6.8 (600/300 is the 300 m row)"
)


def _key(label: str) -> int:
    return zlib.crc32(label.encode())


def noise_seed(seed: int, label: str, k: int) -> int:
    """Sensor-noise seed of frame ``k`` of the pair ``label`` rendered with scene seed ``seed``."""
    return seed * 7919 + _key(label) * 2 + k


@dataclass(frozen=True)
class _Job:
    params: SceneParams
    scene_seed: int
    camera: Camera
    pose: Pose
    sun: Sun
    supersample: int
    max_cells: int = MAX_CELLS
    raster: str = DEFAULT_RASTER
    hazard_truth: bool = True


def _render_job(job: _Job) -> View:
    return render_view(
        Scene(job.params, job.scene_seed),
        job.camera,
        job.pose,
        job.sun,
        supersample=job.supersample,
        noise=False,
        max_cells=job.max_cells,
        raster=job.raster,
        hazard_truth=job.hazard_truth,
    )


def _pose_key(camera: Camera, pose: Pose) -> bytes:
    return repr(camera).encode() + pose.position.tobytes() + pose.R.tobytes()


def render_views(
    scene: Scene,
    camera: Camera,
    poses: list[Pose],
    sun: Sun,
    *,
    supersample: int = 2,
    workers: int | None = 1,
    max_cells: int = MAX_CELLS,
    raster: str = DEFAULT_RASTER,
    on_view: Callable[[int, int], None] | None = None,
    hazard_truth: Sequence[bool] | None = None,
) -> list[View]:
    """Noise-free views of ``poses`` (duplicates rendered once), in a pool of ``workers`` processes;
    ``on_view(done, total)`` as each view is drawn (a progress bar). ``hazard_truth[i]`` False: pose ``i`` needs
    no slope and roughness truth (``render_view(hazard_truth=False)``; a duplicate that needs it gets it)."""
    from ground_sim.parallel import pool_map

    check_max_cells(max_cells)  # here, not in a worker: a bad value is one clear error
    check_raster(raster)
    wants = [True] * len(poses) if hazard_truth is None else [bool(w) for w in hazard_truth]
    if len(wants) != len(poses):
        raise ValueError(f"render_views: {len(wants)} hazard_truth flags for {len(poses)} poses")
    uniq: dict[bytes, int] = {}
    jobs: list[tuple[_Job]] = []
    for p, want in zip(poses, wants, strict=True):
        k = _pose_key(camera, p)
        if k not in uniq:
            uniq[k] = len(jobs)
            jobs.append((_Job(scene.params, scene.seed, camera, p, sun, int(supersample), max_cells, raster, want),))
        elif want:
            i = uniq[k]
            jobs[i] = (replace(jobs[i][0], hazard_truth=True),)
    if workers is None and camera.width * camera.height * len(jobs) <= INLINE_PIXELS:
        workers = 1  # a pool's start-up (spawn + imports, ~1 s) would cost more than it saves
    drawn = [0]

    def done(_: int) -> None:
        drawn[0] += 1
        if on_view is not None:
            on_view(drawn[0], len(jobs))

    if on_view is not None:  # 0 of the views drawn, not of the poses: a frame two pairs share is drawn once
        on_view(0, len(jobs))
    views = pool_map(_render_job, jobs, workers, on_done=done)
    return [views[uniq[_pose_key(camera, p)]] for p in poses]


def _true_frames(poses: tuple[Pose, ...]) -> list[dict[str, Any]]:
    return [p.to_dict(image_name(k)) for k, p in enumerate(poses)]


def assemble_pair(
    scene: Scene,
    spec: PairSpec,
    sun: Sun,
    views: list[View],
    *,
    seed: int = 0,
    pose_error: PoseError | None = None,
) -> Pair:
    """A :class:`Pair` from rendered views: each frame's sensor noise, reported poses, truth of frame 0."""
    images = tuple(noisy_image(v, noise_seed(seed, spec.label, k)) for k, v in enumerate(views))
    truth = {
        "elevation": views[0].elevation,
        "depth": views[0].depth,
        "shadow": views[0].shadow,
        "hazard": views[0].hazard,
    }
    world = np.dstack([views[0].world_xy, views[0].elevation]).reshape(-1, 3).astype(np.float64)
    cov = covered(spec.camera, spec.poses[-1], world).reshape(views[0].hazard.shape)
    meta: dict = {
        "scenario": spec.scenario,
        "label": spec.label,
        "altitude_m": spec.altitude_m,
        "altitude_convention": ALTITUDE_CONVENTION,
        "scene": scene.params.name,
        "scene_variant": scene.params.variant,
        "scene_spec": scene.params.spec,
        "scene_seed": scene.seed,
        "seed": seed,
        "hazards_in_scene_pct": share_pct(views[0].hazard, cov),
        "overlap_pct": 100.0 * float(np.mean(cov)),  # of frame 0's pixels, the last frame sees too
        "hazard_fraction": float(np.mean(views[0].hazard >= 1.0)),
        "true_frames": _true_frames(spec.poses),
        "render": [v.info | {"raster_origin_m": [float(x) for x in v.info["raster_origin_m"]]} for v in views],
        "render_version": RENDER_VERSION,  # render caches reuse a pair only if this renderer drew it
        # ... from these scene parameters, with this render code (ground_sim.render_cache)
        **render_fingerprints(scene.params),
    }
    reported, deltas = reported_poses(spec, seed, pose_error)
    if pose_error is not None:
        meta["pose_error"] = {"distribution": pose_error.to_dict(), "frames": [d.to_dict() for d in deltas]}
    meta = finite_or_null(meta)  # pair.json is strict JSON: a pair without shared ground has no share (null)
    return Pair(spec.camera, reported, images, sun, truth, meta, altimeter_m=tuple(float(v.altimeter_m) for v in views))


def reported_poses(
    spec: PairSpec, seed: int, pose_error: PoseError | None
) -> tuple[tuple[Pose, ...], tuple[PoseDelta, ...]]:
    """The poses navigation reports for ``spec``'s frames (the true ones plus ``pose_error``'s draws, seeded by
    ``seed`` and the pair's label) and the draws."""
    if pose_error is None:
        return spec.poses, ()
    rng = np.random.default_rng([seed & 0xFFFFFFFF, _key(spec.label), 0xE77])
    deltas = pose_error.sample_n(rng, len(spec.poses))
    return tuple(d.apply(p) for d, p in zip(deltas, spec.poses)), deltas


def check_reported_poses(specs: list[PairSpec], seed: int, pose_error: PoseError | None) -> None:
    """Refuse, before any rendering, a pose error that puts a reported camera under the ground or so far from
    its true height that the pair's altimeter check (:func:`protocol.pairdir.check_altimeter`) will refuse the
    pair when it is written. The true pose's range to the datum stands in for the altimeter reading, which
    the terrain moves by tens of metres; the check at writing stays the one that decides."""
    if pose_error is None:
        return
    for spec in specs:
        reported, _ = reported_poses(spec, seed, pose_error)
        for k, (true, rep) in enumerate(zip(spec.poses, reported)):
            what = f"pair {spec.label} frame {k} with the injected pose error"
            check_sees_ground(rep, what)
            cos_off = -float(true.R[2, 2])
            if cos_off <= 0:
                continue
            try:
                check_altimeter(float(true.position[2]) / cos_off, rep, what)
            except PairFormatError:
                raise PairFormatError(
                    f"{what}: the camera is reported at z = {rep.position[2]:.1f} m, {true.position[2]:.1f} m truly; "
                    f"its altimeter reading would contradict that, and the pair would be refused when written "
                    f"(protocol.pairdir.check_altimeter): use a smaller altitude error"
                ) from None


def render_pair(
    scene: Scene,
    spec: PairSpec,
    sun: Sun,
    *,
    seed: int = 0,
    pose_error: PoseError | None = None,
    supersample: int = 2,
    workers: int | None = 1,
    max_cells: int = MAX_CELLS,
    raster: str = DEFAULT_RASTER,
) -> Pair:
    """Render every frame of ``spec``; reported poses carry the injected errors, truth is for frame 0."""
    check_reported_poses([spec], seed, pose_error)
    views = render_views(
        scene,
        spec.camera,
        list(spec.poses),
        sun,
        supersample=supersample,
        workers=workers,
        max_cells=max_cells,
        raster=raster,
        hazard_truth=first_frames([spec]),
    )
    return assemble_pair(scene, spec, sun, views, seed=seed, pose_error=pose_error)


def first_frames(specs: Sequence[PairSpec]) -> list[bool]:
    """Per pose of ``specs`` (in order): True for each pair's frame 0, the only frame whose truth a pair keeps."""
    return [k == 0 for ps in specs for k in range(len(ps.poses))]


def _progress(i: int, n: int, label: str, t0: float, enabled: bool) -> None:
    """Render progress: in place on a terminal, one plain line per frame in a log (no run-on bar)."""
    if not enabled:
        return
    w = 24
    fill = int(w * i / n)
    line = f"render [{'#' * fill}{'.' * (w - fill)}] {i}/{n} {label:<12} {time.time() - t0:6.1f} s"
    if sys.stderr.isatty():
        sys.stderr.write("\r" + line + ("\n" if i == n else ""))
    else:  # the first line too: a log said nothing until the first frame was done
        sys.stderr.write(line + "\n")
    sys.stderr.flush()


def default_scene(scenario: str) -> str:
    """Scene a scenario is rendered on unless told otherwise: the library's ``thesis`` scene.

    ``thesis`` has one variant per thesis scenario (the approach flies over the safer area of
    Table 6.8); custom trajectories use its base (vertical-descent) terrain.
    """
    return "thesis"


def render_scenario(
    spec: str | Path,
    out_dir: str | Path,
    *,
    scene: str | Path | Scene | None = None,
    seed: int = 0,
    pairs: list[str] | None = None,
    frames: list[list[float]] | None = None,
    pose_error: PoseError | None = None,
    progress: bool = True,
    sun: Sun | None = None,
    supersample: int = 2,
    camera: Camera | None = None,
    workers: int | None = None,
    max_cells: int = MAX_CELLS,
    raster: str = DEFAULT_RASTER,
    written: list[str] | None = None,
) -> Path:
    """Render a scenario to ``out_dir/<label with / -> _>/`` plus ``manifest.json`` and ``contact.png``.

    Each pair directory appears whole or not at all, replacing one an earlier render left there (named in one
    line on stderr, as are its pairs this render leaves in place); ``manifest.json`` is written last, so a
    stopped render has none. ``written`` collects the pair directories written so far (what a stop kept).

    ``frames`` (lists of altitudes, highest first) renders multi-frame directories of the
    scenario instead of its pairs. ``camera`` replaces the scenario's camera (e.g. a smaller
    sensor with the same FOV); ``scene=None`` renders on :func:`default_scene`; ``sun=None``
    uses the library scene's sun for this seed (or the scenario's). ``max_cells`` bounds each
    terrain raster (a larger window gets a coarser cell); ``raster="tiles"`` draws each view from
    rasters per image tile at the tile's own GSD (docs/scenes.md). ``workers`` renders frames
    in that many single-threaded processes (default: CPU count).
    """
    check_max_cells(max_cells)
    check_raster(raster)
    specs = load_trajectory(spec, camera)
    name = specs[0].scenario
    if frames:
        specs = [frames_at(name, f, camera) for f in frames]
    elif pairs:
        known = {s.label: s for s in specs}
        missing = [p for p in pairs if p not in known]
        if missing:
            raise TrajectoryError(f"unknown pair(s) {missing}; this scenario has {list(known)}")
        specs = [known[p] for p in pairs]
    check_distinct_dirs([s.label for s in specs], "pairs")  # the later pair would overwrite the earlier
    check_reported_poses(specs, seed, pose_error)  # not after minutes of rendering, when the pair is written
    if sun is not None:
        check_sun(sun)  # an azimuth the pair reader refuses, before rendering
    scene_spec = scene if scene is not None else default_scene(name)
    sc = scene_spec if isinstance(scene_spec, Scene) else load_scene(scene_spec, seed, name)
    sun = sun or library.scene_sun(sc, name, seed)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.time()
    poses = [p for ps in specs for p in ps.poses]
    cam = specs[0].camera
    if any(ps.camera != cam for ps in specs):
        raise TrajectoryError("all pairs of a scenario must share one camera")
    views = render_views(
        sc,
        cam,
        poses,
        sun,
        supersample=supersample,
        workers=workers,
        max_cells=max_cells,
        raster=raster,
        hazard_truth=first_frames(specs),
        # the frames are most of the time: one line each in a log (the pairs' lines follow as they are written)
        on_view=lambda k, n: _progress(k, n, "frames", t0, progress),
    )
    entries, thumbs = [], []
    earlier = earlier_render(out)

    def drop_manifest() -> None:
        # an earlier render's manifest would list a mix of its pairs and ours if this one stopped half-way; dropped
        # as the first pair takes its place, not before: a full disk in the first pair left an intact earlier
        # render without its manifest (QA of stop 72)
        (out / "manifest.json").unlink(missing_ok=True)

    k = 0
    for i, ps in enumerate(specs):
        vs, k = views[k : k + len(ps.poses)], k + len(ps.poses)
        pair = assemble_pair(sc, ps, sun, vs, seed=seed, pose_error=pose_error)
        kept: list[str] = []
        d = write_pair_atomic(
            out / ps.label.replace("/", "_"), pair, replace=True, kept=kept, before_rename=drop_manifest
        )
        if kept:  # a `process --out PAIR/out` was made from the frames this render replaced
            names = ", ".join(kept[:5]) + (", ..." if len(kept) > 5 else "")
            sys.stderr.write(
                f"note: render: kept {len(kept)} file(s) of your own in {d}: {names} (made from the frames this "
                "render replaced, if outputs)\n"
            )
        if written is not None:
            written.append(d.name)
        entries.append(
            {
                "label": ps.label,
                "altitude_m": ps.altitude_m,
                "path": d.name,
                "seed": seed,
                "frames": len(ps.poses),
                "hazards_in_scene_pct": pair.meta["hazards_in_scene_pct"],
                "hazard_fraction": pair.meta["hazard_fraction"],
                "altimeter_m": list(pair.altimeter_m),
                "raster_cell_over_target": max(float(v.info["raster_cell_over_target"]) for v in vs),
            }
        )
        thumbs.append((ps.label, pair.images))
        if pair.meta["hazards_in_scene_pct"] is None:
            _warn_no_overlap(ps.label)
        else:
            _warn_degenerate(ps.label, pair, [float(q.position[2]) for q in ps.poses])
        _progress(i + 1, len(specs), ps.label, t0, progress)
    e = library.entry(sc)
    manifest = {
        "format": MANIFEST_FORMAT,
        "scenario": name,
        "scene": sc.params.name,
        "scene_variant": sc.params.variant,
        "scene_spec": sc.params.spec,
        "scene_description": e.description if e else "",
        "scene_params": sc.params.to_dict(),
        "seed": seed,
        "sun": {"azimuth_deg": sun.azimuth_deg, "elevation_deg": sun.elevation_deg},
        "altitude_convention": ALTITUDE_CONVENTION,
        "pose_error": pose_error.to_dict() if pose_error else None,
        "pairs": entries,
    }
    contact_sheet(thumbs, out / "contact.png")
    write_atomic(out / "manifest.json", json_text(manifest))  # strict JSON: NaN as null; last: the render is whole
    _say_replaced(out, earlier, [e["path"] for e in entries])
    return out


def earlier_render(out: Path) -> list[str]:
    """The pair directories an earlier render left in ``out`` (its manifest's, else any with a pair.json)."""
    try:
        doc = json.loads((out / "manifest.json").read_text())
        return [str(e["path"]) for e in doc["pairs"]]
    except (OSError, ValueError, KeyError, TypeError):
        return sorted(p.parent.name for p in out.glob("*/pair.json") if not is_write_leftover(p.parent.name))


def kept_after_stop(out: Path, written: list[str], earlier: list[str] | None = None) -> str:
    """What a stopped render left in ``out``: the frames are rendered first and the pairs written after (each
    whole, never half), so a stop while rendering keeps nothing; render has no resume, so run it again. The pairs
    an earlier render left there and this one did not replace are named: beside ours they read as one descent of
    two seeds (QA of stop 72)."""
    left = [p for p in earlier or [] if p not in written and (out / p / "pair.json").is_file()]
    more = ", ..." if len(left) > 8 else ""
    old = (
        f"; {len(left)} pair(s) of an earlier render are still there, not this one's: {', '.join(left[:8])}{more}"
        if left
        else ""
    )
    if not written:
        gone = "" if not left or (out / "manifest.json").is_file() else " (its manifest.json was removed)"
        return (
            f"render: stopped before any pair was written (frames are rendered first): nothing new in {out}{old}{gone}"
        )
    return (
        f"render: stopped; {len(written)} pair(s) written whole in {out}: {', '.join(written)}; "
        f"no manifest.json (it is written last){old}"
    )


def _say_replaced(out: Path, earlier: list[str], ours: list[str]) -> None:
    """One line when ``out`` held an earlier render: which pairs this one replaced, and which it left in place
    (kept, nothing deleted, but no longer in manifest.json)."""
    replaced = [p for p in ours if p in earlier]
    left = [p for p in earlier if p not in ours and (out / p / "pair.json").is_file()]
    if not replaced and not left:
        return
    parts = [f"replaced {len(replaced)} pair(s) of an earlier render in {out}"] if replaced else []
    if left:
        parts.append(f"left {len(left)} of its pair(s) in place, no longer in manifest.json: {', '.join(left[:8])}")
    sys.stderr.write("note: render: " + "; ".join(parts) + ("" if len(left) <= 8 else ", ...") + "\n")


# a pair whose last frame sees less of frame 0's ground than this is said: little is left to match (a 16-frame
# approach from 1600 m to 150 m at 64 px shared 30 of 4096 pixels, unflagged); a vertical 2:1 pair shares ~25 %
LOW_OVERLAP_PCT = 2.0


# protocol.pairdir.Pair.scale_notes's note on the metres per pixel (its text: the reader gives no code)
SCALE_NOTE = "m per pixel at"


def _warn_degenerate(label: str, pair: Pair, true_z: list[float] | None = None) -> None:
    """One line on stderr per implausible geometry of a rendered pair: a baseline under 1 % of the altitude
    (``--frames 300,299.9999`` rendered "300/300" without a word), frames sharing under :data:`LOW_OVERLAP_PCT`.
    ``true_z``: the frames' true heights; within render's range, no "positions must be in metres" hint."""
    ours = true_z is not None and all(MIN_ALTITUDE_M <= z <= MAX_ALTITUDE_M for z in true_z)
    for note in pair.scale_notes():
        # the reader's pixel-size note tells a user's pair file in km from one in m: this render placed its own
        # frames in metres within the documented altitudes, where a small camera's pixel is simply coarse
        if ours and SCALE_NOTE in note:
            continue
        sys.stderr.write(f"warning: pair {label}: {note}\n")
    share = pair.meta.get("overlap_pct")
    if share is not None and share < LOW_OVERLAP_PCT:
        sys.stderr.write(
            f"warning: pair {label}: its last frame sees only {share:.2g} % of frame 0's pixels' ground: little is "
            "left to recover elevation from\n"
        )


def _warn_no_overlap(label: str) -> None:
    """One line on stderr: the pair's last frame sees none of frame 0's ground (no DEM, no hazards in scene)."""
    sys.stderr.write(
        f"warning: pair {label}: its frames share no ground (the last frame sees none of what frame 0 sees): "
        "hazards_in_scene_pct is null and no elevation can be recovered from it\n"
    )


def contact_sheet(items: list[tuple[str, tuple[np.ndarray, ...]]], path: Path, tile: int = 200) -> Path:
    """PNG grid for people: each entry's first and last frames with its label, two entries per row (a
    multi-frame entry says how many frames it has: "i4 of 4"; an odd count above one ends with a tile that says so)."""
    import cv2

    font, scale = cv2.FONT_HERSHEY_SIMPLEX, 0.45

    def fits(text: str) -> bool:
        return cv2.getTextSize(text, font, scale, 1)[0][0] <= tile - 6

    def labelled(img: np.ndarray, text: str) -> np.ndarray:
        t = cv2.copyMakeBorder(img, 18, 2, 2, 2, cv2.BORDER_CONSTANT, value=0)
        cv2.putText(t, text, (4, 14), font, scale, 255, 1, cv2.LINE_AA)
        return t

    def short(label: str, suffix: str) -> str:
        """A 16-frame label (600/570/.../150) ran into the next tile and lost its "i1 of 16": keep the ends."""
        parts = label.split("/")
        if fits(label + suffix) or len(parts) < 3:
            return label + suffix
        return f"{parts[0]}/.../{parts[-1]}{suffix}"

    cells = []
    for label, imgs in items:
        n = len(imgs)
        row = []
        for k, img in ((0, imgs[0]), (n - 1, imgs[-1])):
            small = cv2.resize(img, (tile, tile), interpolation=cv2.INTER_AREA)
            row.append(labelled(small, short(label, f" i{k + 1}" + (f" of {n}" if n > 2 else ""))))
        cells.append(np.hstack(row))
    if len(cells) % 2 and len(cells) > 1:  # one entry alone is its own row: a filler would take a third of the sheet
        blank = np.full((tile, 2 * tile + 4), 40, np.uint8)
        cells.append(labelled(blank, "(no more pairs)")[:, : cells[0].shape[1]])
    grid = np.vstack([np.hstack(cells[i : i + 2]) for i in range(0, len(cells), 2)])
    cv2.imwrite(str(path), grid, [cv2.IMWRITE_PNG_COMPRESSION, 9])
    return path
