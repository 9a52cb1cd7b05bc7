"""The scene library: calibrated hazard shares within their bands, measured for real, scene properties."""

import csv
import math

import numpy as np
import pytest

from ground_sim import library as lib
from ground_sim.errors import SceneError
from ground_sim.render import render_view, truth_at
from ground_sim.scene import Scene, load_scene, load_scene_params, parse_scene
from ground_sim.seeds import HELD_OUT_SEEDS
from protocol.pairdir import Camera, Pose, Sun

F128 = 64.0 / math.tan(math.radians(15.0))
CAM = Camera(128, 128, F128, F128, 63.5, 63.5)
REQUIRED = {"thesis", "highland", "mare", "polar-low-sun", "deep-crater", "boulder-field"}


def test_library_has_the_required_scenes_with_bands():
    entries = {e.name: e for e in lib.entries()}
    assert set(entries) >= REQUIRED
    for e in entries.values():
        for scen in lib.SCENARIOS:
            assert e.band(scen, 300 if scen == "vertical" else 250) is not None, (e.name, scen)


def test_thesis_targets_are_the_thesis_tables():
    from studies.evaluate import thesis_csv_path

    with thesis_csv_path().open() as fh:
        tab = {
            (r["table"], int(r["altitude_m"])): float(r["value"])
            for r in csv.DictReader(fh)
            if r["metric"] == "hazards_in_scene_pct"
        }
    t = lib.entry("thesis").targets
    assert t["vertical"].tolerance_rel == t["approach"].tolerance_rel == 0.25
    for scen, table in (("vertical", "6.1"), ("approach", "6.8")):
        got = dict(zip(t[scen].altitudes_m, t[scen].hazards_pct))
        want = {a: v for (tb, a), v in tab.items() if tb == table}
        assert got == pytest.approx(want, abs=1e-9)


def test_stored_hazard_shares_are_current_held_out_and_within_every_band():
    """Every scene's ground-truth hazards in scene (median over held-out seeds) lies in its documented band
    at every table altitude of both scenarios; the table was measured with the scenes as they are now."""
    table = lib.load_shares()
    seeds = table["seeds"]
    assert len(seeds) >= 5 and set(seeds) <= set(HELD_OUT_SEEDS)
    for e in lib.entries():
        rec = table["scenes"].get(e.name)
        assert rec is not None, f"{e.name} not measured"
        assert set(rec["scenarios"]) == set(lib.SCENARIOS)
        for per_alt in rec["scenarios"].values():
            assert len(per_alt) == 8 and all(len(v) == len(seeds) for v in per_alt.values())
        assert lib.check(e, rec) == []


def test_band_check_catches_a_share_outside_its_band():
    e = lib.entry("thesis")
    rec = lib.load_shares()["scenes"]["thesis"]
    bad = {**rec, "scenarios": {**rec["scenarios"], "vertical": {**rec["scenarios"]["vertical"], "100": [5.0] * 3}}}
    assert any("vertical 100 m" in p for p in lib.check(e, bad))
    assert any("stale" in p for p in lib.check(e, {**rec, "digest": "0"}))


@pytest.mark.parametrize(
    "spec,scenario,seed_i,alt",
    [
        ("thesis", "vertical", 0, 100),
        ("thesis", "approach", 1, 150),
        ("polar-low-sun", "vertical", 0, 200),
        ("deep-crater", "vertical", 2, 300),
        ("highland", "approach", 0, 250),
        ("boulder-field", "vertical", 1, 75),
    ],
)
def test_stored_shares_are_real_measurements(spec, scenario, seed_i, alt):
    table = lib.load_shares()
    seed = table["seeds"][seed_i]
    stored = table["scenes"][spec]["scenarios"][scenario][str(alt)][seed_i]
    assert lib.measure_one(spec, scenario, seed, alt) == pytest.approx(stored, abs=0.01)


