"""``hazard-hil process``: outputs on a synthetic pair with truth, clean errors on bad input."""

from __future__ import annotations

import html
import json
import math
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
from browser import browser_available, check_page
from synthetic import crater, make_pair

from hil_server.cli import main
from protocol.outdir import LOCK_NAME
from protocol.pairdir import Pair, Pose, write_pair


def _pair(tmp_path, depth: bool = True):
    cam, p1, p2, i1, i2, z = make_pair(160, 150.0, 75.0, crater(20.0, 4.0), seed=21)
    gt_h = np.zeros_like(z)
    gt_h[60:100, 60:80] = 1.0  # inside the area both images see
    truth = {"elevation": z, "hazard": gt_h}
    if depth:  # a nadir camera: the z-depth is the height above the ground
        truth["depth"] = (150.0 - z).astype(np.float32)
    return write_pair(tmp_path / "pair", Pair(cam, (p1, p2), (i1, i2), truth=truth)), z


def _dem_err(out: Path) -> float:
    """The DEM's mean |error| against the truth, as `process` scored it (score.json)."""
    return json.loads((out / "score.json").read_text())["rows"][0]["dem_mean_abs_m"]


def test_process_writes_outputs(tmp_path, capsys):
    d, z = _pair(tmp_path)
    out = tmp_path / "out"
    assert main(["process", str(d), "--out", str(out), "--preset", "fast"]) == 0
    for f in ("elevation.npy", "state.npy", "result.json", "dem.png", "hazard.png", "report.html"):
        assert (out / f).is_file(), f
    for f in ("score.json", "confusion.png", "dem_error.png"):  # the truth's, written by studies.quicklook
        assert (out / f).is_file(), f
    elev = np.load(out / "elevation.npy")
    assert elev.dtype == np.float32 and elev.shape == z.shape
    doc = json.loads((out / "result.json").read_text())
    assert doc["level"] == "full" and doc["params"]["name"] == "fast"
    assert set(doc["timings"]["full_dem"]) == {"wall_s", "cpu_s"}
    assert "vs_truth" not in doc  # the flight side's record holds no truth (DESIGN.md)
    row = json.loads((out / "score.json").read_text())["rows"][0]
    assert row["dem_mean_abs_m"] < 0.5  # crater at 150 m, 160 px
    assert row["hazards_in_scene_pct"] > 0  # the truth's unsafe strip is scored
    said = capsys.readouterr()
    assert "full" in said.out and f"against the truth: FP {row['fp_pct']:.2f} %" in said.out
    # the trees are calibrated for 512, 256 and 128 px: at 160 px P(safe) falls back, which only result.json used to say
    assert doc["info"]["psafe_fallback"] in said.err and said.err.startswith("warning: calibrated P(safe)"), said.err
    # and in result.json and on the page, not on the console alone (QA of stop 66: a run on swapped frames was a
    # green "full" there)
    assert len(doc["warnings"]) == 1 and doc["warnings"][0].startswith(doc["info"]["psafe_fallback"])
    assert (
        ">Warnings<" in (out / "report.html").read_text()
        and "falls back to the Gaussian rule" in (out / "report.html").read_text()
    )
    if browser_available():
        page = check_page(out / "report.html")
        assert page.ok and page.images == 4, page  # dem, hazard, confusion, dem_error: all load, no console error
    assert ">Against ground truth<" in (out / "report.html").read_text()


def test_the_sites_table_says_how_sites_are_ranked_and_what_their_psafe_is(tmp_path):
    """Sites at P(safe) 0.988 under the caption's 0.99 floor, ranked out of that order, read as a fault (QA round 2 of
    stop 78): the ranking rule and the grid's P(safe) are said beside the table, with each site's distance."""
    from hilkit import small_descent

    small_descent(tmp_path / "d", ["1000/500"])  # 128 px: the vertical 1000/500 pair offers sites
    assert main(["process", "--no-figures", str(tmp_path / "d" / "1000_500"), "--out", str(tmp_path / "o")]) == 0
    doc = json.loads((tmp_path / "o" / "result.json").read_text())
    assert len(doc["sites"]) > 1
    page = (tmp_path / "o" / "report.html").read_text()
    assert "to the aim point [m]" in page and "Ranked by site P(safe) in steps of 0.01" in page
    ranked = [(math.floor(s["p_safe"] / 0.01 + 1e-6), -s["distance_m"]) for s in doc["sites"]]
    assert ranked == sorted(ranked, reverse=True)  # the rule the page states
    # the thesis's spiral search has no P(safe): its page gave the rule above over a table of dashes (QA of stop 84)
    args = ["process", "--no-figures", str(tmp_path / "d" / "1000_500"), "--preset", "thesis"]
    assert main([*args, "--out", str(tmp_path / "t")]) == 0
    doc = json.loads((tmp_path / "t" / "result.json").read_text())
    page = (tmp_path / "t" / "report.html").read_text()
    assert len(doc["sites"]) > 1 and "site P(safe)" not in page and "steps of" not in page
    assert "spiral search" in page and "margin (1 - max hazard)" in page
    rings = [(math.floor(s["distance_m"] / 3.0), -s["margin"]) for s in doc["sites"]]
    assert rings == sorted(rings)  # nearest ring first, then by margin: the rule this page states


def test_process_no_figures_writes_the_same_maps_and_scores_and_no_picture(tmp_path, capsys):
    """`process --no-figures`: the arrays, result.json and score.json as with the pictures, and the page says why
    it has none; an earlier run's pictures in OUT go, as its other outputs do."""
    d, _ = _pair(tmp_path)
    assert main(["process", str(d), "--out", str(tmp_path / "drawn")]) == 0
    out = tmp_path / "bare"
    shutil.copytree(tmp_path / "drawn", out)
    assert main(["process", "--no-figures", str(d), "--out", str(out)]) == 0
    assert "report: " in capsys.readouterr().out
    assert not list(out.glob("*.png")), list(out.glob("*.png"))
    for f in ("elevation.npy", "state.npy", "psafe.npy"):
        assert np.array_equal(np.load(out / f), np.load(tmp_path / "drawn" / f), equal_nan=True), f
    rows = [json.loads((o / "score.json").read_text())["rows"][0] for o in (tmp_path / "drawn", out)]
    same = [{k: v for k, v in r.items() if k not in ("figure", "output_dir")} for r in rows]
    assert same[0] == same[1] and rows[0]["figure"] and not rows[1].get("figure")
    page = (out / "report.html").read_text()
    assert "<img" not in page and "Pictures not drawn (the run was asked for none: --no-figures)." in page
    assert ">Against ground truth<" in page  # the scores' table stays
    # a tool reading result.json tells a run asked for no pictures from one that lost them
    assert [json.loads((o / "result.json").read_text())["figures"] for o in (tmp_path / "drawn", out)] == [True, False]


