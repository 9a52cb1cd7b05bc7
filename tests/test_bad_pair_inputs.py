"""Hostile pair directories and detector outputs at `process` and `score`: one line naming the file, never a
traceback.

Each case once ended in a Python traceback (exit 1) or was silently accepted: a NUL in an image name, a
symlink loop, a FIFO or directory in place of an image, a non-numeric or pickled truth array, a deeply nested
result.json or manifest.json, sites at infinite, huge or non-numeric coordinates.
"""

from __future__ import annotations

import json
import os
import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest
from hilkit import small_descent

from hil_server.cli import main
from protocol.pairdir import PairFormatError, read_pair
from studies.evaluate import backproject_depth, true_poses

PX = 64  # small images: the whole module runs in a few seconds
DEEP = "[" * 5000 + "]" * 5000  # deeper than Python's recursion limit


@pytest.fixture(scope="module")
def good(tmp_path_factory) -> tuple[Path, Path]:
    """A rendered pair and an output directory for it (the true hazard: every pixel scores)."""
    root = tmp_path_factory.mktemp("badpair")
    small_descent(root / "pairs", ["600/300"], px=PX)
    pair_dir = root / "pairs" / "600_300"
    out = root / "out"
    out.mkdir()
    np.save(out / "hazard.npy", read_pair(pair_dir).truth["hazard"].astype(np.float32))
    return pair_dir, out


@pytest.fixture(autouse=True)
def _home(tmp_path, monkeypatch):
    monkeypatch.setenv("HAZARD_HIL_HOME", str(tmp_path / "home"))  # never calibrate this host first


def _copy(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst, symlinks=True)
    return dst


def _rewrite(d: Path, fn) -> None:
    doc = json.loads((d / "pair.json").read_text())
    fn(doc)
    (d / "pair.json").write_text(json.dumps(doc))


def assert_refused(argv: list[str], capsys, *parts: str) -> str:
    """Run ``argv``; it must exit 2 with one error line holding every one of ``parts``."""
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and all(p in err for p in parts), err
    assert err.startswith(f"hazard-hil {argv[0]}: error: ")
    return err


def assert_both_refuse(bad: Path, good_out: Path, tmp_path: Path, capsys, *parts: str) -> None:
    assert_refused(["process", str(bad), "--out", str(tmp_path / "po")], capsys, *parts)
    assert_refused(["score", str(bad), str(good_out)], capsys, *parts)


def _score_rows(pair_dir: Path, out: Path, capsys) -> list[dict]:
    js = out.parent / f"{out.name}-score.json"
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # numpy's RuntimeWarnings used to leak from the site projection
        main(["score", str(pair_dir), str(out), "--json", str(js)])
    capsys.readouterr()
    return json.loads(js.read_text())["rows"]


def test_nul_in_an_image_name(good, tmp_path, capsys):
    bad = _copy(good[0], tmp_path / "bad")
    _rewrite(bad, lambda doc: doc["frames"][1].update(image="i2\x00.png"))
    assert_both_refuse(bad, good[1], tmp_path, capsys, str(bad / "pair.json"), "NUL character")


def test_image_symlink_loop(good, tmp_path, capsys):
    bad = _copy(good[0], tmp_path / "bad")
    (bad / "i2.png").unlink()
    (bad / "i2.png").symlink_to("i2.png")
    assert_both_refuse(bad, good[1], tmp_path, capsys, str(bad), "i2.png", "cannot be resolved")


@pytest.mark.parametrize("kind", ["fifo", "directory"])
def test_image_that_is_not_a_regular_file(good, tmp_path, capsys, kind):
    bad = _copy(good[0], tmp_path / "bad")
    (bad / "i2.png").unlink()
    if kind == "fifo":
        os.mkfifo(bad / "i2.png")
    else:
        (bad / "i2.png").mkdir()
    what = "a FIFO" if kind == "fifo" else "a directory"
    assert_both_refuse(bad, good[1], tmp_path, capsys, str(bad), "i2.png", "exists but is not a regular file", what)


def test_missing_image_is_still_called_missing(good, tmp_path, capsys):
    bad = _copy(good[0], tmp_path / "bad")
    (bad / "i2.png").unlink()
    assert_both_refuse(bad, good[1], tmp_path, capsys, "missing image i2.png")


def test_image_name_too_long_for_the_file_system(good, tmp_path, capsys):
    bad = _copy(good[0], tmp_path / "bad")
    _rewrite(bad, lambda doc: doc["frames"][1].update(image="a" * 5000))
    assert_both_refuse(bad, good[1], tmp_path, capsys, str(bad), "(5000 characters) cannot be read")


