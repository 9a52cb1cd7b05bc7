"""Links: one interface over a serial line, any byte stream, or ZeroMQ.

Every link has ``send(message) -> seq``, ``recv(timeout) -> Message | None``,
``close()``, ``stats`` (a dict snapshot) and ``failures()``. ``send`` is
thread-safe (a heartbeat thread and the main loop may both call it).

Byte-stream links (:class:`SerialLink`, :class:`StreamLink`) use the framing
of :mod:`protocol.framing` and give these delivery guarantees:

* every packet carries a link sequence number; duplicates are dropped;
* messages of a *reliable* type (default: everything but Heartbeat/Ack/Nack)
  ask for an Ack and are retransmitted after ``ack_timeout`` seconds (timer
  started when the last byte was written), up to ``max_attempts`` sends;
* one reliable message is in flight at a time (stop-and-wait), so reliable
  messages arrive in order even across retransmissions - ``send`` of the
  next reliable message blocks until the previous one is resolved;
* every reliable message ends as delivered (``outcome(seq) == "delivered"``)
  or as a :class:`DeliveryFailure` with a reason - never silently lost.

Threads: a reader (bytes -> decoder -> acks/dedup -> receive queue; also the
retransmit timer and the partial-frame timeout) and a writer (a priority
queue: acks jump ahead of data, so two peers both busy sending big frames
cannot deadlock on each other's acks). ``baud`` paces writes at 10 bits per
byte (8N1) because a pty has no baud rate; ``None`` means unlimited.

How two processes connect over a pty (no socat needed)::

    bridge = PtyBridge()                    # parent: two raw ptys + relay thread(s)
    # child A: SerialLink(bridge.paths[0])  # child B: SerialLink(bridge.paths[1])

or with one pty pair: the parent keeps ``master_fd`` from
:func:`protocol.faults.open_pty_pair` and wraps it in ``StreamLink(master_fd)``
while the child opens ``SerialLink(slave_path)``.
"""

from __future__ import annotations

import heapq
import itertools
import os
import queue
import select
import socket
import struct
import threading
import time
from collections import deque
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

from protocol.codec import DEFAULT_LIMITS, CodecError, Limits, decode_parts, encode_message, encode_parts
from protocol.errors import InputError
from protocol.framing import FLAG_ACK_REQ, Packet, StreamDecoder, frame_payload
from protocol.messages import Ack, Heartbeat, Message, Nack, message_class

UNRELIABLE_TYPES = frozenset({Heartbeat.TYPE, Ack.TYPE, Nack.TYPE})
BITS_PER_BYTE = 10  # 8N1: start + 8 data + stop


class LinkClosed(InputError):
    """send() on a link that has been closed or whose transport failed."""


@dataclass(frozen=True)
class DeliveryFailure:
    """A reliable message that was not acknowledged, and why."""

    seq: int
    message_type: str
    reason: str


@dataclass
class _Pending:
    seq: int
    data: bytes
    type_name: str
    attempts: int = 1
    sent_at: float | None = None  # None while queued / being written


