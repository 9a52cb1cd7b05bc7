"""Rendered pairs as ``bench/eval_flight.py`` renders them, for tests that need real descent imagery."""

from __future__ import annotations

import copy
import fcntl
import functools
import os
import pickle
from pathlib import Path

from ground_sim import trajectory
from ground_sim.descent import DEFAULT_SUN, render_pair
from ground_sim.library import scene_sun
from ground_sim.scene import load_scene
from protocol.pairdir import Camera, Pair

# Where the session's workers share their renders (tests/conftest.py sets it; empty: each process renders its own)
PAIR_CACHE: list[Path] = []


def eval_pair(scenario: str, scene: str, seed: int, label: str, image_px: int | None = None) -> Pair:
    """The pair ``label`` (e.g. ``"600/300"``) of ``scenario`` over ``scene``: the `thesis` scene under its
    own sun (``ground_sim.library.scene_sun``), a preset scene under the scenario's default sun; ``image_px``:
    a square thesis camera of that size (default the scenario's 512 px).

    Rendered once per test session (a render is deterministic; the oblique 1000/500 takes ~9 s, and three test
    files render the vertical 600/300), kept per process and shared by the pytest-xdist workers through
    ``PAIR_CACHE``; each call gets a copy of its own, so a test that changes its pair changes no other test's."""
    return copy.deepcopy(_rendered(scenario, scene, seed, label, image_px))


def _render(scenario: str, scene: str, seed: int, label: str, image_px: int | None) -> Pair:
    camera = None if image_px is None else Camera.thesis(image_px)
    spec = next(s for s in getattr(trajectory, scenario)(camera) if s.label == label)
    if scene == "thesis":
        sc = load_scene(scene, seed, scenario)
        return render_pair(sc, spec, scene_sun(sc, scenario, seed), seed=seed)
    return render_pair(load_scene(scene, seed), spec, DEFAULT_SUN[scenario], seed=seed)


@functools.lru_cache(maxsize=4)
def _rendered(scenario: str, scene: str, seed: int, label: str, image_px: int | None) -> Pair:
    if not PAIR_CACHE:
        return _render(scenario, scene, seed, label, image_px)
    root = PAIR_CACHE[0]
    root.mkdir(parents=True, exist_ok=True)
    done = root / f"{scenario}_{scene}_s{seed}_{label.replace('/', '-')}_{image_px or 'default'}px.pickle"
    with open(root / f"{done.name}.lock", "w") as lock:  # pytest-xdist workers share the cache
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not done.is_file():
            part = root / f"{done.name}.part{os.getpid()}"
            part.write_bytes(pickle.dumps(_render(scenario, scene, seed, label, image_px), pickle.HIGHEST_PROTOCOL))
            part.rename(done)
    return pickle.loads(done.read_bytes())
