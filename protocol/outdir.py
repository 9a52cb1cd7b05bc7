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


def _holder_pid(holder: str) -> int | None:
    """The pid in a holder's name ("hazard-hil run (pid 19932)"), if it has one."""
    head, _, tail = holder.rpartition("(pid ")
    return int(tail.rstrip(")")) if head and tail.rstrip(")").isdigit() else None


def _our_line() -> set[int]:
    """This process and its ancestors: a claim under a directory one of them holds is theirs to make (``regress``
    holds OUT while each case's run claims OUT/<case>)."""
    pids, pid = {os.getpid()}, os.getppid()
    while pid > 1 and pid not in pids:
        pids.add(pid)
        try:  # field 4 of /proc/PID/stat, after the parenthesised name (which may hold spaces)
            pid = int(Path(f"/proc/{pid}/stat").read_text().rpartition(")")[2].split()[1])
        except (OSError, ValueError, IndexError):
            break
    return pids


def _refuse_if_held_above(path: Path) -> None:
    """:class:`InputError` when a directory above ``path`` is held by a command outside this process's line: a
    ``render --out RUN/pairs`` replaced the pairs a live ``run --out RUN`` was streaming (stop 63's interrupt QA)."""
    line: set[int] | None = None
    for above in path.resolve().parents:
        if (holder := held_by(above)) is None:
            continue
        line = _our_line() if line is None else line
        if _holder_pid(holder) not in line:
            raise InputError(
                f"{path} is inside {above}, which is being written by {holder}: wait for it to end, or give this "
                "one another --out"
            )


@contextmanager
def claim_out(out: str | Path, command: str) -> Iterator[Path]:
    """Hold ``out`` (created if missing) for ``command`` until the block ends; :class:`InputError` when another
    process holds it, or a directory above it (unless that is this process or one it descends from). Within one
    process, a second claim of a directory already held is refused too. A
    directory this claim created that nothing else was written in is removed at the end (bad input, refused)."""
    path = Path(out)
    _refuse_if_held_above(path)
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


def held_by(path: str | Path) -> str | None:
    """Who holds the directory ``path`` (see :func:`claim_out`), as its holder wrote it, or None: nobody, no lock
    file (none is made), or a file system with no locks (used unguarded, as claim_out does)."""
    try:
        fd = os.open(Path(path) / LOCK_NAME, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)  # a FIFO must not block
    except OSError:
        return None
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except BlockingIOError:
        return _holder(fd)
    except OSError:
        return None
    finally:
        os.close(fd)
    return None


def refuse_if_held(path: str | Path, what: str) -> None:
    """:class:`InputError` when another command holds the directory ``path`` (see :func:`claim_out`), for a
    command that writes one file there and claims nothing (``score --csv``): it wrote into a directory a running
    ``evaluate`` was rewriting. No lock file is made where there is none."""
    if (holder := held_by(path)) is not None:
        raise InputError(f"{what} {path} is being written by {holder}: wait for it to end, or write elsewhere")