class Link:
    """Shared bookkeeping: sequence numbers, stats, dedup, receive queue, failures."""

    def __init__(self, name: str = "") -> None:
        self.name = name
        self._seq = itertools.count(1)
        self._seq_lock = threading.Lock()
        self._rx: queue.Queue[Packet] = queue.Queue()
        self._seen: set[int] = set()
        self._seen_order: deque[int] = deque()
        self._failures: list[DeliveryFailure] = []
        self._outcomes: dict[int, str] = {}
        self._closed = threading.Event()
        self._stats_lock = threading.Lock()
        self._stats: dict[str, float] = dict.fromkeys(
            (
                "bytes_sent",
                "bytes_received",
                "frames_sent",
                "frames_received",
                "retransmits",
                "crc_errors",
                "malformed",
                "oversize",
                "decode_errors",
                "resyncs",
                "bytes_discarded",
                "frame_timeouts",
                "duplicates_dropped",
                "acks_sent",
                "acks_received",
                "delivered",
                "failures",
                "busy_s",
            ),
            0,
        )

    def _next_seq(self) -> int:
        with self._seq_lock:
            return next(self._seq) & 0xFFFFFFFF

    def _count(self, key: str, n: float = 1) -> None:
        with self._stats_lock:
            self._stats[key] = self._stats.get(key, 0) + n

    @property
    def stats(self) -> dict[str, float]:
        with self._stats_lock:
            return dict(self._stats)

    def failures(self) -> list[DeliveryFailure]:
        with self._stats_lock:
            return list(self._failures)

    def outcome(self, seq: int) -> str | None:
        """``"delivered"``, ``"failed: <reason>"``, ``"pending"`` or None (unknown/unreliable seq)."""
        with self._stats_lock:
            return self._outcomes.get(seq)

    def _resolve(self, seq: int, type_name: str, failure: str | None) -> None:
        with self._stats_lock:
            if failure is None:
                self._outcomes[seq] = "delivered"
                self._stats["delivered"] += 1
            else:
                self._outcomes[seq] = f"failed: {failure}"
                self._failures.append(DeliveryFailure(seq, type_name, failure))
                self._stats["failures"] += 1

    def _accept(self, packet: Packet) -> bool:
        """Dedup by link sequence number; True if new."""
        if packet.seq in self._seen:
            self._count("duplicates_dropped")
            return False
        self._seen.add(packet.seq)
        self._seen_order.append(packet.seq)
        if len(self._seen_order) > 8192:
            self._seen.discard(self._seen_order.popleft())
        self._count("frames_received")
        return True

    def recv_packet(self, timeout: float | None = None) -> Packet | None:
        try:
            return self._rx.get(timeout=timeout) if timeout is None or timeout > 0 else self._rx.get_nowait()
        except queue.Empty:
            return None

    def recv(self, timeout: float | None = None) -> Message | None:
        """Next received message, or None after ``timeout`` seconds (``None`` waits forever)."""
        p = self.recv_packet(timeout)
        return None if p is None else p.message

    def send(self, message: Message) -> int:  # pragma: no cover - abstract
        raise NotImplementedError

    def close(self) -> None:  # pragma: no cover - abstract
        raise NotImplementedError

    def __enter__(self) -> Link:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


