#!/usr/bin/env python3
"""A minimal flight program for hazard-hil, written from docs/protocol.md alone.

It speaks wire version 2 over a serial line (a USB-UART device, or the pty the
HIL server gives it) with nothing but pyserial, msgpack and numpy: HDLC-style
frames with CRC-32, the session handshake, the reliable byte stream (in-order
receive, cumulative ACKs, resend after a timeout) and datagrams for heartbeats.

It answers every pair with a valid Result that knows nothing: the upper image's
footprint on the ground as a grid of cells in state 2 (unknown), P(safe) 0, no
elevation, no sites - the honest answer of a hazard detector that has not been
written yet. Replace ``answer()`` with your own and keep the rest: it runs in a thread
beside the link, which keeps the session up (ACKs, keepalives, heartbeats) however long
it takes. A detector that blocked the loop for more than the link timeout (4 s) lost
its session, and the ground blamed the link.

Run it under the emulated budget (the HIL server starts it, gives it its line as
``{port}`` and ``$HAZARD_HIL_PORT``, and throttles, pins, caps and watches it):

    .venv/bin/hazard-hil run --budget snapdragon801 \\
        --flight-cmd ".venv/bin/python examples/minimal_flight.py --port {port}"

or on a board of your own, with the ground streaming to it:

    python minimal_flight.py --port /dev/ttyUSB0 --baud 921600        # on the board
    hazard-hil run --flight external --link serial:/dev/ttyUSB0@921600  # on the ground PC

It imports nothing from hazard-hil on purpose: it is the proof that the spec is enough.
"""

from __future__ import annotations

import argparse
import math
import os
import random
import struct
import sys
import threading
import time
import zlib
from collections import deque
from concurrent.futures import Future

import msgpack
import numpy as np
import serial

# --- section 1: frames --------------------------------------------------------------------------------------
FLAG, ESC = 0x7E, 0x7D
VERSION = 2
DATA, ACK, DGRAM, HELLO, CLOSE, REJECT = 1, 2, 3, 4, 5, 6
MAX_FRAME = 4096  # what we accept (announced in HELLO)
WINDOW = 1 << 20  # receive window we announce (bytes)


def stuff(raw: bytes) -> bytes:
    return raw.replace(b"\x7d", b"\x7d\x5d").replace(b"\x7e", b"\x7d\x5e")


def unstuff(piece: bytes) -> bytes | None:
    out = bytearray()
    i = 0
    while i < len(piece):
        b = piece[i]
        if b == ESC:
            if i + 1 >= len(piece) or piece[i + 1] not in (0x5D, 0x5E):
                return None
            out.append(piece[i + 1] ^ 0x20)
            i += 2
        else:
            out.append(b)
            i += 1
    return bytes(out)


def frame(kind: int, src: int, dst: int, body: bytes) -> bytes:
    raw = struct.pack(">BBHII", VERSION, kind, 0, src, dst) + body
    raw += struct.pack(">I", zlib.crc32(raw))
    return bytes([FLAG]) + stuff(raw) + bytes([FLAG])


def parse(piece: bytes) -> tuple[int, int, int, bytes] | None:
    """(kind, src, dst, body) of a valid frame, None for anything malformed (dropped, never raised)."""
    raw = unstuff(piece)
    if raw is None or len(raw) < 16 or len(raw) > MAX_FRAME:
        return None
    if zlib.crc32(raw[:-4]) != struct.unpack(">I", raw[-4:])[0]:
        return None
    version, kind, flags, src, dst = struct.unpack(">BBHII", raw[:12])
    if version != VERSION or flags != 0 or kind not in (DATA, ACK, DGRAM, HELLO, CLOSE, REJECT):
        return None
    return kind, src, dst, raw[12:-4]


