"""Progress for long work: a bar redrawn in place on a terminal, periodic plain lines otherwise.

CI logs and pipes get one complete line every ``LOG_INTERVAL_S`` (and at the end) instead
of a carriage-return bar that a log shows as one run-on line. Dependency-free on purpose:
every package (ground_sim's renderer, studies' campaigns, the HIL run) uses it.
"""

from __future__ import annotations

import math
import sys
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