class ByteStreamLink(Link):
    """Framed, acknowledged link over a byte stream; subclasses supply ``_read``/``_write``."""

    def __init__(
        self,
        *,
        baud: float | None = None,
        reliable_types: Iterable[int] | None = None,
        ack_timeout: float = 1.0,
        max_attempts: int = 6,
        frame_timeout: float = 2.0,
        acks: bool = True,
        limits: Limits = DEFAULT_LIMITS,
        name: str = "",
    ) -> None:
        super().__init__(name)
        if baud is not None and baud <= 0:
            raise InputError(f"baud must be positive or None, got {baud}")
        if max_attempts < 1 or ack_timeout <= 0:
            raise InputError("max_attempts must be >= 1 and ack_timeout > 0")
        self.baud = baud
        self.acks = acks
        self.ack_timeout = ack_timeout
        self.max_attempts = max_attempts
        self.frame_timeout = frame_timeout
        self._reliable = frozenset(reliable_types) if reliable_types is not None else None
        self._decoder = StreamDecoder(limits.max_message_bytes, limits)
        self._cond = threading.Condition()
        self._inflight: _Pending | None = None
        self._wq: list[tuple[int, int, bytes | None, int | None]] = []
        self._wq_count = itertools.count()
        self._wq_cond = threading.Condition()
        self._writing = False
        self._error: str | None = None
        self._reader = threading.Thread(target=self._reader_loop, name=f"{name or 'link'}-rx", daemon=True)
        self._writer = threading.Thread(target=self._writer_loop, name=f"{name or 'link'}-tx", daemon=True)

    def _start(self) -> None:
        self._reader.start()
        self._writer.start()

    # transport hooks ------------------------------------------------------
    def _read(self, timeout: float) -> bytes:  # pragma: no cover - abstract
        raise NotImplementedError

    def _write(self, data: bytes) -> None:  # pragma: no cover - abstract
        raise NotImplementedError

    def _close_transport(self) -> None:  # pragma: no cover - abstract
        raise NotImplementedError

    # sending --------------------------------------------------------------
    def is_reliable(self, message: Message) -> bool:
        if not self.acks:
            return False
        return message.TYPE in self._reliable if self._reliable is not None else message.TYPE not in UNRELIABLE_TYPES

    def _enqueue(self, priority: int, data: bytes | None, seq: int | None = None) -> None:
        with self._wq_cond:
            heapq.heappush(self._wq, (priority, next(self._wq_count), data, seq))
            self._wq_cond.notify()

    def send(self, message: Message, timeout: float | None = None) -> int:
        """Queue ``message``; returns its link sequence number.

        For a reliable message this first waits (up to ``timeout``) until the
        previous reliable message is acknowledged or failed.
        """
        if self._closed.is_set() or self._error:
            raise LinkClosed(f"link {self.name!r} is closed{': ' + self._error if self._error else ''}")
        body = encode_message(message)  # schema errors surface here, in the caller
        reliable = self.is_reliable(message)
        seq = self._next_seq()
        data = frame_payload(message.TYPE, seq, body, FLAG_ACK_REQ if reliable else 0)
        if reliable:
            with self._cond:
                if not self._cond.wait_for(lambda: self._inflight is None or self._closed.is_set(), timeout):
                    raise TimeoutError(f"link {self.name!r}: previous reliable message still unacknowledged")
                if self._closed.is_set():
                    raise LinkClosed(f"link {self.name!r} closed while waiting to send")
                self._inflight = _Pending(seq, data, type(message).__name__)
                with self._stats_lock:
                    self._outcomes[seq] = "pending"
        self._enqueue(1, data, seq if reliable else None)
        return seq

    def flush(self, timeout: float | None = None) -> bool:
        """Wait until everything queued is written and the in-flight message resolved."""
        deadline = None if timeout is None else time.monotonic() + timeout
        with self._wq_cond:
            if not self._wq_cond.wait_for(lambda: not self._wq and not self._writing, timeout):
                return False
        left = None if deadline is None else max(0.0, deadline - time.monotonic())
        with self._cond:
            return self._cond.wait_for(lambda: self._inflight is None, left)

    def _write_paced(self, data: bytes) -> None:
        if self.baud is None:
            self._write(data)
            return
        chunk = max(16, int(self.baud / BITS_PER_BYTE * 0.02))  # ~20 ms slices
        t0 = time.monotonic()
        for i in range(0, len(data), chunk):
            self._write(data[i : i + chunk])
            wait = t0 + (i + len(data[i : i + chunk])) * BITS_PER_BYTE / self.baud - time.monotonic()
            if wait > 0:
                time.sleep(wait)

    def _writer_loop(self) -> None:
        while True:
            with self._wq_cond:
                self._wq_cond.wait_for(lambda: bool(self._wq))
                _, _, data, seq = heapq.heappop(self._wq)
                self._writing = data is not None
            if data is None:
                return
            t0 = time.monotonic()
            try:
                self._write_paced(data)
            except (OSError, ValueError) as exc:  # pyserial raises SerialException (an OSError)
                self._error = f"write failed: {exc}"
                self._fail_inflight(self._error)
            finally:
                with self._wq_cond:
                    self._writing = False
                    self._wq_cond.notify_all()
            self._count("busy_s", time.monotonic() - t0)
            self._count("bytes_sent", len(data))
            self._count("frames_sent")
            if seq is not None:
                with self._cond:
                    if self._inflight is not None and self._inflight.seq == seq:
                        self._inflight.sent_at = time.monotonic()

    # receiving ------------------------------------------------------------
    def _fail_inflight(self, reason: str, seq: int | None = None) -> None:
        with self._cond:
            p = self._inflight
            if p is None or (seq is not None and p.seq != seq):
                return
            self._inflight = None
            self._resolve(p.seq, p.type_name, reason)
            self._cond.notify_all()

    def _handle(self, p: Packet) -> None:
        msg = p.message
        if isinstance(msg, (Ack, Nack)):
            self._count("acks_received")
            with self._cond:
                cur = self._inflight
                if cur is None or cur.seq != msg.seq:
                    return  # late ack of something already resolved
                self._inflight = None
                self._resolve(cur.seq, cur.type_name, None if isinstance(msg, Ack) else f"peer rejected: {msg.reason}")
                self._cond.notify_all()
            return
        if p.wants_ack:  # ack every copy: the previous ack may have been lost
            self._enqueue(0, frame_payload(Ack.TYPE, self._next_seq(), encode_message(Ack(seq=p.seq))))
            self._count("acks_sent")
        if self._accept(p):
            self._rx.put(p)

    def _check_retransmit(self, now: float) -> None:
        with self._cond:
            p = self._inflight
            if p is None or p.sent_at is None or now - p.sent_at < self.ack_timeout:
                return
            if p.attempts >= self.max_attempts:
                self._inflight = None
                self._resolve(
                    p.seq, p.type_name, f"no ack after {p.attempts} attempts ({self.ack_timeout:g} s timeout each)"
                )
                self._cond.notify_all()
                return
            p.attempts += 1
            p.sent_at = None
        self._count("retransmits")
        self._enqueue(1, p.data, p.seq)

    def _sync_decoder_stats(self) -> None:
        with self._stats_lock:
            for k in ("crc_errors", "malformed", "oversize", "decode_errors", "resyncs", "bytes_discarded"):
                self._stats[k] = self._decoder.stats[k]

    def _reader_loop(self) -> None:
        last_rx = time.monotonic()
        while not self._closed.is_set():
            try:
                data = self._read(0.05)
            except (OSError, ValueError, TypeError) as exc:
                if self._closed.is_set():
                    return
                self._error = f"read failed: {exc}"
                self._fail_inflight(self._error)
                return
            now = time.monotonic()
            if data:
                last_rx = now
                self._count("bytes_received", len(data))
                for p in self._decoder.feed_packets(data):
                    self._handle(p)
                for rej in self._decoder.take_rejected():
                    if rej.flags & FLAG_ACK_REQ:
                        self._enqueue(
                            0,
                            frame_payload(
                                Nack.TYPE, self._next_seq(), encode_message(Nack(seq=rej.seq, reason=rej.reason[:4000]))
                            ),
                        )
                self._sync_decoder_stats()
            elif self._decoder.pending_bytes and now - last_rx > self.frame_timeout:
                self._decoder.expire_partial()
                self._count("frame_timeouts")
                self._sync_decoder_stats()
            self._check_retransmit(now)

    def close(self, flush_timeout: float = 1.0) -> None:
        """Flush (bounded), stop the threads, fail whatever is still in flight, close the transport."""
        if self._closed.is_set():
            return
        if self._error is None and self._writer.is_alive():
            self.flush(flush_timeout)
        self._closed.set()
        self._enqueue(-1, None)
        self._writer.join(timeout=2.0)
        self._reader.join(timeout=2.0)
        self._fail_inflight("link closed before the message was acknowledged")
        with self._cond:
            self._cond.notify_all()
        self._close_transport()


