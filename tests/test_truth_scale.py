"""The slope and roughness truth at the footprint's scale (ground_sim.truth.footprint_planes): the exact LSQ plane
over the 3 m disk, wherever the view raster is too coarse to hold the disk (docs/scenes.md, accuracy item 6)."""

import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest

from ground_sim.geometry import look_rotation
from ground_sim.render import render_view
from ground_sim.scene import Scene, load_scene, parse_scene
from ground_sim.truth import TRUTH_CELL_M, disk_kernels, footprint_cell, footprint_planes, hazard_layers
from protocol.pairdir import Camera, Pose, Sun

F128 = 64.0 / math.tan(math.radians(15.0))
CAM = Camera(128, 128, F128, F128, 63.5, 63.5)
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))


@pytest.fixture(scope="module")
def oblique():
    """The thesis scene (seed 1000) seen from 1200 m at 45 deg with its sun, a view that takes the footprint raster
    for its truth: (scene, pose, sun, view), rendered once for the tests that read it (none changes it)."""
    sc = load_scene("thesis", 1000)
    pose = Pose([0.0, -1500.0, 1200.0], look_rotation(45.0))
    sun = Sun(135.0, 25.0)
    return sc, pose, sun, render_view(sc, CAM, pose, sun, noise=False)


@pytest.fixture(scope="module")
def vertical_80m():
    """The thesis scene (seed 1000) seen straight down from 80 m under a high sun, a view that keeps its view raster
    for the truth: (scene, view), rendered once for the tests that read it (none changes it)."""
    sc = load_scene("thesis", 1000)
    return sc, render_view(sc, CAM, Pose([0.0, 0.0, 80.0], look_rotation(0.0)), Sun(0.0, 89.0), noise=False)


def _surface(x, y):
    return np.sin(x / 1.3) * 0.8 + np.cos(y / 0.9) * x / 10.0 + 0.05 * x


def _heights(x0, y0, cell, nx, ny):
    xs, ys = x0 + np.arange(nx) * cell, y0 + np.arange(ny) * cell
    return _surface(xs[None, :], ys[:, None])


def test_the_plane_is_the_least_squares_plane_over_the_disk_at_every_node():
    rng = np.random.default_rng(5)
    cell = TRUTH_CELL_M
    X = np.round(rng.uniform(-40, 40, 60) / cell) * cell  # on nodes: no interpolation between them
    Y = np.round(rng.uniform(-40, 40, 60) / cell) * cell
    z, a, b, c = footprint_planes(_heights, X, Y)
    n, kz, _, _ = disk_kernels(cell)
    off = np.arange(-n, n + 1) * cell
    dx, dy = (m[kz > 0] for m in np.meshgrid(off, off))
    assert dx.size == 29  # the 3 m disk on 0.5 m cells
    for k in range(X.size):
        zz = _surface(X[k] + dx, Y[k] + dy)
        (pa, pb, pc), *_ = np.linalg.lstsq(np.column_stack([np.ones_like(dx), dx, dy]), zz, rcond=None)
        assert (a[k], b[k], c[k]) == pytest.approx((pa, pb, pc), abs=1e-9)
        assert z[k] == pytest.approx(_surface(X[k], Y[k]), abs=1e-12)


def test_the_truth_does_not_depend_on_the_strips_and_a_plane_is_exact():
    rng = np.random.default_rng(6)
    X, Y = rng.uniform(-300, 300, 5000), rng.uniform(-300, 300, 5000)
    one = footprint_planes(_heights, X, Y, strip_cells=10_000_000)
    many = footprint_planes(_heights, X, Y, strip_cells=20_000)  # dozens of strips
    for p, q in zip(one, many):
        assert np.abs(p - q).max() < 1e-9
    z, a, b, c = footprint_planes(_plane, X, Y)
    assert np.abs(b - 0.3).max() < 1e-9 and np.abs(c + 0.1).max() < 1e-9 and np.abs(z - a).max() < 1e-9
    with pytest.raises(ValueError, match="finite"):
        footprint_planes(_heights, np.array([0.0, np.nan]), np.array([0.0, 1.0]))
    with pytest.raises(ValueError, match="holds no 3 m disk"):
        disk_kernels(2.0)


def _plane(x0, y0, cell, nx, ny):
    xs, ys = x0 + np.arange(nx) * cell, y0 + np.arange(ny) * cell
    return 5.0 + 0.3 * xs[None, :] - 0.1 * ys[:, None]


