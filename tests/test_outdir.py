"""One command at a time in an --out (protocol.outdir): a second writer is refused with who holds it."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from hil_server.cli import main
from protocol.errors import InputError
from protocol.outdir import LOCK_NAME, claim_out

HOLD = """
import sys, time
from protocol.outdir import claim_out
with claim_out(sys.argv[1], "evaluate"):
    print("held", flush=True)
    sys.stdin.readline()
"""


@pytest.fixture
def held(tmp_path: Path):
    """``tmp_path / "out"`` held by another process until the test ends."""
    out = tmp_path / "out"
    proc = subprocess.Popen(
        [sys.executable, "-c", HOLD, str(out)], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
    )
    assert proc.stdout is not None and proc.stdout.readline().strip() == "held"
    yield out, proc
    proc.kill()
    proc.wait()


def test_a_directory_another_process_writes_is_refused_with_its_holder(held):
    out, proc = held
    with (
        pytest.raises(InputError, match=rf"being written by hazard-hil evaluate \(pid {proc.pid}\)"),
        claim_out(out, "run"),
    ):
        pass
    proc.kill()  # however the holder ends, the kernel drops its lock
    proc.wait()
    with claim_out(out, "run") as p:
        assert (p / LOCK_NAME).read_text().startswith("hazard-hil run (pid ")


def test_a_second_claim_in_one_process_is_refused_too(tmp_path: Path):
    with (
        claim_out(tmp_path, "evaluate"),
        pytest.raises(InputError, match="being written by hazard-hil evaluate"),
        claim_out(tmp_path, "landings"),
    ):
        pass
    with claim_out(tmp_path, "landings"):  # released at the end of the first
        pass


def test_a_directory_inside_one_another_process_writes_is_refused_and_nothing_is_made(held, capsys):
    """`render --out RUN/pairs` replaced the pairs of a live `run --out RUN` (stop 63's interrupt QA, L13)."""
    out, proc = held
    assert main(["render", "--scenario", "vertical", "--pairs", "600/300", "--out", str(out / "pairs")]) == 2
    err = capsys.readouterr().err.strip()
    assert f"out/pairs is inside {out}, which is being written by hazard-hil evaluate (pid {proc.pid})" in err, err
    assert len(err.splitlines()) == 1 and sorted(p.name for p in out.iterdir()) == [LOCK_NAME]


def test_a_directory_inside_one_this_process_holds_is_claimed(tmp_path: Path):
    """`regress` holds OUT while each case's run claims OUT/<case>; so may any command below its holder."""
    with claim_out(tmp_path / "out", "regress"), claim_out(tmp_path / "out" / "case", "run") as p:
        assert (p / LOCK_NAME).is_file()


def test_a_directory_the_claim_made_and_nobody_wrote_in_is_removed(tmp_path: Path):
    out = tmp_path / "new" / "out"
    with pytest.raises(ValueError), claim_out(out, "evaluate"):
        raise ValueError("bad input, refused before any work")
    assert not out.exists()
    with claim_out(out, "evaluate"):
        (out / "metrics.csv").write_text("x\n")
    assert sorted(p.name for p in out.iterdir()) == [LOCK_NAME, "metrics.csv"]  # what was written stays


@pytest.mark.parametrize(
    "argv",
    [
        ["evaluate", "--scenario", "vertical", "--seeds", "1", "--out", "OUT"],
        ["landings", "--scenes", "mare", "--n", "8", "--out", "OUT"],
        ["run", "--budget", "host", "--out", "OUT"],
        ["regress", "--cases", "", "--out", "OUT"],
    ],
)
def test_commands_refuse_an_out_being_written_with_one_line_exit_2(held, capsys, argv):
    out, proc = held
    assert main([str(out) if a == "OUT" else a for a in argv]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and f"being written by hazard-hil evaluate (pid {proc.pid})" in err, err
    assert sorted(p.name for p in out.iterdir()) == [LOCK_NAME]  # nothing was written or removed there


def test_score_refuses_to_write_its_rows_into_an_out_being_written(held, tmp_path, capsys):
    """`score --csv` into a directory a running `evaluate` held wrote there anyway (QA 61a L7); nothing is made
    in a directory nobody holds."""
    out, proc = held
    argv = ["score", str(tmp_path / "pairs"), str(tmp_path / "outs")]
    assert main([*argv, "--csv", str(out / "rows.csv")]) == 2
    err = capsys.readouterr().err.strip()
    assert f"--csv's directory {out} is being written by hazard-hil evaluate (pid {proc.pid})" in err, err
    assert sorted(p.name for p in out.iterdir()) == [LOCK_NAME]
    free = tmp_path / "free"
    free.mkdir()
    assert main([*argv, "--csv", str(free / "rows.csv")]) == 2  # on to the missing pairs: no lock file left
    assert "being written" not in capsys.readouterr().err and list(free.iterdir()) == []
