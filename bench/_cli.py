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
one it refuses, so that nothing is rendered or written first. An output file is checked when the arguments are
parsed (``type=out_file``): a path that is a directory, or under a file, or in a directory the script may not
write into, is refused then, not after the work. An :class:`OSError` raised later all the same (a full disk, a
permission changed meanwhile) ends the script with ``SCRIPT: error: cannot write X: reason`` and exit 1: the
arguments were right, the run failed.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import NoReturn

from protocol.errors import InputError, os_error_text

__all__ = [
    "InputError",
    "bounded_int",
    "check_dir",
    "note_cache_dir",
    "out_dir",
    "out_file",
    "out_file_or_empty",
    "out_path",
    "positive_int",
    "prog",
    "run",
    "unknown",
    "write_out",
]


def prog() -> str:
    """The script's name as argparse gives it (``bench_pipeline.py``)."""
    return Path(sys.argv[0]).name


def error_line(exc: BaseException) -> str:
    """One line for an input error or a missing file."""
    text = os_error_text(exc) if isinstance(exc, OSError) and exc.errno is not None else str(exc)
    return " ".join(text.split("\n")).strip() or type(exc).__name__


def run(main: Callable[[], int | None]) -> NoReturn:
    """Exit with ``main()``'s status; an input error or a missing file: one line on stderr and exit 2; any other
    :class:`OSError` (raised late: a full disk, a permission): one line and exit 1. Standard output is line
    buffered meanwhile: a script's result lines are seen as they are printed, also through a pipe or in a file."""
    with contextlib.suppress(AttributeError, ValueError):  # a stream that is no TextIOWrapper: left as it is
        sys.stdout.reconfigure(line_buffering=True)  # type: ignore[union-attr]
    try:
        rc = main()
    except (InputError, FileNotFoundError) as exc:
        print(f"{prog()}: error: {error_line(exc)}", file=sys.stderr)
        raise SystemExit(2) from None
    except OSError as exc:
        print(f"{prog()}: error: {error_line(exc)}", file=sys.stderr, flush=True)
        raise SystemExit(1) from None
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


def bounded_int(lo: int, hi: int) -> Callable[[str], int]:
    """argparse type of a whole number in ``lo..hi``."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a whole number {lo}..{hi}, got {text!r}") from None
        if not lo <= value <= hi:
            raise argparse.ArgumentTypeError(f"must be {lo}..{hi}, got {value}")
        return value

    return parse


def writable_file_problem(path: str | Path) -> str | None:
    """Why a file could not be written at ``path`` (made with its missing directories), or None if it could."""
    p = Path(path)
    if p.is_dir():
        return "is a directory"
    if p.exists():
        return None if os.access(p, os.W_OK) else "cannot write it (permission denied)"
    parent = next((a for a in p.parents if a.exists()), Path("."))
    if not parent.is_dir():
        return f"{parent} is not a directory"
    if not os.access(parent, os.W_OK | os.X_OK):
        return f"cannot write in {parent} (permission denied)"
    return None


def out_file(text: str) -> str:
    """argparse type of a file the script writes (at the end): refused now if it could not be written then."""
    if not text:
        raise argparse.ArgumentTypeError("expected a file name, got ''")
    problem = writable_file_problem(text)
    if problem:
        raise argparse.ArgumentTypeError(f"{text}: {problem}")
    return text


def out_file_or_empty(text: str) -> str:
    """:func:`out_file`, or '' where a script takes '' for "print only, write nothing"."""
    return text if text == "" else out_file(text)


def out_path(text: str) -> Path:
    """:func:`out_file` as a :class:`~pathlib.Path`."""
    return Path(out_file(text))


def out_dir(text: str) -> Path:
    """argparse type of a directory the script makes (if need be) and writes into: refused now if it could not be."""
    p = Path(text)
    if p.exists() and not p.is_dir():
        raise argparse.ArgumentTypeError(f"{text}: not a directory")
    where = p if p.exists() else next((a for a in p.parents if a.exists()), Path("."))
    if not where.is_dir():
        raise argparse.ArgumentTypeError(f"{text}: {where} is not a directory")
    if not os.access(where, os.W_OK | os.X_OK):
        raise argparse.ArgumentTypeError(f"{text}: cannot write in {where} (permission denied)")
    return p


def write_out(path: str | Path, text: str) -> Path:
    """Write ``text`` to the output file ``path`` (an :func:`out_file`), making its missing directories; an error
    names the file (a full disk is said when the file is closed, by an OSError that names none)."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    try:
        p.write_text(text)
    except OSError as exc:
        if exc.filename is not None or exc.errno is None:
            raise
        raise OSError(exc.errno, exc.strerror, str(p)) from exc
    return p


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
