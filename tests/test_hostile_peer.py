"""A hostile or broken flight side, end to end: a record declared far over the size limit must not hold a pair (or
the stream behind it) until a hard deadline, at the HIL server or at the ground; a flight computer that never says
Hello must not hold the ground for 15 minutes.

The hostile flight program is examples/minimal_flight.py that, for the second pair it receives, starts a record
declaring ``--declare`` bytes instead of its Result and trickles its body (64 B every 0.1 s) while its heartbeats go
on: the receiver can neither accept the record nor see its end. Small 128 px pairs, host budget, a 30 s deadline, so
that waiting for the hard limit (60 s at the HIL server) or the ground's timeout (120 s) shows.
"""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from hilkit import small_descent, strict_json

from hil_server.cli import main

PAIRS = ["600/300", "300/150", "200/100"]
EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
DEADLINE_S = 30.0  # HIL server's hard limit: 60 s; the ground's own timeout: 3 x 30 + 30 s
GiB = 1 << 30
PROMPT_S = 15.0  # time to the verdict: generous for a loaded 2-core machine, far under the limits above

HOSTILE_FLIGHT = """
import argparse, os, struct, sys, time
sys.path.insert(0, {examples!r})
import minimal_flight as mf
import serial

ap = argparse.ArgumentParser()
ap.add_argument("--port")
ap.add_argument("--declare", type=int, help="body length the second pair's record declares")
ap.add_argument("--type", type=int, default=mf.RESULT, help="type code of that record")
ap.add_argument("--once", help="a file: hostile only if it does not exist yet (created then), not in every incarnation")
ap.add_argument("--no-hello", action="store_true", help="answer the link's HELLO but never the Hello message")
args = ap.parse_args()
link = mf.Link(serial.serial_for_url(args.port, baudrate=921600, timeout=0.02))
config, pending, answered, next_beat, next_trickle, hostile = None, {{}}, 0, 0.0, 0.0, None

while not link.closed_by_peer:
    for mtype, msg in link.poll():
        if mtype == mf.HELLO_MSG and not args.no_hello:
            link.send(mf.HELLO_MSG, {{"role": "flight", "session": link.local}})
        elif mtype == mf.CONFIG:
            config = msg
        elif mtype == mf.FRAME_MSG:
            pair = pending.setdefault(msg["pair_id"], {{}})
            pair[msg["frame_index"]] = msg
            if len(pair) < 2:
                continue
            del pending[msg["pair_id"]]
            answered += 1
            if answered == 2 and not (args.once and os.path.exists(args.once)):
                # this pair's answer: a record header declaring args.declare bytes, then a trickle of its body
                if args.once:
                    open(args.once, "w").close()
                link.tx_data += struct.pack(">BI", args.type, args.declare)
                hostile = link.local  # only in this session: a new one starts clean
                continue
            link.send(mf.RESULT, mf.answer(pair[0], pair[1], config))
            link.send(mf.TELEMETRY, {{"frame_seqs": [pair[0]["seq"], pair[1]["seq"]], "stages": {{}},
                                      "total_latency_s": 0.0, "deadline_s": float(config["deadline_s"]),
                                      "deadline_met": True}})
    now = time.monotonic()
    if hostile is not None and hostile == link.local and now >= next_trickle:
        link.tx_data += bytes(64)
        next_trickle = now + 0.1
    if now >= next_beat:
        link.datagram(mf.HEARTBEAT, {{"time_s": now, "counter": 1}})
        next_beat = now + 0.5
"""


@pytest.fixture(scope="module")
def manifest(tmp_path_factory):
    return small_descent(tmp_path_factory.mktemp("pairs"), PAIRS)


