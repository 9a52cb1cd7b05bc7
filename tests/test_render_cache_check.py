"""A render-cache hit reads the cached pair once (ground_sim/render_cache.py): the reuse check judges the files
from their structure, as the decoder would, and leaves decoding them to the caller's one read."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from ground_sim.descent import render_pair
from ground_sim.render_cache import reusable, unreadable
from ground_sim.scene import load_scene
from ground_sim.trajectory import frames_at
from protocol.pairdir import Camera, PairFormatError, Sun, read_pair, write_pair_atomic


@pytest.fixture(scope="module")
def small_pair():
    f = 32.0 / math.tan(math.radians(15.0))
    cam = Camera(64, 64, f, f, 31.5, 31.5)
    return render_pair(
        load_scene("default", 3, "vertical"), frames_at("vertical", [120.0, 60.0], cam), Sun(135.0, 25.0), seed=3
    )


def _decodes(d) -> bool:
    """Whether the pair reads whole, every image decoded and every truth array loaded (read_pair)."""
    try:
        read_pair(d)
    except PairFormatError:
        return False
    return True


def test_a_cache_hit_decodes_each_file_once(tmp_path, small_pair, monkeypatch):
    d = tmp_path / "pair"
    write_pair_atomic(d, small_pair)
    calls = {"imdecode": 0, "load": 0}
    imdecode, load = cv2.imdecode, np.load

    def counted_imdecode(*a, **k):
        calls["imdecode"] += 1
        return imdecode(*a, **k)

    def counted_load(*a, **k):
        calls["load"] += 1
        return load(*a, **k)

    monkeypatch.setattr(cv2, "imdecode", counted_imdecode)
    monkeypatch.setattr(np, "load", counted_load)
    assert reusable(d)
    assert calls == {"imdecode": 0, "load": 0}  # the check decodes nothing ...
    pair = read_pair(d)  # ... so the caller's load is the only read: one per image, one per truth array
    assert calls == {"imdecode": pair.n_frames, "load": len(pair.truth)} and len(pair.truth) == 4


def test_the_check_refuses_exactly_what_the_decoder_refuses(tmp_path, small_pair):
    """Every single-bit flip and every cut of an image, and cuts of a truth array: the check calls the pair
    unreadable exactly when reading it whole fails (libpng checks the CRCs of critical chunks but IEND's)."""
    d = tmp_path / "pair"
    write_pair_atomic(d, small_pair)
    img, npy = d / "i2.png", d / "gt_depth_i1.npy"
    png, arr = img.read_bytes(), npy.read_bytes()
    disagree, refused = [], 0
    for i in range(len(png)):
        b = bytearray(png)
        b[i] ^= 1 << (i % 8)
        img.write_bytes(bytes(b))
        verdict = unreadable(d) is not None
        refused += verdict
        if verdict == _decodes(d):
            disagree.append(("flip", i))
    for n in range(len(png)):
        img.write_bytes(png[:n])
        if (unreadable(d) is not None) == _decodes(d):
            disagree.append(("cut", n))
    img.write_bytes(png)
    for n in [*range(160), *range(160, len(arr), 211), len(arr) - 1]:
        npy.write_bytes(arr[:n])
        if (unreadable(d) is not None) == _decodes(d):
            disagree.append(("truth cut", n))
    assert disagree == []
    assert refused > 0.95 * len(png)  # nearly every flip is caught (all but those the decoder lets through)
    npy.write_bytes(arr)
    assert unreadable(d) is None and reusable(d)


@pytest.mark.parametrize("damage", ["flip in an image", "cut truth", "truth of another shape"])
def test_a_damaged_cached_pair_is_rendered_again(tmp_path, small_pair, capsys, damage):
    d = tmp_path / "cache" / "pair"
    write_pair_atomic(d, small_pair)
    if damage == "flip in an image":  # same length: only the CRC tells
        img = d / "i1.png"
        b = bytearray(img.read_bytes())
        b[len(b) // 2] ^= 0x40
        img.write_bytes(bytes(b))
    elif damage == "cut truth":
        npy = d / "gt_hazard_i1.npy"
        npy.write_bytes(npy.read_bytes()[:-7])
    else:
        np.save(d / "gt_shadow_i1.npy", np.zeros((64, 63), bool))
    assert not reusable(d)
    err = capsys.readouterr().err
    assert "unreadable (" in err and "rendering again" in err and not d.exists()


def test_another_image_format_is_judged_by_decoding_it(tmp_path, small_pair):
    """A frame that is not the renderer's PNG (here a PGM under the pair's name) is read whole: kept when it
    decodes, rendered again when it does not."""
    d = tmp_path / "pair"
    write_pair_atomic(d, small_pair)
    img = d / "i2.png"
    ok, pgm = cv2.imencode(".pgm", np.asarray(small_pair.images[1]))
    assert ok
    img.write_bytes(pgm.tobytes())
    assert unreadable(d) is None and reusable(d)
    img.write_bytes(pgm.tobytes()[: len(pgm) // 2])
    assert unreadable(d) is not None and not _decodes(d)
    assert not reusable(d, quiet=True) and not d.exists()
