"""Render and scene-library inputs refused up front, and the JSON render and ``scenes`` write kept strict.

QA findings B5-B7, R1, R10: pairs without shared ground wrote bare NaN tokens; positions, sun angles and
altitudes that ``process`` (or the renderer's run time) cannot take were accepted; a malformed hazard-share
table gave tracebacks; ``scenes --measure`` left the table 0600.
"""

from __future__ import annotations

import copy
import json
import math
import os
import stat
from pathlib import Path
from typing import Any

import pytest
from hilkit import one_line_error, strict_json

from ground_sim import descent
from ground_sim import library as lib
from ground_sim.trajectory import MIN_ALTITUDE_M
from hil_server.cli import main

F128 = 64 / math.tan(math.radians(15))  # 128 px, the thesis's 30 deg field of view
CAM128 = {"width": 128, "height": 128, "fx": F128, "fy": F128, "cx": 63.5, "cy": 63.5}
NADIR = [[1, 0, 0], [0, -1, 0], [0, 0, -1]]
SHARES_FORMAT = "hazard-hil-scene-shares/1"  # the packaged table's format


def _frame(z: float, t: float, x: float = 0.0) -> dict[str, Any]:
    return {"position_m": [x, 0, z], "R_world_to_cam": NADIR, "time_s": t}


def trajectory(tmp_path: Path, frames: list[dict[str, Any]], label: str = "p") -> Path:
    """A 128 px trajectory file of one pair."""
    p = tmp_path / "traj.json"
    p.write_text(json.dumps({"camera": CAM128, "pairs": [{"label": label, "frames": frames}]}))
    return p


@pytest.fixture
def no_rendering(monkeypatch):
    """Fail the test as soon as a view would be drawn: each refusal here must come before it (an altitude of
    1 m rendered for minutes)."""

    def render_views(*args, **kw):
        raise AssertionError("rendered before the input was checked")

    monkeypatch.setattr(descent, "render_views", render_views)


# --------------------------------------------------------------------------- B6: no shared ground, far positions
def test_pair_without_shared_ground_writes_strict_json_and_warns(tmp_path, capsys):
    traj = trajectory(tmp_path, [_frame(300, 0), _frame(150, 10, x=600)], "nooverlap")
    out = tmp_path / "out"
    assert main(["render", "--scenario", str(traj), "--out", str(out), "--no-progress", "--workers", "1"]) == 0
    err = capsys.readouterr().err
    warnings = [line for line in err.splitlines() if line.startswith("warning:")]
    assert len(warnings) == 1 and "nooverlap" in warnings[0] and "share no ground" in warnings[0], err
    manifest = strict_json(out / "manifest.json")
    assert manifest["pairs"][0]["hazards_in_scene_pct"] is None
    assert strict_json(out / "nooverlap" / "pair.json")["hazards_in_scene_pct"] is None


def test_a_pair_with_almost_no_baseline_or_shared_ground_is_rendered_with_a_warning(tmp_path, capsys):
    """`--frames 300,299.9999` rendered a "300/300" pair with a 0.1 mm baseline, and a pair whose frames share under
    1 % of the ground, each without a word; the pair reader's own notes knew the first."""
    traj = trajectory(tmp_path, [_frame(300, 0), _frame(299.9999, 10)], "flat")
    argv = ["render", "--scenario", str(traj), "--out", str(tmp_path / "a"), "--no-progress", "--workers", "1"]
    assert main(argv) == 0
    err = capsys.readouterr().err
    assert "warning: pair flat: the baseline between the first and last frame is 0.0001 m, under 1 %" in err, err
    traj = trajectory(tmp_path, [_frame(300, 0), _frame(150, 10, x=115)], "edge")
    argv = ["render", "--scenario", str(traj), "--out", str(tmp_path / "b"), "--no-progress", "--workers", "1"]
    assert main(argv) == 0
    err = capsys.readouterr().err
    share = strict_json(tmp_path / "b" / "edge" / "pair.json")["overlap_pct"]
    assert 0 < share < 2 and f"its last frame sees only {share:.2g} % of frame 0's pixels' ground" in err, err


def test_position_the_pair_reader_refuses_is_refused_before_rendering(tmp_path, capsys, no_rendering):
    traj = trajectory(tmp_path, [_frame(1e12, 0), _frame(150, 10)])
    err = one_line_error(capsys, ["render", "--scenario", str(traj), "--out", str(tmp_path / "out")])
    assert f"trajectory file {traj} pair #0 frame 0" in err and "over 1e+07 m from the origin" in err, err
    assert not (tmp_path / "out").exists()


