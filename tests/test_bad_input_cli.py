"""Bad input at the command line: each case exits 2 with one line naming the problem, before any work is done.

The pair-directory cases (huge image headers, deep or huge pair.json, paths outside the pair, empty truth files)
are in tests/test_pairdir.py; these are the ones only the CLI sees.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from hil_server.cli import main

CASES = [
    (["render", "--scenario", "vertical", "--pose-error", "alt=1e308"], "--pose-error: alt=1e308 must be a number in"),
    (["render", "--scenario", "vertical", "--pose-error", "pitch=nan"], "--pose-error: pitch=nan must be a number in"),
    (["render", "--scenario", "vertical", "--pose-error", "yaw=1"], "bad item 'yaw=1'"),
    (["render", "--scenario", "vertical", "--pose-error", "alt=0.5,alt=1"], "alt is given twice"),  # last won
    (["render", "--scenario", "vertical", "--pose-error", "equal_pitch=5"], "equal_pitch is 0 or 1"),
    (["render", "--scenario", "vertical", "--pairs", ""], "--pairs is empty"),  # rendered every pair
    (["render", "--scenario", "vertical", "--image-size", "20"], "--image-size must be 32..4096 px, got 20"),
    (["render", "--scenario", "vertical", "--frames", "1e6,300"], "must be at most 50000 m"),  # not processable
    (["process", "PAIR", "--deadline", "-1"], "--deadline must be a finite, non-negative"),
    (["process", "PAIR", "--deadline", "inf"], "--deadline must be a finite, non-negative"),
    (["run", "--baud", "-5"], "--baud must be 0 (unpaced) or in [50, 1e+08] baud"),
    (["run", "--baud", "12"], "--baud must be 0 (unpaced) or in [50, 1e+08] baud"),  # refused after rendering
    (["run", "--link", "zmq", "--baud", "115200"], "--baud applies to serial links"),
    (["run", "--link", "serial", "--insecure"], "--keys and --insecure apply to ZeroMQ links"),
    (["run", "--link", "zmq", "--keys", "PAIR"], "client.key_secret does not exist"),
    # each side settled --keys with --insecure its own way (the board CURVE, the ground none), and they disagreed
    (["run", "--link", "zmq", "--keys", "PAIR", "--insecure"], "--keys and --insecure exclude each other"),
    (["flight", "--link", "zmq:tcp://127.0.0.1:5599", "--keys", "PAIR", "--insecure"], "exclude each other"),
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
    (["run", "--deadline", "-1"], "[0.001, 3600] (a Result cannot cross even a local link in less)"),
    (["run", "--deadline", "1e-6"], "--deadline must be a number of seconds in [0.001, 3600]"),
    (["run", "--link-timeout", "nan"], "--link-timeout must be a number of seconds in [2, 3600]"),
    (["run", "--link-timeout", "0.5"], "--link-timeout must be a number of seconds in [2, 3600]"),
    (
        ["run", "--link", "serial", "--baud", "2400"],
        "at 2400 baud one link frame takes up to 6.4 s, past the 4 s link timeout",
    ),
    (["run", "--scenario", "vertcal"], "unknown scenario 'vertcal'"),
    (["run", "--scenario", "nosuch.toml"], "scenario file 'nosuch.toml' not found (no such file)"),
    (["run", "--budget", "nope"], "unknown budget 'nope'"),
    (["run", "--link-fault", "boom@1"], "--link-fault must be stall@N or exit@N"),
    (["run", "--image-size", "5"], "--image-size must be 32..4096 px"),
    (["run", "--image-size", "20"], "--image-size must be 32..4096 px"),
    (["run", "--link-timeout", "1e12"], "--link-timeout must be a number of seconds in [2, 3600]"),
    (
        ["run", "--deadline", "1e308"],
        "--deadline must be a number of seconds in [0.001, 3600] (an hour per pair at most)",
    ),
    # a ZeroMQ board's endpoint, refused before rendering (the ground refused it after, exit 1)
    (["run", "--flight", "external", "--link", "zmq:tcp://127.0.0.1:abc", "--insecure"], "1..65535, got 'abc'"),
    (["run", "--flight", "external", "--link", "zmq:tcp://127.0.0.1", "--insecure"], "needs a host and a port"),
    (["run", "--flight", "external", "--link", "zmq:foo", "--insecure"], "must be tcp://HOST:PORT, ipc://PATH"),
    (["run", "--flight", "external", "--link", "zmq:tcp://10.1.2.3:5555", "--insecure"], "loopback debugging only"),
    # both waited out the 120 s hello timeout, then read as a board that never answered
    (["run", "--flight", "external", "--link", "zmq:tcp://no-such-host.invalid:5555", "--insecure"], "not resolve"),
    (["run", "--flight", "external", "--link", "zmq:inproc://board", "--insecure"], "inproc:// joins threads"),
    (
        ["run", "--flight", "external", "--link", "serial:/dev/ttyS0@fast"],
        "must be a whole number of bits per second (0: unpaced), got 'fast'",
    ),
    (["run", "--flight", "external", "--link", "serial:/dev/ttyS0@"], "nothing after '@'"),
    # the board: before its warm-up
    (["flight", "--link", "zmq:tcp://*:99999", "--insecure"], "1..65535, got '99999'"),
    (["flight", "--link", "zmq:tcp://127.0.0.1:5999", "--insecure", "--link-timeout", "1e12"], "in [2, 3600]"),
    (["flight", "--link", "zmq:tcp://*:5999"], "ZeroMQ links are CURVE-authenticated: give --keys DIR"),
    (["flight", "--link", "zmq:tcp://*:5999", "--keys", "PAIR"], "server.key_secret does not exist"),
    (["run", "--seed", "99999999999999999999999"], "--seed must be in [0, 2**32)"),  # was an OverflowError
    (["run", "--manifest", "M", "--pairs", "600/300", "--seed", "3"], "--pairs, --seed would be ignored"),
    # refused before the demo's half-minute calibration of a new host (it used to calibrate first)
    (["demo", "--min-hit-rate", "2"], "--min-hit-rate must be in [0, 1]"),
    (["demo", "--pairs", "50/25"], "unknown pair(s) ['50/25']; the vertical scenario has"),
    (["demo", "--scene", "nosuch"], "unknown scene preset 'nosuch'"),
    (["demo", "--budget", "slow10", "--budget-file", "SLOW"], "refused before calibrating this host"),
    (["run", "--reconnect-timeout", "0"], "--reconnect-timeout must be a number of seconds in (0, 3600]"),
    (["sensitivity", "--kind", "altitude", "--samples", "100000000"], "samples must be an integer in [1, 10000]"),
    (["landings", "--scenes", "thesis", "--n", "100000000"], "need --n and --per-render <= 1000000"),
    (["evaluate", "--scenario", "vertical", "--cache", "AFILE"], "is a file, not a directory"),  # was a failed task
    (["evaluate", "--scenario", "vertical", "--seeds", "1", "--seed-list", "1000"], "--seeds N and --seed-list"),
    (["evaluate", "--scenario", "vertical", "--seed-list", ""], "--seed-list is empty"),  # ran the default seeds
    (["evaluate", "--scenario", "vertical", "--seed-list", "1000,-5"], "--seed-list seeds must be in [0, 2**32)"),
    (["landings", "--scenes", "thesis", "--n", "2", "--seed-list", "-5"], "--seed-list seeds must be in [0, 2**32)"),
    (["run", "--link", "serial", "--corrupt", "2"], "--corrupt is a per-byte fault rate in [0, 0.05], got 2"),
    (["run", "--link", "zmq", "--corrupt", "0.01"], "--corrupt applies to the serial link only"),
    # "not to --link zmq" named an option that was never given: the host budget's own link is zmq (QA of stop 71)
    (["run", "--corrupt", "1e-6"], "--corrupt applies to the serial link only, and the host budget's own link is zmq"),
    # "does not exist" of a directory that does; one holding a manifest.json is taken (QA of stop 71)
    (["run", "--manifest", "NOMAN"], "is a directory without a manifest.json (render pairs with"),
    (["run", "--bogus"], "hazard-hil run: error: unrecognized arguments: --bogus (see hazard-hil run --help)"),
    (["evaluate", "--scenario", "vertical", "--frames", "300,250"], "it needs --multi-frame"),  # was ignored
    (["landings", "--scenes", "thesis", "--n", "1", "--per-render", "1000000"], "--per-render 1000000 is more"),
    # an empty item in a comma-separated list was skipped: 1,,2 is more likely a value lost in typing
    (["render", "--scenario", "vertical", "--pairs", "600/300,,300/150"], "--pairs: an empty item in"),
    (["render", "--scenario", "vertical", "--frames", "300,250,"], "--frames: an empty item in '300,250,'"),
    (["render", "--scenario", "vertical", "--frames", "300,nan"], "--frames: altitudes must be finite numbers"),
    (["render", "--scenario", "vertical", "--pose-error", "alt=1,,pitch=0"], "--pose-error: an empty item"),
    (["run", "--pairs", ",600/300"], "--pairs: an empty item in ',600/300'"),
    (["regress", "--cases", "a,,b"], "--cases: an empty item in 'a,,b'"),
    (["evaluate", "--scenario", "vertical", "--seed-list", "1000,,1001"], "--seed-list: an empty item in"),
    (["evaluate", "--scenario", "vertical", "--altitudes", "300,,150"], "--altitudes: an empty item in"),
    (["landings", "--scenes", "thesis,,mare", "--n", "2"], "--scenes: an empty item in 'thesis,,mare'"),
]


NO_OUT = ("budgets", "flight")  # commands without an --out


@pytest.mark.parametrize("argv, message", CASES, ids=[" ".join(a[:1] + a[-2:]) for a, _ in CASES])
def test_bad_cli_input_is_one_line_and_exit_2(tmp_path, capsys, monkeypatch, argv, message):
    monkeypatch.setenv("HAZARD_HIL_HOME", str(tmp_path / "home"))  # an uncalibrated host: nothing calibrates first
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
    rad750 = default_budgets_path().read_text().split("[budget.rad750]", 1)[1].split("\n[", 1)[0]
    slow10 = "\n[budget.slow10]" + rad750.replace("cpu_dmips = 400", "cpu_dmips = 10", 1)  # 0.04 % of the anchor
    (tmp_path / "slow.toml").write_text(default_budgets_path().read_text() + slow10)
    subst["SLOW"] = str(tmp_path / "slow.toml")
    subst["TYPO"] = str(tmp_path / "typo.toml")
    (tmp_path / "afile").write_text("")
    subst["AFILE"] = str(tmp_path / "afile")
    (tmp_path / "noman").mkdir()
    subst["NOMAN"] = str(tmp_path / "noman")
    argv = [subst.get(a, a) for a in argv] + (["--out", str(tmp_path / "out")] if argv[0] not in NO_OUT else [])
    assert main(argv) == 2
    cap = capsys.readouterr()
    err = cap.err.strip()
    assert len(err.splitlines()) == 1 and message in err, err
    assert "calibrat" not in cap.out, cap.out
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
    cases = [(tmp_path / "afile", "is a file, not a directory"), (tmp_path / "afile" / "x", "is under")]
    # one that cannot be created or written, root or not (was a traceback after the work, `process` aside)
    cases.append((Path("/proc/hazard-hil-out"), "cannot be written"))
    for out, why in cases:
        assert main([*command, "--out", str(out)]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and why in err, err
    assert (tmp_path / "afile").read_text() == "keep me"


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["process", "PAIR", "--out", ""], "--out must name a path, got an empty one"),  # wrote into the cwd
        (["process", "PAIR", "--out="], "--out must name a path, got an empty one"),
        (["score", "PAIR", "PAIR", "--csv", "/proc/x.csv"], "--csv's directory /proc cannot be written"),
        (["score", "PAIR", "PAIR", "--json", "AFILE/x.json"], "--json's directory"),
        (["score", "PAIR", "PAIR", "--json", "PAIR"], "is a directory, not a file"),
        (["keys", ""], "key directory must name a path, got an empty one"),  # wrote keys into the cwd
        # the JSON silently replaced the CSV
        (["score", "PAIR", "PAIR", "--csv", "AFILE", "--json", "AFILE"], "--csv and --json name the same file"),
    ],
)
def test_output_paths_that_cannot_be_written_are_refused_first(tmp_path, capsys, argv, message):
    """`score` wrote its --csv/--json after scoring every pair: a path it could not write was a traceback then."""
    (tmp_path / "afile").write_text("")
    subst = {"PAIR": str(tmp_path), "AFILE": str(tmp_path / "afile")}
    assert main([a.replace("AFILE", subst["AFILE"]) if a.startswith("AFILE") else subst.get(a, a) for a in argv]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and message in err, err


@pytest.mark.parametrize(
    "argv, message",
    [
        (["evaluat"], "hazard-hil: error: argument COMMAND: invalid choice: 'evaluat'"),
        (["render"], "hazard-hil render: error: the following arguments are required: --scenario, --out"),
        (["evaluate", "--scenario", "vertical", "--camera-px", "16"], "--camera-px must be >= 32"),
        # render's and run's name for it, taken too
        (["evaluate", "--scenario", "vertical", "--image-size", "16"], "--camera-px must be >= 32"),
        (["sensitivity", "--kind", "altitude", "--image-size", "9999"], "--camera-px must be >= 32 and <= 4096"),
        (["run", "--baud", "fast"], "hazard-hil run: error: argument --baud"),
        # both were taken, the last one winning, and nothing said which
        (["run", "--fusion", "--no-fusion"], "argument --no-fusion: not allowed with argument --fusion"),
    ],
)
def test_usage_errors_are_one_line_too(capsys, argv, message):
    """argparse printed its whole usage block before the error; now only the error, pointing at --help."""
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and message in err and "--help)" in err, err


def test_memory_running_out_past_the_checks_is_one_line_and_exit_1(tmp_path, capsys, monkeypatch):
    """A MemoryError past every memory check (another process took the room) ended in a traceback of 60 lines
    (QA of stop 71: numpy's "Unable to allocate 128. MiB for an array with shape (2048, 2048, 4)")."""
    import flight_sw.cli

    def boom(args, scorer=None):
        raise MemoryError("Unable to allocate 128. MiB for an array with shape (2048, 2048, 4) and data type float64")

    monkeypatch.setattr(flight_sw.cli, "_process_held", boom)
    assert main(["process", str(tmp_path), "--out", str(tmp_path / "o")]) == 1
    err = capsys.readouterr().err.strip()
    assert err == (
        "hazard-hil process: error: out of memory (Unable to allocate 128. MiB for an array with shape (2048, 2048, 4) "
        "and data type float64): free some, or use a smaller camera"
    )


def test_a_full_disk_whose_error_names_no_file_names_the_output_on_it(tmp_path, capsys, monkeypatch):
    """A library's write (numpy's, matplotlib's) fails on a full disk with no file name: `landings`, `sensitivity`,
    `scenes --measure` and others said only "error: No space left on device" (QA of stop 72)."""
    import errno
    import shutil
    from collections import namedtuple

    import flight_sw.cli

    def full(args, scorer=None):
        raise OSError(errno.ENOSPC, "No space left on device")

    out = tmp_path / "o"
    usage = namedtuple("usage", "total used free")
    real = shutil.disk_usage
    monkeypatch.setattr(flight_sw.cli, "_process_held", full)
    monkeypatch.setattr(
        shutil, "disk_usage", lambda p: usage(1, 1, 4096) if Path(p) == tmp_path else real(p)
    )  # the disk holding --out has 4 kB left, the calibration store's has room
    assert main(["process", str(tmp_path), "--out", str(out)]) == 1
    assert capsys.readouterr().err.strip() == (
        f"hazard-hil process: error: No space left on device (the disk holding --out {out} is full)"
    )
    monkeypatch.setattr(shutil, "disk_usage", real)  # no disk is full now (the file that filled it went): as it was
    assert main(["process", str(tmp_path), "--out", str(out)]) == 1
    assert capsys.readouterr().err.strip() == "hazard-hil process: error: No space left on device"


def test_a_closed_stdout_does_not_end_a_long_command(tmp_path):
    """`hazard-hil run ... | head -1`: the next progress line raised BrokenPipeError, `run` ended with exit 1 and its
    summary still said "run in progress" (QA of stop 71). Its console lines now go nowhere and it goes on."""
    import subprocess
    import sys

    done = tmp_path / "done"
    code = (
        "from hil_server.cli import console\n"
        "for i in range(20000):\n"
        "    console(f'line {i}')\n"
        f"open({str(done)!r}, 'w').write('ok')\n"
    )
    script = tmp_path / "long.py"
    script.write_text(code)
    p = subprocess.run(f"{sys.executable} {script} | head -1", shell=True, capture_output=True, text=True)
    assert p.stdout == "line 0\n" and done.read_text() == "ok", p.stderr
    assert "BrokenPipeError" not in p.stderr and "Exception ignored" not in p.stderr, p.stderr
