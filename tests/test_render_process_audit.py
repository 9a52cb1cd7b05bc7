"""Audit of ``render``, ``scenes`` and ``process`` as a new user meets them.

* ``process`` outputs follow DESIGN.md exactly (dtypes, shapes, NaN / 255 conventions, result.json sites),
  ``filled.npy`` and ``sigma.npy`` agree with ``elevation.npy``, and the same pair gives the same bytes.
* ``hazard.png`` does not hide the unknown state: the hazard score writes unknown as 1.0, so the picture
  greys those pixels instead of drawing them as the darkest hazard.
* Landing sites too close to label apart share one label ("1,2,3") instead of the worst rank overprinting.
* ``scenes --measure`` never drops the other scenes of a table measured on other seeds (it did, exit 0);
  ``--seeds``/``--workers`` without ``--measure`` are refused, not ignored; the measurement shows progress.
* ``render`` refuses a bad ``--supersample`` or sun elevation before creating ``--out``.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from hilkit import small_descent

from ground_sim import library as lib
from ground_sim.errors import SceneError
from hil_server.cli import main
from reports import plots
from reports.style import UNKNOWN


@pytest.fixture(scope="module")
def pair_dir(tmp_path_factory) -> Path:
    """A 128 px vertical 600/300 pair with ground truth."""
    out = tmp_path_factory.mktemp("render")
    small_descent(out, ["600/300"])
    return out / "600_300"


@pytest.fixture(scope="module")
def processed(pair_dir, tmp_path_factory) -> tuple[Path, Path]:
    """The pair processed twice into two directories, without the pictures (about 1.2 CPU-s each): these tests read
    the arrays, result.json, score.json and report.html; test_hazard_picture_greys_the_unknown_state draws them."""
    a, b = tmp_path_factory.mktemp("p1"), tmp_path_factory.mktemp("p2")
    for out in (a, b):
        assert main(["process", str(pair_dir), "--out", str(out), "--no-figures"]) == 0
    return a, b


def test_process_outputs_follow_design_md(processed):
    out = processed[0]
    z, h = np.load(out / "elevation.npy"), np.load(out / "hazard.npy")
    state, psafe = np.load(out / "state.npy"), np.load(out / "psafe.npy")
    filled, sigma = np.load(out / "filled.npy"), np.load(out / "sigma.npy")
    shape = z.shape
    assert (z.dtype, h.dtype, state.dtype, psafe.dtype) == (np.float32, np.float32, np.uint8, np.float32)
    assert filled.dtype == bool and sigma.dtype == np.float32
    assert h.shape == state.shape == psafe.shape == filled.shape == sigma.shape == shape == (128, 128)
    covered = np.isfinite(h)
    assert covered.any() and (~covered).any()
    assert np.all((h[covered] >= 0) & (h[covered] <= 1))
    assert set(np.unique(state).tolist()) <= {0, 1, 2, 255}
    assert np.array_equal(state == 255, ~covered)  # 255 outside, exactly where hazard is NaN
    assert np.all(h[state == 2] == 1.0)  # unknown is written as 1.0: never called safe
    assert np.all(h[state == 0] < 1) and np.all(h[state == 1] >= 1)
    assert np.array_equal(np.isnan(psafe), ~covered)
    assert np.all((psafe[covered] >= 0) & (psafe[covered] <= 1))
    # our extensions: a gap fill is an elevation, and every elevation has a positive sigma
    assert np.all(np.isfinite(z[filled]))
    assert np.array_equal(np.isfinite(sigma), np.isfinite(z)) and np.all(sigma[np.isfinite(sigma)] > 0)
    doc = json.loads((out / "result.json").read_text())
    assert doc["valid_fraction"] == pytest.approx(float(np.isfinite(z[covered]).mean()))
    for s in doc["sites"]:
        assert {"x", "y", "z", "distance_m", "p_safe"} <= set(s)
        assert s["distance_m"] == pytest.approx(float(np.hypot(s["x"], s["y"])), abs=1e-6)
    scored = json.loads((out / "score.json").read_text())["rows"][0]  # against the truth, on the ground side
    assert scored["fp_pct"] is not None and scored["dem_mean_abs_m"] is not None and "vs_truth" not in doc


def _without_timings(d):
    if isinstance(d, dict):
        return {k: _without_timings(v) for k, v in d.items() if k not in ("wall_s", "cpu_s")}
    if isinstance(d, list):
        return [_without_timings(v) for v in d]
    return d


def test_process_twice_gives_the_same_bytes(processed):
    a, b = processed
    for name in ("elevation", "hazard", "state", "psafe", "filled", "sigma"):
        assert (a / f"{name}.npy").read_bytes() == (b / f"{name}.npy").read_bytes(), name
    ja, jb = (json.loads((d / "result.json").read_text()) for d in (a, b))
    assert _without_timings(ja) == _without_timings(jb)


def test_hazard_picture_greys_the_unknown_state(pair_dir, tmp_path, monkeypatch):
    """hazard.npy writes unknown as 1.0; the hazard-score panel must not draw it as the darkest hazard."""
    seen: list = []
    real = plots.map_figure
    monkeypatch.setattr(plots, "map_figure", lambda panels, title="", **kw: seen.append(panels) or real(panels, title))
    assert main(["process", str(pair_dir), "--out", str(tmp_path)]) == 0
    state = np.load(tmp_path / "state.npy")
    assert (state == 2).any()  # the property is only tested when there is unknown ground
    score = [p for panels in seen for p in panels if p.title.startswith("hazard score")]
    assert len(score) == 1 and score[0].unknown is not None
    assert np.array_equal(score[0].unknown, state == 2)


def test_scalar_panel_draws_its_unknown_pixels_grey():
    from matplotlib.colors import to_rgba

    score = np.full((20, 20), 1.0, np.float32)
    score[:, :5] = np.nan
    unknown = np.zeros_like(score, bool)
    unknown[10:, 5:] = True  # unknown: 1.0 like the hazard at [:10, 5:]
    fig = plots.map_figure([plots.Panel("scalar", score, "hazard score", "score", "magma_r", 0, 1, unknown=unknown)])
    overlay = fig.axes[0].images[-1].get_array()
    assert np.allclose(overlay[15, 10], to_rgba(UNKNOWN))
    assert overlay[5, 10][3] == 0 and overlay[15, 2][3] == 0  # known hazard and outside stay as they were
    legend = fig.axes[0].get_legend()
    assert legend is not None and any("unknown 50.0 %" in t.get_text() for t in legend.get_texts())
    plots._plt().close(fig)


def test_clustered_sites_share_one_label_in_rank_order():
    sites = [plots.Site(100, 100, 2, 1), plots.Site(300, 300, 2, 2), plots.Site(102, 101, 2, 3)]
    fig = plots.map_figure([plots.Panel("image", np.zeros((512, 512), np.uint8), "image", sites=sites)])
    labels = sorted(t.get_text() for t in fig.axes[0].texts)
    assert labels == ["1,3", "2"]  # one site per label drew "3" over "1"
    plots._plt().close(fig)


def _table(path: Path, seeds: list[int]) -> Path:
    path.write_text(json.dumps({"seeds": seeds, "scenes": {"thesis": {"digest": "x", "scenarios": {}}}}))
    return path


def test_scenes_measure_never_drops_scenes_measured_on_other_seeds(tmp_path, capsys, monkeypatch):
    table = _table(tmp_path / "t.json", list(range(1000, 1010)))
    before = table.read_bytes()
    monkeypatch.setattr(lib, "measure", lambda *a, **k: pytest.fail("measured before refusing"))
    assert main(["scenes", "mare", "--measure", "--seeds", "1", "--table", str(table)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "would drop them" in err and "thesis" in err, err
    assert table.read_bytes() == before
    with pytest.raises(SceneError, match="would drop"):
        lib.merge_shares(json.loads(before), {"seeds": [1000], "scenes": {"mare": {}}})
    # the same seeds merge, and re-measuring every scene of the table on new seeds replaces it
    same = lib.merge_shares(json.loads(before), {"seeds": list(range(1000, 1010)), "scenes": {"mare": {}}})
    assert set(same["scenes"]) == {"thesis", "mare"}
    assert set(lib.merge_shares(json.loads(before), {"seeds": [1000], "scenes": {"thesis": {}}})["scenes"]) == {
        "thesis"
    }


@pytest.mark.parametrize("extra", [["--seeds", "3"], ["--workers", "2"]])
def test_scenes_measure_options_without_measure_are_refused(capsys, extra):
    assert main(["scenes", *extra]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "only with --measure" in err, err


def test_scene_measurement_shows_progress_and_keeps_job_order(monkeypatch, capsys):
    monkeypatch.setattr(lib, "measure_one", lambda n, s, seed, a: float(a + seed))
    jobs = [("mare", "vertical", 1000 + i, 50 * i) for i in range(4)]
    assert lib._measure_jobs(jobs, 1, True) == [float(a + seed) for _, _, seed, a in jobs]
    err = capsys.readouterr().err
    assert "measure [" in err and "4/4" in err
    assert lib._measure_jobs(jobs, 1, False) and capsys.readouterr().err == ""


@pytest.mark.parametrize(
    "extra, message",
    [(["--supersample", "0"], "--supersample must be 1..8"), (["--sun", "10,0"], "elevation must be in (0, 90]")],
)
def test_render_refuses_bad_render_options_before_creating_out(tmp_path, capsys, extra, message):
    out = tmp_path / "out"
    assert main(["render", "--scenario", "vertical", "--pairs", "600/300", *extra, "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and message in err, err
    assert not out.exists()  # an empty --out was left behind


def test_report_page_names_the_frames_used(processed):
    page = (processed[0] / "report.html").read_text()
    assert "2 frames" in page


def test_result_and_report_have_the_same_permissions_as_the_arrays(processed):
    """write_atomic's temporary file was 0600: result.json and report.html unreadable to other users."""
    out = processed[0]
    mode = (out / "elevation.npy").stat().st_mode & 0o777
    assert (out / "result.json").stat().st_mode & 0o777 == mode
    assert (out / "report.html").stat().st_mode & 0o777 == mode


