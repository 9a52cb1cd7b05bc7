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
    (["process", "PAIR", "--deadline", "-1"], "--deadline must be a non-negative"),
    (["run", "--baud", "-5"], "--baud must be a positive rate"),
    (["run", "--deadline", "-1"], "--deadline must be a positive number"),
    (["run", "--link-timeout", "nan"], "--link-timeout must be a positive number"),
    (["run", "--scenario", "vertcal"], "unknown scenario 'vertcal'"),
    (["run", "--budget", "nope"], "unknown budget 'nope'"),
    (["run", "--link-fault", "boom@1"], "--link-fault must be stall@N or exit@N"),
    (["run", "--image-size", "5"], "--image-size must be 16..8192 px"),
    (["run", "--manifest", "M", "--pairs", "600/300", "--seed", "3"], "--pairs, --seed would be ignored"),
    (["demo", "--min-hit-rate", "2"], "--min-hit-rate must be in [0, 1]"),
]


@pytest.mark.parametrize("argv, message", CASES, ids=[" ".join(a[:1] + a[-2:]) for a, _ in CASES])
def test_bad_cli_input_is_one_line_and_exit_2(tmp_path, capsys, argv, message):
    (tmp_path / "manifest.json").write_text('{"pairs": []}')
    subst = {"PAIR": str(tmp_path), "M": str(tmp_path / "manifest.json")}
    argv = [subst.get(a, a) for a in argv] + ["--out", str(tmp_path / "out")]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and message in err, err
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())  # nothing half-made