def test_truth_at_is_the_renderers_truth():
    sc = load_scene("thesis", 1000)
    pose = Pose([0.0, 0.0, 120.0], np.diag([1.0, -1.0, -1.0]))
    v = render_view(sc, CAM, pose, Sun(135, 25), noise=False)
    vv, uu = np.mgrid[20:110:3, 30:100:3]
    tr = truth_at(sc, CAM, pose, Sun(135, 25), uu, vv)
    agree = (v.hazard[vv, uu].ravel() >= 1) == (tr["hazard"] >= 1)
    assert agree.mean() >= 0.995
    assert np.median(np.abs(v.elevation[vv, uu].ravel() - tr["elevation"])) < 1e-3


def test_scene_suns_and_the_deep_crater_floor():
    polar, thesis, deep = lib.entry("polar-low-sun"), lib.entry("thesis"), lib.entry("deep-crater")
    els = [polar.sun("vertical", s).elevation_deg for s in HELD_OUT_SEEDS[:20]]
    assert all(2.0 <= e <= 5.0 for e in els) and np.ptp(els) > 1.0
    assert polar.sun("vertical", 1000) == polar.sun("approach", 1000)  # a property of the scene and seed
    assert thesis.sun("vertical", 1000) == Sun(135.0, 25.0) and thesis.sun("approach", 7) == Sun(120.0, 25.0)
    floors = [
        float(load_scene("deep-crater", s).height(np.array([0.0]), np.array([0.0]))[0]) for s in HELD_OUT_SEEDS[:10]
    ]
    assert all(-60.0 <= z <= -30.0 for z in floors) and np.ptp(floors) > 3.0
    assert deep.sun_varies


def test_variants_and_specs():
    base, app = load_scene_params("thesis"), load_scene_params("thesis", "approach")
    assert (base.spec, app.spec) == ("thesis", "thesis:approach")
    assert load_scene_params("thesis:approach") == app
    assert load_scene_params("thesis", "custom") == base  # no such variant: the base scene
    assert app.features == () and len(base.features) > 5
    with pytest.raises(SceneError, match=r"no variant 'polar' \(it has approach"):
        load_scene_params("thesis:polar")
    with pytest.raises(SceneError, match=r"no variant 'polar' \(it has none: give mare alone\)"):  # was "[]"
        load_scene_params("mare:polar")


def test_radial_profile_thins_the_population_and_fields_are_window_independent():
    doc = {
        "terrain": {"rms_relief_m": 0.0, "micro_rms_m": 0.0},
        "craters": {"coef": 0.079, "d_min_m": 2.0, "d_max_m": 16.0, "profile": [[0, 0.0], [60, 0.0], [61, 2.0]]},
        "boulders": {"coef": 0.0, "rim_density_m2": 0.0},
        "boulder_fields": {"per_km2": 400.0, "radius_m": 20.0, "coef": 0.02},
    }
    sc = Scene(parse_scene(doc, "t"), 3)
    cr, bl = sc.features((-200.0, -200.0, 200.0, 200.0), 0.5)
    r = np.hypot(cr.x, cr.y)
    assert not np.any(r < 60.0)
    ring = (r > 70) & (r < 190)
    expect = 2.0 * 0.079 * (2.0**-2 - 16.0**-2) * math.pi * (190**2 - 70**2)
    assert ring.sum() == pytest.approx(expect, rel=0.15)
    # the same boulders of the fields through a smaller window
    _, small = sc.features((0.0, 0.0, 60.0, 60.0), 0.5)
    inside = lambda f: {(round(x, 6), round(y, 6)) for x, y in zip(f.x, f.y) if 5 < x < 55 and 5 < y < 55}  # noqa: E731
    assert inside(small) == inside(bl) and len(inside(bl)) > 10
    with pytest.raises(SceneError, match="profile"):
        parse_scene({"craters": {"profile": [[10, 1.0], [5, 1.0]]}}, "t")
    with pytest.raises(SceneError, match="range"):
        parse_scene({"feature": [{"kind": "crater", "x_m": 0, "y_m": 0, "diameter_m": [5, 1]}]}, "t")