class StreamLink(ByteStreamLink):
    """Framed link over a connected socket, a pty master fd, or an fd pair (``os.pipe``).

    ``StreamLink(sock)`` / ``StreamLink(fd)`` / ``StreamLink(read_fd, write_fd)``. No baud
    pacing by default; ``acks=False`` turns off acknowledgement for a lossless local stream.
    """

    def __init__(
        self, rx: int | socket.socket, tx: int | socket.socket | None = None, *, close_fds: bool = True, **kw: Any
    ) -> None:
        super().__init__(**kw)
        self._objs = (rx, tx)  # keep socket objects alive
        self._rfd = rx.fileno() if isinstance(rx, socket.socket) else int(rx)
        self._wfd = self._rfd if tx is None else (tx.fileno() if isinstance(tx, socket.socket) else int(tx))
        self._close_fds = close_fds
        self._eof = False
        self._start()

    def _read(self, timeout: float) -> bytes:
        if self._eof:
            time.sleep(timeout)
            return b""
        r, _, _ = select.select([self._rfd], [], [], timeout)
        if not r:
            return b""
        try:
            data = os.read(self._rfd, 1 << 16)
        except OSError as exc:
            if exc.errno == 5:  # EIO: pty slave not (yet / any more) open
                time.sleep(timeout)
                return b""
            raise
        if not data:
            self._eof = True
        return data

    def _write(self, data: bytes) -> None:
        mv = memoryview(data)
        while mv:
            n = os.write(self._wfd, mv)
            mv = mv[n:]

    def _close_transport(self) -> None:
        if not self._close_fds:
            return
        for obj in self._objs:
            if isinstance(obj, socket.socket):
                obj.close()
        for fd in {self._rfd, self._wfd}:
            if not any(isinstance(o, socket.socket) for o in self._objs):
                try:
                    os.close(fd)
                except OSError:
                    pass


