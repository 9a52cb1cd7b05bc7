#!/usr/bin/env python3
"""The minimal flight program of ``minimal_flight.py`` over ZeroMQ, written from docs/protocol.md alone.

It binds a ZeroMQ PAIR socket (section 7), with CURVE when given a key directory, runs the session layer (the
16-byte header, the HELLO handshake and its 1 s keepalive, rising message numbers, CLOSE) and answers every
pair with ``minimal_flight.answer()``: everything unknown. Replace that function with your own detector.

    hazard-hil keys keys/                                                     # one key set for both ends
    python examples/minimal_flight_zmq.py --endpoint tcp://*:5555 --keys keys/       # on the board
    hazard-hil run --flight external --link zmq:tcp://BOARD:5555 --keys keys/        # on the ground PC

On one machine, without keys: ``--endpoint tcp://127.0.0.1:5555 --insecure`` on both ends.

It imports nothing from hazard-hil (only the message helpers of ``minimal_flight.py`` beside it): pyzmq,
msgpack and numpy are all it needs. The detector runs in a thread of its own, one pair at a time, while the
main loop keeps the session up (a HELLO each second): a detector slower than the ground's link timeout (4 s)
does not lose the session, though its pairs miss their deadlines.
"""

from __future__ import annotations

import argparse
import random
import struct
import sys
import time
from collections import deque
from collections.abc import Callable
from pathlib import Path

import msgpack
import numpy as np
import zmq
import zmq.auth
from zmq.auth.thread import ThreadAuthenticator

sys.path.insert(0, str(Path(__file__).resolve().parent))
try:
    import minimal_flight as mf  # the message layer is the serial program's, unchanged
except ImportError as exc:  # copied to a board alone: say what is missing, not a traceback
    sys.exit(f"minimal_flight_zmq.py: needs minimal_flight.py beside it, for its messages ({exc})")

HEAD = struct.Struct(">BBBBIII")  # version, kind, type, flags, src_session, dst_session, seq (section 7)
MSG, HELLO, CLOSE = 1, 4, 5
KEEPALIVE_S = 1.0  # a HELLO at least this often keeps the session (section 2 rule 4)
PEER_TIMEOUT_S = 4.0  # nothing from the peer for this long: the session is lost (section 2 rule 7)


def ext_hook(parts: list[bytes]):
    """Section 5.2 arrays: ext 1 and 3 as on the serial line, and ext 2, the array in ZeroMQ frame 2 + index."""

    def hook(code: int, data: bytes):
        if code != 2:
            return mf.ext_hook(code, data)
        dt = np.dtype(mf.DTYPES[data[0]])
        ndim = data[1]
        shape = struct.unpack(f">{ndim}I", data[2 : 2 + 4 * ndim])
        (index,) = struct.unpack(">I", data[2 + 4 * ndim : 6 + 4 * ndim])
        return np.frombuffer(parts[2 + index], dt).reshape(shape)

    return hook


