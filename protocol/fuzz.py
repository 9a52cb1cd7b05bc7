"""Seeded fuzzing of :class:`protocol.framing.StreamDecoder`.

Each fuzz input is a byte string built from segments: intact frames, random
garbage, truncated frames, bit-flipped frames, frames with bytes dropped or
duplicated. It is fed to a fresh decoder in random-sized chunks. Every frame
in an input has a unique link sequence number, so the check is exact:

* the decoder never raises (an exception propagates and fails the caller);
* every decoded packet is a frame that was in the input, with its original
  message (``spurious`` counts violations), in input order;
* every intact frame is decoded (``missed_intact`` counts violations).

Used by ``tests/test_protocol_framing.py`` (bounded) and
``bench/bench_protocol.py --fuzz`` (>= 100 000 inputs).
"""

from __future__ import annotations

import math

import numpy as np

from protocol.codec import encode_message
from protocol.framing import StreamDecoder, frame_payload
from protocol.messages import Ack, Error, Frame, Heartbeat, Message, Result, Site, Telemetry


def sample_messages(seed: int, image_side: int = 32) -> list[Message]:
    """A small, deterministic set of messages of every data-bearing type."""
    rng = np.random.default_rng(seed)
    grid = rng.normal(0, 1, (8, 8)).astype(np.float32)
    grid[0, :3] = np.nan
    return [
        Frame(
            seq=1,
            capture_time_s=0.5,
            position_m=(1.0, -2.0, 1000.0),
            R_world_to_cam=np.eye(3),
            altimeter_m=999.5,
            image=rng.integers(0, 256, (image_side, image_side), dtype=np.uint8),
        ),
        Result(
            frame_seqs=(1, 2),
            hazard_grid=grid,
            elevation_grid=-grid,
            grid_origin_xy=(-4.0, -4.0),
            grid_cell_m=1.0,
            sites=[Site(0.0, 1.0, -0.5, 0.1, 3.0, 2.0)],
        ),
        Result(
            frame_seqs=(3, 4),
            hazard_grid=grid[:0],
            elevation_grid=grid[:0],
            grid_origin_xy=(0.0, 0.0),
            grid_cell_m=0.5,
            sites=[],
            degraded=True,
            level="coarse",
        ),
        Telemetry(
            frame_seqs=(1, 2),
            stages={"dem": {"wall_s": 1.5, "cpu_s": 0.4}},
            total_latency_s=2.0,
            link={"crc_errors": 3},
        ),
        Heartbeat(time_s=12.0, counter=7),
        Error(code="deadline", text="pair 3 missed its deadline", seq=3),
        Ack(seq=123456),
    ]


def _mutate(frame: bytes, rng: np.random.Generator) -> tuple[bytes, bool]:
    """Return ``(bytes, intact)``: a corrupted variant of ``frame`` or the frame itself."""
    kind = rng.integers(0, 6)
    n = len(frame)
    if kind == 0:
        return frame, True
    if kind == 1:  # truncated (head or tail missing)
        cut = int(rng.integers(1, n))
        return (frame[:cut] if rng.random() < 0.5 else frame[cut:]), False
    arr = np.frombuffer(frame, np.uint8).copy()
    if kind == 2:  # 1-3 bit flips anywhere (including the flags)
        pos = rng.integers(0, n, int(rng.integers(1, 4)))
        arr[pos] ^= (1 << rng.integers(0, 8, len(pos))).astype(np.uint8)
    elif kind == 3:  # bytes dropped
        arr = np.delete(arr, rng.integers(1, n - 1, int(rng.integers(1, 4))))
    elif kind == 4:  # bytes duplicated
        arr = np.insert(arr, (pos := rng.integers(1, n - 1, int(rng.integers(1, 4)))), arr[pos])
    else:  # a burst overwritten with random bytes
        start = int(rng.integers(0, n))
        arr[start : start + 16] = rng.integers(0, 256, len(arr[start : start + 16]))
    out = arr.tobytes()
    return out, out == frame


def fuzz_decoder(
    n_inputs: int, seed: int, messages: list[Message] | None = None, max_segments: int = 6
) -> dict[str, int]:
    """Run ``n_inputs`` mutated inputs; return counters (``spurious`` and ``missed_intact`` must be 0)."""
    rng = np.random.default_rng(seed)
    msgs = messages or sample_messages(seed)
    bodies = [(m.TYPE, encode_message(m)) for m in msgs]
    report = dict.fromkeys(
        (
            "inputs",
            "bytes",
            "intact_frames",
            "recovered_intact",
            "mutated_frames",
            "recovered_mutated",
            "spurious",
            "missed_intact",
            "out_of_order",
        ),
        0,
    )
    for _ in range(n_inputs):
        parts: list[bytes] = []
        sent: dict[int, int] = {}  # seq -> message index
        intact: list[int] = []
        seq = int(rng.integers(0, 2**31))
        for _ in range(int(rng.integers(1, max_segments + 1))):
            if rng.random() < 0.25:
                parts.append(rng.integers(0, 256, int(rng.integers(1, 200)), dtype=np.uint8).tobytes())
                continue
            k = int(rng.integers(0, len(bodies)))
            frame = frame_payload(bodies[k][0], seq, bodies[k][1], int(rng.integers(0, 2)))
            data, ok = _mutate(frame, rng)
            parts.append(data)
            sent[seq] = k
            (intact.append(seq) if ok else None)
            report["intact_frames" if ok else "mutated_frames"] += 1
            seq += 1
        blob = b"".join(parts)
        report["bytes"] += len(blob)
        dec = StreamDecoder()
        got = []
        pos = 0
        while pos < len(blob):
            step = int(rng.integers(1, 4096))
            got += dec.feed_packets(blob[pos : pos + step])
            pos += step
        last = -1
        got_seqs = set()
        for p in got:
            if p.seq not in sent or not same_message(p.message, msgs[sent[p.seq]]):
                report["spurious"] += 1
                continue
            if p.seq <= last:
                report["out_of_order"] += 1
            last = p.seq
            got_seqs.add(p.seq)
        for s in intact:
            report["recovered_intact" if s in got_seqs else "missed_intact"] += 1
        report["recovered_mutated"] += len(got_seqs) - len(set(intact) & got_seqs)
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
        elif x != y and not (isinstance(x, float) and isinstance(y, float) and math.isnan(x) and math.isnan(y)):
            return False
    return True
