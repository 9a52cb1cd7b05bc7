"""Stream framing (wire version 2): byte stuffing, CRC, frame kinds, resynchronisation, bounded fuzz runs.

The full >= 100 000-input fuzz campaign is ``bench/bench_protocol.py --fuzz``; this
file runs the same generators (``protocol.fuzz``) on a bounded number of inputs.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from protocol.framing import (
    ACK,
    CLOSE,
    DATA,
    DGRAM,
    HELLO,
    REJECT,
    StreamDecoder,
    _frame,
    ack_frame,
    close_frame,
    data_frame,
    dgram_frame,
    hello_frame,
    reject_frame,
    stuff,
    unstuff,
)
from protocol.fuzz import fuzz_hostile, fuzz_noise


@given(st.binary(max_size=300))
def test_stuffing_roundtrip_and_no_flag_inside(data):
    s = stuff(data)
    assert b"\x7e" not in s and unstuff(s) == data


def test_sack_ranges_are_above_cum_in_serial_number_order_across_the_wrap():
    """Stream positions are u32 on the wire (docs/protocol.md section 1): a range above a cum just short of 2**32 may
    end, or lie wholly, past the wrap."""
    cum = 2**32 - 10
    for ranges in ([(2**32 - 8, 0), (3, 6)], [(2**32 - 4, 3)]):  # one ends at the wrap, one crosses it
        [f] = StreamDecoder().feed(ack_frame(1, 2, cum, 5, ranges))
        assert f.kind == ACK and (f.cum, f.sacks) == (cum, ranges)


def test_unstuff_rejects_dangling_escape():
    assert unstuff(b"ab\x7d") is None and unstuff(b"\x7d\x41") is None


def test_every_kind_round_trips_with_its_fields():
    d = StreamDecoder()
    wire = (
        data_frame(7, 9, 1000, b"\x7e\x7dpayload")
        + ack_frame(7, 9, 5, 32768, [(8, 10), (12, 20)])
        + dgram_frame(7, 9, 6, b"\x01\x02")
        + hello_frame(7, 0, 1024, 65536)
        + close_frame(7, 9, 77, "bye", 1)
        + reject_frame(7, 9, 44, "too big")
    )
    f = d.feed(wire)
    assert [x.kind for x in f] == [DATA, ACK, DGRAM, HELLO, CLOSE, REJECT]
    assert all(x.src == 7 for x in f) and f[3].dst == 0 and f[0].dst == 9
    assert f[0].pos == 1000 and f[0].payload == b"\x7e\x7dpayload"
    assert (f[1].cum, f[1].window, f[1].sacks) == (5, 32768, [(8, 10), (12, 20)])
    assert (f[2].type_code, f[2].payload) == (6, b"\x01\x02")
    assert (f[3].max_frame, f[3].window) == (1024, 65536)
    assert (f[4].cum, f[4].code, f[4].reason) == (77, 1, "bye") and (f[5].pos, f[5].reason) == (44, "too big")


@pytest.mark.parametrize(
    "frame",
    [
        _frame(ACK, 1, 2, b"\x00\x00\x00\x05\x00\x00\x00\x01\x01"),  # claims one SACK range, has none
        ack_frame(1, 2, 10, 5, [(4, 8)]),  # SACK range below cum
        ack_frame(1, 2, 10, 5, [(12, 11)]),  # a range that ends before it starts
        ack_frame(1, 2, 2**32 - 10, 5, [(2**32 - 20, 2)]),  # starts below cum, across the wrap
        ack_frame(1, 2, 10, 5, [(12, 2**31 + 10)]),  # ends 2 GiB above cum: no window is that wide
        _frame(HELLO, 1, 2, b"\x00\x00\x00\x10\x00\x00\x00\x01"),  # max_frame 16 < the minimum
        _frame(HELLO, 0, 2, b"\x00\x00\x04\x00\x00\x00\x00\x01"),  # session id 0
        _frame(DATA, 1, 2, b"\x00\x00\x00"),  # no payload
        _frame(99, 1, 2, b"x"),  # unknown kind
        _frame(DGRAM, 1, 2, b"\x06"),  # empty body
    ],
)
def test_crc_valid_but_malformed_frames_are_counted_not_raised(frame):
    d = StreamDecoder()
    assert d.feed(frame) == [] and d.stats["malformed"] == 1


def test_byte_by_byte_feeding_equals_bulk():
    frames = [data_frame(1, 2, i * 10, bytes([i]) * 10) for i in range(20)]
    d = StreamDecoder()
    got = []
    for b in b"".join(frames):
        got += d.feed(bytes([b]))
    assert [f.pos for f in got] == [i * 10 for i in range(20)] and d.stats["frames_ok"] == 20


def test_truncated_frame_then_intact_frame_recovers_immediately():
    a = data_frame(1, 2, 0, b"first")
    b = data_frame(1, 2, 5, b"second")
    d = StreamDecoder()
    got = d.feed(a[:-7] + b)
    assert [f.payload for f in got] == [b"second"]
    assert d.stats["crc_errors"] + d.stats["malformed"] == 1 and d.pending_bytes == 0


def test_the_decoder_names_the_sender_of_a_frame_still_arriving_or_garbled():
    """``claimed``: the src id of a frame whose head is in and whose tail is not (or whose CRC failed), so that a
    slow line's long frame counts as its sender talking; nothing for a piece too short to hold a header."""
    f = data_frame(0x1234ABCD, 2, 0, bytes(range(256)) * 3)
    d = StreamDecoder()
    assert d.feed(f[:5]) == [] and d.claimed == set()  # flag + 4 bytes: no header yet
    assert d.feed(f[5:40]) == [] and d.claimed == {0x1234ABCD}
    assert d.feed(f[40:41]) == [] and d.claimed == {0x1234ABCD}  # every feed while it arrives
    assert [x.src for x in d.feed(f[41:])] == [0x1234ABCD] and d.claimed == set()  # whole: a frame, not a claim
    garbled = bytearray(f)
    garbled[100] ^= 0x01
    # a piece that fails its CRC claims nothing when it closes (its bytes were claimed as they came): a peer that
    # died mid-frame and restarted would wait for it
    assert d.feed(bytes(garbled[:60])) == [] and d.claimed == {0x1234ABCD}
    assert d.feed(bytes(garbled[60:])) == [] and d.claimed == set() and d.stats["crc_errors"] == 1
    # noise in the body's first bytes (a bad escape) does not hide the header before it
    bad = bytearray(f[:40])
    bad[16:18] = b"\x7d\x00"
    assert d.feed(bytes(bad)) == [] and d.claimed == {0x1234ABCD}
    assert d.feed(b"\x7e" + bytes(60)) == [] and d.claimed == set()  # a piece of another wire version


