"""Bad arguments to the bench/ scripts: exit 2 with one line naming the problem (the valid choices where there are
some), no traceback, and nothing rendered or written first. Each case runs the script as `make bench` would, in a
process of its own; all of them are refused before any work, in about 10 s
(each script starts a Python of its own)."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
BENCH = ROOT / "bench"
sys.path.insert(0, str(BENCH))

# (script, arguments, what the error line says); W: a directory that must stay empty (outputs and caches go
# there), IN: inputs made for the case, MISSING: a path that does not exist
CASES = [
    ("bench_pipeline.py", ["--presets", "accurate"], "--presets: unknown 'accurate'; choose from 'fast'"),
    ("bench_pipeline.py", ["--pair", "MISSING", "--json", "W/p.json"], "MISSING: not a directory"),
    ("bench_pipeline.py", ["--pair", "IN/empty", "--json", "W/p.json"], "missing pair.json"),
    ("bench_pipeline.py", ["--runs", "0", "--json", "W/p.json"], "argument --runs: must be at least 1, got 0"),
    ("bench_render.py", ["--repeat", "0", "--out", "W/r.md"], "argument --repeat: must be at least 1, got 0"),
    ("bench_render.py", ["--cases", "nadir300", "--out", "W/r.md"], "unknown 'nadir300'; choose from 'nadir 1000 m'"),
    ("bench_protocol.py", ["--only", "nosuch", "--json", "W/p.json"], "--only: unknown 'nosuch'; choose from 'codec'"),
    ("bench_result_size.py", ["--manifest", "MISSING/manifest.json"], "--manifest MISSING/manifest.json: no such"),
    ("bench_result_size.py", ["--steps", "3", "--cache", "W/pairs"], "--steps: expected 2 comma-separated whole"),
    ("eval_flight.py", ["--altitudes", "301", "--cache", "W/c"], "no pair at 301 m (vertical has 50, 75,"),
    ("eval_flight.py", ["--cases", "vertical", "--altitudes", "1200", "--cache", "W/c"], "no pair at 1200 m"),
    ("eval_flight.py", ["--n-seeds", "0", "--cache", "W/c"], "argument --n-seeds: must be at least 1"),
    ("eval_flight.py", ["--presets", "bogus", "--cache", "W/c"], "--presets: unknown 'bogus'; choose from 'fast'"),
    ("eval_flight.py", ["--library", "MISSING", "--cache", "W/c"], "--library MISSING: no such directory"),
    ("bench_hil.py", ["--budgets", "host,nosuch", "--out", "W/h.md"], "unknown budget 'nosuch'; choose one of: host"),
    ("bench_hil.py", ["--scenario", "nosuch", "--out", "W/h.md"], "unknown scenario 'nosuch'"),
    ("bench_hil.py", ["--pairs", "600/301", "--out", "W/h.md"], "--pairs: unknown '600/301'; choose from '1000/500'"),
    ("bench_budget_speed.py", ["--budgets", "nosuch", "--out", "W/b.md"], "unknown budget 'nosuch'; choose one of"),
    ("bench_budget_speed.py", ["--runs", "0", "--out", "W/b.md"], "argument --runs: must be at least 1"),
    ("bench_first_pair.py", ["--pair", "MISSING"], "MISSING: not a directory"),
    ("bench_first_pair.py", ["--pair", "IN/empty"], "missing pair.json"),
    ("bench_pose.py", ["--altitudes", "301", "--cache", "W/c", "--out", "W/o"], "no pair at altitude(s) [301] m"),
    ("bench_pose.py", ["--refine", "nosuch=1", "--cache", "W/c", "--out", "W/o"], "a field of RefineParams"),
    ("results.py", ["MISSING", "--results", "W/RESULTS.md"], "MISSING: no such directory"),
    ("results.py", ["IN/results_out", "--results", "IN/RESULTS.md"], "<!-- END name --> block for landings"),
    ("bench_parallel.py", ["--only", "nosuch", "--out", "W/p.md"], "--only: unknown 'nosuch'; choose from 'render'"),
    (
        "truth_scale.py",
        ["--cases", "approach", "--seeds", "1000", "--altitudes", "1234", "--cache", "W/c", "--json", "W/t.json"],
        "no pair at 1234 m (approach has 125, 150,",
    ),
    ("run_all.py", ["nosuch"], "NAME: unknown 'nosuch'; choose from 'budget_speed'"),
    (
        "op_ceiling.py",
        ["--library", "MISSING", "--cache", "W/c", "--layers", "W/l"],
        "--library MISSING: no such directory",
    ),
    ("site_rules.py", ["--cache", "IN/file"], "--cache IN/file: not a directory"),
    ("bench_derived_truth.py", ["--out", "IN/derived"], "holds vertical renders of seed 1000 at 256 px, not seed 1000"),
    # an output file that could not be written: refused when the arguments are read, not after the work (IN/file
    # is a regular file, IN/empty a directory)
    (
        "bench_pipeline.py",
        ["--runs", "2", "--presets", "fast", "--json", "IN/file/x.json"],
        "argument --json: IN/file/x.json: IN/file is not a directory",
    ),
    (
        "bench_render.py",
        ["--repeat", "1", "--cases", "nadir 1000 m", "--out", "IN/empty"],
        "argument --out: IN/empty: is a directory",
    ),
    ("bench_hil.py", ["--out", "IN/file/hil.md"], "argument --out: IN/file/hil.md: IN/file is not a directory"),
    ("bench_protocol.py", ["--only", "codec", "--json", "IN/file/x.json"], "argument --json: IN/file/x.json: IN/file"),
    ("bench_protocol.py", ["--only", "codec", "--json", "IN/empty"], "argument --json: IN/empty: is a directory"),
    ("bench_budget_speed.py", ["--runs", "1", "--out", "IN/empty"], "argument --out: IN/empty: is a directory"),
    ("bench_parallel.py", ["--out", "IN/file/p.md"], "argument --out: IN/file/p.md: IN/file is not a directory"),
    ("bench_parallel.py", ["--json", "IN/empty"], "argument --json: IN/empty: is a directory"),
    ("bench_throttle.py", ["--quick", "--out", "IN/empty"], "argument --out: IN/empty: is a directory"),
    ("bench_flight_memory.py", ["--cache", "W/c", "--json", "IN/empty"], "argument --json: IN/empty: is a directory"),
    ("bench_fusion_stream.py", ["--cache", "W/c", "--json", "IN/empty"], "argument --json: IN/empty: is a directory"),
    ("bench_multiframe.py", ["accuracy", "--cache", "W/c", "--json", "IN/empty"], "argument --json: IN/empty: is a"),
    ("bench_site_guard.py", ["--cache", "W/c", "--json", "IN/file/s.json"], "argument --json: IN/file/s.json: IN/file"),
    ("eval_flight.py", ["--cache", "W/c", "--json", "IN/empty"], "argument --json: IN/empty: is a directory"),
    ("site_rules.py", ["--cache", "W/c", "--json", "IN/empty"], "argument --json: IN/empty: is a directory"),
    ("slope_errors.py", ["--cache", "W/c", "--json", "IN/empty"], "argument --json: IN/empty: is a directory"),
    ("truth_scale.py", ["--cache", "W/c", "--json", "IN/file/t.json"], "argument --json: IN/file/t.json: IN/file"),
    ("fit_psafe.py", ["--cache", "W/c", "--layers", "W/l", "--write", "IN/empty"], "argument --write: IN/empty: is a"),
    ("results.py", ["IN/results_out", "--results", "IN/empty"], "argument --results: IN/empty: is a directory"),
    ("fit_mapping_cost.py", ["--cache", "W/c", "--out", "IN/file"], "argument --out: IN/file: not a directory"),
    ("bench_pose.py", ["--cache", "W/c", "--out", "IN/file"], "argument --out: IN/file: not a directory"),
    ("bench_derived_truth.py", ["--out", "IN/file/d"], "argument --out: IN/file/d: IN/file is not a directory"),
    # values checked before any render or start
    ("bench_flight_memory.py", ["--scale", "0", "--cache", "W/c"], "argument --scale: must be at least 1, got 0"),
    ("bench_flight_memory.py", ["--scale", "-1", "--cache", "W/c"], "argument --scale: must be at least 1, got -1"),
    ("bench_flight_memory.py", ["--pair", "IN/empty"], "--pair IN/empty: not a pair directory (no pair.json)"),
    (
        "fit_psafe.py",
        ["--cases", "bogus", "--cache", "W/c", "--layers", "W/l"],
        "--cases: unknown 'bogus'; choose from 'vertical'",
    ),
    (
        "fit_psafe.py",
        ["--cases", "vertical", "bogus2", "--cache", "W/c", "--layers", "W/l"],
        "--cases: unknown 'bogus2'; choose from 'vertical'",
    ),
    ("bench_derived_truth.py", ["--image-size", "99999", "--out", "W/d"], "argument --image-size: must be 32..4096"),
    ("bench_derived_truth.py", ["--image-size", "31", "--out", "W/d"], "argument --image-size: must be 32..4096, got"),
    ("bench_first_pair.py", ["--cpu", "99"], "--cpu 99: no such CPU here; choose from "),
    ("slope_errors.py", ["--variants", "bogus", "--cache", "W/c"], "--variants 'bogus': expected base or k=v,k=v"),
    ("slope_errors.py", ["--cases", "nosuch", "--cache", "W/c"], "--cases: unknown 'nosuch'; choose from 'vertical'"),
    # counts: a 0 ran nothing and reported it, or failed deep in the work
    ("slope_errors.py", ["--n-seeds", "0", "--cache", "W/c"], "argument --n-seeds: must be at least 1, got 0"),
    ("bench_fusion_stream.py", ["--n-seeds", "0"], "argument --n-seeds: must be at least 1, got 0"),
    ("bench_site_guard.py", ["--workers", "0"], "argument --workers: must be at least 1, got 0"),
    ("fit_psafe.py", ["--folds", "1", "--cache", "W/c", "--layers", "W/l"], "argument --folds: must be 2..100, got 1"),
    ("fit_psafe.py", ["--per-pair", "0", "--cache", "W/c", "--layers", "W/l"], "argument --per-pair: must be at least"),
]


def _inputs(d: Path) -> None:
    """The inputs the cases name under IN."""
    (d / "empty").mkdir()
    (d / "file").write_text("not a directory\n")
    out = d / "results_out"  # every file bench/results.py reads, and a RESULTS.md without the landings block
    for scen in ("vertical", "approach"):
        (out / f"eval_{scen}" / "report").mkdir(parents=True)
        (out / f"eval_{scen}" / "report" / f"tables_{scen}.md").write_text("|a|\n")
        (out / f"eval_{scen}" / "metrics.csv").write_text("seed\n1000\n")
    (out / "landings" / "report").mkdir(parents=True)
    (out / "landings" / "landings.json").write_text("{}")
    for f in ("p_safe_by_scene.png", "outcomes.png", "divert_cdf.png"):
        (out / "landings" / "report" / f).write_bytes(b"")
    blocks = "".join(f"<!-- BEGIN {b} -->\nold\n<!-- END {b} -->\n" for b in ("provenance", "vertical", "approach"))
    (d / "RESULTS.md").write_text(blocks)
    pair = d / "derived" / "vertical" / "600_300"  # a 256 px render bench_derived_truth would have reused as 512
    pair.mkdir(parents=True)
    (pair.parent / "manifest.json").write_text("{}")
    (pair / "pair.json").write_text(json.dumps({"scene_seed": 1000, "camera": {"width": 256, "height": 256}}))


def _tree(d: Path) -> dict[str, float]:
    return {str(p.relative_to(d)): p.stat().st_mtime for p in sorted(d.rglob("*"))}


def _run(script: str, args: list[str], cwd: Path, tmp: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "TMPDIR": str(tmp)}  # a temporary directory made would be seen
    return subprocess.run(
        [sys.executable, str(BENCH / script), *args], cwd=cwd, env=env, capture_output=True, text=True, timeout=120
    )


def _error_line(p: subprocess.CompletedProcess, script: str) -> str:
    """The one error line; before it only argparse's usage (its first line and indented continuations)."""
    assert p.returncode == 2, (p.returncode, p.stdout[-500:], p.stderr[-2000:])
    assert "Traceback" not in p.stderr, p.stderr
    lines = p.stderr.rstrip("\n").splitlines()
    *usage, last = lines
    assert re.match(rf"{re.escape(script)}( [a-z]+)?: error: ", last), p.stderr  # (a subcommand's prog names it)
    assert not usage or (usage[0].startswith("usage: ") and all(u.startswith(" ") for u in usage[1:])), p.stderr
    return last