# --------------------------------------------------------------------------- B7: sun angles
@pytest.mark.parametrize(
    "sun, message",
    [
        ("-400,25", "--sun: azimuth must be in [-360, 360] deg, got -400"),
        ("1e9,25", "--sun: azimuth must be in [-360, 360] deg, got 1e+09"),
        ("10,95", "--sun: elevation must be in (0, 90] deg, got 95"),
    ],
)
def test_sun_the_pair_reader_refuses_is_refused_before_rendering(tmp_path, capsys, no_rendering, sun, message):
    traj = trajectory(tmp_path, [_frame(300, 0), _frame(150, 10)])
    err = one_line_error(capsys, ["render", "--scenario", str(traj), f"--sun={sun}", "--out", str(tmp_path / "o")])
    assert message in err, err
    assert not (tmp_path / "o").exists()


def test_sun_azimuth_at_the_limit_renders(tmp_path, capsys):
    traj = trajectory(tmp_path, [_frame(300, 0), _frame(150, 10)])
    argv = ["render", "--scenario", str(traj), "--sun=-360,25", "--out", str(tmp_path / "o"), "--no-progress"]
    assert main([*argv, "--workers", "1"]) == 0
    assert strict_json(tmp_path / "o" / "p" / "pair.json")["sun"]["azimuth_deg"] == -360.0


# --------------------------------------------------------------------------- R1: implausibly low altitudes
def test_low_frames_are_refused_before_rendering(tmp_path, capsys, no_rendering):
    argv = ["render", "--scenario", "vertical", "--frames", "2,1", "--out", str(tmp_path / "low"), "--workers", "1"]
    err = one_line_error(capsys, argv)
    assert f"--frames: altitudes must be at least {MIN_ALTITUDE_M:g} m, got 2, 1" in err, (
        err
    )  # every one too low (QA of stop 84)
    assert not (tmp_path / "low").exists()


def test_low_trajectory_frame_is_refused_before_rendering(tmp_path, capsys, no_rendering):
    traj = trajectory(tmp_path, [_frame(300, 0), _frame(MIN_ALTITUDE_M / 2, 10)])
    err = one_line_error(capsys, ["render", "--scenario", str(traj), "--out", str(tmp_path / "out")])
    assert f"trajectory file {traj} pair #0 frame 1" in err and f"{MIN_ALTITUDE_M:g} m" in err, err


# --------------------------------------------------------------------------- B5: malformed tables
def _bad_table(tmp_path: Path, name: str, edit) -> Path:
    doc = copy.deepcopy(lib.load_shares())
    edit(doc)
    p = tmp_path / f"tab_{name}.json"
    p.write_text(json.dumps(doc))
    return p


def _set_500(value: Any):
    def edit(doc: dict[str, Any]) -> None:
        doc["scenes"]["thesis"]["scenarios"]["vertical"]["500"] = value

    return edit


@pytest.mark.parametrize(
    "name, edit, entry",
    [
        ("emp", _set_500([]), "scenes.thesis.scenarios.vertical.500"),
        ("str", _set_500("abc"), "scenes.thesis.scenarios.vertical.500"),
        ("item", _set_500([1.0, "x"]), "scenes.thesis.scenarios.vertical.500"),
        ("scen", lambda d: d["scenes"]["thesis"].update(scenarios="x"), "scenes.thesis.scenarios"),
        ("alt", lambda d: d["scenes"]["thesis"]["scenarios"]["vertical"].update(high=[1.0]), "altitude 'high'"),
        ("format", lambda d: d.update(format="other/9"), "format must be 'hazard-hil-scene-shares/1'"),
        ("seeds", lambda d: d.update(seeds="1000"), "seeds must be a list of integers"),
    ],
)
def test_malformed_table_is_one_line_naming_file_and_entry(tmp_path, capsys, name, edit, entry):
    table = _bad_table(tmp_path, name, edit)
    for extra in ([], ["--json"]):
        err = one_line_error(capsys, ["scenes", "thesis", "--table", str(table), *extra])
        assert f"--table {table}: " in err and entry in err, err


