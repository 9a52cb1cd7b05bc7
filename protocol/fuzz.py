"""Seeded fuzzing of the receive path: frame decoder -> ARQ/reassembly -> codec budget -> schema.

Two campaigns, each input fed to a fresh receiving :class:`protocol.arq.Arq`
(established with a known peer) in random-sized chunks:

* :func:`fuzz_noise` - a valid reliable stream of messages, cut into DATA
  frames of random sizes, mixed with garbage, control frames, and mutated
  copies (truncated, bit-flipped, bytes dropped or duplicated, random bursts,
  delimiters hit); every frame hit by a mutation is later sent intact again
  (a retransmission) within the window. The check is exact: the decoder never
  raises, the messages come out exactly once, in order, equal to what was sent
  (``spurious`` and ``missed`` must be 0).
* :func:`fuzz_hostile` - frames with *valid CRCs and session ids* whose content
  is hostile: records that are msgpack bombs (nested empty maps, deep nesting,
  huge declared strings/containers), zlib bombs and lying array sizes, unknown
  types and fields, schema violations, records declaring more than the message
  limit, random bodies, out-of-window and overlapping DATA, ACKs of data never
  sent, bogus SACK ranges, HELLO/DGRAM/REJECT/CLOSE with random bodies. The
  check: nothing raises, every delivered message passed the schema, and memory
  held by the receiver stays inside its bounds (frame buffer <= 2 x max_frame,
  out-of-order data <= window, reassembly <= the message limit) after every
  input; the slowest input is reported.

Used by ``tests/test_protocol_framing.py`` (bounded) and
``bench/bench_protocol.py --fuzz`` (>= 100 000 inputs).
"""

from __future__ import annotations

import math
import struct
import time
import zlib
from collections.abc import Callable

import msgpack
import numpy as np

from protocol.arq import RECORD, Arq, ArqConfig
from protocol.codec import encode_message
from protocol.framing import (
    ACK_HEAD,
    CLOSE,
    DATA_OVERHEAD,
    DGRAM,
    REJECT,
    _frame,
    ack_frame,
    data_frame,
    dgram_frame,
    hello_frame,
)
from protocol.messages import Config, Error, Frame, Heartbeat, Hello, Message, Result, Site, Telemetry

RX, PEER = 0x52520001, 0x50500002  # receiver and peer session ids of every fuzz input


def sample_messages(seed: int, image_side: int = 32) -> list[Message]:
    """A small, deterministic set of messages of every type; each Result field is off its default in one of the two
    Results (tests/test_protocol_framing.py checks it)."""
    rng = np.random.default_rng(seed)
    state = rng.choice(np.array([0, 1, 2, 255], np.uint8), (8, 8))
    elevation = rng.normal(0.0, 2.0, (6, 6)).astype(np.float32)
    elevation[rng.random((6, 6)) < 0.2] = np.nan
    return [
        Hello(role="flight", session=1234),
        Config(
            camera={"width": 64, "height": 64, "fx": 60.0, "fy": 60.0, "cx": 31.5, "cy": 31.5},
            budget="host",
            deadline_s=2.0,
            options={"full_maps": 0},
        ),
        Frame(
            seq=1,
            capture_time_s=0.5,
            position_m=(1.0, -2.0, 1000.0),
            R_world_to_cam=np.eye(3),
            altimeter_m=999.5,
            image=rng.integers(0, 256, (image_side, image_side), dtype=np.uint8),
            pair_id="p0",
            frame_index=0,
        ),
        Result(
            frame_seqs=(1, 2),
            state_grid=state,
            psafe_grid=rng.integers(0, 256, (4, 4), dtype=np.uint8),
            psafe_step=2,
            elevation_grid=rng.integers(-32768, 32767, (4, 4), dtype=np.int16),
            grid_origin_xy=(-4.0, 4.0),
            grid_cell_m=1.0,
            elevation_step=2,
            elevation_offset_m=-12.0,
            elevation_unit_cm=10,
            sites=[Site(0.0, 1.0, -0.5, 0.1, 0.9, 2.0, 0.97, 1.5), Site(1.0, 1.0, math.nan, 0.2, 0.8, 3.0)],
            no_site_reason=None,
            elevation_filled=np.array([[0, 1, 0, 0], [0, 0, 0, 0], [1, 1, 0, 0], [0, 0, 0, 1]], np.uint8),
        ),
        Result(
            frame_seqs=(3, 4),
            state_grid=state[:0],
            psafe_grid=state[:0],
            elevation_grid=np.zeros((0, 8), np.int16),
            grid_origin_xy=(0.0, 0.0),
            grid_cell_m=0.5,
            degraded=True,
            level="image_only",
            no_site_reason="no footprint is known safe",
            skipped=("full_dem", "sites"),
            hazard_image=rng.random((6, 6), dtype=np.float32),
            elevation_image=elevation,
            state_image=np.zeros((6, 6), np.uint8),
            # the gap fills among elevation_image's pixels (a fill always has an elevation)
            elevation_filled_image=((rng.random((6, 6)) < 0.3) & np.isfinite(elevation)).astype(np.uint8),
        ),
        Telemetry(
            frame_seqs=(1, 2),
            stages={"dem": {"wall_s": 1.5, "cpu_s": 0.4}},
            link={"crc_errors": 3},
            pose={"applied": 1, "inliers": 212, "rot_deg": 0.31},
            pose_verdict="refined",
            notes=("frame 2's image is noisy",),
        ),
        Heartbeat(time_s=12.0, counter=7),
        Error(code="deadline", text="pair 3 missed its deadline", seq=3),
    ]


