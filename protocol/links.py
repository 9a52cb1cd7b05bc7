"""Links: one interface over a serial line, any byte stream, or ZeroMQ (docs/protocol.md).

Every link has ``send(message, timeout) -> id``, ``recv(timeout) -> Message |
None``, ``recv_packet(timeout) -> Received | None`` (the message with its
reception times), ``flush(timeout)``, ``close()``, ``stats`` (a dict
snapshot), ``failures()``, ``outcome(id)``, ``times(id)``,
``take_refusals()`` (type code, reason and time of each message refused from the
peer: over the size limit, of an unknown type, failing to decode or the
schema) and the session state: ``established``, ``epoch`` (sessions so far),
``wait_established()``, ``events()``. ``send`` is thread-safe; it raises
:class:`InputError` for a message over ``limits.max_message_bytes`` (nothing
is sent).

Every blocking call has a timeout: ``send`` waits for buffer space at most
``timeout``, ``recv``/``flush``/``wait_established`` take one, writes time out
after ``write_timeout`` (a frame that cannot be written counts as lost), the
handshake and reassembly are bounded by the session timers of
:class:`protocol.arq.ArqConfig`. A peer that stops reading, goes silent or
closes ends the session within ``peer_timeout`` (default 4 s): every message
in flight fails with the reason (:meth:`Link.failures`), an event says so, and
the link waits for a new session (a restarted peer resynchronises). Only a
broken transport (EOF, device gone) or :meth:`Link.close` ends a link for good:
``send`` then raises :class:`LinkClosed` and ``recv`` raises it once the
received messages are drained.

Byte-stream links (:class:`SerialLink`, :class:`StreamLink`) run
:class:`protocol.arq.Arq` (segmentation, selective repeat, sessions) with a
reader and a writer thread; ``baud`` paces writes at 10 bits per byte (8N1),
the frame leaving when the line would have carried its last byte.
:class:`ZmqLink` carries whole messages as multipart ZeroMQ messages with
CURVE authentication, one peer per session, and the same session rules.

How two processes connect over a pty (no socat needed)::

    bridge = PtyBridge()                    # parent: two raw ptys + relay thread(s)
    # child A: SerialLink(bridge.paths[0])  # child B: SerialLink(bridge.paths[1])
"""

from __future__ import annotations

import dataclasses
import errno
import fcntl
import ipaddress
import math
import os
import queue
import select
import socket
import struct
import threading
import time
from collections import OrderedDict, deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Self

from protocol.arq import (
    POS_MOD,
    REFUSALS_KEPT,
    Arq,
    ArqConfig,
    DeliveryFailure,
    MessageTimes,
    Received,
    Refusal,
    Skipping,
    unwrap,
)
from protocol.codec import DEFAULT_LIMITS, CodecError, Encoded, Limits, decode_parts, encode_message, encode_parts
from protocol.errors import InputError
from protocol.framing import CLOSE_APP, CLOSE_LOST
from protocol.messages import Heartbeat, Message, message_class
from protocol.quiet import Quieter
from protocol.session import SessionState, SessionView
from protocol.stall import OWN_STALL_S, forgiven_hearing

UNRELIABLE_TYPES = frozenset({Heartbeat.TYPE})
# A lossless local socket pair (HIL supervisor <-> flight process): big frames, a big window, and no
# peer timeout - a throttled flight process answers late; the supervisor's heartbeat watchdog judges it.
LOCAL_CONFIG = ArqConfig(max_frame=1 << 16, window=1 << 22, peer_timeout=None, connect_timeout=None, keepalive=5.0)
# The HIL server's side of a `--flight-cmd` program's pty: docs/protocol.md's 1 s keepalive (section 2 rule 6). At
# 5 s a program kept to rule 7's 4 s timeout gave its session up while it computed (QA of stop 79); our own flight
# process, which keeps no peer timeout, is spared the wake-ups.
PTY_CONFIG = dataclasses.replace(LOCAL_CONFIG, keepalive=1.0)
BITS_PER_BYTE = 10  # 8N1: start + 8 data + stop
RX_QUEUE_MESSAGES = 256  # received but not yet taken by recv(): beyond this the reader stops reading
# events a retrying peer repeats (a wrong CURVE key, a second ground on a busy board): said once per
# REPEAT_QUIET_S with a count; every one is still an event and a stat
# how long a reader of a message's times may wait for the writer's record of its last write, when the peer's ACK
# was read first (microseconds after the write, unless that thread was preempted): StreamLink.times(settle_s)
WRITE_RECORD_WAIT_S = 0.2
REPEATING_EVENTS = frozenset({"auth_failed", "refused", "echo", "foreign"})
REPEAT_QUIET_S = 10.0

__all__ = [
    "BITS_PER_BYTE",
    "LOCAL_CONFIG",
    "PTY_CONFIG",
    "ByteStreamLink",
    "DeliveryFailure",
    "Link",
    "LinkClosed",
    "MessageTimes",
    "Received",
    "SerialLink",
    "StreamLink",
    "ZmqLink",
]

Log = Callable[[str], None]


def _say_traceback() -> None:
    """The traceback of the exception being handled, on stderr if it can be written (for whoever fixes the bug)."""
    import traceback

    try:
        traceback.print_exc()
    except Exception:  # stderr a closed pipe: the link's failure reason still names it
        pass


class LinkClosed(InputError):
    """The link was closed or its transport failed; nothing more can be sent or received."""


@dataclass(frozen=True)
class LinkEvent:
    time: float  # monotonic
    kind: str  # established | lost | restarted | closed | refused | auth_failed | transport | relisten | stalled | echo
    text: str
    epoch: int


# the ZMTP handshake's own word for one side with CURVE and the other without (--insecure)
MECHANISM_MISMATCH_TEXT = "security mechanisms differ: one side has CURVE keys, the other runs --insecure"


class Link:
    """Shared bookkeeping: receive queue, events, logging, the common API."""

    def __init__(self, name: str = "", log: Log | None = None) -> None:
        self.name = name
        self._log = log
        self._rx: queue.Queue[Received] = queue.Queue(maxsize=RX_QUEUE_MESSAGES)
        # taken off the line while the queue above was full, in order: the I/O thread never waits for the
        # application (it went deaf, and its peer timed the session out: review of stop 66); flow control bounds it
        self._held: deque[Received] = deque()
        self._events: deque[LinkEvent] = deque(maxlen=256)
        self._closed = threading.Event()
        self._failed: str | None = None  # transport failure: permanent
        self._failing = False  # a transport failure is being said: said before it is seen, so it is never said last
        self.last_error: str | None = None  # the most recent session loss / failure reason
        self._quiet = Quieter(first=1, quiet_s=REPEAT_QUIET_S)  # keyed by (repeating kind, reason)
        self.log_failures = 0  # events the log raised on (kept in events() all the same)

    def _event(self, kind: str, text: str, epoch: int) -> None:
        now = time.monotonic()
        self._events.append(LinkEvent(now, kind, text, epoch))
        if kind in ("lost", "closed", "restarted", "refused", "auth_failed", "transport"):
            self.last_error = text
        if self._log is None:
            return
        if kind in REPEATING_EVENTS:  # a peer that retries (libzmq redials ~10 times a second) must not flood the log
            # keyed by the reason, not the sender (its port changes with every redial): a wrong key hidden
            # behind a mechanism mismatch said a moment earlier would be news lost
            say, quiet, since = self._quiet.offer((kind, text.rsplit(": ", 1)[-1]), now)
            if not say:
                return
            if quiet:
                text += f" ({quiet} more like it, not shown, after the one said {since:.0f} s ago)"
        try:
            self._log(f"link {self.name or '?'}: {kind}: {text}")
        except Exception:  # a log that cannot write (stderr a closed pipe) must not kill the I/O thread
            # that called it: the link went deaf with nothing failed (review of stop 66). The event is kept above
            self.log_failures += 1

    def events(self) -> list[LinkEvent]:
        """Session events so far (and clears them): established, lost, restarted, closed, refused, ..."""
        out = list(self._events)
        self._events.clear()
        return out

    @property
    def failed(self) -> str | None:
        """Why the transport failed for good (None while usable)."""
        return self._failed

    def recv_packet(self, timeout: float | None = None) -> Received | None:
        """Next received message with its reception times, or None after ``timeout`` s."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            left = 0.05 if deadline is None else min(0.05, deadline - time.monotonic())
            try:
                return self._rx.get(timeout=max(left, 0.0)) if left > 0 else self._rx.get_nowait()
            except queue.Empty:
                pass
            if self._failed is not None or self._closed.is_set():
                raise LinkClosed(f"link {self.name!r} is closed: {self._failed or 'closed'}")
            if deadline is not None and time.monotonic() >= deadline:
                return None

    def recv(self, timeout: float | None = None) -> Message | None:
        """Next received message, or None after ``timeout`` seconds (``None`` waits forever)."""
        p = self.recv_packet(timeout)
        return None if p is None else p.message

    def take_drop_notes(self) -> list[str]:
        """What the session layer dropped from the peer since the last call that the peer most likely meant to
        deliver, once per kind of mistake and session (a ZeroMQ seq that did not rise, a wrong dst_session): such
        frames are only counted in ``stats``, and a peer of one's own making them saw its answers vanish."""
        return []

    def refused_count(self) -> int:
        """Every message from the peer this link refused so far, those :meth:`take_refusals` no longer holds too
        (it keeps the latest :data:`protocol.arq.REFUSALS_KEPT` between two calls)."""
        stats: dict = getattr(self, "stats", {})  # every link below has it
        return sum(int(stats.get(k, 0) or 0) for k in ("decode_errors", "reassembly_errors", "protocol_drops"))

    def take_refusals(self) -> list[Refusal]:
        """Each message from the peer that this link refused since the last call (:class:`protocol.arq.Refusal`:
        type code, reason, when): over the size limit, of an unknown type, failing to decode or the schema (e.g. a
        wrong-shaped grid). The latest :data:`protocol.arq.REFUSALS_KEPT` are kept; ``stats["decode_errors"]``
        counts them all. The type code is None where the message did not say (a malformed header). Such a message
        never reaches :meth:`recv`."""
        return []  # pragma: no cover - every link below implements it

    def _offer_received(self, items: Iterable[Received] = ()) -> bool:
        """Queue received messages for :meth:`recv` without waiting; True while some are held because the
        application is not taking them (the queue holds :data:`RX_QUEUE_MESSAGES`): the caller then stops taking
        more from the peer (flow control), and keeps its session alive meanwhile."""
        self._held.extend(items)
        while self._held:
            try:
                self._rx.put_nowait(self._held[0])
            except queue.Full:
                return True
            self._held.popleft()
        return False

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    # implemented by subclasses
    def send(
        self, message: Message | Encoded, timeout: float | None = None, epoch: int | None = None
    ) -> int:  # pragma: no cover - abstract
        """Queue ``message`` (or an :class:`~protocol.codec.Encoded` one, sent with its body as it is); its id."""
        raise NotImplementedError

    def close(self) -> None:  # pragma: no cover - abstract
        raise NotImplementedError