def _boulder_scene() -> Scene:
    doc = {
        "terrain": {"rms_relief_m": 0.0, "micro_rms_m": 0.0},
        "craters": {"coef": 0.0},
        "boulders": {"coef": 0.0, "rim_density_m2": 0.0},
        "albedo": {"sigma": 0.0},
        "feature": [
            {"kind": "boulder", "x_m": x, "y_m": y, "diameter_m": 2.5, "height_m": 0.8}
            for x in (-12.0, -4.0, 4.0, 12.0)
            for y in (-12.0, -4.0, 4.0, 12.0)
        ],
    }
    return Scene(parse_scene(doc, "test"), 0)


def test_a_high_view_sees_the_footprint_scale_hazards_a_low_view_sees():
    """The same ground gets the same truth from 80 m (a 0.15 m view raster) and from 800 m (a 1.7 m view raster,
    whose 3x3 fallback plane spans 5 m and whose band limit smooths a 2.5 m boulder away)."""
    sc, sun = _boulder_scene(), Sun(0.0, 89.0)  # no shadow: slope and roughness only
    low = render_view(sc, CAM, Pose([0.0, 0.0, 80.0], look_rotation(0.0)), sun, noise=False)
    high = render_view(sc, CAM, Pose([0.0, 0.0, 800.0], look_rotation(0.0)), sun, noise=False)
    assert low.info["raster_cell_m"] <= TRUTH_CELL_M < high.info["raster_cell_m"]
    assert low.info["truth_cell_m"] == low.info["raster_cell_m"] and high.info["truth_cell_m"] == TRUTH_CELL_M
    # the low view's truth at each high pixel's ground point (its nearest pixel centre)
    lx, ly = low.world_xy[..., 0], low.world_xy[..., 1]
    step = float(lx[0, 1] - lx[0, 0])
    hx, hy = high.world_xy[..., 0], high.world_xy[..., 1]
    j = np.rint((hx - lx[0, 0]) / step).astype(int)
    i = np.rint((hy - ly[0, 0]) / float(ly[1, 0] - ly[0, 0])).astype(int)
    inside = (j >= 0) & (j < 128) & (i >= 0) & (i < 128) & (np.maximum(np.abs(hx), np.abs(hy)) < 16.0)
    assert inside.sum() >= 80
    ref = low.hazard[i[inside], j[inside]] >= 1.0
    got = high.hazard[inside] >= 1.0
    assert ref.sum() >= 10  # the boulders' flanks
    assert np.mean(got[ref]) > 0.8 and np.mean(got == ref) > 0.97  # the view-raster truth: 5 of 16, 89 %


def test_a_high_oblique_view_takes_its_slope_truth_at_the_footprint_scale(oblique):
    sc, _, _, v = oblique
    cell = v.info["truth_cell_m"]
    assert v.info["raster_cell_m"] > 2 * cell and cell == 1.0  # a 128 px camera: 0.5 m would take 436 cells a pixel
    X, Y = (v.world_xy[..., k].ravel().astype(np.float64) for k in (0, 1))
    planes = footprint_planes(lambda *a: sc.raster(*a)[0], X, Y, cell)
    fine = hazard_layers(*planes, v.shadow.ravel()).reshape(128, 128)
    assert np.mean((fine >= 1.0) == (v.hazard >= 1.0)) > 0.999


@pytest.mark.parametrize(
    "view_cell,m2_per_pixel,expect",
    [
        (0.3, 27.0, None),  # the view raster holds the disk
        (3.4, 27.0, 0.5),  # a 512 px view at 2400 m on the approach
        (3.4, 100.0, 1.0),  # 0.5 and 0.75 m would cost 400 and 178 cells a pixel
        (6.0, 437.0, None),  # a 128 px camera there: no footprint raster fits, the view raster stays
        (0.7, 40.0, None),  # the only cell that fits (0.75 m) is no finer than the view's
    ],
)
def test_the_truth_cell_is_the_finest_that_the_view_affords(view_cell, m2_per_pixel, expect):
    assert footprint_cell(view_cell, m2_per_pixel) == expect