def _mutate(frame: bytes, rng: np.random.Generator) -> bytes:
    """A corrupted variant of ``frame`` (never the frame itself)."""
    n = len(frame)
    while True:
        kind = int(rng.integers(0, 5))
        if kind == 0:  # truncated (head or tail missing)
            cut = int(rng.integers(1, n))
            out = frame[:cut] if rng.random() < 0.5 else frame[cut:]
        else:
            arr = np.frombuffer(frame, np.uint8).copy()
            if kind == 1:  # 1-3 bit flips anywhere (including the flags)
                pos = rng.integers(0, n, int(rng.integers(1, 4)))
                arr[pos] ^= (1 << rng.integers(0, 8, len(pos))).astype(np.uint8)
            elif kind == 2:  # bytes dropped
                arr = np.delete(arr, rng.integers(1, n - 1, int(rng.integers(1, 4))))
            elif kind == 3:  # bytes duplicated
                arr = np.insert(arr, (pos := rng.integers(1, n - 1, int(rng.integers(1, 4)))), arr[pos])
            else:  # a burst overwritten with random bytes
                start = int(rng.integers(0, n))
                arr[start : start + 16] = rng.integers(0, 256, len(arr[start : start + 16]))
            out = arr.tobytes()
        if out != frame:
            return out


def _receiver(window: int = 32 << 10, max_frame: int = 1024) -> Arq:
    arq = Arq(ArqConfig(window=window, max_frame=max_frame, peer_timeout=None), session_id=RX)
    arq.receive(hello_frame(PEER, RX, max_frame, window), 0.0)
    assert arq.established
    return arq


def _feed(arq: Arq, blob: bytes, rng: np.random.Generator) -> None:
    pos = 0
    while pos < len(blob):
        step = int(rng.integers(1, 4096))
        arq.receive(blob[pos : pos + step], 1.0)
        pos += step