class SerialLink(ByteStreamLink):
    """Framed, acknowledged link over pyserial: ``/dev/ttyUSB0``, a pty slave path, or ``loop://``.

    ``baud`` paces writes in software (a pty ignores the line rate); ``None`` is unlimited.
    The port's own reads use a short timeout and our frame timeout, never
    ``inter_byte_timeout`` or DTR (both unreliable on ptys).
    """

    def __init__(self, port: str, baud: float | None = None, **kw: Any) -> None:
        import serial

        super().__init__(baud=baud, **kw)
        try:
            self._ser = serial.serial_for_url(
                port, baudrate=int(baud or 115200), timeout=0.05, write_timeout=None, dsrdtr=False, rtscts=False
            )
        except (serial.SerialException, ValueError) as exc:
            raise InputError(f"cannot open serial port {port!r}: {exc}") from None
        self.port = port
        self._start()

    def _read(self, timeout: float) -> bytes:
        self._ser.timeout = timeout
        first = self._ser.read(1)  # short read on timeout is normal
        if not first:
            return b""
        n = self._ser.in_waiting
        return first + (self._ser.read(n) if n else b"")

    def _write(self, data: bytes) -> None:
        self._ser.write(data)

    def _close_transport(self) -> None:
        try:
            self._ser.close()
        except OSError:
            pass


_ZHEAD = struct.Struct(">BBHI")  # version, type, flags, seq