@pytest.mark.parametrize(("script", "args", "said"), CASES, ids=[f"{c[0]} {' '.join(c[1])}" for c in CASES])
def test_a_bad_argument_is_one_line_and_exit_2_before_any_work(tmp_path, script, args, said):
    w, inp, tmp = tmp_path / "w", tmp_path / "in", tmp_path / "tmp"
    for d in (w, inp, tmp):
        d.mkdir()
    _inputs(inp)
    before = _tree(inp)

    def path(a: str) -> str:
        return a.replace("W/", f"{w}/").replace("IN/", f"{inp}/").replace("MISSING", str(tmp_path / "missing"))

    p = _run(script, [path(a) for a in args], w, tmp)
    line = _error_line(p, script)
    expected = path(said)
    assert expected in line
    assert list(w.iterdir()) == [] and list(tmp.iterdir()) == []  # nothing rendered, cached or written
    assert _tree(inp) == before
    assert not (tmp_path / "missing").exists()


def test_run_all_has_help_and_names_its_scripts(tmp_path):
    p = _run("run_all.py", ["--help"], tmp_path, tmp_path)
    assert p.returncode == 0 and p.stderr == ""
    assert p.stdout.startswith("usage: run_all.py") and "budget_speed" in p.stdout and "throttle" in p.stdout


