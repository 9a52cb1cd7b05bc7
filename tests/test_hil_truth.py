"""HIL truth (issue 13): the deadline judged end to end at the ground, budgets that scale, exit codes, clean
shutdown, a user's own flight program in the loop (emulated and external), memory refused up front.

Each end-to-end test starts real OS processes; a 128 px camera (96 px for the slowest budget) keeps them quick.
"""

from __future__ import annotations

import ast
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from hilkit import run_hil, small_descent

from ground_sim.descent import render_scenario
from hil_server.cli import main as cli
from hil_server.run import exit_code, scaled_camera
from protocol.errors import InputError

ROOT = Path(__file__).resolve().parents[1]
MINIMAL = ROOT / "examples" / "minimal_flight.py"
PAIRS = ["600/300", "300/150"]


@pytest.fixture(scope="module")
def manifest(tmp_path_factory):
    return small_descent(tmp_path_factory.mktemp("pairs"), PAIRS)


def run(manifest, tmp_path, **kw):
    return run_hil(manifest, tmp_path, kw.pop("link", "zmq"), **kw)


@pytest.fixture(scope="module")
def one_pair(tmp_path_factory):
    """The descent's first pair alone: a test that holds its core alone holds it half as long (test_board.py renders
    the same pair, so the session's cache has it)."""
    return small_descent(tmp_path_factory.mktemp("one"), PAIRS[:1])


@pytest.mark.exclusive_core
def test_result_line_time_that_pushes_past_the_deadline_is_reported_missed(one_pair, tmp_path, capsys):
    # Full maps at 115200 baud: even an image-only Result needs ~0.12 s on the line, more than the 0.1 s deadline,
    # while the flight side answers within a few hundredths of a second. Counting only "last frame in -> result
    # out" (the flight latency) would call it met; the ground, which holds the Result only after its line time,
    # must not.
    out = tmp_path / "run"
    args = ["run", "--manifest", str(one_pair), "--link", "serial", "--budget", "host", "--baud", "115200"]
    args += ["--full-maps", "--deadline", "0.1", "--out", str(out), "--no-figures"]  # its files, not pictures
    assert cli(args) == 1  # a missed deadline fails the run
    assert "FAIL: " in capsys.readouterr().out
    s = json.loads((out / "summary.json").read_text())
    recs = s["records"]
    assert all(r["status"] == "result" for r in recs) and s["complete"] is True
    for r in recs:
        assert r["deadline_met"] == (r["e2e_latency_s"] <= 0.1)
        assert r["e2e_latency_s"] >= r["result_line_s"] > 0.1  # the line alone is past the deadline
        # the sender's own figure, not one cut to the end to end (but for a loaded host's scheduling jitter)
        assert r.get("result_line_sender_s", r["result_line_s"]) - r["result_line_s"] < 0.05
        assert r["deadline_margin_s"] == pytest.approx(0.1 - r["e2e_latency_s"])
    assert not any(r["deadline_met"] for r in recs) and s["deadline_hit_rate"] == 0.0
    assert min(r["flight_latency_s"] for r in recs) < 0.1  # computed in time, late only on the line
    # the HIL server's own view agrees: judged from the last frame in to the Result acknowledged, so it holds the
    # Result's line time; a server that judged on the flight latency alone, or called every pair met, passed the
    # ground's checks above (mutation audit of stop 75)
    for r in recs:
        assert r["flight_deadline_met"] is False  # the Telemetry's verdict is the server's
        assert r["server_e2e_s"] >= r["flight_latency_s"] + r["result_line_s"] > 0.1
    events = [json.loads(line) for line in (out / "supervisor.jsonl").read_text().splitlines()]
    served = [e for e in events if e["event"] == "result"]
    assert [e["pair_id"] for e in served] == [r["pair_id"] for r in recs]
    assert not any(e["server_deadline_met"] for e in served) and all(e["server_e2e_s"] > 0.1 for e in served)
    assert s["supervisor_counters"]["deadline_missed"] == len(recs) == s["deadline_missed"]
    assert "over **serial** (115200 baud)" in (out / "summary.md").read_text()