# --- section 5: messages ------------------------------------------------------------------------------------
HELLO_MSG, CONFIG, FRAME_MSG, RESULT, TELEMETRY, HEARTBEAT, ERROR = 1, 2, 3, 4, 5, 6, 7
PROTOCOL = 2  # the messages' version (section 5), said in our Hello
DTYPES = {1: "|u1", 2: "|i1", 3: "<u2", 4: "<i2", 5: "<u4", 6: "<i4", 7: "<u8", 8: "<i8", 9: "<f4", 10: "<f8"}
DTYPES.update({11: "|b1", 12: "<f2"})
CODES = {np.dtype(v): k for k, v in DTYPES.items()}


def ext_hook(code: int, data: bytes):
    """Arrays: ext 1 (raw) and ext 3 (zlib, delta filter 0, 1 or 2: the trailing axes differenced) - section 5.2."""
    dt = np.dtype(DTYPES[data[0]])
    ndim = data[1]
    shape = struct.unpack(f">{ndim}I", data[2 : 2 + 4 * ndim])
    rest = data[2 + 4 * ndim :]
    if code == 1:
        return np.frombuffer(rest, dt).reshape(shape)
    if code == 3:
        arr = np.frombuffer(zlib.decompress(rest[1:]), dt).reshape(shape)
        if rest[0] > min(ndim, 2) or (rest[0] and dt.kind not in "iu"):
            raise ValueError(f"filter {rest[0]} does not apply to a {ndim}-d {dt} array")
        for axis in range(ndim - rest[0], ndim):  # filter k: the last k axes were differenced, in order
            arr = np.cumsum(arr, axis=axis, dtype=dt)
        return arr
    raise ValueError(f"ext type {code} is not for byte streams")


def array(a: np.ndarray) -> msgpack.ExtType:
    """ext 3, zlib, no filter."""
    a = np.ascontiguousarray(a)
    head = struct.pack(f">BB{a.ndim}I", CODES[a.dtype], a.ndim, *a.shape)
    return msgpack.ExtType(3, head + b"\x00" + zlib.compress(a.tobytes(), 6))


def body(mtype: int, fields: dict) -> bytes:
    return msgpack.packb([mtype, fields], use_bin_type=True)


