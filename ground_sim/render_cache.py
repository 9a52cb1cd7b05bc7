"""Render caches: reuse a rendered pair directory only if what defines it is unchanged.

Studies keep renders between runs (``hazard-hil landings --cache``, ``evaluate``'s ``OUT/*/cache``,
``bench/eval_flight.py --cache``), keyed by scene *name*, seed, scenario, pair, sun, camera, raster. Neither
the scene's parameters (a preset edited under the same name) nor the code that draws the images and the
truth is in that key, so either change would score the flight software against stale images and truth
without a word. Each pair therefore records in its ``pair.json`` meta:

* :data:`ground_sim.render.RENDER_VERSION` (bumped by hand when the output changes),
* ``render_code``: :func:`render_code_fingerprint`, a hash of the ground_sim modules that make renders and
  truth (:data:`RENDER_SOURCES`; not the whole package, so editing e.g. ``stream.py`` keeps every cache),
* ``scene_params``: :func:`scene_fingerprint` of the resolved scene parameters it was drawn from.

A cached pair whose record differs from today's is removed and rendered again, and the caller is told in one
line. A pair from before the fingerprints were recorded is rendered again too, except where the caller
trusts such pairs (``trust_unrecorded``, ``bench/`` only: hours of renders there), said once per process. So
is a damaged one (an image or a truth array cut off or corrupt): that check reads the files' structure, not
their pixels, so a cache hit costs one decode of the pair, the caller's.
"""

from __future__ import annotations

import ast
import dataclasses
import functools
import hashlib
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
# the ground_sim modules whose code decides a render's images and truth (the renderer, terrain, scene, shading,
# truth, trajectories and the pair's assembly); the presets count through the resolved scene parameters
RENDER_SOURCES = (
    "descent.py",
    "features.py",
    "fbm.py",
    "geometry.py",
    "hashing.py",
    "heightfield.py",
    "library.py",
    "render.py",
    "scene.py",
    "shading.py",
    "stamp.py",
    "trajectory.py",
    "truth.py",
)
# the first directory whose unfingerprinted pairs were trusted: said once per process (a bench run reads dozens)
_TRUSTED_SAID: list[Path] = []


def code_text(source: str) -> str:
    """``source`` as its syntax tree, without docstrings, comments or layout: what a fingerprint of code should
    follow. Whole files put a reworded message's or comment's edit in it, and one in ``descent.py`` or
    ``library.py`` (render orchestration, contact sheets, library measurements) redrew every cached render
    (review of stop 65: 32 commits had touched those two files, most of them not the pixels)."""
    tree = ast.parse(source)
    for node in ast.walk(tree):
        body = getattr(node, "body", None)
        if (
            isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef))
            and isinstance(body, list)
            and body
            and isinstance(body[0], ast.Expr)
            and isinstance(body[0].value, ast.Constant)
            and isinstance(body[0].value.value, str)
        ):
            node.body = body[1:] or [ast.Pass()]
    return ast.dump(tree, annotate_fields=False, include_attributes=False)


@functools.cache
def render_code_fingerprint() -> str:
    """SHA-256 (16 hex digits) of :data:`RENDER_SOURCES`' code (:func:`code_text`): a pair drawn by other code is
    drawn again. (Python's own version changes the tree's dump, and so the fingerprint: renders are redrawn once
    after an upgrade.)"""
    root = Path(__file__).parent
    h = hashlib.sha256()
    for name in RENDER_SOURCES:
        h.update(name.encode() + b"\0" + code_text((root / name).read_text()).encode() + b"\0")
    return h.hexdigest()[:16]


def scene_fingerprint(params: Any) -> str:
    """SHA-256 (16 hex digits) of resolved scene parameters (a :class:`ground_sim.scene.SceneParams`): the same
    scene name with other parameters (its preset edited) is another render."""
    doc = params.to_dict() if hasattr(params, "to_dict") else dataclasses.asdict(params)
    text = json.dumps(doc, sort_keys=True, separators=(",", ":"), default=repr)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def render_fingerprints(params: Any) -> dict[str, str]:
    """What a pair drawn today from ``params`` records in its meta (``render_code``, ``scene_params``)."""
    return {"render_code": render_code_fingerprint(), "scene_params": scene_fingerprint(params)}


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


def _stale(doc: Any, v: int, scene: str | None, trust_unrecorded: bool, where: Path) -> str | None:
    """Why the pair whose meta is ``doc`` (renderer version ``v``) is not today's render, or None. ``scene``: the
    :func:`scene_fingerprint` it must record (None: not checked)."""
    if v != RENDER_VERSION:
        if v < 0:  # "version -1" read as a real one
            return "its pair.json is unreadable or records no renderer version"
        return f"rendered by renderer version {v}, this is {RENDER_VERSION}"
    code, params = doc.get("render_code"), doc.get("scene_params")
    if code is None or (scene is not None and params is None):
        if not trust_unrecorded:
            return "rendered before pairs recorded their scene and render-code fingerprints"
        if not _TRUSTED_SAID:
            _TRUSTED_SAID.append(where)
            print(
                f"warning: {where}: pairs rendered before render fingerprints were recorded are reused unchecked, "
                "here and in any other cache directory of this run (a scene preset or the render code changed since "
                "would not be seen; delete them to render again)",
                file=sys.stderr,
                flush=True,
            )
        return None
    if code != render_code_fingerprint():
        now = render_code_fingerprint()
        return f"drawn by other render or truth code (ground_sim render code {code}, this is {now})"
    if scene is not None and params != scene:
        return f"drawn from other scene parameters ({params}, now {scene}: the scene preset changed)"
    return None


def reusable(pair_dir: str | Path, *, quiet: bool = False, scene: Any = None, trust_unrecorded: bool = False) -> bool:
    """True when ``pair_dir`` holds a readable pair drawn by this renderer and render code (and, with ``scene``,
    a :class:`ground_sim.scene.SceneParams` or its :func:`scene_fingerprint`, from these scene parameters). A stale
    or unreadable one is removed (so the caller renders it again, e.g. with ``write_pair_atomic``) and a one-line
    note goes to stderr: a damaged cache entry would otherwise fail every run that reads it, and "rerun to retry"
    could not help. ``trust_unrecorded``: reuse a pair from before the fingerprints were recorded, with a one-line
    warning per process (``bench/`` only)."""
    d = Path(pair_dir)
    want = scene if scene is None or isinstance(scene, str) else scene_fingerprint(scene)
    v, doc = _read_meta(d)  # read once: its version, then what it names
    if v is None:
        return False
    why = _stale(doc, v, want, trust_unrecorded, d.parent)
    if why is None:
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
        if v is not None and _stale(doc, v, want, trust_unrecorded, d.parent) is None and _damage(d, doc) is None:
            return True  # another process re-rendered it
        raise
    shutil.rmtree(aside, ignore_errors=True)
    if not quiet:
        print(f"note: {d}: {why}: rendering again", file=sys.stderr)
    return False