def test_every_single_bit_flip_is_caught():
    body = b"\x92\x06\x81\xa6time_s\xcb" + bytes(8)
    frame = dgram_frame(3, 4, 6, body)
    bits = np.unpackbits(np.frombuffer(frame, np.uint8))
    for k in range(len(bits)):
        flipped = bits.copy()
        flipped[k] ^= 1
        d = StreamDecoder()
        out = d.feed(np.packbits(flipped).tobytes() + frame)
        # the corrupted copy is dropped; the intact copy that follows is always recovered
        assert len(out) == 1 and out[0].payload == body and out[0].type_code == 6 and out[0].src == 3, k


def test_oversize_frame_is_dropped_without_buffering_it_all():
    d = StreamDecoder(max_frame=1000)
    big = data_frame(1, 2, 0, b"\x01" * 5000)
    ok = data_frame(1, 2, 0, b"ok")
    out = []
    for i in range(0, len(big), 100):
        out += d.feed(big[i : i + 100])
        assert d.pending_bytes <= 2 * 1000
    out += d.feed(ok)
    assert [f.payload for f in out] == [b"ok"] and d.stats["oversize"] == 1


def test_a_frame_one_byte_over_max_frame_is_refused_whatever_its_stuffing():
    """``max_frame`` bounds the unstuffed frame (header to CRC): one of 1001 to 1999 bytes is refused and counted
    as oversize although its stuffed piece is within the 2 x max_frame the decoder holds, also when it is made mostly
    of flag bytes (each stuffed to two); one of exactly max_frame decodes. Until the mutation audit of stop 75 only
    a 5000-byte frame was tried, which the piece's own length refuses before it is unstuffed."""
    overhead = len(unstuff(data_frame(1, 2, 0, b"")[1:-1]))  # header, DATA head, CRC
    # (fill, unstuffed length): 1001 flag bytes' frame stuffs to 1978 bytes, 1010 to 1996; 1500 to 2952, which the
    # piece's length refuses unread
    for fill, lengths in ((b"\x01", (1001, 1500, 1999)), (b"\x7e", (1001, 1010, 1500))):
        for n in lengths:
            d = StreamDecoder(max_frame=1000)
            big = data_frame(1, 2, 0, fill * (n - overhead))
            assert len(unstuff(big[1:-1])) == n
            assert (len(big) - 2 <= 2 * 1000) == (fill == b"\x01" or n < 1500)  # held whole, unstuffed, refused
            out = d.feed(big + data_frame(1, 2, 0, b"ok"))
            assert [f.payload for f in out] == [b"ok"], (fill, n)
            assert d.stats["oversize"] == 1 and d.stats["frames_ok"] == 1, (fill, n, d.stats)
        d = StreamDecoder(max_frame=1000)
        exact = fill * (1000 - overhead)
        assert len(unstuff(data_frame(1, 2, 0, exact)[1:-1])) == 1000
        out = d.feed(data_frame(1, 2, 0, exact))
        assert [f.payload for f in out] == [exact] and d.stats["oversize"] == 0, fill