# --- sections 2-4: one link session over a serial port ------------------------------------------------------
class Link:
    """Handshake, in-order reliable stream (both directions), datagrams. Single-threaded: call poll() often."""

    RTO = 1.0  # resend the oldest unacknowledged bytes after this long without progress

    def __init__(self, port: serial.Serial) -> None:
        self.port = port
        self.buf = bytearray()
        self.retired: set[int] = set()
        self.closed_by_peer = False
        self.new_session()

    def new_session(self) -> None:
        self.local = random.randrange(1, 2**32)
        self.peer = 0
        self.established = False
        self.peer_max_frame = 1024
        self.peer_window = 32 << 10
        self.rx_cum, self.rx_stream, self.echo = 0, bytearray(), 0  # receive side
        self.tx_data, self.tx_base, self.tx_sent, self.tx_high, self.txid = bytearray(), 0, 0, 0, 0  # send side
        self.tx_progress = time.monotonic()
        self.next_hello = 0.0
        self.last_answer = 0.0

    def write(self, kind: int, payload: bytes, dst: int | None = None) -> None:
        self.port.write(frame(kind, self.local, self.peer if dst is None else dst, payload))

    def hello(self, dst: int) -> None:
        self.write(HELLO, struct.pack(">II", MAX_FRAME, WINDOW), dst)

    # sending
    def send(self, mtype: int, fields: dict) -> None:
        """Reliable: one record ``type:u8 | length:u32 | body`` appended to the stream (section 3.1)."""
        b = body(mtype, fields)
        self.tx_data += struct.pack(">BI", mtype, len(b)) + b

    def datagram(self, mtype: int, fields: dict) -> None:
        if self.established:
            self.write(DGRAM, bytes([mtype]) + body(mtype, fields))

    def _pump(self, now: float) -> None:
        if not self.established:
            return
        if self.tx_sent > self.tx_base and now - self.tx_progress > self.RTO:
            self.tx_sent = self.tx_base  # go back: resend everything unacknowledged
            self.tx_progress = now
        seg = self.peer_max_frame - 12 - 4 - 8  # header, CRC, pos + txid
        end = self.tx_base + len(self.tx_data)
        while self.tx_sent < end and self.tx_sent - self.tx_base < min(self.peer_window, 32 << 10):
            chunk = self.tx_data[self.tx_sent - self.tx_base : self.tx_sent - self.tx_base + seg]
            self.txid += 1
            self.write(DATA, struct.pack(">II", self.tx_sent, self.txid) + chunk)
            self.tx_sent += len(chunk)
            self.tx_high = max(self.tx_high, self.tx_sent)

    # receiving
    def poll(self, timeout: float = 0.02) -> list[tuple[int, dict]]:
        """Read the port, run the timers; returns the messages (type, fields) that arrived."""
        now = time.monotonic()
        if now >= self.next_hello:  # rule 6: HELLO every 0.25 s until established, then a keepalive every 1 s
            # (the reference sends one only on an idle line: this side sends little, so every 1 s does no harm)
            self.hello(self.peer)
            self.next_hello = now + (1.0 if self.established else 0.25)
        self._pump(now)
        self.port.timeout = timeout
        data = self.port.read(max(1, self.port.in_waiting))
        self.buf += data
        out: list[tuple[int, dict]] = []
        acked = False
        *pieces, self.buf = self.buf.split(bytes([FLAG]))
        for piece in pieces:
            f = parse(bytes(piece)) if piece else None
            if f is not None:
                acked |= self._on_frame(*f, out)
        if acked:  # one ACK per batch of DATA: cum, window, echo, no SACK ranges
            self.write(ACK, struct.pack(">IIIB", self.rx_cum, WINDOW, self.echo, 0))
        return out

    def _on_frame(self, kind: int, src: int, dst: int, payload: bytes, out: list) -> bool:
        if src in self.retired:
            return False
        if kind == HELLO and len(payload) == 8:
            max_frame, window = struct.unpack(">II", payload)
            if src != self.peer:  # rule 2: a new peer, or a restarted one (the stranger clause is left out here)
                if self.peer:
                    self.retired.add(self.peer)
                    self.new_session()
                self.peer = src
            self.peer_max_frame, self.peer_window = min(max_frame, MAX_FRAME), window
            if dst == self.local:  # rule 3
                if not self.established:
                    self.established = True
                    self.hello(self.peer)
            elif time.monotonic() - self.last_answer >= 0.125:  # rule 4
                self.last_answer = time.monotonic()
                self.hello(src)
            return False
        if src != self.peer or dst != self.local:  # rule 5
            return False
        self.established = True
        if kind == DATA and len(payload) > 8:
            pos, txid = struct.unpack(">II", payload[:8])
            chunk = payload[8:]
            self.echo = max(self.echo, txid)
            if pos <= self.rx_cum < pos + len(chunk):  # in order (or overlapping): take the new bytes
                self.rx_stream += chunk[self.rx_cum - pos :]
                self.rx_cum = pos + len(chunk)
                self._records(out)
            return True  # out-of-order bytes are not held here: the sender resends them
        if kind == ACK and len(payload) >= 13:
            cum = struct.unpack(">I", payload[:4])[0]
            self.peer_window = struct.unpack(">I", payload[4:8])[0]
            if self.tx_base < cum <= self.tx_high:  # beyond what we sent: malformed, ignored
                del self.tx_data[: cum - self.tx_base]
                self.tx_base = cum
                self.tx_sent = max(self.tx_sent, cum)
                self.tx_progress = time.monotonic()
        elif kind == DGRAM and payload:
            out.append(msgpack.unpackb(payload[1:], ext_hook=ext_hook, raw=False))
        elif kind == CLOSE:  # rule 8: code 0 = the ground is done; 1 = it gave up and will offer a new session
            if len(payload) >= 5 and payload[4] == 0:
                self.closed_by_peer = True
            self.retired.add(self.peer)
            self.new_session()
        return False

    def _records(self, out: list) -> None:
        while len(self.rx_stream) >= 5:
            mtype, length = struct.unpack(">BI", self.rx_stream[:5])
            if len(self.rx_stream) < 5 + length:
                return
            out.append(msgpack.unpackb(bytes(self.rx_stream[5 : 5 + length]), ext_hook=ext_hook, raw=False))
            del self.rx_stream[: 5 + length]


