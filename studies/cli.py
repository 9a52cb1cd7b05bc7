"""``hazard-hil evaluate`` and ``hazard-hil sensitivity``: the thesis's ch. 6 tables and sec 6.3 Monte Carlo."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from protocol.errors import InputError


def _positive(kind: str):
    def conv(text: str) -> int:
        try:
            v = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{kind} must be an integer, got {text!r}") from None
        if v < 1:
            raise argparse.ArgumentTypeError(f"{kind} must be >= 1, got {v}")
        return v

    return conv


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--seeds",
        type=_positive("--seeds"),
        default=None,
        help="number of scene seeds (0..N-1); results are medians over seeds",
    )
    p.add_argument("--out", required=True, type=Path, help="output directory (resumes if it exists)")
    p.add_argument("--cache", type=Path, default=None, help="rendered-pair cache (default OUT/cache)")
    p.add_argument(
        "--scheduler", default=None, help="Dask scheduler address, e.g. tcp://host:8786 (default: local processes)"
    )
    p.add_argument(
        "--workers",
        type=_positive("--workers"),
        default=None,
        help="local worker processes (default: CPU count; 1 = in-process)",
    )
    p.add_argument(
        "--camera-px",
        type=_positive("--camera-px"),
        default=None,
        help="square camera size with the thesis's 30 deg FOV (default 512, the thesis camera)",
    )
    p.add_argument("--altitudes", default=None, help="comma-separated subset of table altitudes [m]")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")


def register(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "evaluate",
        help="score the pipeline against ground truth; thesis tables side by side",
        description="Render (or reuse) a scenario, run the pipeline, score it against "
        "ground truth and print/write the thesis's ch. 6 tables next to ours.",
    )
    p.add_argument("--scenario", required=True, choices=["vertical", "approach"])
    p.add_argument("--preset", choices=["fast", "thesis", "both"], default="both")
    _common(p)
    p.set_defaults(func=_evaluate, seeds_default=2)

    s = subparsers.add_parser(
        "sensitivity",
        help="pose-error Monte Carlo (thesis sec 6.3)",
        description="DEM error increase under pose-knowledge errors on the approach "
        "scenario (Tables 6.12-6.19), relative to perfect knowledge.",
    )
    s.add_argument("--kind", required=True, choices=["altitude", "attitude", "lateral", "rollyaw"])
    s.add_argument("--samples", type=_positive("--samples"), default=20, help="samples per seed and altitude")
    s.add_argument("--preset", choices=["fast", "thesis", "both"], default="both")
    _common(s)
    s.set_defaults(func=_sensitivity, seeds_default=2)


def _parse_alts(text: str | None) -> list[int] | None:
    if text is None:
        return None
    try:
        return [int(float(a)) for a in text.split(",") if a.strip()]
    except ValueError:
        raise InputError(f"--altitudes: expected comma-separated numbers, got {text!r}") from None


def _presets(choice: str) -> list[str]:
    return ["fast", "thesis"] if choice == "both" else [choice]


def _evaluate(args: argparse.Namespace) -> int:
    from studies import evaluate as ev
    from studies import report
    from studies.executor import CampaignError

    seeds = list(range(args.seeds or args.seeds_default))
    try:
        rows = ev.evaluate_scenario(
            args.scenario,
            args.out,
            presets=_presets(args.preset),
            seeds=seeds,
            cache_dir=args.cache,
            camera_px=args.camera_px,
            altitudes=_parse_alts(args.altitudes),
            scheduler=args.scheduler,
            workers=args.workers,
            progress=not args.no_progress,
        )
    except CampaignError as exc:
        print(f"hazard-hil evaluate: {exc}; rerun the same command to retry them", file=sys.stderr)
        return 1
    page = report.evaluation_report(args.out, rows, title=f"hazard-hil evaluate: {args.scenario} scenario")
    print((args.out / "report" / f"tables_{args.scenario}.md").read_text())
    print(f"metrics: {args.out / 'metrics.csv'}\nreport:  {page}")
    return 0


def _sensitivity(args: argparse.Namespace) -> int:
    from studies import evaluate as ev
    from studies import report
    from studies.executor import CampaignError

    seeds = list(range(args.seeds or args.seeds_default))
    alts = _parse_alts(args.altitudes) or list(ev.SENSITIVITY_ALTITUDES)
    try:
        rows = ev.sensitivity_campaign(
            args.kind,
            args.out,
            samples=args.samples,
            seeds=seeds,
            presets=_presets(args.preset),
            cache_dir=args.cache,
            camera_px=args.camera_px,
            altitudes=alts,
            scheduler=args.scheduler,
            workers=args.workers,
            progress=not args.no_progress,
        )
    except CampaignError as exc:
        print(f"hazard-hil sensitivity: {exc}; rerun the same command to retry them", file=sys.stderr)
        return 1
    summ = ev.sensitivity_summary(rows)
    print(report.rows_markdown(summ, list(summ[0]) if summ else []))
    # one page for every study run into this directory, so kinds do not overwrite each other
    sections = []
    for kind in ev.SENSITIVITY_KINDS:
        csv_path = args.out / f"sensitivity_{kind}.csv"
        if not csv_path.is_file():
            continue
        krows = rows if kind == args.kind else ev.read_metrics_csv(csv_path)
        ks = ev.sensitivity_summary(krows)
        plot = report.plot_sensitivity(krows, kind, args.out / "report" / f"sensitivity_{kind}.png")
        sections.append((f"sensitivity: {kind}", report.rows_markdown(ks, list(ks[0]) if ks else []), [plot.name]))
    page = report.write_html(args.out / "report", "hazard-hil sensitivity (thesis sec 6.3)", sections)
    print(f"samples: {args.out / f'sensitivity_{args.kind}.csv'}\nreport:  {page}")
    return 0
