"""Stops of this whole process (SIGSTOP, a paused VM, a starved host), told apart from a loop's own busy time.

A watchdog that reads a peer's silence from the wall clock blames the peer for the time its own process was not
scheduled: an 8 s SIGSTOP of the HIL server killed a healthy flight process as hung. Measuring the gap between
two turns of the watchdog's own loop also counts the loop's work (a flight restart, encoding a 1024² Result:
0.4 s), and called that a stop. :class:`StallClock` ticks on a thread of its own every ``tick_s``: every thread
of a process stops together, so a tick that came ``threshold_s`` late is a stop of the process, and a loop busy
in Python bytecode elsewhere is not one (the ticker needs the GIL only for a moment; Python hands it over every
5 ms). A C call that holds the GIL for over ``threshold_s`` (a huge ``json.dumps``) is still taken for a stop.

The HIL server's watchdogs and the ground's latency notes read it. The links' loops measure their own turns
with the same threshold (:mod:`protocol.links`): the ZeroMQ I/O loop does nothing but poll, and the byte-stream
reader only reads and decodes what came, so a turn over a second late is a stop there too (stop 83).
"""

from __future__ import annotations

import threading
import time

OWN_STALL_S = 1.0  # a 50 ms tick this much late: the process was stopped (a loaded host delays a tick by ms)
TICK_S = 0.05


def forgiven_hearing(last_heard: float, forgave_at: float | None, gap: float) -> float | None:
    """When the peer was last heard, moved past a stop of this process of ``gap`` s; None when a stop since that
    hearing was forgiven already (``forgave_at``, what an earlier forgiveness left ``last_heard`` at).

    A stop is forgiven once between two hearings of the peer: what a live peer sent is read within a turn after
    the stop, so a second stop with nothing heard in between counts against it. Forgiven every time, a loop
    starved for over a second again and again would never time out a dead peer. Both links use this rule
    (:mod:`protocol.links`, :meth:`protocol.arq.Arq.forgive`); the caller sets both clocks to the value returned.
    """
    if forgave_at is not None and last_heard == forgave_at:
        return None
    return last_heard + gap


class StallClock:
    """Sums the stops of this process that a ticker thread sees; :meth:`take` hands over what it saw since the
    last call. A context manager; the thread is a daemon and ends with :meth:`close`."""

    def __init__(self, threshold_s: float = OWN_STALL_S, tick_s: float = TICK_S) -> None:
        if not (0 < tick_s < threshold_s):
            raise ValueError(f"need 0 < tick_s < threshold_s, got {tick_s!r}, {threshold_s!r}")
        self.threshold_s, self.tick_s = float(threshold_s), float(tick_s)
        self._lock = threading.Lock()
        self._last = time.monotonic()  # the last look at the clock, the ticker's or take()'s
        self._pending = 0.0
        self.total_s = 0.0  # every stop seen, taken or not
        self._closed = threading.Event()
        self._thread = threading.Thread(target=self._tick, name="stall-clock", daemon=True)
        self._thread.start()

    def _look(self, now: float) -> None:
        """Caller holds the lock: a stop since the last look (the ticker's or :meth:`take`'s) is counted, once."""
        late = now - self._last - self.tick_s
        if late > self.threshold_s:
            self._pending += late
            self.total_s += late
        self._last = now

    def _tick(self) -> None:
        while not self._closed.wait(self.tick_s):
            with self._lock:
                self._look(time.monotonic())

    def take(self) -> float:
        """Seconds this process was stopped since the last call (0.0: none beyond ``threshold_s``). A stop the
        ticker has not ticked after yet is counted here: after SIGCONT the caller's loop may run first (a watchdog
        then judged a healthy flight process silent in 3 of 6 stops)."""
        with self._lock:
            self._look(time.monotonic())
            gap, self._pending = self._pending, 0.0
        return gap

    def close(self) -> None:
        self._closed.set()
        self._thread.join(timeout=1.0)

    def __enter__(self) -> StallClock:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
