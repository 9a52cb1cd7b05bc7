"""Rendered pairs as ``bench/eval_flight.py`` renders them, for tests that need real descent imagery."""

from __future__ import annotations

import copy
import functools

from ground_sim import trajectory
from ground_sim.descent import DEFAULT_SUN, render_pair
from ground_sim.library import scene_sun
from ground_sim.scene import load_scene
from protocol.pairdir import Camera, Pair


def eval_pair(scenario: str, scene: str, seed: int, label: str, image_px: int | None = None) -> Pair:
    """The pair ``label`` (e.g. ``"600/300"``) of ``scenario`` over ``scene``: the `thesis` scene under its
    own sun (``ground_sim.library.scene_sun``), a preset scene under the scenario's default sun; ``image_px``:
    a square thesis camera of that size (default the scenario's 512 px).

    Rendered once per test process (a render is deterministic; the oblique 1000/500 takes ~9 s); each call gets
    a copy of its own, so a test that changes its pair changes no other test's."""
    return copy.deepcopy(_rendered(scenario, scene, seed, label, image_px))


@functools.lru_cache(maxsize=4)
def _rendered(scenario: str, scene: str, seed: int, label: str, image_px: int | None) -> Pair:
    camera = None if image_px is None else Camera.thesis(image_px)
    spec = next(s for s in getattr(trajectory, scenario)(camera) if s.label == label)
    if scene == "thesis":
        sc = load_scene(scene, seed, scenario)
        return render_pair(sc, spec, scene_sun(sc, scenario, seed), seed=seed)
    return render_pair(load_scene(scene, seed), spec, DEFAULT_SUN[scenario], seed=seed)
