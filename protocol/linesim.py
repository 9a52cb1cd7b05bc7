"""A simulated full-duplex serial line between two :class:`protocol.arq.Arq` endpoints, on a virtual clock.

Each direction carries ``rate`` bytes per second (8N1: baud / 10); a frame is
on the line for ``len / rate`` seconds and arrives whole at the far end after
``latency`` more, passed through an optional
:class:`protocol.faults.CorruptingChannel`. Endpoints are polled every
``poll_s``. Deterministic for given inputs and channel seeds, and fast: an
event loop, not real time. Used by the tests and the benchmark to check the
ARQ (throughput against line rate, loss recovery, timeouts) without threads.
"""

from __future__ import annotations

import heapq
from collections.abc import Callable

from protocol.arq import Arq, ArqConfig
from protocol.codec import encode_message
from protocol.faults import CorruptingChannel
from protocol.messages import Error


class SimLine:
    """Two endpoints, two directions; :meth:`run` advances virtual time."""

    def __init__(
        self,
        a: Arq,
        b: Arq,
        rate: float,
        *,
        channels: tuple[CorruptingChannel | None, CorruptingChannel | None] = (None, None),
        latency: float = 0.0,
        poll_s: float = 0.01,
    ) -> None:
        self.eps = (a, b)
        self.rate = float(rate)
        self.channels = channels
        self.latency = latency
        self.poll_s = poll_s
        self.now = 0.0
        self._writing: list[tuple[float, bytes, int | None] | None] = [None, None]
        self._arrivals: list[tuple[float, int, int, bytes]] = []
        self._n = 0
        self._next_poll = 0.0
        self.stopped = [False, False]  # a stopped endpoint neither reads nor writes (a stalled peer)
        self.received: list[list] = [[], []]  # Received items per endpoint

    def run(self, until: float, stop: Callable[[SimLine], bool] | None = None) -> float:
        """Advance to ``until`` (virtual seconds) or until ``stop(self)``; returns the time reached."""
        while self.now < until:
            if stop is not None and stop(self):
                break
            self._step()
            t_next = self._next_poll
            for w in self._writing:
                if w is not None:
                    t_next = min(t_next, w[0])
            if self._arrivals:
                t_next = min(t_next, self._arrivals[0][0])
            self.now = max(self.now, min(t_next, until))
        return self.now

    def _step(self) -> None:
        now = self.now
        while self._arrivals and self._arrivals[0][0] <= now:
            _, _, dst, data = heapq.heappop(self._arrivals)
            if not self.stopped[dst]:
                self.eps[dst].receive(data, now)
        for i, ep in enumerate(self.eps):
            w = self._writing[i]
            if w is not None and w[0] <= now:
                self._writing[i] = None
                _, frame, token = w
                ep.written(token, len(frame), now, started=now - len(frame) / self.rate)
                ch = self.channels[i]
                data = ch.apply(frame) if ch is not None else frame
                if data:
                    self._n += 1
                    heapq.heappush(self._arrivals, (now + self.latency, self._n, 1 - i, data))
        if now >= self._next_poll:
            for i, ep in enumerate(self.eps):
                if not self.stopped[i]:
                    ep.poll(now)
            self._next_poll = now + self.poll_s
        for i, ep in enumerate(self.eps):
            self.received[i] += ep.take_received()
            if self._writing[i] is None and not self.stopped[i]:
                nxt = ep.next_frame(now)
                if nxt is not None:
                    frame, token = nxt
                    self._writing[i] = (now + len(frame) / self.rate, frame, token)


def paused_receiver(rate: float, n: int, latency: float = 0.1) -> tuple[Arq, Arq, SimLine]:
    """a and b on a :class:`SimLine` at ``rate`` bytes/s with ``latency``, established; b's application then takes
    nothing (window 0, docs/protocol.md section 3.2) and a submits ``n`` Error messages of 0.9 kB whose texts start
    with their index (``000000``, ``000001``, ...), and the line runs until a has been told window 0 and at least
    5 s have gone. The retransmission floor is three 1 kB frames' line time, as the tests use."""
    cfg = ArqConfig(rto_min=3 * 1024 / rate + 0.02)
    a, b = Arq(cfg, session_id=0xA, now=0.0), Arq(cfg, session_id=0xB, now=0.0)
    line = SimLine(a, b, rate, latency=latency)
    line.run(5.0, stop=lambda s: a.established and b.established)
    t0 = line.now
    b.set_rx_full(True, t0)
    for i in range(n):
        a.submit(Error.TYPE, encode_message(Error(code="m", text=f"{i:06d}" + "x" * 900)), "Error", t0)
    line.run(t0 + 60.0, stop=lambda s: a.peer_full and line.now > t0 + 5)
    return a, b, line
