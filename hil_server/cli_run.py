"""Subcommands ``run``, ``demo`` and ``regress``: end-to-end HIL descents."""
from __future__ import annotations

import argparse
from pathlib import Path

# The demo: a short vertical descent over loopback serial on a flight-computer
# budget, sized to finish well inside two minutes on a 2-core machine.
DEMO_DEFAULTS = {"scenario": "vertical", "link": "serial", "budget": "snapdragon801",
                 "pairs": ["600/300", "300/150", "200/100"]}


def _pairs(text: str | None) -> list[str] | None:
    return [p.strip() for p in text.split(",") if p.strip()] if text else None


def _add_run_options(p: argparse.ArgumentParser, defaults: dict) -> None:
    p.add_argument("--scenario", default=defaults.get("scenario", "vertical"),
                   help="vertical | approach | trajectory FILE")
    p.add_argument("--link", choices=("serial", "zmq"), default=defaults.get("link", "serial"))
    p.add_argument("--budget", default=defaults.get("budget", "host"), help="see `hazard-hil budgets`")
    p.add_argument("--pairs", default=",".join(defaults["pairs"]) if defaults.get("pairs") else None,
                   help="comma-separated pair labels, e.g. 600/300,300/150 (default: all)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--scene", default=None, help="scene preset or TOML file")
    p.add_argument("--preset", choices=("fast", "thesis"), default="fast")
    p.add_argument("--pace", choices=("lockstep", "asap"), default="lockstep")
    p.add_argument("--deadline", type=float, default=None, help="override the budget's deadline (s)")
    p.add_argument("--baud", type=int, default=None, help="override the budget's serial baud rate")
    p.add_argument("--image-size", type=int, default=None, help="render a smaller square camera, same FOV")
    p.add_argument("--manifest", type=Path, default=None,
                   help="stream pairs already rendered by `hazard-hil render` (their manifest.json)")
    p.add_argument("--corrupt", type=float, default=0.0,
                   help="serial only: per-byte drop/flip/duplicate rate injected on the line (e.g. 1e-6)")
    p.add_argument("--out", type=Path, default=Path("out/run"))


def _config(args: argparse.Namespace):
    from hil_server.run import RunConfig

    return RunConfig(scenario=args.scenario, link=args.link, budget=args.budget, out=args.out,
                     pairs=_pairs(args.pairs), seed=args.seed, scene=args.scene, preset=args.preset,
                     pace=args.pace, deadline_s=args.deadline, baud=args.baud, image_size=args.image_size,
                     manifest=args.manifest, corrupt=args.corrupt)


def _cmd_run(args: argparse.Namespace) -> int:
    from hil_server.run import run_descent

    summary = run_descent(_config(args))
    print(f"report: {Path(args.out) / 'report.html'}")
    return 0 if summary["pairs"] and summary["results"] + summary["errors"] == summary["pairs"] else 1


def _cmd_demo(args: argparse.Namespace) -> int:
    from hil_server.budgets import calibrate_host, load_calibration
    from hil_server.run import run_descent

    if load_calibration() is None:  # a budget means an absolute speed only on a calibrated host
        print("demo: this host is not calibrated yet; measuring it once (hazard-hil calibrate)")
        cal = calibrate_host(seconds=2.0)
        print(f"demo: {cal.units_per_s:.1f} reference units/s on {cal.cpu_model}")
    run_descent(_config(args))
    print(f"\nDemo finished. Report: {(Path(args.out) / 'report.html').resolve()}")
    print(f"Summary table: {(Path(args.out) / 'summary.md').resolve()}")
    return 0


def _cmd_regress(args: argparse.Namespace) -> int:
    from hil_server.regress import run_regression

    return run_regression(args.baseline, update=args.update, out=args.out, cases=_pairs(args.cases))


def register(sub) -> None:
    p = sub.add_parser("run", help="end-to-end HIL descent: ground sim -> link -> emulated flight processor")
    _add_run_options(p, {})
    p.set_defaults(func=_cmd_run)

    p = sub.add_parser("demo", help="a short HIL descent over loopback serial with sensible defaults")
    _add_run_options(p, DEMO_DEFAULTS)
    p.set_defaults(func=_cmd_demo, out=Path("out/demo"))

    p = sub.add_parser("regress", help="re-run fixed scenario x budget cases and compare to a baseline")
    p.add_argument("--baseline", type=Path, default=Path("bench/latency_baseline.json"))
    p.add_argument("--update", action="store_true", help="rewrite the baseline with this run's numbers")
    p.add_argument("--cases", default=None, help="comma-separated case names (default: all in the baseline)")
    p.add_argument("--out", type=Path, default=Path("out/regress"))
    p.set_defaults(func=_cmd_regress)