def _stall_note(gap: float, forgiven: bool, peer_timeout: float | None) -> str:
    """The ``stalled`` event's text for a stop of this process of ``gap`` s, or "" when the stop was under half the
    peer timeout (said only where it could have cost a session)."""
    if peer_timeout is None or gap <= peer_timeout / 2:
        return ""
    return f"this side was not scheduled for {gap:.1f} s; " + (
        "the peer's silence is counted from now"
        if forgiven
        else "the peer, not heard since the last such stop, is judged by its silence meanwhile"
    )


class ByteStreamLink(Link):
    """Segmented, selectively acknowledged link over a byte stream; subclasses supply ``_read``/``_write``."""

    def __init__(
        self,
        *,
        baud: float | None = None,
        config: ArqConfig | None = None,
        session_id: int | None = None,
        write_timeout: float = 1.0,
        frame_timeout: float = 2.0,
        limits: Limits | None = None,
        name: str = "",
        log: Log | None = None,
    ) -> None:
        super().__init__(name, log)
        if baud is not None and baud <= 0:
            raise InputError(f"baud must be positive or None, got {baud}")
        if not write_timeout > 0:
            raise InputError(f"write_timeout must be > 0, got {write_timeout}")
        cfg = config or ArqConfig()
        if limits is not None:
            cfg = ArqConfig(**{**cfg.__dict__, "limits": limits})
        if baud is not None:  # an ack may wait for a full frame in the other direction: RTO above ~3 frames
            floor = 3 * cfg.max_frame * BITS_PER_BYTE / baud + 0.02
            if cfg.rto_min < floor:
                cfg = ArqConfig(**{**cfg.__dict__, "rto_min": floor, "rto_initial": max(cfg.rto_initial, floor)})
        self.baud = baud
        self.write_timeout = write_timeout
        self.frame_timeout = frame_timeout
        self.arq = Arq(cfg, session_id=session_id, now=time.monotonic())
        self._cv = threading.Condition()
        self._stop = False
        self._line_free = 0.0
        self._extra = {"busy_s": 0.0, "write_timeouts": 0.0, "frame_timeouts": 0.0}
        self._reader = threading.Thread(target=self._reader_loop, name=f"{name or 'link'}-rx", daemon=True)
        self._writer = threading.Thread(target=self._writer_loop, name=f"{name or 'link'}-tx", daemon=True)

    def _start(self) -> None:
        self._reader.start()
        self._writer.start()

    # transport hooks ------------------------------------------------------
    def _read(self, timeout: float) -> bytes:  # pragma: no cover - abstract
        """Up to 64 KiB within ``timeout`` (b"" if none); raises EOFError at end of stream."""
        raise NotImplementedError

    def _write(self, data: bytes, timeout: float) -> bool:  # pragma: no cover - abstract
        """Write all of ``data`` within ``timeout``; False if it timed out (part may be on the line)."""
        raise NotImplementedError

    def _close_transport(self) -> None:  # pragma: no cover - abstract
        raise NotImplementedError

    # session state ----------------------------------------------------------
    @property
    def established(self) -> bool:
        return self.arq.established

    @property
    def epoch(self) -> int:
        return self.arq.epoch

    @property
    def session_id(self) -> int:
        return self.arq.session_id

    @property
    def peer_session(self) -> int:
        return self.arq.peer_session

    def wait_established(self, timeout: float | None = None) -> bool:
        with self._cv:
            return self._cv.wait_for(lambda: self.arq.established or self._dead(), timeout) and self.arq.established

    @property
    def skipping(self) -> Skipping | None:
        """The refused record whose bytes the stream is skipping now (nothing behind it can arrive meanwhile)."""
        return self.arq.skipping

    def abandon_session(self, reason: str) -> None:
        """Give up on the current session (:meth:`protocol.arq.Arq.abandon`): the peer is told, the messages in
        flight fail with ``reason``, a "lost" event follows and a new session is offered."""
        with self._cv:
            self.arq.abandon(reason, time.monotonic())
            self._cv.notify_all()

    def _dead(self) -> bool:
        return self._failed is not None or self._closed.is_set()

    @property
    def stats(self) -> dict[str, float]:
        with self._cv:
            return {**self.arq.snapshot(), **self._extra, "log_failures": float(self.log_failures)}

    def failures(self) -> list[DeliveryFailure]:
        with self._cv:
            return self.arq.failures()

    def take_refusals(self) -> list[Refusal]:
        return list(self.arq.take_refusals())  # the Arq's deque is safe to pop while the reader appends

    def outcome(self, msg_id: int) -> str | None:
        """``"pending"``, ``"delivered"`` (every byte acknowledged), ``"failed: <reason>"`` or None."""
        with self._cv:
            return self.arq.outcome(msg_id)

    def times(self, msg_id: int, settle_s: float = 0.0) -> MessageTimes | None:
        """A snapshot of the message's times; ``settle_s``: wait up to that long for the writer's record of its
        last write, when the peer's ACK was read first (its times then end at the hand-over, a frame early)."""
        with self._cv:
            self._cv.wait_for(lambda: not getattr(self.arq.times(msg_id), "last_tx_pending", False), settle_s)
            t = self.arq.times(msg_id)
            return None if t is None else dataclasses.replace(t)  # a snapshot: the writer updates the original

    # sending --------------------------------------------------------------
    def send(self, message: Message | Encoded, timeout: float | None = None, epoch: int | None = None) -> int:
        """Queue ``message``; returns its id. Waits at most ``timeout`` s for send-buffer space.

        ``epoch``: send only within that session (see :meth:`protocol.arq.Arq.submit`). An
        :class:`~protocol.codec.Encoded` message goes with its body, not encoded again.
        """
        if self._dead():
            raise LinkClosed(f"link {self.name!r} is closed: {self._failed or 'closed'}")
        if isinstance(message, Encoded):
            body, message = message.body, message.message
        else:
            body = encode_message(message)  # schema errors surface here, in the caller
        reliable = message.TYPE not in UNRELIABLE_TYPES
        with self._cv:
            if not self._cv.wait_for(lambda: self._dead() or self.arq.can_accept(len(body)), timeout):
                raise TimeoutError(f"link {self.name!r}: send buffer still full after {timeout:g} s")
            if self._dead():
                raise LinkClosed(f"link {self.name!r} is closed: {self._failed or 'closed'}")
            mid = self.arq.submit(message.TYPE, body, type(message).__name__, time.monotonic(), reliable, epoch)
            self._cv.notify_all()
        return mid

    def flush(self, timeout: float | None = None) -> bool:
        """Wait until every queued message is delivered or failed; False on timeout."""
        with self._cv:
            return self._cv.wait_for(lambda: self.arq.idle or self._dead(), timeout) and self.arq.idle

    def acknowledged(self, timeout: float) -> bool:
        """Wait (at most ``timeout`` s) until an ACK for every byte received so far has been written; False if not.
        A process about to die on purpose calls it, so that the peer knows what reached it (the tests' crash fault)."""
        with self._cv:
            return bool(self._cv.wait_for(lambda: not self.arq.ack_pending or self._dead(), timeout))

    def _pace(self, n: int) -> float:
        """Sleep until the line has carried ``n`` more bytes; returns when the first of them started."""
        now = time.monotonic()
        if self.baud is None:
            return now
        start = max(self._line_free, now)
        self._line_free = start + n * BITS_PER_BYTE / self.baud
        wait = self._line_free - now
        if wait > 0:
            time.sleep(wait)
        return start

    def _writer_loop(self) -> None:
        while True:
            with self._cv:
                while True:
                    if self._stop or self._failed is not None:
                        return
                    nxt = self.arq.next_frame(time.monotonic())
                    if nxt is not None:
                        break
                    self._cv.wait(0.05)
            frame, token = nxt
            t0 = time.monotonic()
            started = self._pace(len(frame))
            try:
                ok = self._write(frame, self.write_timeout)
            except (OSError, ValueError) as exc:  # pyserial raises SerialException (an OSError)
                self._fail_transport(f"write failed: {exc}")
                return
            now = time.monotonic()
            with self._cv:
                self._extra["busy_s"] += now - t0
                if not ok:
                    self._extra["write_timeouts"] += 1
                self.arq.written(token, len(frame), now, ok, started)
                self._cv.notify_all()

    # receiving ------------------------------------------------------------
    def _reader_loop(self) -> None:
        try:
            self._read_until_stopped()
        except Exception as exc:  # a bug below must fail the link, not leave it open and deaf
            _say_traceback()
            self._fail_transport(f"internal error in the link's reader: {exc!r}")

    def _read_until_stopped(self) -> None:
        last_rx = prev = time.monotonic()
        while not self._stop:
            try:
                data = self._read(0.05)
            except EOFError:
                self._fail_transport("end of stream: the peer closed the connection")
                return
            except (OSError, ValueError, TypeError) as exc:
                if not self._stop:
                    self._fail_transport(f"read failed: {exc}")
                return
            now = time.monotonic()
            stalled = ""
            with self._cv:
                # a turn this late: the process was stopped, and the peer's silence meanwhile is not the peer's
                # (as on ZeroMQ, _forgive; likely what lost two serial runs' sessions at once in a CI of stop 83)
                if now - prev > OWN_STALL_S:
                    stalled = _stall_note(now - prev, self.arq.forgive(now - prev), self.arq.cfg.peer_timeout)
                prev = now
                if data:
                    last_rx = now
                    self.arq.receive(data, now)
                elif self.arq.decoder.pending_bytes and now - last_rx > self.frame_timeout:
                    self.arq.decoder.expire_partial()
                    self._extra["frame_timeouts"] += 1
                self.arq.poll(now)
                got = self.arq.take_received()
                events = self.arq.take_events()
                self._cv.notify_all()
            if stalled:
                self._event("stalled", stalled, self.arq.epoch)
            for ev in events:
                self._event(ev.kind, ev.text, ev.epoch)
            full = self._offer_received(got)
            if full != self.arq.rx_full:
                with self._cv:
                    self.arq.set_rx_full(full, time.monotonic())  # its ACK (window 0, or the window again) goes now
                    self._cv.notify_all()

    def _fail_transport(self, reason: str) -> None:
        with self._cv:
            if self._failed is not None or self._failing:
                return
            self._failing = True
        try:  # said before anyone can see `failed`: a board that ends on it says its summary after this, last
            self._event("transport", reason, self.arq.epoch)
        except OSError:
            pass  # a log that cannot write (stderr a closed pipe) has nowhere to say so; the link fails all the same
        finally:  # a log that raised had left the link failing and never failed
            with self._cv:
                self._failed = reason
                self.arq.transport_failed(reason, time.monotonic())
                self._cv.notify_all()

    def say_done(self, reason: str, flush_timeout: float = 1.0) -> None:
        """Flush (bounded) and tell the peer the session is over (CLOSE code 0 with ``reason``), keeping the
        transport open: a pty's master closed at once hangs its slave up, and the kernel drops what the peer had not
        read yet, the CLOSE with it. :meth:`close` ends the link."""
        if self._closed.is_set():
            return
        if self._failed is None and self.arq.established:
            self.flush(flush_timeout)
        with self._cv:
            self.arq.close(reason)
            self._cv.notify_all()
            self._cv.wait_for(lambda: not self.arq.control_pending or self._failed is not None, 0.5)

    def close(self, flush_timeout: float = 1.0) -> None:
        """Flush (bounded), tell the peer (CLOSE), stop the threads, fail what is left, close the transport."""
        if self._closed.is_set():
            return
        if self._failed is None and self.arq.established and not self.arq.closed:
            self.flush(flush_timeout)
        with self._cv:
            self.arq.close()
            self._cv.notify_all()
            self._cv.wait_for(lambda: not self.arq.control_pending or self._failed is not None, 0.5)
            self.arq.fail_all("link closed before the message was delivered")
            self._stop = True
            self._cv.notify_all()
        self._closed.set()
        self._writer.join(timeout=2.0)
        self._reader.join(timeout=2.0)
        self._close_transport()