# --- section 6: the application --------------------------------------------------------------------------
def footprint(frame_msg: dict, cam: dict) -> tuple[np.ndarray, np.ndarray]:
    """World x, y of the upper image's corners on the ground plane under the camera."""
    pos = np.asarray(frame_msg["position_m"], float)
    r = np.asarray(frame_msg["R_world_to_cam"], float)
    axis = r.T @ np.array([0.0, 0.0, 1.0])  # optical axis in world
    alt = frame_msg["altimeter_m"]
    ground_z = pos[2] + alt * axis[2] if not math.isnan(alt) and axis[2] < 0 else 0.0  # NaN: no reading -> datum
    u = np.array([0.0, cam["width"] - 1.0, cam["width"] - 1.0, 0.0])
    v = np.array([0.0, 0.0, cam["height"] - 1.0, cam["height"] - 1.0])
    rays = r.T @ np.stack([(u - cam["cx"]) / cam["fx"], (v - cam["cy"]) / cam["fy"], np.ones(4)])
    t = (ground_z - pos[2]) / np.minimum(rays[2], -1e-6)
    return pos[0] + t * rays[0], pos[1] + t * rays[1]


def answer(upper: dict, lower: dict, config: dict) -> dict:
    """The Result fields for one pair: everything unknown, on a 64-cell grid over the footprint."""
    xs, ys = footprint(upper, config["camera"])
    cell = max(float(np.ptp(xs)), float(np.ptp(ys)), 1.0) / 64.0
    cols = int(np.ceil(np.ptp(xs) / cell)) + 1
    rows = int(np.ceil(np.ptp(ys) / cell)) + 1
    return {
        "frame_seqs": [upper["seq"], lower["seq"]],
        "state_grid": array(np.full((rows, cols), 2, np.uint8)),  # 2 = unknown
        "psafe_grid": array(np.zeros((rows, cols), np.uint8)),  # P(safe) 0/254
        "elevation_grid": array(np.full((rows, cols), -32768, np.int16)),  # no elevation
        "grid_origin_xy": [float(xs.min()), float(ys.max())],  # cell [0, 0]; rows run toward -Y
        "grid_cell_m": cell,
        "sites": [],
        "no_site_reason": "minimal_flight.py detects no hazards: every cell is unknown",
        "degraded": True,
        "level": "none",
    }


def telemetry(upper: dict, lower: dict, config: dict, wall: float, cpu: float) -> dict:
    """The Telemetry fields for one pair answered in ``wall`` s (``cpu`` s of CPU): one stage, ``total``."""
    return {
        "frame_seqs": [upper["seq"], lower["seq"]],
        "stages": {"total": {"wall_s": wall, "cpu_s": cpu}},
        "total_latency_s": wall,
        "cpu_fraction": float("nan"),
        "deadline_s": float(config["deadline_s"]),
        "deadline_met": wall <= config["deadline_s"],
    }


def detect(pair: dict, config: dict) -> Future:
    """``answer()`` for ``pair`` (frame index -> Frame) in a thread of its own, beside the link loop, which keeps the
    session up meanwhile; the Future holds ``(result fields, CPU seconds)``. The CPU is the process's over the
    call, so that a detector's own threads (OpenCV, BLAS) count. A daemon thread: a detector still running, or
    hung, does not keep the program from exiting when its ground is done."""
    done: Future = Future()

    def run() -> None:
        c0 = time.process_time()
        try:
            done.set_result((answer(pair[0], pair[1], config), time.process_time() - c0))
        except BaseException as exc:  # said by the loop, which sends the Error
            done.set_exception(exc)

    threading.Thread(target=run, name="detector", daemon=True).start()
    return done


