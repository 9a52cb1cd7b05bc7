"""Render descent pairs to pair directories (DESIGN.md format) with ground truth."""

from __future__ import annotations

import json
import sys
import time
import zlib
from pathlib import Path

import numpy as np

from ground_sim.errors import TrajectoryError
from ground_sim.pose_error import PoseError
from ground_sim.render import render_view
from ground_sim.scene import Scene, load_scene
from ground_sim.trajectory import PairSpec, load_trajectory
from protocol.pairdir import Camera, Pair, Sun, write_pair

DEFAULT_SUN = {"vertical": Sun(135.0, 25.0), "approach": Sun(120.0, 25.0)}
ALTITUDE_CONVENTION = (
    "altitude_m is the LOWER frame's altitude above the reference plane, as in "
    "thesis Tables 6.1/6.8 (600/300 is the 300 m row)"
)


def _key(label: str) -> int:
    return zlib.crc32(label.encode())


def render_pair(
    scene: Scene, spec: PairSpec, sun: Sun, *, seed: int = 0, pose_error: PoseError | None = None, supersample: int = 2
) -> Pair:
    """Render both frames of ``spec``; reported poses carry the injected errors, truth is for i1."""
    views = [
        render_view(scene, spec.camera, p, sun, seed=seed * 7919 + _key(spec.label) * 2 + k, supersample=supersample)
        for k, p in enumerate(spec.poses)
    ]
    reported = spec.poses
    meta: dict = {
        "scenario": spec.scenario,
        "label": spec.label,
        "altitude_m": spec.altitude_m,
        "altitude_convention": ALTITUDE_CONVENTION,
        "scene": scene.params.name,
        "scene_seed": scene.seed,
        "seed": seed,
        "true_frames": [p.to_dict(n) for p, n in zip(spec.poses, ("i1.png", "i2.png"))],
        "render": [v.info | {"raster_origin_m": [float(x) for x in v.info["raster_origin_m"]]} for v in views],
    }
    if pose_error is not None:
        rng = np.random.default_rng([seed & 0xFFFFFFFF, _key(spec.label), 0xE77])
        deltas = pose_error.sample(rng)
        reported = (deltas[0].apply(spec.poses[0]), deltas[1].apply(spec.poses[1]))
        meta["pose_error"] = {"distribution": pose_error.to_dict(), "frames": [d.to_dict() for d in deltas]}
    truth = {
        "elevation": views[0].elevation,
        "depth": views[0].depth,
        "shadow": views[0].shadow,
        "hazard": views[0].hazard,
    }
    return Pair(spec.camera, reported, (views[0].image, views[1].image), sun, truth, meta)


def _progress(i: int, n: int, label: str, t0: float, enabled: bool) -> None:
    """Render progress: in place on a terminal, one plain line per frame in a log (no run-on bar)."""
    if not enabled:
        return
    w = 24
    fill = int(w * i / n)
    line = f"render [{'#' * fill}{'.' * (w - fill)}] {i}/{n} {label:<12} {time.time() - t0:6.1f} s"
    if sys.stderr.isatty():
        sys.stderr.write("\r" + line + ("\n" if i == n else ""))
    elif i > 0:
        sys.stderr.write(line + "\n")
    sys.stderr.flush()


def default_scene(scenario: str) -> str:
    """Scene preset a scenario is rendered on unless told otherwise.

    The approach scenario flies over the thesis's safer area (Table 6.8, fewer
    hazards than the vertical descent's Table 6.1 scene); everything else,
    custom trajectories included, uses ``default``.
    """
    return "approach" if scenario == "approach" else "default"


def render_scenario(
    spec: str | Path,
    out_dir: str | Path,
    *,
    scene: str | Path | Scene | None = None,
    seed: int = 0,
    pairs: list[str] | None = None,
    pose_error: PoseError | None = None,
    progress: bool = True,
    sun: Sun | None = None,
    supersample: int = 2,
    camera: Camera | None = None,
) -> Path:
    """Render a scenario to ``out_dir/<label with / -> _>/`` plus ``manifest.json`` and ``contact.png``.

    ``camera`` replaces the scenario's camera (e.g. a smaller sensor with the same FOV);
    ``scene=None`` renders on :func:`default_scene` of the scenario.
    """
    specs = load_trajectory(spec, camera)
    if pairs:
        known = {s.label: s for s in specs}
        missing = [p for p in pairs if p not in known]
        if missing:
            raise TrajectoryError(f"unknown pair(s) {missing}; this scenario has {list(known)}")
        specs = [known[p] for p in pairs]
    name = specs[0].scenario
    sc = scene if isinstance(scene, Scene) else load_scene(scene if scene is not None else default_scene(name), seed)
    sun = sun or DEFAULT_SUN.get(name, Sun(135.0, 25.0))
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    entries, thumbs = [], []
    t0 = time.time()
    _progress(0, len(specs), "", t0, progress)
    for i, ps in enumerate(specs):
        pair = render_pair(sc, ps, sun, seed=seed, pose_error=pose_error, supersample=supersample)
        d = write_pair(out / ps.label.replace("/", "_"), pair)
        entries.append(
            {
                "label": ps.label,
                "altitude_m": ps.altitude_m,
                "path": d.name,
                "seed": seed,
                "hazard_fraction": float(np.mean(pair.truth["hazard"] >= 1.0)),
            }
        )
        thumbs.append((ps.label, pair.images))
        _progress(i + 1, len(specs), ps.label, t0, progress)
    manifest = {
        "format": "hazard-hil-descent/1",
        "scenario": name,
        "scene": sc.params.name,
        "scene_params": sc.params.to_dict(),
        "seed": seed,
        "sun": {"azimuth_deg": sun.azimuth_deg, "elevation_deg": sun.elevation_deg},
        "altitude_convention": ALTITUDE_CONVENTION,
        "pose_error": pose_error.to_dict() if pose_error else None,
        "pairs": entries,
    }
    (out / "manifest.json").write_text(json.dumps(manifest, indent=1) + "\n")
    contact_sheet(thumbs, out / "contact.png")
    return out


def contact_sheet(items: list[tuple[str, tuple[np.ndarray, ...]]], path: Path, tile: int = 200) -> Path:
    """PNG grid for people: each pair as i1 | i2 with its label, two pairs per row."""
    import cv2

    cells = []
    for label, (i1, i2) in items:
        row = []
        for k, img in enumerate((i1, i2)):
            t = cv2.resize(img, (tile, tile), interpolation=cv2.INTER_AREA)
            t = cv2.copyMakeBorder(t, 18, 2, 2, 2, cv2.BORDER_CONSTANT, value=0)
            cv2.putText(t, f"{label} i{k + 1}", (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.45, 255, 1, cv2.LINE_AA)
            row.append(t)
        cells.append(np.hstack(row))
    if len(cells) % 2:
        cells.append(np.zeros_like(cells[0]))
    grid = np.vstack([np.hstack(cells[i : i + 2]) for i in range(0, len(cells), 2)])
    cv2.imwrite(str(path), grid, [cv2.IMWRITE_PNG_COMPRESSION, 9])
    return path