class StreamLink(ByteStreamLink):
    """Link over a connected socket, a pty master fd, or an fd pair (``os.pipe``).

    ``StreamLink(sock)`` / ``StreamLink(fd)`` / ``StreamLink(read_fd, write_fd)``. No baud pacing by default.
    """

    def __init__(
        self, rx: int | socket.socket, tx: int | socket.socket | None = None, *, close_fds: bool = True, **kw: Any
    ) -> None:
        super().__init__(**kw)
        self._objs = (rx, tx)  # keep socket objects alive
        self._rfd = rx.fileno() if isinstance(rx, socket.socket) else int(rx)
        self._wfd = self._rfd if tx is None else (tx.fileno() if isinstance(tx, socket.socket) else int(tx))
        for fd in {self._rfd, self._wfd}:
            fcntl.fcntl(fd, fcntl.F_SETFL, fcntl.fcntl(fd, fcntl.F_GETFL) | os.O_NONBLOCK)
        self._close_fds = close_fds
        self._start()

    def _read(self, timeout: float) -> bytes:
        r, _, _ = select.select([self._rfd], [], [], timeout)
        if not r:
            return b""
        try:
            data = os.read(self._rfd, 1 << 16)
        except BlockingIOError:
            return b""
        except OSError as exc:
            if exc.errno == errno.EIO:  # pty slave not (yet / any more) open
                time.sleep(timeout)
                return b""
            raise
        if not data:
            raise EOFError
        return data

    def _write(self, data: bytes, timeout: float) -> bool:
        mv = memoryview(data)
        deadline = time.monotonic() + timeout
        while mv:
            try:
                n = os.write(self._wfd, mv)
                mv = mv[n:]
                continue
            except BlockingIOError:
                pass
            left = deadline - time.monotonic()
            if left <= 0:
                return False
            select.select([], [self._wfd], [], left)
        return True

    def _close_transport(self) -> None:
        if not self._close_fds:
            return
        socks = [o for o in self._objs if isinstance(o, socket.socket)]
        for s in socks:
            s.close()
        if not socks:
            for fd in {self._rfd, self._wfd}:
                try:
                    os.close(fd)
                except OSError:
                    pass


class SerialLink(ByteStreamLink):
    """Link over pyserial: any ``serial_for_url`` URL - ``/dev/ttyUSB0``, a pty, ``socket://``, ``rfc2217://``.

    ``baud`` sets the port's rate and paces writes in software (a pty or a socket has
    no line rate of its own); ``None`` leaves writes unpaced. Reads use a short
    timeout and our frame timeout, never ``inter_byte_timeout`` or DTR (both
    unreliable on ptys).
    """

    def __init__(self, port: str, baud: float | None = None, *, device_baud: int | None = None, **kw: Any) -> None:
        import serial

        super().__init__(baud=baud, **kw)
        try:
            self._ser = serial.serial_for_url(
                port,
                baudrate=int(device_baud or baud or 115200),
                timeout=0.05,
                write_timeout=self.write_timeout,
                dsrdtr=False,
                rtscts=False,
                # a device, not a URL handler: an advisory lock (flock), so a second board or a ground left
                # running on the same device is refused at open instead of both reading half the bytes
                **({} if "://" in port else {"exclusive": True}),
            )
        except (serial.SerialException, ValueError, OSError) as exc:
            held = (
                " (another process holds it: a second board, or a ground still running?)" if "lock" in str(exc) else ""
            )
            raise InputError(f"cannot open serial port {port!r}: {exc}{held}") from None
        self.port = port
        self._timeout_exc = serial.SerialTimeoutException
        self._start()

    def _read(self, timeout: float) -> bytes:
        self._ser.timeout = timeout
        first = self._ser.read(1)  # short read on timeout is normal
        if not first:
            return b""
        n = self._ser.in_waiting
        return first + (self._ser.read(min(n, 1 << 16)) if n else b"")

    def _write(self, data: bytes, timeout: float) -> bool:
        try:
            self._ser.write(data)
        except self._timeout_exc:
            return False
        return True

    def _close_transport(self) -> None:
        try:
            self._ser.close()
        except OSError:
            pass


