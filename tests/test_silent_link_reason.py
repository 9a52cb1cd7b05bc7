"""The ground's one line when no flight computer ever says Hello tells a silent port from a port full of bytes that
are not this protocol (another device, or the right one at another baud: both read as line noise)."""

from __future__ import annotations

import os
import random
import time
import tty

from ground_sim.stream import _silent_link_reason
from protocol.links import SerialLink


def test_a_port_full_of_foreign_bytes_is_told_from_a_silent_one():
    master, slave = os.openpty()
    tty.setraw(slave)
    tty.setraw(master)
    try:
        with SerialLink(os.ttyname(slave), baud=None, name="ground") as link:
            where = f"serial:{os.ttyname(slave)}"
            time.sleep(0.3)  # the link says its own Hello: nobody answers
            assert "its link never answered (is it powered, on this port, at this baud?)" in _silent_link_reason(
                link, where
            )
            rng = random.Random(7)  # a stranger on the port: a GPS, a console, a board at another baud
            for _ in range(40):
                os.write(master, bytes(rng.randrange(256) for _ in range(256)))
                time.sleep(0.005)
            deadline = time.monotonic() + 5
            while link.stats.get("bytes_received", 0) < 40 * 256 and time.monotonic() < deadline:
                time.sleep(0.05)
            why = _silent_link_reason(link, where)
            assert f"its line carried {40 * 256} bytes but not one valid frame of this protocol" in why, why
            assert why.endswith("another device on this port, or another baud?")
    finally:
        os.close(master)
        os.close(slave)


def test_frames_without_a_session_and_zmq_wording():
    class Fake:
        def __init__(self, stats: dict) -> None:
            self.stats = stats

    why = _silent_link_reason(Fake({"bytes_received": 900, "frames_received": 12}), "serial:/dev/ttyUSB0")
    assert why.startswith("its line carried 12 frames (900 bytes) but never a link session")
    why = _silent_link_reason(Fake({"bytes_received": 0}), "zmq:tcp://10.0.0.2:5555")
    assert why.startswith("its link never answered (is it powered, serving this endpoint, with these keys, and not")


def test_a_line_that_echoes_is_named_and_no_session_is_made_with_ourselves():
    """serial:loop:// (a loopback plug) gave the ground a session with itself: it took its own Hello, and each pair
    waited out a full answer timeout (a 1-pair run took 77 s). Now nothing is established and the reason says so."""
    with SerialLink("loop://", baud=None, name="ground") as link:
        deadline = time.monotonic() + 5
        while link.stats.get("echoed_frames", 0) < 2 and time.monotonic() < deadline:
            time.sleep(0.05)
        assert not link.wait_established(0.5)
        why = _silent_link_reason(link, "serial:loop://")
    assert why.startswith("the line returns this side's own frames (a loopback plug, serial:loop://"), why
    assert any(e.kind == "echo" for e in link.events())
