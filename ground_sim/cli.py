"""``hazard-hil render`` (a descent to pair directories) and ``hazard-hil scenes`` (the scene library)."""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path
from typing import Any

from ground_sim.render import DEFAULT_RASTER, RASTERS
from ground_sim.trajectory import MAX_ALTITUDE_M, MIN_ALTITUDE_M


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "render",
        help="render a descent (image pairs + ground truth) to pair directories",
        description="Render a descent scenario: one pair directory per pair (docs/design.md format, with "
        "gt_*_i1.npy and each frame's altimeter range), manifest.json (scene, sun, hazards in scene per "
        "pair) and contact.png. Frames are rendered in a pool of single-threaded processes. Exit 0 when every pair "
        "is written, 1 when a worker died or the system refused a read or write, 2 on bad input, 128 + N when "
        "signal N stopped it (130: Ctrl-C); the pairs written whole are kept and said.",
    )
    p.add_argument("--scenario", required=True, help="vertical, approach, or a .toml/.json trajectory file")
    p.add_argument("--pairs", default=None, help="comma-separated pair labels, e.g. 600/300,400/200")
    p.add_argument(
        "--frames",
        action="append",
        default=None,
        metavar="ALT,ALT,...",
        help="one multi-frame directory (2-16 frames, highest first) at these altitudes along the "
        f"scenario's path ({MIN_ALTITUDE_M:g} m - {MAX_ALTITUDE_M / 1000:g} km), e.g. 300,250,200,150; "
        "repeat for several; not with --pairs",
    )
    p.add_argument("--seed", type=int, default=0, help="scene and noise seed (default 0)")
    p.add_argument(
        "--scene",
        default=None,
        help="library scene (hazard-hil scenes), other preset, name:variant, or .toml file "
        "(default: thesis, in the scenario's variant)",
    )
    p.add_argument(
        "--pose-error",
        default=None,
        help="inject navigation errors into the reported poses (the true ones are kept as true_frames), drawn "
        "with the seed per frame: alt=B and pitch=B uniform in +-B (m, deg), alt_sigma, pitch_sigma, roll_yaw and "
        "lateral Gaussian sds (m, deg); equal_pitch=1 (the default, as thesis 6.3.2) gives every frame frame 0's "
        "pitch draw, which the images cannot see; equal_pitch=0 draws each frame's own. "
        "E.g. alt=0.5,pitch=0.15,equal_pitch=0",
    )
    p.add_argument("--sun", default=None, help="AZ,EL in degrees (default: the scene's sun for this seed)")
    p.add_argument("--supersample", type=int, default=2, help="sub-pixels per axis (default 2)")
    p.add_argument(
        "--max-raster-cells",
        type=int,
        default=None,
        help="terrain raster cells per view or tile (default 1000000, at most 16000000): above it the "
        "raster is coarser than GSD/supersample and finer detail is not rendered (docs/scenes.md)",
    )
    p.add_argument(
        "--raster",
        choices=list(RASTERS),
        default=DEFAULT_RASTER,
        help="tiles (default): one terrain raster per image tile at its own GSD/supersample; view: one per "
        "view, capped, so 512 px views are drawn 1.2-4.2x coarser (the renders before 2026-11-25; "
        "docs/scenes.md)",
    )
    p.add_argument(
        "--image-size",
        type=int,
        default=None,
        metavar="PX",
        help="a square camera of this many px (32-4096) with the thesis camera's 30 deg FOV, in place of the "
        "scenario's camera (a trajectory file's own too; default: the scenario's, 512 px for vertical and approach), "
        "as `run --image-size` renders: smaller is quicker",
    )
    p.add_argument("--workers", type=int, default=None, help="render processes (default: CPU count)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar on stderr")
    p.add_argument("--out", required=True, help="output directory")
    p.set_defaults(func=_run)

    s = subparsers.add_parser(
        "scenes",
        help="list the scene library: parameters, sun, measured hazards in scene",
        description="The named scenes, their parameters, their sun and their ground-truth hazards in scene "
        "(the thesis's Table 6.1/6.8 quantity) per table altitude, median and range over the held-out "
        "seeds, against each scene's documented band. --measure re-measures and rewrites the table.",
    )
    s.add_argument("names", nargs="*", help="scenes to show (default: all)")
    s.add_argument("--measure", action="store_true", help="re-measure the hazard shares and store them")
    s.add_argument(
        "--seeds", type=int, default=None, help="with --measure: held-out seeds to measure (default 10: 1000-1009)"
    )
    s.add_argument(
        "--workers", type=int, default=None, help="with --measure: measurement processes (default: CPU count)"
    )
    s.add_argument("--no-progress", action="store_true", help="with --measure: no progress bar on stderr")
    s.add_argument("--table", default=None, help="hazard-share table to read/write (default: the packaged one)")
    s.add_argument("--json", action="store_true", help="print the library as JSON")
    s.set_defaults(func=_scenes)


