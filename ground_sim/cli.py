"""``hazard-hil render``: render a descent scenario to pair directories."""

from __future__ import annotations

import argparse


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "render",
        help="render a descent (image pairs + ground truth) to pair directories",
        description="Render a descent scenario: one pair directory per pair "
        "(DESIGN.md format, with gt_*_i1.npy), manifest.json and contact.png.",
    )
    p.add_argument("--scenario", required=True, help="vertical, approach, or a .toml/.json trajectory file")
    p.add_argument("--pairs", default=None, help="comma-separated pair labels, e.g. 600/300,400/200")
    p.add_argument("--seed", type=int, default=0, help="scene and noise seed (default 0)")
    p.add_argument(
        "--scene",
        default=None,
        help="scene preset (default, approach, flat) or .toml file "
        "(default: 'approach' for the approach scenario, else 'default')",
    )
    p.add_argument(
        "--pose-error",
        default=None,
        help="inject pose errors, e.g. alt=0.5,pitch=0.05,roll_yaw=0,lateral=0,equal_pitch=1",
    )
    p.add_argument("--sun", default=None, help="AZ,EL in degrees (default per scenario)")
    p.add_argument("--supersample", type=int, default=2, help="sub-pixels per axis (default 2)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar on stderr")
    p.add_argument("--out", required=True, help="output directory")
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    from ground_sim.descent import render_scenario
    from ground_sim.errors import RenderError
    from ground_sim.pose_error import PoseError
    from protocol.pairdir import Sun

    pe = PoseError.parse(args.pose_error) if args.pose_error else None
    sun = None
    if args.sun:
        try:
            az, el = (float(v) for v in args.sun.split(","))
        except ValueError:
            raise RenderError(f"--sun: expected AZ,EL in degrees, got {args.sun!r}") from None
        sun = Sun(az, el)
    scene = args.scene or None  # None: the scenario's default scene
    pairs = [s.strip() for s in args.pairs.split(",") if s.strip()] if args.pairs else None
    out = render_scenario(
        args.scenario,
        args.out,
        scene=scene,
        seed=args.seed,
        pairs=pairs,
        pose_error=pe,
        progress=not args.no_progress,
        sun=sun,
        supersample=args.supersample,
    )
    print(out / "manifest.json")
    return 0
