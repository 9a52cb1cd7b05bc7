"""protocol.stall: a stop of the whole process is told from a loop's own busy time."""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from types import SimpleNamespace

import pytest

from protocol.stall import StallClock

CHILD = """
import sys, time
from protocol.stall import StallClock
with StallClock() as clock:
    print("ready", flush=True)
    sys.stdin.readline()          # the parent stops us meanwhile, then says go
    first = clock.take()          # at once: the ticker need not have ticked since the stop
    time.sleep(0.2)
    print(f"{first:.3f} {clock.take():.3f}", flush=True)
"""


def test_a_stop_of_the_whole_process_is_measured_once():
    p = subprocess.Popen([sys.executable, "-c", CHILD], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert p.stdout.readline().strip() == "ready"
        p.send_signal(signal.SIGSTOP)
        time.sleep(2.0)
        p.send_signal(signal.SIGCONT)
        p.stdin.write("go\n")
        p.stdin.flush()
        first, second = (float(x) for x in p.stdout.readline().split())
    finally:
        p.kill()
        p.wait()
    assert 1.5 < first < 4.0 and second == 0.0  # the stop, minus a tick; taken once


def test_a_stop_the_ticker_has_not_ticked_after_is_taken_by_the_caller(monkeypatch):
    """After SIGCONT the caller's loop may run before the ticker thread: a take() then read 0 and the watchdog judged a
    healthy flight process silent (3 of 6 stops in a copy of the HIL server's loop)."""
    from protocol import stall

    clock = StallClock()
    clock.close()  # no ticker: only take() looks
    now = [time.monotonic() + 5.0]  # 5 s since the last look: a stop
    monkeypatch.setattr(stall.time, "monotonic", lambda: now[0])
    assert clock.take() == pytest.approx(5.0 - clock.tick_s, abs=0.2) and clock.take() == 0.0  # counted once
    now[0] += 0.5
    assert clock.take() == 0.0  # a busy half second is no stop


def test_a_busy_or_blocked_loop_is_not_a_stop():
    """A watchdog loop that restarts a flight process or encodes a large Result (0.4 s) was said to be "not
    scheduled" when the gap between its own turns was taken for a stop; the ticker thread keeps ticking."""
    with StallClock() as clock:
        t0 = time.monotonic()
        n = 0
        while time.monotonic() - t0 < 1.6:  # pure Python: the GIL is handed over every 5 ms
            n += 1
        time.sleep(1.2)  # blocked
        assert clock.take() == 0.0 and clock.total_s == 0.0
    with pytest.raises(ValueError):
        StallClock(threshold_s=0.01, tick_s=0.05)


def test_the_hil_server_forgives_its_flight_one_stop_between_two_hearings():
    """Forgiven every time, a server starved for over a second again and again would never find a hung flight
    process: as the ZeroMQ link does, a second stop with nothing heard from the flight in between counts."""
    from hil_server.supervisor import Supervisor

    pair = SimpleNamespace(done=False, complete_at=1.0, stopped_s=0.0)
    said: list[str] = []
    sup = SimpleNamespace(
        pairs={"p": pair},
        flight_reader=SimpleNamespace(last_message=100.0),
        _forgave_at=None,
        log=said.append,
        stopped_s=0.0,
    )
    Supervisor._forgive_own_stop(sup, 3.0)
    assert pair.stopped_s == 3.0 and sup.flight_reader.last_message == 103.0 and "not blamed" in said[-1]
    Supervisor._forgive_own_stop(sup, 2.0)  # nothing heard since: its silence counts
    assert pair.stopped_s == 3.0 and sup.flight_reader.last_message == 103.0 and "judged by its silence" in said[-1]
    sup.flight_reader.last_message = 110.0  # it spoke
    Supervisor._forgive_own_stop(sup, 2.0)
    assert pair.stopped_s == 5.0 and sup.flight_reader.last_message == 112.0
    # every stop counts in the server's own total, which the run's summary says (QA of stop 72)
    from hil_server.run import server_stop_note

    assert sup.stopped_s == 7.0
    note = server_stop_note({"supervisor_counters": {"server_stopped_s": sup.stopped_s}})
    assert note.startswith("the HIL server itself was not scheduled for 7.0 s in all")
    assert server_stop_note({"supervisor_counters": {"server_stopped_s": 0.2}}) == "" and server_stop_note({}) == ""