def test_a_cache_made_on_demand_is_said_in_one_line(tmp_path):
    """op_ceiling's --cache (eval_flight's renders) is made on first use: a path that does not exist yet is said,
    not refused; here the stale --layers then stop it before any work."""
    layers = tmp_path / "layers"
    layers.mkdir()
    (layers / "pipeline.json").write_text('{"other": 1}\n')  # layers made with other settings: refused
    cache = tmp_path / "typo_cache"
    p = _run("op_ceiling.py", ["--cache", str(cache), "--layers", str(layers)], tmp_path, tmp_path)
    assert p.returncode == 2, p.stderr
    assert f"op_ceiling.py: --cache {cache} does not exist yet: it will be created and filled" in p.stderr
    assert "Traceback" not in p.stderr and not cache.exists()


def test_bench_hil_removes_its_temporary_directory(tmp_path, monkeypatch, capsys):
    """After a run that fails as after one that succeeds; --keep keeps it and names it."""
    import bench_hil

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    seen = []

    def fail(args, work):
        seen.append(work)
        (work / "pairs").mkdir()
        raise RuntimeError("stop")

    monkeypatch.setattr(bench_hil, "bench", fail)
    with pytest.raises(RuntimeError):
        bench_hil.main(["--budgets", "host", "--pairs", "200/100"])
    monkeypatch.setattr(bench_hil, "bench", lambda args, work: seen.append(work) or 0)
    assert bench_hil.main(["--budgets", "host", "--pairs", "200/100"]) == 0
    assert len(seen) == 2 and all(w.name.startswith("bench_hil_") for w in seen)
    assert list(tmp_path.iterdir()) == []
    assert bench_hil.main(["--budgets", "host", "--pairs", "200/100", "--keep"]) == 0
    assert seen[-1].is_dir() and f"bench_hil: kept {seen[-1]}" in capsys.readouterr().err