def test_table_altitude_without_a_target_band_is_listed(tmp_path, capsys):
    table = _bad_table(tmp_path, "alt", lambda d: d["scenes"]["thesis"]["scenarios"]["vertical"].update({"123": [9.0]}))
    assert main(["scenes", "thesis", "--table", str(table)]) == 0  # was a ValueError (no target at 123 m)
    assert "123" in capsys.readouterr().out


def test_table_share_without_value_lists_as_strict_json(tmp_path, capsys):
    table = _bad_table(tmp_path, "nan", _set_500([float("nan")]))
    assert main(["scenes", "thesis", "--json", "--table", str(table)]) == 0
    out = capsys.readouterr().out
    doc = json.loads(out, parse_constant=lambda t: pytest.fail(f"{t} in --json output"))
    assert doc[0]["hazards_in_scene_pct"]["vertical"]["500"]["median"] is None
    assert main(["scenes", "thesis", "--table", str(table)]) == 0  # the text listing shows "-", no traceback


# --------------------------------------------------------------------------- R10: the table's mode
def test_measure_keeps_the_table_mode(tmp_path, capsys, monkeypatch):
    table = tmp_path / "t.json"
    table.write_text(json.dumps({"format": SHARES_FORMAT, "seeds": [1000], "scenes": {}}))
    os.chmod(table, 0o644)

    def measure(names, seeds, **kw):  # the table's write is under test, not minutes of measuring
        return {"format": SHARES_FORMAT, "seeds": seeds, "scenes": {n: {"scenarios": {}} for n in names}}

    monkeypatch.setattr(lib, "measure", measure)
    main(["scenes", "thesis", "--measure", "--seeds", "1", "--no-progress", "--table", str(table)])
    assert stat.S_IMODE(table.stat().st_mode) == 0o644
    assert set(strict_json(table)["scenes"]) == {"thesis"}
    new = tmp_path / "new.json"
    old_umask = os.umask(0o027)
    try:
        main(["scenes", "thesis", "--measure", "--seeds", "1", "--no-progress", "--table", str(new)])
    finally:
        os.umask(old_umask)
    assert stat.S_IMODE(new.stat().st_mode) == 0o640  # 0666 & ~umask, as any new file


def test_a_stopped_render_says_what_it_kept(tmp_path, capsys, monkeypatch):
    """A render stopped after 6 of 7 frames ended "stopped by SIGTERM" and left an empty --out without a word."""

    def ctrl_c(*args, **kw):
        raise KeyboardInterrupt

    monkeypatch.setattr(descent, "render_views", ctrl_c)
    assert main(["render", "--scenario", "vertical", "--pairs", "600/300", "--out", str(tmp_path / "o")]) == 130
    err = capsys.readouterr().err
    assert "stopped before any pair was written" in err and "nothing new" in err, err


def test_a_render_stopped_while_writing_a_pair_leaves_no_half_pair_and_no_mixed_render(tmp_path, capsys, monkeypatch):
    """A stop between pair.json and the truth files left a pair without truth that `process` took as whole, and
    over an earlier render a pair with new images beside the old truth, which `score` then blamed on the detector."""
    import numpy as np

    from protocol.pairdir import read_pair

    out = tmp_path / "o"
    args = ["render", "--scenario", "vertical", "--pairs", "600/300,300/150", "--image-size", "32", "--no-progress"]
    assert main([*args, "--seed", "0", "--out", str(out)]) == 0
    before = {p: (out / p / "gt_hazard_i1.npy").read_bytes() for p in ("600_300", "300_150")}
    saves = []
    real_save = np.save

    def stop_in_the_second_pair(path, arr):  # the second pair's second truth file
        saves.append(path)
        if len(saves) == len(before) * 2 + 2:
            raise KeyboardInterrupt
        real_save(path, arr)

    monkeypatch.setattr(np, "save", stop_in_the_second_pair)
    assert main([*args, "--seed", "1", "--out", str(out)]) == 130
    err = capsys.readouterr().err
    assert "1 pair(s) written whole" in err and "600_300;" in err and "no manifest.json" in err, err
    # the pair not replaced is the earlier render's, and said (QA of stop 72: beside ours it read as one descent)
    assert "1 pair(s) of an earlier render are still there, not this one's: 300_150" in err, err
    assert not (out / "manifest.json").exists()  # the old one listed a mix of both renders
    assert sorted(p.name for p in out.iterdir() if p.is_dir()) == ["300_150", "600_300"]  # no partial siblings
    new, old = read_pair(out / "600_300"), read_pair(out / "300_150")
    assert new.meta["seed"] == 1 and old.meta["seed"] == 0  # each pair whole: all new, or all as it was
    assert (out / "300_150" / "gt_hazard_i1.npy").read_bytes() == before["300_150"]
    assert (out / "600_300" / "gt_hazard_i1.npy").read_bytes() != before["600_300"]