def test_every_table_view_of_both_scenarios_takes_its_truth_at_half_a_metre():
    """The 0.5 m truth on every 512 px table view: its ground per pixel stays inside the budget, with room for a
    scene whose ground lies 50 m lower (deep-crater) or higher."""
    from ground_sim.geometry import ground_footprint
    from ground_sim.trajectory import load_trajectory
    from ground_sim.truth import TRUTH_CELLS_PER_PIXEL

    worst = 0.0
    for scenario in ("vertical", "approach"):
        for spec in load_trajectory(scenario):
            for pose in spec.poses:
                for z in (-50.0, 50.0):
                    x, y = ground_footprint(spec.camera, pose, z).T
                    m2 = 0.5 * abs(float(np.dot(x, np.roll(y, 1)) - np.dot(y, np.roll(x, 1))))
                    m2 /= spec.camera.width * spec.camera.height
                    assert footprint_cell(10.0, m2) == TRUTH_CELL_M
                    worst = max(worst, m2 / TRUTH_CELL_M**2)
    assert 100 < worst < TRUTH_CELLS_PER_PIXEL  # the approach's 2400 m view is the widest


def test_evaluate_takes_the_renderers_slope_and_roughness_truth():
    """`evaluate`'s slope and roughness truth (its slope/roughness errors and FN causes) is the renderer's rule:
    with the old rule (a 3x3 block of GSD cells) it missed the boulders' flanks the hazard truth holds."""
    from studies.evaluate import truth_slope_roughness

    sc = _boulder_scene()
    v = render_view(sc, CAM, Pose([0.0, 0.0, 800.0], look_rotation(0.0)), Sun(0.0, 89.0), noise=False)
    world = np.dstack([v.world_xy, v.elevation]).astype(np.float64)
    assert v.info["truth_cell_m"] == TRUTH_CELL_M < v.info["raster_cell_m"]
    unsafe = v.hazard >= 1.0
    assert unsafe.sum() >= 10
    for view in (v.info, None):
        slope, rough = truth_slope_roughness(sc, world, 3.35, view=view)
        called = (slope >= 15.0) | (rough >= 0.30)
        if view is None:
            assert np.mean(called[unsafe]) < 0.5  # the old rule
        else:
            assert np.mean(called[unsafe]) > 0.95 and np.mean(called == unsafe) > 0.999


@pytest.mark.parametrize("altitude", [80.0, 4000.0])
def test_evaluate_takes_the_renderers_view_raster_where_it_keeps_one(altitude):
    """Where a render keeps its view raster for the truth (a fine view, or a small camera high up), `evaluate`
    fits on the render's own raster and reproduces the hazard truth; with a cell of the GSD it disagreed with it on
    a third of a 128 px view's pixels at 1000-2400 m (QA of stop 67)."""
    import json

    from studies.evaluate import recorded_truth_planes, truth_slope_roughness

    sc = load_scene("thesis", 1000)
    v = render_view(sc, CAM, Pose([0.0, 0.0, altitude], look_rotation(0.0)), Sun(0.0, 89.0), noise=False)
    assert v.info["truth_cell_m"] == v.info["raster_cell_m"]
    world = np.dstack([v.world_xy, v.elevation]).astype(np.float64)
    view = json.loads(json.dumps(v.info))  # as pair.json holds it
    slope, rough = truth_slope_roughness(sc, world, v.info["raster_cell_m"], view=view)
    called = (slope >= 15.0) | (rough >= 0.30)
    X, Y = (v.world_xy[..., k].ravel().astype(np.float64) for k in (0, 1))
    planes = recorded_truth_planes(sc, view, X, Y)
    assert planes is not None
    again = hazard_layers(*planes, v.shadow.ravel()).reshape(v.hazard.shape)
    assert np.array_equal(again >= 1.0, v.hazard >= 1.0)  # the renderer's truth, every pixel
    lit = ~v.shadow
    assert np.mean(called[lit] == (v.hazard[lit] >= 1.0)) > 0.98
    if altitude > 1000:  # the old cell of the GSD
        gsd = float(np.nanmedian(np.hypot(*np.gradient(v.world_xy[..., 0]))))
        slope, rough = truth_slope_roughness(sc, world, gsd)
        old = (slope >= 15.0) | (rough >= 0.30)
        assert np.mean(old[lit] == (v.hazard[lit] >= 1.0)) < 0.95


@pytest.mark.parametrize(
    "damage",
    [
        {"raster_cell_m": None},
        {"raster_origin_m": ["0", 0]},
        {"raster_origin_m": [float("nan"), 0.0]},
        {"raster_shape": [10**6, 10**6]},  # a stranger's pair.json: memory is bounded before it is spent
        {"raster_shape": [3, 3]},  # does not hold the points
        {"raster_shape": "big"},
        {"truth_cell_m": 1e-6},  # a 65 TiB raster
        {"truth_cell_m": 0.02},  # no cell the renderer takes: its cost grows as 1/cell^2
        {"truth_cell_m": 0.5, "raster_cell_m": 10**400},  # valid JSON
        {"raster_origin_m": [10**400, 0]},
    ],
)
def test_a_render_record_that_is_not_whole_falls_back_to_the_scene(damage, vertical_80m):
    from studies.evaluate import recorded_truth_planes

    sc, v = vertical_80m
    X, Y = (v.world_xy[..., k].ravel().astype(np.float64) for k in (0, 1))
    assert recorded_truth_planes(sc, v.info, X, Y) is not None
    assert recorded_truth_planes(sc, v.info | damage, X, Y) is None