@pytest.fixture(scope="module")
def hostile(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("flight") / "hostile_flight.py"
    path.write_text(HOSTILE_FLIGHT.format(examples=str(EXAMPLES)))
    return path


def run_cli(manifest: Path, out: Path, *extra: str) -> tuple[int, dict]:
    """`hazard-hil run` with a 30 s deadline, its page without pictures: (exit code, summary.json)."""
    argv = ["run", "--manifest", str(manifest), "--deadline", str(DEADLINE_S), "--out", str(out), "--no-figures"]
    argv += extra
    code = main(argv)
    return code, strict_json(out / "summary.json")


def outcomes(summary: dict) -> list[tuple[str, str, str | None]]:
    return [(r["label"], r["status"], r.get("code")) for r in summary["records"]]


def test_a_result_declared_over_the_limit_ends_its_pair_at_once_and_restarts_the_flight(manifest, hostile, tmp_path):
    """The HIL server skipped the 1 GiB record's bytes as they came and refused it only at the hard limit (60 s
    here), reported as a hang; every message behind it on the stream waited too."""
    cmd = f"{sys.executable} {hostile} --declare {GiB} --port {{port}}"
    code, s = run_cli(manifest, tmp_path, "--budget", "host", "--link", "serial", "--flight-cmd", cmd)
    assert code == 1 and s["complete"] is True
    assert outcomes(s) == [("600/300", "result", None), ("300/150", "error", "bad_result"), ("200/100", "result", None)]
    bad = s["records"][1]
    assert bad["elapsed_s"] < PROMPT_S, bad
    assert f"Result was refused: message of {GiB} bytes exceeds the {32 << 20}-byte limit" in bad["text"]
    counters = s["supervisor_counters"]
    assert counters["refused_messages"] == 1 and counters["hangs"] == 0
    assert counters["restarts"] == 1 and counters["errors"] == 1 and counters["results"] == 2
    (refused,) = [e for e in s["flight_events"] if e["event"] == "refused"]
    assert refused["type"] == "Result" and str(GiB) in refused["reason"]
    (restart,) = [e for e in s["flight_events"] if e["event"] == "restart"]
    assert "held by a Result refused from its header" in restart["reason"]


def test_a_record_of_no_known_type_declared_over_the_limit_restarts_the_flight_and_its_pair_is_replayed(
    manifest, hostile, tmp_path
):
    """No pair can be blamed for a record of an unknown type; the stream behind it is held all the same. The new
    incarnation gets the pair again and answers it."""
    cmd = f"{sys.executable} {hostile} --declare {GiB} --type 99 --once {tmp_path / 'once'} --port {{port}}"
    code, s = run_cli(manifest, tmp_path, "--budget", "host", "--link", "serial", "--flight-cmd", cmd)
    assert code == 0 and [r["status"] for r in s["records"]] == ["result"] * 3
    assert s["records"][1]["elapsed_s"] < PROMPT_S
    counters = s["supervisor_counters"]
    assert counters["refused_messages"] == 1 and counters["restarts"] == 1 and counters["hangs"] == 0
    (refused,) = [e for e in s["flight_events"] if e["event"] == "refused"]
    assert refused["type"] == "message" and f"message of {GiB} bytes" in refused["reason"]


def test_a_record_refused_from_its_header_is_not_counted_again_when_its_reject_comes():
    """The HIL server refuses a record over the limit from its header; should all its bytes still arrive before the
    restart, the link's own refusal of it must not count it twice nor end a second pair."""
    from types import SimpleNamespace

    from hil_server.supervisor import PairState, Supervisor
    from protocol.arq import Refusal, Skipping
    from protocol.messages import Result

    class Flight:  # the link's view of one flight incarnation, as FlightHandle gives it
        def __init__(self) -> None:
            self.refused_early, self.last_refusal = None, None
            self.counts: dict[str, int] = {}
            self.refusals: list[tuple[int, str]] = []

        def new_counts(self) -> dict[str, int]:
            out, self.counts = self.counts, {}
            return out

        def take_refusals(self) -> list[Refusal]:
            out, self.refusals = self.refusals, []
            return out

    logs: list[str] = []
    sup = Supervisor(None, SimpleNamespace(deadline_s=2.0), None, log=logs.append)
    sup.flight = Flight()  # type: ignore[assignment]
    for pid in ("a", "b"):  # two pairs waiting for their Results
        sup.pairs[pid] = PairState(pid, complete_at=time.monotonic())
        sup.order.append(pid)
    why = f"message of {GiB} bytes exceeds the {32 << 20}-byte limit"
    sup._refuse_skipped(Skipping(Result.TYPE, GiB, 0, why, oversize=True))
    assert sup.pairs["a"].done and not sup.pairs["b"].done and sup.counters["refused_messages"] == 1
    sup.flight.counts, sup.flight.refusals = (
        {"reassembly_errors": 1},
        [Refusal(Result.TYPE, why, 0.0)],
    )  # its REJECT, late
    sup._check_refusals()
    assert not sup.pairs["b"].done and sup.counters["refused_messages"] == 1 and sup.counters["errors"] == 1
    sup.flight.counts, sup.flight.refusals = (
        {"reassembly_errors": 1},
        [Refusal(Result.TYPE, why, 0.0)],
    )  # another such record
    sup._check_refusals()
    assert sup.pairs["b"].done and sup.counters["refused_messages"] == 2
    assert sum("Result the HIL server refused" in line for line in logs) == 2


def test_the_arq_names_the_record_it_skips_and_its_owner_can_give_up_the_session():
    """What the HIL server and the ground act on: the skipped record's type and declared size from its header (its
    REJECT would come only after all of it), and a session given up at once, the peer told why."""
    import struct

    from protocol.arq import Arq, ArqConfig, Skipping
    from protocol.framing import data_frame
    from protocol.linesim import SimLine
    from protocol.messages import Result

    line = SimLine(Arq(ArqConfig(), session_id=0xA), Arq(ArqConfig(), session_id=0xB), 92160.0)
    line.run(1.0, stop=lambda s: s.eps[0].established and s.eps[1].established)
    a, b = line.eps
    b.receive(data_frame(0xA, 0xB, 0, struct.pack(">BI", Result.TYPE, GiB) + bytes(100), txid=1), line.now)
    why = f"message of {GiB} bytes exceeds the {32 << 20}-byte limit"
    assert b.skipping == Skipping(Result.TYPE, GiB, 0, why, oversize=True) and b.refusing == why
    assert b.take_refusals() == [] and b.held_bytes()["reassembly"] == 0  # refused only once all of it is in
    b.abandon("held by a record over the size limit", line.now)
    assert not b.established and b.skipping is None
    assert [(e.kind, e.text) for e in b.take_events()][-1] == ("lost", "held by a record over the size limit")
    line.run(line.now + 2, stop=lambda s: any(e.kind == "lost" for e in s.eps[0].take_events()))
    assert a.stats["peer_losses"] == 1  # told by the CLOSE: it gave up on the session
    line.run(line.now + 5, stop=lambda s: s.eps[0].established and s.eps[1].established)
    assert a.established and b.established and b.epoch == 2


def test_an_external_flight_computer_declaring_a_result_over_the_limit_fails_that_pair_and_the_descent_goes_on(
    manifest, hostile, tmp_path
):
    """With no HIL server in between, the ground's own link skipped the record and waited out its 120 s response
    timeout; the stream stayed held, so every later pair timed out too."""
    from protocol.faults import PtyBridge

    with PtyBridge() as bridge:
        board = subprocess.Popen([sys.executable, str(hostile), "--declare", str(GiB), "--port", bridge.paths[0]])
        try:
            code, s = run_cli(manifest, tmp_path, "--flight", "external", "--link", f"serial:{bridge.paths[1]}")
        finally:
            board.terminate()
            board.wait(timeout=10)
    assert code == 1 and s["complete"] is True
    assert outcomes(s) == [("600/300", "result", None), ("300/150", "error", "bad_result"), ("200/100", "result", None)]
    bad = s["records"][1]
    assert bad["elapsed_s"] < PROMPT_S, bad
    assert f"Result was refused from its header: message of {GiB} bytes exceeds the {32 << 20}-byte" in bad["text"]
    assert s["link_errors"] == 0  # the flight computer misbehaved; the link did not fail


def test_a_flight_computer_that_never_answers_ends_the_run_after_the_hello_timeout(manifest, tmp_path, capfd):
    """The ground waited 60 s for a link session, then 900 s for the Hello, silently, and again for every pair.
    (A line says the wait every 2 s here, not every 10 s: a 4 s hello timeout shows one.)"""
    from protocol.faults import PtyBridge

    with PtyBridge() as bridge:  # nobody on the other end
        t0 = time.monotonic()
        link = f"serial:{bridge.paths[1]}"
        code, s = run_cli(manifest, tmp_path, "--flight", "external", "--link", link, "--hello-timeout", "4",
                          "--hello-note", "2")  # fmt: skip
        took = time.monotonic() - t0
    assert code == 1 and s["complete"] is False and s["ground_exit"] == 5
    assert 4 <= took < 60
    why = f"no Hello from the flight computer on serial:{bridge.paths[1]} within 4 s: its link never answered"
    assert s["reason"].startswith(why)
    assert outcomes(s) == [(label, "error", "not_run") for label in PAIRS]  # every pair, none lost
    assert all(r["text"] == f"not run: {s['reason']}" for r in s["records"])
    assert s["results"] == 0 and s["errors"] == 3 and s["link_errors"] == 0
    out, err = capfd.readouterr()
    assert f"waiting for the flight computer's Hello on serial:{bridge.paths[1]} (2 s of 4 s)" in err
    assert f"ground: error: {why}" in err
    assert err.count("ground: error:") == 1 and "ERROR not_run" not in err  # one line, not one per pair
    assert f"INCOMPLETE ({why}" in out


def test_a_flight_computer_whose_link_answers_but_never_says_hello(manifest, hostile, tmp_path):
    from protocol.faults import PtyBridge

    with PtyBridge() as bridge:
        board = subprocess.Popen(
            [sys.executable, str(hostile), "--declare", "0", "--no-hello", "--port", bridge.paths[0]]
        )
        try:
            code, s = run_cli(
                manifest,
                tmp_path,
                "--flight",
                "external",
                "--link",
                f"serial:{bridge.paths[1]}",
                "--hello-timeout",
                "4",
            )
        finally:
            board.terminate()
            board.wait(timeout=10)
    assert code == 1 and s["ground_exit"] == 5 and s["complete"] is False
    assert "within 4 s (its link answers: is its flight software running?)" in s["reason"]
    assert outcomes(s) == [(label, "error", "not_run") for label in PAIRS]


def test_a_zmq_endpoint_nobody_serves_ends_the_run_after_the_hello_timeout(manifest, tmp_path):
    import socket

    with socket.socket() as sock:  # a loopback port nobody listens on
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    link = f"zmq:tcp://127.0.0.1:{port}"
    args = ("--flight", "external", "--link", link, "--insecure", "--hello-timeout", "3")
    code, s = run_cli(manifest, tmp_path, *args)
    assert code == 1 and s["ground_exit"] == 5
    assert s["reason"].startswith(f"no Hello from the flight computer on {link} within 3 s")
    assert outcomes(s) == [(label, "error", "not_run") for label in PAIRS]


@pytest.mark.parametrize("value", ["0", "-1", "nan"])
def test_a_hello_timeout_that_is_no_time_is_refused_up_front(tmp_path, value, capsys):
    argv = ["run", "--flight", "external", "--link", "serial:/dev/null", "--hello-timeout", value]
    assert main([*argv, "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "--hello-timeout must be a number of seconds in (0, 86400]" in err and len(err.strip().splitlines()) == 1


def test_a_serial_device_that_is_not_there_is_refused_before_rendering(tmp_path, capsys):
    out = tmp_path / "o"
    argv = ["run", "--flight", "external", "--link", "serial:/dev/no-such-board@115200", "--out", str(out)]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "no serial device /dev/no-such-board" in err and len(err.strip().splitlines()) == 1
    assert not (out / "pairs").exists()  # nothing rendered for a run that could not start


def test_a_pair_in_flight_when_the_run_is_stopped_is_interrupted_not_not_run(manifest, hostile, tmp_path):
    """A Ctrl-C while a pair's answer was on its way recorded that pair as not_run, which means "the run ended
    before its frames went"; the board had computed it. It is now `interrupted`, with the signal."""
    import json
    import re
    import signal

    out = tmp_path / "run"
    # the second pair's answer trickles (a record of 1 MB, 640 B/s): it is in flight when the signal comes
    cmd = f"{sys.executable} {hostile} --declare {1 << 20} --port {{port}}"
    argv = [sys.executable, "-m", "hil_server.cli", "run", "--manifest", str(manifest), "--deadline", "30"]
    argv += ["--out", str(out), "--budget", "host", "--link", "serial", "--flight-cmd", cmd, "--no-figures"]
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        results = out / "received" / "results.jsonl"
        t0 = time.monotonic()
        while time.monotonic() - t0 < 60 and not (results.is_file() and results.read_text().strip()):
            time.sleep(0.1)
        time.sleep(4.0)  # the second pair's frames go (a loaded host is slow), its answer trickles for ~30 min
        proc.send_signal(signal.SIGINT)
        proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130
    s = json.loads((out / "summary.json").read_text())
    assert outcomes(s) == [
        ("600/300", "result", None),
        ("300/150", "error", "interrupted"),
        ("200/100", "error", "not_run"),
    ]
    # "while" when the interrupt came before both frames were confirmed on the far side (a loaded host)
    assert re.fullmatch(
        r"interrupted by SIGINT (after|while) its frames went; its answer was not awaited", s["records"][1]["text"]
    )
    assert s["not_run"] == 1


@pytest.mark.parametrize("filt", [0, 1, 2])
def test_the_example_flight_program_decodes_every_filter_the_spec_allows(filt):
    """examples/minimal_flight.py's decoder handled filters 0 and 1 only, and read a filter-2 array (which section
    5.2 lets a sender use on any integer array) as if unfiltered (QA of stop 73). Against the reference encoder."""
    import sys
    import zlib

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "examples"))
    import minimal_flight as mf

    from protocol.codec import _array_header, _wire_array, delta_encode

    a = _wire_array((np.arange(48, dtype=np.int16).reshape(6, 8) * 37) % 251 - 100)
    payload = _array_header(a) + bytes((filt,)) + zlib.compress(delta_encode(a, filt).tobytes())
    assert np.array_equal(mf.ext_hook(3, payload), a)
