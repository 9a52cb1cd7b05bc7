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
]


@pytest.mark.parametrize("argv, message", CASES, ids=[" ".join(a[:1] + a[-2:]) for a, _ in CASES])
def test_bad_cli_input_is_one_line_and_exit_2(tmp_path, capsys, argv, message):
    argv = [str(tmp_path) if a == "PAIR" else a for a in argv] + ["--out", str(tmp_path / "out")]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and message in err, err
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())  # nothing half-made