def test_a_pair_whose_truth_cannot_be_derived_keeps_its_row():
    """bench_derived_truth's table with such a pair (the approach's 600/300 at 256 px): the row says why, the
    others are printed as before."""
    from bench_derived_truth import table

    note = "no gt_hazard_i1.npy, and none can be derived from gt_elevation and gt_depth: frame 0 samples ..."
    rows = [
        {"pair": "approach 600/300", "not_derived": note, "fp": (0.05, None), "cdi": (45.4, None),
         "pixels": (100, None), "top": (True, None), "s": 0.014},
        {"pair": "approach 300/150", "resolved_pct": 76.5, "agree_pct": 97.0, "missed_pct": 1.72, "fp": (0.01, 0.0),
         "cdi": (49.7, 51.7), "pixels": (100, 90), "top": (True, True), "s": 0.022},
    ]  # fmt: skip
    lines = table(rows)
    assert len(lines) == 4
    said = f"| approach 600/300 | 0.0 | no truth derived: {note} | - | 0.05 / - | 45.4 / - | True / - | 0.014 |"
    assert lines[2] == said
    assert lines[3].startswith("| approach 300/150 | 76.5 | 97.0 | 1.72 | 0.01 / 0.00 | 49.7 / 51.7 |")


@pytest.mark.skipif(not Path("/dev/full").exists(), reason="needs /dev/full (a disk that is always full)")
def test_an_output_that_fails_late_is_one_line_and_exit_1(tmp_path):
    """The arguments were right (/dev/full can be opened for writing), the write at the end fails: one line naming
    the file, exit 1 (not 2: no bad argument), no traceback."""
    p = _run("bench_protocol.py", ["--only", "codec", "--json", "/dev/full"], tmp_path, tmp_path)
    assert p.returncode == 1, (p.returncode, p.stderr[-2000:])
    assert "Traceback" not in p.stderr
    assert p.stderr.splitlines() == ["bench_protocol.py: error: cannot write /dev/full: No space left on device"]


