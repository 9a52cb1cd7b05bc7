"""Console lines that repeat, quieted: the first few of a kind said one by one, then one line per period.

A peer that retries (libzmq redials about ten times a second), a stranger's garbage or a flight side that
floods Errors would otherwise print hundreds of identical lines a second and push everything else off the
screen. Every occurrence is still counted by its caller; only the saying is limited. The ground (its
unattributed Errors), the board (refused messages) and every link (repeating events) share this one rule.
"""

from __future__ import annotations

from collections.abc import Hashable
from dataclasses import dataclass, field


@dataclass
class _Kind:
    seen: int = 0  # every occurrence
    said_at: float = float("-inf")  # when one was last said
    unsaid: int = 0  # since then, not said
    latest: str = ""  # the newest unsaid one's text


@dataclass
class Quieter:
    """Per key: the first ``first`` occurrences are said, then at most one per ``quiet_s`` seconds.

    :meth:`offer` says whether to say an occurrence now, and how many went unsaid before it; :meth:`due` gives
    the keys whose unsaid occurrences have waited ``quiet_s`` for a line of their own (for callers that sum
    them on a timer rather than with the next one said)."""

    first: int = 1
    quiet_s: float = 10.0
    _kinds: dict[Hashable, _Kind] = field(default_factory=dict)

    def offer(self, key: Hashable, now: float, text: str = "") -> tuple[bool, int, float]:
        """An occurrence of ``key`` at ``now``: ``(say it, unsaid before it, seconds since one was last said)``;
        the unsaid count restarts when one is said."""
        k = self._kinds.setdefault(key, _Kind())
        k.seen += 1
        since = now - k.said_at
        if k.seen <= self.first or since >= self.quiet_s:
            unsaid, k.unsaid, k.said_at = k.unsaid, 0, now
            return True, unsaid, since
        k.unsaid += 1
        k.latest = text
        return False, 0, since

    def add_unsaid(self, key: Hashable, n: int, text: str = "") -> None:
        """``n`` occurrences of ``key`` known only by count (their texts were not kept): counted and summed in the
        next line :meth:`due` gives."""
        if n > 0:
            k = self._kinds.setdefault(key, _Kind())
            k.seen += n
            k.unsaid += n
            k.latest = text or k.latest

    def seen(self, key: Hashable) -> int:
        """Occurrences of ``key`` so far, said or not."""
        k = self._kinds.get(key)
        return 0 if k is None else k.seen

    def due(self, now: float) -> list[tuple[Hashable, int, float, str]]:
        """``(key, unsaid, seconds since one was said, the latest unsaid text)`` for each key whose unsaid
        occurrences have waited ``quiet_s``; they count as said now."""
        out = []
        for key, k in self._kinds.items():
            if k.unsaid and now - k.said_at >= self.quiet_s:
                out.append((key, k.unsaid, now - k.said_at, k.latest))
                k.unsaid, k.said_at = 0, now
        return out
