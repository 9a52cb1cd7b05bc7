"""Multi-frame pair directories from `render`, the altimeter range, and frames rendered in a process pool."""

import itertools
import json
import math

import numpy as np
import pytest

from ground_sim.descent import render_scenario
from ground_sim.errors import TrajectoryError
from ground_sim.pose_error import PoseError
from ground_sim.scene import load_scene
from ground_sim.trajectory import frames_at
from protocol.pairdir import Camera, read_pair

F96 = 48.0 / math.tan(math.radians(15.0))
CAM = Camera(96, 96, F96, F96, 47.5, 47.5)


def _ground(scene, info, x, y):
    """Height of the renderer's ground at (x, y): bilinear in the frame's raster (same grid and band limit)."""
    x0, y0 = info["raster_origin_m"]
    c = info["raster_cell_m"]
    j, i = math.floor((x - x0) / c), math.floor((y - y0) / c)
    H, _ = scene.raster(x0 + j * c, y0 + i * c, c, 2, 2)
    fx, fy = (x - x0) / c - j, (y - y0) / c - i
    return (H[0, 0] * (1 - fx) + H[0, 1] * fx) * (1 - fy) + (H[1, 0] * (1 - fx) + H[1, 1] * fx) * fy


@pytest.mark.parametrize("scenario", ["vertical", "approach"])
def test_multi_frame_render_round_trips_with_true_altimeter_ranges(tmp_path, scenario):
    alts = [300.0, 250.0, 200.0, 150.0]
    pe = PoseError(altitude_uniform_m=0.5)
    # one raster per view, whose grid the render info gives: the ground is rebuilt below on that grid (a tiled
    # frame's range ends on its centre tile's finer raster; test_ground_sim holds it to the capped one, flat)
    out = render_scenario(
        scenario,
        tmp_path,
        frames=[alts],
        camera=CAM,
        seed=1000,
        pose_error=pe,
        progress=False,
        workers=1,
        raster="view",
    )
    man = json.loads((out / "manifest.json").read_text())
    assert man["pairs"][0]["frames"] == 4 and man["pairs"][0]["label"] == "300/250/200/150"
    pair = read_pair(out / man["pairs"][0]["path"])
    assert pair.n_frames == 4 and len(pair.altimeter_m) == 4
    spec = frames_at(scenario, alts, CAM)
    sc = load_scene(man["scene_spec"], 1000)
    true = pair.meta["true_frames"]
    assert [f["position_m"][2] for f in true] == alts  # frame 0 highest, ordered by time
    assert all(b["time_s"] > a["time_s"] for a, b in itertools.pairwise(true))
    assert len(pair.meta["pose_error"]["frames"]) == 4
    for k, (pose, alt_m) in enumerate(zip(spec.poses, pair.altimeter_m)):
        # the range ends on the true ground - the bilinear surface through the frame's terrain raster,
        # rebuilt here around the hit - along the optical axis
        X = pose.position + alt_m * pose.optical_axis
        assert abs(_ground(sc, pair.meta["render"][k], X[0], X[1]) - X[2]) < 2e-3, k
        # and nothing is hit before it: the ray stays above the (band-limited) terrain until then
        band = 2.0 * pair.meta["render"][k]["raster_cell_m"]
        t = np.linspace(0.0, alt_m - 3 * band, 400)
        P = pose.position + t[:, None] * pose.optical_axis
        assert np.all(P[:, 2] > sc.height(P[:, 0], P[:, 1], band))
        assert np.array_equal(pair.poses[k].R, pose.R) and pair.poses[k].position[2] != pose.position[2]
    if scenario == "vertical":  # nadir: the range is the height above the ground right below
        assert pair.altimeter_m[-1] == pytest.approx(150.0 - _ground(sc, pair.meta["render"][3], 0.0, 0.0), abs=2e-3)
    assert pair.meta["hazards_in_scene_pct"] == man["pairs"][0]["hazards_in_scene_pct"]


def test_frames_option_is_checked():
    with pytest.raises(TrajectoryError, match="decreasing"):
        frames_at("vertical", [100, 200])
    with pytest.raises(TrajectoryError, match="2-16"):
        frames_at("vertical", [100])
    with pytest.raises(TrajectoryError, match="vertical or approach"):
        frames_at("custom.toml", [200, 100])
    p = frames_at("approach", [600, 300, 150])
    offs = [round(math.degrees(math.acos(-q.optical_axis[2]))) for q in p.poses]
    assert offs == [49, 40, 40]


@pytest.mark.slow
def test_pool_renders_the_same_bytes_as_one_process(tmp_path):
    a = render_scenario("vertical", tmp_path / "a", pairs=["400/200", "200/100"], camera=CAM, progress=False, workers=1)
    b = render_scenario("vertical", tmp_path / "b", pairs=["400/200", "200/100"], camera=CAM, progress=False, workers=2)
    for label in ("400_200", "200_100"):
        pa, pb = read_pair(a / label), read_pair(b / label)
        assert all(np.array_equal(x, y) for x, y in zip(pa.images, pb.images))
        assert all(np.array_equal(pa.truth[k], pb.truth[k]) for k in pa.truth)
        assert pa.altimeter_m == pb.altimeter_m
    # the shared 200 m frame is rendered once but keeps each pair's own sensor noise
    lower, upper = read_pair(a / "400_200").images[1], read_pair(a / "200_100").images[0]
    assert not np.array_equal(lower, upper) and np.mean(np.abs(lower.astype(int) - upper.astype(int))) < 2.0
