"""What a test session makes once and its pytest-xdist workers share (tests/conftest.py names the directory)."""

from __future__ import annotations

import fcntl
import os
import shutil
from collections.abc import Callable
from pathlib import Path


def made_once(root: Path, name: str, make: Callable[[Path], None]) -> Path:
    """``root / name``, made by ``make(path)`` the first time any worker asks: under a lock the workers share, into
    a ``.part`` path of its own, renamed when whole (a worker stopped midway leaves no half-made entry)."""
    root.mkdir(parents=True, exist_ok=True)
    done = root / name
    with open(root / f"{name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not done.exists():
            part = root / f"{name}.part{os.getpid()}"
            shutil.rmtree(part, ignore_errors=True)
            make(part)
            part.rename(done)
    return done
