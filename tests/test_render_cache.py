"""Render caches reuse a pair only if this renderer drew it (ground_sim/render_cache.py)."""

from __future__ import annotations

import hashlib
import json
import math

import numpy as np
import pytest

from ground_sim.descent import render_pair
from ground_sim.render import RENDER_VERSION
from ground_sim.render_cache import render_version, reusable
from ground_sim.scene import load_scene
from ground_sim.trajectory import frames_at
from protocol.pairdir import Camera, Sun, read_pair, write_pair_atomic

# the bytes of one small render (images and truth) for each renderer version
PINNED = {1: "362e0ff796e9ff65", 2: "9042bf4b5299e43e", 3: "9042bf4b5299e43e"}  # 3 changed high views only


def _small_pair():
    f = 32.0 / math.tan(math.radians(15.0))
    cam = Camera(64, 64, f, f, 31.5, 31.5)
    spec = frames_at("vertical", [120.0, 60.0], cam)
    return render_pair(load_scene("default", 3, "vertical"), spec, Sun(135.0, 25.0), seed=3)


@pytest.fixture(scope="module")
def small_pair():
    return _small_pair()


def test_the_render_version_is_bumped_with_the_renderers_output(small_pair):
    h = hashlib.sha256()
    for im in small_pair.images:
        h.update(np.ascontiguousarray(im).tobytes())
    for k in sorted(small_pair.truth):
        h.update(np.ascontiguousarray(small_pair.truth[k]).tobytes())
    assert h.hexdigest()[:16] == PINNED.get(RENDER_VERSION), (
        "the renderer's output changed: bump ground_sim.render.RENDER_VERSION (render caches then draw again)"
        f" and pin {h.hexdigest()[:16]} for it here"
    )
    assert small_pair.meta["render_version"] == RENDER_VERSION


# the same for a view whose slope and roughness truth takes the footprint raster (ground_sim.truth.footprint_planes,
# from version 3): the pair above keeps its view rasters, which hold the 3 m disk
PINNED_FOOTPRINT = {3: "2b06f8bafbca66b2"}


def test_the_render_version_is_bumped_with_the_footprint_truths_output():
    from ground_sim.geometry import look_rotation
    from ground_sim.render import render_view
    from protocol.pairdir import Pose

    f = 32.0 / math.tan(math.radians(15.0))
    cam = Camera(64, 64, f, f, 31.5, 31.5)
    v = render_view(load_scene("default", 3), cam, Pose([0.0, 0.0, 600.0], look_rotation(0.0)), Sun(135.0, 25.0))
    assert v.info["truth_cell_m"] == 0.5 < v.info["raster_cell_m"]
    h = hashlib.sha256()
    for a in (v.image, v.hazard, v.shadow, v.elevation):
        h.update(np.ascontiguousarray(a).tobytes())
    assert h.hexdigest()[:16] == PINNED_FOOTPRINT.get(RENDER_VERSION), (
        "the footprint truth's output changed: bump ground_sim.render.RENDER_VERSION and pin "
        f"{h.hexdigest()[:16]} for it here"
    )


def test_a_current_pair_is_reused_and_a_stale_one_rendered_again(tmp_path, small_pair, capsys):
    d = tmp_path / "cache" / "pair_a"
    assert render_version(d) is None and not reusable(d)
    write_pair_atomic(d, small_pair)
    assert render_version(d) == RENDER_VERSION and reusable(d)
    assert capsys.readouterr().err == ""

    doc = json.loads((d / "pair.json").read_text())
    doc["render_version"] = RENDER_VERSION - 1  # drawn by an older renderer
    (d / "pair.json").write_text(json.dumps(doc))
    assert not reusable(d)
    err = capsys.readouterr().err
    assert "rendering again" in err and f"version {RENDER_VERSION - 1}" in err
    assert not d.exists() and list((tmp_path / "cache").iterdir()) == []  # nothing stale left under the key
    write_pair_atomic(d, small_pair)  # the caller renders it again into the same key
    assert reusable(d) and read_pair(d).meta["render_version"] == RENDER_VERSION


def test_unversioned_and_unreadable_pairs(tmp_path, small_pair):
    d = tmp_path / "old"
    write_pair_atomic(d, small_pair)
    doc = json.loads((d / "pair.json").read_text())
    del doc["render_version"]  # written before versions were recorded: the first versioned renderer
    (d / "pair.json").write_text(json.dumps(doc))
    assert render_version(d) == 1
    (d / "pair.json").write_text("{not json")
    assert render_version(d) == -1 and not reusable(d, quiet=True) and not d.exists()


def test_a_cached_pair_json_that_does_not_parse_is_said_as_such(tmp_path, small_pair, capsys):
    """It was "rendered by renderer version -1, this is 2": a version no renderer had."""
    d = tmp_path / "bad"
    write_pair_atomic(d, small_pair)
    (d / "pair.json").write_text("{bad")
    assert not reusable(d)
    err = capsys.readouterr().err
    assert "its pair.json is unreadable or records no renderer version" in err and "version -1" not in err


