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
PINNED = {1: "362e0ff796e9ff65", 2: "9042bf4b5299e43e"}


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