def answered(pair: dict, config: dict, t0: float, done: Future) -> list[tuple[int, dict]]:
    """The messages that end a pair whose :func:`detect` (started at ``t0``, monotonic) is done: its Result and
    Telemetry, or an Error with the detector's exception, so that one bad pair does not end the program."""
    failed = done.exception()
    if failed is not None:
        text = f"{type(failed).__name__}: {failed}"[:2000]
        return [(ERROR, {"code": "pipeline_failure", "text": text, "seq": pair[1]["seq"]})]
    result, cpu = done.result()
    return [(RESULT, result), (TELEMETRY, telemetry(pair[0], pair[1], config, time.monotonic() - t0, cpu))]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--port", default=os.environ.get("HAZARD_HIL_PORT"), help="serial device (default $HAZARD_HIL_PORT)"
    )
    ap.add_argument("--baud", type=int, default=921600, help="line rate of a real serial port (a pty ignores it)")
    args = ap.parse_args(argv)
    if not args.port:
        ap.error("no serial port: give --port or set HAZARD_HIL_PORT")
    try:
        port = serial.serial_for_url(args.port, baudrate=args.baud, timeout=0.02)
    except (serial.SerialException, OSError, ValueError) as exc:  # no such device, or another program holds it
        print(f"minimal_flight: cannot open {args.port}: {exc}", file=sys.stderr)
        return 1
    link = Link(port)
    config: dict | None = None
    pending: dict[str, dict] = {}
    next_beat, beats = 0.0, 0
    ready: deque[tuple[dict, dict, int]] = deque()  # pairs whose frames are all in, with their Config and session
    work: tuple[dict, dict, int, float, Future] | None = None  # the pair the detector is on, since when
    try:
        while not link.closed_by_peer:
            for mtype, msg in link.poll():
                if mtype == HELLO_MSG:  # the ground (or the HIL server) says Hello: answer once ready
                    # a new ground session: the last one's half-received pairs will never complete (docs/hil.md)
                    pending.clear()
                    ready.clear()
                    link.send(
                        HELLO_MSG,
                        {
                            "role": "flight",
                            "protocol_version": PROTOCOL,
                            "software": "minimal_flight",
                            "session": link.local,
                        },
                    )
                elif mtype == CONFIG:
                    config = msg
                elif mtype == FRAME_MSG and config is not None:
                    pair = pending.setdefault(msg["pair_id"], {})
                    pair[msg["frame_index"]] = msg
                    if len(pair) == 2:
                        del pending[msg["pair_id"]]
                        ready.append((pair, config, link.local))
                elif mtype == FRAME_MSG:  # a frame before any Config
                    link.send(ERROR, {"code": "no_config", "text": "frame before Config", "seq": msg["seq"]})
            while work is None and ready:  # one pair at a time, in the order their frames completed
                pair, cfg, session = ready.popleft()
                if session == link.local:  # not an earlier ground's pair, which no one would read
                    work = (pair, cfg, session, time.monotonic(), detect(pair, cfg))
            if work is not None and work[4].done():
                pair, cfg, session, t0, future = work
                work = None
                if session == link.local:  # its ground is still the one attached (a new session has a new id)
                    for mtype, fields in answered(pair, cfg, t0, future):
                        link.send(mtype, fields)
            now = time.monotonic()
            if now >= next_beat:  # any message at least every second: the HIL server's watchdog listens
                beats += 1
                link.datagram(HEARTBEAT, {"time_s": now, "counter": beats})
                next_beat = now + 0.5
    except (serial.SerialException, OSError):  # the line went away (the HIL server closed its end)
        return 0
    finally:
        port.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