def _parse_frames(groups: list[str] | None) -> list[list[float]] | None:
    from ground_sim.errors import TrajectoryError
    from protocol.errors import comma_items

    if not groups:
        return None
    out = []
    for g in groups:
        items = comma_items(g, "--frames")
        try:
            out.append([float(a) for a in items])
        except ValueError:
            raise TrajectoryError(f"--frames: expected comma-separated altitudes, got {g!r}") from None
    return out


# A scene seed is hashed as a signed 64-bit integer, but the sensor noise and the pose errors draw from its low
# 32 bits: seeds 2**32 apart had the same noise and navigation errors (QA of stop 65). 2**32 seeds are more than
# anyone runs, and every seed below keeps its bytes.
MAX_SEED = 2**32


def check_seed(seed: int, option: str = "--seed") -> None:
    """Refuse a seed outside [0, MAX_SEED) as one line (beyond it two seeds would share their noise draws)."""
    from ground_sim.errors import RenderError

    if not 0 <= seed < MAX_SEED:
        raise RenderError(f"{option} must be in [0, 2**32), got {seed}")


def _parse_sun(text: str) -> tuple[float, float]:
    """``AZ,EL`` in degrees; a missing, extra or non-finite value is named (render checks the EL range)."""
    from ground_sim.errors import RenderError

    parts = text.split(",")
    try:
        az, el = (float(v) for v in parts)
    except ValueError:
        raise RenderError(f"--sun: expected AZ,EL in degrees, got {text!r}") from None
    for what, v in (("azimuth", az), ("elevation", el)):
        if not math.isfinite(v):
            raise RenderError(f"--sun: {what} must be a finite number of degrees, got {v}")
    return az, el


def _run(args: argparse.Namespace) -> int:
    from ground_sim.descent import render_scenario
    from ground_sim.errors import RenderError
    from ground_sim.pose_error import PoseError
    from ground_sim.render import MAX_CELLS, check_sun
    from ground_sim.trajectory import check_distinct_dirs
    from protocol.errors import comma_items
    from protocol.outdir import claim_out
    from protocol.pairdir import Sun, square_camera

    check_seed(args.seed)
    pe = PoseError.parse(args.pose_error) if args.pose_error else None
    sun = Sun(*_parse_sun(args.sun)) if args.sun else None
    if sun is not None:  # an azimuth of -400 was rendered, then the pair refused by process
        check_sun(sun, "--sun")
    if args.frames and args.pairs:
        raise RenderError("--frames and --pairs exclude each other")
    if args.workers is not None and args.workers < 1:
        raise RenderError(f"--workers must be >= 1, got {args.workers}")
    if not 1 <= args.supersample <= 8:  # the renderer says so too, but only after creating --out
        raise RenderError(f"--supersample must be 1..8, got {args.supersample}")
    camera = square_camera(args.image_size) if args.image_size is not None else None
    pairs = comma_items(args.pairs, "--pairs") if args.pairs is not None else None
    if pairs is not None and not pairs:  # an empty list would have rendered every pair of the scenario
        raise RenderError(f"--pairs is empty: give pairs like 600/300,300/150, got {args.pairs!r}")
    frames = _parse_frames(args.frames)
    # two pairs with one directory: the second would overwrite the first, with exit 0
    if pairs:
        check_distinct_dirs(pairs, "--pairs")
    if frames:
        check_distinct_dirs(["/".join(f"{a:g}" for a in f) for f in frames], "--frames")
    written: list[str] = []
    from ground_sim.descent import earlier_render, kept_after_stop

    earlier = earlier_render(Path(args.out)) if Path(args.out).is_dir() else []
    try:
        with claim_out(args.out, "render"):  # two renders into one --out replaced each other's pairs, both exit 0
            out = render_scenario(
                args.scenario,
                args.out,
                scene=args.scene or None,
                seed=args.seed,
                pairs=pairs,
                frames=frames,
                pose_error=pe,
                progress=not args.no_progress,
                sun=sun,
                supersample=args.supersample,
                workers=args.workers,
                max_cells=MAX_CELLS if args.max_raster_cells is None else args.max_raster_cells,
                raster=args.raster,
                camera=camera,
                written=written,
            )
    except (KeyboardInterrupt, OSError):  # a stop, or a full disk (said by the caller, in one line)
        print(kept_after_stop(Path(args.out), written, earlier), file=sys.stderr)
        raise
    except BrokenProcessPool:  # a worker killed outright (the OOM killer): one line, as evaluate and landings say it
        print(
            "render: a worker process died (killed, or out of memory): run it again, with fewer --workers if memory "
            f"is short; {kept_after_stop(Path(args.out), written, earlier).split(': ', 1)[1]}",
            file=sys.stderr,
        )
        return 1
    worst = max(e.get("raster_cell_over_target", 1.0) for e in json.loads((out / "manifest.json").read_text())["pairs"])
    if worst > 1.05:
        print(
            f"note: the terrain raster is up to {worst:.1f}x coarser than GSD/{args.supersample} (the raster-size "
            "cap): detail finer than that is in neither the images nor the truth; --raster tiles draws it "
            "(docs/scenes.md)",
            file=sys.stderr,
        )
    print(out / "manifest.json")
    return 0


