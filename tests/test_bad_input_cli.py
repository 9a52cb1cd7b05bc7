"""Bad input at the command line: each case exits 2 with one line naming the problem, before any work is done.

The pair-directory cases (huge image headers, deep or huge pair.json, paths outside the pair, empty truth files)
are in tests/test_pairdir.py; these are the ones only the CLI sees.
"""

from __future__ import annotations

import pytest

from hil_server.cli import main

CASES = [
    (["render", "--scenario", "vertical", "--pose-error", "alt=1e308"], "altitude_uniform_m must be a number in"),
    (["render", "--scenario", "vertical", "--pose-error", "pitch=nan"], "pitch_uniform_deg must be a number in"),
    (["render", "--scenario", "vertical", "--pose-error", "yaw=1"], "bad item 'yaw=1'"),
    (["render", "--scenario", "vertical", "--pairs", ""], "--pairs is empty"),  # rendered every pair
    (["render", "--scenario", "vertical", "--frames", "1e6,300"], "must be at most 50000 m"),  # not processable
    (["process", "PAIR", "--deadline", "-1"], "--deadline must be a non-negative"),
    (["run", "--baud", "-5"], "--baud must be in [50, 1e+08] baud"),
    (["run", "--baud", "12"], "--baud must be in [50, 1e+08] baud"),  # the ground refused it after rendering
    (["run", "--link", "zmq", "--baud", "115200"], "--baud applies to serial links"),
    (["run", "--link", "serial", "--insecure"], "--keys and --insecure apply to ZeroMQ links"),
    (["run", "--link", "zmq", "--keys", "PAIR"], "client.key_secret does not exist"),
    (["run", "--manifest", "BAD"], "not JSON"),
    (["run", "--manifest", "M"], '"pairs" must be a non-empty list'),  # was a 0/0 run, exit 1
    (["run", "--manifest", "NOPATH"], 'pair 0 has no "path"'),
    (["run", "--manifest", "ALT"], '"altitude_m" must be a number of metres, got "high"'),
    (["run", "--manifest", "ALTNAN"], '"altitude_m" must be a number of metres, got NaN'),  # was taken silently
    (["run", "--manifest", "STR"], 'pair 0 must be an object with a "path"'),
    (["run", "--manifest", "LIST"], "must be a JSON object"),
    (["run", "--manifest", "FORMAT"], "format must be 'hazard-hil-descent/1'"),
    (["budgets", "--file", "PAIR"], "cannot be read as a budget file"),
    (["budgets", "--file", "TYPO"], "unknown key(s) baudd"),
    (["run", "--deadline", "-1"], "--deadline must be a positive number"),
    (["run", "--link-timeout", "nan"], "--link-timeout must be a positive number"),
    (["run", "--scenario", "vertcal"], "unknown scenario 'vertcal'"),
    (["run", "--budget", "nope"], "unknown budget 'nope'"),
    (["run", "--link-fault", "boom@1"], "--link-fault must be stall@N or exit@N"),
    (["run", "--image-size", "5"], "--image-size must be 16..8192 px"),
    (["run", "--seed", "99999999999999999999999"], "--seed must be in [0, 2**62)"),  # was an OverflowError
    (["run", "--manifest", "M", "--pairs", "600/300", "--seed", "3"], "--pairs, --seed would be ignored"),
    (["demo", "--min-hit-rate", "2"], "--min-hit-rate must be in [0, 1]"),
    (["sensitivity", "--kind", "altitude", "--samples", "100000000"], "samples must be an integer in [1, 10000]"),
    (["landings", "--scenes", "thesis", "--n", "100000000"], "need n and per_render <= 1000000"),
    (["evaluate", "--scenario", "vertical", "--cache", "AFILE"], "is a file, not a directory"),  # was a failed task
    (["evaluate", "--scenario", "vertical", "--seeds", "1", "--seed-list", "1000"], "--seeds N and --seed-list"),
    (["evaluate", "--scenario", "vertical", "--seed-list", ""], "--seed-list is empty"),  # ran the default seeds
    (["evaluate", "--scenario", "vertical", "--frames", "300,250"], "it needs --multi-frame"),  # was ignored
]


@pytest.mark.parametrize("argv, message", CASES, ids=[" ".join(a[:1] + a[-2:]) for a, _ in CASES])
def test_bad_cli_input_is_one_line_and_exit_2(tmp_path, capsys, argv, message):
    (tmp_path / "manifest.json").write_text('{"pairs": []}')
    subst = {"PAIR": str(tmp_path), "M": str(tmp_path / "manifest.json")}
    manifests = {
        "BAD": "{bad",
        "NOPATH": '{"pairs": [{"label": "x"}]}',
        "ALT": '{"pairs": [{"path": "p", "altitude_m": "high"}]}',
        "ALTNAN": '{"pairs": [{"path": "p", "altitude_m": NaN}]}',
        "STR": '{"pairs": ["ok"]}',
        "LIST": "[]",
        "FORMAT": '{"format": "x", "pairs": [{"path": "p"}]}',
    }
    for name, text in manifests.items():  # each once crashed `run` with a traceback
        (tmp_path / f"{name}.json").write_text(text)
        subst[name] = str(tmp_path / f"{name}.json")
    from hil_server.budgets import default_budgets_path

    typo = default_budgets_path().read_text().replace("[budget.host]", "[budget.host]\nbaudd = 5", 1)
    (tmp_path / "typo.toml").write_text(typo)
    subst["TYPO"] = str(tmp_path / "typo.toml")
    (tmp_path / "afile").write_text("")
    subst["AFILE"] = str(tmp_path / "afile")
    argv = [subst.get(a, a) for a in argv] + (["--out", str(tmp_path / "out")] if argv[0] != "budgets" else [])
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and message in err, err
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())  # nothing half-made


OUT_COMMANDS = [
    ["render", "--scenario", "vertical"],
    ["run"],
    ["demo"],
    ["regress"],
    ["landings", "--scenes", "thesis", "--n", "1"],
    ["evaluate", "--scenario", "vertical"],
    ["sensitivity", "--kind", "altitude"],
]


@pytest.mark.parametrize("command", OUT_COMMANDS, ids=[c[0] for c in OUT_COMMANDS])
def test_an_out_that_is_a_file_is_refused_before_any_work(tmp_path, capsys, command):
    """Every command creates its --out directory; an existing file there (or above it) was a traceback, some
    of them only after the work was done."""
    (tmp_path / "afile").write_text("keep me")
    for out, why in ((tmp_path / "afile", "is a file, not a directory"), (tmp_path / "afile" / "x", "is under")):
        assert main([*command, "--out", str(out)]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and why in err, err
    assert (tmp_path / "afile").read_text() == "keep me"


@pytest.mark.parametrize(
    "argv, message",
    [
        (["evaluat"], "hazard-hil: error: argument COMMAND: invalid choice: 'evaluat'"),
        (["render"], "hazard-hil render: error: the following arguments are required: --scenario, --out"),
        (["evaluate", "--scenario", "vertical", "--camera-px", "16"], "--camera-px must be >= 32"),
        (["run", "--baud", "fast"], "hazard-hil run: error: argument --baud"),
    ],
)
def test_usage_errors_are_one_line_too(capsys, argv, message):
    """argparse printed its whole usage block before the error; now only the error, pointing at --help."""
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and message in err and "--help)" in err, err
