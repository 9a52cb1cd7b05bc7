"""Links: delivery guarantees in-process, and two real OS processes over a pty pair and ZeroMQ."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from protocol.codec import encode_message
from protocol.faults import CorruptingChannel, PtyBridge, open_pty_pair
from protocol.framing import frame_payload
from protocol.links import LinkClosed, SerialLink, StreamLink, ZmqLink
from protocol.messages import Frame, Heartbeat, Hello, Result, Telemetry

PEER = Path(__file__).with_name("protocol_peer.py")
ROOT = Path(__file__).resolve().parents[1]


def frame(i: int, side: int = 512) -> Frame:
    img = np.random.default_rng(i).integers(0, 256, (side, side), dtype=np.uint8)
    return Frame(
        seq=i,
        capture_time_s=0.5 * i,
        position_m=(0.0, 0.0, 1000.0 - 20 * i),
        R_world_to_cam=np.eye(3),
        altimeter_m=1000.0 - 20 * i,
        image=img,
    )


def test_socketpair_delivers_in_order_and_acks():
    a, b = socket.socketpair()
    with StreamLink(a, name="A") as A, StreamLink(b, name="B") as B:
        for i in range(5):
            A.send(frame(i, 64))
        A.send(Heartbeat(time_s=1.0))
        assert A.flush(5.0)
        got = [B.recv(2.0) for _ in range(6)]
        assert [m.seq for m in got[:5]] == list(range(5)) and isinstance(got[5], Heartbeat)
        assert all(np.array_equal(m.image, frame(i, 64).image) for i, m in enumerate(got[:5]))
        assert B.recv(0.05) is None
        s = A.stats
        assert s["delivered"] == 5 and s["acks_received"] == 5 and A.failures() == []


def test_unanswered_frame_fails_with_reason_never_silently():
    a, b = socket.socketpair()  # nobody reads b
    with StreamLink(a, ack_timeout=0.05, max_attempts=3, name="A") as A:
        seq = A.send(frame(1, 8))
        assert A.flush(3.0)
        [f] = A.failures()
        assert f.seq == seq and f.message_type == "Frame" and "no ack after 3 attempts" in f.reason
        assert A.outcome(seq).startswith("failed") and A.stats["retransmits"] == 2
    b.close()


def test_retransmitted_duplicates_are_dropped():
    a, b = socket.socketpair()
    with StreamLink(b, name="B") as B:
        wire = frame_payload(Heartbeat.TYPE, 9, encode_message(Heartbeat(time_s=2.0, counter=1)), 1)
        a.sendall(wire + wire + wire)  # same link seq three times, ack requested
        assert B.recv(2.0) == Heartbeat(time_s=2.0, counter=1)
        assert B.recv(0.2) is None
        assert B.stats["duplicates_dropped"] == 2 and B.stats["acks_sent"] == 3
    a.close()


def test_peer_rejection_becomes_failure_with_reason():
    a, b = socket.socketpair()
    with StreamLink(a, name="A"):
        raw = frame_payload(Frame.TYPE, 1, b"\x92\x03\x80", 1)  # valid CRC, Frame body missing fields
        b.sendall(raw)
        deadline = time.monotonic() + 2
        data = b""
        while time.monotonic() < deadline and b"\x7e" not in data[1:]:
            b.settimeout(0.2)
            try:
                data += b.recv(4096)
            except TimeoutError:
                pass
    from protocol.framing import StreamDecoder

    [nack] = StreamDecoder().feed(data)
    assert nack.seq == 1 and "missing field" in nack.reason
    b.close()


def test_baud_pacing_costs_real_line_time():
    a, b = socket.socketpair()
    with StreamLink(a, baud=9600, acks=False) as A, StreamLink(b) as B:
        t0 = time.monotonic()
        A.send(frame(0, 30))  # ~960 bytes -> >= 1.0 s at 9600 baud 8N1
        assert B.recv(5.0) is not None
        elapsed = time.monotonic() - t0
        line_time = A.stats["bytes_sent"] * 10 / 9600
        assert elapsed >= 0.95 * line_time and A.stats["busy_s"] >= 0.95 * line_time


def test_send_on_closed_link_is_a_clear_error():
    a, b = socket.socketpair()
    A = StreamLink(a)
    A.close()
    with pytest.raises(LinkClosed):
        A.send(Heartbeat(time_s=0.0))
    b.close()


def test_serial_link_over_one_pty_pair_with_master_as_stream():
    master, slave_path = open_pty_pair()
    with StreamLink(master, name="ground") as G, SerialLink(slave_path, name="flight") as F:
        G.send(frame(3, 128))
        got = F.recv(5.0)
        assert got.seq == 3 and np.array_equal(got.image, frame(3, 128).image)
        F.send(Heartbeat(time_s=4.0, counter=2))
        assert G.recv(5.0) == Heartbeat(time_s=4.0, counter=2)
        assert G.flush(2.0) and G.stats["delivered"] == 1


def test_serial_link_bad_port_is_input_error():
    from protocol.errors import InputError

    with pytest.raises(InputError, match="cannot open serial port"):
        SerialLink("/dev/definitely-not-a-port")


def _descent(link, n: int = 20) -> tuple[list[Result], Telemetry]:
    hello = link.recv(60.0)  # the peer may start slowly on a loaded machine
    assert isinstance(hello, Hello) and hello.role == "flight"
    for i in range(n):
        link.send(frame(i))
    link.send(Heartbeat(time_s=0.0, counter=0xFFFF))
    results, telem = [], None
    deadline = time.monotonic() + 120
    while telem is None and time.monotonic() < deadline:
        m = link.recv(1.0)
        if isinstance(m, Result):
            results.append(m)
        elif isinstance(m, Telemetry):
            telem = m
    return results, telem


def _spawn(*args: str) -> subprocess.Popen:
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    return subprocess.Popen([sys.executable, str(PEER), *args], env=env, cwd=ROOT)


def _check_descent(results: list[Result], telem: Telemetry | None, n: int = 20) -> None:
    assert telem is not None
    assert [r.frame_seqs[1] for r in results] == list(range(n))  # exactly once, in order
    for r in results:  # content made it through: the peer reports each image's mean
        assert r.hazard_grid[0, 0] == pytest.approx(frame(r.frame_seqs[1]).image.mean(), abs=1e-3)
        assert r.hazard_image.shape == (512, 512)


@pytest.mark.slow
def test_two_processes_over_corrupting_pty_bridge():
    down = CorruptingChannel(seed=11, drop=4e-7, flip=4e-7, dup=4e-7)  # ~1/3 of 256 KiB frames hit
    up = CorruptingChannel(seed=12, drop=2e-7, flip=2e-7, dup=2e-7)
    with PtyBridge(down, up) as bridge:
        peer = _spawn("serial", bridge.paths[1])
        try:
            with SerialLink(
                bridge.paths[0],
                ack_timeout=0.3,
                max_attempts=20,
                name="ground",
                reliable_types={Frame.TYPE, Heartbeat.TYPE},
            ) as G:
                results, telem = _descent(G)
                assert G.flush(30.0)
                failures = G.failures()
                stats = G.stats
        finally:
            assert peer.wait(60) == 0
    hit = down.stats["dropped"] + down.stats["flipped"] + down.stats["duplicated"]
    assert hit > 0, "the channel must actually corrupt something"
    if failures:  # allowed only as explicit, reasoned failures - and then the frame is missing
        pytest.fail(f"unexpected delivery failures at these rates: {failures}")
    _check_descent(results, telem)
    assert stats["retransmits"] >= 1 and telem.link["crc_errors"] + telem.link["malformed"] >= 1
    assert stats["delivered"] == 21  # 20 frames + the 'done' heartbeat (made reliable on this link)


@pytest.mark.slow
def test_two_processes_over_zeromq_tcp():
    with ZmqLink("tcp://127.0.0.1:*", bind=True, name="ground") as G:
        peer = _spawn("zmq", G.endpoint)
        try:
            results, telem = _descent(G)
        finally:
            assert peer.wait(60) == 0
        assert G.failures() == [], G.failures()
    _check_descent(results, telem)
    assert telem.link["frames_received"] == 21 and telem.link["decode_errors"] == 0