# ---------------------------------------------------------------------------------- ZeroMQ
_ZHEAD = struct.Struct(">BBBBIII")  # version, kind, type, flags, src session, dst session, seq
Z_VERSION = 2
Z_MSG, Z_HELLO, Z_CLOSE = 1, 4, 5
_LOOPBACK_HOSTS = {"localhost"}
# libzmq reconnects a connecting socket by itself after a network error (it reports CONNECT_RETRIED at once), never
# after a protocol error (a message part over MAXMSGSIZE, broken ZMTP): a drop with no retry this long after is one
REDIAL_AFTER_S = 0.5
RELISTEN_S = 2.0  # how long the binding side tries to bind its endpoint again after dropping its connections
SESSIONLESS_OWNER_S = 10.0  # binding side, no peer timeout: the attached peer's time to open a session
UNANSWERED_S = 2.0  # a connection up this long with no link session on it: the peer does not answer (ZmqLink.answered)


def is_loopback_endpoint(endpoint: str) -> bool:
    """``ipc://``, ``inproc://`` or ``tcp://`` to a loopback address."""
    scheme, _, rest = endpoint.partition("://")
    if scheme in ("ipc", "inproc"):
        return True
    if scheme != "tcp":
        return False
    host = rest.rsplit(":", 1)[0].strip("[]")
    if host in _LOOPBACK_HOSTS:
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def check_zmq_security(endpoint: str, keys: str | Path | None, insecure: bool) -> None:
    """CURVE keys, or ``insecure`` on a loopback endpoint only (docs/protocol.md section 7); said before any work
    by :func:`protocol.linkspec.check_link_spec` and again when a link opens."""
    if keys is None and not insecure:
        raise InputError(
            "ZeroMQ links are CURVE-authenticated: give --keys DIR (`hazard-hil keys DIR` makes one) or "
            "--insecure on loopback"
        )
    if insecure and not is_loopback_endpoint(endpoint):
        raise InputError(f"--insecure is for loopback debugging only; {endpoint!r} is not a loopback endpoint")


@dataclass
class _ZOut:
    id: int
    name: str
    type_code: int
    body: bytes
    bufs: list
    submitted: float
    nbytes: int


