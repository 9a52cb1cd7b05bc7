"""Odd geometries reach the pipeline as results or as one clear FlightInputError, never as a crash.

Seeded random descents: tilts up to 95 deg (views past the horizon), baselines from 5 % to camera 2 above
camera 1, lateral offsets, blank images, tight deadlines on slow emulated processors. A fuzz of 220 such
pairs found three crashes (no shared ground: cv2.remap on an empty grid; a view toward the horizon: a 16 GiB
world grid; a baseline too short for three planes: a ValueError in the thesis flow's sweep).
"""

from __future__ import annotations

import numpy as np
import pytest
from synthetic import make_pair, plane, tilted_R

from flight_sw.anytime import MAX_GRID_CELLS_PER_PIXEL
from flight_sw.pipeline import run_pipeline
from flight_sw.validate import FlightInputError


@pytest.mark.parametrize("seed", range(12))
def test_random_geometry_gives_a_result_or_a_clear_error(seed):
    rng = np.random.default_rng(1000 + seed)
    a1 = float(rng.uniform(20, 800))
    a2 = a1 * float(rng.choice([rng.uniform(0.3, 0.95), 1.0, rng.uniform(1.05, 1.5)]))
    tilt = float(rng.choice([0.0, rng.uniform(0, 60), rng.uniform(60, 95)]))
    off = (float(rng.normal(0, 0.2 * a1)), float(rng.normal(0, 0.2 * a1))) if rng.random() < 0.5 else (0.0, 0.0)
    cam, p1, p2, i1, i2, _ = make_pair(
        64, a1, a2, plane(float(rng.uniform(-20, 20))), seed=seed, R=tilted_R(tilt, str(rng.choice(["x", "y"]))),
        offset2=off,
    )  # fmt: skip
    if rng.random() < 0.2:
        i2 = np.full_like(i2, int(rng.choice([0, 255])))
    for preset in ("fast", "thesis"):
        kw = {"sun_azimuth_deg": float(rng.uniform(0, 360)), "sun_elevation_deg": float(rng.uniform(1, 80))}
        if rng.random() < 0.3:
            kw.update(deadline_s=float(rng.uniform(0.01, 0.5)), time_scale=float(rng.uniform(1, 50)))
        try:
            r = run_pipeline(i1, i2, p1, p2, cam, preset=preset, **kw)
        except FlightInputError as exc:
            assert "\n" not in str(exc)  # one clear line
            continue
        assert r.level in ("image_only", "coarse", "full")
        assert r.grid.state.size <= MAX_GRID_CELLS_PER_PIXEL * i1.size


def _mutations():
    from protocol.pairdir import Camera, Pose

    cam, p1, p2, i1, i2, _ = make_pair(64, 200.0, 100.0, plane(0.0), seed=1)
    c = cam
    yield "NaN altitude", c, p1, Pose(np.array([0.0, 0.0, np.nan]), p2.R), i1, i2
    yield "scaled rotation", c, p1, Pose(p2.position, p2.R * 2.0), i1, i2
    yield "negative focal length", Camera(c.width, c.height, -c.fx, c.fy, c.cx, c.cy), p1, p2, i1, i2
    yield "principal point far off", Camera(c.width, c.height, c.fx, c.fy, 1e6, c.cy), p1, p2, i1, i2
    yield "zero baseline", c, p1, Pose(p1.position.copy(), p1.R), i1, i2
    yield "camera 2 below ground", c, p1, Pose(np.array([0.0, 0.0, -50.0]), p2.R), i1, i2
    yield "wrong image size", c, p1, p2, i1, i2[:, :32]
    yield "NaN image", c, p1, p2, i1.astype(np.float32) * np.nan, i2
    # the pose refinement's blur for a 10^7 GSD ratio asked OpenCV for a kernel it could not allocate
    yield "camera 1 at 10^9 m", c, Pose(np.array([0.0, 0.0, 1e9]), p1.R), p2, i1, i2
    yield "tiny focal length", Camera(c.width, c.height, 1e-6, 1e-6, c.cx, c.cy), p1, p2, i1, i2
    yield "camera 2 100 km away", c, p1, Pose(np.array([1e5, 0.0, 100.0]), p2.R), i1, i2
    # finite but past any descent: the geometry overflowed into NaN parallax inside the sweep
    yield "camera 1 at 1e300 m", c, Pose(np.array([0.0, 0.0, 1e300]), p1.R), p2, i1, i2
    yield "principal point at 1e300 px", Camera(c.width, c.height, c.fx, c.fy, 1e300, c.cy), p1, p2, i1, i2
    yield "focal length 1e300 px", Camera(c.width, c.height, 1e300, 1e300, c.cx, c.cy), p1, p2, i1, i2


@pytest.mark.parametrize("case", list(_mutations()), ids=lambda c: c[0])
@pytest.mark.parametrize("preset", ["fast", "thesis"])
def test_bad_poses_cameras_and_images_give_a_result_or_a_clear_error(case, preset):
    _, cam, p1, p2, i1, i2 = case
    try:
        r = run_pipeline(i1, i2, p1, p2, cam, preset=preset)
    except FlightInputError as exc:
        assert str(exc) and "\n" not in str(exc)
        return
    assert r.level in ("image_only", "coarse", "full")
