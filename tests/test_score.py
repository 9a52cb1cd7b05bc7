"""`hazard-hil score`: any detector's output directory scored against the truth by the design's convention."""

from __future__ import annotations

import json
import os
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
from hilkit import small_descent

from hil_server.cli import main
from protocol.pairdir import read_pair
from studies.evaluate import backproject_depth, true_poses
from studies.score import CSV_COLUMNS

PAIRS = ["600/300", "300/150"]


@pytest.fixture(scope="module")
def descent(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("score")
    small_descent(root / "pairs", PAIRS, px=128)
    return root / "pairs"


def _write(out: Path, hazard: np.ndarray, *, elevation=None, state=None, sites=None) -> Path:
    out.mkdir(parents=True, exist_ok=True)
    np.save(out / "hazard.npy", hazard.astype(np.float32))
    if elevation is not None:
        np.save(out / "elevation.npy", elevation.astype(np.float32))
    if state is not None:
        np.save(out / "state.npy", state.astype(np.uint8))
    if sites is not None:
        (out / "result.json").write_text(json.dumps({"sites": sites}))
    return out


def _score(pairs: Path, outputs: Path, capsys, *extra: str) -> tuple[int, dict]:
    js = outputs.parent / f"{outputs.name}-score.json"
    code = main(["score", str(pairs), str(outputs), "--json", str(js), *extra])
    capsys.readouterr()
    return code, json.loads(js.read_text()) if js.is_file() else {}


def test_perfect_all_unsafe_all_safe_and_blank_detectors(descent, tmp_path, capsys):
    d = descent / "300_150"
    pair = read_pair(d)
    gt = pair.truth["hazard"]
    truth_z = pair.truth["elevation"]
    # the oracle: every truth call, the true elevation
    code, doc = _score(d, _write(tmp_path / "oracle", gt, elevation=truth_z), capsys)
    (r,) = doc["rows"]
    assert code == 0 and r["fp_pct"] == 0 and r["fn_pct"] == 0 and r["cdi_pct"] == pytest.approx(100.0)
    assert r["dem_mean_abs_m"] == 0 and r["unmapped_pct"] == 0
    hazards = r["hazards_in_scene_pct"]
    assert 1 < hazards < 99  # the scene has both
    # everything unsafe: no FP, CDI = the hazards' share
    code, doc = _score(d, _write(tmp_path / "unsafe", np.ones_like(gt)), capsys)
    assert code == 0 and doc["rows"][0]["fp_pct"] == 0 and doc["rows"][0]["cdi_pct"] == pytest.approx(hazards)
    # everything safe: every hazard undetected -> over the 1 % limit, exit 1
    code, doc = _score(d, _write(tmp_path / "safe", np.zeros_like(gt)), capsys)
    assert (
        code == 1 and doc["rows"][0]["fp_pct"] == pytest.approx(hazards) and doc["summary"]["pairs_over_fp_limit"] == 1
    )
    code, _ = _score(d, tmp_path / "safe", capsys, "--max-fp", "100")
    assert code == 0
    # a detector that writes NaN does not shrink the scored area: not called safe, counted as unmapped
    js = tmp_path / "blank-score.json"
    code = main(["score", str(d), str(_write(tmp_path / "blank", np.full(gt.shape, np.nan))), "--json", str(js)])
    assert "warning: 300_150: 100 % of the scored pixels have no hazard value" in capsys.readouterr().err
    doc = json.loads(js.read_text())
    r = doc["rows"][0]
    assert code == 0 and r["unmapped_pct"] == 100 and r["cdi_pct"] == pytest.approx(hazards)
    assert r["pixels"] == doc["rows"][0]["pixels"] > 0.2 * gt.size
    # an elevation.npy of NaN alone is said too, as hazard.npy's is (it read "-" without a word; QA of stop 78)
    nodem = _write(tmp_path / "nodem", gt, elevation=np.full(gt.shape, np.nan, np.float32))
    assert main(["score", str(d), str(nodem)]) == 0
    err = capsys.readouterr().err
    assert "warning: 300_150: elevation.npy has a value on 0 % of the scored pixels" in err, err
    assert main(["score", str(d), str(tmp_path / "oracle")]) == 0
    assert "elevation.npy has a value" not in capsys.readouterr().err


def test_sites_judged_over_their_true_footprint(descent, tmp_path, capsys):
    d = descent / "300_150"
    pair = read_pair(d)
    gt = pair.truth["hazard"]
    true1, _ = true_poses(pair)
    world = backproject_depth(pair.camera, true1, pair.truth["depth"].astype(np.float64))
    world[..., 2] = pair.truth["elevation"]
    h, w = gt.shape
    # a pixel deep inside clear ground and one on a hazard, away from the image edge
    clear = (gt < 1).astype(np.uint8)
    import cv2

    inner = cv2.erode(clear, np.ones((15, 15), np.uint8)).astype(bool)
    inner[:20], inner[-20:], inner[:, :20], inner[:, -20:] = False, False, False, False
    hv, hu = np.argwhere(gt[20:-20, 20:-20] >= 1)[0] + 20
    sv, su = np.argwhere(inner)[len(np.argwhere(inner)) // 2]
    site = {k: float(v) for k, v in zip("xyz", world[sv, su])}
    bad = {k: float(v) for k, v in zip("xyz", world[hv, hu])}
    code, doc = _score(d, _write(tmp_path / "good", np.ones_like(gt), sites=[site, bad]), capsys)
    r = doc["rows"][0]
    assert (r["sites"], r["sites_truly_safe"], r["top_site_truly_safe"]) == (2, 1, True)
    code, doc = _score(d, _write(tmp_path / "bad", np.ones_like(gt), sites=[bad, site]), capsys)
    r = doc["rows"][0]
    assert (r["sites"], r["sites_truly_safe"], r["top_site_truly_safe"]) == (2, 1, False)
    assert doc["summary"]["top_sites_truly_safe"] == 0 and doc["summary"]["top_sites"] == 1


def test_our_process_output_scores_as_process_saw_it(descent, tmp_path, capsys):
    """`process` scores its output as `score` does (the flight side never reads the truth, DESIGN.md): its own
    vs_truth over the map's covered pixels differed from `score`'s by the edge band."""
    d = descent / "600_300"
    assert main(["process", str(d), "--out", str(tmp_path / "p"), "--no-figures"]) == 0  # its scores, not pictures
    said, _ = capsys.readouterr()
    assert "vs_truth" not in json.loads((tmp_path / "p" / "result.json").read_text())  # the flight side's record
    own = json.loads((tmp_path / "p" / "score.json").read_text())
    code, doc = _score(d, tmp_path / "p", capsys)
    r = doc["rows"][0]
    mine = own["rows"][0]
    for key in ("pixels", "fp_pct", "cdi_pct", "hazards_detected_pct", "safe_recognised_pct", "dem_mean_abs_m",
                "sites", "sites_truly_safe", "top_site_truly_safe"):  # fmt: skip
        assert mine[key] == r[key], key
    assert own["summary"]["fp_worst_pct"] == doc["summary"]["fp_worst_pct"]
    assert f"against the truth: FP {r['fp_pct']:.2f} %" in said and f"CDI {r['cdi_pct']:.1f} %" in said, said
    # DESIGN.md's TN% and TP% are rates: hazards detected and safe ground recognised, under their own names
    assert r["cdi_pct"] == pytest.approx(r["tp_pct"] + r["tn_pct"])
    assert r["hazards_detected_pct"] == pytest.approx(100.0 * r["tn_pct"] / (r["tn_pct"] + r["fp_pct"]))
    assert r["safe_recognised_pct"] == pytest.approx(100.0 * r["tp_pct"] / (r["tp_pct"] + r["fn_pct"]))
    assert r["state_safe_pct"] == pytest.approx(r["tp_pct"] + r["fp_pct"])  # state.npy agrees with hazard.npy
    assert code == (0 if r["fp_pct"] <= 1.0 else 1)


def test_a_descent_with_one_output_missing_scores_the_rest_and_fails(descent, tmp_path, capsys):
    outs = tmp_path / "outs"
    pair = read_pair(descent / "600_300")
    _write(outs / "600_300", pair.truth["hazard"])
    figs = tmp_path / "figs"
    code = main(["score", str(descent), str(outs), "--csv", str(tmp_path / "rows.csv"), "--figures", str(figs)])
    out, _ = capsys.readouterr()
    assert code == 3
    assert sorted(p.name for p in figs.glob("*.png")) == ["600_300_score.png"]  # the scored pair's picture only
    assert (figs / "600_300_score.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "| 300/150 | no usable output: " in out and "no such output directory" in out
    assert "1 of 2 pairs scored" in out and "1 without a usable output" in out
    assert len((tmp_path / "rows.csv").read_text().splitlines()) == 3  # header + both pairs, none dropped
    import csv

    with (tmp_path / "rows.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    # score's own columns, always the same and in one order (they changed with what each run filled); none of
    # evaluate's ~30 that score never fills (slope_*, epi_*, ...)
    assert tuple(rows[0]) == CSV_COLUMNS and "slope_mean_abs_deg" not in rows[0]
    assert rows[1]["error"] and rows[1]["fp_pct"] == "" and rows[0]["top_site_truly_safe"] in ("true", "false", "")


@pytest.mark.parametrize(
    "write, message",
    [
        (
            lambda o, s: np.save(o / "hazard.npy", np.zeros((s[0] + 1, s[1]), np.float32)),
            "hazard.npy: must be 128x128 (frame 0's pixels), got (129, 128)",
        ),
        (lambda o, s: np.save(o / "hazard.npy", np.full(s, -1.0, np.float32)), "values must lie in [0, 1] or be NaN"),
        (lambda o, s: np.save(o / "hazard.npy", np.full(s, 2.0, np.float32)), "values must lie in [0, 1] or be NaN"),
        (
            lambda o, s: np.save(o / "hazard.npy", np.ones(s)),
            "hazard.npy: must be float32 (DESIGN.md), got dtype float64; save it with np.save(path, a.astype(np",
        ),
        (lambda o, s: np.save(o / "hazard.npy", np.ones(s, np.int64)), "must be float32 (DESIGN.md), got dtype int64"),
        (lambda o, s: (o / "hazard.npy").write_bytes(b"not npy"), "not a readable .npy"),
        (lambda o, s: (o / "hazard.npy").write_bytes(b""), "not a readable .npy file (No data left in file)"),
        (lambda o, s: np.save(o / "elevation.npy", np.zeros(s, np.int32)), "elevation.npy: must be float32"),
        (lambda o, s: np.save(o / "elevation.npy", np.full(s, np.inf, np.float32)), "elevation.npy: holds inf"),
        (lambda o, s: np.save(o / "state.npy", np.full(s, 7, np.uint8)), "state.npy: must be uint8 codes"),
        (lambda o, s: np.save(o / "state.npy", np.ones(s, np.int64)), "state.npy: must be uint8 codes"),
        # not scored, but DESIGN.md's probability: a 5.0 or a float64 file passed without a word
        (lambda o, s: np.save(o / "psafe.npy", np.full(s, 5.0, np.float32)), "psafe.npy: a probability"),
        (lambda o, s: np.save(o / "psafe.npy", np.full(s, 0.5)), "psafe.npy: must be float32 (DESIGN.md), got"),
        # NaN means outside: inside the map it passed without a word (QA of stop 75)
        (lambda o, s: np.save(o / "psafe.npy", np.full(s, np.nan, np.float32)), "psafe.npy: NaN on 16384 pixels"),
        # hazard.npy is 1.0 everywhere (not called safe): each disagreement is named with its direction
        (lambda o, s: np.save(o / "state.npy", np.zeros(s, np.uint8)), "says 0 (safe) where hazard.npy is >= 1 on"),
        (lambda o, s: np.save(o / "state.npy", np.full(s, 255, np.uint8)), "says 255 (outside) where hazard.npy has"),
        (lambda o, s: (o / "result.json").write_text('{"sites": [{"x": 1}]}'), 'site 0 needs "x", "y" and "z"'),
        # by name but not a file: a FIFO state.npy was taken for no state.npy, and the pair scored without it
        (lambda o, s: os.mkfifo(o / "state.npy"), "state.npy: exists but is not a regular file (a FIFO)"),
        (lambda o, s: (o / "result.json").mkdir(), "result.json: exists but is not a regular file (a directory)"),
        (lambda o, s: (o / "result.json").write_bytes(b" " * (17 * 2**20)), "bytes is more than a result.json can be"),
        (lambda o, s: (o / "hazard.npy").write_text("0.5\n" * 99), "not a numeric array: a text file"),
        # damaged headers were tracebacks: an unterminated bracket reached the tokenizer, a negative shape the mmap
        (lambda o, s: _damage_header(o / "hazard.npy", b"(128, 128)", b"(128, 128 "), "damaged header"),
        (lambda o, s: _damage_header(o / "hazard.npy", b"(128, 128)", b"(-12, 128)"), "not a readable .npy file"),
    ],
)
def test_broken_output_is_that_pairs_one_line_failure(descent, tmp_path, capsys, write, message):
    d = descent / "300_150"
    shape = read_pair(d).images[0].shape
    out = _write(tmp_path / "o", np.ones(shape))
    write(out, shape)
    code = main(["score", str(d), str(out)])
    text, err = capsys.readouterr()
    assert code == 3 and message in text and "no pair scored" in text  # exit 1 is a detector over its FP budget
    assert err.startswith("hazard-hil score: 300_150: no usable output: ") and message in err, err  # for a CI log


def _damage_header(path, old: bytes, new: bytes) -> None:
    data = path.read_bytes()
    assert old in data[:128]
    path.write_bytes(data.replace(old, new, 1))


@pytest.mark.parametrize("old, new", [(b"(128, 128)", b"(128, 128 "), (b"(128, 128)", b"(-12, 128)")])
def test_a_damaged_truth_header_is_one_line_exit_2(descent, tmp_path, capsys, old, new):
    d = tmp_path / "pair"
    shutil.copytree(descent / "300_150", d)
    _damage_header(d / "gt_hazard_i1.npy", old, new)
    _write(tmp_path / "o", np.ones((128, 128)))
    assert main(["score", str(d), str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "gt_hazard_i1.npy: not a readable .npy file" in err[0], err


def test_process_output_scored_against_another_pair_is_refused(descent, tmp_path, capsys):
    """`process` records the pair it read; `score` quietly scored that output against another pair of the same size
    (and blamed the detector for the other pair's hazards)."""
    a, b = sorted(p for p in descent.iterdir() if (p / "pair.json").is_file())[:2]
    out = tmp_path / "p"
    assert main(["process", str(a), "--out", str(out), "--no-figures"]) == 0  # the pair it records, not pictures
    capsys.readouterr()
    assert main(["score", str(a), str(out)]) in (0, 1)  # its own pair: scored (1 only if FP is over the limit)
    assert "made from another pair" not in capsys.readouterr().out
    assert main(["score", str(b), str(out)]) == 3
    text = capsys.readouterr().out
    assert "made from another pair" in text and a.name in text and "no pair scored" in text, text


@pytest.mark.parametrize("option, victim", [("--json", "gt_hazard_i1.npy"), ("--csv", "pair.json"), ("--csv", "OUT")])
def test_a_report_file_that_is_one_of_the_inputs_is_refused(descent, tmp_path, capsys, option, victim):
    """`score --json PAIR/gt_hazard_i1.npy` replaced the ground truth with the scores, exit 0."""
    d = tmp_path / "pair"
    shutil.copytree(descent / "300_150", d)
    out = _write(tmp_path / "o", np.ones((128, 128)))
    path = out / "hazard.npy" if victim == "OUT" else d / victim
    before = path.read_bytes()
    assert main(["score", str(d), str(out), option, str(path)]) == 2
    assert "is one of the files this scoring reads" in capsys.readouterr().err
    assert path.read_bytes() == before
    assert main(["score", str(d), str(out), option, str(out / "scores.json")]) in (0, 1)  # a new file there is fine


def test_an_image_the_pair_keeps_in_a_subdirectory_is_not_overwritten_by_a_report(descent, tmp_path, capsys):
    """pair.json may name its images anywhere inside the pair directory: `--csv PAIR/img/frame0.png` replaced the
    image with the table, exit 0."""
    import json

    d = tmp_path / "pair"
    shutil.copytree(descent / "300_150", d)
    (d / "img").mkdir()
    (d / "i1.png").rename(d / "img" / "frame0.png")
    doc = json.loads((d / "pair.json").read_text())
    doc["frames"][0]["image"] = "img/frame0.png"
    (d / "pair.json").write_text(json.dumps(doc))
    out = _write(tmp_path / "o", np.ones((128, 128)))
    before = (d / "img" / "frame0.png").read_bytes()
    assert main(["score", str(d), str(out), "--csv", str(d / "img" / "frame0.png")]) == 2
    assert "is one of the files this scoring reads" in capsys.readouterr().err
    assert (d / "img" / "frame0.png").read_bytes() == before
    # a report of one's own beside the pair is written, and written again (any file in it was refused at first)
    for _ in range(2):
        assert main(["score", str(d), str(out), "--csv", str(d / "scores.csv")]) in (0, 1)
    assert (d / "scores.csv").read_text().startswith("pair,")


def test_bad_usage_is_exit_2(descent, tmp_path, capsys):
    assert main(["score", str(tmp_path), str(tmp_path)]) == 2
    assert "neither a pair directory" in capsys.readouterr().err
    nogt = tmp_path / "nogt"
    shutil.copytree(descent / "300_150", nogt)
    for f in nogt.glob("gt_*"):
        f.unlink()
    _write(tmp_path / "o", np.ones((128, 128)))
    assert main(["score", str(nogt), str(tmp_path / "o")]) == 2
    assert "no ground truth" in capsys.readouterr().err
    assert main(["score", str(descent / "300_150"), str(tmp_path / "o"), "--max-fp", "nan"]) == 2


def test_an_output_claiming_a_huge_array_is_refused_from_its_header(descent, tmp_path, capsys):
    """The header says 200 000 x 200 000 float32 (149 GiB); the file holds a few bytes: nothing is allocated."""
    out = tmp_path / "huge"
    out.mkdir()
    with open(out / "hazard.npy", "wb") as f:
        np.lib.format.write_array_header_1_0(f, {"descr": "<f4", "fortran_order": False, "shape": (200_000, 200_000)})
    code = main(["score", str(descent / "300_150"), str(out)])
    text, _ = capsys.readouterr()
    assert code == 3 and "hazard.npy: " in text and ("must be 128x128" in text or "not a readable" in text)


def test_an_hil_runs_full_maps_are_scored_with_the_sites_of_its_records(descent, tmp_path, capsys):
    """`score RUN/pairs RUN/received`: the image maps a flight side sent (`--full-maps`) against the truth; the
    sites come from the run's records; a pair the run ended in an error is listed with the run's reason."""
    from hilkit import run_hil

    s = run_hil(descent / "manifest.json", tmp_path / "run", "zmq", full_maps=True, deadline_s=30.0)
    assert s["results"] == 2
    received = tmp_path / "run" / "received"
    code, doc = _score(descent, received, capsys)
    assert code == 0 and [r["pair"] for r in doc["rows"]] == PAIRS
    records = [json.loads(x) for x in (received / "results.jsonl").read_text().splitlines()]
    for r, rec in zip(doc["rows"], records):
        assert r["error"] is None and r["sites"] == len(rec["sites"])
        assert r["fp_pct"] <= 1.0 and r["cdi_pct"] > 10
    # one pair of it alone: its sites from the run's record too (it read "no site", stop 59's QA). At 128 px
    # the flight side offers none: one is written into the record, as a Result would carry it
    records[0]["sites"] = [{"x": 0.0, "y": 0.0, "z": 0.0, "slope_deg": 1.0, "roughness_m": 0.0, "clearance_m": 3.0}]
    (received / "results.jsonl").write_text("".join(json.dumps(r) + "\n" for r in records))
    code, single = _score(descent / Path(records[0]["pair_dir"]).name, Path(records[0]["out_dir"]), capsys)
    assert code in (0, 1) and single["rows"][0]["sites"] == 1, single["rows"][0]
    # the run ended the second pair in an error: said, not scored, exit 3 (no usable output)
    records[1].update(status="error", code="deadline_hit", text="hard deadline passed")
    (received / "results.jsonl").write_text("".join(json.dumps(r) + "\n" for r in records))
    code, doc = _score(descent, received, capsys)
    assert code == 3 and doc["rows"][0]["error"] is None
    assert doc["rows"][1]["error"].startswith("the run ended this pair as deadline_hit: hard deadline passed")
    # ... and without truth either: both said, as bad input (exit 2), not only the missing Result (stop 62's review)
    bare = tmp_path / "bare"
    shutil.copytree(descent, bare)
    for f in (bare / "300_150").glob("gt_*"):
        f.unlink()
    code, doc = _score(bare, received, capsys)
    err = doc["rows"][1]["error"]
    assert code == 2 and doc["rows"][1]["pair_error"] and "no ground truth gt_depth_i1.npy" in err, err
    assert "no usable output: the run ended this pair as deadline_hit" in err
    (Path(records[0]["out_dir"]) / "hazard.npy").unlink()  # as a run without --full-maps leaves it
    code, doc = _score(descent, received, capsys)
    assert code == 3 and "saves the image maps only with `run --full-maps`" in doc["rows"][0]["error"]


def test_outputs_that_are_not_a_directory_are_a_usage_error(descent, tmp_path, capsys):
    """A mistyped OUTPUTS listed every pair as "no such output directory" and exited 1, as if the detector had
    failed on each."""
    (tmp_path / "afile").write_text("")
    for outs, says in ((tmp_path / "nosuch", "no such directory"), (tmp_path / "afile", "not a directory")):
        assert main(["score", str(descent), str(outs)]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and says in err and str(outs) in err, err


def test_state_and_hazard_disagreements_are_named_by_direction():
    """A state 1 on a pixel hazard.npy calls safe was reported as "says safe ... or the reverse"."""
    from studies.score import ScoreError, _check_state

    hazard = np.array([[0.2, 1.0, np.nan]], np.float32)
    _check_state(Path("s.npy"), np.array([[0, 2, 255]], np.uint8), hazard)  # agrees: nothing raised
    for state, what in (
        ([[1, 2, 255]], "1 or 2 (not safe) where hazard.npy is < 1 (called safe) on 1 pixels"),
        ([[0, 1, 0]], "a code other than 255 (outside) where hazard.npy is NaN on 1 pixels"),
        ([[0, 255, 255]], "255 (outside) where hazard.npy has a value on 1 pixels"),
    ):
        with pytest.raises(ScoreError, match=re.escape(what)):
            _check_state(Path("s.npy"), np.array(state, np.uint8), hazard)


def test_a_site_without_a_height_is_judged_by_its_x_y(descent, tmp_path, capsys):
    """A degraded Result's site may carry z NaN (docs/protocol.md); one such site threw the pair's scores away."""
    d = descent / "300_150"
    gt = read_pair(d).truth["hazard"]
    out = _write(tmp_path / "o", np.ones_like(gt))
    (out / "result.json").write_text('{"sites": [{"x": 0.0, "y": 0.0, "z": NaN}, {"x": 1.0, "y": 1.0, "z": null}]}')
    code, doc = _score(d, out, capsys)
    r = doc["rows"][0]
    assert r["error"] is None and r["sites"] == 2 and r["cdi_pct"] is not None


def test_a_big_endian_float32_map_is_float32(descent, tmp_path, capsys):
    """DESIGN.md's float32 in the other byte order (MATLAB, Java) was refused as 'not float32'."""
    d = descent / "300_150"
    gt = read_pair(d).truth["hazard"]
    out = tmp_path / "be"
    out.mkdir()
    np.save(out / "hazard.npy", gt.astype(">f4"))
    code, doc = _score(d, out, capsys)
    assert doc["rows"][0]["error"] is None and doc["rows"][0]["fp_pct"] == 0 and code == 0


@pytest.fixture(scope="module")
def fine_descent(tmp_path_factory) -> Path:
    """A pair whose ground is sampled finely enough (0.4 m at 256 px, 200 m) for a truth from pixels."""
    root = tmp_path_factory.mktemp("fine")
    small_descent(root / "pairs", ["200/100"], px=256)
    return root / "pairs"


def test_a_pair_with_only_designs_truth_files_is_scored_against_a_derived_truth(fine_descent, tmp_path, capsys):
    """DESIGN.md's truth files are gt_elevation, gt_depth and gt_shadow; score refused a pair without the
    renderer's gt_hazard_i1.npy, so no one's own data could be scored (stop 58's QA). The rules now derive it;
    on the renderer's pair both truths must give nearly the same scores to the same detector."""
    d = fine_descent / "200_100"
    pair = read_pair(d)
    gt = pair.truth["hazard"]
    mine = tmp_path / "nogt"
    shutil.copytree(d, mine)
    (mine / "gt_hazard_i1.npy").unlink()
    # a detector that gets the truth right but for a band of mistakes: what both truths score
    rng = np.random.default_rng(5)
    called = np.where(rng.random(gt.shape) < 0.1, 1.0 - (gt >= 1), gt).astype(np.float32)
    out = _write(tmp_path / "o", called)
    _, given = _score(d, out, capsys)
    code = main(["score", str(mine), str(out), "--json", str(tmp_path / "derived.json")])
    err = capsys.readouterr().err
    derived = json.loads((tmp_path / "derived.json").read_text())
    (a,), (b,) = given["rows"], derived["rows"]
    assert code in (0, 1) and a["truth"] == "gt_hazard_i1.npy" and b["truth"] == "derived"
    # the shadow it counts is named with the rest (QA of stop 79: two of the three files were)
    assert "the true hazard was derived from gt_elevation, gt_depth and gt_shadow by" in err
    assert b["pixels"] > 0.9 * a["pixels"]  # nearly all of the overlap resolved
    assert abs(a["fp_pct"] - b["fp_pct"]) < 1.0 and abs(a["cdi_pct"] - b["cdi_pct"]) < 3.0
    assert abs(a["hazards_in_scene_pct"] - b["hazards_in_scene_pct"]) < 3.0
    assert derived["summary"]["truth_derived"] == 1


def test_a_descent_scores_its_other_pairs_when_one_has_no_truth(descent, tmp_path, capsys):
    """One pair without ground truth stopped the whole descent with exit 2, the others unscored."""
    root = tmp_path / "descent"
    shutil.copytree(descent, root)
    for f in (root / "300_150").glob("gt_*"):
        f.unlink()
    outs = tmp_path / "outs"
    for name in ("600_300", "300_150"):
        _write(outs / name, np.ones((128, 128)))
    code, doc = _score(root, outs, capsys)
    rows = {r["pair"]: r for r in doc["rows"]}
    assert code == 2 and doc["summary"]["scored"] == 1
    assert rows["600/300"]["error"] is None and rows["600/300"]["fp_pct"] == 0  # all unsafe: no FP
    assert rows["300/150"]["pair_error"] and "no ground truth gt_depth_i1.npy" in rows["300/150"]["error"]


def test_a_pair_without_true_frames_is_said_to_be_scored_on_its_reported_poses(descent, tmp_path, capsys):
    """DESIGN.md: scoring judges against the true poses. A pair of one's own without `true_frames` was scored on
    its reported poses, the sites placed on the ground through them, without a word (stop 58's QA, L3)."""
    mine = tmp_path / "p"
    shutil.copytree(descent / "300_150", mine)
    doc = json.loads((mine / "pair.json").read_text())
    meta = doc.get("meta", doc)
    assert meta.pop("true_frames")
    (mine / "pair.json").write_text(json.dumps(doc))
    out = _write(tmp_path / "o", np.ones((128, 128)))
    _, given = _score(descent / "300_150", out, capsys)
    assert given["rows"][0]["truth_poses"] == "true_frames"
    assert main(["score", str(mine), str(out), "--json", str(tmp_path / "s.json")]) == 0
    assert "has no true_frames, so its frames' reported poses are taken as true" in capsys.readouterr().err
    assert json.loads((tmp_path / "s.json").read_text())["rows"][0]["truth_poses"] == "reported"


def test_a_truth_hazard_outside_0_1_is_refused(descent, tmp_path, capsys):
    d = tmp_path / "p"
    shutil.copytree(descent / "300_150", d)
    gt = np.load(d / "gt_hazard_i1.npy")
    np.save(d / "gt_hazard_i1.npy", np.where(gt >= 1, 5.0, gt).astype(np.float32))  # degrees, not a hazard
    _write(tmp_path / "o", np.ones((128, 128)))
    assert main(["score", str(d), str(tmp_path / "o")]) == 2
    assert "ground truth hazard must lie in [0, 1]" in capsys.readouterr().err


def test_an_hil_run_scores_a_pair_without_gt_hazard_against_the_derived_truth(fine_descent, tmp_path):
    from hilkit import run_hil

    from hil_server.run import truth_note

    root = tmp_path / "pairs"
    shutil.copytree(fine_descent, root)
    (root / "200_100" / "gt_hazard_i1.npy").unlink()
    s = run_hil(root / "manifest.json", tmp_path / "run", "zmq")
    (rec,) = s["records"]
    assert rec["status"] == "result" and "derived from gt_elevation" in rec["truth_note"]
    assert 0 <= rec["scores"]["fp_pct"] <= 100 and rec["scores"]["cdi_pct"] > 0
    assert "the scores of 200/100 are against a truth hazard derived" in truth_note(s)
    assert "truth hazard derived from gt_elevation" in (tmp_path / "run" / "summary.md").read_text()
    kept = Path(rec["out_dir"]) / "truth_hazard_derived.npy"  # the truth the scores used, for the report too
    assert kept.is_file() and np.isfinite(np.load(kept)).any()


def test_an_hil_run_says_a_pair_without_derivable_truth_is_unscored_and_blames_no_grid(descent, tmp_path):
    """A truth that could not be derived (128 px at 600 m: 2.5 m per pixel) gave the Result zero scores, and the
    summary said it 'mapped none of the upper image's ground (its origin, cell size or axes?)' (stop 58's QA)."""
    from hilkit import run_hil

    root = tmp_path / "pairs"
    shutil.copytree(descent, root)
    (root / "600_300" / "gt_hazard_i1.npy").unlink()
    s = run_hil(root / "manifest.json", tmp_path / "run", "zmq")
    rec = next(r for r in s["records"] if r["label"] == "600/300")
    assert rec["status"] == "result" and "scores" not in rec and "none can be derived" in rec["truth_note"]
    md = (tmp_path / "run" / "summary.md").read_text()
    assert (
        "mapped none of the scored ground" not in md and "Pair 600/300 could not be scored" in md
    )  # the label as given (QA of stop 84)


# --------------------------------------------------------------------------- QA 61a
def test_output_directories_of_no_pair_are_named(descent, tmp_path, capsys):
    """An output directory named as no pair (a typo, `600-300` for `600_300`) was skipped without a word."""
    outs = tmp_path / "outs"
    gt = read_pair(descent / "600_300").truth["hazard"]
    _write(outs / "600_300", gt)
    _write(outs / "typo_dir", np.zeros_like(gt))
    (outs / "not_a_dir.txt").write_text("x")
    assert main(["score", str(descent), str(outs)]) == 3  # 300_150 has no output
    err = capsys.readouterr().err
    assert f"note: {outs} also holds typo_dir, which is no pair of the manifest" in err, err
    assert "600_300, 300_150" in err and "not_a_dir" not in err, err
    shutil.rmtree(outs / "typo_dir")
    _write(outs / "300_150", read_pair(descent / "300_150").truth["hazard"])
    assert main(["score", str(descent), str(outs)]) == 0
    assert "also holds" not in capsys.readouterr().err
    assert main(["score", str(descent / "manifest.json"), str(outs)]) == 0  # the file `run --manifest` takes (QA 64a)
    assert main(["score", str(descent / "600_300" / "pair.json"), str(outs / "600_300")]) == 0
    capsys.readouterr()
    # the figures this run makes inside OUTPUTS are its own, not a stray output (stop 61's review)
    for _ in range(2):  # made by the first run, there before the second
        assert main(["score", str(descent), str(outs), "--figures", str(outs / "figs")]) == 0
        assert "also holds" not in capsys.readouterr().err


def test_outputs_one_level_too_high_says_where_the_output_is(descent, tmp_path, capsys):
    """`score PAIR OUTPUTS` given the per-pair directories' parent said only "OUTPUTS: no hazard.npy"."""
    outs = tmp_path / "outs"
    _write(outs / "600_300", read_pair(descent / "600_300").truth["hazard"])
    assert main(["score", str(descent / "600_300"), str(outs)]) == 3
    err = capsys.readouterr().err
    assert f"{outs}: no hazard.npy" in err and f"{outs / '600_300'} holds one: give that as OUTPUTS" in err, err


def test_one_output_given_with_a_descent_says_to_give_its_pair(descent, tmp_path, capsys):
    """`score DESCENT OUT` with OUT one pair's output said only "OUT/600_300: no such output directory" (a new
    user's walk through the README, stop 72)."""
    out = _write(tmp_path / "one", read_pair(descent / "600_300").truth["hazard"])
    assert main(["score", str(descent), str(out)]) == 3
    err = capsys.readouterr().err
    assert f"{out} is one output itself: score it against its pair directory, not the descent" in err, err


def test_a_site_without_z_is_refused_saying_z_may_be_null(descent, tmp_path, capsys):
    """A site with no "z" was refused as needing a numeric z, while "z": null was scored: DESIGN.md lists z for
    every site (only p_safe is "where known"), and protocol.md lets a degraded Result's z be NaN."""
    d = descent / "300_150"
    out = _write(tmp_path / "o", np.ones_like(read_pair(d).truth["hazard"]))
    (out / "result.json").write_text('{"sites": [{"x": 0.0, "y": 0.0}]}')
    assert main(["score", str(d), str(out)]) == 3
    err = capsys.readouterr().err
    assert 'site 0 needs "x", "y" and "z"' in err and '"z" may be null or NaN where the height is unknown' in err, err


def test_json_rows_have_the_csv_keys_with_null_where_no_value(descent, tmp_path, capsys):
    """A detector without elevation.npy or state.npy had no dem_* or state_* keys in --json rows at all, where
    the CSV keeps empty columns: row["dem_mean_abs_m"] was a KeyError on some rows."""
    outs = tmp_path / "outs"
    for name in ("600_300", "300_150"):
        gt = read_pair(descent / name).truth["hazard"]
        extra = {"elevation": np.zeros_like(gt), "state": np.where(gt < 1, 0, 1)} if name == "600_300" else {}
        _write(outs / name, gt, **extra)
    code, doc = _score(descent, outs, capsys)
    full, bare = doc["rows"]
    assert code == 0 and list(full) == list(bare), (list(full), list(bare))
    assert set(CSV_COLUMNS) <= set(bare) and bare["dem_mean_abs_m"] is None and bare["state_safe_pct"] is None
    assert full["dem_mean_abs_m"] is not None


def test_figures_into_an_out_being_written_are_refused_and_a_csv_is_not_a_figure(descent, tmp_path, capsys):
    """`score --figures` drew into a directory a running `evaluate` held (QA 61a L7), and a --csv named as a
    pair's picture left CSV text under a .png name (L4)."""
    import subprocess
    import sys

    d = descent / "300_150"
    out = _write(tmp_path / "outs" / "300_150", np.ones((128, 128)))
    figs = tmp_path / "figs"
    hold = "import sys\nfrom protocol.outdir import claim_out\nwith claim_out(sys.argv[1], 'evaluate'):\n"
    hold += "    print('held', flush=True)\n    sys.stdin.readline()\n"
    proc = subprocess.Popen([sys.executable, "-c", hold, str(figs)], stdin=subprocess.PIPE, stdout=subprocess.PIPE)
    try:
        assert proc.stdout is not None and proc.stdout.readline().strip() == b"held"
        assert main(["score", str(d), str(out), "--figures", str(figs)]) == 2
        assert f"being written by hazard-hil evaluate (pid {proc.pid})" in capsys.readouterr().err
        assert not list(figs.glob("*.png"))
    finally:
        proc.kill()
        proc.wait()
    assert main(["score", str(d), str(out), "--figures", str(figs), "--csv", str(figs / "300_150_score.png")]) == 2
    assert "is the picture --figures draws for its pair" in capsys.readouterr().err
    assert main(["score", str(d), str(out), "--figures", str(figs), "--csv", str(figs / "rows.csv")]) == 0
    assert (figs / "300_150_score.png").read_bytes()[:4] == b"\x89PNG"
    capsys.readouterr()


def test_a_pair_with_neither_truth_nor_output_says_both(descent, tmp_path, capsys):
    """A pair with no truth and no output was said only to have no output (exit 3), its truth problem hidden
    until an output was given (QA 61a L6)."""
    root = tmp_path / "descent"
    shutil.copytree(descent, root)
    for f in (root / "300_150").glob("gt_*"):
        f.unlink()
    outs = tmp_path / "outs"
    _write(outs / "600_300", np.ones((128, 128)))
    code, doc = _score(root, outs, capsys)
    rows = {r["pair"]: r for r in doc["rows"]}
    assert code == 2 and doc["summary"]["scored"] == 1
    err = rows["300/150"]["error"]
    assert rows["300/150"]["pair_error"] and "no ground truth gt_depth_i1.npy" in err and "output" in err, err


def test_the_runs_grid_scores_are_the_score_commands_whatever_part_of_the_ground_the_grid_maps(descent):
    """The run scored only the pixels a Result's grid mapped: an all-unknown answer on an 8x8 corner scored CDI 69 %
    against 22 % on the whole grid, and `score` gave 27.8 % for the same call (QA 64a, H2). Both now score the
    ground the last frame sees, where an unmapped pixel is not called safe."""
    from ground_sim.gridscore import pixel_ground_xy, score_grids
    from protocol.pairdir import STATE_SAFE, STATE_UNKNOWN
    from studies.score import DetectorOutput, score_output

    pair = read_pair(descent / "600_300")
    x, y = pixel_ground_xy(pair.camera, true_poses(pair)[0], pair.truth["depth"])
    cell = 2.0
    origin = (float(np.nanmin(x)) - cell, float(np.nanmax(y)) + cell)
    shape = (int((origin[1] - np.nanmin(y)) / cell) + 3, int((np.nanmax(x) - origin[0]) / cell) + 3)
    unknown = np.full(shape, STATE_UNKNOWN, np.uint8)
    whole, _ = score_grids(pair, unknown, origin, cell)
    corner, _ = score_grids(pair, unknown[:8, :8], origin, cell)
    assert (whole["cdi_pct"], whole["n"], whole["fp_pct"]) == (corner["cdi_pct"], corner["n"], 0.0)
    assert whole["mapped_pct"] == 100.0 and corner["mapped_pct"] < 5.0
    none = DetectorOutput(np.full(pair.truth["hazard"].shape, np.nan, np.float32), None, None, np.zeros((0, 3)))
    by_score = score_output(pair, none)
    assert (by_score["cdi_pct"], by_score["pixels"]) == pytest.approx((whole["cdi_pct"], whole["n"]))
    safe, _ = score_grids(pair, np.full(shape, STATE_SAFE, np.uint8), origin, cell)  # FP = the hazard share
    assert safe["fp_pct"] == pytest.approx(by_score["hazards_in_scene_pct"]) and safe["fp_pct"] > 5.0


@pytest.mark.parametrize("preset", ["fast", "thesis"])
def test_evaluate_and_score_give_one_figure_for_one_map(descent, tmp_path, capsys, preset):
    """`evaluate` scored over the area the pipeline reported covered: its unmapped rim (2-6.5 % of the overlap)
    dropped out, and the same map read up to 2.5 CDI points above `score`'s figure (QA of stop 65). Both now score
    DESIGN.md's covered area, the true overlap, where an unmapped pixel is not called safe."""
    from studies.evaluate import evaluate_pair

    d = descent / "300_150"
    m = evaluate_pair(str(d), preset, truth_slope=False)
    assert main(["process", str(d), "--out", str(tmp_path / "p"), "--preset", preset]) == 0
    capsys.readouterr()
    _, doc = _score(d, tmp_path / "p", capsys)
    r = doc["rows"][0]
    assert r["unmapped_pct"] > 0.5  # the case that told the two apart: the map leaves part of the overlap NaN
    for key in ("fp_pct", "fn_pct", "cdi_pct", "unmapped_pct"):
        assert m[key] == pytest.approx(r[key], abs=1e-9), key


def test_a_report_file_the_system_refuses_is_exit_4_naming_it_not_the_fp_verdict(descent, tmp_path, capsys):
    """``--json /dev/full`` exited 1, "FP over the limit", for a detector that passed, and named no file (QA 65b L4)."""
    d = descent / "300_150"
    out = _write(tmp_path / "unsafe", np.ones_like(read_pair(d).truth["hazard"]))  # FP 0: passes
    if not Path("/dev/full").exists():
        pytest.skip("no /dev/full here")
    for option in ("--json", "--csv"):
        assert main(["score", str(d), str(out), option, "/dev/full"]) == 4
        captured = capsys.readouterr()
        assert f"hazard-hil score: error: cannot write {option} /dev/full: No space left on device" in captured.err
        assert "| 300_150 |" in captured.out  # the scores stand, printed before
    # a refused --csv does not keep a good --json from being written
    js = tmp_path / "s.json"
    assert main(["score", str(d), str(out), "--csv", "/dev/full", "--json", str(js)]) == 4
    assert json.loads(js.read_text())["rows"][0]["pair"] == "300_150"


def test_a_figure_the_disk_refuses_is_exit_4_naming_it_and_the_scores_stand(descent, tmp_path, capsys, monkeypatch):
    """``--figures`` on a full disk exited 1, "FP over the limit", printed no scores, wrote no --json, and said
    "error: No space left on device" (QA of stop 72)."""
    import errno

    import studies.score

    d = descent / "300_150"
    out = _write(tmp_path / "unsafe", np.ones_like(read_pair(d).truth["hazard"]))  # FP 0: passes

    def full(path, *args, **kw):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(studies.score, "_figure", full)
    js = tmp_path / "s.json"
    assert main(["score", str(d), str(out), "--figures", str(tmp_path / "fig"), "--json", str(js)]) == 4
    captured = capsys.readouterr()
    fig = tmp_path / "fig" / "300_150_score.png"
    assert f"hazard-hil score: error: 300_150: its figure: cannot write {fig}: No space left on device" in captured.err
    assert "| 300_150 |" in captured.out and "figures: none" in captured.out
    row = json.loads(js.read_text())["rows"][0]
    assert row["fp_pct"] == 0.0 and row.get("figure") is None


def test_a_manifest_naming_one_pair_twice_is_refused_not_weighed_twice(descent, tmp_path, capsys):
    """Entries naming the same pair directory, or with the same label, were each scored and counted in the medians
    (QA of stop 66: "CDI median 27.9 %" where the two pairs gave 37.2 %)."""
    outs = tmp_path / "outs"
    for name in ("600_300", "300_150"):
        _write(outs / name, read_pair(descent / name).truth["hazard"])
    twin = tmp_path / "twin"
    twin.mkdir()
    for name in ("600_300", "300_150"):
        (twin / name).symlink_to(descent / name)
    for pairs, what in (
        ([{"path": "600_300"}, {"path": "./600_300"}], "names the same pair directory as pair 0"),
        ([{"path": "600_300"}, {"path": "300_150", "label": "600_300"}], "has the same label as pair 0"),
        ([{"path": "600_300"}, {"path": "sub/600_300", "label": "b"}], "has the same directory name"),
    ):
        (twin / "manifest.json").write_text(json.dumps({"pairs": pairs}))
        assert main(["score", str(twin), str(outs)]) == 2
        assert what in capsys.readouterr().err
    (twin / "manifest.json").write_text(json.dumps({"pairs": [{"path": "600_300"}, {"path": "300_150"}]}))
    assert main(["score", str(twin), str(outs)]) == 0


def test_a_pair_too_large_to_read_is_refused_before_its_frames_are_decoded(descent, tmp_path, monkeypatch, capsys):
    """`score` decoded every frame with no memory check: 16 frames of 4096^2 16-bit RGB took 2.2 GB and 15 s to say
    "no ground truth" (QA of stop 66). The room is now checked from pair.json first, as `process` does."""
    from flight_sw import validate

    outs = tmp_path / "o"
    _write(outs, read_pair(descent / "600_300").truth["hazard"])
    monkeypatch.setattr(validate, "memory_room", lambda: (100 << 10, "of memory is available"))  # a 100 kB machine
    assert main(["score", str(descent / "600_300"), str(outs)]) == 2
    err = capsys.readouterr().err
    assert "128x128 px x 2 frames needs ~1 MiB to read, but only 0 MiB of memory is available" in err, err


def test_an_output_without_result_json_has_unknown_sites_not_no_site(descent, tmp_path, capsys):
    """An interrupted `process` (hazard.npy, no result.json) was scored "no site", as if its detector had found none
    (QA of stop 66). Its sites are now unknown, and said so."""
    out = tmp_path / "o"
    _write(out, read_pair(descent / "600_300").truth["hazard"])
    assert main(["score", str(descent / "600_300"), str(out), "--json", str(tmp_path / "s.json")]) == 0
    said = capsys.readouterr().out
    assert "no result.json: its sites are unknown" in said and "1 whose sites are unknown" in said, said
    (row,) = json.loads((tmp_path / "s.json").read_text())["rows"]
    assert row["sites_unknown"].startswith("no result.json")
    (out / "result.json").write_text(json.dumps({"sites": []}))
    assert main(["score", str(descent / "600_300"), str(out)]) == 0
    said = capsys.readouterr().out
    assert "| no site |" in said and "unknown" not in said, said


def test_a_site_list_too_long_to_judge_is_refused(descent, tmp_path, capsys):
    """800 000 sites fit in a result.json and took about 10 min to judge (QA of stop 66)."""
    from studies.score import MAX_SCORED_SITES

    out = tmp_path / "o"
    _write(out, read_pair(descent / "600_300").truth["hazard"])
    (out / "result.json").write_text(json.dumps({"sites": [{"x": 0, "y": 0, "z": 0}] * (MAX_SCORED_SITES + 1)}))
    assert main(["score", str(descent / "600_300"), str(out)]) == 3
    assert "sites is more than a ranked list" in capsys.readouterr().err


def test_a_long_descent_shows_its_progress_and_an_interrupt_says_how_far_it_got(monkeypatch, capsys):
    """3000 pairs were scored for 21 s without a word, and a Ctrl-C said only "interrupted" (QA of stop 74)."""
    from types import SimpleNamespace

    import pytest

    from studies import cli as scli

    jobs = [SimpleNamespace(label=f"p{k}") for k in range(60)]
    monkeypatch.setattr(scli, "_score_job", lambda job, n, figures: {"pair": job.label})
    assert [r["pair"] for r in scli._score_rows(jobs, None)] == [j.label for j in jobs]
    err = capsys.readouterr().err
    assert "score [" in err and "60/60" in err, err

    def stop_at_30(job, n, figures):
        if job.label == "p30":
            raise KeyboardInterrupt
        return {"pair": job.label}

    monkeypatch.setattr(scli, "_score_job", stop_at_30)
    with pytest.raises(KeyboardInterrupt):
        scli._score_rows(jobs, None)
    assert "interrupted after 30 of 60 pairs: no table, --csv or --json" in capsys.readouterr().err
    monkeypatch.setattr(scli, "_score_job", lambda job, n, figures: {"pair": job.label})
    scli._score_rows(jobs[:3], None)
    assert capsys.readouterr().err == ""  # a short descent draws no bar
