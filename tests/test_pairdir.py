"""The pair-directory format (shared/DESIGN.md) round-trips and rejects bad input."""

import json

import numpy as np
import pytest

from protocol.pairdir import Camera, Pair, PairFormatError, Pose, Sun, read_pair, write_pair

NADIR = np.diag([1.0, -1.0, -1.0])  # camera looking straight down, x east, y south


def make_pair(seed: int = 0) -> Pair:
    rng = np.random.default_rng(seed)
    cam = Camera.thesis()
    imgs = tuple(rng.integers(0, 256, (512, 512), dtype=np.uint8) for _ in range(2))
    poses = (Pose([0, 0, 600.0], NADIR, 0.0), Pose([0, 0, 300.0], NADIR, 12.5))
    truth = {"elevation": rng.normal(size=(512, 512)).astype(np.float32), "shadow": rng.random((512, 512)) > 0.5}
    return Pair(cam, poses, imgs, Sun(135.0, 20.0), truth, {"scenario": "vertical"})


def test_thesis_camera_matches_eq_3_16():
    cam = Camera.thesis()
    assert cam.fx == pytest.approx(955.405, abs=1e-3)
    assert (cam.cx, cam.cy) == (255.5, 255.5)


def test_round_trip_is_exact(tmp_path):
    pair = make_pair()
    write_pair(tmp_path, pair)
    back = read_pair(tmp_path)
    assert back.camera == pair.camera
    for a, b in zip(back.images, pair.images):
        np.testing.assert_array_equal(a, b)
    for a, b in zip(back.poses, pair.poses):
        np.testing.assert_array_equal(a.position, b.position)
        np.testing.assert_array_equal(a.R, b.R)
        assert a.time_s == b.time_s
    np.testing.assert_array_equal(back.truth["elevation"], pair.truth["elevation"])
    assert back.truth["shadow"].dtype == np.bool_
    assert back.meta == {"scenario": "vertical"}
    assert back.sun == pair.sun


def test_sun_direction_convention():
    # azimuth clockwise from +Y (north) toward +X (east)
    np.testing.assert_allclose(Sun(90.0, 0.0).direction(), [1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(Sun(0.0, 90.0).direction(), [0, 0, 1], atol=1e-12)


@pytest.mark.parametrize(
    "mutate, message",
    [
        (lambda d: d["frames"][0].update(position_m=[0, 0, float("nan")]), "finite"),
        (lambda d: d["frames"][1].update(R_world_to_cam=[[1, 0, 0], [0, 2, 0], [0, 0, 1]]), "orthonormal"),
        (lambda d: d["frames"][1].update(position_m=[0, 0, 900.0]), "below"),
        (lambda d: d.update(format="other/1"), "format"),
        (lambda d: d["camera"].update(width=640), "does not match"),
    ],
)
def test_bad_metadata_is_named(tmp_path, mutate, message):
    write_pair(tmp_path, make_pair())
    doc = json.loads((tmp_path / "pair.json").read_text())
    mutate(doc)
    (tmp_path / "pair.json").write_text(json.dumps(doc))
    with pytest.raises(PairFormatError, match=message):
        read_pair(tmp_path)


def test_missing_files_are_named(tmp_path):
    with pytest.raises(PairFormatError, match=r"pair\.json"):
        read_pair(tmp_path)
    write_pair(tmp_path, make_pair())
    (tmp_path / "i2.png").unlink()
    with pytest.raises(PairFormatError, match=r"i2\.png"):
        read_pair(tmp_path)