def test_a_pair_that_fits_only_without_its_pictures_is_told_so_and_runs_without_them(tmp_path, capsys, monkeypatch):
    """The pictures drawn after the maps are most of the memory a large pair needs (~180 MiB + 110 B per pixel):
    a machine with room for the maps alone is told that --no-figures fits, and the run with it goes through."""
    from flight_sw import validate

    d, _ = _pair(tmp_path)
    bare, drawn = (validate.peak_memory_bytes(160, 160, 2, pictures) for pictures in (False, True))
    monkeypatch.setattr(validate, "memory_room", lambda: ((bare + drawn) // 2, "of memory is available"))
    assert main(["process", str(d), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "160x160 px x 2 frames needs ~" in err and err.rstrip().endswith(
        "without its pictures (--no-figures) it would fit"
    )
    assert main(["process", "--no-figures", str(d), "--out", str(tmp_path / "o")]) == 0
    monkeypatch.setattr(validate, "memory_room", lambda: (bare // 2, "of memory is available"))  # fits neither way
    assert main(["process", str(d), "--out", str(tmp_path / "o2")]) == 2
    assert "--no-figures" not in capsys.readouterr().err


def test_process_without_gt_depth_scores_over_the_covered_pixels(tmp_path, capsys):
    """A truth without gt_depth_i1.npy cannot give the ground both frames truly see, as `score` needs: `process`
    still scores its map where it covers, says so, and judges no site."""
    d, z = _pair(tmp_path, depth=False)
    out = tmp_path / "out"
    assert main(["process", str(d), "--out", str(out)]) == 0
    said = capsys.readouterr()
    row = json.loads((out / "score.json").read_text())["rows"][0]
    assert row["scored_over"] == "covered" and "gt_depth_i1.npy" in row["truth_problem"]
    assert row["dem_mean_abs_m"] < 0.5 and row["fp_pct"] is not None and row["sites_truly_safe"] is None
    assert "of the map's covered pixels" in said.out and "not as `hazard-hil score` scores it" in said.err
    page = (out / "report.html").read_text()
    assert "nothing to score against" not in said.err + page  # it scored what it could (QA of stop 73)
    summary = json.loads((out / "score.json").read_text())["summary"]
    assert summary["scored_over"] == "covered" and "gt_depth_i1.npy" in summary["truth_problem"]
    assert (out / "dem_error.png").is_file() and (out / "confusion.png").is_file()  # the pixel scores drawn too


def test_process_writes_no_score_when_the_truth_scores_nothing(tmp_path, capsys):
    """A pair with only gt_shadow_i1.npy got a score.json of nulls, linked from nowhere (QA of stop 73)."""
    d, z = _pair(tmp_path, depth=False)
    for f in ("gt_hazard_i1.npy", "gt_elevation_i1.npy"):
        (d / f).unlink()
    np.save(d / "gt_shadow_i1.npy", np.zeros(z.shape, bool))
    assert main(["process", str(d), "--out", str(tmp_path / "o")]) == 0
    said = capsys.readouterr()
    assert not any((tmp_path / "o" / f).exists() for f in ("score.json", "confusion.png", "dem_error.png"))
    assert (
        "nothing of this output could be scored against the truth" in said.err and "against the truth" not in said.out
    )


def test_a_refused_score_file_costs_process_nothing_else(tmp_path, capsys):
    """score.json refused (a directory by its name): the run stopped before its pictures and page, and said to run
    it again "for the rest", which could not help (QA of stop 73). Now the flight side's files are all written, and
    the refusal is said, exit 1."""
    d, _ = _pair(tmp_path)
    out = tmp_path / "o"
    (out / "score.json").mkdir(parents=True)
    assert main(["process", str(d), "--out", str(out)]) == 1
    err = capsys.readouterr().err
    assert all((out / f).is_file() for f in ("result.json", "dem.png", "hazard.png", "report.html"))
    assert "score.json" in err and "run it again for the rest" not in err, err


def test_a_second_run_into_the_same_out_leaves_nothing_of_the_first(tmp_path):
    """`fast` writes sigma.npy and the thesis preset does not: a thesis run after a fast one left the fast
    run's sigma beside the thesis maps, where a reader would take it for theirs."""
    d, _ = _pair(tmp_path)
    out = tmp_path / "out"
    # the maps alone: an earlier run's pictures go as its other outputs do (test_process_no_figures_writes_...)
    assert main(["process", "--no-figures", str(d), "--out", str(out), "--preset", "fast"]) == 0
    assert (out / "sigma.npy").is_file()
    filled, elev = np.load(out / "filled.npy"), np.load(out / "elevation.npy")
    assert filled.dtype == bool and filled.shape == elev.shape and np.isfinite(elev[filled]).all()
    assert main(["process", "--no-figures", str(d), "--out", str(out), "--preset", "thesis"]) == 0
    assert json.loads((out / "result.json").read_text())["preset"] == "thesis"
    assert not (out / "sigma.npy").exists() and not (out / "filled.npy").exists()


def test_process_holds_its_out_as_the_other_commands_do(tmp_path, capsys):
    """It wrote into a directory a live run was writing (QA 64b)."""
    import subprocess

    d, _ = _pair(tmp_path)
    out = tmp_path / "out"
    hold = (
        "import sys\nfrom protocol.outdir import claim_out\nwith claim_out(sys.argv[1], 'run'):\n"
        "    print('held', flush=True)\n    sys.stdin.readline()"
    )
    proc = subprocess.Popen(
        [sys.executable, "-c", hold, str(out)], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
    )
    try:
        assert proc.stdout is not None and proc.stdout.readline().strip() == "held"
        assert main(["process", str(d), "--out", str(out)]) == 2
        assert f"is being written by hazard-hil run (pid {proc.pid})" in capsys.readouterr().err
        assert sorted(p.name for p in out.iterdir()) == [LOCK_NAME]
    finally:
        proc.kill()
        proc.wait()
    assert main(["process", "--no-figures", str(d), "--out", str(out)]) == 0


def test_a_run_interrupted_while_it_writes_leaves_nothing_of_the_run_before(tmp_path, monkeypatch, capsys):
    """A kill mid-write left the earlier run's result.json, sigma and pictures beside the new maps, and `score`
    took the mix for one run (stop 63's QA). The earlier outputs go first; each new one is renamed into place."""
    from flight_sw import cli

    d, _ = _pair(tmp_path)
    out = tmp_path / "out"
    assert main(["process", str(d), "--out", str(out), "--preset", "thesis"]) == 0
    before = {p.name for p in out.iterdir()}
    assert {"result.json", "report.html", "hazard.png", "psafe.npy"} <= before
    saved = cli._save_npy

    def dies_at_psafe(path, arr):
        if path.name == "psafe.npy":
            raise KeyboardInterrupt
        saved(path, arr)

    monkeypatch.setattr(cli, "_save_npy", dies_at_psafe)
    assert main(["process", str(d), "--out", str(out), "--preset", "fast"]) == 130  # said as interrupted
    left = {p.name for p in out.iterdir()} - {LOCK_NAME}  # process holds its --out (QA 64b)
    assert left == {"elevation.npy", "hazard.npy", "state.npy"}, left  # this run's, whole; none of the thesis run's
    said = capsys.readouterr().err
    assert "it holds this run's elevation.npy, hazard.npy, state.npy only (no result.json: incomplete)" in said
    monkeypatch.setattr(cli, "_save_npy", saved)
    # a whole earlier run again (its maps, result.json and page; pictures are outputs as these are)
    assert main(["process", "--no-figures", str(d), "--out", str(out), "--preset", "thesis"]) == 0
    capsys.readouterr()
    real_unlink = Path.unlink

    def dies_at_the_second(self, *a, **kw):  # a stop while the earlier run's outputs are removed
        if self.name != "result.json" and self.parent == out:
            raise KeyboardInterrupt
        real_unlink(self, *a, **kw)

    monkeypatch.setattr(Path, "unlink", dies_at_the_second)
    assert main(["process", str(d), "--out", str(out), "--preset", "fast"]) == 130
    said = capsys.readouterr().err  # they are the thesis run's, and said so (review of stop 63: "this run's")
    assert f"stopped while removing an earlier run's outputs from {out}; it still holds the earlier run's " in said
    assert "this run's" not in said


def test_process_deadline_zero_is_degraded(tmp_path, capsys):
    d, _ = _pair(tmp_path)
    out = tmp_path / "out0"
    assert main(["process", "--no-figures", str(d), "--out", str(out), "--deadline", "0"]) == 0
    doc = json.loads((out / "result.json").read_text())
    assert doc["level"] == "image_only" and doc["degraded"] is True
    # and why: the plan had no time left for the coarse DEM (result.json keeps the figures)
    plan = doc["info"]["plan"]
    assert plan["coarse_dem_left_s"] <= 0 < plan["coarse_dem_need_s"]
    said = capsys.readouterr().out
    assert "skipped " in said and "coarse_dem not started: " in said


def test_an_image_only_map_of_every_preset_calls_no_ground_safe_and_offers_no_site(tmp_path, capsys, monkeypatch):
    """The v1 flow (`thesis`, `fast_v1`) at the image-only level wrote 0 (safe) on ground it marked unknown, offered
    sites with no elevation under them (2 of 5 not truly clear), and `score` refused its own output (QA of stop 66).
    DESIGN.md: an unknown pixel is written as 1.0."""
    from hilkit import small_descent

    manifest = small_descent(tmp_path / "pairs", ["600/300"], px=96)
    d = manifest.parent / json.loads(manifest.read_text())["pairs"][0]["path"]
    from flight_sw import pipeline

    # no time for a DEM, and time for the rest (a deadline of 0.02 s did so on a quiet machine only)
    monkeypatch.setattr(pipeline.Clock, "decide", lambda self, info, stage, reserve_s: not stage.endswith("_dem"))
    for preset in ("fast", "thesis", "fast_v1"):
        out = tmp_path / preset
        assert main(["process", "--no-figures", str(d), "--out", str(out), "--preset", preset]) == 0  # maps: no picture
        doc = json.loads((out / "result.json").read_text())
        assert doc["level"] == "image_only" and doc["sites"] == [], (preset, doc["sites"])
        hazard, state = np.load(out / "hazard.npy"), np.load(out / "state.npy")
        assert np.all(hazard[state == 2] == 1.0) and not np.any(state == 0), preset
        assert main(["score", str(d), str(out)]) == 0, capsys.readouterr().err


def test_process_bad_input_is_one_line(tmp_path, capsys):
    assert main(["process", str(tmp_path / "missing"), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip()
    assert "not a directory" in err and len(err.splitlines()) == 1
    d, _ = _pair(tmp_path)
    (d / "i2.png").unlink()
    assert main(["process", str(d), "--out", str(tmp_path / "o")]) == 2
    assert "missing image i2.png" in capsys.readouterr().err


def test_process_refuses_a_camera_too_large_for_this_machine_before_reading_it(tmp_path, capsys, monkeypatch):
    from types import SimpleNamespace

    import psutil

    from flight_sw.validate import peak_memory_bytes

    d, _ = _pair(tmp_path)
    assert 34 * 2**20 < peak_memory_bytes(160, 160, 2) < 40 * 2**20  # 160^2: the process's base and ~5 MiB of work
    # and the pictures drawn after the maps: a camera that passed the check ended in a traceback while drawing them
    # (QA of stop 71: `process` peaked at 1.34 GiB at 2048 px, where the pipeline's model said 830 MiB)
    need = peak_memory_bytes(160, 160, 2, pictures=True)
    assert need - peak_memory_bytes(160, 160, 2) == 180 * 2**20 + 110 * 160 * 160
    for px, measured_mib in ((512, 255), (1024, 510), (2048, 1372), (4096, 4813)):
        assert measured_mib * 2**20 < peak_memory_bytes(px, px, 2, pictures=True) < 1.2 * measured_mib * 2**20, px
    monkeypatch.setattr(psutil, "virtual_memory", lambda: SimpleNamespace(available=need - 1))
    assert main(["process", str(d), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip()
    assert "160x160 px x 2 frames needs ~" in err and "MiB of memory is available" in err and len(err.splitlines()) == 1
    assert not (tmp_path / "o").exists()  # nothing run, nothing written
    monkeypatch.setattr(psutil, "virtual_memory", lambda: SimpleNamespace(available=need))
    assert main(["process", str(d), "--out", str(tmp_path / "o")]) == 0
    # the largest camera the format allows: ~12 GiB for a pair, refused on a machine with 8 GiB free
    monkeypatch.setattr(psutil, "virtual_memory", lambda: SimpleNamespace(available=8 * 2**30))
    doc = json.loads((d / "pair.json").read_text())
    doc["camera"].update(width=8192, height=8192)
    (d / "pair.json").write_text(json.dumps(doc))
    assert main(["process", str(d), "--out", str(tmp_path / "o2")]) == 2
    assert "8192x8192 px x 2 frames" in capsys.readouterr().err


def test_the_memory_room_counts_an_address_space_limit():
    """Under `ulimit -v` (`prlimit --as`) a 4096 px pair was started with 23 GiB free, and numpy ran out of address
    space 14 s later with a traceback. The room is now the least of free memory and what the limit leaves."""
    import subprocess
    import sys

    code = (
        "import resource, psutil\n"
        "import flight_sw.validate as v\n"
        "v._cgroup_room = lambda: None  # a container's own limit would name itself instead\n"
        "memory_room = v.memory_room\n"
        "vms = psutil.Process().memory_info().vms\n"
        "resource.setrlimit(resource.RLIMIT_AS, (vms + 64 * 2**20, resource.RLIM_INFINITY))\n"
        "room, what = memory_room()\n"
        "print(room <= 64 * 2**20, what)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True).stdout
    assert out.strip() == "True of address space is left under this process's limit (ulimit -v)", out


def test_process_warns_when_the_images_cannot_check_the_navigation_poses(tmp_path, capsys):
    """Frames swapped (or mislabelled): the DEM was 46 m off and the run said "full" like any other; the reason sat
    in result.json only. A clean pair says nothing."""
    import shutil

    from hilkit import small_descent

    pair = small_descent(tmp_path / "pairs", ["300/150"], px=256).parent / "300_150"
    assert main(["process", "--no-figures", str(pair), "--out", str(tmp_path / "ok")]) == 0
    err = capsys.readouterr().err
    assert "navigation pose" not in err and "P(safe)" not in err  # 256 px has its own trees (stop 63)
    swapped = tmp_path / "swapped"
    shutil.copytree(pair, swapped)
    (swapped / "i1.png").write_bytes((pair / "i2.png").read_bytes())
    (swapped / "i2.png").write_bytes((pair / "i1.png").read_bytes())
    assert main(["process", "--no-figures", str(swapped), "--out", str(tmp_path / "bad")]) == 0
    err = capsys.readouterr().err
    # texture, and no consistent match: the image does not bear the pose out (said as "could not check" until the
    # withheld sites' reason said "contradict" of the same frame, stop 61's QA)
    assert "warning: frame 1: its image does not match where its navigation pose says" in err, err
    assert "whose image does not match frame 0's where its navigation pose says" in err, err
    info = json.loads((tmp_path / "bad" / "result.json").read_text())["info"]["pose_refinement"]
    assert info["refined"] is False and info["reason"] in err


def test_process_warns_when_the_images_disagree_with_the_navigation_pose(tmp_path, capsys):
    """A 30 m lateral navigation error at 150 m: the refinement matched the images, found they need a 5 deg
    correction - beyond any navigation error - and kept the pose, and the run said nothing about its 21 m DEM
    error."""
    import shutil

    from hilkit import small_descent

    pair = small_descent(tmp_path / "pairs", ["300/150"], px=256).parent / "300_150"
    gross = tmp_path / "gross"
    shutil.copytree(pair, gross)
    doc = json.loads((gross / "pair.json").read_text())
    doc["frames"][1]["position_m"][0] += 30.0
    (gross / "pair.json").write_text(json.dumps(doc))
    assert main(["process", "--no-figures", str(gross), "--out", str(tmp_path / "o")]) == 0
    err = capsys.readouterr().err
    assert "warning: frame 1: the images disagree with its navigation pose (attitude correction" in err, err
    res = json.loads((tmp_path / "o" / "result.json").read_text())
    info = res["info"]["pose_refinement"]
    assert info["refined"] is False and info["reason"].startswith("attitude correction")
    assert res["sites"] == [] and res["info"]["no_site_reason"].startswith("no site is offered on this map")


def _pitched_pair(tmp_path: Path, deg: float) -> tuple[Path, Path]:
    """A rendered 256 px 300/150 pair, and a copy whose lower frame's navigation attitude is pitched ``deg``."""
    import math
    import shutil

    from hilkit import small_descent

    pair = small_descent(tmp_path / "pairs", ["300/150"], px=256).parent / "300_150"
    off = tmp_path / "off"
    shutil.copytree(pair, off)
    doc = json.loads((off / "pair.json").read_text())
    a = math.radians(deg)
    rx = np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])
    doc["frames"][1]["R_world_to_cam"] = (rx @ np.array(doc["frames"][1]["R_world_to_cam"])).tolist()
    (off / "pair.json").write_text(json.dumps(doc))
    return pair, off


def test_no_site_is_offered_on_a_map_resting_on_a_pose_the_images_contradict(tmp_path, capsys):
    """A 2 deg pitch of a 300/150 pair's lower frame: refused and warned, and a pair cannot leave its frame out, so
    the map rests on it (DEM 27 m off); no altimeter check fires. Sites on such a map had been offered all the
    same (a 3 deg pitch, stop 59's QA: FP 2.07 %, the top site unsafe)."""
    pair, off = _pitched_pair(tmp_path, 2.0)
    assert main(["process", "--no-figures", str(off), "--out", str(tmp_path / "o")]) == 0
    err = capsys.readouterr().err
    assert "warning: frame 1: the images disagree with its navigation pose" in err
    assert "warning: no site is offered on this map: it rests on frame 1" in err, err
    res = json.loads((tmp_path / "o" / "result.json").read_text())
    assert "altimeter_disagreement" not in res["info"] and res["sites"] == []
    assert "rests on frame 1, whose navigation pose the images contradict" in res["info"]["no_site_reason"]
    assert res["info"]["sites_withheld"] == res["info"]["no_site_reason"]  # the HIL's fused map withholds on it
    # the clean pair offers its sites
    assert main(["process", "--no-figures", str(pair), "--out", str(tmp_path / "clean")]) == 0
    clean = json.loads((tmp_path / "clean" / "result.json").read_text())["info"]
    assert "sites_withheld" not in clean
    # a principal point off the image: the DEM-altimeter check cannot be made, and says so (it crashed once)
    doc = json.loads((pair / "pair.json").read_text())
    doc["camera"]["cx"] = doc["camera"]["width"] + 40.0
    (off / "pair.json").write_text(json.dumps(doc))
    capsys.readouterr()
    assert main(["process", "--no-figures", str(off), "--out", str(tmp_path / "cx")]) == 0
    said = capsys.readouterr()
    assert "frame 0's altimeter was not checked against the DEM: its optical axis meets the ground off" in said.out
    assert "warning: the camera's principal point (296, " in said.err, said.err
    assert json.loads((tmp_path / "cx" / "result.json").read_text())["info"]["altimeter_dem_unchecked"]


def test_process_says_what_the_pose_refinement_corrected_and_can_be_told_not_to(tmp_path, capsys):
    """A correction was said only in result.json, and `process` had no way to run without it (stop 59's QA)."""
    _, off = _pitched_pair(tmp_path, 0.3)
    assert main(["process", "--no-figures", str(off), "--out", str(tmp_path / "on")]) == 0
    said = capsys.readouterr().out
    # a nadir pair: the fit holds the relative rotation and turns the baseline, and says both (a 1 deg pitch read
    # "corrected by 0.10 deg" with the baseline's 0.54 deg unsaid, stop 61's QA)
    assert "refined from the images: frame 1 (near-nadir: relative rotation held across the view, corrected" in said
    assert "the baseline turned 0." in said, said
    assert main(["process", "--no-figures", str(off), "--out", str(tmp_path / "raw"), "--no-refine-pose"]) == 0
    said = capsys.readouterr().out
    raw = json.loads((tmp_path / "raw" / "result.json").read_text())
    assert "refined from the images" not in said and raw["params"]["refine_pose"] is False
    assert "pose_refinement" not in raw["info"]


def test_a_later_frame_the_images_cannot_check_is_left_out_of_the_maps(tmp_path, capsys):
    """A noise image as the last of four frames was refused by the pose refinement, warned about, and swept all
    the same: DEM 7.9 m off against 0.34 m without it (stop 59's QA). A frame the images contradict is now left
    out; one that merely overlaps little stays."""
    import shutil

    from hilkit import small_descent

    from flight_sw.pipeline import _contradicted_frames, _frames_to_leave_out
    from flight_sw.pose_refine import DEGENERATE, DISAGREES, FEW_MATCHES, KEPT, NO_OVERLAP, SKIPPED, UNMATCHED

    root = small_descent(tmp_path / "pairs", ["600/300", "300/150"], px=256).parent
    three = tmp_path / "three"
    shutil.copytree(root / "600_300", three)
    low = json.loads((root / "300_150" / "pair.json").read_text())
    doc = json.loads((three / "pair.json").read_text())
    doc["frames"].append({**low["frames"][1], "image": "i3.png", "time_s": doc["frames"][1]["time_s"] + 10.0})
    doc["true_frames"].append({**low["true_frames"][1], "image": "i3.png"})
    (three / "pair.json").write_text(json.dumps(doc))
    import cv2

    shutil.copy(root / "300_150" / low["frames"][1]["image"], three / "i3.png")
    # the 300 m frame's image is another view (frame 0's, turned 90 deg): it matches, and contradicts its pose
    cv2.imwrite(str(three / "i2.png"), np.rot90(cv2.imread(str(three / "i1.png"), cv2.IMREAD_GRAYSCALE)).copy())
    assert main(["process", "--no-figures", str(three), "--out", str(tmp_path / "o")]) == 0
    err = capsys.readouterr().err
    res = json.loads((tmp_path / "o" / "result.json").read_text())
    assert res["info"]["frames_dropped"] == [1], res["info"].get("pose_refinement")
    assert "warning: frame 1: its image does not match" in err and "left out of the maps" in err, err
    # and frame 2 (150 m) shares too little with frame 0 to be checked: nothing left confirms frame 0's pose
    assert "no frame left confirms frame 0's pose" in res["info"]["sites_withheld"]
    # what is left is a 600/150 pair, whose DEM is as good as that pair's alone
    pair = tmp_path / "pair"
    shutil.copytree(three, pair)
    doc["frames"].pop(1)
    doc["true_frames"].pop(1)
    (pair / "pair.json").write_text(json.dumps(doc))
    assert main(["process", "--no-figures", str(pair), "--out", str(tmp_path / "pair")]) == 0
    alone = _dem_err(tmp_path / "pair")
    assert _dem_err(tmp_path / "o") <= 1.2 * alone + 0.05
    # a noise image there: its corners track nothing (it read "too few matches", as a small overlap does, and was
    # swept: a DEM 6.9 m off, stop 59's review)
    cv2.imwrite(str(three / "i2.png"), (np.random.default_rng(1).random((256, 256)) * 255).astype(np.uint8))
    assert main(["process", "--no-figures", str(three), "--out", str(tmp_path / "noise")]) == 0
    noisy = json.loads((tmp_path / "noise" / "result.json").read_text())["info"]
    assert noisy["frames_dropped"] == [1], noisy["pose_refinement"]["frames"]
    # frame 0 is never left alone, and small images (whose clean frames fail the checks too) drop nothing
    info = {"frames": [{"frame": 1, "refined": False, "verdict": UNMATCHED, "reason": "too few RANSAC inliers"}]}
    assert _frames_to_leave_out(info, 3, 256) == [1] and _frames_to_leave_out(info, 2, 256) == []
    assert _frames_to_leave_out(info, 3, 128) == []
    both = {"frames": [dict(info["frames"][0]), {"frame": 2, "refined": False, "verdict": DISAGREES}]}
    assert _frames_to_leave_out(both, 3, 256) == []
    # a small overlap is the frames' geometry, not evidence against one: a clean 100 m frame of a 1000 m descent
    # was left out, and the map became the 1000/500 pair's (stop 59's review); nor is a degenerate geometry, a pose
    # the images confirmed, or one the deadline left untried
    for verdict in (NO_OVERLAP, FEW_MATCHES, DEGENERATE, KEPT, SKIPPED):
        assert _frames_to_leave_out({"frames": [{"frame": 1, "refined": False, "verdict": verdict}]}, 3, 256) == []
    # every contradicted frame, for the sites of a map that still rests on one: whatever is left, a pair included
    assert _contradicted_frames(both, 3, 256) == [1, 2]
    assert _contradicted_frames(info, 2, 256) == [1] and _contradicted_frames(info, 2, 128) == []


def test_a_deep_descents_last_frame_is_checked_against_the_frame_above_and_left_out_when_wrong(tmp_path, capsys):
    """The last frame of a 256 px 1000/600/300 approach shares too little ground with frame 0 to be checked, and a
    2 deg pitch fault in it left the DEM 52 m off with a note (stop 60's QA). Against the 600 m frame the images
    refuse it: warned, left out, and the map is the 1000/600 pair's."""
    rc = main(["render", "--scenario", "approach", "--frames", "1000,600,300", "--image-size", "256", "--seed", "0",
               "--workers", "1", "--no-progress", "--out", str(tmp_path / "r")])  # fmt: skip
    assert rc == 0
    d = tmp_path / "r" / "1000_600_300"
    assert main(["process", "--no-figures", str(d), "--out", str(tmp_path / "clean")]) == 0
    capsys.readouterr()
    original = json.loads((d / "pair.json").read_text())

    def pitched(k: int, deg: float) -> None:
        doc = json.loads(json.dumps(original))
        c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
        R = np.array([[1, 0, 0], [0, c, -s], [0, s, c]]) @ doc["frames"][k]["R_world_to_cam"]
        doc["frames"][k]["R_world_to_cam"] = R.tolist()
        (d / "pair.json").write_text(json.dumps(doc))

    pitched(2, 2.0)
    assert main(["process", "--no-figures", str(d), "--out", str(tmp_path / "o")]) == 0
    err = capsys.readouterr().err
    res = json.loads((tmp_path / "o" / "result.json").read_text())
    last = res["info"]["pose_refinement"]["frames"][-1]
    assert last["against"] == 1 and last["verdict"] == "disagrees" and res["info"]["frames_dropped"] == [2]
    assert "warning: frame 2: the images disagree with its navigation pose (against frame 1:" in err, err
    assert _dem_err(tmp_path / "o") < 2 * _dem_err(tmp_path / "clean") + 0.5
    # frame 0 pitched instead: the one frame that can check it contradicts it and is left out, and what is left
    # (frame 0 and the unchecked 300 m frame) offers no site, saying frame 0 may be the wrong one; it had been
    # mapped 51-362 m off with nothing withheld (stop 61's QA)
    pitched(0, 1.5)
    assert main(["process", "--no-figures", str(d), "--out", str(tmp_path / "f0")]) == 0
    err = capsys.readouterr().err
    info = json.loads((tmp_path / "f0" / "result.json").read_text())["info"]
    assert info["frames_dropped"] == [1] and "no frame left confirms frame 0's pose" in info["sites_withheld"]
    assert "it may be frame 0's that is wrong" in err, err


def test_process_scores_against_a_derived_truth_where_score_can_derive_one(tmp_path, capsys):
    """Without gt_hazard_i1.npy `process` scores against the hazard DESIGN.md's rules derive from gt_elevation and
    gt_depth, as `score` does; where frame 0 samples the ground too coarsely for that, it scores the DEM alone and
    says why (it pointed to `score`, which then refused the pair: stop 59's QA)."""
    import shutil

    from hilkit import small_descent

    root = small_descent(tmp_path / "pairs", ["600/300", "200/100"], px=128).parent
    said = {}
    for label in ("600_300", "200_100"):
        d = tmp_path / label
        shutil.copytree(root / label, d)
        (d / "gt_hazard_i1.npy").unlink()
        assert main(["process", "--no-figures", str(d), "--out", str(tmp_path / f"o{label}")]) == 0
        said[label] = capsys.readouterr()
    fine = json.loads((tmp_path / "o200_100" / "score.json").read_text())["rows"][0]
    assert fine["truth"] == "derived" and fine["fp_pct"] is not None
    assert "the true hazard was derived from gt_elevation, gt_depth and gt_shadow" in said["200_100"].err
    coarse = json.loads((tmp_path / "o600_300" / "score.json").read_text())["rows"][0]
    assert coarse["scored_over"] == "covered" and coarse["fp_pct"] is None and coarse["dem_mean_abs_m"] > 0
    assert "over half the 3 m footprint" in said["600_300"].err and "give gt_hazard_i1.npy" in said["600_300"].err
    assert "FP" not in said["600_300"].out and "DEM mean |error|" in said["600_300"].out
    assert main(["score", str(tmp_path / "600_300"), str(tmp_path / "o600_300")]) == 2  # as the note says


def test_widest_pair_messages_name_the_directorys_frames():
    """`process --widest-pair` runs frames 0 and n - 1 as a pair: its warnings named the last frame "frame 1", and
    so did the altimeter's (stop 59's note)."""
    from flight_sw.pipeline import _renumber
    from flight_sw.rangefind import altimeter_disagreement

    info = {"pose_refinement": {"frames": [{"frame": 1, "refined": True}]}, "frames_dropped": [1]}
    _renumber(info, [0, 3])
    assert info["pose_refinement"]["frames"][0]["frame"] == 3 and info["frames_dropped"] == [3]
    chained = {"pose_refinement": {"against": 1, "frames": [{"frame": 1}, {"frame": 2, "against": 1}]}}
    _renumber(chained, [0, 2, 5])  # a frame checked against the one above it names that one as the directory does
    assert chained["pose_refinement"]["frames"][1] == {"frame": 5, "against": 2}
    assert chained["pose_refinement"]["against"] == 2
    same = {"pose_refinement": {"frames": [{"frame": 2}]}}
    _renumber(same, [0, 1, 2])
    assert same["pose_refinement"]["frames"][0]["frame"] == 2
    up = Pose(np.array([0.0, 0.0, 300.0]), np.diag([1.0, -1.0, -1.0]))
    low = Pose(np.array([0.0, 0.0, 150.0]), np.diag([1.0, -1.0, -1.0]), 1.0)
    said = altimeter_disagreement([up, low], [300.0, 200.0], [0, 3])
    assert "frame 0 puts it at 0.0 m, frame 3 at -50.0 m" in said, said
    assert "frame 1 at -50.0 m" in altimeter_disagreement([up, low], [300.0, 200.0])


def test_a_clean_frame_that_hardly_overlaps_frame_0_is_a_note_not_a_warning(tmp_path, capsys):
    """A clean 1000/500/150 descent warned that frame 2's pose was unchecked: true, as the navigation poses leave
    the frames 20 px in common, but nothing is against it, and such warnings on every deep descent (29 in one QA
    pass) teach users to skip warnings. Said as a note; a frame the images contradict still warns."""
    assert main(["render", "--scenario", "vertical", "--frames", "1000,500,150", "--image-size", "256",
                 "--out", str(tmp_path), "--no-progress"]) == 0  # fmt: skip
    capsys.readouterr()
    assert main(["process", "--no-figures", str(tmp_path / "1000_500_150"), "--out", str(tmp_path / "o")]) == 0
    said = capsys.readouterr()
    assert "frame 2: its pose is not checked by the images (the images hardly overlap" in said.out, said.out
    assert "a fault in it would go unseen" in said.out
    assert "warning: frame" not in said.err, said.err
    # the last frame 2 km off shares no ground with frame 0: the error names which frame, not "the other" of three
    doc = json.loads((tmp_path / "1000_500_150" / "pair.json").read_text())
    doc["frames"][-1]["position_m"][0] += 2000.0
    (tmp_path / "1000_500_150" / "pair.json").write_text(json.dumps(doc))
    assert main(["process", "--no-figures", str(tmp_path / "1000_500_150"), "--out", str(tmp_path / "o2")]) == 2
    err = capsys.readouterr().err
    assert "the frames do not overlap" in err and "that the last frame used" in err, err


def test_an_image_from_another_altitude_is_refused_by_the_scale_frame_0s_altimeter_gives(tmp_path, capsys):
    """Two images swapped in a descent, the altimeters staying with their entries: the frame whose image came from
    lower matched and was "kept" (a swap scales the ground, which the poses alone cannot see) and was swept unsaid,
    DEM 29 m off (stop 59's QA). The ground it triangulates lies 150 m from where frame 0's altimeter reads it."""
    assert main(["render", "--scenario", "vertical", "--frames", "600,450,300,200", "--image-size", "256",
                 "--out", str(tmp_path), "--no-progress"]) == 0  # fmt: skip
    d = tmp_path / "600_450_300_200"
    doc = json.loads((d / "pair.json").read_text())
    doc["frames"][2]["image"], doc["frames"][3]["image"] = doc["frames"][3]["image"], doc["frames"][2]["image"]
    (d / "pair.json").write_text(json.dumps(doc))
    capsys.readouterr()
    assert main(["process", "--no-figures", str(d), "--out", str(tmp_path / "o")]) == 0
    err = capsys.readouterr().err
    res = json.loads((tmp_path / "o" / "result.json").read_text())
    f2 = res["info"]["pose_refinement"]["frames"][1]
    assert f2["verdict"] == "disagrees" and f2["scale_disagrees"] and f2["ground_gap_m"] > 100.0, f2
    assert (
        "warning: frame 2: its images and navigation pose put the ground away" in err
        and "from where the first frame's altimeter" in err
    ), err
    assert res["info"]["frames_dropped"] == [2, 3] and _dem_err(tmp_path / "o") < 2.0
    # without altimeters (they are optional): the fits' grounds against one another. Frame 2's and 3's were
    # "kept", DEM 202 m off, an unsafe site offered (stop 60's QA)
    blind = json.loads(json.dumps(doc))
    for f in blind["frames"]:
        f.pop("altimeter_m", None)
    (d / "pair.json").write_text(json.dumps(blind))
    assert main(["process", "--no-figures", str(d), "--out", str(tmp_path / "blind")]) == 0
    res = json.loads((tmp_path / "blind" / "result.json").read_text())
    odd = res["info"]["pose_refinement"]["frames"][1:]
    assert [f["verdict"] for f in odd] == ["disagrees", "disagrees"] and all(f["scale_disagrees"] for f in odd), odd
    assert "from where the other frames' images put it" in odd[0]["reason"]
    assert res["info"]["frames_dropped"] == [2, 3] and _dem_err(tmp_path / "blind") < 2.0
    assert "altimeter_disagreement" not in res["info"]
    # as a pair, frame 2 cannot be left out: said, and no site on a map resting on it
    doc["frames"], doc["true_frames"] = [doc["frames"][0], doc["frames"][2]], [doc["true_frames"][k] for k in (0, 2)]
    (d / "pair.json").write_text(json.dumps(doc))
    assert main(["process", "--no-figures", str(d), "--out", str(tmp_path / "p")]) == 0
    err = capsys.readouterr().err
    info = json.loads((tmp_path / "p" / "result.json").read_text())["info"]
    assert "frame 1's images put the ground +" in info["altimeter_disagreement"], info
    assert info["no_site_reason"].startswith("no site is offered on this map") and "warning: frame 1" in err


def test_process_widest_pair_names_the_directorys_frame_in_the_altimeter_warning(tmp_path, capsys):
    assert main(["render", "--scenario", "vertical", "--frames", "300,250,200,150", "--image-size", "96",
                 "--out", str(tmp_path), "--no-progress"]) == 0  # fmt: skip
    d = tmp_path / "300_250_200_150"
    doc = json.loads((d / "pair.json").read_text())
    doc["frames"][3]["altimeter_m"] += 50.0  # 50 m long: frame 3's beam puts the ground 50 m down
    (d / "pair.json").write_text(json.dumps(doc))
    assert main(["process", "--no-figures", str(d), "--widest-pair", "--out", str(tmp_path / "o")]) == 0
    err = capsys.readouterr().err
    assert "frame 3 at" in err and "frame 1 at" not in err, err


def test_a_pose_the_images_matched_but_cannot_fix_is_said():
    """A `degenerate` fallback (matched, but parallax, depth or spread cannot fix the pose) was said only in
    result.json: a 1 deg pitch of a highland approach pair went by with its DEM 10.6 m off (stop 60's QA F7)."""
    from flight_sw.cli import _degenerate_poses

    pair_info = {"verdict": "degenerate", "reason": "too little parallax (0.20 px < 0.5)"}
    assert _degenerate_poses(pair_info, 512) == [(1, "too little parallax (0.20 px < 0.5)")]
    assert _degenerate_poses(pair_info, 128) == []  # under CHECK_MIN_SIDE clean pairs cannot be checked either
    multi = {"frames": [{"frame": 1, "verdict": "refined"}, {"frame": 2, "verdict": "degenerate", "reason": "r",
                                                              "against": 1}]}  # fmt: skip
    assert _degenerate_poses(multi, 256) == [(2, "against frame 1: r")]
    assert _degenerate_poses({"verdict": "kept"}, 512) == [] and _degenerate_poses(None, 512) == []


def test_a_pairs_fit_that_cannot_fix_its_poses_names_both_frames(tmp_path, capsys):
    """A pair's fit is of both frames' attitudes: its `degenerate` fallback said "frame 1: ... cannot fix its pose",
    laying it on the lower frame alone (the HIL's note already said "the pair's poses")."""
    assert main(["render", "--scenario", "vertical", "--frames", "300,299", "--image-size", "256", "--no-progress",
                 "--out", str(tmp_path / "pairs")]) == 0  # fmt: skip
    assert main(["process", "--no-figures", str(tmp_path / "pairs" / "300_299"), "--out", str(tmp_path / "o")]) == 0
    out = capsys.readouterr().out
    assert "frames 0 and 1: the images matched but cannot fix the pair's poses (too little parallax" in out, out
    assert "frame 1: the images matched" not in out


def test_a_frame_sent_twice_is_warned_and_offers_no_site(tmp_path, capsys):
    """i2 a copy of i1 (a camera that repeated its last image) was refined as `degenerate` and said nothing:
    the DEM 21 m off, "full", exit 0 (stop 62's QA H1). The images have no parallax where the navigation's
    baseline predicts tens of pixels: warned, and no site on that map."""
    import shutil

    # a 2:1 pair's copy does not even track through the navigation's 2x scale (`unmatched` already): 6:5 does
    assert main(["render", "--scenario", "vertical", "--frames", "300,250", "--image-size", "256", "--no-progress",
                 "--out", str(tmp_path / "pairs")]) == 0  # fmt: skip
    pair = tmp_path / "pairs" / "300_250"
    bad = tmp_path / "bad"
    shutil.copytree(pair, bad)
    shutil.copy(bad / "i1.png", bad / "i2.png")
    assert main(["process", "--no-figures", str(bad), "--out", str(tmp_path / "o")]) == 0
    err = capsys.readouterr().err
    assert "warning: frame 1: its image does not match where its navigation pose says (its image is frame 0's" in err
    assert "warning: no site is offered on this map: it rests on frame 1" in err, err
    doc = json.loads((tmp_path / "o" / "result.json").read_text())
    assert doc["sites"] == [] and doc["info"]["pose_refinement"]["verdict"] == "repeated"
    # not the same bytes (another exposure from the same place: its own noise): no parallax where the baseline
    # predicts some
    import cv2

    img = cv2.imread(str(bad / "i1.png"), cv2.IMREAD_GRAYSCALE).astype(np.int16)
    img += np.random.default_rng(0).integers(-1, 2, img.shape).astype(np.int16)
    cv2.imwrite(str(bad / "i2.png"), np.clip(img, 0, 255).astype(np.uint8))
    assert main(["process", "--no-figures", str(bad), "--out", str(tmp_path / "o2")]) == 0
    err = capsys.readouterr().err
    assert "warning: frame 1: its image does not match where its navigation pose says (no parallax between" in err
    assert "warning: no site is offered on this map: it rests on frame 1" in err, err


def test_a_descent_frame_that_repeats_the_one_before_is_left_out(tmp_path, capsys):
    """Frame 2 a copy of frame 1: against frame 0 its motion is frame 1's, which no fit of that pair alone can tell
    from its own, so it was "kept", unwarned, the DEM 32 m off without altimeters (stop 62's review). Two
    exposures are never equal pixel for pixel: named as the same image twice, and left out, at any image size (below
    256 px, where the fits' verdicts are not evidence, it went unwarned and stayed in the maps; QA of stop 71). A
    pair cannot leave its frame out: it is warned of, and offers no site."""
    import shutil

    from flight_sw.pose_refine import repeated_images

    a = np.arange(16, dtype=np.uint8).reshape(4, 4)
    b = a[::-1].copy()
    assert repeated_images([a, b, a.copy(), b, b.astype(np.uint16), a.view(np.int8)]) == {2: 0, 3: 1}  # dtype counts
    blank = np.zeros((4, 4), np.uint8)  # two lost frames are blank, not "a camera that sent an image again"
    assert repeated_images([a, blank, blank.copy()]) == {}
    assert main(["render", "--scenario", "vertical", "--frames", "300,250,200", "--image-size", "128", "--no-progress",
                 "--out", str(tmp_path / "pairs")]) == 0  # fmt: skip
    bad = tmp_path / "bad"
    shutil.copytree(tmp_path / "pairs" / "300_250_200", bad)
    shutil.copy(bad / "i2.png", bad / "i3.png")
    doc = json.loads((bad / "pair.json").read_text())
    for f in doc["frames"]:
        f.pop("altimeter_m", None)  # the altimeters' own check would see it
    (bad / "pair.json").write_text(json.dumps(doc))
    capsys.readouterr()
    assert main(["process", "--no-figures", str(bad), "--out", str(tmp_path / "o")]) == 0
    err = capsys.readouterr().err
    assert "warning: frame 2: its image does not match where its navigation pose says (its image is frame 1's" in err
    assert "the same image twice (a camera that sent an image again)); it is left out of the maps" in err, err
    info = json.loads((tmp_path / "o" / "result.json").read_text())["info"]
    assert info["frames_dropped"] == [2] and info["pose_refinement"]["frames"][1]["repeat_of"] == 1
    two = tmp_path / "two"  # frames 0 and 1 alone, the lower image frame 0's
    shutil.copytree(tmp_path / "pairs" / "300_250_200", two)
    (two / "i3.png").unlink()
    doc = json.loads((two / "pair.json").read_text())
    for key in ("frames", "true_frames"):
        if key in doc:
            doc[key] = doc[key][:2]
    (two / "pair.json").write_text(json.dumps(doc))
    shutil.copy(two / "i1.png", two / "i2.png")
    assert main(["process", "--no-figures", str(two), "--out", str(tmp_path / "o2")]) == 0
    err = capsys.readouterr().err
    assert "warning: frame 1: its image does not match where its navigation pose says (its image is frame 0's" in err
    doc = json.loads((tmp_path / "o2" / "result.json").read_text())
    assert doc["sites"] == [] and "whose image is an earlier frame's, pixel for pixel" in doc["info"]["sites_withheld"]
    assert any("frame 1: its image does not match" in w for w in doc["warnings"])


def test_tiny_cameras_infinite_widths_and_huge_pair_files_are_refused_in_one_line(tmp_path, capsys):
    """QA of stop 66: a 1 or 2 px camera crashed `process` with a traceback (and `render --scenario FILE` made such
    pairs); a width of 1e400 did too; a 200 MB pair.json or trajectory file cost its size in memory to refuse."""
    from ground_sim.trajectory import TrajectoryError, from_file
    from protocol.pairdir import MAX_PAIR_JSON_BYTES

    d, _ = _pair(tmp_path)
    doc = json.loads((d / "pair.json").read_text())
    for name, cam in (("tiny", {"width": 2, "height": 2, "cx": 1.0, "cy": 1.0}), ("inf", {"width": 1e400})):
        bad = tmp_path / name
        bad.mkdir()
        for f in d.iterdir():
            if not f.name.startswith("gt_"):
                (bad / f.name).write_bytes(f.read_bytes())
        (bad / "pair.json").write_text(json.dumps({**doc, "camera": {**doc["camera"], **cam}}))
        if name == "tiny":  # images of the camera's size, so only the size is wrong
            from PIL import Image

            for f in ("i1.png", "i2.png"):
                Image.fromarray(np.full((2, 2), 120, np.uint8)).save(bad / f)
        assert main(["process", "--no-figures", str(bad), "--out", str(tmp_path / f"o_{name}")]) == 2
        err = capsys.readouterr().err
        assert "Traceback" not in err and err.count("\n") <= 2, err
        assert ("too small to map" if name == "tiny" else "whole number") in err, err
    huge = tmp_path / "huge"
    huge.mkdir()
    (huge / "pair.json").write_text(json.dumps({**doc, "pad": "x" * MAX_PAIR_JSON_BYTES}))
    assert main(["process", "--no-figures", str(huge), "--out", str(tmp_path / "o_huge")]) == 2
    assert "more than a pair.json can be" in capsys.readouterr().err
    traj = tmp_path / "t.json"
    traj.write_text(json.dumps({"camera": {"width": 2, "height": 2, "fx": 4.0, "fy": 4.0, "cx": 1.0, "cy": 1.0},
                                "pairs": [{"frames": [[0, 0, 200], [0, 0, 100]]}]}))  # fmt: skip
    with pytest.raises(TrajectoryError, match=r"render draws 32\.\.4096 px"):
        from_file(traj)
    traj.write_text(" " * (5 << 20))
    with pytest.raises(TrajectoryError, match="more than a trajectory can be"):
        from_file(traj)


def test_an_install_without_the_compiled_kernels_is_said(tmp_path, capsys, monkeypatch):
    """setup.py builds the SGM and trees kernels as optional extensions: a machine without a C compiler installed,
    ran the numpy references (4-11x slower) and said nothing, so its timings and deadlines misled (review of stop
    74). `process` warns, into result.json too; so does a HIL run's summary."""
    from flight_sw import kernels
    from hil_server.run import kernel_note

    assert kernels.missing_kernels() == []  # this install built them (`make install`)
    monkeypatch.setattr(kernels, "load_kernel", lambda module: None)
    missing = kernels.missing_kernels()
    assert missing == ["the SGM aggregation (~4x slower)", "the P(safe) trees (~11x slower)"]
    d, _ = _pair(tmp_path)
    assert main(["process", "--no-figures", str(d), "--out", str(tmp_path / "o"), "--sites", "0"]) == 0
    err = capsys.readouterr().err
    assert "warning: the install built no compiled kernel for the SGM aggregation (~4x slower) or the P(safe)" in err
    doc = json.loads((tmp_path / "o" / "result.json").read_text())
    assert any(w.startswith("the install built no compiled kernel") for w in doc["warnings"]), doc["warnings"]
    assert "then `.venv/bin/pip install -e .` builds them" in kernel_note({"kernels_missing": missing})
    assert kernel_note({"kernels_missing": []}) == "" and kernel_note({}) == ""


def _copy_without_truth(d: Path, dst: Path, camera: dict | None = None, scale_m: float = 1.0) -> Path:
    """``d``'s pair.json and images in ``dst`` (no truth), its camera updated by ``camera`` and its positions
    multiplied by ``scale_m`` (their altimeter readings and true poses dropped)."""
    dst.mkdir()
    for f in d.iterdir():
        if not f.name.startswith("gt_") and f.name != "pair.json":
            (dst / f.name).write_bytes(f.read_bytes())
    doc = json.loads((d / "pair.json").read_text())
    doc["camera"].update(camera or {})
    for fr in doc["frames"]:
        fr["position_m"] = [v * scale_m for v in fr["position_m"]]
        fr.pop("altimeter_m", None)
    doc.pop("true_frames", None)
    (dst / "pair.json").write_text(json.dumps(doc))
    return dst


def test_the_readers_warnings_and_notes_are_recorded_in_result_json_and_on_the_page(tmp_path, capsys):
    """QA of stop 75: positions in km ("frame 1 sees 0.00063 m per pixel ... positions must be in metres") were a
    note on stderr alone: exit 0, a DEM in km, result.json `warnings` [] and nothing on report.html. The reader's
    warnings are the run's first warnings; its notes (a 16-bit frame shifted) are result.json `notes`, on the page
    too."""
    import cv2

    d, _ = _pair(tmp_path)
    km = _copy_without_truth(d, tmp_path / "km", scale_m=1e-3)
    i2 = cv2.imread(str(km / "i2.png"), cv2.IMREAD_UNCHANGED)
    cv2.imwrite(str(km / "i2.png"), i2.astype(np.uint16) * 257)  # a 16-bit frame: converted, with a note
    out = tmp_path / "out"
    assert main(["process", "--no-figures", str(km), "--out", str(out), "--sites", "0"]) == 0
    err = capsys.readouterr().err
    doc = json.loads((out / "result.json").read_text())
    scale = [w for w in doc["warnings"] if "positions must be in metres" in w]
    assert len(scale) == 1 and scale[0].startswith(f"{km / 'pair.json'}: frame "), doc["warnings"]
    assert doc["warnings"][0] == scale[0] and f"warning: {scale[0]}" in err  # the reader's, first, as said
    assert doc["notes"] == ["16-bit images (i2.png) shifted right by 8 bits to 8-bit"], doc["notes"]
    page = (out / "report.html").read_text()
    assert ">Warnings<" in page and "positions must be in metres" in page
    assert ">Reading the pair<" in page and "shifted right by 8 bits" in page


def test_a_camera_too_small_to_map_is_its_one_error_without_a_note_before_it(tmp_path, capsys):
    """A 2 px camera: `process` printed the reader's "160 m per pixel ... positions must be in metres" first, then
    the real error (QA of stop 75). The pipeline's own checks come before anything is said of the pair."""
    from PIL import Image

    d, _ = _pair(tmp_path)
    tiny = _copy_without_truth(d, tmp_path / "tiny", {"width": 2, "height": 2, "fx": 1.0, "fy": 1.0, "cx": 0.5,
                                                       "cy": 0.5})  # fmt: skip
    for f in ("i1.png", "i2.png"):
        Image.fromarray(np.full((2, 2), 120, np.uint8)).save(tiny / f)
    from protocol.pairdir import read_pair

    assert any("m per pixel" in w for w in read_pair(tiny).scale_notes())  # the reader has a word to say, unsaid
    assert main(["process", "--no-figures", str(tiny), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("hazard-hil process: error: "), err
    assert f"{tiny / 'pair.json'}: camera: images of 2x2 px are too small to map" in err, err


def test_widest_pair_warns_of_no_crushed_frame_it_leaves_out(tmp_path, capsys):
    """A middle frame of 12-bit values in a 16-bit file beside full 16-bit ones: the reader warns of it, and
    `process --widest-pair`, which uses frames 0 and 2 only, listed that warning on its maps too (QA of stop 75)."""
    import cv2

    from protocol.pairdir import read_pair

    d, _ = _pair(tmp_path)
    three = _copy_without_truth(d, tmp_path / "three")
    for f in ("i1.png", "i2.png"):
        img = cv2.imread(str(three / f), cv2.IMREAD_UNCHANGED)
        cv2.imwrite(str(three / f), img.astype(np.uint16) * 257)
    cv2.imwrite(str(three / "mid.png"), cv2.imread(str(d / "i2.png"), cv2.IMREAD_UNCHANGED).astype(np.uint16) * 16)
    doc = json.loads((three / "pair.json").read_text())
    a, b = doc["frames"]
    mid = {**b, "image": "mid.png", "position_m": [(x + y) / 2 for x, y in zip(a["position_m"], b["position_m"])],
           "time_s": (a["time_s"] + b["time_s"]) / 2}  # fmt: skip
    doc["frames"] = [a, mid, b]
    (three / "pair.json").write_text(json.dumps(doc))
    crushed = f"{(three / 'mid.png').resolve()}: after the common 8-bit shift"
    assert [w for w in read_pair(three).warnings if w.startswith(crushed)]  # the reader says it
    out = tmp_path / "out"
    assert main(["process", "--no-figures", str(three), "--out", str(out), "--widest-pair", "--sites", "0"]) == 0
    said, err = capsys.readouterr()
    assert not [line for line in err.splitlines() if line.startswith("warning:") and "mid.png" in line], err
    doc = json.loads((out / "result.json").read_text())
    assert not any("mid.png" in w for w in doc["warnings"])
    # which of the directory's frames the run read: said nowhere, the page read "2 frames" (QA of stop 78)
    assert (doc["frames_used"], doc["frames_in_dir"]) == ([0, 2], 3)
    assert "; frames 0 (" in said and " m), 2 (" in said and " m) of 3" in said, said
    assert "preset fast, frames 0 and 2 of 3" in (out / "report.html").read_text()


def test_a_16_bit_frame_the_common_shift_crushed_is_not_called_a_lost_image(tmp_path, capsys):
    """i1.png 12-bit values in a 16-bit file, i2.png full 16-bit: the one shift left i1 ~16 grey levels, and the only
    words were "frame 0's image is blank ... (a black, saturated or lost image)" (QA of stop 75). The reader's
    warning names the file and the bit spans; the blank-image warning points to it."""
    import cv2

    d, _ = _pair(tmp_path)
    mixed = _copy_without_truth(d, tmp_path / "mixed")
    for f, gain in (("i1.png", 16), ("i2.png", 257)):
        img = cv2.imread(str(mixed / f), cv2.IMREAD_UNCHANGED)
        cv2.imwrite(str(mixed / f), img.astype(np.uint16) * gain)
    out = tmp_path / "out"
    assert main(["process", "--no-figures", str(mixed), "--out", str(out), "--sites", "0"]) == 0
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.startswith(f"warning: {(mixed / 'i1.png').resolve()}: ")]
    assert len(lines) == 1 and "its values span 12 bits, i2.png's 16" in lines[0], err
    # the noise readings compare frame 0's ~16 levels with frame 1's 256: at this size frame 1 reads noisy (at 256
    # px frame 0 read blank): either warning points to the shift, not to a lost image or a sensor fault
    said = [line for line in err.splitlines() if "image is blank" in line or "image is noisy" in line]
    assert said, err
    for line in said:
        assert "lost image" not in line and "sensor fault" not in line and "common 8-bit shift" in line, err
    doc = json.loads((out / "result.json").read_text())
    assert doc["warnings"][0] == lines[0].removeprefix("warning: ")


def test_a_wrong_frame_0_altimeter_is_not_blamed_on_the_other_frames_poses(tmp_path, capsys):
    """Frame 0's altimeter reading 15 % long: every later frame was warned as "the images disagree with its
    navigation pose", though their poses were exact (pose QA of stop 75). The ground against frame 0's altimeter
    cannot tell the two apart: the warning names both, and when every frame checked disagrees alike, the reading."""
    assert main(["render", "--scenario", "vertical", "--frames", "600,450,300", "--image-size", "256", "--seed",
                 "1000", "--no-progress", "--out", str(tmp_path / "r")]) == 0  # fmt: skip
    d = tmp_path / "r" / "600_450_300"
    doc = json.loads((d / "pair.json").read_text())
    doc["frames"][0]["altimeter_m"] *= 1.15
    (d / "pair.json").write_text(json.dumps(doc))
    capsys.readouterr()
    main(["process", "--no-figures", str(d), "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    said = [line for line in err.splitlines() if line.startswith("warning: frame ") and "altimeter" in line]
    assert len(said) == 2, err
    for line in said:
        assert "the pose or frame 0's altimeter reading is wrong" in line and "points to frame 0's altimeter" in line
        assert "disagree with its navigation pose" not in line


def test_the_aim_point_can_be_given_and_one_off_the_map_is_said(tmp_path, capsys):
    """The sites are ranked by distance to an aim point that nothing but the library could set: `process` always
    measured from the world origin, and an aim off the map put the sites in its nearest corner without a word
    (sites QA of stop 75)."""
    assert main(["render", "--scenario", "approach", "--pairs", "600/300", "--image-size", "256", "--no-progress",
                 "--out", str(tmp_path / "r")]) == 0  # fmt: skip
    d = tmp_path / "r" / "600_300"
    for aim, out in (("3,-2", "near"), ("2000,0", "far")):
        assert (
            main(["process", "--no-figures", str(d), "--out", str(tmp_path / out), "--aim", aim, "--sites", "20"]) == 0
        )
        doc = json.loads((tmp_path / out / "result.json").read_text())
        ax, ay = (float(v) for v in aim.split(","))
        assert doc["aim_xy"] == [ax, ay] and doc["sites"], doc["no_site_reason"]
        for s in doc["sites"]:
            assert s["distance_m"] == pytest.approx(math.hypot(s["x"] - ax, s["y"] - ay), abs=1e-6)
        said = capsys.readouterr().out
        assert ("the aim point (2000, 0) lies outside the mapped ground" in said) == (out == "far"), said
        # kept with the outputs, not said on stdout alone (QA of stop 79)
        kept = [n for n in doc["run_notes"] if n.startswith("the aim point (2000, 0) lies outside the mapped")]
        assert len(kept) == (out == "far"), doc["run_notes"]
        page = html.unescape((tmp_path / out / "report.html").read_text())
        assert ("Notes on the run" in page and "the aim point (2000, 0) lies outside" in page) == (out == "far")
    assert main(["process", "--no-figures", str(d), "--out", str(tmp_path / "bad"), "--aim", "3"]) == 2
    assert "--aim must be X,Y in metres, got '3'" in capsys.readouterr().err