def fuzz_noise(
    n_inputs: int,
    seed: int,
    messages: list[Message] | None = None,
    max_messages: int = 5,
    progress: Callable[[int], None] | None = None,
) -> dict:
    """Corrupted valid streams; returns counters (``spurious`` and ``missed`` must be 0). ``progress`` is called
    with the number of inputs done before each input (a campaign of 100 000 runs for minutes)."""
    rng = np.random.default_rng(seed)
    msgs = messages or sample_messages(seed)
    records = [RECORD.pack(m.TYPE, len(b)) + b for m in msgs for b in (encode_message(m),)]
    report = dict.fromkeys(("inputs", "bytes", "frames", "mutated_frames", "messages", "spurious", "missed"), 0)
    for done in range(n_inputs):
        if progress is not None:
            progress(done)
        picks = [int(k) for k in rng.integers(0, len(msgs), int(rng.integers(1, max_messages + 1)))]
        stream = b"".join(records[k] for k in picks)
        frames = []
        pos = 0
        while pos < len(stream):
            n = int(rng.integers(1, 1024 - DATA_OVERHEAD + 1))
            frames.append(data_frame(PEER, RX, pos, stream[pos : pos + n]))
            pos += n
        parts: list[bytes] = []
        owed: list[tuple[int, bytes]] = []  # (emit after this many more frames, intact frame)
        for f in frames:
            if rng.random() < 0.15:
                parts.append(rng.integers(0, 256, int(rng.integers(1, 200)), dtype=np.uint8).tobytes())
            if rng.random() < 0.1:
                parts.append(ack_frame(PEER, RX, 0, 1024, []))
            report["frames"] += 1
            if rng.random() < 0.5:
                parts.append(_mutate(f, rng))
                report["mutated_frames"] += 1
                owed.append((int(rng.integers(0, 4)), f))
            else:
                parts.append(f)
            still = []
            for k, g in owed:
                if k <= 0:
                    parts.append(g)
                else:
                    still.append((k - 1, g))
            owed = still
        parts += [g for _, g in owed]
        blob = b"".join(parts)
        report["bytes"] += len(blob)
        arq = _receiver()
        _feed(arq, blob, rng)
        got = [r.message for r in arq.take_received()]
        want = [msgs[k] for k in picks]
        report["messages"] += len(want)
        for i, m in enumerate(got):
            if i >= len(want) or not same_message(m, want[i]):
                report["spurious"] += 1
        report["missed"] += max(0, len(want) - len(got))
        report["inputs"] += 1
    return report