def test_deeply_nested_pair_json_is_refused_by_the_reader(good, tmp_path):
    bad = _copy(good[0], tmp_path / "bad")
    text = (bad / "pair.json").read_text().rstrip().removesuffix("}") + f', "meta": {DEEP}}}'
    (bad / "pair.json").write_text(text)
    with pytest.raises(PairFormatError, match=r"pair\.json: JSON nested too deeply"):
        read_pair(bad)


def test_an_integer_of_more_digits_than_python_reads_in_pair_json(good, tmp_path, capsys):
    """A 4301-digit width ended process and score with a traceback; manifest.json and result.json refused it."""
    bad = _copy(good[0], tmp_path / "bad")
    doc = json.loads((bad / "pair.json").read_text())
    text = json.dumps(doc).replace(f'"width": {doc["camera"]["width"]}', '"width": ' + "1" * 4301, 1)
    (bad / "pair.json").write_text(text)
    assert_both_refuse(bad, good[1], tmp_path, capsys, "pair.json: not valid JSON", "4300 digits")


def test_deeply_nested_pair_json_at_process(good, tmp_path, capsys):
    bad = _copy(good[0], tmp_path / "bad")
    text = (bad / "pair.json").read_text().rstrip().removesuffix("}") + f', "meta": {DEEP}}}'
    (bad / "pair.json").write_text(text)
    assert_refused(["process", str(bad), "--out", str(tmp_path / "po")], capsys, "pair.json", "nested too deeply")


def _save_object(p: Path) -> None:
    np.save(p, np.full((PX, PX), None, dtype=object), allow_pickle=True)


@pytest.mark.parametrize(
    "fname, write, says",
    [
        ("gt_hazard_i1.npy", lambda p: np.save(p, np.full((PX, PX), "x")), "must hold numbers"),
        ("gt_depth_i1.npy", lambda p: np.save(p, np.full((PX, PX), 1j)), "must hold numbers"),
        ("gt_elevation_i1.npy", _save_object, "Python objects"),  # never unpickled
        ("gt_shadow_i1.npy", lambda p: np.save(p, np.full((PX, PX), 0.5)), "must hold bool"),
        ("gt_hazard_i1.npy", lambda p: np.save(p, np.zeros((3, 3), np.float32)), "shape (3, 3) != image shape"),
        # a 2 passed as shadow unsaid (QA of stop 85)
        ("gt_shadow_i1.npy", lambda p: np.save(p, np.full((PX, PX), 2, np.uint8)), "bool or integer 0/1; 4096 pixels"),
    ],
    ids=["string", "complex", "object", "float-shadow", "shape", "shadow-of-2"],
)
def test_truth_arrays_that_are_not_numeric_maps(good, tmp_path, capsys, fname, write, says):
    bad = _copy(good[0], tmp_path / "bad")
    write(bad / fname)
    assert_both_refuse(bad, good[1], tmp_path, capsys, str(bad / fname), says)


def test_truth_file_that_is_a_fifo(good, tmp_path, capsys):
    bad = _copy(good[0], tmp_path / "bad")
    (bad / "gt_shadow_i1.npy").unlink()
    os.mkfifo(bad / "gt_shadow_i1.npy")
    assert_both_refuse(bad, good[1], tmp_path, capsys, "gt_shadow_i1.npy", "not a regular file (a FIFO)")


def test_deeply_nested_result_json(good, tmp_path, capsys):
    out = _copy(good[1], tmp_path / "out")
    (out / "result.json").write_text('{"sites": ' + DEEP + "}")
    (row,) = _score_rows(good[0], out, capsys)
    assert row["error"] == f"{out / 'result.json'}: JSON nested too deeply"


def test_deeply_nested_manifest_json(good, tmp_path, capsys):
    (tmp_path / "descent").mkdir()
    (tmp_path / "descent" / "manifest.json").write_text('{"pairs": ' + DEEP + "}")
    assert_refused(["score", str(tmp_path / "descent"), str(good[1])], capsys, "manifest.json", "nested too deeply")


@pytest.mark.parametrize("x", ["Infinity", "-Infinity", "NaN", "1e300", '"1"', "true", "null", "[1]"])
def test_sites_at_coordinates_that_are_not_finite_numbers(good, tmp_path, capsys, x):
    out = _copy(good[1], tmp_path / "out")
    ok = '{"x": 0, "y": 0, "z": 0, "distance_m": 0}'
    (out / "result.json").write_text(f'{{"sites": [{ok}, {{"x": {x}, "y": 0, "z": 0, "distance_m": 0}}]}}')
    (row,) = _score_rows(good[0], out, capsys)
    assert row["error"] is not None and row["error"].startswith(f'{out / "result.json"}: site 1: "x" must be a finite')


