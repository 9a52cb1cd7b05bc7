"""``hazard-hil budgets`` and ``hazard-hil calibrate``: processor budgets and host calibration."""
from __future__ import annotations

import argparse
import sys


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("budgets", help="list processor budgets and the duty cycle each means on this host",
                              description="List the processor budgets (hil_server/budgets.toml) with the CPU duty "
                                          "cycle each one means on this host.")
    p.add_argument("--file", default=None, help="budget file (default: the packaged budgets.toml)")
    p.add_argument("--sources", action="store_true", help="also print where each figure comes from")
    p.set_defaults(func=_budgets)

    c = subparsers.add_parser("calibrate", help="measure this host's single-core speed and store it",
                              description="Run the reference workload (plane-sweep image operations) on one "
                                          "thread and store this host's speed for the budgets.")
    c.add_argument("--seconds", type=float, default=3.0, help="CPU seconds to measure (default 3)")
    c.add_argument("--file", default=None, help="budget file whose anchor to report against")
    c.set_defaults(func=_calibrate)


def _budgets(args: argparse.Namespace) -> int:
    import warnings

    from hil_server.budgets import UncalibratedWarning, calibration_path, load_budgets, load_calibration

    budgets = load_budgets(args.file)
    cal = load_calibration()
    anchor = next(iter(budgets.values())).anchor
    if cal is None:
        print(f"warning: this host is not calibrated; assuming the anchor's {anchor.dmips:.0f} DMIPS "
              "(run `hazard-hil calibrate`)", file=sys.stderr)
        host_dmips = anchor.dmips
    else:
        host_dmips = cal.host_dmips(anchor)
        print(f"host: {cal.cpu_model} on {cal.hostname}, {host_dmips:.0f} DMIPS per core "
              f"(calibrated {cal.measured_at}, {calibration_path()})")
    print(f"{'budget':<15}{'DMIPS':>8}{'duty':>9}{'slower':>8}{'memory':>10}{'deadline':>10}  {'link':<16}description")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UncalibratedWarning)  # said once above
        for b in budgets.values():
            dmips = "host" if b.is_host else f"{b.cpu_dmips:.0f}"
            link = b.link if b.baud is None else f"{b.link} {b.baud}"
            duty = b.duty_fraction(cal)
            print(f"{b.name:<15}{dmips:>8}{duty:>9.2%}{1 / duty:>7.1f}x{b.memory_mib:>6} MiB{b.deadline_s:>9g}s"
                  f"  {link:<16}{b.description}")
            if args.sources:
                print(f"{'':<15}source: {b.source}")
    return 0


def _calibrate(args: argparse.Namespace) -> int:
    from hil_server.budgets import calibrate_host, calibration_path, load_budgets

    from hil_server.budgets import BudgetError

    if not 0 < args.seconds <= 600:
        raise BudgetError(f"--seconds must be in (0, 600], got {args.seconds:g}")
    anchor = next(iter(load_budgets(args.file).values())).anchor
    print(f"measuring the reference workload for ~{args.seconds:g} CPU seconds on one thread...")
    cal = calibrate_host(seconds=args.seconds)
    print(f"{cal.units_per_s:.2f} units/s (spread p10-p90 {cal.spread:.0%}); anchor {anchor.units_per_s:g} units/s "
          f"= {anchor.dmips:.0f} DMIPS -> this host {cal.host_dmips(anchor):.0f} DMIPS per core")
    print(f"stored for {cal.key} in {calibration_path()}")
    return 0
