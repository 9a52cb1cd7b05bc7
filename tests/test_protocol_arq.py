"""The ARQ engine on a simulated serial line (virtual clock): throughput, loss recovery, sessions, timeouts.

Deterministic: the line is :class:`protocol.linesim.SimLine` with seeded
:class:`protocol.faults.CorruptingChannel` faults, so these tests measure the
protocol, not the machine. The same properties over real ptys and processes are
in tests/test_protocol_links.py and tests/test_protocol_hil.py.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from protocol.arq import Arq, ArqConfig, unwrap
from protocol.codec import encode_message
from protocol.faults import CorruptingChannel
from protocol.framing import data_frame, hello_frame
from protocol.fuzz import same_message
from protocol.linesim import SimLine
from protocol.messages import Frame, Heartbeat

RATE = 921600 / 10  # bytes per second on the line (8N1)
CFG = ArqConfig(rto_min=3 * 1024 / RATE + 0.02)


def frame(i: int, side: int = 128) -> Frame:
    img = np.random.default_rng(i).integers(0, 256, (side, side), dtype=np.uint8)
    return Frame(
        seq=i, capture_time_s=0.0, position_m=(0.0, 0.0, 100.0), R_world_to_cam=np.eye(3), altimeter_m=1.0, image=img
    )


def pair(rate: float = RATE, corrupt: float = 0.0, seed: int = 0, cfg: ArqConfig = CFG) -> SimLine:
    channels = (None, None)
    if corrupt:
        channels = tuple(CorruptingChannel(seed * 2 + k, corrupt, corrupt, corrupt) for k in range(2))  # type: ignore[assignment]
    line = SimLine(Arq(cfg, session_id=0xA), Arq(cfg, session_id=0xB), rate, channels=channels)
    line.run(1.0, stop=lambda s: s.eps[0].established and s.eps[1].established)
    assert line.eps[0].established and line.eps[1].established
    return line


def send(line: SimLine, msgs, side: int = 0) -> list[int]:
    ep = line.eps[side]
    return [ep.submit(m.TYPE, encode_message(m), type(m).__name__, line.now) for m in msgs]


def test_clean_line_runs_at_over_90_percent_of_line_rate():
    line = pair()
    msgs = [frame(i, 256) for i in range(4)]
    ids = send(line, msgs)
    t0 = line.now
    line.run(t0 + 60, stop=lambda s: all(s.eps[0].outcome(i) == "delivered" for i in ids))
    payload = sum(len(encode_message(m)) for m in msgs)
    assert payload / (line.now - t0) >= 0.9 * RATE
    assert [r.message.seq for r in line.received[1]] == [0, 1, 2, 3]
    assert line.eps[0].stats["retransmits"] == 0
    t = line.eps[0].times(ids[0])
    assert t is not None and t.line_s == pytest.approx(len(encode_message(msgs[0])) / RATE, rel=0.1)
    # the last waited in the send queue while the three before it went out (a Result behind an earlier Result)
    ahead = sum(len(encode_message(m)) for m in msgs[:3]) / RATE
    queued = [line.eps[0].times(i).queue_s for i in ids]  # type: ignore[union-attr]
    assert queued[0] == pytest.approx(0.0, abs=0.01) and queued[3] == pytest.approx(ahead, rel=0.1), queued


def test_line_time_ends_at_the_last_byte_written_not_at_its_late_acknowledgement():
    # A Result's "line s" read first byte -> acknowledged, and the ACK can wait behind the far end's own data (a
    # ground streaming the next pair): the HIL showed a Result's line time above its whole end-to-end latency.
    # Here the ACK's delay is the line's latency, 0.5 s each way, which is no part of the message's line time.
    rate, latency = 57600 / 10, 0.5
    cfg = ArqConfig(rto_min=1.5, rto_initial=2.0)
    line = SimLine(Arq(cfg, session_id=0xA), Arq(cfg, session_id=0xB), rate, latency=latency)
    line.run(10.0, stop=lambda s: s.eps[0].established and s.eps[1].established)
    msg = Heartbeat(time_s=1.0, counter=7)
    (i,) = send(line, [msg])
    line.run(line.now + 10, stop=lambda s: s.eps[0].outcome(i) == "delivered")
    t = line.eps[0].times(i)
    assert t is not None and t.delivered is not None and t.first_tx is not None and t.line_s is not None
    assert t.delivered - t.first_tx > 2 * latency  # acknowledged a round trip later ...
    assert t.line_s == pytest.approx(len(encode_message(msg)) / rate, rel=0.25, abs=0.02)  # ... on the line for this


def test_line_time_ends_at_the_write_even_when_its_ack_came_first():
    """Under load the reader thread took the peer's ACK before the writer recorded its write's end: the message was
    delivered (and left the queue the line times were looked up in), and its "line s" ended at the moment the last
    segment was handed to the writer, before that segment's own line time (0.54 s read for 0.83 s; a CI run failed
    on it). The write's end now reaches the message's times whatever came first."""
    line = pair()
    a, b = line.eps
    msg = Heartbeat(time_s=1.0, counter=3)
    (i,) = send(line, [msg])
    t0 = line.now
    out = a.next_frame(t0)
    assert out is not None
    data, token = out
    b.receive(data, t0 + 0.5)  # the bytes arrived; the peer acknowledges at once
    ack = b.next_frame(t0 + 0.5)
    assert ack is not None
    a.receive(ack[0], t0 + 0.6)
    assert a.outcome(i) == "delivered"
    a.written(token, len(data), t0 + 0.55, started=t0 + 0.05)  # the writer's record comes last
    t = a.times(i)
    assert t is not None and t.first_tx == pytest.approx(t0 + 0.05) and t.written == pytest.approx(t0 + 0.55)
    assert t.line_s == pytest.approx(0.5)


def test_line_time_read_before_the_writer_records_its_last_write_is_bounded_by_the_ack():
    """Read in that window (a ground reading its Result's times as soon as it is delivered), a two-frame message's
    line time ended when its last frame was handed to the writer, before that frame's own line time: 0.54 s for
    0.83 s under CPU load. Until the writer's record comes, the acknowledgement bounds it; then the write's end."""
    line = pair()
    a, b = line.eps
    (i,) = send(line, [frame(1, 40)])  # 1.8 kB: two DATA frames
    t0 = line.now
    first = a.next_frame(t0)
    assert first is not None
    a.written(first[1], len(first[0]), t0 + 0.4, started=t0)
    second = a.next_frame(t0 + 0.4)
    assert second is not None
    for data in (first[0], second[0]):
        b.receive(data, t0 + 0.8)
    ack = b.next_frame(t0 + 0.8)
    assert ack is not None
    a.receive(ack[0], t0 + 0.9)
    assert a.outcome(i) == "delivered"
    t = a.times(i)
    assert t is not None and t.line_s == pytest.approx(0.9)  # not 0.4: the last frame's 0.4 s are in it
    a.written(second[1], len(second[0]), t0 + 0.8, started=t0 + 0.4)
    assert t.line_s == pytest.approx(0.8)


@pytest.mark.parametrize("corrupt", [1e-4, 1e-3])
def test_noisy_line_loses_nothing(corrupt):
    """drop, flip and duplicate each at ``corrupt`` per byte, both directions: all delivered, once, in order."""
    line = pair(corrupt=corrupt, seed=3)
    msgs = [frame(i) for i in range(6)] + [Heartbeat(time_s=1.0, counter=i) for i in range(3)]
    ids = send(line, msgs[:6])
    line.run(line.now + 120, stop=lambda s: all(s.eps[0].outcome(i) != "pending" for i in ids))
    a = line.eps[0]
    assert [a.outcome(i) for i in ids] == ["delivered"] * 6, a.failures()
    got = [r.message for r in line.received[1]]
    assert len(got) == 6 and all(same_message(g, m) for g, m in zip(got, msgs))
    hit = sum(ch.stats["flipped"] + ch.stats["dropped"] + ch.stats["duplicated"] for ch in line.channels if ch)
    assert hit > 20 and a.stats["retransmits"] > 0
    # what was resent, in bytes: each retransmission is one DATA frame's payload, at most a whole frame
    assert 0 < a.stats["retransmit_bytes"] <= a.stats["retransmits"] * a.cfg.max_frame
    if corrupt >= 1e-3:  # the frame size adapted to the line, and so did what each retransmission resends
        assert a.snapshot()["frame_bytes"] < 400
        assert a.stats["retransmit_bytes"] / a.stats["retransmits"] < 0.5 * a.cfg.max_frame


@given(st.integers(0, 2**40), st.integers(-(2**31) + 1, 2**31 - 1))
def test_a_wire_position_reads_as_the_whole_position_within_2_GiB_of_the_one_expected(near, offset):
    true = max(0, near + offset)
    assert unwrap(true % 2**32, near) == true


def test_a_session_streams_on_across_the_4_GiB_stream_position_wrap():
    """Stream positions go on the wire as u32. A session used to end 64 MiB short of 4 GiB, failing what was in flight
    (a message the peer held unacknowledged too). Here both directions start 20 kB short of 2**32 on a noisy line: what
    each side sends crosses the wrap with losses, retransmissions and SACK ranges on both sides of it, and everything
    arrives once, in order, in the one session."""
    line = pair(corrupt=1e-3, seed=7)
    a, b = line.eps
    start = 2**32 - 20_000
    for x, y in ((a, b), (b, a)):  # white box: 4 GiB of traffic in no time
        assert x._nxt == x._una == y._cum == 0 and not x._sbuf
        x._una = x._nxt = start
        y._cum = start
    there = [frame(i) for i in range(4)]  # 4 x 16 kB: past the wrap by 45 kB
    back = [frame(10 + i) for i in range(3)]
    ids_a, ids_b = send(line, there), send(line, back, side=1)
    line.run(
        line.now + 120,
        stop=lambda s: all(a.outcome(i) != "pending" for i in ids_a) and all(b.outcome(i) != "pending" for i in ids_b),
    )
    assert [a.outcome(i) for i in ids_a] == ["delivered"] * 4, a.failures()
    assert [b.outcome(i) for i in ids_b] == ["delivered"] * 3, b.failures()
    for got, sent in ((line.received[1], there), (line.received[0], back)):
        assert len(got) == len(sent) and all(same_message(g.message, m) for g, m in zip(got, sent))
    assert a._una > 2**32 + 40_000 and b._cum == a._una and b._una > 2**32 + 20_000
    assert a.stats["retransmits"] > 0 and b.stats["retransmits"] > 0  # the noise was mended across the wrap
    for ep in (a, b):
        assert ep.stats["peer_losses"] == 0 and ep.stats["sessions"] == 1 and ep._bad_acks == 0


def test_a_session_whose_transmission_numbers_run_out_ends_with_the_reason_and_a_new_one_carries_on():
    """``txid`` is a u32 that does not wrap (4 TiB of 1 kB frames): the session ends with the reason, as any loss."""
    line = pair()
    a, b = line.eps
    a._txid = 2**32 - 1  # white box
    (i,) = send(line, [Heartbeat(time_s=1.0, counter=1)])
    line.run(line.now + 10, stop=lambda s: a.outcome(i) != "pending")
    assert a.outcome(i) == "failed: session lost: transmission numbers exhausted (2**32 DATA frames in one session)"
    (j,) = send(line, [Heartbeat(time_s=2.0, counter=2)])
    line.run(line.now + 10, stop=lambda s: a.outcome(j) != "pending")
    assert a.outcome(j) == "delivered" and a.stats["sessions"] == 2 and a._txid < 10


def test_very_noisy_line_ends_every_message_delivered_or_failed_with_a_reason():
    line = pair(corrupt=1e-2, seed=5)
    ids = send(line, [frame(i, 64) for i in range(3)])
    line.run(line.now + 60, stop=lambda s: all(s.eps[0].outcome(i) != "pending" for i in ids))
    a = line.eps[0]
    outcomes = [a.outcome(i) for i in ids]
    assert all(o == "delivered" or o.startswith("failed: ") for o in outcomes), outcomes
    for f in a.failures():
        assert f.reason  # explicit


def test_stalled_peer_is_an_explicit_error_within_the_timeout():
    line = pair()
    ids = send(line, [frame(0, 256)])
    line.run(line.now + 0.2)
    line.stopped[1] = True  # the far end stops reading (and writing)
    t_stop = line.now
    line.run(line.now + 30, stop=lambda s: s.eps[0].outcome(ids[0]) != "pending")
    a = line.eps[0]
    assert a.outcome(ids[0]).startswith("failed: session lost")
    assert line.now - t_stop <= CFG.peer_timeout + 0.1  # 4 s default: explicit within <= 5 s
    [ev] = [e for e in a.take_events() if e.kind == "lost"]
    assert "peer" in ev.text and not a.established


def test_idle_link_notices_a_silent_peer_through_keepalives():
    line = pair()
    line.stopped[1] = True
    t0 = line.now
    line.run(line.now + 30, stop=lambda s: not s.eps[0].established)
    assert line.now - t0 <= CFG.peer_timeout + 0.1
    assert any(e.kind == "lost" and "no frame from the peer" in e.text for e in line.eps[0].take_events())


def test_peer_close_is_immediate_and_explicit():
    line = pair()
    ids = send(line, [frame(0, 256)])
    line.run(line.now + 0.1)
    line.eps[1].close("shutting down")
    t0 = line.now
    line.run(line.now + 5, stop=lambda s: s.eps[0].outcome(ids[0]) != "pending")
    assert line.now - t0 < 0.1
    assert "peer closed the link (shutting down)" in line.eps[0].outcome(ids[0])


def test_restarted_receiver_resynchronises_and_old_session_frames_are_dropped():
    line = pair()
    a = line.eps[0]
    ids = send(line, [frame(0, 256)])
    line.run(line.now + 0.2)
    line.stopped[1] = True  # the old receiver dies mid-message; a restarted one takes its place at once
    b2 = Arq(CFG, session_id=0xC)
    line.eps = (a, b2)
    line.stopped[1] = False
    line.run(line.now + 2, stop=lambda s: s.eps[0].outcome(ids[0]) != "pending" and s.eps[0].established)
    assert "peer started a new session" in a.outcome(ids[0])
    assert a.peer_session == 0xC and a.epoch == 2
    assert b2.stats["old_session_frames"] > 0  # a's frames for the dead session, dropped and counted
    ids2 = send(line, [frame(1), frame(2)])
    line.run(line.now + 10, stop=lambda s: all(a.outcome(i) == "delivered" for i in ids2))
    assert [r.message.seq for r in line.received[1] if r.epoch == 1] == [1, 2]
    # a frame of the dead session arriving late is dropped and counted, not delivered
    before = a.stats["old_session_frames"]
    a.receive(data_frame(0xB, 0xA, 0, b"\x03\x00\x00\x00\x05stale"), line.now)
    assert a.stats["old_session_frames"] == before + 1


def test_restarted_sender_resynchronises():
    line = pair()
    b = line.eps[1]
    send(line, [frame(0, 256)])
    line.run(line.now + 0.2)
    a2 = Arq(CFG, session_id=0xD)  # the sending side restarts mid-message
    line.eps = (a2, b)
    line.run(line.now + 2, stop=lambda s: s.eps[1].peer_session == 0xD and s.eps[0].established)
    assert b.stats["peer_restarts"] == 1
    ids = send(line, [frame(5)])
    line.run(line.now + 10, stop=lambda s: a2.outcome(ids[0]) == "delivered")
    assert [r.message.seq for r in line.received[1]] == [5]  # the half-sent message of the old session is gone


def test_a_peer_that_never_completed_its_handshake_is_replaced_without_a_restart_event():
    # a board opening a line that still held a dead ground's HELLOs said "the peer restarted" before serving anything
    b = Arq(CFG, session_id=0xB)
    b.receive(hello_frame(0x51, 0, 1024, 1 << 20), 0.0)  # the dead ground's, never answered
    b.receive(hello_frame(0x52, 0, 1024, 1 << 20), 0.1)  # the live ground's
    b.receive(hello_frame(0x52, 0xB, 1024, 1 << 20), 0.2)  # ... which completes the handshake
    assert b.established and b.peer_session == 0x52
    assert b.stats["peer_restarts"] == 0 and not [e for e in b.take_events() if e.kind == "restarted"]
    # a new session's HELLO while this peer still talks is a stranger's (stop 60's QA: one such frame took the
    # session over); once the old session has fallen silent, a peer that starts afresh did restart
    b.receive(hello_frame(0x53, 0, 1024, 1 << 20), 0.3)
    assert b.peer_session == 0x52 and b.stats["foreign_hellos"] == 1 and b.stats["peer_restarts"] == 0
    assert [e.kind for e in b.take_events()] == ["foreign"]
    b.receive(hello_frame(0x53, 0, 1024, 1 << 20), 0.2 + 1.6 * CFG.keepalive)
    assert b.peer_session == 0x53 and b.stats["peer_restarts"] == 1
    restarted = [e for e in b.take_events() if e.kind == "restarted"]
    assert len(restarted) == 1
    # the HELLO held back was the restarted peer's own: not "another device on the line?" (QA 64a, M2)
    assert b.stats["foreign_hellos"] == 0 and "the 1 HELLO(s) held back" in restarted[0].text


def test_a_strangers_hello_on_a_live_line_changes_nothing():
    """One valid HELLO of another session, written onto a line whose two ends talk: the session stays, and the
    traffic goes on (it had taken the session over, lost the pair in flight and stalled the real peer for 8 s)."""
    line = pair()
    a, b = line.eps
    before = (a.peer_session, b.peer_session, a.epoch, b.epoch)
    b.receive(hello_frame(0x99, 0, 1024, 1 << 20), line.now)
    ids = send(line, [frame(4)])
    line.run(line.now + 5, stop=lambda s: s.eps[0].outcome(ids[0]) == "delivered")
    assert a.outcome(ids[0]) == "delivered" and line.received[1][-1].message.seq == 4
    assert (a.peer_session, b.peer_session, a.epoch, b.epoch) == before and b.stats["foreign_hellos"] == 1


def test_a_strangers_hello_while_the_peer_writes_one_long_frame_changes_nothing():
    """At 2400 baud a 1 kB frame is on the line 3.5 s, longer than the 1.5 keepalives after which a silent peer is
    taken for restarted: a stranger's HELLO in that time took the session over. The frame's bytes arriving count."""
    b = Arq(CFG, session_id=0xB)
    b.receive(hello_frame(0x52, 0xB, 1024, 1 << 20), 0.0)
    assert b.established and b.peer_session == 0x52
    long = data_frame(0x52, 0xB, 0, bytes(900))
    t = 0.0
    for k in range(0, len(long) - 50, 50):  # 50 bytes every 0.2 s: 250 B/s
        t += 0.2
        b.receive(long[k : k + 50], t)
    assert t > 1.5 * CFG.keepalive
    b.receive(hello_frame(0x99, 0, 1024, 1 << 20), t)  # its flag ends the long frame: garbled, and still the peer's
    assert b.peer_session == 0x52 and b.stats["foreign_hellos"] == 1 and b.stats["peer_restarts"] == 0
    # a peer that has really gone quiet is still replaced
    b.receive(hello_frame(0x99, 0, 1024, 1 << 20), t + 1.6 * CFG.keepalive)
    assert b.peer_session == 0x99 and b.stats["peer_restarts"] == 1 and b.stats["foreign_hellos"] == 0
    # a peer that dies part-way through a frame and restarts: its first HELLO closes the dead frame, which is not
    # taken for the old session talking, so it is taken 1.5 keepalives after the dead frame's last bytes
    b.receive(hello_frame(0x99, 0xB, 1024, 1 << 20), t + 2.0)
    assert b.established
    b.receive(data_frame(0x99, 0xB, 0, bytes(900))[:300], t + 3.0)  # ... and dies here
    b.receive(hello_frame(0x77, 0, 1024, 1 << 20), t + 3.5)  # too soon: it may be a stranger's
    assert b.peer_session == 0x99 and b.stats["foreign_hellos"] == 1
    b.receive(hello_frame(0x77, 0, 1024, 1 << 20), t + 3.0 + 1.6 * CFG.keepalive)
    assert b.peer_session == 0x77 and b.stats["peer_restarts"] == 2 and b.stats["foreign_hellos"] == 0


def test_both_sides_recover_after_a_long_stall():
    """A frozen peer that wakes up after both sides gave up: a new session, new ids, and traffic flows."""
    line = pair()
    line.stopped[1] = True
    line.run(line.now + 6)
    assert not line.eps[0].established
    line.stopped[1] = False
    line.run(line.now + 10, stop=lambda s: s.eps[0].established and s.eps[1].established)
    assert line.eps[0].established and line.eps[1].established and line.eps[0].epoch == 2
    ids = send(line, [frame(9)])
    line.run(line.now + 5, stop=lambda s: s.eps[0].outcome(ids[0]) == "delivered")
    assert line.received[1][-1].message.seq == 9


def test_oversize_record_is_rejected_before_it_is_buffered():
    small = ArqConfig(**{**CFG.__dict__, "limits": type(CFG.limits)(max_message_bytes=10_000)})
    line = SimLine(Arq(CFG, session_id=1), Arq(small, session_id=2), RATE)
    line.run(1.0)
    ids = send(line, [frame(0, 128)])  # ~16 kB > the receiver's 10 kB limit
    line.run(line.now + 10, stop=lambda s: str(s.eps[0].outcome(ids[0])).startswith("failed"))
    assert "peer rejected: message of" in line.eps[0].outcome(ids[0])
    assert line.eps[1].held_bytes()["reassembly"] == 0 and line.received[1] == []
    # the receiver's owner learns the same reason, once, with the refused record's type (a Frame)
    (refused,) = line.eps[1].take_refusals()
    assert refused[0] == Frame.TYPE and refused[1].startswith("message of") and "10000-byte limit" in refused[1]
    assert line.eps[1].take_refusals() == [] and line.eps[1].refusing is None
    ids = send(line, [frame(1, 32)])  # the stream goes on after the refused record
    line.run(line.now + 5, stop=lambda s: s.eps[0].outcome(ids[0]) == "delivered")
    assert [r.message.seq for r in line.received[1]] == [1]


def test_messages_wait_for_a_session_at_most_connect_timeout():
    a = Arq(ArqConfig(connect_timeout=2.0), session_id=1)
    mid = a.submit(6, encode_message(Heartbeat(time_s=0.0)), "Heartbeat", 0.0)
    a.poll(1.0)
    assert a.outcome(mid) == "pending"
    a.poll(2.5)
    assert a.outcome(mid) == "failed: no session with the peer within 2 s"


def test_a_message_bound_to_a_session_never_reaches_the_next_one():
    line = pair()
    a = line.eps[0]
    epoch = a.epoch
    line.eps[1].close()
    line.run(line.now + 0.1)
    mid = a.submit(6, encode_message(Heartbeat(time_s=0.0)), "Heartbeat", line.now, epoch=epoch)
    assert a.outcome(mid).startswith("failed") and a.idle


def test_duplicated_frames_on_the_line_give_each_message_once():
    line = pair()
    dup = CorruptingChannel(1, dup=0.0)
    orig = dup.apply
    dup.apply = lambda data: orig(data) * 2  # type: ignore[method-assign]  # every frame arrives twice
    line.channels = (dup, None)
    ids = send(line, [frame(i) for i in range(3)])
    line.run(line.now + 10, stop=lambda s: all(s.eps[0].outcome(i) == "delivered" for i in ids))
    assert [r.message.seq for r in line.received[1]] == [0, 1, 2]
    assert line.eps[1].stats["duplicates_dropped"] > 0


def test_partly_overlapping_segments_give_each_stream_byte_once():
    """A segment held out of order that the in-order one then partly covers gives only its new bytes: DATA
    [10, n) then [0, 15) is the stream [0, n) once, and its two messages once each. A receiver that handed on the
    whole held segment (bytes 10-14 twice) passed every test (mutation audit of stop 75)."""
    from protocol.arq import RECORD
    from protocol.messages import Error

    a, b = Arq(ArqConfig(), now=0.0), Arq(ArqConfig(), now=0.0)
    line = SimLine(a, b, rate=1e5)
    line.run(1.0)
    assert a.established and b.established
    msgs = [Error(code="x", text="first"), Error(code="y", text="second")]
    records = [RECORD.pack(Error.TYPE, len(body)) + body for body in map(encode_message, msgs)]
    stream = b"".join(records)
    n = len(stream)
    assert n > 20
    got: list[bytes] = []
    consume = b._consume
    b._consume = lambda data, now: (got.append(bytes(data)), consume(data, now))[1]  # type: ignore[method-assign]
    b.receive(data_frame(a.session_id, b.session_id, 10, stream[10:], txid=1), 1.1)
    assert got == [] and b.take_received() == []  # held: bytes 0-9 are missing
    b.receive(data_frame(a.session_id, b.session_id, 0, stream[:15], txid=2), 1.2)
    assert b"".join(got) == stream  # bytes 0..n-1, each once
    assert [(r.message, r.seq) for r in b.take_received()] == [(msgs[0], 0), (msgs[1], len(records[0]))]
    assert b.stats["decode_errors"] == 0 and b.take_refusals() == []


def test_a_gap_after_a_long_idle_is_not_a_stall():
    """Regression: the reassembly clock starts when data is first held, not at the last message
    (the first frame of a Result lost after 10 s of silence ended the session at once)."""
    line = pair()
    line.run(line.now + 10)  # idle, keepalives only
    drop_first = CorruptingChannel(1)
    dropped = []

    def apply(data: bytes) -> bytes:
        if data[2] == 1 and not dropped:  # the first DATA frame (kind byte after the flag and version)
            dropped.append(data)
            return b""
        return data

    drop_first.apply = apply  # type: ignore[method-assign]
    line.channels = (drop_first, None)
    ids = send(line, [frame(0, 64)])
    line.run(line.now + 10, stop=lambda s: s.eps[0].outcome(ids[0]) != "pending")
    assert dropped and line.eps[0].outcome(ids[0]) == "delivered" and line.eps[1].stats["peer_losses"] == 0


def test_heartbeats_on_a_slow_line_do_not_starve_a_message():
    """At 2400 baud a heartbeat every 0.25 s fills 80 % of the line. The heartbeats queued while one DATA frame was
    on the line (4 s) used to go first, each in turn, and the next DATA frame waited until the peer gave the session
    up (a board at 2400 baud with a 20 s link timeout lost every Result). A newer heartbeat now replaces a queued
    one, and heartbeats take turns with DATA."""
    rate = 2400 / 10
    cfg = ArqConfig(rto_min=3 * 1024 / rate + 0.02, peer_timeout=20.0)
    line = pair(rate=rate, cfg=cfg)
    a = line.eps[0]
    body = encode_message(frame(0, 48))  # about 2.4 kB: three DATA frames
    (mid,) = send(line, [frame(0, 48)])
    beats = 0
    t0 = line.now
    while a.outcome(mid) == "pending" and line.now - t0 < 60:
        beats += 1
        a.submit(
            Heartbeat.TYPE, encode_message(Heartbeat(time_s=line.now, counter=beats)), "Heartbeat", line.now, False
        )
        line.run(line.now + 0.25)
    assert a.outcome(mid) == "delivered" and a.established, a.take_events()
    # the message's own line time plus one heartbeat per DATA frame, not a minute of heartbeats
    assert line.now - t0 <= 1.3 * len(body) / rate + 2.0, line.now - t0
    assert a.stats["dgrams_superseded"] > 0
    got = [r.message for r in line.received[1]]
    assert any(isinstance(m, Heartbeat) for m in got)  # the peer still hears them: liveness is kept


def test_keepalives_do_not_starve_a_message_on_a_very_slow_line():
    """At 300 baud a 1 kB DATA frame is on the line for 34 s; a keepalive HELLO was queued every second meanwhile,
    each 0.8 s on the line and ahead of DATA, and the stream stopped: "peer stopped acknowledging: no progress for
    100 s (0 bytes unacknowledged, 2018 in the stream)" (stop 60's QA). A keepalive goes only on an idle line."""
    rate = 300 / 10
    cfg = ArqConfig(rto_min=3 * 1024 / rate + 0.02, rto_initial=3 * 1024 / rate + 0.02, peer_timeout=100.0)
    line = SimLine(Arq(cfg, session_id=0xA), Arq(cfg, session_id=0xB), rate)
    line.run(10.0, stop=lambda s: s.eps[0].established and s.eps[1].established)  # the handshake alone: 4 s
    a = line.eps[0]
    body = encode_message(frame(0, 40))  # about 1.9 kB: two DATA frames, 62 s on the line
    (mid,) = send(line, [frame(0, 40)])
    t0, others = line.now, a.stats["frames_sent"] - a.stats["data_frames_sent"]
    line.run(t0 + 300, stop=lambda s: s.eps[0].outcome(mid) != "pending")
    assert a.outcome(mid) == "delivered" and a.established, a.take_events()
    assert line.now - t0 <= 1.3 * len(body) / rate + 5.0, line.now - t0
    # besides its DATA frames, keepalives while it waits for an ACK (the old code: 102 in 100 s, and no DATA)
    assert a.stats["frames_sent"] - a.stats["data_frames_sent"] - others <= 20, a.stats


def test_hellos_do_not_pile_up_while_a_side_waits_on_a_very_slow_line():
    """Below ~1040 baud a HELLO takes longer than the 0.25 s between them while a side waits for its peer: a board
    that waited 30 s at 300 baud held 83, which once the session was up went ahead of ACKs and DATA and lost it
    (stop 60's review). At most one waits."""
    rate = 300 / 10
    cfg = ArqConfig(rto_min=3 * 1024 / rate + 0.02, rto_initial=3 * 1024 / rate + 0.02, peer_timeout=60.0)
    ground, board = Arq(cfg, session_id=0xA), Arq(cfg, session_id=0xB)
    line = SimLine(ground, board, rate)
    line.stopped[0] = True  # the ground is not running yet
    line.run(30.0)
    assert len(board._control) <= 1
    line.stopped[0] = False
    line.run(90.0, stop=lambda s: ground.established and board.established)
    (mid,) = send(line, [frame(0, 16)])  # one DATA frame
    t0 = line.now
    line.run(t0 + 120, stop=lambda s: ground.outcome(mid) != "pending")
    assert ground.outcome(mid) == "delivered" and line.now - t0 < 40, (ground.outcome(mid), line.now - t0)
    assert [e.kind for e in ground.take_events()] == ["established"]


def test_a_line_that_echoes_our_own_frames_is_no_session():
    """On a loopback plug (serial:loop://) a ground took its own HELLO for a peer's, "established" a session with
    itself and waited out a deadline per pair on its own frames. An echoed frame is counted and said instead."""
    a = Arq(CFG, session_id=0x1234)
    t = 0.0
    for _ in range(20):  # whatever it sends comes straight back
        t += 0.1
        a.poll(t)
        while (out := a.next_frame(t)) is not None:
            a.written(out[1], len(out[0]), t)
            a.receive(out[0], t)
    assert not a.established and a.stats["echoed_frames"] > 0 and a.sess.peer == 0
    kinds = {e.kind for e in a.take_events()}
    assert kinds == {"echo"}


def test_acks_closes_and_rejects_fit_a_small_frame_peers_announced_size():
    """Section 1: a side never sends a frame longer than the peer announced (64 bytes allowed). Only DATA and DGRAM
    kept to it: ACKs with 3+ SACK ranges, CLOSE and REJECT with their reasons were longer, and a 64-byte peer
    dropped them as oversize; on a lossy line its messages then failed with the session (review of stop 66)."""
    from protocol.framing import StreamDecoder, close_frame, reject_frame
    from protocol.messages import Error

    # fixed session ids: random ones put the seeded drops on other bytes each run, and 3 % of runs lost the session
    # on this 1.5 % line's backed-off timer (a fresh clone's CI of stop 69; 4 of 150 runs before that stop too)
    big = Arq(ArqConfig(peer_timeout=4.0), session_id=0xB, now=0.0)
    small = Arq(ArqConfig(max_frame=64, min_frame=64, window=4096, peer_timeout=4.0), session_id=0xA, now=0.0)
    line = SimLine(small, big, rate=9600, channels=(CorruptingChannel(1, drop=1.5e-2), None))
    line.run(1.0)
    assert big.peer_max_frame == 64
    body = encode_message(Error(code="x", text="y" * 3000))
    ids = [small.submit(Error.TYPE, body, "Error", 1.0) for _ in range(5)]
    line.run(200.0, stop=lambda L: small.idle)
    assert small.decoder.stats["oversize"] == 0 and big.stats["acks_sent"] > 0
    assert [small.outcome(i) for i in ids] == ["delivered"] * 5
    long = "session lost: " + "é" * 300
    for f in (close_frame(1, 2, 0, long, max_frame=64), reject_frame(1, 2, 0, long, 64)):
        assert len(f) <= 64 + 2 + 2 * 64  # the stuffed frame of at most 64 unstuffed bytes
        (got,) = StreamDecoder(64).feed(f)
        assert got.reason.startswith("session lost: ")


def test_a_rejected_message_is_a_failure_not_also_delivered_and_a_bad_ack_is_counted():
    """A message the peer REJECTed was counted delivered as well as failed; an ACK of what was never sent was
    counted malformed, then the count was overwritten by the decoder's in the same call (review of stop 66)."""
    from protocol.framing import ack_frame

    a, b = Arq(ArqConfig(), now=0.0), Arq(ArqConfig(), now=0.0)
    line = SimLine(a, b, rate=1e5)
    line.run(1.0)
    mid = a.submit(99, b"\x00" * 10, "Bogus", 1.0)  # an unknown type: b skips it and REJECTs it
    line.run(3.0)
    assert a.outcome(mid).startswith("failed: peer rejected")
    assert (a.stats["delivered"], a.stats["failures"]) == (0, 1)
    a.receive(ack_frame(b.session_id, a.session_id, cum=10**6, window=32768, sacks=[], echo=0), 3.5)
    assert a.stats["malformed"] == 1


def test_a_heartbeat_with_no_session_to_hear_it_is_dropped_not_a_delivery_failure():
    """Section 4: a heartbeat with no session is dropped. Bound to an ended session (a board between grounds), each
    was a delivery failure: 4 a second, pushing real failures out of failures() (review of stop 66)."""
    a, b = Arq(ArqConfig(), now=0.0), Arq(ArqConfig(), now=0.0)
    line = SimLine(a, b, rate=1e5)
    line.run(1.0)
    epoch = a.epoch
    a.abandon("the ground went", 1.5)
    for i in range(40):
        a.submit(Heartbeat.TYPE, encode_message(Heartbeat(time_s=float(i), counter=i)), "Heartbeat", 2.0, False, epoch)
    assert a.stats["failures"] == 0 and a.stats["dgrams_dropped"] == 40 and a.failures() == []


def test_only_heartbeats_are_taken_as_datagrams_and_a_reject_names_a_record_of_its_own_session():
    """Section 4: only a Heartbeat travels as a DGRAM; a Result sent so reached the application out of order with the
    stream. And a REJECT whose position named a record of an earlier session failed a message delivered then (review
    of stop 66)."""
    from protocol.framing import dgram_frame, reject_frame
    from protocol.messages import Error

    a, b = Arq(ArqConfig(), now=0.0), Arq(ArqConfig(), now=0.0)
    line = SimLine(a, b, rate=1e5)
    line.run(1.0)
    body = encode_message(Error(code="x", text="as a datagram"))
    b.receive(dgram_frame(a.session_id, b.session_id, Error.TYPE, body), 1.5)
    assert b.take_received() == [] and b.stats["decode_errors"] == 1
    assert "only Heartbeats" in b.take_refusals()[0].reason
    hb = encode_message(Heartbeat(time_s=1.0, counter=1))
    b.receive(dgram_frame(a.session_id, b.session_id, Heartbeat.TYPE, hb), 1.6)
    assert [type(r.message).__name__ for r in b.take_received()] == ["Heartbeat"]
    mid = a.submit(Error.TYPE, body, "Error", 2.0)
    line.run(3.0)
    assert a.outcome(mid) == "delivered"
    a.abandon("a new session", 3.0)
    line.run(5.0)
    assert a.established
    a.receive(reject_frame(b.session_id, a.session_id, 0, "late"), 5.1)  # position 0: the old session's record
    assert a.outcome(mid) == "delivered" and a.stats["failures"] == 0


def _paused_receiver_run(noise: float, seed: int, n: int = 600, latency: float = 0.0) -> dict:
    """``n`` messages a -> b over a SimLine (``noise`` per byte for drop, flip and duplicate, both ways) while b's
    application alternates 3 s of reading nothing with 0.5 s of reading, its queue holding 256 (as the links do:
    set_rx_full while any message waits beyond it). Returns what b's application read, in order, and the counters."""
    from collections import deque

    from protocol.messages import Error

    a, b = Arq(CFG, session_id=0xA, now=0.0), Arq(CFG, session_id=0xB, now=0.0)
    chans = (CorruptingChannel(2 * seed, noise, noise, noise), CorruptingChannel(2 * seed + 1, noise, noise, noise))
    line = SimLine(a, b, RATE, channels=chans if noise else (None, None), latency=latency)
    line.run(1.0, stop=lambda s: a.established and b.established)
    held: deque = deque()
    queue: deque = deque()
    got: list[str] = []
    sent, t, resume_at, read_until = 0, line.now, line.now + 3.0, None
    while t < 300:
        while sent < n and a.can_accept(300):
            a.submit(Error.TYPE, encode_message(Error(code="m", text=f"{sent:06d}" + "x" * 200)), "Error", t)
            sent += 1
        t = line.run(t + 0.005)
        held.extend(line.received[1])
        line.received[1].clear()
        while held and len(queue) < 256:
            queue.append(held.popleft())
        if bool(held) != b.rx_full:
            b.set_rx_full(bool(held), t)
        if resume_at is not None and t >= resume_at:
            resume_at, read_until = None, t + 0.5
        if resume_at is None:
            got.extend(r.message.text[:6] for r in queue)
            queue.clear()
            if t >= read_until:
                resume_at = t + 3.0
        if sent >= n and a.idle and not held and not queue:
            break
    return {"got": got, "a": a, "b": b, "t": t}


@pytest.mark.parametrize(("noise", "seed"), [(0.0, 0), (1e-3, 1), (3e-3, 2)])
def test_a_receiver_that_pauses_again_and_again_loses_nothing_and_keeps_its_session(noise, seed):
    """Flow control (section 3.2, window 0): on a clean or noisy line every message arrives once, in order, and
    neither side loses the session though b's application reads nothing for 3 s at a time (peer timeout 4 s)."""
    r = _paused_receiver_run(noise, seed)
    assert r["got"] == [f"{i:06d}" for i in range(600)]
    a, b = r["a"], r["b"]
    assert a.stats["peer_losses"] == 0 and b.stats["peer_losses"] == 0 and a.stats["failures"] == 0
    assert a.stats["peer_full"] >= 1 and b.stats["rx_full_drops"] > 0  # the pause was met by window 0


def test_a_zero_window_is_probed_sparingly_and_its_reopening_is_no_line_loss():
    """Told window 0 with 19 frames in flight (0.1 s of line latency), the sender resent every one of them on every
    ACK: 851 frames in 10 s, 95 % of the line; reopening then took the refused frames for line loss and shrank the
    frame size 1024 -> 229 B (review of stop 66). Now one probe goes on its timer, and the frame size stays."""
    from protocol.messages import Error

    a, b = Arq(CFG, session_id=0xA, now=0.0), Arq(CFG, session_id=0xB, now=0.0)
    line = SimLine(a, b, RATE, latency=0.1)
    line.run(1.0, stop=lambda s: a.established and b.established)
    t = line.now
    b.set_rx_full(True, t)
    for i in range(200):
        a.submit(Error.TYPE, encode_message(Error(code="m", text=f"{i:06d}" + "x" * 900)), "Error", t)
    t = line.run(t + 0.5)
    assert a.peer_full and a._nxt - a._una > 5 * 1024  # several frames in flight when the window shut
    frames0 = a.stats["frames_sent"]
    t = line.run(t + 10.0)
    assert a.stats["frames_sent"] - frames0 <= 30 and a.stats["peer_losses"] == 0  # probes and keepalives only
    b.set_rx_full(False, t)
    t = line.run(t + 0.5)
    assert not a.peer_full and a.snapshot()["frame_bytes"] == 1024 and a.snapshot()["loss_rate"] == 0.0
    line.run(t + 10.0, stop=lambda s: a.idle)
    assert [r.message.text[:6] for r in line.received[1]] == [f"{i:06d}" for i in range(200)]


def test_a_zero_window_on_a_slow_line_is_probed_with_one_byte_and_everything_goes_after():
    """The probe was a whole segment: through a pause a 960 byte/s line's sender direction was 35 % busy with
    probes (stop 66's known limit). A probe is now one byte of the stream; what was in flight goes on reopening."""
    from protocol.linesim import paused_receiver

    rate = 9600 / 10
    a, b, line = paused_receiver(rate, 40)
    assert a.peer_full and a._nxt > a._una  # data in flight when the window shut
    t, before = line.now, dict(a.stats)
    t = line.run(t + 20.0)
    probes = a.stats["probes"] - before["probes"]
    assert probes >= 3 and a.stats["data_frames_sent"] - before["data_frames_sent"] == probes  # probing, nothing else
    assert a.stats["retransmits"] == before["retransmits"]  # a probe is no line loss (the HIL reports retransmits)
    assert a.stats["bytes_sent"] - before["bytes_sent"] < 0.1 * 20 * rate  # 35 % of it with whole-segment probes
    assert a.stats["peer_losses"] == 0 and b.stats["peer_losses"] == 0
    b.set_rx_full(False, t)
    line.run(t + 200.0, stop=lambda s: a.idle)
    assert [r.message.text[:6] for r in line.received[1]] == [f"{i:06d}" for i in range(40)]
    assert a.stats["failures"] == 0
    # what the paused peer dropped unread went again, counted apart: the line lost nothing
    assert a.stats["refused_resends"] > 0 and a.stats["retransmits"] == before["retransmits"]


def test_a_window_that_shuts_again_as_it_reopens_gets_one_probe_at_a_time_and_no_fragments():
    """A slow consumer reopens the window for 20 ms, then shuts it for 2 s, over and over, with 27 kB in flight at
    0.3 s latency. The first one-byte probe split each range still queued for resending into a byte and a rest, and
    sent every byte back to back: 505 DATA frames a cycle and 528 segments after 20 cycles, over max_segments after
    90 (review of stop 69). The queued ranges are now held as sent while the window is 0."""
    from protocol.linesim import paused_receiver

    a, b, line = paused_receiver(92160.0, 100, latency=0.3)
    t, segments = line.now, len(a._segs)
    assert a.peer_full and segments >= 20
    for _ in range(20):
        frames0 = a.stats["data_frames_sent"]
        b.set_rx_full(False, t)
        t = line.run(t + 0.02)
        b.set_rx_full(True, t)
        t = line.run(t + 2.0)
        assert a.stats["data_frames_sent"] - frames0 <= 8  # probes, not a burst
        assert len(a._segs) <= segments and all(s.end - s.start > 1 for s in a._segs.values())
    b.set_rx_full(False, t)
    line.run(t + 60.0, stop=lambda s: a.idle)
    assert [r.message.text[:6] for r in line.received[1]] == [f"{i:06d}" for i in range(100)]
    assert a.stats["peer_losses"] == 0 and a.stats["failures"] == 0 and a.snapshot()["loss_rate"] < 0.01
