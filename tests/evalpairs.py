"""Rendered pairs as ``bench/eval_flight.py`` renders them, for tests that need real descent imagery."""

from __future__ import annotations

import copy
import functools
import pickle
from pathlib import Path

from sessioncache import made_once

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
    name = f"{scenario}_{scene}_s{seed}_{label.replace('/', '-')}_{image_px or 'default'}px.pickle"

    def render(path: Path) -> None:
        path.write_bytes(pickle.dumps(_render(scenario, scene, seed, label, image_px), pickle.HIGHEST_PROTOCOL))

    return pickle.loads(made_once(PAIR_CACHE[0], name, render).read_bytes())
