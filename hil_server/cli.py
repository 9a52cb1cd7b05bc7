"""The ``hazard-hil`` console script.

Each package contributes its subcommands through a module exposing
``register(subparsers)``; this file only assembles them, so packages stay
independent (ground_sim never imports flight_sw and vice versa). Heavy imports
happen inside the command handlers, keeping ``hazard-hil --help`` fast.

A handler is stored as ``func`` on the parsed namespace and returns an exit
code. Errors meant for users are raised as :class:`protocol.errors.InputError`
(or a subclass) and printed as one line, not a traceback.
"""
from __future__ import annotations

import argparse
import importlib
import importlib.util
import sys

from protocol.errors import InputError

# Modules that add subcommands, in help order. A module that does not exist
# yet is skipped; one that exists but fails to import is a real error.
COMMAND_MODULES: tuple[str, ...] = (
    "ground_sim.cli",          # render
    "flight_sw.cli",           # process
    "hil_server.cli_hil",      # budgets, calibrate
    "hil_server.cli_run",      # run, demo, regress
    "hil_server.cli_evaluate", # evaluate, sensitivity
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="hazard-hil",
        description="Hardware-in-the-loop emulation of vision-based hazard detection for planetary landing.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMAND_MODULES:
        if importlib.util.find_spec(name) is None:
            continue
        importlib.import_module(name).register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except InputError as exc:
        print(f"hazard-hil {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
