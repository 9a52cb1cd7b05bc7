"""What the bench scripts share on the command line: a bad argument ends a script with one line, not a traceback.

    from _cli import positive_int, run
    ...
    ap.add_argument("--runs", type=positive_int, default=7)
    ...
    if __name__ == "__main__":
        run(main)

:func:`run` calls a script's ``main`` and turns the project's input errors (:class:`protocol.errors.InputError`
and its kinds: ``FlightInputError``, ``PairFormatError``, ``BudgetError``, ``TrajectoryError``,
``EvaluationError``, ...) and a missing file into ``SCRIPT: error: message`` on stderr and exit status 2, as
argparse says a bad option. A script checks its arguments before any work and raises :class:`InputError` for
one it refuses, so that nothing is rendered or written first.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import NoReturn

from protocol.errors import InputError, os_error_text

__all__ = ["InputError", "check_dir", "note_cache_dir", "positive_int", "prog", "run", "unknown"]


def prog() -> str:
    """The script's name as argparse gives it (``bench_pipeline.py``)."""
    return Path(sys.argv[0]).name


def error_line(exc: BaseException) -> str:
    """One line for an input error or a missing file."""
    text = os_error_text(exc) if isinstance(exc, OSError) and exc.errno is not None else str(exc)
    return " ".join(text.split("\n")).strip() or type(exc).__name__


def run(main: Callable[[], int | None]) -> NoReturn:
    """Exit with ``main()``'s status; an input error or a missing file: one line on stderr and exit 2."""
    try:
        rc = main()
    except (InputError, FileNotFoundError) as exc:
        print(f"{prog()}: error: {error_line(exc)}", file=sys.stderr)
        raise SystemExit(2) from None
    raise SystemExit(rc)


def positive_int(text: str) -> int:
    """argparse type of a count: a whole number >= 1."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number >= 1, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {value}")
    return value


def unknown(option: str, given: Iterable[object], valid: Iterable[object]) -> None:
    """Refuse the ``given`` values of ``option`` that are not among ``valid``, naming the valid ones."""
    choices = list(valid)
    bad = [g for g in given if g not in choices]
    if bad:
        listed = ", ".join(repr(c) if isinstance(c, str) else str(c) for c in choices)
        said = ", ".join(repr(b) if isinstance(b, str) else str(b) for b in bad)
        raise InputError(f"{option}: unknown {said}; choose from {listed}")


def check_dir(path: str | Path, option: str) -> Path:
    """``path``, which must be an existing directory (an input the script reads)."""
    p = Path(path)
    if not p.is_dir():
        raise InputError(f"{option} {p}: {'not a directory' if p.exists() else 'no such directory'}")
    return p


def note_cache_dir(path: str | Path, option: str) -> Path:
    """``path``, a cache directory the script fills on demand: if it does not exist yet, say in one line that it
    will be created (so that a mistyped path is seen); one that exists but is no directory is refused."""
    p = Path(path)
    if p.exists() and not p.is_dir():
        raise InputError(f"{option} {p}: not a directory")
    if not p.exists():
        print(f"{prog()}: {option} {p} does not exist yet: it will be created and filled", file=sys.stderr)
    return p
