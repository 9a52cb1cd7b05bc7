"""A child's output pipe read to its end and passed on line by line, each destination with its own byte cap.

The run keeps the ground simulator's lines in ``ground.log`` and shows them as they come; the emulated
processor passes a flight program's lines to the supervisor's log and keeps their tail for its exit report.
Both must read the pipe to its end whatever a destination does (a child whose pipe fills blocks on its next
line), hold no more than one bounded line in memory (a program that prints without a newline would otherwise
grow one line without end), and say what they did not pass on rather than lose it silently.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import IO

MAX_LINE_BYTES = 64 << 10  # a longer line is passed on in pieces of this size


@dataclass
class Sink:
    """Where lines go: ``write`` (an ``OSError`` or ``ValueError`` from it ends this sink, not the others) up to
    ``cap`` bytes (None: no cap); past the cap a line is counted and ``over(bytes not passed on)`` is written
    once the pipe ends."""

    write: Callable[[bytes], object]
    cap: int | None = None
    over: Callable[[int], bytes] | None = None
    flush: Callable[[], object] | None = None
    passed: int = 0
    dropped: int = 0
    dead: bool = field(default=False, repr=False)

    def take(self, line: bytes) -> None:
        if self.dead:
            return
        if self.cap is not None and (self.dropped or self.passed + len(line) > self.cap):
            self.dropped += len(line)  # past the cap: whole lines only, then nothing more
            return
        self.passed += len(line)
        self._call(self.write, line)

    def end(self) -> None:
        if self.dropped and self.over is not None and not self.dead:
            self._call(self.write, self.over(self.dropped))

    def _call(self, fn: Callable[[bytes], object], data: bytes) -> None:
        try:
            fn(data)
            if self.flush is not None:
                self.flush()
        except (OSError, ValueError):  # a full disk, a closed terminal: the other sinks still get it
            self.dead = True


def pump(stream: IO[bytes], sinks: list[Sink], on_line: Callable[[bytes], object] | None = None) -> None:
    """Read ``stream`` to its end, handing each line (at most :data:`MAX_LINE_BYTES`) to every sink and to
    ``on_line``; then each sink's closing note, and the stream is closed."""
    try:
        for line in iter(lambda: stream.readline(MAX_LINE_BYTES), b""):
            if on_line is not None:
                on_line(line)
            for s in sinks:
                s.take(line)
    except (OSError, ValueError):  # the pipe itself failed: what came is passed on
        pass
    finally:
        for s in sinks:
            s.end()
        try:
            stream.close()
        except OSError:
            pass
