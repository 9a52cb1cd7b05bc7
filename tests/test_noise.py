"""Image noise (flight_sw/noise.py): the estimate recovers added white noise, and a frame far noisier than the
others is named, in `process` too (a 30-grey-level noise image was mapped unsaid, its DEM 3-5x worse)."""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))

from flight_sw.noise import blank_frames, noise_sigma, noisy_frames
from hil_server.cli import main


@pytest.mark.parametrize("sd", [2.0, 8.0, 30.0])
def test_the_estimate_recovers_white_noise_on_a_smooth_scene(sd):
    y, x = np.mgrid[0:256, 0:256].astype(np.float32)
    smooth = 100 + 0.3 * x + 0.2 * y + 20 * np.sin(x / 40.0) * np.cos(y / 55.0)  # ramps and slow waves cancel
    noisy = smooth + np.random.default_rng(int(sd)).normal(0.0, sd, smooth.shape)
    assert noise_sigma(noisy) == pytest.approx(sd, rel=0.08)
    assert noise_sigma(smooth) < 0.3
    assert np.isnan(noise_sigma(np.zeros((2, 9))))
    assert noise_sigma(np.clip(noisy, 0, 255) / 255.0) == pytest.approx(noise_sigma(np.clip(noisy, 0, 255)), rel=1e-4)


def test_a_frame_far_noisier_than_the_others_is_named_and_a_blank_is_no_reference():
    assert noisy_frames([4.5, 30.0]) == [1] and noisy_frames([30.0, 3.5, 4.2, 3.5]) == [0]
    assert noisy_frames([4.0, 9.0, 11.0]) == []  # texture: clean frames of a descent differ by up to 2.9x
    assert noisy_frames([4.0, 0.0]) == []  # a blank partner would make the good frame "noisy"
    assert noisy_frames([4.0, float("nan")]) == [] and noisy_frames([5.0]) == []


def test_a_blank_frame_is_named_and_the_quietest_clean_frames_are_not():
    assert blank_frames([0.0, 2.0]) == [0] and blank_frames([4.0, 3.5, 3.2, 0.0]) == [3]
    assert blank_frames([1.0, 2.9]) == [] and blank_frames([1.0, 1.2, 1.1]) == []  # a polar low sun, a mare
    assert blank_frames([0.0, 0.0]) == [0, 1] and blank_frames([0.5, 0.6]) == []  # nothing to judge against: uniform
    assert blank_frames([0.7, 2.0]) == []  # dim, but over a quarter of the other's


def test_process_warns_of_a_noisy_frame(tmp_path, capsys):
    from hilkit import small_descent

    pair = small_descent(tmp_path / "pairs", ["300/150"], px=256).parent / "300_150"
    assert main(["process", "--no-figures", str(pair), "--out", str(tmp_path / "ok")]) == 0
    assert "noisy" not in capsys.readouterr().err
    info = json.loads((tmp_path / "ok" / "result.json").read_text())["info"]
    assert "noisy_frames" not in info and "blank_frames" not in info
    bad = tmp_path / "bad"
    shutil.copytree(pair, bad)
    img = cv2.imread(str(bad / "i2.png"), cv2.IMREAD_GRAYSCALE).astype(np.float32)
    img += np.random.default_rng(3).normal(0.0, 30.0, img.shape)
    cv2.imwrite(str(bad / "i2.png"), np.clip(img, 0, 255).astype(np.uint8))
    assert main(["process", "--no-figures", str(bad), "--out", str(tmp_path / "o")]) == 0
    err = capsys.readouterr().err
    assert "warning: frame 1's image is noisy: its pixel noise reads ~" in err, err
    (f,) = json.loads((tmp_path / "o" / "result.json").read_text())["info"]["noisy_frames"]
    assert f["frame"] == 1 and f["noise_dn"] > 20 and f["others_dn"][0] < 8


def test_process_names_a_blank_frame_0(tmp_path, capsys):
    """A blank frame 0 left every other frame "could not check" and the maps empty, and nothing named it."""
    from hilkit import small_descent

    pair = small_descent(tmp_path / "pairs", ["300/150"], px=256).parent / "300_150"
    bad = tmp_path / "bad"
    shutil.copytree(pair, bad)
    img = cv2.imread(str(bad / "i1.png"), cv2.IMREAD_GRAYSCALE)
    cv2.imwrite(str(bad / "i1.png"), np.zeros_like(img))
    assert main(["process", "--no-figures", str(bad), "--out", str(tmp_path / "o")]) == 0
    err = capsys.readouterr().err
    assert "warning: frame 0's image is blank: its pixel-scale detail reads 0.0 grey levels against" in err, err
    assert "little or nothing in it can be matched" in err
    (f,) = json.loads((tmp_path / "o" / "result.json").read_text())["info"]["blank_frames"]
    assert f["frame"] == 0 and f["noise_dn"] == 0 and f["others_dn"][0] >= 1.0
