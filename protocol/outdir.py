"""One command at a time in an output directory.

Two commands writing the same ``--out`` at once undo each other without a word: a run clears ``received/``
and rewrites ``summary.json`` as it starts, and two evaluations merge ``metrics.csv`` by reading it and
writing it back, so one scenario's rows were lost. A command holds an advisory lock (``flock``) on
``OUT/.hazard-hil.lock`` for as long as it writes there; a second one is refused with the holder's name and
pid. The kernel drops the lock when its holder exits, however it exits; a command that ends removes the file,
and one that was killed leaves it, meaning nothing (the next command takes it over).
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


def _lock(path: Path) -> tuple[int, bool]:
    """An open descriptor of ``path / LOCK_NAME`` holding its flock, and whether a lock was had (False: the file
    system has none). A file its holder unlinked as we opened it is opened again: the lock must be on the file
    the path names now, or two commands could each hold a lock, on two files."""
    lock = path / LOCK_NAME
    while True:
        try:
            fd = os.open(lock, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
        except OSError as exc:
            raise InputError(f"cannot write in {path}: {exc.strerror or exc}") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 200, 0).decode("utf-8", "replace").strip() or "another command"
            os.close(fd)
            raise InputError(
                f"{path} is being written by {holder}: wait for it to end, or give this one another --out"
            ) from None
        except OSError as exc:  # a file system without locks: the directory is used unguarded, as before
            if exc.errno not in (errno.ENOLCK, errno.EOPNOTSUPP):
                os.close(fd)
                raise
            return fd, False
        try:
            same = os.stat(lock).st_ino == os.fstat(fd).st_ino
        except FileNotFoundError:
            same = False
        if same:
            return fd, True
        os.close(fd)


@contextmanager
def claim_out(out: str | Path, command: str) -> Iterator[Path]:
    """Hold ``out`` (created if missing) for ``command`` until the block ends; :class:`InputError` when another
    process holds it. Within one process, a second claim of a directory already held is refused too. The lock
    file goes at the end, and so does a directory this claim created that nothing was written in."""
    path = Path(out)
    created = not path.exists()
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"cannot write in {path}: {exc.strerror or exc}") from None
    fd, locked = _lock(path)
    try:
        if locked:
            os.ftruncate(fd, 0)
            os.pwrite(fd, f"hazard-hil {command} (pid {os.getpid()})\n".encode(), 0)
        yield path
    finally:
        if locked:  # unlinked while still held: a command opening it meanwhile finds it gone and opens anew
            with contextlib.suppress(OSError):
                (path / LOCK_NAME).unlink()
        os.close(fd)  # releases the lock
        if created:  # refused before it wrote anything (bad input): no empty directory left behind
            with contextlib.suppress(OSError):
                path.rmdir()  # only if empty