def test_baud_0_runs_the_loopback_line_unpaced_as_serial_dev_at_0_does(manifest, tmp_path):
    # `--baud 0` was refused while `serial:DEV@0` meant unpaced; an unset --baud is the default 921600
    for baud, said in (["0"], "(unpaced)"), ([], "(921600 baud)"):
        out = tmp_path / f"run{len(baud)}"
        args = ["run", "--manifest", str(manifest), "--link", "serial", "--budget", "host", "--no-figures"]
        assert cli([*args, *(["--baud", *baud] if baud else []), "--out", str(out)]) == 0
        assert f"over **serial** {said}" in (out / "summary.md").read_text()
        ground = json.loads((out / "received" / "ground.json").read_text())
        assert ground["line_baud"] == (0 if baud else 921600)


@pytest.mark.exclusive_core
@pytest.mark.slow  # ~13 s: the flight process's Python imports take ~10 s at a 4 % duty
def test_a_slow_budgets_deadline_the_full_level_cannot_meet_returns_a_degraded_result_in_time(tmp_path):
    """A board of 1000 DMIPS (x23 slower than the anchor; rad750 is x59 and was this test until it took 28 s of
    every CI run: `hazard-hil regress` keeps a rad750 case). The full level of a 96 px pair takes ~1.0 s end to end
    there; the reserves are in emulated seconds and every stage checks the clock, so the anytime pipeline answers
    a 0.7 s deadline in time with a coarser level (measured: image-only at 0.21-0.25 s)."""
    from hil_server.budgets import default_budgets_path

    shipped = default_budgets_path().read_text()
    board = (
        '[budget.slowboard]\ndescription = "a slow board"\ncpu_dmips = 1000\nmemory_mib = 256\ndeadline_s = 30.0\n'
        'link = "serial"\nbaud = 921600\nsource = "test"\n'
    )
    budgets = tmp_path / "boards.toml"
    budgets.write_text(shipped[: shipped.index("[budget.")] + board)
    pairs = render_scenario("vertical", tmp_path / "pairs", pairs=["300/150"], camera=scaled_camera(96), progress=False)
    s = run(
        pairs / "manifest.json",
        tmp_path / "run",
        budget="slowboard",
        budget_file=budgets,
        link="serial",
        deadline_s=0.7,
        throttle_check=False,
    )
    (r,) = s["records"]
    assert s["cpu_fraction"] < 0.1  # truly throttled
    assert r["status"] == "result" and r["degraded"] and r["level"] != "full", r
    assert r["deadline_met"] and r["e2e_latency_s"] <= 0.7
    assert exit_code(s) == 0


def test_exit_codes_follow_the_rules():
    base = {"complete": True, "pairs": 4, "deadline_met": 4, "deadline_hit_rate": 1.0}
    assert exit_code(base) == 0
    late = {**base, "deadline_met": 3, "deadline_hit_rate": 0.75}
    assert exit_code(late) == 1
    assert exit_code(late, min_hit_rate=0.75) == 0 and exit_code(late, min_hit_rate=0.8) == 1
    assert exit_code({**base, "pairs": 0, "deadline_met": 0, "deadline_hit_rate": float("nan")}) == 1
    assert exit_code({**base, "complete": False}) == 1
    assert exit_code({**base, "complete": False, "interrupted_by": 15}) == 143