def test_a_damaged_pair_is_rendered_again_not_failed_on_every_run(tmp_path, small_pair, capsys):
    """A truncated image in the cache failed every task that read it, and "rerun to retry" could not help."""
    d = tmp_path / "cache" / "pair_b"
    write_pair_atomic(d, small_pair)
    img = d / "i2.png"
    img.write_bytes(img.read_bytes()[:100])  # cut in the middle of its data
    assert not reusable(d)
    err = capsys.readouterr().err
    assert "unreadable (" in err and "rendering again" in err and not d.exists()


def test_a_pair_of_other_scene_parameters_or_render_code_is_drawn_again(tmp_path, small_pair, capsys, monkeypatch):
    """The cache key names the scene, not its parameters, and reuse checked only RENDER_VERSION: an edited preset
    or truth rule served the old renders (and their numbers) with a note that said they were computed again (QA
    65b H2). Each pair now records both fingerprints and is drawn again when either differs."""
    from dataclasses import replace

    from ground_sim import render_cache
    from ground_sim.scene import load_scene_params

    params = load_scene_params("default", "vertical")
    d = tmp_path / "cache" / "pair_c"
    write_pair_atomic(d, small_pair)
    assert reusable(d, scene=params) and capsys.readouterr().err == ""

    edited = replace(params, terrain=replace(params.terrain, rms_relief_m=params.terrain.rms_relief_m * 3))
    assert not reusable(d, scene=edited) and not d.exists()
    err = capsys.readouterr().err
    assert "drawn from other scene parameters" in err and "rendering again" in err and len(err.splitlines()) == 1

    write_pair_atomic(d, small_pair)
    monkeypatch.setattr(render_cache, "render_code_fingerprint", lambda: "0123456789abcdef")  # truth.py edited
    assert not reusable(d, scene=params) and not d.exists()
    err = capsys.readouterr().err
    assert "drawn by other render or truth code" in err and "this is 0123456789abcdef" in err


def test_pairs_from_before_the_fingerprints_are_drawn_again_or_trusted_by_bench_with_one_warning(
    tmp_path, small_pair, capsys, monkeypatch
):
    """A study cache without fingerprints cannot vouch for its scene: drawn again, said. bench/'s caches (hours of
    renders) may trust theirs: reused, with one warning for the run, not one per pair or directory."""
    from ground_sim import render_cache
    from ground_sim.scene import load_scene_params

    monkeypatch.setattr(render_cache, "_TRUSTED_SAID", [])

    params = load_scene_params("default", "vertical")

    def unrecorded(d):
        write_pair_atomic(d, small_pair)
        doc = json.loads((d / "pair.json").read_text())
        del doc["render_code"], doc["scene_params"]
        (d / "pair.json").write_text(json.dumps(doc))

    unrecorded(tmp_path / "study" / "p")
    assert not reusable(tmp_path / "study" / "p", scene=params)
    assert "rendered before pairs recorded their scene and render-code fingerprints: rendering again" in (
        capsys.readouterr().err
    )
    for name in ("a", "b", "other/c"):
        unrecorded(tmp_path / "bench" / name)
    names = ("a", "b", "a", "other/c")
    assert all(reusable(tmp_path / "bench" / n, scene=params, trust_unrecorded=True) for n in names)
    err = capsys.readouterr().err.splitlines()
    assert (
        len(err) == 1
        and err[0].startswith(f"warning: {tmp_path / 'bench'}: pairs rendered before")
        and ("reused unchecked" in err[0])
    )


def test_the_render_fingerprint_covers_every_module_a_render_runs():
    """A module the renderer, the scene or the truth imports but the fingerprint leaves out would serve stale
    renders after it changed: the list is checked against their imports (those deliberately left out named)."""
    import ast
    from pathlib import Path

    from ground_sim.render_cache import RENDER_SOURCES

    root = Path(__file__).resolve().parents[1] / "ground_sim"
    # messages, pools, seed sets, the cache itself, and pose errors (never applied to a cached render)
    outside = {"errors", "parallel", "seeds", "render_cache", "pose_error"}
    seen, todo = set(), ["descent", "render", "truth", "scene"]
    while todo:
        mod = todo.pop()
        if mod in seen:
            continue
        seen.add(mod)
        for n in ast.walk(ast.parse((root / f"{mod}.py").read_text())):
            if isinstance(n, ast.ImportFrom) and n.module and n.module.startswith("ground_sim."):
                todo.append(n.module.split(".")[1])
    assert {f"{m}.py" for m in seen - outside} == set(RENDER_SOURCES)


def test_the_render_fingerprint_follows_code_not_its_docstrings_or_comments():
    """Whole files redrew every cache for a reworded message or comment in descent.py or library.py (review of
    stop 65); a changed constant or statement still changes it."""
    from ground_sim.render_cache import code_text

    base = 'def f(x):\n    """Doc."""\n    # why\n    return x + 1\n'
    assert code_text(base) == code_text('def f(x):\n    """Other words."""\n    return x+1  # another why\n')
    assert code_text(base) != code_text('def f(x):\n    """Doc."""\n    return x + 2\n')
    assert code_text(base) != code_text('def f(x):\n    """Doc."""\n    return x - 1\n')
