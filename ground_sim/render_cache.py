"""Render caches: reuse a rendered pair directory only if this renderer drew it.

Studies keep renders between runs (``hazard-hil landings --cache``, ``evaluate``'s ``OUT/*/cache``,
``bench/eval_flight.py --cache``), keyed by everything the render depends on: scene, seed, scenario,
pair, sun, camera, raster. The renderer's own code is not in that key, so a renderer change would
score the flight software against stale images and truth without a word. Each pair records
:data:`ground_sim.render.RENDER_VERSION` in its ``pair.json`` meta; a cached pair with another
version is removed and rendered again, and the caller is told. So is a damaged one (an image or a
truth array cut off or corrupt): that check reads the files' structure, not their pixels, so a cache
hit costs one decode of the pair, the caller's.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import sys
from pathlib import Path
from typing import Any

import numpy as np

from ground_sim.render import RENDER_VERSION
from protocol.pairdir import NPY_FAULTS, npy_fault

# pairs written before the version was recorded were drawn by the renderer of version 1
UNVERSIONED = 1


def _read_meta(pair_dir: Path) -> tuple[int | None, Any]:
    """``(renderer version, parsed pair.json)``: ``(None, None)`` without a pair.json, version -1 when it is
    unreadable or records no usable version."""
    path = pair_dir / "pair.json"
    if not path.is_file():
        return None, None
    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError):
        return -1, None  # unreadable: as stale as it gets
    v = doc.get("render_version", UNVERSIONED) if isinstance(doc, dict) else -1
    return (int(v) if isinstance(v, int) and not isinstance(v, bool) else -1), doc


def render_version(pair_dir: str | Path) -> int | None:
    """The renderer version a cached pair was drawn with; None when there is no complete pair there."""
    return _read_meta(Path(pair_dir))[0]


class _OtherLayout(Exception):
    """A file the renderer does not write this way: the decoder judges it (:func:`_read_whole`)."""


def _npy_damage(path: Path, shape: tuple[int, int]) -> str | None:
    """Why the .npy at ``path`` would not load as a ``shape`` array, or None; reads its header only. Raises
    :class:`_OtherLayout` for a format version ``np.save`` writes only for exotic dtypes."""
    fmt = np.lib.format
    try:
        with path.open("rb") as f:
            version = fmt.read_magic(f)
            if version not in ((1, 0), (2, 0)):
                raise _OtherLayout
            read = fmt.read_array_header_1_0 if version == (1, 0) else fmt.read_array_header_2_0
            got, _, dtype = read(f)
            start = f.tell()
    except NPY_FAULTS as exc:
        return f"header unreadable ({npy_fault(exc)})"
    if dtype.hasobject:
        return "holds Python objects"  # np.load(allow_pickle=False) refuses it
    if tuple(got) != shape:
        return f"shape {tuple(got)} != image shape {shape}"
    need = start + math.prod(got) * dtype.itemsize
    have = path.stat().st_size
    return None if have >= need else f"cut off ({have} of {need} bytes)"


def _damage(pair_dir: Path, doc: Any) -> str | None:
    """Why the cached pair in ``pair_dir`` (``doc`` its parsed pair.json) cannot be read, or None.

    The layout the renderer writes (PNG frames, .npy truth) is checked from the files' structure: each
    image whole as the reader checks it (:func:`protocol.pairdir.png_damage`: its chunks, its pixel stream
    inflated) and its size the camera's, each truth file's header against its length and the camera. The
    images are not decoded nor the truth arrays loaded, so a cache hit decodes them once, when the caller
    loads the pair. Anything else is read whole (:func:`protocol.pairdir.read_pair`).
    pair.json's own content is the renderer's: ``write_pair`` validated the pair before writing it.
    """
    from protocol.pairdir import FORMAT, MAX_FRAMES, MIN_FRAMES, PNG_MAGIC, TRUTH_FILES, png_damage

    try:
        if doc["format"] != FORMAT:
            raise _OtherLayout
        size = (int(doc["camera"]["width"]), int(doc["camera"]["height"]))
        names = [fr["image"] for fr in doc["frames"]]
        if not MIN_FRAMES <= len(names) <= MAX_FRAMES:
            raise _OtherLayout
        root = pair_dir.resolve()
        for name in names:
            path = (pair_dir / name).resolve()  # a name that is no path (not a str) raises TypeError
            if not name or not path.is_relative_to(root) or not path.is_file():
                raise _OtherLayout  # read_pair says which and how
            try:
                data = path.read_bytes()
            except OSError as exc:
                return f"{path}: not a readable image ({exc.strerror or exc})"
            if data[:8] != PNG_MAGIC:
                raise _OtherLayout
            # inflated as the reader does (so both refuse the same files), not decoded: a hit decodes once, later
            why = png_damage(data, size=size)
            if why is not None:
                return f"{path}: not a readable image ({why})"
        for fname in TRUTH_FILES.values():
            path = pair_dir / fname
            if path.is_file() and (why := _npy_damage(path, (size[1], size[0]))) is not None:
                return f"{path}: unreadable ({why})"
    except (_OtherLayout, KeyError, TypeError, ValueError, OverflowError):
        return _read_whole(pair_dir)
    return None


def _read_whole(pair_dir: Path) -> str | None:
    """Why :func:`protocol.pairdir.read_pair` refuses the pair, or None (it decodes every file)."""
    from protocol.pairdir import PairFormatError, read_pair

    try:
        read_pair(pair_dir)
    except (PairFormatError, OSError, ValueError) as exc:
        return str(exc).splitlines()[0] if str(exc) else type(exc).__name__
    return None


def unreadable(pair_dir: str | Path) -> str | None:
    """Why the pair in ``pair_dir`` cannot be read (a truncated or corrupt image, a truncated truth file), or
    None; see :func:`_damage` for what is checked without decoding."""
    d = Path(pair_dir)
    doc = _read_meta(d)[1]
    return _read_whole(d) if doc is None else _damage(d, doc)


def reusable(pair_dir: str | Path, *, quiet: bool = False) -> bool:
    """True when ``pair_dir`` holds a readable pair this renderer drew. A stale or unreadable one is removed
    (so the caller renders it again, e.g. with ``write_pair_atomic``) and a one-line note goes to stderr: a
    damaged cache entry would otherwise fail every run that reads it, and "rerun to retry" could not help."""
    d = Path(pair_dir)
    v, doc = _read_meta(d)  # read once: its version, then what it names
    if v is None:
        return False
    why = (
        f"rendered by renderer version {v}, this is {RENDER_VERSION}"
        if v >= 0
        else "its pair.json is unreadable or records no renderer version"  # "version -1" read as a real one
    )
    if v == RENDER_VERSION:
        broken = _damage(d, doc)
        if broken is None:
            return True
        why = f"unreadable ({broken})"
    # aside first, then delete: a concurrent reader never sees a half-deleted pair under the cache key
    aside = d.with_name(f"{d.name}.stale{os.getpid()}")
    try:
        os.replace(d, aside)
    except OSError:
        v, doc = _read_meta(d)
        if v == RENDER_VERSION and _damage(d, doc) is None:  # another process re-rendered it
            return True
        raise
    shutil.rmtree(aside, ignore_errors=True)
    if not quiet:
        print(f"note: {d}: {why}: rendering again", file=sys.stderr)
    return False