@pytest.mark.parametrize(
    "extra",
    [
        ["--min-hit-rate", "1.5"],
        ["--link", "serial:/dev/ttyUSB0"],  # a device needs --flight external
        ["--flight", "external"],  # ... and external needs a device
        ["--flight-cmd", "no-such-flight-program --port {port}"],
        ["--flight-cmd", "'unbalanced"],
        ["--budget", "rad750", "--image-size", "2048"],  # does not fit 256 MiB
    ],
)
def test_bad_usage_is_a_one_line_error_and_exit_2_before_anything_runs(tmp_path, capsys, extra):
    out = tmp_path / "out"
    assert cli(["run", "--out", str(out), *extra]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("hazard-hil run: error:"), err
    assert not (out / "pairs").exists()  # refused up front: nothing rendered


def test_memory_ceiling_admits_960_and_refuses_1024_on_256_mib_budgets():
    from hil_server.budgets import flight_peak_rss_mib, get_budget, max_image_side
    from hil_server.run import check_memory

    for name in ("rad750", "gr740"):
        b = get_budget(name)
        # the flight process peaked at 245.0 MiB private over a 1024^2 approach descent and 252.3 MiB at 1047^2
        # (stop 71; stop 35 had measured 216-222 MiB at 1024^2): 1024^2 leaves the 10 % margin no room under 256 MiB
        assert flight_peak_rss_mib(1024 * 1024) / 1.1 >= 245.0 and flight_peak_rss_mib(1047 * 1047) / 1.1 >= 252.3
        check_memory(b, 960, 960)
        check_memory(b, 512, 512)
        with pytest.raises(InputError, match=r"1024x1024 camera needs ~\d+ MiB peak private RSS"):
            check_memory(b, 1024, 1024)
        side = max_image_side(b.memory_mib)
        assert 960 <= side < 1024 and flight_peak_rss_mib(side * side) <= b.memory_mib
        assert flight_peak_rss_mib((side + 1) ** 2) > b.memory_mib


def test_minimal_flight_imports_nothing_of_this_project():
    tree = ast.parse(MINIMAL.read_text())
    roots = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            roots |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            roots.add((node.module or "").split(".")[0])
    assert roots - sys.stdlib_module_names == {"msgpack", "numpy", "serial"}


def _check_minimal_results(s: dict, out: Path) -> None:
    assert s["results"] == s["pairs"] == len(PAIRS) and s["errors"] == 0
    for r in s["records"]:
        assert r["status"] == "result" and r["level"] == "none" and r["degraded"] and r["deadline_met"]
        states = np.load(out / "received" / r["pair_id"] / "state_grid.npy")
        assert states.size > 0 and set(np.unique(states)) == {2}  # everything unknown, honestly


@pytest.mark.exclusive_core
def test_minimal_flight_runs_a_descent_under_flight_cmd(manifest, tmp_path, capsys):
    out = tmp_path / "run"
    cmd = f"{sys.executable} {MINIMAL} --port {{port}}"
    args = ["run", "--manifest", str(manifest), "--link", "serial", "--budget", "snapdragon801"]
    assert cli([*args, "--flight-cmd", cmd, "--out", str(out)]) == 0
    assert "PASS: 2/2 pairs" in capsys.readouterr().out
    s = json.loads((out / "summary.json").read_text())
    _check_minimal_results(s, out)
    assert s["flight"].startswith("command:") and s["budget"] == "snapdragon801"
    from hil_server.run import unpaced_note

    assert unpaced_note(s) == ""  # the HIL server paces its relay of the program's Results at the line's rate
    assert 0 < np.median([r["cpu_fraction"] for r in s["records"]]) < 0.9  # throttled like ours


def test_external_flight_computer_on_a_serial_device(manifest, tmp_path):
    from hil_server.run import unpaced_note
    from protocol.faults import PtyBridge

    with PtyBridge() as bridge:
        board = subprocess.Popen([sys.executable, str(MINIMAL), "--port", bridge.paths[0]])
        try:
            s = run(manifest, tmp_path, flight="external", link=f"serial:{bridge.paths[1]}@115200")
        finally:
            board.terminate()
            board.wait(timeout=10)
    _check_minimal_results(s, tmp_path)
    assert s["budget"] is None and s["memory_mib"] is None and exit_code(s) == 0
    # minimal_flight measures no line time: unknown, not the span of its one-frame Result here (QA 64a)
    assert all(r["e2e_latency_s"] >= r["result_rx_s"] >= 0 and r["result_line_s"] is None for r in s["records"])
    assert all(r["outside_flight_s"] >= 0 for r in s["records"])
    assert not any("result_line_sender_s" in r for r in s["records"])  # no cut needed on a clean line
    assert not (tmp_path / "supervisor.log").exists()  # no supervisor
    # it writes unpaced into a pty, so its Results arrive faster than 115200 baud carries them: said, with the
    # downlink the latencies leave out (QA of stop 74: "end to end 0.0011 s, met", nothing said)
    note = "Results reached this ground faster than 115200 baud carries them"
    assert note in unpaced_note(s) and note in (tmp_path / "summary.md").read_text(), unpaced_note(s)


def test_the_serial_examples_detector_may_take_longer_than_the_link_timeout(manifest, tmp_path):
    """examples/minimal_flight.py called answer() inside its link loop: a detector of one's own that took 6 s left
    the line silent past the 4 s link timeout, and every pair ended "link_down", the link blamed (QA of stop 78).
    The detector now runs beside the link, as the ZeroMQ example's does."""
    from protocol.faults import PtyBridge

    slow = tmp_path / "slow.py"  # the first pair's answer takes 5 s, past the 4 s without a frame
    slow.write_text(
        f"import sys, time\nsys.path.insert(0, {str(MINIMAL.parent)!r})\nimport minimal_flight as mf\n"
        "real, calls = mf.answer, []\n"
        "def answer(*a):\n    calls.append(1)\n    time.sleep(5.0 if len(calls) == 1 else 0.0)\n    return real(*a)\n"
        "mf.answer = answer\nsys.exit(mf.main())\n"
    )
    with PtyBridge() as bridge:
        board = subprocess.Popen([sys.executable, str(slow), "--port", bridge.paths[0]])
        try:
            link = f"serial:{bridge.paths[1]}@921600"
            s = run(manifest, tmp_path / "run", flight="external", link=link, deadline_s=20.0)
        finally:
            board.terminate()
            board.wait(timeout=10)
    assert [r["status"] for r in s["records"]] == ["result", "result"], [r.get("text") for r in s["records"]]
    assert s["records"][0]["e2e_latency_s"] > 5.0 and exit_code(s) == 0


def test_the_examples_detector_thread_neither_holds_the_exit_nor_ends_the_program_when_it_fails():
    """The detector ran in a ThreadPoolExecutor, whose threads Python joins at exit: a detector still running (or
    hung) kept the board program alive after its ground was done (review of stop 78). It is a daemon thread now;
    and an exception in it is the pair's Error, not the end of the program."""
    import importlib.util
    import threading

    spec = importlib.util.spec_from_file_location("minimal_flight_t", MINIMAL)
    assert spec is not None and spec.loader is not None
    mf = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mf)
    release = threading.Event()
    mf.answer = lambda *a: release.wait(10) and {"frame_seqs": [1, 2]}
    pair = {0: {"seq": 1}, 1: {"seq": 2}}
    done = mf.detect(pair, {"deadline_s": 2.0})
    (thread,) = [t for t in threading.enumerate() if t.name == "detector"]
    assert thread.daemon and not done.done()
    release.set()
    assert done.result(timeout=5)[0] == {"frame_seqs": [1, 2]}

    def broken(*a):
        raise ValueError("my detector's bug")

    mf.answer = broken
    done = mf.detect(pair, {"deadline_s": 2.0})
    done.exception(timeout=5)
    (said,) = mf.answered(pair, {"deadline_s": 2.0}, 0.0, done)
    assert said == (mf.ERROR, {"code": "pipeline_failure", "text": "ValueError: my detector's bug", "seq": 2})


