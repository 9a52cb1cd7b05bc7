"""One command at a time in an output directory.

Two commands writing the same ``--out`` at once undo each other without a word: a run clears ``received/``
and rewrites ``summary.json`` as it starts, and two evaluations merge ``metrics.csv`` by reading it and
writing it back, so one scenario's rows were lost. A command holds an advisory lock (``flock``) on
``OUT/.hazard-hil.lock`` for as long as it writes there; a second one is refused with the holder's name and
pid. The kernel drops the lock when its holder exits, however it exits.

The file stays in ``OUT`` (it names the last command that wrote there). Unlinked at release, a command that
had just opened it would lock a file no path names, and over NFS a held file that goes away gives stale
handles. Only a directory the claim itself created and nothing else was written in is removed again.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from protocol.errors import InputError

LOCK_NAME = ".hazard-hil.lock"
NO_LOCKS = (errno.ENOLCK, errno.EOPNOTSUPP, errno.EINVAL, errno.ENOSYS)  # file systems that offer no flock


def _open(path: Path) -> int:
    lock = path / LOCK_NAME
    try:
        return os.open(lock, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
    except PermissionError:
        if lock.exists():  # left by a command of another user
            raise InputError(
                f"{lock} is not yours to lock (a command of another user wrote in {path}): remove it, or give this "
                "one another --out"
            ) from None
        raise InputError(f"cannot write in {path}: permission denied") from None
    except OSError as exc:
        raise InputError(f"cannot write in {path}: {exc.strerror or exc}") from None


def _holder(fd: int) -> str:
    """Who holds the lock file open on ``fd``, as its holder wrote it ("hazard-hil evaluate (pid N)")."""
    try:
        return os.pread(fd, 200, 0).decode("utf-8", "replace").strip() or "another command"
    except OSError:
        return "another command"


def _lock(path: Path) -> tuple[int, bool]:
    """An open descriptor of ``path / LOCK_NAME`` holding its flock, and whether a lock was had (False: the file
    system has none)."""
    fd = _open(path)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        try:
            holder = _holder(fd)
        finally:
            os.close(fd)
        raise InputError(
            f"{path} is being written by {holder}: wait for it to end, or give this one another --out"
        ) from None
    except OSError as exc:
        if exc.errno in NO_LOCKS:  # the directory is used unguarded, as before
            return fd, False
        os.close(fd)
        raise InputError(f"cannot lock {path / LOCK_NAME}: {exc.strerror or exc}") from None
    return fd, True


@contextmanager
def claim_out(out: str | Path, command: str) -> Iterator[Path]:
    """Hold ``out`` (created if missing) for ``command`` until the block ends; :class:`InputError` when another
    process holds it. Within one process, a second claim of a directory already held is refused too. A
    directory this claim created that nothing else was written in is removed at the end (bad input, refused)."""
    path = Path(out)
    created = not path.exists()
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"cannot write in {path}: {exc.strerror or exc}") from None
    fd, locked = _lock(path)
    try:
        if locked:
            with contextlib.suppress(OSError):  # the name is for people; the lock holds without it
                os.ftruncate(fd, 0)
                os.pwrite(fd, f"hazard-hil {command} (pid {os.getpid()})\n".encode(), 0)
        yield path
    finally:
        try:
            if created:  # nothing but the lock file in a directory made for this command: it goes
                with contextlib.suppress(OSError):
                    if [p.name for p in path.iterdir()] == [LOCK_NAME]:
                        (path / LOCK_NAME).unlink()
                        path.rmdir()
        finally:
            os.close(fd)  # releases the lock


def refuse_if_held(path: str | Path, what: str) -> None:
    """:class:`InputError` when another command holds the directory ``path`` (see :func:`claim_out`), for a
    command that writes one file there and claims nothing (``score --csv``): it wrote into a directory a running
    ``evaluate`` was rewriting. No lock file is made where there is none."""
    lock = Path(path) / LOCK_NAME
    try:
        fd = os.open(lock, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)  # a FIFO by that name must not block
    except OSError:
        return  # no lock file (or none readable): nobody claimed it
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except BlockingIOError:
        raise InputError(
            f"{what} {path} is being written by {_holder(fd)}: wait for it to end, or write elsewhere"
        ) from None
    except OSError:
        return  # a file system with no locks: used unguarded, as claim_out does
    finally:
        os.close(fd)