def test_contact_sheet_pads_an_odd_count_with_a_tile_that_says_so(tmp_path):
    """An odd number of entries ended with an all-black tile, which read as a black render."""
    import cv2

    from ground_sim.descent import contact_sheet

    img = np.full((64, 64), 128, np.uint8)
    entries = [("a", (img, img)), ("b", (img, img, img)), ("c", (img, img))]
    sheet = cv2.imread(str(contact_sheet(entries, tmp_path / "c.png")), 0)
    half = sheet.shape[1] // 2
    pad = sheet[sheet.shape[0] // 2 :, half:]
    assert sheet.shape == (2 * 220, 2 * half) and pad.max() == 255  # a label
    assert pad[30:-3, 3:-3].min() > 0  # and no black tile
    # one entry alone is its own row: a filler took a third of the sheet in the commonest case
    one = cv2.imread(str(contact_sheet(entries[:1], tmp_path / "one.png")), 0)
    assert one.shape == (220, half)


def test_a_render_worker_that_dies_is_one_line_not_a_traceback(tmp_path, monkeypatch, capsys):
    """A worker killed outright (the OOM killer) ended `render` with an 18-line BrokenProcessPool traceback (stop 63's
    QA); it is now one line that says what died and what was kept, exit 1, as `evaluate` and `landings` say it."""
    from concurrent.futures.process import BrokenProcessPool

    from ground_sim import descent

    def dies(*args, **kw):
        raise BrokenProcessPool("A process in the process pool was terminated abruptly")

    monkeypatch.setattr(descent, "render_scenario", dies)
    assert main(["render", "--scenario", "vertical", "--pairs", "600/300", "--out", str(tmp_path / "r")]) == 1
    err = capsys.readouterr().err
    assert "Traceback" not in err and err.count("\n") == 1
    assert "a worker process died" in err and "nothing new in" in err