def _descendants(pid: int) -> set[int]:
    children: dict[int, list[int]] = {}
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                ppid = int((d / "stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                continue
            children.setdefault(ppid, []).append(int(d.name))
    out, todo = set(), [pid]
    while todo:
        for c in children.get(todo.pop(), []):
            out.add(c)
            todo.append(c)
    return out


def _is_flight(pid: int) -> bool:
    try:
        return b"flight_sw.flight_main" in Path(f"/proc/{pid}/cmdline").read_bytes()
    except OSError:
        return False


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


def test_a_hil_server_stopped_to_the_end_of_the_run_is_said(manifest, tmp_path):
    """A HIL server stopped (SIGSTOP) until the run ended it had its stop unsaid: the run continues and stops it at
    once, before its loop looked at the clock, so its summary said 0 s and the lost pairs read as the flight
    computer's (QA of stop 85). Its last look now counts it."""
    out = tmp_path / "run"
    cmd = [sys.executable, "-m", "hil_server.cli", "run", "--manifest", str(manifest), "--link", "serial"]
    cmd += ["--budget", "host", "--out", str(out), "--no-figures", "--reconnect-timeout", "1"]
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    server = None
    t0 = time.monotonic()
    try:
        results = out / "received" / "results.jsonl"
        while server is None and time.monotonic() - t0 < 60:  # stopped once the first pair is answered
            if results.is_file() and results.read_text().strip():
                kids = _descendants(proc.pid)
                server = next(p for p in kids if b"hil_server.supervisor" in Path(f"/proc/{p}/cmdline").read_bytes())
            time.sleep(0.05)
        assert server is not None
        os.kill(server, signal.SIGSTOP)  # the ground's session lapses (4 s), it waits 1 s, and the run ends it
        proc.wait(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 1
    s = json.loads((out / "summary.json").read_text())
    assert s["supervisor_counters"]["server_stopped_s"] >= 3.0, s["supervisor_counters"]
    md = (out / "summary.md").read_text()
    assert "The HIL server itself was not scheduled for" in md, md


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_signal_stops_every_process_and_leaves_an_incomplete_summary(manifest, tmp_path, sig):
    out = tmp_path / "run"
    cmd = [sys.executable, "-m", "hil_server.cli", "run", "--manifest", str(manifest), "--link", "serial"]
    cmd += ["--budget", "snapdragon801", "--baud", "115200", "--out", str(out), "--no-figures"]
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    seen: set[int] = set()
    t0 = time.monotonic()
    try:
        # the flight process by name: a run's host-rate probe (stop 82) made three descendants before the ground had
        # started its threads, and the signal came in the middle of that
        while not any(_is_flight(p) for p in seen) and time.monotonic() - t0 < 60:
            seen |= _descendants(proc.pid)
            time.sleep(0.1)
        assert len(seen) >= 3 and any(_is_flight(p) for p in seen), seen
        time.sleep(0.5)
        seen |= _descendants(proc.pid)
        proc.send_signal(sig)
        stdout, stderr = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 128 + sig
    assert "INCOMPLETE" in stdout
    # the ground says the signal the run got: a Ctrl-C read "ground: interrupted by SIGTERM"; a SIGTERM is the
    # run's own stop, which it says was the run's, not a signal from outside (QA of stop 85)
    said = "interrupted by SIGINT" if sig == signal.SIGINT else "stopped by `hazard-hil run` (SIGTERM"
    assert f"ground: {said}" in stderr, stderr[-2000:]
    left = [p for p in seen if _alive(p)]
    assert not left, [Path(f"/proc/{p}/cmdline").read_bytes() for p in left]
    s = json.loads((out / "summary.json").read_text())
    assert s["complete"] is False and sig.name in s["reason"]
    assert len(s["records"]) == len(PAIRS)  # every pair accounted for, unfinished ones marked
    assert all(r["status"] == "result" or r["code"] in ("not_run", "link_down", "interrupted") for r in s["records"])
    # a pair whose frames went when the signal came is not "not run": it was interrupted in flight
    assert all(sig.name in r["text"] for r in s["records"] if r.get("code") == "interrupted")
    # no temporary files left behind (the out directory's lock file names the last command that wrote there)
    assert not [p.name for p in out.rglob(".*") if p.is_file() and p.name != ".hazard-hil.lock"]


def test_regress_from_another_directory_uses_the_packaged_baseline(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert (
        cli(["regress", "--uncalibrated", "--cases", "nope", "--out", "o"]) == 2
    )  # found the packaged baseline, named the case
    err = capsys.readouterr().err
    assert "unknown regression case" in err and "vertical-host-zmq" in err


def test_a_signal_while_the_summary_is_written_lets_it_finish(manifest, tmp_path, monkeypatch):
    """A Ctrl-C in the ~3 s after the ground finished left summary.json saying "run in progress" and no report.html;
    the pairs survived only in received/."""
    import os

    from hil_server import run_report
    from hil_server.run import RunConfig, exit_code, run_descent, verdict_line

    real = run_report.write_run_report

    def interrupted_while_writing(*a, **kw):
        os.kill(os.getpid(), signal.SIGINT)  # delivered to the main thread at once: the write goes on
        return real(*a, **kw)

    monkeypatch.setattr(run_report, "write_run_report", interrupted_while_writing)
    said: list[str] = []
    cfg = RunConfig(out=tmp_path / "o", manifest=manifest, link="zmq", budget="host", pairs=None)
    summary = run_descent(cfg, log=said.append)  # the signal still ends the run (exit 130), once all is written
    assert summary["late_signal"] == signal.SIGINT and exit_code(summary) == 130
    # said, not raised: raised, it cost the verdict and report lines (stop 63's interrupt QA, L11)
    assert verdict_line(summary).startswith("PASS")
    assert (tmp_path / "o" / "report.html").is_file()
    assert json.loads((tmp_path / "o" / "summary.json").read_text())["complete"] is True
    assert any("SIGINT came while the summary was written: it was finished first" in x for x in said), said[-3:]


def test_a_report_page_that_fails_does_not_cost_the_run_its_summary(manifest, tmp_path, monkeypatch):
    """A failure while report.html was drawn ended the run in a traceback, summary.json saying "in progress". The
    summary also says what the budget stood for here (stop 56's budget QA: only supervisor.log did)."""
    from hil_server import run_report
    from hil_server.run import RunConfig, run_descent

    def broken(*a, **kw):
        raise RuntimeError("no display")

    monkeypatch.setattr(run_report, "write_run_report", broken)
    said: list[str] = []
    cfg = RunConfig(out=tmp_path / "o", manifest=manifest, link="zmq", budget="host", pairs=None)
    summary = run_descent(cfg, log=said.append)
    on_disk = json.loads((tmp_path / "o" / "summary.json").read_text())
    assert on_disk["complete"] is True and on_disk["report_error"] == "RuntimeError: no display"
    assert summary["results"] == summary["pairs"] > 0
    assert any("report.html could not be written (RuntimeError: no display)" in x for x in said), said[-3:]
    assert on_disk["budget_speed"] == {"cpu_dmips": None, "share": 1.0}
    assert "Budget host: one core of this host at full speed" in (tmp_path / "o" / "summary.md").read_text()


def test_a_killed_hil_server_is_named_as_killed_and_blamed_for_the_pair_in_flight(manifest, tmp_path):
    """A SIGKILLed server read "exited with -9: flight: boot warm-up ..." (its log's last, unrelated line), and the
    pair in flight "interrupted by SIGTERM", a signal only the run itself had sent (to its ground)."""
    slow = tmp_path / "slow.py"  # answers each pair after 3 s: the kill lands while one is in flight
    slow.write_text(
        f"import sys, time\nsys.path.insert(0, {str(MINIMAL.parent)!r})\nimport minimal_flight as mf\n"
        "real = mf.answer\nmf.answer = lambda *a: (time.sleep(3.0), real(*a))[1]\nsys.exit(mf.main())\n"
    )
    out = tmp_path / "run"
    cmd = [sys.executable, "-m", "hil_server.cli", "run", "--manifest", str(manifest), "--link", "serial"]
    cmd += ["--budget", "host", "--deadline", "10", "--flight-cmd", f"{sys.executable} {slow} --port {{port}}"]
    proc = subprocess.Popen(
        [*cmd, "--out", str(out), "--no-figures"], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE
    )
    try:
        t0 = time.monotonic()
        server = None
        while server is None and time.monotonic() - t0 < 60:
            for pid in _descendants(proc.pid):
                try:
                    if b"hil_server.supervisor" in Path(f"/proc/{pid}/cmdline").read_bytes():
                        server = pid
                except OSError:
                    pass
            time.sleep(0.1)
        assert server is not None
        time.sleep(2.5)  # its flight process up, the first pair in flight
        os.kill(server, signal.SIGKILL)
        proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    s = json.loads((out / "summary.json").read_text())
    assert proc.returncode == 1 and s["complete"] is False
    assert s["reason"].startswith("the HIL server (supervisor) was killed by SIGKILL"), s["reason"]
    assert not any("interrupted by SIGTERM" in str(r.get("text")) for r in s["records"]), s["records"]
    blamed = [r for r in s["records"] if r.get("code") == "server_failed"]  # the pair in flight, if one was
    assert all("killed by SIGKILL" in r["text"] for r in blamed), blamed


def test_the_memory_estimate_holds_the_flight_processs_floor_at_small_cameras():
    """A 36 MiB budget admitted a 32 px camera (estimate 35.4 MiB), then every pair breached its ceiling at 36.6 MiB:
    the process peaks at ~37.2 MiB however small its camera (QA of stop 73)."""
    from hil_server.budgets import flight_peak_rss_mib, max_image_side

    assert min(flight_peak_rss_mib(px * px) for px in (32, 64, 128)) >= 37.2 * 1.1
    assert max_image_side(36) == 0 and max_image_side(37.2 * 1.1) == 0 and max_image_side(42) >= 128