def test_a_render_a_full_disk_stops_says_what_it_kept_and_what_is_an_earlier_renders(tmp_path, capsys, monkeypatch):
    """A full disk removed an intact earlier render's manifest.json and said only "No space left on device"
    (QA of stop 72)."""
    import errno

    import numpy as np

    out = tmp_path / "o"
    args = ["render", "--scenario", "vertical", "--pairs", "600/300,300/150", "--image-size", "32", "--no-progress"]
    assert main([*args, "--seed", "0", "--out", str(out)]) == 0
    capsys.readouterr()

    def full(path, arr):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(np, "save", full)
    assert main([*args, "--seed", "1", "--out", str(out)]) == 1
    err = capsys.readouterr().err
    assert "nothing new in" in err and "2 pair(s) of an earlier render are still there, not this one's: " in err, err
    assert "600_300, 300_150" in err and "error: cannot write " in err and "No space left on device" in err, err
    # nothing was replaced, so the earlier render stays whole, its manifest.json included
    assert json.loads((out / "manifest.json").read_text())["seed"] == 0


def test_a_render_over_an_earlier_one_says_what_it_replaced_and_what_it_left(tmp_path, capsys):
    out = tmp_path / "o"
    args = ["render", "--scenario", "vertical", "--image-size", "32", "--no-progress", "--out", str(out)]
    assert main([*args, "--pairs", "600/300,300/150"]) == 0
    capsys.readouterr()
    assert main([*args, "--pairs", "600/300", "--seed", "1"]) == 0
    err = capsys.readouterr().err
    assert "replaced 1 pair(s) of an earlier render" in err and "no longer in manifest.json: 300_150" in err, err
    assert (out / "300_150" / "pair.json").is_file()  # nothing deleted


def test_a_label_with_a_control_character_is_refused(tmp_path, capsys, no_rendering):
    """A newline in a trajectory file's label made a directory with a newline in its name."""
    traj = trajectory(tmp_path, [_frame(300.0, 0.0), _frame(150.0, 10.0)], label="p\n1")
    err = one_line_error(capsys, ["render", "--scenario", str(traj), "--out", str(tmp_path / "o")])
    assert "without control characters" in err


def test_a_camera_that_is_not_an_object_is_refused(tmp_path, capsys, no_rendering):
    """`"camera": "x"` was ignored and the 512 px camera rendered in its place."""
    traj = trajectory(tmp_path, [_frame(300.0, 0.0), _frame(150.0, 10.0)])
    doc = json.loads(traj.read_text())
    doc["camera"] = "x"
    traj.write_text(json.dumps(doc))
    err = one_line_error(capsys, ["render", "--scenario", str(traj), "--out", str(tmp_path / "o")])
    assert "'camera' must be an object" in err and str(traj) in err


def test_render_takes_a_small_camera_as_run_does(tmp_path, capsys):
    """`run --image-size` and `evaluate --camera-px` rendered small cameras; `render` could not, so the
    render -> process -> score walk-through always drew 512 px frames."""
    from protocol.pairdir import Camera, read_pair

    out = tmp_path / "r"
    assert main(["render", "--scenario", "vertical", "--pairs", "300/150", "--image-size", "64", "--no-progress",
                 "--out", str(out)]) == 0  # fmt: skip
    pair = read_pair(out / "300_150")
    assert pair.camera == Camera.thesis(64) and pair.images[0].shape == (64, 64)
    assert pair.truth["hazard"].shape == (64, 64)
    # the thesis camera's field of view at every size (run and evaluate build theirs the same way)
    assert Camera.thesis(512) == Camera.thesis() and Camera.thesis(64).fx * 8 == Camera.thesis().fx