def test_run_says_a_late_os_error_in_one_line(monkeypatch, capsys):
    import errno

    import _cli

    monkeypatch.setattr(sys, "argv", ["bench_x.py"])

    def fail() -> int:
        raise PermissionError(errno.EACCES, "Permission denied", "/data/out.json")

    with pytest.raises(SystemExit) as exc:
        _cli.run(fail)
    assert exc.value.code == 1
    assert capsys.readouterr().err == "bench_x.py: error: cannot use /data/out.json: Permission denied\n"


def test_output_file_types(tmp_path):
    import argparse

    import _cli

    (tmp_path / "file").write_text("x")
    deep = tmp_path / "new" / "dirs" / "x.json"  # missing directories are made when the file is written
    assert _cli.out_file(str(deep)) == str(deep)
    assert _cli.out_path(str(deep)) == deep
    assert _cli.write_out(deep, "{}\n") == deep and deep.read_text() == "{}\n"
    assert _cli.out_file(str(deep)) == str(deep)  # an existing file is overwritten
    assert _cli.out_file_or_empty("") == ""
    assert _cli.out_dir(str(tmp_path / "made" / "later")) == tmp_path / "made" / "later"
    refused = {
        _cli.out_file: ["", str(tmp_path), str(tmp_path / "file" / "x.json"), str(tmp_path / "file" / "a" / "b")],
        _cli.out_file_or_empty: [str(tmp_path)],
        _cli.out_dir: [str(tmp_path / "file"), str(tmp_path / "file" / "d")],
    }
    for parse, texts in refused.items():
        for text in texts:
            with pytest.raises(argparse.ArgumentTypeError):
                parse(text)
    if os.geteuid() != 0:  # root may write anywhere
        ro = tmp_path / "ro"
        ro.mkdir(mode=0o500)
        with pytest.raises(argparse.ArgumentTypeError, match="permission denied"):
            _cli.out_file(str(ro / "x.json"))
    with pytest.raises(argparse.ArgumentTypeError, match=re.escape("must be 32..4096, got 4097")):
        _cli.bounded_int(32, 4096)("4097")


def test_bench_protocol_prints_as_it_goes_and_says_how_far_the_fuzz_is(tmp_path):
    """Through a pipe (block buffered unless said otherwise) each result line arrives when printed, not when the
    script ends; a fuzz campaign says on stderr how far it is (here at each tenth of its inputs)."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONUNBUFFERED"}
    cmd = [sys.executable, str(BENCH / "bench_protocol.py"), "--only", "codec", "--fuzz", "--fuzz-inputs", "2000"]
    t0 = time.monotonic()
    with subprocess.Popen(cmd, cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) as p:
        assert p.stdout is not None and p.stderr is not None
        first = p.stdout.readline()
        t_first = time.monotonic()
        rest, err = p.stdout.read(), p.stderr.read()
        rc = p.wait(60)
    t_end = time.monotonic()
    assert rc == 0, err[-2000:]
    assert first.startswith("host load average")
    assert "noise fuzz: 2000 inputs" in rest and "hostile fuzz: 2000 inputs" in rest
    assert t_end - t_first > 0.5, (t_first - t0, t_end - t0)  # printed before the fuzz ran, not at the end
    assert "  noise fuzz: 200/2000 inputs, " in err and "  hostile fuzz: 1800/2000 inputs, " in err
