"""Stream framing: byte stuffing, CRC, resynchronisation, and a bounded fuzz run.

The full >= 100 000-input fuzz run is ``bench/bench_protocol.py --fuzz``; this
file runs the same generator (``protocol.fuzz``) on a bounded number of inputs.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from protocol.framing import FLAG_ACK_REQ, StreamDecoder, encode_stream_frame, frame_payload, stuff, unstuff
from protocol.fuzz import fuzz_decoder, sample_messages
from protocol.messages import Ack, Frame, Heartbeat


@given(st.binary(max_size=300))
def test_stuffing_roundtrip_and_no_flag_inside(data):
    s = stuff(data)
    assert b"\x7e" not in s and unstuff(s) == data


def test_unstuff_rejects_dangling_escape():
    assert unstuff(b"ab\x7d") is None and unstuff(b"\x7d\x41") is None


def test_header_carries_seq_flags_and_type():
    d = StreamDecoder()
    [p] = d.feed_packets(encode_stream_frame(Heartbeat(time_s=1.0, counter=9), seq=77, flags=FLAG_ACK_REQ))
    assert p.seq == 77 and p.wants_ack and p.message == Heartbeat(time_s=1.0, counter=9)


def test_byte_by_byte_feeding_equals_bulk():
    frames = [encode_stream_frame(Ack(seq=i), seq=i) for i in range(20)]
    d = StreamDecoder()
    got = []
    for b in b"".join(frames):
        got += d.feed(bytes([b]))
    assert got == [Ack(seq=i) for i in range(20)] and d.stats["frames_ok"] == 20


def test_truncated_frame_then_intact_frame_recovers_immediately():
    a = encode_stream_frame(Ack(seq=1), seq=1)
    b = encode_stream_frame(Ack(seq=2), seq=2)
    d = StreamDecoder()
    assert d.feed(a[:-7] + b) == [Ack(seq=2)]
    assert d.stats["crc_errors"] + d.stats["malformed"] == 1 and d.pending_bytes == 0


def test_every_single_bit_flip_is_caught():
    frame = encode_stream_frame(Heartbeat(time_s=2.5, counter=3), seq=5)
    bits = np.unpackbits(np.frombuffer(frame, np.uint8))
    for k in range(len(bits)):
        flipped = bits.copy()
        flipped[k] ^= 1
        d = StreamDecoder()
        out = d.feed(np.packbits(flipped).tobytes() + frame)
        # the corrupted copy is dropped; the intact copy that follows is always recovered
        assert out == [Heartbeat(time_s=2.5, counter=3)], k


def test_oversize_frame_is_dropped_without_buffering_it_all():
    d = StreamDecoder(max_frame_bytes=1000)
    big = frame_payload(6, 1, b"\x01" * 5000)
    ok = encode_stream_frame(Ack(seq=3), seq=3)
    out = []
    for i in range(0, len(big), 100):
        out += d.feed(big[i : i + 100])
        assert d.pending_bytes <= 2 * 1100
    out += d.feed(ok)
    assert out == [Ack(seq=3)] and d.stats["oversize"] == 1


def test_crc_ok_but_bad_payload_is_reported_as_rejected():
    d = StreamDecoder()
    assert d.feed(frame_payload(8, 41, b"\x92\x08\x80", FLAG_ACK_REQ)) == []  # Ack body missing 'seq'
    [rej] = d.take_rejected()
    assert rej.seq == 41 and "missing field" in rej.reason and d.stats["decode_errors"] == 1


def test_big_image_frame_survives_and_recovers_after_garbage():
    rng = np.random.default_rng(1)
    f = Frame(
        seq=1,
        capture_time_s=0.0,
        position_m=(0, 0, 1000),
        R_world_to_cam=np.eye(3),
        altimeter_m=1000.0,
        image=rng.integers(0, 256, (512, 512), dtype=np.uint8),
    )
    wire = encode_stream_frame(f, seq=1)
    d = StreamDecoder()
    out = d.feed(rng.integers(0, 256, 5000, dtype=np.uint8).tobytes() + wire[:100_000] + wire)
    assert len(out) == 1 and np.array_equal(out[0].image, f.image)


@pytest.mark.parametrize("seed", [0, 1])
def test_fuzz_bounded(seed):
    report = fuzz_decoder(n_inputs=5000, seed=seed, messages=sample_messages(seed, image_side=32))
    assert report["spurious"] == 0, report
    assert report["missed_intact"] == 0, report
    assert report["inputs"] == 5000 and report["intact_frames"] > 2000 and report["mutated_frames"] > 8000