def test_a_site_off_the_image_is_not_truly_safe(good, tmp_path, capsys):
    """A site far off frame 0's image used to be judged by the edge pixel nearest to it; one on the image's edge
    was judged by the half of its footprint the image holds. DESIGN.md's rule cannot confirm either."""
    pair = read_pair(good[0])
    true1, _ = true_poses(pair)
    world = backproject_depth(pair.camera, true1, pair.truth["depth"].astype(np.float64))
    gt = pair.truth["hazard"]
    rows = [v for v in range(PX) if np.all(gt[max(0, v - 3) : v + 4, PX - 4 :] < 1.0)]
    assert rows, "the scene has no safe stretch of the right edge to place the site against"
    inner, edge = world[rows[len(rows) // 2], PX - 3], world[rows[len(rows) // 2], PX - 1]
    far = edge + 1000.0 * true1.R[0]  # along camera 1's x axis: far right of the image, same row
    sites = [{"x": float(p[0]), "y": float(p[1]), "z": float(p[2])} for p in (inner, edge, far)]
    out = _copy(good[1], tmp_path / "out")
    (out / "result.json").write_text(json.dumps({"sites": sites}))
    (row,) = _score_rows(good[0], out, capsys)
    assert row["error"] is None and row["sites"] == 3
    assert row["top_site_truly_safe"] is True and row["top_site_confirmed"] is True  # wholly seen, all safe
    assert (row["sites_truly_safe"], row["sites_unconfirmed"]) == (1, 2)  # the edge and the far one
    (out / "result.json").write_text(json.dumps({"sites": sites[1:]}))
    (row,) = _score_rows(good[0], out, capsys)
    assert row["top_site_truly_safe"] is False and row["top_site_confirmed"] is False


@pytest.mark.parametrize(
    "edit, says",
    [
        (lambda doc: doc["camera"].update(width=PX + 0.5), "width must be a whole number"),  # was truncated
        (lambda doc: doc["frames"][1].update(position_m=["0", "0", "150"]), "position_m entries must be a number"),
        (lambda doc: doc["frames"][1].update(position_m=[True, False, 150]), "position_m entries must be a number"),
        # the field at fault alone: the message listed the fields a frame needs, which were all there
        (lambda doc: doc["frames"][1].update(altimeter_m="150"), "frame 1: altimeter_m must be a number, got '150'"),
        (  # numpy's "cannot reshape array of size 3 into shape (4,)"
            lambda doc: doc["frames"][1].update(q_world_to_cam=[1, 0, 0]) or doc["frames"][1].pop("R_world_to_cam"),
            "frame 1: q_world_to_cam has shape (3,), need 4 numbers [w, x, y, z]",
        ),
        (lambda doc: doc["frames"][1].pop("position_m"), "need image, position_m[3], R_world_to_cam[3][3] or"),
        (lambda doc: doc["frames"][0].update(time_s="0"), "time_s must be a number"),
        # a missing time read as 0: "frame 1 is earlier than frame 0 (time_s 0 vs 9.96)", or no check at all
        (lambda doc: doc["frames"][1].pop("time_s"), "frame 1: time_s missing"),
        # numpy's overflow warning and "pose2: position [-1e+300, ...]" (no file) came first
        (
            lambda doc: doc["frames"][1]["position_m"].__setitem__(0, -1e300),
            "frame 1: position_m [-1e+300, 0, 300] m is over 1e+07 m from the origin",
        ),
        # a quaternion of norm 2 was normalised without a word, where a matrix that far off is an error
        (
            lambda doc: (
                doc["frames"][1].update(q_world_to_cam=[0, 2, 0, 0], R_world_to_cam=None)
                or doc["frames"][1].pop("R_world_to_cam")
            ),
            "frame 1: q_world_to_cam has norm 2; a unit quaternion",
        ),
        (
            lambda doc: doc["frames"][1].update(q_world_to_cam=[0, 0, 0, 0]) or doc["frames"][1].pop("R_world_to_cam"),
            "frame 1: q_world_to_cam has norm 0",
        ),
        # numpy's "setting an array element with a sequence. The requested array has an inhomogeneous shape"
        (
            lambda doc: doc["frames"][1].update(R_world_to_cam=[[1, 0, 0], [0, -1], [0, 0, -1]]),
            "frame 1: R_world_to_cam has rows of unequal length",
        ),
        # numpy's overflow warning and its source line came before the error (QA of stop 85)
        (
            lambda doc: doc["frames"][1]["R_world_to_cam"][0].__setitem__(0, 1e308),
            "R_world_to_cam is not orthonormal (max |R R^T - I| = inf",
        ),
        # read as a memory shortfall of 2.3e28 MiB (QA of stop 85)
        (lambda doc: doc["camera"].update(width=10**30), "camera: size must be 1..8192 px per side"),
    ],
)
@pytest.mark.filterwarnings("error::RuntimeWarning")  # a numpy warning is a second line on a user's console
def test_pair_json_numbers_must_be_numbers(good, tmp_path, capsys, edit, says):
    """float() took "150" and true as numbers and int() cut 64.5 px to 64: a hand-edited pair.json with quoted or
    fractional values ran as if it were fine."""
    bad = _copy(good[0], tmp_path / "bad")
    _rewrite(bad, edit)
    assert_refused(["process", str(bad), "--out", str(tmp_path / "po")], capsys, str(bad / "pair.json"), says)


@pytest.mark.parametrize(
    "edit, says",
    [
        (lambda doc: doc["frames"][1]["position_m"].__setitem__(0, float("nan")), "frame 1: position, rotation"),
        (lambda doc: doc.update(sun={"azimuth_deg": 400.0, "elevation_deg": 20.0}), "sun.azimuth_deg must be in"),
        (lambda doc: doc.update(sun={"azimuth_deg": 40.0, "elevation_deg": -5.0}), "sun.elevation_deg must be in"),
        # the pipeline's own checks of the camera named no file ("camera: focal length 1e+300 px ...")
        (lambda doc: doc["camera"].update(fx=1e300, fy=1e300), "pair.json: camera: focal length 1e+300 px"),
    ],
)
def test_pose_and_sun_errors_name_the_file(good, tmp_path, capsys, edit, says):
    """The errors for a non-finite pose and a sun out of range named neither the file nor, for the sun, the field
    as the file spells it (sun_azimuth_deg)."""
    bad = _copy(good[0], tmp_path / "bad")
    _rewrite(bad, edit)
    assert_refused(["process", str(bad), "--out", str(tmp_path / "po")], capsys, str(bad / "pair.json"), says)


def test_an_all_nan_truth_is_named_not_called_a_geometry_problem(good, tmp_path, capsys):
    """It read "frame 0 and the last frame share no ground"."""
    bad = _copy(good[0], tmp_path / "bad")
    np.save(bad / "gt_hazard_i1.npy", np.full((PX, PX), np.nan, np.float32))
    err = assert_refused(["score", str(bad), str(good[1])], capsys, "gt_hazard_i1.npy holds no finite value")
    assert "share no ground" not in err


@pytest.mark.parametrize(
    "edit, says",
    [
        (lambda doc: doc["true_frames"].pop(), "true_frames must list one pose per frame (2), got 1"),
        (lambda doc: doc.update(true_frames="x"), "true_frames must list one pose per frame (2), got str"),
        (lambda doc: doc["true_frames"][1].pop("position_m"), "true_frames[1]: need position_m"),
        (lambda doc: doc["true_frames"][0]["position_m"].__setitem__(2, float("nan")), "true_frames[0]: position"),
    ],
)
def test_true_poses_that_cannot_be_read_are_refused_not_replaced_by_the_reported_ones(
    good, tmp_path, capsys, edit, says
):
    """The site judge fell back to the reported pose when true_frames was unreadable: a pair with injected
    navigation errors was then scored against the very poses the errors were in, without a word."""
    bad = _copy(good[0], tmp_path / "bad")
    _rewrite(bad, edit)
    assert_both_refuse(bad, good[1], tmp_path, capsys, str(bad / "pair.json"), says)


def test_a_pair_file_the_system_will_not_let_us_read_is_bad_input_exit_2(good, tmp_path, capsys, monkeypatch):
    """An unreadable image, pair.json or directory was exit 1 (an OSError) where every other bad pair is exit 2."""
    from pathlib import Path as _Path

    bad = _copy(good[0], tmp_path / "bad")
    real = _Path.open

    def refuse(self, *a, **kw):
        if self.name == "i1.png":
            raise PermissionError(13, "Permission denied", str(self))
        return real(self, *a, **kw)

    monkeypatch.setattr(_Path, "open", refuse)
    from hil_server.cli import main

    assert main(["process", str(bad), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].endswith(f"cannot read {bad / 'i1.png'}: Permission denied"), err