class Session:
    """One ground at a time: its session id, ours, and the numbers of the messages both ways."""

    def __init__(self, listen: Callable[[], zmq.Socket]) -> None:
        self.listen = listen
        self.sock = listen()
        self.local = random.randint(1, 2**32 - 1)  # never 0: 0 means "no session yet"
        self.peer = 0
        self.seq = 0  # the last message number we used (each message: one more, from 1)
        self.peer_seq = 0  # the last one we took from the peer
        self.heard = time.monotonic()
        self.said = 0.0
        self.epoch = 0  # sessions so far: a new one starts with no Config and no frames held

    def give_up(self, reason: str) -> None:
        """End this session (section 2 rule 7): CLOSE code 1 to the peer, and a new session id for the next one,
        so that a ground that was only stalled starts afresh rather than meet numbers it has already seen."""
        if self.peer:
            self.put([HEAD.pack(2, CLOSE, 0, 0, self.local, self.peer, 0), bytes((1,)) + reason.encode()[:255]])
        self.local, self.peer, self.seq, self.peer_seq = random.randint(1, 2**32 - 1), 0, 0, 0
        self.epoch += 1
        # a PAIR socket keeps the old ground's connection, and never attaches one it refused meanwhile: listen
        # anew, so that whoever dials next is served
        self.sock.close()
        self.sock = self.listen()

    def put(self, parts: list[bytes]) -> None:
        """Send without waiting: a PAIR socket whose ground has gone blocks a send for good (the board then never
        read again). What cannot go now is lost, and the session times out as section 2 says."""
        try:
            self.sock.send_multipart(parts, flags=zmq.NOBLOCK)
        except zmq.Again:
            pass

    def hello(self) -> None:  # type and seq 0: a HELLO numbers no message
        self.put([HEAD.pack(2, HELLO, 0, 0, self.local, self.peer, 0)])
        self.said = time.monotonic()

    def send(self, mtype: int, fields: dict) -> None:
        self.seq += 1
        self.put([HEAD.pack(2, MSG, mtype, 0, self.local, self.peer, self.seq), mf.body(mtype, fields)])

    def receive(self, parts: list[bytes]) -> tuple[int, dict] | None:
        """A message of the session, or None (a HELLO, a CLOSE, another session's frame, a repeat)."""
        if len(parts[0]) != HEAD.size:
            return None
        version, kind, mtype, _, src, dst, seq = HEAD.unpack(parts[0])
        if version != 2:
            return None
        if kind == HELLO:
            if src != self.peer:  # a new ground (or the same one restarted): a new session
                self.peer, self.peer_seq, self.seq = src, 0, 0
                self.epoch += 1
            self.heard = time.monotonic()
            if dst != self.local:  # it does not know us yet: answer at once
                self.hello()
            return None
        if src != self.peer or dst != self.local:
            return None
        self.heard = time.monotonic()
        if kind == CLOSE:  # the ground ended the session: the next one is new on both sides
            self.peer = 0
            self.give_up("")
            return None
        if kind != MSG or seq <= self.peer_seq:
            return None
        self.peer_seq = seq
        got = msgpack.unpackb(parts[1], ext_hook=ext_hook(parts), raw=False, strict_map_key=False)
        return int(got[0]), got[1]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--endpoint",
        default="tcp://*:5555",
        help="where to bind (default tcp://*:5555; with --insecure give a loopback one)",
    )
    ap.add_argument("--keys", type=Path, help="key directory of `hazard-hil keys`: CURVE, clients/ allowed")
    ap.add_argument("--insecure", action="store_true", help="no CURVE (loopback only)")
    args = ap.parse_args(argv)
    if (args.keys is None) == (not args.insecure):
        ap.error("give --keys DIR (CURVE) or --insecure (loopback only)")
    host = args.endpoint.removeprefix("tcp://").rpartition(":")[0]
    if args.insecure and host not in ("127.0.0.1", "localhost", "[::1]"):  # anyone on the network could drive it
        ap.error(f"--insecure binds on loopback only (tcp://127.0.0.1:PORT), not {args.endpoint}; use --keys DIR")
    ctx = zmq.Context()
    auth = None
    if args.keys is not None:
        try:
            public, secret = zmq.auth.load_certificate(str(args.keys / "server.key_secret"))
        except (OSError, ValueError) as exc:
            ap.error(f"cannot read the server key in {args.keys} ({exc}): make one with `hazard-hil keys DIR`")
        auth = ThreadAuthenticator(ctx)
        auth.start()
        auth.configure_curve(domain="*", location=str(args.keys / "clients"))

    def listen() -> zmq.Socket:
        sock = ctx.socket(zmq.PAIR)
        sock.linger = 0
        if args.keys is not None:
            sock.curve_secretkey, sock.curve_publickey, sock.curve_server = secret, public, True
        for _ in range(50):  # the port of a socket just closed is free again within moments
            try:
                sock.bind(args.endpoint)
                return sock
            except zmq.ZMQError:
                time.sleep(0.05)
        sock.bind(args.endpoint)  # still taken: say why
        return sock

    try:
        s = Session(listen)
    except zmq.ZMQError as exc:  # the port is another program's
        if auth is not None:
            auth.stop()
        ctx.destroy(linger=0)
        print(f"minimal_flight_zmq: cannot bind {args.endpoint}: {exc}", file=sys.stderr)
        return 1
    print(f"minimal_flight_zmq: listening on {args.endpoint}", file=sys.stderr, flush=True)
    config: dict | None = None
    pending: dict[str, dict] = {}
    epoch = 0
    ready: deque[tuple[dict, dict, int]] = deque()  # pairs whose frames are all in, with their Config and session
    work = None  # the pair the detector is on: (pair, config, session, start, future)
    try:
        while True:
            if s.sock.poll(50):
                got = s.receive(s.sock.recv_multipart())
                if s.epoch != epoch:  # another session: what the last one sent is not this one's
                    config, pending, epoch = None, {}, s.epoch
                mtype, msg = got if got is not None else (0, {})
                if mtype == mf.HELLO_MSG:  # the ground's Hello message: ours in reply
                    pending.clear()  # a new ground session's Hello: the last one's half pairs never complete
                    hello = {"role": "flight", "protocol_version": mf.PROTOCOL, "software": "minimal_flight_zmq"}
                    s.send(mf.HELLO_MSG, {**hello, "session": s.local})
                elif mtype == mf.CONFIG:
                    config = msg
                elif mtype == mf.FRAME_MSG and config is not None:
                    pair = pending.setdefault(msg["pair_id"], {})
                    pair[msg["frame_index"]] = msg
                    if len(pair) == 2:
                        del pending[msg["pair_id"]]
                        ready.append((pair, config, epoch))
                elif mtype == mf.FRAME_MSG:  # a frame before any Config
                    s.send(mf.ERROR, {"code": "no_config", "text": "frame before Config", "seq": msg["seq"]})
            while work is None and ready:  # the detector runs beside the link, which keeps the session up meanwhile
                pair, cfg, of = ready.popleft()
                if of == s.epoch:  # not an earlier ground's pair, which no one would read
                    work = (pair, cfg, of, time.monotonic(), mf.detect(pair, cfg))  # mf.answer: your detector
            if work is not None and work[4].done():
                pair, cfg, of, t0, future = work
                work = None
                if of == s.epoch:  # its ground is still the one attached
                    for mtype, fields in mf.answered(pair, cfg, t0, future):
                        s.send(mtype, fields)
            now = time.monotonic()
            if s.peer and now - s.heard > PEER_TIMEOUT_S:  # the ground went away: wait for the next one
                s.give_up(f"no message from the ground for {now - s.heard:.1f} s")
            if s.peer and now - s.said >= KEEPALIVE_S:
                s.hello()
    except KeyboardInterrupt:
        return 0
    finally:
        s.sock.close()
        if auth is not None:
            auth.stop()
        ctx.term()


if __name__ == "__main__":
    sys.exit(main())