# ------------------------------------------------------------------------------------ hostile input
def nested_map_bomb(nbytes: int) -> bytes:
    """The issue's bomb, about ``nbytes`` of msgpack: a Heartbeat body whose extra field holds arrays of
    arrays of 4096 empty maps - every container within the 4096-item and depth-8 limits, one object per byte."""
    inner = b"\xdc\x10\x00" + b"\x80" * 4096
    n = max(1, (nbytes - 64) // len(inner))
    k = -(-n // 4096)
    m = max(1, (nbytes - 64 - 3 * k) // (len(inner) * k))
    mid = b"\xdc" + m.to_bytes(2, "big") + inner * m
    head = b"\x92\x06\x82\xa6time_s\xcb" + struct.pack(">d", 1.0) + b"\xa1x\xdc" + k.to_bytes(2, "big")
    return head + mid * k


def _ext(code: int, payload: bytes) -> msgpack.ExtType:
    return msgpack.ExtType(code, payload)


def hostile_bodies(rng: np.random.Generator) -> list[bytes]:
    """msgpack message bodies a receiver must refuse (each raises in the codec or the schema)."""
    shape = lambda *s: bytes((1, len(s))) + b"".join(int(v).to_bytes(4, "big") for v in s)  # noqa: E731 (u8 arrays)
    zeros = zlib.compress(bytes(1 << 20), 9)
    good = encode_message(sample_messages(0)[3])
    return [
        nested_map_bomb(int(rng.integers(20_000, 120_000))),
        msgpack.packb([6, {"time_s": 0.0, "x": [[[[[[[[[[1]]]]]]]]]]}]),
        b"\x92\x06\x81\xa1x\xdb\x7f\xff\xff\xff",  # str32 declaring 2 GiB
        b"\x92\x06\x81\xa1x\xdd\x7f\xff\xff\xff",  # array32 declaring 2**31 items
        b"\x92\x06\x81\xa1x\xdf\x00\x01\x00\x00",  # map32 of 65536 pairs, truncated
        msgpack.packb([4, {"x": _ext(3, shape(4096, 4096) + b"\x00" + zeros)}]),  # zlib stream shorter than declared
        msgpack.packb([4, {"x": _ext(3, shape(512, 512) + b"\x00" + zeros)}]),  # inflates to more than declared
        msgpack.packb([4, {f"a{i}": _ext(3, shape(4096, 4096) + b"\x00" + zeros) for i in range(4)}]),  # > budget
        msgpack.packb([4, {"x": _ext(3, shape(8, 8) + b"\x07" + zlib.compress(bytes(64)))}]),  # unknown filter
        msgpack.packb([3, {"image": _ext(1, shape(100, 100) + b"abc")}]),  # lying inline size
        msgpack.packb([99, {}]),
        msgpack.packb([8, {"seq": 1}]),  # retired type code
        msgpack.packb([6, {"time_s": 1.0, "evil": 2}]),
        msgpack.packb([7, {"code": "x" * 70, "text": "t"}]),
        good[:-3],  # truncated
        good + b"\x00",  # trailing byte
        rng.integers(0, 256, int(rng.integers(1, 600)), dtype=np.uint8).tobytes(),
        _result_with(rng, state=np.full((4, 4), 7, np.uint8)),  # invalid state codes
        _result_with(rng, psafe=np.zeros((3, 4), np.uint8)),  # grids that do not agree
        # a fill mask of another shape than elevation_image, and one with no elevation_image to mark
        _result_with(
            rng, elevation_image=np.zeros((6, 6), np.float32), elevation_filled_image=np.ones((6, 5), np.uint8)
        ),
        _result_with(rng, elevation_filled_image=np.ones((6, 6), np.uint8)),
    ]


def _result_with(rng: np.random.Generator, **over: np.ndarray) -> bytes:
    """A Result body (inline arrays) with ``state`` / ``psafe`` grids or any other field given in ``over``."""
    body = {
        "frame_seqs": [1, 2],
        "state_grid": over.pop("state", np.zeros((4, 4), np.uint8)),
        "psafe_grid": over.pop("psafe", np.zeros((4, 4), np.uint8)),
        "elevation_grid": np.zeros((4, 4), np.int16),
        "grid_origin_xy": [0.0, 0.0],
        "grid_cell_m": 1.0,
        **over,
    }

    def default(o: object) -> object:
        if isinstance(o, np.ndarray):
            head = bytes(({np.dtype("u1"): 1, np.dtype("<i2"): 4, np.dtype("<f4"): 9}[o.dtype], o.ndim))
            return _ext(1, head + b"".join(int(s).to_bytes(4, "big") for s in o.shape) + o.tobytes())
        raise TypeError

    return msgpack.packb([4, body], default=default)


def _hostile_frame(rng: np.random.Generator, bodies: list[bytes], stream_pos: int) -> bytes:
    kind = int(rng.integers(0, 9))
    if kind == 0:  # DATA far outside the window
        return data_frame(PEER, RX, int(rng.integers(1 << 20, 2**32 - 2048)), rng.bytes(int(rng.integers(1, 900))))
    if kind == 1:  # DATA overlapping what was already received
        return data_frame(PEER, RX, int(rng.integers(0, stream_pos + 1)), rng.bytes(int(rng.integers(1, 900))))
    if kind == 2:  # ACK of data never sent / bogus SACK ranges
        n = int(rng.integers(0, 17))
        sacks = sorted({(int(a), int(a) + int(rng.integers(1, 1 << 20))) for a in rng.integers(1, 2**31, n)})
        return ack_frame(
            PEER, RX, int(rng.integers(0, 2**32)), int(rng.integers(0, 2**32)), sacks, int(rng.integers(0, 2**32))
        )
    if kind == 3:  # a raw ACK body with inconsistent counts
        body = ACK_HEAD.pack(0, 1, int(rng.integers(0, 2**32)), int(rng.integers(0, 256))) + rng.bytes(
            int(rng.integers(0, 64))
        )
        return _frame(2, PEER, RX, body)
    if kind == 4:  # datagrams with hostile bodies
        return dgram_frame(PEER, RX, int(rng.integers(0, 256)), bodies[int(rng.integers(0, len(bodies)))][:900])
    if kind == 5:
        return hello_frame(int(rng.integers(1, 2**32)), int(rng.integers(0, 2**32)), int(rng.integers(0, 2**32)), 1)
    if kind == 6:
        return _frame(REJECT, PEER, RX, rng.bytes(int(rng.integers(0, 300))))
    if kind == 7:  # random kind and body, valid CRC
        return _frame(int(rng.integers(0, 256)), PEER, RX, rng.bytes(int(rng.integers(0, 900))))
    return _frame(CLOSE if rng.random() < 0.01 else DGRAM, PEER, RX, rng.bytes(int(rng.integers(0, 300))))


def fuzz_hostile(
    n_inputs: int,
    seed: int,
    max_frame: int = 1024,
    window: int = 32 << 10,
    progress: Callable[[int], None] | None = None,
) -> dict:
    """CRC-valid hostile frames; returns counters and the worst per-input time (see module doc). ``progress``: as
    :func:`fuzz_noise`'s."""
    rng = np.random.default_rng(seed + 7919)
    valid = sample_messages(seed, image_side=16)
    fixed = hostile_bodies(rng)  # built once: the zlib bombs cost ~10 ms each to make
    report: dict[str, float] = dict.fromkeys(
        ("inputs", "frames", "bytes", "hostile_records", "delivered", "rejected_sent", "decode_errors", "violations"),
        0,
    )
    report["max_input_s"] = 0.0
    for done in range(n_inputs):
        if progress is not None:
            progress(done)
        bodies = fixed + [rng.bytes(int(rng.integers(1, 600))), nested_map_bomb(int(rng.integers(20_000, 60_000)))]
        recs = []
        for _ in range(int(rng.integers(1, 4))):
            if rng.random() < 0.3:
                m = valid[int(rng.integers(0, len(valid)))]
                b = encode_message(m)
                recs.append(RECORD.pack(m.TYPE, len(b)) + b)
            else:
                b = bodies[int(rng.integers(0, len(bodies)))]
                t = int(rng.integers(0, 10)) if rng.random() < 0.3 else int(b[1]) if len(b) > 1 and b[1] < 16 else 4
                recs.append(RECORD.pack(t, len(b)) + b)
                report["hostile_records"] += 1
        if rng.random() < 0.2:  # a record declaring more than the limit (the stream ends there)
            recs.append(RECORD.pack(4, int(rng.integers(32 << 20, 2**32))) + rng.bytes(100))
        stream = b"".join(recs)
        parts = []
        pos = 0
        while pos < len(stream):
            n = int(rng.integers(1, max_frame - DATA_OVERHEAD + 1))
            parts.append(data_frame(PEER, RX, pos, stream[pos : pos + n]))
            pos += n
            while rng.random() < 0.3:
                parts.append(_hostile_frame(rng, bodies, pos))
        blob = b"".join(parts)
        report["frames"] += len(parts)
        report["bytes"] += len(blob)
        arq = _receiver(window, max_frame)
        t0 = time.perf_counter()
        pos = 0
        while pos < len(blob):
            step = int(rng.integers(1, 1 << 15))
            arq.receive(blob[pos : pos + step], 1.0)
            pos += step
            held = arq.held_bytes()
            if (
                held["frame"] > 2 * max_frame
                or held["out_of_order"] > window
                or held["reassembly"] > arq.cfg.limits.max_message_bytes
            ):
                report["violations"] += 1
        report["max_input_s"] = max(report["max_input_s"], time.perf_counter() - t0)
        got = arq.take_received()
        report["delivered"] += len(got)
        report["rejected_sent"] += int(arq.stats["rejected_sent"])
        report["decode_errors"] += int(arq.stats["decode_errors"])
        report["inputs"] += 1
    return report


def same_message(a: Message, b: Message) -> bool:
    """Message equality with arrays compared bitwise and NaN equal to NaN
    (dataclass ``==`` is ambiguous for arrays)."""
    if type(a) is not type(b):
        return False
    for name in a.__dataclass_fields__:  # type: ignore[attr-defined]
        x, y = getattr(a, name), getattr(b, name)
        if isinstance(x, np.ndarray) or isinstance(y, np.ndarray):
            if not (
                isinstance(x, np.ndarray)
                and isinstance(y, np.ndarray)
                and x.dtype == y.dtype
                and x.shape == y.shape
                and x.tobytes() == y.tobytes()
            ):
                return False
        elif isinstance(x, list) and isinstance(y, list):
            if len(x) != len(y) or any(
                not (u == v or all(_nan_eq(p, q) for p, q in zip(_astuple(u), _astuple(v)))) for u, v in zip(x, y)
            ):
                return False
        elif x != y and not (isinstance(x, float) and isinstance(y, float) and math.isnan(x) and math.isnan(y)):
            return False
    return True


def _astuple(v: object) -> tuple:
    if hasattr(v, "__dataclass_fields__"):
        return tuple(getattr(v, k) for k in v.__dataclass_fields__)  # type: ignore[attr-defined]
    return (v,)


def _nan_eq(x: object, y: object) -> bool:
    return x == y or (isinstance(x, float) and isinstance(y, float) and math.isnan(x) and math.isnan(y))