class ZmqLink(Link):
    """ZeroMQ PAIR link: multipart ``[header, msgpack body, *array buffers]``.

    Arrays of at least ``oob_min_bytes`` go as separate zero-copy frames
    (``copy=False``), smaller ones inline. TCP gives integrity and order, so
    there are no acks; sequence numbers still let the receiver drop
    duplicates. ``MAXMSGSIZE`` and high-water marks bound what a peer can make
    us buffer; a send that cannot complete within ``send_timeout`` is
    reported in :meth:`failures`.

    Every send is tracked (``track=True``) so :meth:`flush` means "handed to
    the kernel", and each link owns its context, terminated on close: libzmq
    must have released every zero-copy buffer before the interpreter may free
    it (exiting with frames still queued otherwise crashes the process in the
    I/O thread - "Bad address" - under load).
    """

    def __init__(
        self,
        endpoint: str,
        bind: bool,
        *,
        hwm: int = 256,
        send_timeout: float = 30.0,
        oob_min_bytes: int = 64 << 10,
        limits: Limits = DEFAULT_LIMITS,
        name: str = "",
    ) -> None:
        import zmq

        super().__init__(name)
        self._zmq = zmq
        self.limits = limits
        self.oob_min_bytes = oob_min_bytes
        self._ctx = zmq.Context(io_threads=1)
        self._sock = self._ctx.socket(zmq.PAIR)
        for opt, val in (
            (zmq.MAXMSGSIZE, limits.max_message_bytes + (1 << 20)),
            (zmq.SNDHWM, hwm),
            (zmq.RCVHWM, hwm),
            (zmq.LINGER, 1000),
            (zmq.SNDTIMEO, int(send_timeout * 1000)),
        ):
            self._sock.setsockopt(opt, val)
        self._sock.copy_threshold = 0  # track every frame, so flush() covers small messages too
        try:
            (self._sock.bind if bind else self._sock.connect)(endpoint)
        except zmq.ZMQError as exc:
            self._sock.close(0)
            self._ctx.term()
            raise InputError(f"cannot {'bind' if bind else 'connect'} {endpoint!r}: {exc}") from None
        self.endpoint = self._sock.getsockopt_string(zmq.LAST_ENDPOINT) if bind else endpoint
        self._lock = threading.Lock()
        self._trackers: deque[tuple[int, str, Any]] = deque()  # (seq, type name, zmq.MessageTracker)

    def send(self, message: Message, timeout: float | None = None) -> int:
        if self._closed.is_set():
            raise LinkClosed(f"link {self.name!r} is closed")
        body, bufs = encode_parts(message, self.oob_min_bytes)
        seq = self._next_seq()
        head = _ZHEAD.pack(1, message.TYPE, 0, seq)
        t0 = time.monotonic()
        with self._lock:
            try:
                parts: list[Any] = [head, body, *bufs]
                trackers = [
                    self._sock.send(part, self._zmq.SNDMORE if i < len(parts) - 1 else 0, copy=False, track=True)
                    for i, part in enumerate(parts)
                ]
                tracker = self._zmq.MessageTracker(*trackers)
            except self._zmq.Again:
                self._resolve(
                    seq, type(message).__name__, "send timed out: peer not connected or not draining (high-water mark)"
                )
                return seq
            self._trackers.append((seq, type(message).__name__, tracker))
            while self._trackers and self._trackers[0][2].done:
                self._trackers.popleft()
        self._count("busy_s", time.monotonic() - t0)
        self._count("bytes_sent", len(head) + len(body) + sum(b.nbytes for b in bufs))
        self._count("frames_sent")
        return seq

    def _poll_one(self) -> None:
        zmq = self._zmq
        try:
            parts = self._sock.recv_multipart(flags=zmq.NOBLOCK, copy=False)
        except zmq.Again:
            return
        self._count("bytes_received", sum(len(p.buffer) for p in parts))
        try:
            if len(parts) < 2 or len(parts[0].buffer) != _ZHEAD.size:
                raise CodecError(f"bad multipart shape ({len(parts)} parts)")
            version, type_code, flags, seq = _ZHEAD.unpack(parts[0].buffer)
            if version != 1:
                raise CodecError(f"unsupported wire version {version}")
            message_class(type_code)
            msg = decode_parts(parts[1].buffer, [p.buffer for p in parts[2:]], self.limits, expect_type=type_code)
        except InputError:
            self._count("decode_errors")
            return
        p = Packet(seq, flags, msg)
        if self._accept(p):
            self._rx.put(p)

    def recv_packet(self, timeout: float | None = None) -> Packet | None:
        deadline = None if timeout is None else time.monotonic() + timeout
        while not self._closed.is_set():
            p = super().recv_packet(0)
            if p is not None:
                return p
            with self._lock:
                ready = self._sock.poll(20)
                if ready:
                    self._poll_one()
            if self._rx.empty() and deadline is not None and time.monotonic() >= deadline:
                return None
        return None

    def flush(self, timeout: float | None = None) -> bool:
        """Wait until every message sent so far has left this process (True) or ``timeout`` passes."""
        deadline = None if timeout is None else time.monotonic() + timeout
        with self._lock:
            pending = list(self._trackers)
        for _, _, tracker in pending:
            left = None if deadline is None else max(0.0, deadline - time.monotonic())
            try:
                tracker.wait(left)
            except self._zmq.NotDone:
                return False
        return True

    def close(self, flush_timeout: float = 5.0) -> None:
        """Flush (bounded), report what never left as failures, close and terminate the context."""
        if self._closed.is_set():
            return
        self.flush(flush_timeout)
        self._closed.set()
        with self._lock:
            for seq, type_name, tracker in self._trackers:
                if not tracker.done:
                    self._resolve(seq, type_name, "link closed before the message left this process")
            self._sock.close(linger=1000)
            self._ctx.term()  # returns once libzmq has released every buffer it still held
            self._trackers.clear()