@pytest.mark.parametrize("scene,scenario,idx", [("thesis", "approach", 0), ("highland", "approach", 4)])
def test_truth_geometry_error_at_grazing_angles_is_bounded(scene, scenario, idx):
    """The truth march steps ~1.2 raster cells along a ray; at 41-64 deg from nadir it can step over a thin
    crest and report the ground behind it. Against a 0.05-cell march of the same raster the error is bounded
    (docs/scenes.md "Ground truth accuracy"): few pixels off by > 1 cm, almost none by > 0.3 m or in hazard."""
    from ground_sim.geometry import pixel_rays
    from ground_sim.heightfield import intersect
    from ground_sim.render import _Caster
    from ground_sim.trajectory import load_trajectory
    from ground_sim.truth import footprint_planes, hazard_layers, plane_fit

    spec = load_trajectory(scenario, CAM)[idx]
    sc, sun = load_scene(scene, 1000, scenario), lib.scene_sun(scene, scenario, 1000)
    pose = spec.poses[0]
    # the view's one raster (the march below is the one every tile runs on its own raster)
    v = render_view(sc, CAM, pose, sun, noise=False, raster="view")
    cs = _Caster(sc, CAM, pose, sun, 2)
    vv, uu = np.mgrid[0:128, 0:128]
    d = pixel_rays(CAM, pose, uu.ravel().astype(float), vv.ravel().astype(float))
    C = pose.position
    s = np.sqrt(1 - d[:, 2] ** 2)
    t, hit = intersect(
        cs.r, C, d, np.maximum((C[2] - cs.zmax) / -d[:, 2], 0), (C[2] - cs.zmin) / -d[:, 2], 0.05 * cs.cell / s
    )
    assert hit.all()
    X = C + t[:, None] * d
    dz = np.abs(v.elevation.ravel() - X[:, 2])
    if cs.truth_cell is not None:  # the render's rule: the footprint's plane on a raster that holds the disk
        planes = footprint_planes(cs.heights, X[:, 0], X[:, 1], cs.truth_cell)
    else:
        planes = (X[:, 2], *(cs.r.sample(X[:, 0], X[:, 1], m) for m in plane_fit(cs.H, cs.cell)))
    ref_unsafe = hazard_layers(*planes, v.shadow.ravel()) >= 1
    assert np.mean(dz > 0.01) < 0.03
    assert np.mean(dz > 0.3) < 0.002
    assert np.mean(ref_unsafe != (v.hazard.ravel() >= 1)) < 0.003


def test_scenes_command_lists_the_library(capsys):
    from hil_server.cli import main

    assert main(["scenes"]) == 0
    out = capsys.readouterr().out
    for name in REQUIRED:
        assert f"\n{name}: " in "\n" + out
    assert out.count("hazards in scene %") == 2 * len(REQUIRED)
    assert "held-out seeds 1000-1009" in out and "sun drawn per seed: azimuth 0-360 deg, elevation 2-5 deg" in out
    assert main(["scenes", "--json", "thesis"]) == 0
    import json

    (d,) = json.loads(capsys.readouterr().out)
    assert d["name"] == "thesis" and d["problems"] == [] and set(d["hazards_in_scene_pct"]) == {"vertical", "approach"}


def test_a_scene_name_means_the_preset_whatever_the_working_directory_holds(tmp_path, monkeypatch):
    """`render --scene mare --out mare` failed "scene file mare does not exist" (its --out made first), and an empty
    file named mare gave the default terrain under the name mare (QA of stop 73): a spec is a file only when it
    ends in .toml or names a directory."""
    from ground_sim.errors import SceneError
    from ground_sim.scene import PRESET_DIR, load_scene_params, split_scene_spec

    preset = load_scene_params("mare")
    monkeypatch.chdir(tmp_path)
    (tmp_path / "mare").mkdir()
    (tmp_path / "thesis").write_text("")
    assert load_scene_params("mare") == preset and load_scene_params("thesis").name == "thesis"
    assert split_scene_spec("mine.toml:approach") == ("mine.toml", "approach")
    assert split_scene_spec("./mine") == ("./mine", None) and split_scene_spec("mare:vertical") == ("mare", "vertical")
    (tmp_path / "mine.toml").write_text((PRESET_DIR / "thesis.toml").read_text())
    assert load_scene_params("mine.toml") == load_scene_params("thesis")  # the file, read as one
    with pytest.raises(SceneError, match=r"scene file nope does not exist"):
        load_scene_params("./nope")
