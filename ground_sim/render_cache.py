"""Render caches: reuse a rendered pair directory only if this renderer drew it.

Studies keep renders between runs (``hazard-hil landings --cache``, ``evaluate``'s ``OUT/*/cache``,
``bench/eval_flight.py --cache``), keyed by everything the render depends on: scene, seed, scenario,
pair, sun, camera, raster. The renderer's own code is not in that key, so a renderer change would
score the flight software against stale images and truth without a word. Each pair records
:data:`ground_sim.render.RENDER_VERSION` in its ``pair.json`` meta; a cached pair with another
version is removed and rendered again, and the caller is told.
"""

from __future__ import annotations

import json
import os
import shutil
import sys
from pathlib import Path

from ground_sim.render import RENDER_VERSION

# pairs written before the version was recorded were drawn by the renderer of version 1
UNVERSIONED = 1


def render_version(pair_dir: str | Path) -> int | None:
    """The renderer version a cached pair was drawn with; None when there is no complete pair there."""
    path = Path(pair_dir) / "pair.json"
    if not path.is_file():
        return None
    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError):
        return -1  # unreadable: as stale as it gets
    v = doc.get("render_version", UNVERSIONED) if isinstance(doc, dict) else -1
    return int(v) if isinstance(v, int) and not isinstance(v, bool) else -1


def unreadable(pair_dir: str | Path) -> str | None:
    """Why the pair in ``pair_dir`` cannot be read (a truncated image, a missing truth file), or None."""
    from protocol.pairdir import PairFormatError, read_pair

    try:
        read_pair(pair_dir)
    except (PairFormatError, OSError, ValueError) as exc:
        return str(exc).splitlines()[0] if str(exc) else type(exc).__name__
    return None


def reusable(pair_dir: str | Path, *, quiet: bool = False) -> bool:
    """True when ``pair_dir`` holds a readable pair this renderer drew. A stale or unreadable one is removed
    (so the caller renders it again, e.g. with ``write_pair_atomic``) and a one-line note goes to stderr: a
    damaged cache entry would otherwise fail every run that reads it, and "rerun to retry" could not help."""
    d = Path(pair_dir)
    v = render_version(d)
    if v is None:
        return False
    why = f"rendered by renderer version {v}, this is {RENDER_VERSION}"
    if v == RENDER_VERSION:
        broken = unreadable(d)
        if broken is None:
            return True
        why = f"unreadable ({broken})"
    # aside first, then delete: a concurrent reader never sees a half-deleted pair under the cache key
    aside = d.with_name(f"{d.name}.stale{os.getpid()}")
    try:
        os.replace(d, aside)
    except OSError:
        if render_version(d) == RENDER_VERSION and unreadable(d) is None:  # another process re-rendered it
            return True
        raise
    shutil.rmtree(aside, ignore_errors=True)
    if not quiet:
        print(f"note: {d}: {why}: rendering again", file=sys.stderr)
    return False
