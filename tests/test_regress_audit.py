"""Audit of the CI-facing commands: regress's baseline checks and diff, budget files, calibration.

None of these tests runs a descent: every refusal must happen before anything runs.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from hil_server import budgets as B
from hil_server.cli import main
from hil_server.regress import DEFAULT_TOLERANCES, compare, default_baseline_path, diff_table
from protocol.errors import InputError


@pytest.fixture()
def home(tmp_path, monkeypatch):
    monkeypatch.setenv("HAZARD_HIL_HOME", str(tmp_path / "home"))
    return tmp_path / "home"


def _shipped() -> dict:
    return json.loads(default_baseline_path().read_text())


BASE = {
    "deadline_hit_rate": 1.0,
    "errors": 0,
    "latency_p50_ref_s": 1.0,
    "latency_p95_ref_s": 1.0,
    "latency_max_ref_s": 1.0,
}


# --- regress: what regressed ----------------------------------------------------------------


def test_more_degraded_results_is_a_regression_named_in_the_diff():
    # the same latency or less, but a Result cut to a coarser level: faster because it did less
    base = {**BASE, "degraded": 0}
    cur = {**BASE, "degraded": 1, "latency_p50_ref_s": 0.5}
    o = compare("c", cur, base, DEFAULT_TOLERANCES)
    assert any(p.startswith("degraded 1 > baseline 0") for p in o.problems)
    row = next(line for line in diff_table([o]).splitlines() if " degraded " in line)
    assert row.split()[-1] == "REGRESSION"
    assert compare("c", {**cur, "degraded": 0}, base, DEFAULT_TOLERANCES).problems == []


def test_a_baseline_without_the_degraded_count_says_it_cannot_judge_it():
    o = compare("c", {**BASE, "degraded": 2}, dict(BASE), DEFAULT_TOLERANCES)
    assert o.problems == []
    row = next(line for line in diff_table([o]).splitlines() if " degraded " in line)
    assert "not judged" in row and "REGRESSION" not in row


def test_missing_current_values_print_as_a_dash_not_nan():
    o = compare(
        "c", {"deadline_hit_rate": 0.0, "errors": 2, "degraded": 0}, {**BASE, "degraded": 0}, DEFAULT_TOLERANCES
    )
    table = diff_table([o])
    assert "nan" not in table
    assert "REGRESSION" in next(line for line in table.splitlines() if "latency_p50_ref_s" in line)


# --- regress: a malformed baseline is one line, exit 2, before anything runs -----------------


def _edit(doc: dict, path: str, value: object) -> dict:
    *keys, last = path.split("/")
    d = doc
    for k in keys:
        d = d[k]
    if value is KeyError:
        del d[last]
    else:
        d[last] = value
    return doc


@pytest.mark.parametrize(
    "path, value, reason",
    [
        ("cases", {}, "'cases' must be a non-empty object"),
        ("cases/vertical-host-zmq/budget", KeyError, "'budget' must be a non-empty string"),
        ("cases/vertical-host-zmq/budget", "pentium", "unknown budget 'pentium'"),
        ("cases/vertical-host-zmq/budgett", "host", "unknown key(s) budgett"),
        ("cases/vertical-host-zmq/metrics/cpu_p50_ref_s", "fast", "metric 'cpu_p50_ref_s' must be a finite number"),
        (
            "cases/vertical-host-zmq/metrics/deadline_hit_rate",
            -0.5,
            "metric 'deadline_hit_rate' is a share of pairs in",
        ),
        ("cases/vertical-host-zmq/metrics/deadline_hit_rate", 1.5, "metric 'deadline_hit_rate' is a share of pairs in"),
        ("cases/vertical-host-zmq/metrics/deadline_hit_rate", KeyError, "'metrics' has no 'deadline_hit_rate'"),
        ("cases/vertical-host-zmq/metrics/errors", 0.5, "metric 'errors' must be a whole number"),
        ("cases/vertical-host-zmq/pairs", "600/300", "'pairs' must be a non-empty list"),
        ("tolerances/latency_rel", -1, "tolerance 'latency_rel' must be a number >= 0"),
        (
            "cases/vertical-host-zmq/deadline_s",
            1e9,
            "'deadline_s' (as `run --deadline`) must be a number of seconds in [0.001, 3600]",
        ),
        ("cases/vertical-host-zmq/budget_recorded", {"dmips": 1}, "'budget_recorded' is what --update writes"),
        ("tolerances/latency_rell", 0.1, "unknown tolerance 'latency_rell'"),
    ],
)
def test_malformed_baseline_is_one_line_exit_2(tmp_path, capsys, path, value, reason):
    bad = tmp_path / "baseline.json"
    bad.write_text(json.dumps(_edit(_shipped(), path, value)))
    assert main(["regress", "--uncalibrated", "--baseline", str(bad), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert reason in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "o").exists()  # refused before any case ran


def test_baseline_that_is_not_an_object_is_exit_2(tmp_path, capsys):
    bad = tmp_path / "baseline.json"
    bad.write_text("[]")
    assert main(["regress", "--uncalibrated", "--baseline", str(bad), "--out", str(tmp_path / "o")]) == 2
    assert "expected a JSON object" in capsys.readouterr().err


@pytest.mark.parametrize(
    "text, reason",
    [("null", "expected a JSON object"), ('"x"', "expected a JSON object")],  # null ran the shipped cases
)
def test_a_baseline_of_json_null_is_refused_not_the_shipped_cases(tmp_path, capsys, text, reason):
    bad = tmp_path / "baseline.json"
    bad.write_text(text)
    for extra in ([], ["--update"]):
        assert main(["regress", "--uncalibrated", "--baseline", str(bad), "--out", str(tmp_path / "o"), *extra]) == 2
        assert reason in capsys.readouterr().err
    assert bad.read_text() == text and not (tmp_path / "o").exists()


@pytest.mark.parametrize("name", ["evil\x1b[2J\nPASS", "/tmp/elsewhere", "..", "a/b"])
def test_a_case_name_that_could_drive_the_terminal_or_leave_out_is_refused(tmp_path, capsys, name):
    """It went raw into the diff table (an ESC sequence cleared the screen) and named a directory: an absolute
    one ran the whole case outside --out."""
    doc = _shipped()
    doc["cases"] = {name: doc["cases"]["vertical-host-zmq"]}
    bad = tmp_path / "baseline.json"
    bad.write_text(json.dumps(doc))
    assert main(["regress", "--uncalibrated", "--baseline", str(bad), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "a case name is 1-100 printable characters without '/'" in err and len(err.strip().splitlines()) == 1


def test_update_into_a_directory_is_refused_before_the_cases_run(tmp_path, capsys, monkeypatch):
    from hil_server import run

    monkeypatch.setattr(run, "run_descent", lambda *a, **k: pytest.fail("a case ran"))
    (tmp_path / "dir.json").mkdir()
    assert (
        main(
            [
                "regress",
                "--uncalibrated",
                "--baseline",
                str(tmp_path / "dir.json"),
                "--update",
                "--out",
                str(tmp_path / "o"),
            ]
        )
        == 2
    )
    assert "is a directory" in capsys.readouterr().err


def test_every_case_is_checked_before_the_first_runs(tmp_path, capsys, monkeypatch):
    """A later case that could not run (a camera over its budget's memory, a scenario file that is not there)
    was found after the earlier cases had run, and their results were lost."""
    from hil_server import run

    monkeypatch.setattr(run, "run_descent", lambda *a, **k: pytest.fail("a case ran"))
    doc = _shipped()
    good = doc["cases"]["vertical-host-zmq"]
    for later, reason in (
        ({**good, "budget": "rad750", "link": "serial", "image_size": 4096}, "needs ~"),
        ({**good, "scenario": str(tmp_path / "missing.toml")}, "missing.toml"),
    ):
        doc["cases"] = {"first": good, "second": later}
        bad = tmp_path / "baseline.json"
        bad.write_text(json.dumps(doc))
        assert main(["regress", "--uncalibrated", "--baseline", str(bad), "--out", str(tmp_path / "o")]) == 2
        err = capsys.readouterr().err
        assert "case 'second': " in err and reason in err and len(err.strip().splitlines()) == 1, err


def test_a_signal_stops_regress_at_its_case_and_exits_128_plus_n(tmp_path, capsys, monkeypatch):
    """Ctrl-C (or a cancelled CI job's SIGTERM) ended the case it cut short, then regress ran the next cases and
    exited 1, the cancellation reported as a regression."""
    from hil_server import run

    ran = []

    def interrupted(cfg, log=print):
        ran.append(cfg.out.name)
        return {"interrupted_by": 15, "complete": False}

    monkeypatch.setattr(run, "run_descent", interrupted)
    doc = _shipped()
    good = doc["cases"]["vertical-host-zmq"]
    doc["cases"] = {"first": good, "second": good}
    base = tmp_path / "baseline.json"
    base.write_text(json.dumps(doc))
    before = base.read_bytes()
    for extra in ([], ["--update"]):
        assert (
            main(["regress", "--uncalibrated", "--baseline", str(base), "--out", str(tmp_path / "o"), *extra])
            == 128 + 15
        )
        out, err = capsys.readouterr()
        assert "interrupted by SIGTERM during case first; the cases after it were not run" in err
        assert "REGRESSION" not in out and "INTERRUPTED" in out
    assert ran == ["first", "first"] and base.read_bytes() == before
    # stopped during the second case: the first case's verdicts are shown, not lost (QA of stop 66)
    calls = iter([{}, None])

    def second_interrupted(cfg, log=print):
        if next(calls) is None:
            return {"interrupted_by": 15, "complete": False}
        return {"complete": True, "deadline_hit_rate": 1.0, "errors": 0, "pairs": 2, "degraded": 0, "records": [],
                **{f"flight_latency_{q}_s": 0.2 for q in ("p50", "p95", "max")},
                "e2e_latency_max_s": 0.3, "e2e_latency_p50_s": 0.3}  # fmt: skip

    monkeypatch.setattr(run, "run_descent", second_interrupted)
    assert main(["regress", "--uncalibrated", "--baseline", str(base), "--out", str(tmp_path / "o")]) == 128 + 15
    out, err = capsys.readouterr()
    assert "interrupted by SIGTERM during case second" in err and out.rstrip().endswith("INTERRUPTED")
    assert "first " in out and "deadline_hit_rate" in out, out
    # and OUT/regress.json says so, with the finished case's row: a CI job reading it found no file (QA of stop 78)
    report = json.loads((tmp_path / "o" / "regress.json").read_text())
    assert report["verdict"] == "INTERRUPTED" and report["exit_code"] == 128 + 15 and report["judged_ok"] is False
    assert [r["case"] for r in report["cases"]] == ["first"] and "during case second" in report["interrupted"]


def test_empty_cases_option_is_refused_not_all_cases(tmp_path, capsys):
    assert main(["regress", "--uncalibrated", "--cases", ",", "--out", str(tmp_path / "o")]) == 2
    assert "--cases names no case" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_update_of_the_shipped_baseline_refuses_an_uncalibrated_host(home, tmp_path, capsys):
    before = default_baseline_path().read_bytes()
    code = main(["regress", "--uncalibrated", "--update", "--cases", "vertical-host-zmq", "--out", str(tmp_path / "o")])
    assert code == 2
    assert "uncalibrated host" in capsys.readouterr().err
    assert default_baseline_path().read_bytes() == before and not (tmp_path / "o").exists()


def _calibration(**change) -> dict:
    """A calibration store entry for this host, as `hazard-hil calibrate` writes it, with ``change`` applied."""
    entry = {
        "key": B.host_key(),
        "hostname": "h",
        "cpu_model": "m",
        "units_per_s": 50.0,
        "spread": 0.1,
        "seconds": 1.0,
        "measured_at": "2026-01-01T00:00:00+00:00",
    }
    return {**entry, **change}


def test_host_conditions_report_uncalibrated_and_stale(home):
    from hil_server.regress import host_conditions

    cond, notes = host_conditions()
    assert cond["calibration"] is None and any("not calibrated" in n for n in notes)
    cal = _calibration(measured_at="2020-01-01T00:00:00+00:00")
    home.mkdir(parents=True, exist_ok=True)
    (home / "calibration.json").write_text(json.dumps({B.host_key(): cal}))
    cond, notes = host_conditions()
    assert cond["calibration"]["measured_at"] == cal["measured_at"]
    assert any("days old" in n for n in notes)


# --- budget files -----------------------------------------------------------------------------

ANCHOR = '[anchor]\ndescription = "a"\ndmips = 23461\nunits_per_s = 51.0\n'
GOOD = {
    "description": '"mine"',
    "cpu_dmips": "1000",
    "memory_mib": "512",
    "deadline_s": "10",
    "link": '"serial"',
    "baud": "115200",
    "source": '"me"',
}


def _budget_file(tmp_path, name: str = "myboard", **changes: str | None) -> str:
    entry = {**GOOD, **changes}
    body = "".join(f"{k} = {v}\n" for k, v in entry.items() if v is not None)
    p = tmp_path / "mine.toml"
    p.write_text(f"{ANCHOR}\n[budget.{name}]\n{body}")
    return str(p)


@pytest.mark.parametrize(
    "changes, reason",
    [
        ({"deadline_s": None}, "missing 'deadline_s'"),
        ({"description": None, "link": None}, "missing 'description', 'link'"),  # at once, not one per round
        ({"cpu_dmips": "0"}, "'cpu_dmips' must be > 0"),
        ({"memory_mib": "-5"}, "'memory_mib' must be > 0"),
        ({"memory_mib": "1e30"}, "'memory_mib' must be <= 1048576"),
        ({"cpu_dmips": "1e300"}, "'cpu_dmips' must be <="),
        ({"deadline_s": "1e9"}, "'deadline_s' must be <="),
        ({"deadline_s": "1e-4"}, "'deadline_s' must be >= 0.001"),
        ({"link": '"spacewire"'}, "'link' must be one of"),
        ({"baud": "1"}, "'baud' must be an integer in"),
    ],
)
def test_bad_user_budget_file_is_one_line_exit_2(tmp_path, capsys, changes, reason):
    assert main(["budgets", "--file", _budget_file(tmp_path, **changes)]) == 2
    err = capsys.readouterr().err
    assert reason in err and len(err.strip().splitlines()) == 1


def test_an_anchor_missing_keys_names_them_all_at_once(tmp_path, capsys):
    """hil.md says the missing keys are named at once; the [anchor] table's came one a round (QA of stop 80)."""
    p = tmp_path / "mine.toml"
    body = "".join(f"{k} = {v}\n" for k, v in GOOD.items())
    p.write_text(f'[anchor]\ndescription = "a"\n[budget.myboard]\n{body}')
    assert main(["budgets", "--file", str(p)]) == 2
    err = capsys.readouterr().err
    assert "[anchor]: missing 'dmips', 'units_per_s'" in err and len(err.strip().splitlines()) == 1, err


def test_a_budget_whose_line_run_refuses_is_noted_in_the_listing(tmp_path, capsys):
    """A 300-baud budget listed without a word, and `run` then refused it: one link frame takes 51 s, past the 4 s
    link timeout (QA of stop 78)."""
    assert main(["budgets", "--file", _budget_file(tmp_path, baud="300")]) == 0
    out = capsys.readouterr().out
    assert "note: `run` refuses its line at the default --link-timeout: at 300 baud one link frame" in out, out
    assert main(["budgets", "--file", _budget_file(tmp_path, baud="115200")]) == 0
    assert "refuses its line" not in capsys.readouterr().out


def test_a_budget_file_changed_since_the_baseline_is_named_and_fails_the_case(tmp_path, capsys, monkeypatch):
    """Latencies are in reference seconds, so a board made 7x slower in its file read exactly as before and the
    baseline held nothing to notice it (stop 56's budget QA). --update records the budget's figures; a later run
    names what moved and fails the case."""
    from hil_server import regress

    board = _budget_file(tmp_path, cpu_dmips="2760")
    metrics = {**BASE, "pairs": 2, "degraded": 0}
    monkeypatch.setattr(regress, "measure_case", lambda *a, **k: dict(metrics))
    base = tmp_path / "baseline.json"
    case = {"scenario": "vertical", "budget": "myboard", "budget_file": board, "link": "serial"}
    base.write_text(json.dumps({"cases": {"mine": case}}))
    assert main(["regress", "--uncalibrated", "--baseline", str(base), "--update", "--out", str(tmp_path / "o")]) == 0
    recorded = json.loads(base.read_text())["cases"]["mine"]["budget_recorded"]
    assert recorded["cpu_dmips"] == 2760 and recorded["deadline_s"] == 10 and recorded["baud"] == 115200
    capsys.readouterr()
    assert (
        main(["regress", "--uncalibrated", "--baseline", str(base), "--out", str(tmp_path / "o")]) == 0
    )  # unchanged: passes
    _budget_file(tmp_path, cpu_dmips="400")
    assert main(["regress", "--uncalibrated", "--baseline", str(base), "--out", str(tmp_path / "o")]) == 1
    out, err = capsys.readouterr()
    said = "budget myboard changed since the baseline (cpu_dmips 2760.0 -> 400.0)"
    assert said in out and said in err and "--update" in out
    assert "no longer measure the same computer" in out
    # a deadline is what the case asks of the computer, not the computer (QA of stop 80)
    _budget_file(tmp_path, cpu_dmips="2760", deadline_s="3")
    assert main(["regress", "--uncalibrated", "--baseline", str(base), "--out", str(tmp_path / "o")]) == 1
    out, _ = capsys.readouterr()
    assert "(deadline_s 10.0 -> 3.0): the case no longer asks the same of it" in out and "computer" not in out, out


def test_a_case_whose_workload_changed_since_the_baseline_is_named_and_fails(tmp_path, capsys, monkeypatch):
    """Only the pair count was compared: a case moved to another scenario, seed or image size, or its manifest
    rendered again, passed against latencies measured on the old workload (QA of stop 78). --update records the
    workload; a later run names what moved and fails the case; a seed written out as its default is no change."""
    from hil_server import regress

    metrics = {**BASE, "pairs": 2, "degraded": 0, "cpu_p50_ref_s": 0.1, "cpu_p95_ref_s": 0.1, "cpu_max_ref_s": 0.1}
    monkeypatch.setattr(regress, "measure_case", lambda *a, **k: dict(metrics))
    base = tmp_path / "baseline.json"
    case = {"scenario": "vertical", "budget": "host", "link": "zmq", "pairs": ["600/300", "300/150"]}
    base.write_text(json.dumps({"cases": {"mine": case}}))
    argv = ["regress", "--uncalibrated", "--baseline", str(base), "--out", str(tmp_path / "o")]
    assert main([*argv, "--update"]) == 0
    doc = json.loads(base.read_text())
    assert doc["cases"]["mine"]["workload_recorded"]["scenario"] == "vertical"
    doc["cases"]["mine"]["seed"] = 0  # its default, now written out
    base.write_text(json.dumps(doc))
    capsys.readouterr()
    assert main(argv) == 0
    for change, said in (
        ({"scenario": "approach", "pairs": ["500/250", "250/125"]}, "scenario 'vertical' -> 'approach', pairs"),
        ({"seed": 7}, "seed 0 -> 7"),
        ({"image_size": 64}, "image_size None -> 64"),
    ):
        base.write_text(json.dumps({**doc, "cases": {"mine": {**doc["cases"]["mine"], **change}}}))
        assert main(argv) == 1, change
        out, err = capsys.readouterr()
        assert f"the case's workload changed since the baseline ({said}" in out and said in err, out
        assert "re-record the case with --update" in out
    # a manifest rendered again under the same path: its digest moved
    from hilkit import small_descent

    manifest = small_descent(tmp_path / "m", ["600/300", "300/150"], px=64)
    case_m = {**case, "manifest": "m"}
    base.write_text(json.dumps({"cases": {"mine": case_m}}))
    assert main([*argv, "--update"]) == 0
    assert main(argv) == 0
    doc_m = json.loads(manifest.read_text())
    manifest.write_text(json.dumps({**doc_m, "seed": 1}))
    capsys.readouterr()
    assert main(argv) == 1
    assert "manifest_sha256 " in capsys.readouterr().out
    # a trajectory file edited under the same name
    traj = tmp_path / "mine.json"
    frames = [{"position_m": [0, 0, 600]}, {"position_m": [0, 0, 300]}]
    traj.write_text(json.dumps({"pairs": [{"label": "600/300", "frames": frames}]}))
    base.write_text(json.dumps({"cases": {"mine": {**case, "scenario": str(traj), "pairs": ["600/300"]}}}))
    metrics["pairs"] = 1
    assert main([*argv, "--update"]) == 0
    assert main(argv) == 0
    traj.write_text(json.dumps({"pairs": [{"label": "600/300", "frames": frames, "altitude_m": 250}]}))
    capsys.readouterr()
    assert main(argv) == 1
    assert "scenario_sha256 " in capsys.readouterr().out
    # what --update writes is what the checker takes, and nothing else
    bad = {"cases": {"mine": {**case, "workload_recorded": {"colour": 1}}}}
    base.write_text(json.dumps(bad))
    assert main(argv) == 2
    assert "'workload_recorded' is what --update writes" in capsys.readouterr().err


def test_a_case_without_recorded_metrics_is_refused_before_any_case_runs(tmp_path, capsys, monkeypatch):
    """It ran in full, then failed "no baseline for this case" with exit 1 (QA of stop 71); a missing baseline is
    bad usage, exit 2, and found before the first case."""
    from hil_server import regress

    ran: list[str] = []
    monkeypatch.setattr(regress, "measure_case", lambda name, *a, **k: ran.append(name) or dict(BASE))
    base = tmp_path / "baseline.json"
    case = {"scenario": "vertical", "budget": "host", "link": "zmq"}
    base.write_text(json.dumps({"cases": {"old": {**case, "metrics": dict(BASE)}, "new": case}}))
    assert main(["regress", "--uncalibrated", "--baseline", str(base), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "case new in " in err and f"metrics: record them with `hazard-hil regress --baseline {base} --update" in err
    assert ran == [] and len(err.strip().splitlines()) == 1
    assert (
        main(["regress", "--uncalibrated", "--baseline", str(base), "--cases", "old", "--out", str(tmp_path / "o")])
        == 0
    )
    assert ran == ["old"]


def test_a_budget_file_that_would_mislead_a_table_or_a_summary_is_refused(tmp_path, capsys):
    """Found by stop 56's budget QA, each accepted with exit 0: a 300-character name (it broke every table), two
    names that differ only in case, an [anchor] of its own (dmips = 1 made every board faster than the host), and a
    fractional baud whose message showed the valid-looking 115200."""
    long_name = _budget_file(tmp_path, name="b" * 41)
    assert main(["budgets", "--file", long_name]) == 2
    assert "at most 40 characters, got 41" in capsys.readouterr().err
    twins = tmp_path / "twins.toml"
    body = "".join(f"{k} = {v}\n" for k, v in GOOD.items())
    twins.write_text(f"{ANCHOR}\n[budget.myboard]\n{body}\n[budget.MyBoard]\n{body}")
    assert main(["budgets", "--file", str(twins)]) == 2
    assert "'myboard' and 'MyBoard' differ only in case" in capsys.readouterr().err
    own_anchor = tmp_path / "anchor.toml"
    own_anchor.write_text(Path(_budget_file(tmp_path)).read_text().replace("dmips = 23461", "dmips = 1"))
    assert main(["budgets", "--file", str(own_anchor)]) == 2
    assert "differs from the shipped anchor (dmips = 1, shipped 23461)" in capsys.readouterr().err
    assert main(["budgets", "--file", _budget_file(tmp_path, baud="115200.5")]) == 2
    assert "got 115200.5" in capsys.readouterr().err


def test_budgets_says_which_boards_run_will_refuse_or_cap(tmp_path, capsys):
    """A board too slow to emulate, one faster than this host's core, and one no camera fits were listed like any
    other; `run` refused the first and the last, and ran the second at host speed without a word."""
    p = tmp_path / "boards.toml"
    boards = {"crawl": {"cpu_dmips": "1"}, "rocket": {"cpu_dmips": "1e6"}, "tiny": {"memory_mib": "16"}}
    p.write_text(
        ANCHOR
        + "".join(
            f"\n[budget.{n}]\n" + "".join(f"{k} = {v}\n" for k, v in {**GOOD, **c}.items()) for n, c in boards.items()
        )
    )
    assert main(["budgets", "--file", str(p)]) == 0
    out = capsys.readouterr().out
    assert "note: `run` refuses it here: one host-second of flight work would take" in out
    assert "note: faster than this host's core" in out and "pessimistic" in out
    assert "note: no camera fits" in out and " none " in out


def test_a_case_whose_run_did_not_finish_says_why_in_the_table(tmp_path, capsys, monkeypatch):
    """A board that was off read as a "latency regression" whose rows were all REGRESSION; the reason (no Hello
    from the flight computer) was only in the captured stderr."""
    from hil_server import regress

    why = "no Hello from the flight computer on serial:/dev/ttyE@921600 within 8 s: its link never answered"
    metrics = {**BASE, "pairs": 2, "degraded": 0, "deadline_hit_rate": 0.0, "errors": 2}
    monkeypatch.setattr(regress, "measure_case", lambda *a, **k: {**metrics, "incomplete_reason": why})
    base = tmp_path / "baseline.json"
    case = {"scenario": "vertical", "budget": "host", "link": "zmq", "metrics": {**BASE, "pairs": 2, "degraded": 0}}
    base.write_text(json.dumps({"cases": {"board": case}}))
    assert main(["regress", "--uncalibrated", "--baseline", str(base), "--out", str(tmp_path / "o")]) == 1
    assert f"board                          the run did not finish: {why}" in capsys.readouterr().out


def test_user_budget_may_not_redefine_a_shipped_name(tmp_path, capsys):
    assert main(["budgets", "--file", _budget_file(tmp_path, name="rad750")]) == 2
    assert "redefines the shipped budget 'rad750'" in capsys.readouterr().err
    # a verbatim copy of the shipped file with one more budget is fine
    mine = tmp_path / "copy.toml"
    mine.write_text(
        B.default_budgets_path().read_text() + "\n[budget.myboard]\n" + "".join(f"{k} = {v}\n" for k, v in GOOD.items())
    )
    assert set(B.load_budgets(mine)) == {*B.load_budgets(), "myboard"}


# --- calibration ------------------------------------------------------------------------------


def test_calibrate_replaces_a_corrupt_store_and_keeps_the_old_one(home, monkeypatch, capsys):
    from hil_server import calibrate as C

    home.mkdir(parents=True)
    (home / "calibration.json").write_text('{"x": ')
    monkeypatch.setattr(C, "measure_rate", lambda s: C.WorkloadRate(60.0, 0.01, 6, s, 1))
    cal = B.calibrate_host(seconds=0.1, efficiency_fractions=())
    assert B.load_calibration() == cal
    assert (home / "calibration.json.corrupt").read_text() == '{"x": '  # nothing lost
    assert "kept it as" in capsys.readouterr().err


@pytest.mark.parametrize(
    "field, value, reason",
    [
        ("units_per_s", math.inf, "units_per_s"),
        ("spread", "wide", "spread"),
        ("measured_at", "yesterday", "isoformat"),
        # accepted, it made every duty 1e-299: the throttle thread died and the flight ran at full speed, PASS
        ("units_per_s", 1e300, r"units_per_s must be in \[0.05, 50000\]"),
        ("units_per_s", 1e-6, r"units_per_s must be in \[0.05, 50000\]"),
    ],
)
def test_bad_calibration_entry_is_input_error(home, field, value, reason):
    home.mkdir(parents=True)
    entry = _calibration(**{field: value})
    (home / "calibration.json").write_text(json.dumps({B.host_key(): entry}))
    with pytest.raises(InputError, match=reason):
        B.load_calibration()


# --- the run report ---------------------------------------------------------------------------


def test_run_report_headline_counts_degraded_results(tmp_path):
    from hil_server.run_report import write_run_report

    records = [
        {"label": f"{a}/{a // 2}", "status": "result", "degraded": d, "level": lvl, "deadline_met": True}
        for a, d, lvl in ((600, True, "coarse"), (300, False, "full"))
    ]
    summary = {"scenario": "vertical", "link": "zmq", "pairs": 2, "results": 2, "deadline_met": 2}
    page = write_run_report({**summary, "deadline_hit_rate": 1.0, "records": records}, tmp_path / "r.html")
    html = page.read_text()
    assert "Results degraded (a coarser level or stages skipped)" in html and "1/2" in html


def test_a_budget_description_that_could_drive_the_terminal_is_refused(tmp_path):
    """The name was checked, the description and source printed raw (an ESC sequence cleared the screen)."""
    text = (
        B.default_budgets_path()
        .read_text()
        .replace('description = "one unthrottled core', 'description = "evil\\u001b[2J\\nline" # "', 1)
    )
    (tmp_path / "b.toml").write_text(text)
    with pytest.raises(B.BudgetError, match="'description' must be printable text on one line"):
        B.load_budgets(tmp_path / "b.toml")


@pytest.mark.parametrize("value", ["1e-9", "0.0005"])
def test_calibrate_refuses_a_duty_cycle_it_could_not_finish(capsys, value):
    """1e-9 was accepted and the probe never ended, deaf to Ctrl-C."""
    with pytest.raises(SystemExit) as exc:
        main(["calibrate", "--duty-cycles", value])
    assert exc.value.code == 2 and "each duty cycle must be in [0.001, 1)" in capsys.readouterr().err


def test_a_calibration_entry_missing_fields_names_them(home):
    """It said "HostCalibration.__init__() missing 7 required positional arguments: 'key', 'hostname', ..."."""
    home.mkdir(parents=True)
    entry = _calibration()
    del entry["hostname"], entry["seconds"]
    (home / "calibration.json").write_text(json.dumps({B.host_key(): {**entry, "colour": "red"}}))
    with pytest.raises(InputError, match=r"bad entry for this host \(missing hostname, seconds, unknown colour\)"):
        B.load_calibration()


def test_runs_throttle_check_may_measure_below_the_calibration_grids_floor():
    """The floor meant for `calibrate --duty-cycles` was put in the shared probe, and `run`'s check of a budget
    below 0.1 % duty (a 10-DMIPS board) then always failed (review, stop 53)."""
    from hil_server.calibrate import measure_throttle_efficiency

    with pytest.raises(ValueError, match="units must be >= 1"):  # the duty passed its check; units are next
        measure_throttle_efficiency((0.0005,), units=0)
    with pytest.raises(ValueError, match=r"duty cycles must be in \(0, 1\)"):
        measure_throttle_efficiency((0.0,), units=1)


def test_calibrate_refuses_a_store_it_could_not_write_before_measuring(tmp_path, monkeypatch, capsys):
    """HAZARD_HIL_HOME set to a regular file: `calibrate` measured for half a minute, then failed to store."""
    afile = tmp_path / "afile"
    afile.write_text("x")
    monkeypatch.setenv("HAZARD_HIL_HOME", str(afile))
    monkeypatch.setattr(B, "calibrate_host", lambda *a, **k: pytest.fail("measured before the store was checked"))
    assert main(["calibrate"]) == 2
    assert "is a file, not a directory" in capsys.readouterr().err


def test_a_budget_file_without_budget_names_what_it_defines(tmp_path, capsys):
    """`run --budget-file F` alone said "unknown budget 'host'": a name the user never typed."""
    assert main(["run", "--budget-file", _budget_file(tmp_path), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "is not in" in err and "which defines myboard: name one with --budget" in err


def test_update_into_a_new_file_records_the_shipped_cases_named_and_only_those(tmp_path, capsys, monkeypatch):
    """`--update --baseline NEW --cases one` put all three shipped cases in the new file, ran one, then refused to
    write it because the other two measured nothing (QA of stop 71)."""
    from hil_server import regress

    cpu = {"cpu_p50_ref_s": 0.2, "cpu_p95_ref_s": 0.2, "cpu_max_ref_s": 0.2}  # the host case is judged on CPU
    monkeypatch.setattr(regress, "measure_case", lambda *a, **k: {**BASE, **cpu, "pairs": 3, "degraded": 0})
    base = tmp_path / "new.json"
    args = ["regress", "--uncalibrated", "--baseline", str(base), "--update", "--out", str(tmp_path / "o")]
    assert main([*args, "--cases", "vertical-host-zmq"]) == 0, capsys.readouterr().err
    assert list(json.loads(base.read_text())["cases"]) == ["vertical-host-zmq"]
    err = capsys.readouterr().err
    assert "recording the shipped cases (vertical-host-zmq) into it" in err and "did you mean" not in err
    # a misspelt name beside a baseline that is there: said, as it records into a new file (QA of stop 80)
    typo = tmp_path / "nwe.json"
    assert main(["regress", *args[1:3], str(typo), *args[4:], "--cases", "vertical-host-zmq"]) == 0
    assert f"into it (not {base}, which is there: did you mean it?)" in capsys.readouterr().err
    base.unlink()
    assert main([*args, "--cases", "mine"]) == 2
    err = capsys.readouterr().err
    assert "no baseline at" in err and "to hold case(s) ['mine']: name shipped cases" in err and not base.exists()


def test_an_uncalibrated_host_is_refused_unless_told_and_its_verdict_says_so(home, tmp_path, capsys, monkeypatch):
    """On a runner never calibrated, reference seconds assume the anchor's speed: the host case read 30 % low and
    passed with a warning on stderr alone (QA of stop 73). It is refused before any case runs; --uncalibrated
    judges anyway, and the verdict line says so."""
    from hil_server import regress

    metrics = {**BASE, "pairs": 2, "degraded": 0}
    ran = []
    monkeypatch.setattr(regress, "measure_case", lambda *a, **k: ran.append(1) or dict(metrics))
    base = tmp_path / "baseline.json"
    case = {"scenario": "vertical", "budget": "snapdragon801", "link": "serial", "metrics": metrics}
    base.write_text(json.dumps({"cases": {"c": case}}))
    assert main(["regress", "--baseline", str(base), "--out", str(tmp_path / "o")]) == 2
    assert "this host is not calibrated" in capsys.readouterr().err and not ran
    assert main(["regress", "--uncalibrated", "--baseline", str(base), "--out", str(tmp_path / "o")]) == 0
    out = capsys.readouterr().out.strip().splitlines()
    assert ran and out[-1].startswith("PASS against") and "(uncalibrated host" in out[-1], out


def test_update_says_it_records_degraded_results_as_allowed(tmp_path, capsys, monkeypatch):
    """A deadline the board could not meet: every pair came back image_only, and --update recorded "degraded 2",
    PASS, without a word; every later check then allowed it (QA of stop 80)."""
    from hil_server import regress

    degraded = {**BASE, "pairs": 2, "degraded": 2}
    monkeypatch.setattr(regress, "measure_case", lambda *a, **k: dict(degraded))
    base = tmp_path / "baseline.json"
    case = {"scenario": "vertical", "budget": "snapdragon801", "link": "serial"}
    base.write_text(json.dumps({"cases": {"c": case}}))
    argv = ["regress", "--uncalibrated", "--baseline", str(base), "--update", "--out", str(tmp_path / "o")]
    assert main(argv) == 0
    said = "case c: 2 of 2 pairs came back degraded (a coarser level or stages skipped); the baseline allows"
    assert said in capsys.readouterr().err
    assert said in json.loads(base.read_text())["recorded"]["warnings"][-1]


def test_update_shows_what_it_replaces_and_does_not_record_missed_deadlines(tmp_path, capsys, monkeypatch):
    """--update overwrote a baseline 3x faster without showing the old figure, and recorded a case that missed
    every deadline, which every later run then passed against (QA of stop 73)."""
    from hil_server import regress

    old = {**BASE, "pairs": 2, "degraded": 0}
    now = {**old, "latency_p50_ref_s": 3.0 * old["latency_p50_ref_s"]}
    monkeypatch.setattr(regress, "measure_case", lambda *a, **k: dict(now))
    base = tmp_path / "baseline.json"
    case = {"scenario": "vertical", "budget": "snapdragon801", "link": "serial", "metrics": old}
    base.write_text(json.dumps({"cases": {"c": case}}))
    argv = ["regress", "--uncalibrated", "--baseline", str(base), "--update", "--out", str(tmp_path / "o")]
    assert main(argv) == 0
    row = next(ln for ln in capsys.readouterr().out.splitlines() if "latency_p50_ref_s" in ln)
    assert "recorded (was 1.000, +200 %)" in row, row
    missed = {**now, "deadline_hit_rate": 0.0}
    monkeypatch.setattr(regress, "measure_case", lambda *a, **k: dict(missed))
    before = base.read_text()
    assert main(argv) == 1
    out = capsys.readouterr().out
    assert "baseline NOT written" in out and base.read_text() == before
    rows = [ln for ln in out.splitlines() if ln.startswith("c ") and "_" in ln.split()[1]]
    assert rows and all("not recorded" in ln for ln in rows), out  # not "recorded" above "NOT written"
    report = json.loads((tmp_path / "o" / "regress.json").read_text())
    assert report["exit_code"] == 1 and not report["cases"][0]["recorded"]
    assert main([*argv, "--min-hit-rate", "0"]) == 0  # recorded when asked to, by the hit rate it may have
    assert json.loads(base.read_text())["cases"]["c"]["metrics"]["deadline_hit_rate"] == 0.0


def test_a_case_recorded_with_min_hit_rate_is_checked_at_that_rate_unless_told_otherwise(tmp_path, capsys, monkeypatch):
    """A case recorded with --min-hit-rate 0.5 failed every later check that did not repeat the option: the
    baseline kept the hit rate but not the rate allowed (QA of stop 80)."""
    from hil_server import regress

    half = {**BASE, "pairs": 2, "degraded": 0, "deadline_hit_rate": 0.5}
    monkeypatch.setattr(regress, "measure_case", lambda *a, **k: dict(half))
    base = tmp_path / "baseline.json"
    base.write_text(json.dumps({"cases": {"c": {"scenario": "vertical", "budget": "snapdragon801", "link": "serial"}}}))
    argv = ["regress", "--uncalibrated", "--baseline", str(base), "--out", str(tmp_path / "o")]
    assert main([*argv, "--update", "--min-hit-rate", "0.5"]) == 0
    assert json.loads(base.read_text())["cases"]["c"]["min_hit_rate"] == 0.5
    assert main(argv) == 0  # checked at the rate it was recorded at
    assert main([*argv, "--min-hit-rate", "1"]) == 1  # the option, when given, wins
    assert "50% of pairs met theirs end to end, 100% required" in capsys.readouterr().out
    none = {**half, "deadline_hit_rate": 0.0}
    monkeypatch.setattr(regress, "measure_case", lambda *a, **k: dict(none))
    assert main(argv) == 1
    assert "0% of pairs met theirs end to end, 50% required (the baseline's min_hit_rate" in capsys.readouterr().out
    monkeypatch.setattr(regress, "measure_case", lambda *a, **k: dict(half, deadline_hit_rate=1.0))
    assert main([*argv, "--update"]) == 0  # recorded again without the option: every pair is required again
    assert "min_hit_rate" not in json.loads(base.read_text())["cases"]["c"]
    doc = json.loads(base.read_text())
    doc["cases"]["c"]["min_hit_rate"] = 1.5
    base.write_text(json.dumps(doc))
    assert main(argv) == 2
    assert "'min_hit_rate' (as --min-hit-rate) must be a number in [0, 1], got 1.5" in capsys.readouterr().err


def test_a_metric_the_absolute_tolerance_lets_double_reads_loosely_ok():
    """A 0.03 s case could grow 3x under the 0.1 s absolute tolerance and read plain "ok" (QA of stop 73); the
    verdict then said "double" of a 0.003 s case held to 0.103 s, 34x (QA of stop 80)."""
    from hil_server.regress import DEFAULT_TOLERANCES, compare, diff_table

    base = {**BASE, "latency_p50_ref_s": 0.03, "latency_p95_ref_s": 2.0, "latency_max_ref_s": 0.003}
    o = compare("c", {**base, "latency_p50_ref_s": 0.09}, base, DEFAULT_TOLERANCES)
    rows = {ln.split()[1]: ln for ln in diff_table([o]).splitlines()[1:]}
    assert not o.problems and "ok (loosely: the absolute tolerance lets it grow 4x)" in rows["latency_p50_ref_s"]
    assert "lets it grow 34x" in rows["latency_max_ref_s"], rows
    assert rows["latency_p95_ref_s"].endswith(" ok")  # 2 s: held to +35 %


def test_a_serial_budget_may_leave_out_its_baud_and_source(tmp_path):
    """`run --help` said the baud defaults to "the budget's, else 921600", yet a serial budget without one was
    refused; so was one without its free-text source (QA of stop 73)."""
    from hil_server.budgets import load_budgets

    b = load_budgets(_budget_file(tmp_path, link='"serial"', baud=None, source=None))["myboard"]
    assert b.baud == 921600 and b.source == "(not given)"


def test_a_memory_ceiling_past_the_host_and_the_camera_cap_is_said_and_the_table_stays_aligned(tmp_path, capsys):
    """A 1 TiB ceiling ran its columns together ("100%1048576 MiB68183x68183"), offered a 68183 px camera
    `run --image-size` cannot make, and said nothing of this host having far less RAM (QA of stop 73)."""
    assert main(["budgets", "--file", _budget_file(tmp_path, memory_mib="1048576")]) == 0
    out = capsys.readouterr().out.splitlines()
    head = next(ln for ln in out if ln.startswith("budget "))
    row = next(ln for ln in out if ln.startswith("myboard"))
    assert " 1024 GiB" in row and ">=4096" in row and "68183" not in row, row
    assert row.index("1024 GiB") + len("1024 GiB") == head.index("memory") + len("memory")  # under its header
    assert any("over this host's" in ln and "MiB of RAM" in ln for ln in out), out


def test_regress_writes_its_verdict_for_a_ci_to_read(tmp_path, capsys, monkeypatch):
    """The diff table and the verdict were on the console alone (QA of stop 73): OUT/regress.json holds each case's
    metrics with baseline, limit, current and verdict, and the command's verdict and exit code."""
    from hil_server import regress

    metrics = {**BASE, "pairs": 2, "degraded": 0}
    slow = {**metrics, "latency_p50_ref_s": 2.0}
    monkeypatch.setattr(regress, "measure_case", lambda *a, **k: dict(slow))
    base = tmp_path / "baseline.json"
    case = {"scenario": "vertical", "budget": "snapdragon801", "link": "serial", "metrics": metrics}
    base.write_text(json.dumps({"cases": {"c": case}}))
    assert main(["regress", "--uncalibrated", "--baseline", str(base), "--out", str(tmp_path / "o")]) == 1
    doc = json.loads((tmp_path / "o" / "regress.json").read_text())
    assert doc["exit_code"] == 1 and doc["verdict"].startswith("FAIL against") and not doc["judged_ok"]
    (c,) = doc["cases"]
    p50 = c["metrics"]["latency_p50_ref_s"]
    assert (p50["baseline"], p50["current"], p50["verdict"]) == (1.0, 2.0, "REGRESSION") and p50["limit"] == 1.35
    assert c["metrics"]["deadline_hit_rate"]["verdict"] == "ok" and c["problems"]


def test_an_interrupted_update_does_not_say_recorded(tmp_path, capsys, monkeypatch):
    """A SIGINT during the second case of an --update left the first one's rows reading "recorded", then "the
    baseline is unchanged" (QA of stop 73)."""
    from hil_server import regress

    metrics = {**BASE, "pairs": 2, "degraded": 0}
    calls = []

    def measure(name, *a, **k):
        calls.append(name)
        if len(calls) > 1:
            raise regress.RegressInterrupted(2, name)
        return dict(metrics)

    monkeypatch.setattr(regress, "measure_case", measure)
    base = tmp_path / "baseline.json"
    case = {"scenario": "vertical", "budget": "snapdragon801", "link": "serial", "metrics": metrics}
    base.write_text(json.dumps({"cases": {"a": case, "b": case}}))
    before = base.read_text()
    argv = ["regress", "--uncalibrated", "--baseline", str(base), "--update", "--out", str(tmp_path / "o")]
    assert main(argv) == 130
    out = capsys.readouterr().out
    assert "recorded" not in out.replace("not recorded", "") and "not recorded (interrupted" in out, out
    assert base.read_text() == before


def test_an_uncalibrated_run_says_so_once_and_does_not_claim_the_duty_delivers(home, tmp_path, capsys):
    """An uncalibrated run warned three times, and its summary said "the throttle's duty cycle 32.6 % delivers that
    share", which nothing had measured (QA of stop 73)."""
    argv = [
        "run",
        "--budget",
        "snapdragon801",
        "--image-size",
        "64",
        "--pairs",
        "600/300",
        "--out",
        str(tmp_path / "r"),
    ]
    assert main(argv) == 0
    err = capsys.readouterr().err
    assert err.count("no calibration for this host") == 1, err
    assert "no calibration" not in (tmp_path / "r" / "supervisor.log").read_text()
    md = (tmp_path / "r" / "summary.md").read_text()
    assert "delivers that share" not in md and "not measured here" in md


def test_a_run_that_ends_early_leaves_no_earlier_verdict_behind(tmp_path, capsys, monkeypatch):
    """regress.json is written at the end: a later run into the same --out that ended with exit 2 left the earlier
    run's PASS for a CI to read (review of stop 73)."""
    from hil_server import regress

    metrics = {**BASE, "pairs": 2, "degraded": 0}
    monkeypatch.setattr(regress, "measure_case", lambda *a, **k: dict(metrics))
    base = tmp_path / "baseline.json"
    case = {"scenario": "vertical", "budget": "snapdragon801", "link": "serial", "metrics": metrics}
    base.write_text(json.dumps({"cases": {"c": case}}))
    argv = ["regress", "--uncalibrated", "--baseline", str(base), "--out", str(tmp_path / "o")]
    assert main(argv) == 0 and json.loads((tmp_path / "o" / "regress.json").read_text())["exit_code"] == 0
    assert main([*argv, "--cases", "nosuch"]) == 2
    assert not (tmp_path / "o" / "regress.json").exists()


def test_a_board_case_on_an_uncalibrated_host_is_not_called_uncalibrated(home, tmp_path, capsys, monkeypatch):
    """The verdict's "uncalibrated host" looked at every case of the baseline, not those run: a board case, which
    needs no calibration, was labelled so (review of stop 73)."""
    from hil_server import regress

    metrics = {**BASE, "pairs": 2, "degraded": 0, "e2e_latency_max_s": 1.0, "e2e_latency_p50_s": 1.0}
    monkeypatch.setattr(regress, "measure_case", lambda *a, **k: dict(metrics))
    monkeypatch.setattr(regress, "check_cases", lambda *a, **k: None)
    base = tmp_path / "baseline.json"
    board = {"scenario": "vertical", "budget": "snapdragon801", "link": "serial:/dev/x", "flight": "external"}
    emulated = {"scenario": "vertical", "budget": "snapdragon801", "link": "serial"}
    base.write_text(json.dumps({"cases": {"b": {**board, "metrics": metrics}, "e": {**emulated, "metrics": metrics}}}))
    assert main(["regress", "--baseline", str(base), "--cases", "b", "--out", str(tmp_path / "o")]) == 0
    verdict = capsys.readouterr().out.strip().splitlines()[-1]
    assert verdict.startswith("PASS against") and "uncalibrated" not in verdict, verdict


def test_a_cases_contention_reaches_its_row_in_the_table(tmp_path, capsys, monkeypatch):
    """measure_case carries the run's flight_contention_pct to the case outcome, which notes it under the case, and
    regress.json keeps it; it is not written into the baseline (review of stop 73)."""
    from hil_server import run

    summary = {"deadline_hit_rate": 1.0, "errors": 0, "pairs": 2, "degraded": 0, "complete": True,
               "flight_latency_p50_s": 1.0, "flight_latency_p95_s": 1.0, "flight_latency_max_s": 1.0,
               "e2e_latency_max_s": 1.2, "e2e_latency_p50_s": 1.1, "records": [], "flight_contention_pct": 40.0,
               "flight_contention_s": 0.8}  # fmt: skip
    monkeypatch.setattr(run, "run_descent", lambda cfg, log=None: dict(summary))
    base = tmp_path / "baseline.json"
    case = {"scenario": "vertical", "budget": "snapdragon801", "link": "serial"}
    base.write_text(json.dumps({"cases": {"c": case}}))
    argv = ["regress", "--uncalibrated", "--baseline", str(base), "--update", "--out", str(tmp_path / "o")]
    main(argv)
    out = capsys.readouterr().out
    assert "note: its flight process waited 40 % of its flight time for its core" in out, out
    assert json.loads((tmp_path / "o" / "regress.json").read_text())["cases"][0]["contention_pct"] == 40.0
    assert "contention_pct" not in json.loads(base.read_text())["cases"]["c"].get("metrics", {})