class ZmqLink(Link, SessionView):
    """ZeroMQ PAIR link: multipart ``[header, msgpack body, *array buffers]``, CURVE-authenticated.

    Header (16 bytes, big-endian): ``version:u8 (=2) | kind:u8 (1 message, 4 HELLO, 5 CLOSE) |
    type:u8 | flags:u8 | src_session:u32 | dst_session:u32 | seq:u32``. TCP gives integrity
    and order, so there is no ARQ; sessions, keepalives and timeouts follow the same rules as
    the byte-stream links. Arrays of at least ``oob_min_bytes`` go as separate zero-copy
    frames (tracked: :meth:`flush` means "left this process").

    Security: with ``keys`` (a directory from :func:`protocol.zmqauth.generate_keys`) the
    binding side is a CURVE server that accepts only the client keys in ``keys/clients``
    (ZAP, ``zmq.auth.thread.ThreadAuthenticator``); the connecting side authenticates with
    ``keys/client.key_secret``. ``insecure=True`` turns CURVE off and is refused unless the
    endpoint is loopback. A PAIR socket attaches exactly one peer: a second connection is
    refused by libzmq (it gets nothing) and logged here from the socket monitor.
    """

    def __init__(
        self,
        endpoint: str,
        bind: bool,
        *,
        keys: str | Path | None = None,
        insecure: bool = False,
        hwm: int = 256,
        peer_timeout: float | None = 4.0,
        connect_timeout: float | None = 30.0,
        keepalive: float = 1.0,
        hello_interval: float = 0.25,
        oob_min_bytes: int = 64 << 10,
        limits: Limits = DEFAULT_LIMITS,
        session_id: int | None = None,
        name: str = "",
        log: Log | None = None,
    ) -> None:
        import zmq

        super().__init__(name, log)
        check_zmq_security(endpoint, keys, insecure)
        self._zmq = zmq
        self.limits = limits
        self.oob_min_bytes = oob_min_bytes
        self.peer_timeout = peer_timeout
        self.connect_timeout = connect_timeout
        self.keepalive = keepalive
        self.hello_interval = hello_interval
        self.bind = bind
        self.secure = keys is not None
        self.sess = SessionState(session_id)
        self._cv = threading.Condition()
        self._out: deque[_ZOut] = deque()
        self._trackers: deque[tuple[int, str, Any]] = deque()
        self._head_pending_at = 0.0  # when the oldest tracker was last seen not done: its release came after
        self._outcomes: OrderedDict[int, str] = OrderedDict()
        self._times: OrderedDict[int, MessageTimes] = OrderedDict()
        self._failures: deque[DeliveryFailure] = deque(maxlen=4096)
        self._next_id = 1
        self._seq = 0
        self._peer_seq = -1
        self._control: deque[list[Any]] = deque()
        self._stats: dict[str, float] = dict.fromkeys(
            (
                "bytes_sent",
                "bytes_received",
                "frames_sent",
                "frames_received",
                "messages_sent",
                "messages_received",
                "decode_errors",
                "duplicates_dropped",
                "old_session_frames",
                "misaddressed_frames",  # of them, from the peer's own session to another of ours (its mistake)
                "foreign_frames",
                "failures",
                "peer_restarts",
                "peer_losses",
                "peers_refused",
                "auth_failures",
                "connections",
                "protocol_drops",
                "listener_resets",
                "redials",  # connecting side: connections dropped after a silent session, and dialled anew
                "busy_s",
                "dgrams_dropped",  # heartbeats sent with no session to hear them
                "rx_full",  # times this side stopped reading: its application was not taking messages
                "peer_busy",  # times the peer took no messages for a peer timeout while it was heard (not a loss)
            ),
            0,
        )
        now = time.monotonic()
        self._last_heard = now
        self._forgave_at: float | None = None  # _last_heard as a stop's forgiveness left it (see _forgive)
        self._last_sent = -1e9
        self._last_hello = -1e9
        self._stall_since: float | None = None
        self._peer_busy_said = False  # this spell of blocked sends to a peer that answers was said
        self._paused_at: float | None = None  # since when this side reads nothing: its application takes nothing
        self._auth: Any = None
        self._ctx = zmq.Context(io_threads=1)
        self._sock = self._ctx.socket(zmq.PAIR)
        try:
            for opt, val in (
                (zmq.MAXMSGSIZE, limits.max_message_bytes + (1 << 20)),
                (zmq.SNDHWM, hwm),
                (zmq.RCVHWM, hwm),
                (zmq.LINGER, 1000),
                (zmq.RECONNECT_IVL, 100),
                (zmq.RECONNECT_IVL_MAX, 1000),
                # A dead peer is found by TCP keepalive and our own silence timer, not by ZMTP heartbeats: with
                # heartbeats on, libzmq 4.3 aborts the whole process (stream_engine_base.cpp "!_io_error") when a
                # peer that PAIR refused goes away. No TCP_MAXRT (TCP_USER_TIMEOUT) either: Linux applies it to
                # zero-window probes too, so it cut the connection of a live peer whose application was busy
                # (flow control) for twice the peer timeout, and what libzmq held for it was lost unsaid (CI of
                # stop 82). A silent session's connection is dropped by the silence timer instead (_timers).
                (zmq.TCP_KEEPALIVE, 1),
                (zmq.TCP_KEEPALIVE_IDLE, max(1, math.ceil((peer_timeout or 30.0) / 2))),
                (zmq.TCP_KEEPALIVE_INTVL, 1),
                (zmq.TCP_KEEPALIVE_CNT, 3),
                # libzmq takes an IPv6 address ("tcp://[::1]:5555") only on a socket told it may; off, binding
                # one fails with a bare EAGAIN and connecting to one never happens
                (zmq.IPV6, 1 if "://[" in endpoint else 0),
            ):
                self._sock.setsockopt(opt, val)
            self._sock.copy_threshold = 0  # track every frame, so flush() covers small messages too
            if keys is not None:
                self._setup_curve(Path(keys), bind)
            self._mon = self._sock.get_monitor_socket()
            (self._sock.bind if bind else self._sock.connect)(endpoint)
        except (zmq.ZMQError, InputError) as exc:
            self._teardown()
            if isinstance(exc, InputError):
                raise
            raise InputError(f"cannot {'bind' if bind else 'connect'} {endpoint!r}: {exc}") from None
        self.endpoint = self._sock.getsockopt_string(zmq.LAST_ENDPOINT) if bind else endpoint
        self._pending_events: list[tuple[str, str, int]] = []
        self._closing = False
        self._accepted: deque[tuple[int, str]] = deque()  # (fd, peer address) awaiting their handshake
        self._owner: int | None = None  # fd of the attached peer
        # (type code, reason, when) of the latest messages refused from the peer (take_refusals); bounded like the Arq's
        self._refusals: deque[Refusal] = deque(maxlen=REFUSALS_KEPT)
        self._drop_notes: list[str] = []
        self._arrivals = 0  # messages received, taken or refused: their order (Received.order, Refusal.order)
        self._drop_said: set[tuple[str, int]] = set()  # (kind, peer session) said once
        self._handshaken = False  # connecting side: a connection is up (its ZMTP handshake succeeded)
        self._handshaken_at: float | None = None  # connecting side: since when, with no link session on it yet
        self._relisten: str | None = None  # binding side: why every connection is to be dropped (listen anew)
        self._unheard: set[int] = set()  # binding side: fds of connections PAIR refused, still open
        self._sessionless_since = time.monotonic()  # binding side: the attached peer has had no session since
        self._attached_heard_at = -1e9  # when the attached connection last carried a message
        self._dropped_at: float | None = None  # connecting side: that connection dropped, no retry reported yet
        self._redial_why: str | None = None  # connecting side: why the connection is to be dropped and dialled anew
        self._disconnected_at: float | None = None  # the attached peer's connection closed (said in a loss's reason)
        self._connect_retries, self._connected_ever = 0, False  # connecting side: TCP attempts refused, any made
        self._stop = False
        self._io = threading.Thread(target=self._io_loop, name=f"{name or 'zmq'}-io", daemon=True)
        self._io.start()

    def _setup_curve(self, keys: Path, bind: bool) -> None:
        from protocol.zmqauth import client_keys, server_keys

        zmq = self._zmq
        if not zmq.has("curve"):
            raise InputError("this libzmq has no CURVE support; use --insecure on loopback only")
        if bind:
            from zmq.auth.thread import ThreadAuthenticator

            pub, sec, clients = server_keys(keys)
            self._auth = ThreadAuthenticator(self._ctx)
            self._auth.start()
            self._auth.configure_curve(domain="*", location=str(clients))
            self._sock.curve_server = True
            self._sock.curve_publickey = pub
            self._sock.curve_secretkey = sec
        else:
            pub, sec, server_pub = client_keys(keys)
            self._sock.curve_serverkey = server_pub
            self._sock.curve_publickey = pub
            self._sock.curve_secretkey = sec

    # session state (established, epoch, session_id, peer_session: SessionView) ---------
    def wait_established(self, timeout: float | None = None) -> bool:
        with self._cv:
            ok = self._cv.wait_for(lambda: self.sess.established or self._dead(), timeout)
            return bool(ok) and self.sess.established

    def _dead(self) -> bool:
        return self._failed is not None or self._closed.is_set()

    @property
    def stats(self) -> dict[str, float]:
        with self._cv:
            return {
                **self._stats,
                "established": float(self.sess.established),
                "sessions": float(self.sess.epoch),
                "log_failures": float(self.log_failures),
            }

    def failures(self) -> list[DeliveryFailure]:
        with self._cv:
            return list(self._failures)

    def take_refusals(self) -> list[Refusal]:
        with self._cv:
            out = list(self._refusals)
            self._refusals.clear()
            return out

    def take_drop_notes(self) -> list[str]:
        with self._cv:
            out, self._drop_notes = self._drop_notes, []
            return out

    def _drop_note(self, kind: str, src: int, text: str) -> None:
        """Keep ``text`` for :meth:`take_drop_notes`, once per ``kind`` and peer session (under ``_cv``)."""
        if (kind, src) not in self._drop_said and len(self._drop_said) < 64:
            self._drop_said.add((kind, src))
            self._drop_notes.append(text)

    def _refuse(self, type_code: int | None, reason: str, seqs: tuple[int, int] | None = None) -> None:
        """A message from the peer refused: counted (``decode_errors``) and its reason kept for the owner."""
        with self._cv:
            self._stats["decode_errors"] += 1
            self._arrivals += 1
            self._refusals.append(Refusal(type_code, reason, time.monotonic(), self._arrivals, seqs))

    def outcome(self, msg_id: int) -> str | None:
        """``"pending"``, ``"sent"`` (left this process), ``"failed: <reason>"`` or None."""
        with self._cv:
            return self._outcomes.get(msg_id)

    def times(self, msg_id: int, settle_s: float = 0.0) -> MessageTimes | None:
        """The message's times (``settle_s`` as :meth:`StreamLink.times`: nothing to wait for here)."""
        with self._cv:
            return self._times.get(msg_id)

    def _remember(self, table: OrderedDict, key: int, value: Any) -> None:
        table[key] = value
        while len(table) > 8192:
            table.popitem(last=False)

    def _fail(self, mid: int, name: str, reason: str) -> None:
        self._remember(self._outcomes, mid, f"failed: {reason}")
        self._failures.append(DeliveryFailure(mid, name, reason))
        self._stats["failures"] += 1

    # sending --------------------------------------------------------------
    def send(self, message: Message | Encoded, timeout: float | None = None, epoch: int | None = None) -> int:
        """Queue ``message``; returns its id (never blocks: libzmq's high-water mark is watched instead).

        A message over ``limits.max_message_bytes`` (body and out-of-band arrays together) raises
        :class:`InputError` and is not sent, as on the byte-stream links. An :class:`~protocol.codec.Encoded`
        message goes with its body (every array inline), not encoded again."""
        if self._dead():
            raise LinkClosed(f"link {self.name!r} is closed: {self._failed or 'closed'}")
        bufs: list[memoryview] = []
        if isinstance(message, Encoded):
            body, message = message.body, message.message
        else:
            body, bufs = encode_parts(message, self.oob_min_bytes)
        n = len(body) + sum(b.nbytes for b in bufs)
        limit = self.limits.max_message_bytes
        if n > limit:  # as the byte-stream links: the peer would refuse it (or libzmq drop the connection)
            raise InputError(f"message of {n} bytes exceeds the {limit}-byte limit")
        with self._cv:
            mid = self._next_id
            self._next_id += 1
            if message.TYPE in UNRELIABLE_TYPES and (
                not self.sess.established or (epoch is not None and epoch != self.sess.epoch)
            ):
                # a heartbeat with nobody to hear it is dropped, not a delivery failure: a board between grounds
                # counted 4 a second and pushed real failures out of failures() (review of stop 66)
                self._stats["dgrams_dropped"] += 1
                return mid
            if epoch is not None and (epoch != self.sess.epoch or not self.sess.established):
                self._fail(mid, type(message).__name__, f"session {epoch} has ended")
                return mid
            self._out.append(_ZOut(mid, type(message).__name__, message.TYPE, body, bufs, time.monotonic(), n))
            self._remember(self._outcomes, mid, "pending")
            self._remember(self._times, mid, MessageTimes(time.monotonic()))
            self._stats["messages_sent"] += 1
            self._cv.notify_all()
        return mid

    def flush(self, timeout: float | None = None) -> bool:
        """Wait until every message sent so far has left this process (True), or ``timeout`` passes."""

        def done() -> bool:
            return self._dead() or (not self._out and all(t.done for _, _, t in self._trackers))

        with self._cv:
            ok = bool(self._cv.wait_for(done, timeout)) and not self._out
            self._retire_trackers(time.monotonic())
            return ok

    def _hello(self) -> list[bytes]:
        return [_ZHEAD.pack(Z_VERSION, Z_HELLO, 0, 0, self.sess.local, self.sess.peer, 0)]

    def _lose(self, reason: str, kind: str = "lost", notify: bool = True) -> None:
        """Caller holds the lock."""
        self._stats["peer_losses"] += 1
        if notify and self.sess.peer:
            self._control.append(
                [
                    _ZHEAD.pack(Z_VERSION, Z_CLOSE, 0, 0, self.sess.local, self.sess.peer, 0),
                    bytes((CLOSE_LOST,)) + f"session lost: {reason}".encode()[:256],
                ]
            )
        self._drop_all(f"session lost: {reason}")
        if self._handshaken_at is not None:
            self._handshaken_at = time.monotonic()  # the connection may stay up: unanswered from now on
        self._sessionless_since = time.monotonic()
        self.last_error = reason  # now, with the session: its event is told later, and a reader asking why
        self.sess.lose()  # in between got "the link is down"
        self._pending_events.append((kind, reason, self.sess.epoch))

    def _drop_all(self, reason: str) -> None:
        while self._out:
            m = self._out.popleft()
            self._fail(m.id, m.name, reason)
        for mid, name, tracker in self._trackers:
            if not tracker.done:
                self._fail(mid, name, f"{reason} (it had not left this process)")
        self._seq = 0
        self._peer_seq = -1

    # the I/O thread ---------------------------------------------------------
    def _io_loop(self) -> None:
        try:
            self._io_until_stopped()
        except Exception as exc:  # a bug below must fail the link, not leave it open and deaf
            _say_traceback()
            reason = f"internal error in the link's I/O thread: {exc!r}"
            with self._cv:
                events, self._pending_events = self._pending_events, []
                self._drop_all(reason)
            for kind, text, epoch in [*events, ("transport", reason, self.sess.epoch)]:
                self._event(kind, text, epoch)
            with self._cv:
                self._failed = reason
                self._cv.notify_all()

    def _io_until_stopped(self) -> None:
        zmq = self._zmq
        poller = zmq.Poller()
        poller.register(self._sock, zmq.POLLIN)
        poller.register(self._mon, zmq.POLLIN)
        prev = time.monotonic()
        while not self._stop:
            now = time.monotonic()
            # flow control: while the application takes nothing, this side reads nothing more (libzmq's high-water
            # marks hold the rest, and the peer's sends wait), and the peer's silence meanwhile is not the peer's
            full = self._offer_received()
            if full != (self._paused_at is not None):
                if full:
                    poller.unregister(self._sock)  # a readable socket would wake the poll at once, a busy loop
                    self._stats["rx_full"] += 1
                    self._paused_at = now
                else:
                    poller.register(self._sock, zmq.POLLIN)
                    self._paused_at = None
            with self._cv:
                if now - prev > OWN_STALL_S:
                    self._forgive(now - prev)
                prev = now
                gone = self._disconnected_at
                if self._paused_at is not None and (gone is None or gone < self._paused_at):
                    # unless TCP said the peer's connection closed during the pause: a dead peer was hidden until
                    # the application had read everything, and then blamed on silence (review of stop 66)
                    self._last_heard = max(self._last_heard, now)
                self._timers(now)
                control: list[Any] = list(self._control)
                self._control.clear()
            for parts in control:
                try:
                    self._sock.send_multipart(parts, flags=zmq.NOBLOCK)
                    self._last_sent = now
                except zmq.Again:
                    pass  # a HELLO or CLOSE is best effort
            self._send_pending(now)
            if self._relisten is not None:
                self._listen_anew(self._relisten)
            if self._redial_why is not None:
                self._dial_anew()
            try:
                ready = dict(poller.poll(20))
            except zmq.ZMQError:
                if self._stop:
                    return
                raise
            if self._mon in ready:
                self._monitor()
            if self._dropped_at is not None and time.monotonic() - self._dropped_at > REDIAL_AFTER_S:
                self._redial()
            if self._paused_at is None and self._sock in ready:
                for _ in range(64):
                    try:
                        parts = self._sock.recv_multipart(flags=zmq.NOBLOCK, copy=False)
                    except zmq.Again:
                        break
                    self._on_parts(parts, time.monotonic())
                self._offer_received()
            with self._cv:
                events, self._pending_events = self._pending_events, []
                self._cv.notify_all()
            for kind, text, epoch in events:
                self._event(kind, text, epoch)

    def _forgive(self, gap: float) -> None:
        """Caller holds the lock. This loop was not scheduled for ``gap`` s (the process stopped: SIGSTOP, a
        suspended laptop, a VM paused): the peer's silence meanwhile is this side's, and what it sent is still
        in libzmq's queue. The silence clocks restart, so a Result that arrived during the stop is read before
        the peer is judged silent (after an 8 s stop it was dropped and the peer blamed).

        The peer's silence is forgiven for one stop between two hearings of it (:func:`protocol.stall.
        forgiven_hearing`). This side's own clocks (no session yet, a handshake unanswered, a connect timeout) are
        its own and always move with the stop."""
        heard = forgiven_hearing(self._last_heard, self._forgave_at, gap)
        forgiven = heard is not None
        if heard is not None:
            self._last_heard = self._forgave_at = heard
            if self._stall_since is not None:
                self._stall_since += gap
        self._sessionless_since += gap
        if self._handshaken_at is not None:  # "up but unanswered" is timed from the connection, not the stop
            self._handshaken_at += gap
        for m in self._out:  # the connect timeout of what waits to be sent: the stop was not the peer's
            m.submitted += gap
        if text := _stall_note(gap, forgiven, self.peer_timeout):
            self._pending_events.append(("stalled", text, self.sess.epoch))

    def _timers(self, now: float) -> None:
        self._retire_trackers(now)
        if not self.sess.established:
            if now - self._last_hello >= self.hello_interval:
                self._control.append(self._hello())
                self._last_hello = now
            wait = self.peer_timeout if self.peer_timeout is not None else SESSIONLESS_OWNER_S
            idle = now - self._sessionless_since
            # A stranger, or a frozen peer, holds the one place while others wait. And every peer says HELLO while
            # it has no session: one that has said nothing at all may be on a connection PAIR refused unseen (a
            # peer that left and dialled again while this side was stopped: both seen at once on waking, the new
            # pipe before the old one's end), and it held the place, deaf, for good, with no one else waiting.
            mute = self._paused_at is None and now - max(self._sessionless_since, self._attached_heard_at) > wait
            if self._owner is not None and self._relisten is None and idle > wait and (self._unheard or mute):
                self._relisten = f"the attached peer opened no session in {idle:.1f} s" + (
                    " and has said nothing" if mute else ""
                )
                if self._unheard:
                    self._relisten += f" while {len(self._unheard)} other(s) waited"
            if self.connect_timeout is not None:
                while self._out and now - self._out[0].submitted > self.connect_timeout:
                    m = self._out.popleft()
                    self._fail(m.id, m.name, f"no session with the peer within {self.connect_timeout:g} s")
            return
        if now - self._last_hello >= self.keepalive:
            self._control.append(self._hello())
            self._last_hello = now
        if self.peer_timeout is not None:
            quiet = now - self._last_heard
            if quiet > self.peer_timeout:
                reason = f"no message from the peer for {quiet:.1f} s (timeout {self.peer_timeout:g} s)"
                gone = self._disconnected_at
                if gone is not None and gone >= self._last_heard:  # TCP told: the far program, not a slow line
                    reason += f"; its connection closed {now - gone:.1f} s ago (its program ended or crashed?)"
            else:
                # sends blocked at the high-water mark while the peer is heard: its application is busy and not
                # reading (flow control), not a lost session; said once a spell. Losing it failed every pair in
                # flight, where the peer's own deadlines judge the pairs (review of stop 66)
                blocked = self._stall_since is not None and now - self._stall_since > self.peer_timeout
                # not while this side pauses itself: the peer's silence is then forgiven, not heard
                if blocked and self._paused_at is None and not self._peer_busy_said:
                    self._peer_busy_said = True
                    self._stats["peer_busy"] += 1
                    self._pending_events.append(
                        (
                            "peer_busy",
                            f"the peer has taken no message for {now - (self._stall_since or now):.1f} s while it "
                            "answers (its application busy, not reading): what waits goes when it reads",
                            self.sess.epoch,
                        )
                    )
                elif self._stall_since is None:
                    self._peer_busy_said = False
                return
            if self.bind:
                # PAIR keeps the silent peer's connection attached (a frozen ground's kernel still acknowledges),
                # and refuses every other ground meanwhile: drop them all, and whoever dials first is served
                self._relisten = "the silent peer's connection held the one place"
                reason += "; its connection is dropped so that another peer can attach"
            elif gone is None or gone < self._last_heard:
                # TCP has not said the connection closed. To a host that vanished it stays up, retransmitting for
                # many minutes (no TCP_MAXRT: see __init__), and a board back on that address is never dialled
                self._redial_why = reason
                reason += "; its connection is dropped and the peer dialled again"
            self._lose(reason)

    def _retire_trackers(self, now: float) -> None:
        """Caller holds the lock: messages whose frames libzmq has released are ``sent``. Their ``delivered`` is
        the last time they were seen unreleased (or taken): the release came after it, by up to a poll and the
        loop's lag. This earliest bound errs against the deadline; ``now``, up to a loaded loop's lag later,
        erred in its favour."""
        while self._trackers and self._trackers[0][2].done:
            mid, _, _ = self._trackers.popleft()
            if self._outcomes.get(mid) == "pending":
                self._remember(self._outcomes, mid, "sent")
                t = self._times.get(mid)
                if t is not None:
                    t.delivered = max(t.written or 0.0, self._head_pending_at)
        if self._trackers:
            self._head_pending_at = now

    def _send_pending(self, now: float) -> None:
        zmq = self._zmq
        while True:
            with self._cv:
                if not self._out or not self.sess.established:
                    self._stall_since = None
                    return
                m = self._out[0]
                self._seq += 1
                # whole on this side, modulo 2**32 on the wire: a session outlives 4e9 messages (section 7)
                wire_seq = self._seq % POS_MOD
                head = _ZHEAD.pack(Z_VERSION, Z_MSG, m.type_code, 0, self.sess.local, self.sess.peer, wire_seq)
            parts: list[Any] = [head, m.body, *m.bufs]
            t0 = time.monotonic()
            try:
                trackers = [
                    self._sock.send(p, (zmq.SNDMORE if i < len(parts) - 1 else 0) | zmq.NOBLOCK, copy=False, track=True)
                    for i, p in enumerate(parts)
                ]
            except zmq.Again:  # high-water mark: the peer is not draining
                with self._cv:
                    self._seq -= 1
                    if self._stall_since is None:
                        self._stall_since = now
                return
            with self._cv:
                if self._out and self._out[0] is m:
                    self._out.popleft()
                self._stall_since = None
                self._trackers.append((m.id, m.name, zmq.MessageTracker(*trackers)))
                t = self._times.get(m.id)
                if t is not None:
                    t.first_tx = t0
                    t.written = time.monotonic()
                self._stats["busy_s"] += time.monotonic() - t0
                self._stats["bytes_sent"] += len(head) + m.nbytes
                self._stats["frames_sent"] += 1
                self._last_sent = now

    def _on_parts(self, parts: list, now: float) -> None:
        self._attached_heard_at = now
        self._stats["bytes_received"] += sum(len(p.buffer) for p in parts)
        self._stats["frames_received"] += 1
        if self._closing:  # we said CLOSE: whatever the peer says now is not for this link
            return
        if not parts or len(parts[0].buffer) != _ZHEAD.size:
            n = len(parts[0].buffer) if parts else 0
            self._refuse(None, f"malformed message header: {n} bytes, not {_ZHEAD.size}")
            return
        version, kind, type_code, flags, src, dst, seq = _ZHEAD.unpack(parts[0].buffer)
        if version != Z_VERSION or flags != 0 or src == 0:
            what = f"wire version {version}, not {Z_VERSION}" if version != Z_VERSION else f"flags {flags}, src {src}"
            self._refuse(None if version != Z_VERSION else type_code, f"malformed message header: {what}")
            return
        with self._cv:
            if kind == Z_HELLO:
                if self.sess.retired(src) or len(parts) != 1:
                    self._stats["old_session_frames"] += 1
                    return
                ended = self.sess.epoch  # the "restarted" event names the session that ended
                was_up = self.sess.established
                replaced, reply, newly = self.sess.on_hello(src, dst)
                if replaced is not None:
                    self._drop_all(f"peer started a new session {src:08x} (it restarted, or gave up on {replaced:08x})")
                if replaced is not None and was_up:  # a handshake never completed is no restart (SerialLink's too)
                    self._stats["peer_restarts"] += 1
                    self._pending_events.append(
                        (
                            "restarted",
                            f"the peer started a new link session (it restarted, or gave up the last one) "
                            f"(session {replaced:08x} -> {src:08x})",
                            ended,
                        )
                    )
                self._last_heard = now
                if newly:
                    self._established(now)
                elif reply:
                    self._control.append(self._hello())
                    self._last_hello = now
                return
            verdict = self.sess.classify(src, dst)
            if verdict != "ok":
                self._stats["old_session_frames" if verdict == "old" else "foreign_frames"] += 1
                if verdict == "old" and src == self.sess.peer and self.sess.was_local(dst):
                    # sent to this side's session before the loss, before the peer heard of the new one: expected
                    # after a stall (a board SIGSTOPped past the timeout read as its mistake; QA of stop 72)
                    self._control.append(self._hello())
                elif verdict == "old" and src == self.sess.peer:
                    self._control.append(self._hello())
                    self._stats["misaddressed_frames"] += 1
                    self._drop_note(
                        "dst",
                        src,
                        f"messages addressed to session {dst:08x}, not this link's {self.sess.local:08x} (the peer's "
                        "dst_session must be the session its HELLO named, docs/protocol.md section 7)",
                    )
                elif verdict == "foreign":
                    self._drop_note("foreign", src, f"messages from session {src:08x}, which said no HELLO first")
                return
            self._last_heard = now
            if self.sess.confirm():
                self._established(now)
            if kind == Z_CLOSE:
                body = bytes(parts[1].buffer[:257]) if len(parts) > 1 else b""
                reason = body[1:].decode("utf-8", "replace") or "no reason given"
                if body[:1] == bytes((CLOSE_LOST,)):  # it gave up on this session and will start a new one
                    self._lose(f"peer gave up on the session ({reason})", kind="lost", notify=False)
                else:
                    self._lose(f"peer closed the link ({reason})", kind="closed", notify=False)
                return
            if kind != Z_MSG:
                self._arrivals += 1
                self._refusals.append(Refusal(type_code, f"unknown message kind {kind}", now, self._arrivals))
                self._stats["decode_errors"] += 1
                return
            whole = unwrap(seq, self._peer_seq + 1)  # serial-number order (RFC 1982), as the byte stream's positions
            if whole <= self._peer_seq:  # TCP neither repeats nor reorders: the peer's seq did not rise
                self._stats["duplicates_dropped"] += 1
                self._drop_note(
                    "seq",
                    src,
                    f"messages whose seq ({seq}) is not above the last one taken ({self._peer_seq % POS_MOD}), as "
                    "repeats (each message's seq must rise, docs/protocol.md section 7)",
                )
                return
            self._peer_seq = whole
            epoch = self.sess.epoch
        nbytes = sum(len(p.buffer) for p in parts)
        try:
            if len(parts) < 2:
                raise CodecError(f"bad multipart shape ({len(parts)} parts)")
            message_class(type_code)
            size, limit = nbytes - len(parts[0].buffer), self.limits.max_message_bytes
            if size > limit:  # body and out-of-band arrays together, as the sender counts them
                raise CodecError(f"message of {size} bytes exceeds the {limit}-byte limit")
            msg = decode_parts(parts[1].buffer, [p.buffer for p in parts[2:]], self.limits, expect_type=type_code)
        except InputError as exc:
            self._refuse(type_code, str(exc), getattr(exc, "frame_seqs", None))
            return
        with self._cv:
            self._stats["messages_received"] += 1
            self._arrivals += 1
            order = self._arrivals
        self._held.append(Received(msg, seq, now, now, nbytes, epoch, order))

    def _redial(self) -> None:
        """The connection dropped and libzmq will not retry: it does that after a protocol error, such as a message
        part from the peer over MAXMSGSIZE (the size limit + 1 MiB), and that message is lost unseen. Left alone the
        session would time out and the link never connect again. Instead: the drop is a refusal with its likely
        reason, the session is given up at once (what was in flight fails with that reason, the peer is told), and
        the link connects anew; a new session follows as after any loss."""
        self._dropped_at = None
        reason = (
            "libzmq dropped the connection: the peer sent a message part over its "
            f"{self.limits.max_message_bytes + (1 << 20)}-byte maximum (or broke the ZeroMQ protocol); "
            "that message is lost"
        )
        reason += self._reconnect()
        with self._cv:
            self._stats["protocol_drops"] += 1
            self._arrivals += 1
            self._refusals.append(Refusal(None, reason, time.monotonic(), self._arrivals))
            if self.sess.established:
                self._lose(reason)
            else:
                self._pending_events.append(("lost", reason, self.sess.epoch))

    def _reconnect(self) -> str:
        """Connecting side: close the connection and dial again (libzmq retries until the peer answers); what
        went wrong, as a clause to add to a reason, or ""."""
        zmq = self._zmq
        try:
            self._sock.disconnect(self.endpoint)
        except zmq.ZMQError:
            pass  # already forgotten by libzmq
        try:
            # PAIR refuses a second pipe, and the old one ends only once libzmq's I/O thread has acknowledged its
            # end: a pipe made at once by connect() can find it still attached and be refused, deaf. IMMEDIATE
            # makes the pipe when the new connection's handshake is done, a round trip to the peer later.
            self._sock.setsockopt(zmq.IMMEDIATE, 1)
            self._sock.connect(self.endpoint)
        except zmq.ZMQError as exc:
            return f"; connecting again failed: {exc}"
        return ""

    def _dial_anew(self) -> None:
        """Connecting side: the session was lost to silence on a connection TCP still holds up; drop it and dial
        again, so that a peer back on its address is reached (event ``redial``, stat ``redials``)."""
        why, self._redial_why = self._redial_why, None
        trouble = self._reconnect()
        with self._cv:
            self._stats["redials"] += 1
            text = f"dropped the connection and dialling again: {why}{trouble}"
            self._pending_events.append(("redial", text, self.sess.epoch))

    def _listen_anew(self, why: str) -> None:
        """Binding side: unbind the endpoint, which closes every connection accepted on it, and bind it again.
        The rebind is retried for a while (the listener closes in libzmq's I/O thread); when the address has been
        taken meanwhile the link fails with that reason."""
        zmq = self._zmq
        self._relisten = None
        try:
            self._sock.unbind(self.endpoint)
        except zmq.ZMQError:
            pass  # not bound (a failed rebind before): bind below says why if it cannot
        end = time.monotonic() + RELISTEN_S
        while True:
            try:
                self._sock.bind(self.endpoint)
                break
            except zmq.ZMQError as exc:
                if time.monotonic() >= end:
                    reason = f"cannot listen on {self.endpoint} again: {exc}"
                    with self._cv:  # what led here (the peer lost) first, then this, before `failed` is seen
                        events, self._pending_events = self._pending_events, []
                    try:
                        for kind, text, epoch in [*events, ("transport", reason, self.sess.epoch)]:
                            self._event(kind, text, epoch)
                    except OSError:
                        pass  # as in ByteStreamLink._fail_transport: nowhere to say it, the link fails all the same
                    finally:
                        with self._cv:
                            self._failed = reason
                            self._cv.notify_all()
                    return
                time.sleep(0.02)
        with self._cv:
            self._stats["listener_resets"] += 1
            self._owner = None
            self._accepted.clear()
            self._unheard.clear()
            text = f"dropped every connection and listening again: {why}"
            self._pending_events.append(("relisten", text, self.sess.epoch))

    @property
    def refused_only(self) -> bool:
        """Connecting side: every attempt so far was turned away at the TCP level (connection refused: nothing
        listens on that port), none ever connected. libzmq retries such a port in silence."""
        return not self.bind and self._connect_retries > 0 and not self._connected_ever

    @property
    def answered(self) -> bool | None:
        """Connecting side: False while a connection is up (its ZeroMQ handshake done) but the peer has not
        answered on it for :data:`UNANSWERED_S` - a board that serves another ground (PAIR attaches one peer and
        leaves the others connected and unheard) or whose program does not read; True otherwise; None on the
        binding side."""
        if self.bind:
            return None
        at = self._handshaken_at
        return not (at is not None and not self.sess.established and time.monotonic() - at >= UNANSWERED_S)

    def _established(self, now: float) -> None:
        self._last_heard = now
        self._control.append(self._hello())
        self._last_hello = now
        self._pending_events.append(
            ("established", f"session {self.sess.local:08x} <-> {self.sess.peer:08x}", self.sess.epoch)
        )

    def _monitor(self) -> None:
        from zmq.utils.monitor import recv_monitor_message

        zmq = self._zmq
        while True:
            try:
                ev = recv_monitor_message(self._mon, flags=zmq.NOBLOCK)
            except zmq.Again:
                return
            except zmq.ZMQError:
                return
            kind, value = ev["event"], ev["value"]
            if kind == zmq.EVENT_ACCEPTED:
                self._accepted.append((value, _peer_address(value)))
            elif kind == zmq.EVENT_HANDSHAKE_SUCCEEDED:
                self._handshaken, self._dropped_at = not self.bind, None
                self._handshaken_at = None if self.bind else time.monotonic()
                self._disconnected_at = None
                fd, addr = self._accepted.popleft() if self._accepted else (-1, "?")
                with self._cv:
                    self._stats["connections"] += 1
                    if self.bind and self._owner is not None:
                        self._unheard.add(fd)
                        self._stats["peers_refused"] += 1
                        self._pending_events.append(
                            ("refused", f"second peer from {addr} refused: this session already has one", self.epoch)
                        )
                    elif self.bind:
                        self._owner, self._sessionless_since = fd, time.monotonic()
            elif kind in (
                zmq.EVENT_HANDSHAKE_FAILED_AUTH,
                zmq.EVENT_HANDSHAKE_FAILED_PROTOCOL,
                zmq.EVENT_HANDSHAKE_FAILED_NO_DETAIL,
            ):
                fd, addr = self._accepted.popleft() if self._accepted and self.bind else (-1, "the server")
                # one side with CURVE keys and the other --insecure is no key problem: say which it is
                mismatch = kind == zmq.EVENT_HANDSHAKE_FAILED_PROTOCOL and value == getattr(
                    zmq, "PROTOCOL_ERROR_ZMTP_MECHANISM_MISMATCH", -1
                )
                with self._cv:
                    self._stats["auth_failures"] += 1
                    who = f"connection from {addr}" if self.bind else "the server"
                    if mismatch:
                        why = MECHANISM_MISMATCH_TEXT
                    elif not self.secure:  # no CURVE here: "wrong or missing key" named a cause this side lacks
                        why = (
                            "ZeroMQ handshake failed (not a peer of this protocol, or one with CURVE keys while this "
                            "side runs --insecure?)"
                        )
                    elif kind == zmq.EVENT_HANDSHAKE_FAILED_AUTH:  # the authenticator said no: the key itself
                        why = "CURVE handshake failed: its key is not accepted (not in clients/)"
                    elif kind == zmq.EVENT_HANDSHAKE_FAILED_NO_DETAIL:  # a peer that left mid-handshake, too
                        why = "CURVE handshake failed (wrong or missing key, or the peer left during it)"
                    else:
                        why = "CURVE handshake failed (wrong or missing key?)"
                    self._pending_events.append(("auth_failed", f"{who}: {why}", self.epoch))
            elif kind == zmq.EVENT_DISCONNECTED:
                if self._handshaken or value == self._owner:
                    self._disconnected_at = time.monotonic()
                self._unheard.discard(value)
                if value == self._owner:
                    self._owner = None
                    # PAIR never attaches a connection it refused, even once the slot is free: the waiting
                    # peers would wait forever. Dropping them makes them dial again, and the first is served.
                    if self._unheard and self._relisten is None:
                        self._relisten = f"the peer left while {len(self._unheard)} other(s) waited unheard"
                self._accepted = deque((f, a) for f, a in self._accepted if f != value)
                self._handshaken_at = None
                if self._handshaken:  # libzmq retries at once, unless the peer broke the protocol (see _redial)
                    self._handshaken, self._dropped_at = False, time.monotonic()
            elif kind == zmq.EVENT_CONNECT_RETRIED:
                self._dropped_at = None
                self._connect_retries += 1
            elif kind == zmq.EVENT_CONNECTED:
                self._connected_ever = True

    # closing ----------------------------------------------------------------
    def close(self, flush_timeout: float = 5.0) -> None:
        """Flush (bounded), tell the peer (CLOSE), close the socket and terminate the context."""
        if self._closed.is_set():
            return
        if self.sess.established and self._failed is None:
            self.flush(flush_timeout)
        with self._cv:
            self._closing = True
            if self.sess.peer:
                self._control.append(
                    [
                        _ZHEAD.pack(Z_VERSION, Z_CLOSE, 0, 0, self.sess.local, self.sess.peer, 0),
                        bytes((CLOSE_APP,)) + b"its program ended, or was stopped",
                    ]
                )
            self._cv.wait_for(lambda: not self._control, 0.5)
            self._stop = True
            for m in self._out:
                self._fail(m.id, m.name, "link closed before the message was sent")
            self._out.clear()
        self._closed.set()
        self._io.join(timeout=3.0)
        with self._cv:
            for mid, name, tracker in self._trackers:
                if not tracker.done:
                    self._fail(mid, name, "link closed before the message left this process")
        self._teardown()
        with self._cv:
            self._trackers.clear()

    def _teardown(self) -> None:
        try:
            self._sock.disable_monitor()
        except Exception:
            pass
        mon = getattr(self, "_mon", None)
        if mon is not None:
            mon.close(0)
        self._sock.close(linger=1000)
        if self._auth is not None:
            self._auth.stop()
        self._ctx.term()  # returns once libzmq has released every buffer it still held


def _peer_address(fd: int) -> str:
    """``host:port`` of an accepted TCP connection (from the monitor's fd), for the log."""
    gone = "a peer whose connection had already closed"  # an fd number meant nothing to a reader
    try:
        s = socket.socket(fileno=os.dup(fd))
    except OSError:
        return gone
    try:
        host, port = s.getpeername()[:2]
        return f"{host}:{port}"
    except (OSError, ValueError):
        return gone
    finally:
        s.close()
