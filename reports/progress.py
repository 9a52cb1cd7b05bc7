"""Progress for long work: a bar redrawn in place on a terminal, periodic plain lines otherwise.

CI logs and pipes get one complete line every ``LOG_INTERVAL_S`` (and at the end) instead
of a carriage-return bar that a log shows as one run-on line. Dependency-free on purpose:
every package (ground_sim's renderer, studies' campaigns, the HIL run) uses it.
"""

from __future__ import annotations

import math
import sys
import threading
import time
from typing import TextIO

TTY_INTERVAL_S = 0.2
LOG_INTERVAL_S = 5.0


class Progress:
    """A text progress bar on stderr: ``update()`` per finished item; ``label`` names the latest one."""

    def __init__(
        self,
        total: int,
        done: int = 0,
        desc: str = "",
        *,
        enabled: bool = True,
        stream: TextIO | None = None,
        width: int = 28,
    ):
        self.total, self.done, self.desc, self.width = total, done, desc, width
        self.stream = stream if stream is not None else sys.stderr
        self.enabled = enabled and total > 0
        self._t0 = time.monotonic()
        self._start_done = done
        self._last = 0.0
        self._tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.label = ""
        self._draw(force=True)

    def update(self, n: int = 1, label: str = "") -> None:
        self.done += n
        self.label = label
        self._draw(force=self.done >= self.total)

    def _draw(self, force: bool = False) -> None:
        if not self.enabled:
            return
        now = time.monotonic()
        if not force and now - self._last < (TTY_INTERVAL_S if self._tty else LOG_INTERVAL_S):
            return
        self._last = now
        frac = self.done / self.total
        fill = int(round(frac * self.width))
        elapsed = now - self._t0
        ran = self.done - self._start_done
        eta = elapsed / ran * (self.total - self.done) if ran else math.nan
        eta_s = "?" if math.isnan(eta) else f"{eta:5.0f}s"
        line = (
            f"{self.desc} [{'#' * fill}{'.' * (self.width - fill)}] {self.done}/{self.total} "
            f"{100 * frac:3.0f}% {elapsed:5.0f}s elapsed, eta {eta_s}"
        ) + (f"  {self.label}" if self.label else "")
        self.stream.write(("\r" + line) if self._tty else (line + "\n"))
        if self._tty and self.done >= self.total:
            self.stream.write("\n")
        self.stream.flush()


TICK_FIRST_S = 15.0
TICK_EVERY_S = 15.0


class Ticker:
    """A line on stderr now and then while one long call runs that has no steps to count: `process` on a large
    pair went without a word (12-19 s at 2048 px on a loaded 2-core host, and 4x the pixels at 4096). A context
    manager: the first line after ``first_s``, then one every ``every_s``, from a daemon thread; nothing for work
    shorter than ``first_s``, and nothing drawn in place, so a log reads as a terminal does."""

    def __init__(
        self,
        desc: str,
        *,
        enabled: bool = True,
        stream: TextIO | None = None,
        first_s: float = TICK_FIRST_S,
        every_s: float = TICK_EVERY_S,
        since: float | None = None,
    ):
        self.desc, self.enabled, self.first_s, self.every_s = desc, enabled, first_s, every_s
        self.stream = stream if stream is not None else sys.stderr
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        # when the work began (time.monotonic()): a second phase's ticker counts from the first's start, so two
        # phases of 10 s each are not 20 s without a word
        self.since = since
        self._t0 = time.monotonic()
        self.lines = 0

    def __enter__(self) -> Ticker:
        self._t0 = time.monotonic() if self.since is None else self.since
        self._stop = threading.Event()
        if self.enabled:
            self._thread = threading.Thread(target=self._run, args=(self._stop,), name="ticker", daemon=True)
            self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        if self._thread is not None:
            # a line half written to a blocked stderr must not hold up the exit (or a Ctrl-C): it is a daemon
            self._thread.join(timeout=1.0)
            self._thread = None

    def _run(self, stop: threading.Event) -> None:
        wait = max(0.0, self._t0 + self.first_s - time.monotonic())
        while not stop.wait(wait):
            self.stream.write(f"{self.desc}: {time.monotonic() - self._t0:.0f} s so far\n")
            self.stream.flush()
            self.lines += 1
            wait = self.every_s