def _table_doc(path: Path) -> dict[str, Any]:
    """The hazard-share table at ``path`` (empty when absent), checked to be one before it is used."""
    from ground_sim import library as lib
    from ground_sim.errors import SceneError

    if not path.exists():
        return {"scenes": {}, "seeds": []}
    if not path.is_file():
        raise SceneError(f"--table {path}: not a file")
    try:
        doc = lib.load_shares(path)
    except (OSError, UnicodeDecodeError) as exc:
        raise SceneError(f"--table {path}: unreadable ({exc})") from None
    problem = lib.table_problem(doc)  # a bad entry was a traceback of the listing (zero-size array, ...)
    if problem:
        raise SceneError(f"--table {path}: {problem}")
    return doc


def _check_writable(path: Path) -> None:
    """Refuse a table path that cannot be written, before the measurement it would store (minutes of work)."""
    import tempfile

    from ground_sim.errors import SceneError

    parent = path.parent
    if not parent.is_dir():
        raise SceneError(f"--table {path}: directory {parent} does not exist")
    if path.is_dir():
        raise SceneError(f"--table {path}: is a directory")
    if not os.access(path if path.exists() else parent, os.W_OK):
        raise SceneError(f"--table {path}: not writable")
    try:  # the table is written beside itself and renamed over: a file must be creatable in its directory, which
        # os.access does not prove to root (/sys, a read-only file system), as hil_server.cli.check_out_dir does
        with tempfile.TemporaryFile(dir=parent):
            pass
    except OSError as exc:
        why = exc.strerror or str(exc)
        raise SceneError(f"--table {path} cannot be written: no file can be made in {parent} ({why})") from None


def _scenes(args: argparse.Namespace) -> int:
    from ground_sim import library as lib
    from ground_sim.errors import SceneError
    from ground_sim.seeds import HELD_OUT_SEEDS

    known = {e.name: e for e in lib.entries()}
    names = list(dict.fromkeys(args.names)) or list(known)  # `scenes mare mare` listed mare twice
    bad = [n for n in names if n not in known]
    if bad:
        raise SceneError(f"not library scenes: {', '.join(bad)} (library: {', '.join(known)})")
    table_path = Path(args.table or lib.SHARES_PATH)
    if not args.measure:  # they only mean something to a measurement: a listing would ignore them, exit 0
        given = [o for o, v in (("--seeds", args.seeds), ("--workers", args.workers)) if v is not None]
        given += ["--no-progress"] if args.no_progress else []
        if given:
            raise SceneError(f"{', '.join(given)} {'applies' if len(given) == 1 else 'apply'} only with --measure")
    if args.measure:
        n_seeds = 10 if args.seeds is None else args.seeds
        if not 1 <= n_seeds <= len(HELD_OUT_SEEDS):
            raise SceneError(f"--seeds must be 1..{len(HELD_OUT_SEEDS)}, got {n_seeds}")
        if args.workers is not None and args.workers < 1:
            raise SceneError(f"--workers must be >= 1, got {args.workers}")
        _check_writable(table_path)
        old = _table_doc(table_path)  # a broken table is refused now, not after the measurement
        seeds = list(HELD_OUT_SEEDS[:n_seeds])
        conflict = lib.merge_conflict(old, names, seeds)  # was: the other scenes silently dropped from the table
        if conflict:
            raise SceneError(f"--table {table_path}: {conflict}")
        print(f"measuring {len(names)} scene(s) on held-out seeds {seeds[0]}-{seeds[-1]} ...", file=sys.stderr)
        new = lib.measure(names, seeds, workers=args.workers, progress=not args.no_progress)
        doc = lib.merge_shares(old, new)
        from reports.html import write_atomic
        from reports.jsondoc import json_text

        write_atomic(table_path, json_text(doc))  # minutes of measuring: never half a table; NaN as null
    elif args.table and not table_path.exists():
        # without --measure there is nothing to list: every scene would be "not measured", exit 0
        raise SceneError(f"--table {table_path}: no such file")
    table = _table_doc(table_path)
    if args.json:
        from reports.jsondoc import json_text

        print(json_text(lib.describe(names, table)), end="")  # strict JSON: a share without a value is null
        return 0
    print(lib.format_listing(names, table))
    problems = [p for n in names for p in lib.check(known[n], table.get("scenes", {}).get(n))]
    for p in problems:
        print(f"WARNING: {p}", file=sys.stderr)
    return 1 if problems and args.measure else 0