@pytest.mark.parametrize(
    "record, cell",
    [
        ({"raster_cell_m": 3.4, "truth_cell_m": 0.5}, 0.5),
        ({"raster_cell_m": 0.4, "truth_cell_m": 0.4}, None),  # the truth on the view raster itself
        ({"raster_cell_m": 0.4, "truth_cell_m": None}, None),  # a later frame: no truth taken
        ({"raster_cell_m": 3.4}, None),  # renderer version 2
        ({"raster_cell_m": 10**400, "truth_cell_m": 0.5}, None),
        ({"raster_cell_m": True, "truth_cell_m": 0.5}, None),
        ({"raster_cell_m": 3.4, "truth_cell_m": -1.0}, None),
    ],
)
def test_one_predicate_says_where_a_render_took_its_truth_finer_than_its_view(record, cell, tmp_path):
    """evaluate's planes and fit_psafe's labels ask the same question of the record (stop 68's leftover)."""
    from fit_psafe import footprint_truth

    from studies.evaluate import footprint_truth_cell

    assert footprint_truth_cell(record) == cell
    (tmp_path / "pair.json").write_text(json.dumps({"render": [record]}))
    assert footprint_truth(str(tmp_path)) is (cell is not None)


def test_a_frame_without_hazard_truth_keeps_every_other_byte_and_its_pair_keeps_frame_0s_truth(oblique):
    from ground_sim.descent import render_views

    sc, pose, sun, full = oblique  # takes the footprint raster (test above)
    bare = render_view(sc, CAM, pose, sun, noise=False, hazard_truth=False)
    for k in ("image", "elevation", "depth", "shadow", "world_xy", "radiance"):
        assert np.array_equal(getattr(full, k), getattr(bare, k)), k
    assert np.isnan(bare.hazard).all() and np.isfinite(full.hazard).all()
    assert bare.info["truth_cell_m"] is None and full.info["truth_cell_m"] == 1.0
    # a pose two pairs share is drawn once, with the truth if any of them needs it
    a, b = render_views(sc, CAM, [pose, pose], sun, hazard_truth=[False, True])
    assert np.array_equal(a.hazard, full.hazard) and b is a
    with pytest.raises(ValueError, match="2 poses"):
        render_views(sc, CAM, [pose, pose], sun, hazard_truth=[True])


def test_a_multi_frame_render_draws_the_truth_of_frame_0_only(tmp_path):
    import json

    from ground_sim.descent import render_scenario

    render_scenario("approach", tmp_path, frames=[[2400, 2000, 1200]], camera=CAM, progress=False, workers=1)
    (d,) = [p for p in tmp_path.iterdir() if p.is_dir()]
    views = json.loads((d / "pair.json").read_text())["render"]
    assert views[0]["truth_cell_m"] is not None and [v["truth_cell_m"] for v in views[1:]] == [None, None]
    assert np.isfinite(np.load(d / "gt_hazard_i1.npy")).all()


@pytest.mark.parametrize("altitude", [80.0, 1000.0])
def test_evaluate_reproduces_a_view_raster_renders_truth(altitude):
    """A render drawn from one raster per view (``raster="view"``) took its roughness from the pixel's own hit, not
    the raster's height: `evaluate` takes the same (review of stop 68: 7 of 16 384 pixels flipped otherwise)."""
    from studies.evaluate import recorded_truth_planes

    sc = load_scene("thesis", 1000)
    pose = Pose([0.0, -altitude, altitude], look_rotation(45.0))
    v = render_view(sc, CAM, pose, Sun(135.0, 25.0), noise=False, raster="view")
    X, Y = (v.world_xy[..., k].ravel().astype(np.float64) for k in (0, 1))
    planes = recorded_truth_planes(sc, v.info, X, Y, Z=v.elevation.ravel())
    assert planes is not None
    again = hazard_layers(*planes, v.shadow.ravel()).reshape(v.hazard.shape)
    assert np.array_equal(again >= 1.0, v.hazard >= 1.0)
    assert np.max(np.abs(again - v.hazard)) < 1e-3