def test_garbage_and_idle_flags_between_frames():
    rng = np.random.default_rng(1)
    d = StreamDecoder()
    wire = b"\x7e\x7e\x7e" + rng.integers(0, 256, 5000, dtype=np.uint8).tobytes() + data_frame(1, 2, 0, b"x" * 900)
    out = d.feed(wire)
    assert len(out) == 1 and out[0].payload == b"x" * 900


@pytest.mark.parametrize("seed", [0, 1])
def test_noise_fuzz_bounded(seed):
    report = fuzz_noise(n_inputs=1500, seed=seed)
    assert report["spurious"] == 0 and report["missed"] == 0, report
    assert report["inputs"] == 1500 and report["mutated_frames"] > 1000 and report["messages"] > 3000


@pytest.mark.parametrize("seed", [0, 1])
def test_hostile_fuzz_bounded(seed):
    report = fuzz_hostile(n_inputs=300, seed=seed)
    assert report["violations"] == 0, report
    assert report["inputs"] == 300 and report["hostile_records"] > 200
    assert report["rejected_sent"] + report["decode_errors"] > 200  # refused, never delivered


def test_the_fuzz_samples_fill_every_result_field_and_the_hostile_ones_break_the_fill_mask():
    """The noise fuzz carries each Result field off its default in some sample (a field added to the schema
    without a sample fails here), and the hostile bodies include fill masks that do not fit elevation_image."""
    from dataclasses import MISSING, fields

    from protocol.codec import decode_message
    from protocol.errors import InputError
    from protocol.fuzz import hostile_bodies, sample_messages
    from protocol.messages import Result

    for seed in (0, 1):
        samples = [m for m in sample_messages(seed) if isinstance(m, Result)]
        for f in fields(Result):
            default = f.default_factory() if f.default_factory is not MISSING else f.default
            if default is MISSING:
                continue
            off = [getattr(r, f.name) is not default and not _same(getattr(r, f.name), default) for r in samples]
            assert any(off), f"no fuzz sample Result sets {f.name}"
    reasons = []
    for body in hostile_bodies(np.random.default_rng(0)):
        try:
            decode_message(body)
        except InputError as exc:  # every one is refused, in the codec or the schema
            reasons.append(str(exc))
        else:
            raise AssertionError("a hostile body was accepted")
    assert any("elevation_filled_image: shape (6, 5) != elevation_image (6, 6)" in r for r in reasons)
    assert any("elevation_filled_image: shape (6, 6) sent without elevation_image" in r for r in reasons)


def _same(a, b) -> bool:
    return not isinstance(a, np.ndarray) and not isinstance(b, np.ndarray) and a == b
