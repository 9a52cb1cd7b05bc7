"""The one rule for console lines that repeat (protocol.quiet): the first few said, then one per quiet time."""

from __future__ import annotations

from protocol.quiet import Quieter


def test_the_first_are_said_then_one_per_quiet_time_with_the_count_unsaid_before_it():
    q = Quieter(first=2, quiet_s=10.0)
    said = [q.offer("k", t)[:2] for t in (0.0, 1.0, 2.0, 3.0, 4.0)]
    assert said == [(True, 0), (True, 0), (False, 0), (False, 0), (False, 0)]
    assert q.offer("k", 11.0) == (True, 3, 10.0)  # 10 s after the last said: said, with the 3 unsaid before it
    assert q.offer("k", 12.0)[0] is False and q.seen("k") == 7


def test_keys_are_quieted_apart_and_a_due_sum_is_given_once():
    q = Quieter(first=1, quiet_s=5.0)
    assert q.offer("a", 0.0)[0] and q.offer("b", 0.5)[0]  # another key's first is news, whatever came before
    q.offer("a", 1.0, "the latest a")
    q.offer("a", 2.0, "the newest a")
    assert q.due(4.9) == []  # not yet
    assert q.due(5.0) == [("a", 2, 5.0, "the newest a")]
    assert q.due(20.0) == []  # summed once; nothing unsaid since
    assert q.offer("a", 21.0) == (True, 0, 16.0)