# --------------------------------------------------------------------------- QA 61a
@pytest.mark.skipif(not Path("/sys").is_dir(), reason="needs /sys, where no file can be made")
def test_measure_into_a_directory_where_no_file_can_be_made_is_refused_before_measuring(capsys, monkeypatch):
    """os.access says yes to root on /sys: the table's directory passed, the scenes were measured for minutes,
    then the write failed naming an internal temp file (/sys/.x.json.dqp42k_4), exit 1."""

    def measure(*args, **kw):
        raise AssertionError("measured before --table was checked")

    monkeypatch.setattr(lib, "measure", measure)
    monkeypatch.setattr(os, "access", lambda *a, **k: True)  # as root sees it, whoever runs the test
    err = one_line_error(capsys, ["scenes", "mare", "--measure", "--seeds", "1", "--table", "/sys/x.json"])
    assert "--table /sys/x.json cannot be written" in err and "/sys/." not in err, err


def test_a_render_at_a_documented_altitude_gives_no_metres_hint(tmp_path, capsys):
    """45 km at 64 px sees 380 m per pixel: the pair reader's "positions must be in metres" (meant for a user's
    pair files) was said of the tool's own render within its documented 30 m - 50 km."""
    argv = ["render", "--scenario", "vertical", "--frames", "45000,40000", "--image-size", "64"]
    assert main([*argv, "--out", str(tmp_path / "o"), "--workers", "1", "--no-progress"]) == 0
    assert "metres" not in capsys.readouterr().err


@pytest.mark.parametrize("spec, said", [("alt=-1", "alt=-1"), ("pitch_sigma=1e9", "pitch_sigma=1e9")])
def test_a_pose_error_out_of_range_is_named_as_typed(tmp_path, capsys, no_rendering, spec, said):
    """`--pose-error alt=-1` was refused as "pose error altitude_uniform_m must be ...", a name the user never saw."""
    err = one_line_error(capsys, ["render", "--scenario", "vertical", "--pose-error", spec, "--out", str(tmp_path)])
    assert f"--pose-error: {said}" in err and "_uniform_" not in err and "_sigma_" not in err, err


def test_the_trajectory_file_design_md_shows_is_one(tmp_path):
    """design.md documents the --scenario FILE format with an example (it had none; stop 62's QA L2): the example
    loads as written, and its frames are where it says."""
    import re

    import numpy as np

    from ground_sim.trajectory import load_trajectory

    text = (Path(__file__).parents[1] / "docs" / "design.md").read_text()
    (block,) = re.findall(r"```toml\n(.*?)```", text, re.S)
    f = tmp_path / "steep.toml"
    f.write_text(block)
    (spec,) = load_trajectory(f)
    assert spec.label == "400/200" and spec.altitude_m == 200 and spec.camera.width == 256
    assert [float(p.position[2]) for p in spec.poses] == [400.0, 200.0] and spec.poses[1].time_s == 4.0
    axis = spec.poses[0].R[2]  # the optical axis in world: 30 deg off nadir toward +Y
    assert axis[1] > 0 and abs(float(np.degrees(np.arccos(-axis[2]))) - 30.0) < 1e-6


def test_a_trajectorys_frames_without_times_get_the_descents(tmp_path):
    """Frames without time_s were all given 0 s, so every rendered pair read as frames taken at one time (a note
    since stop 74). Now they follow the descent's velocity profile over their heights; where some frame gives a
    time, a frame without one is at 0 s, as design.md's example has it (a later one is then said to come first)."""
    from ground_sim.errors import TrajectoryError
    from ground_sim.trajectory import load_trajectory

    untimed = [{k: v for k, v in _frame(z, 0.0).items() if k != "time_s"} for z in (400.0, 300.0, 200.0)]
    (spec,) = load_trajectory(trajectory(tmp_path, untimed))
    t = [q.time_s for q in spec.poses]
    assert t[0] == 0.0 and t[0] < t[1] < t[2], t
    (vert,) = [s for s in load_trajectory("vertical") if s.label == "400/200"]
    assert t[2] - t[0] == pytest.approx(vert.poses[1].time_s - vert.poses[0].time_s, rel=1e-9)  # the same profile
    with pytest.raises(TrajectoryError, match=r"frame 1 is earlier than frame 0 \(time_s 0 vs 3\)"):
        load_trajectory(trajectory(tmp_path, [{**untimed[0], "time_s": 3.0}, untimed[1]]))
    (given,) = load_trajectory(trajectory(tmp_path, [_frame(400.0, 0.0), _frame(200.0, 4.0)]))
    assert [q.time_s for q in given.poses] == [0.0, 4.0]  # given times are kept
