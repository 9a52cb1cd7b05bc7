"""Segmentation and selective-repeat ARQ over a byte stream, as a sans-I/O state machine.

:class:`Arq` knows nothing of threads, sockets or clocks: the caller feeds it
received bytes (:meth:`Arq.receive`), asks it for the next frame to write
(:meth:`Arq.next_frame`), reports when that frame has been written
(:meth:`Arq.written`) and calls :meth:`Arq.poll` for the timers, always with
the current time. :mod:`protocol.links` drives it with a reader and a writer
thread; tests drive it with a simulated line and a virtual clock.

Sending (models: TCP's byte sequence with SACK RFC 2018, RACK RFC 8985, RTO RFC 6298; CCSDS COP-1):

* each session direction is one reliable byte stream of records
  ``type:u8 | length:u32 | body`` (one per message), numbered by stream position
  from 0 (on the wire modulo 2**32: :func:`unwrap`); DATA frames carry any range of it, at most the current
  frame size;
* at most ``window`` bytes (and at most the peer's announced window) are
  outstanding, counted from the lowest unacknowledged byte;
* the receiver's ACK carries ``cum`` (every byte below it arrived), up to 16
  SACK ranges above it (the most recently received first, then the lowest),
  and ``echo``, the transmission number of the latest DATA frame it received;
* loss detection: every DATA frame carries a new transmission number, so an
  ACK's echo says exactly which transmissions preceded the last one received;
  any still unacknowledged is lost (a serial line does not reorder) and is
  resent at once, cut to the current frame size. Otherwise after the
  retransmission timeout ``RTO = SRTT + 4 RTTVAR`` (samples from the echo, exact
  even for resent frames), doubled per timeout period up to ``rto_max``;
* frame size adapts to the line: from the loss rate L of frames of mean size n
  the per-byte error rate is ``e = -ln(1 - L) / n`` and the size maximising
  goodput ``(1 - h/f)(1 - e)^f`` (h = per-frame overhead) is
  ``f = (e h + sqrt(e^2 h^2 + 4 e h)) / (2 e)``, clamped to
  [``min_frame``, ``max_frame``];
* a message is *delivered* when ``cum`` passes the end of its record, and
  *failed* with a reason when the session it was sent in ends first (peer
  lost, restarted or closed) or the peer rejects it (REJECT). Nothing is
  dropped silently.

Receiving: bytes are accepted inside ``[cum, cum + window)`` and held out of
order until the gap fills (at most ``window`` bytes), then parsed into records.
A record announcing more than ``limits.max_message_bytes`` or an unknown type
is skipped without keeping a byte of it and refused (REJECT) once it has gone
by (:attr:`Arq.skipping` says so from its header on: nothing behind it can be
read meanwhile; an owner that will not wait for a record declared over the
limit ends the session with :meth:`Arq.abandon`), and every other body is
decoded under the codec's budget (:func:`protocol.codec.decode_parts`).
Duplicates and bytes outside the window are dropped and acknowledged again.

Liveness: while a session is up each side sends a HELLO as keepalive when it
has sent nothing for ``keepalive`` s. The session is lost (an explicit error
for every message in flight, reported by :meth:`Arq.take_events`) when the
peer has sent nothing valid for ``peer_timeout`` s, when outstanding data
makes no progress for ``peer_timeout`` s, when a started message gets no byte
in order for ``2 * peer_timeout`` s (reassembly timeout), or when the peer
sends CLOSE. Queued messages wait at most ``connect_timeout`` s for a session.

Unreliable messages (heartbeats) go as DGRAM frames. A newer one of a type replaces one still queued (a stale
heartbeat says nothing the newer does not), and datagrams take turns with DATA instead of going first: on a slow
line a heartbeat every 0.25 s fills 80 % of 2400 baud, and with strict priority the backlog built while one DATA
frame was on the line kept every later DATA frame off it until the peer timed the session out.
"""

from __future__ import annotations

import bisect
import math
import struct
from collections import OrderedDict, deque
from dataclasses import dataclass, field
from typing import NamedTuple

from protocol.codec import DEFAULT_LIMITS, Limits, decode_parts
from protocol.errors import InputError
from protocol.framing import (
    ACK,
    CLOSE,
    CLOSE_LOST,
    DATA,
    DATA_OVERHEAD,
    DEFAULT_MAX_FRAME,
    DGRAM,
    HELLO,
    MIN_FRAME,
    OVERHEAD,
    REJECT,
    StreamDecoder,
    WireFrame,
    ack_frame,
    ack_sack_room,
    close_frame,
    data_frame,
    dgram_frame,
    hello_frame,
    reject_frame,
)
from protocol.messages import MESSAGE_TYPES, Heartbeat, Message
from protocol.session import SessionState, SessionView
from protocol.stall import forgiven_hearing

# a zero window is probed with this many bytes of the stream, not a whole segment: on a 960 byte/s line a 1 kB probe
# kept the sender's direction 35-40 % busy through a pause (stop 66's known limit); TCP probes with one byte (RFC 9293)
PROBE_BYTES = 1
RECORD = struct.Struct(">BI")  # a message in the reliable stream: type, body length
POS_MOD = 1 << 32  # stream positions go on the wire modulo 2**32 (u32); each side keeps them whole
_HALF = 1 << 31


def unwrap(wire: int, near: int) -> int:
    """The whole stream position congruent to ``wire`` (mod 2**32) nearest to ``near``: ``near + ((wire - near +
    2**31) mod 2**32) - 2**31``. Serial-number arithmetic (RFC 1982), decoded as QUIC decodes packet numbers
    (RFC 9000 A.3): exact while the true position is within 2 GiB of ``near``, and a side's window is at most 1 GiB.
    Stream positions ended the session at 4 GiB (stop 66's known limit), failing what was in flight."""
    return near + ((wire - near + _HALF) % POS_MOD) - _HALF


@dataclass(frozen=True)
class ArqConfig:
    """Tunables of one endpoint (both ends need not agree: HELLO announces frame size and window)."""

    max_frame: int = DEFAULT_MAX_FRAME  # unstuffed bytes per frame, header to CRC; also what we accept
    min_frame: int = 64  # the adaptive frame size never goes below this
    window: int = 32 << 10  # bytes in flight / accepted beyond cum
    max_segments: int = 2048  # transmissions tracked at once (bounds the scoreboard)
    adaptive: bool = True
    peer_timeout: float | None = 4.0  # silent or stalled peer -> session lost (detected within 4.1 s); None = never
    connect_timeout: float | None = 30.0  # a queued message waits this long for a session; None = forever
    keepalive: float = 1.0
    hello_interval: float = 0.25
    rto_initial: float = 1.0
    rto_min: float = 0.05
    rto_max: float = 2.0
    send_buffer: int = 64 << 20  # bytes queued but not yet acknowledged (send() waits beyond this)
    limits: Limits = DEFAULT_LIMITS

    def validate(self) -> ArqConfig:
        if not MIN_FRAME <= self.min_frame <= self.max_frame <= 1 << 24:
            raise InputError(f"frame sizes must satisfy {MIN_FRAME} <= min_frame <= max_frame <= 16 MiB")
        if not self.max_frame <= self.window <= 1 << 30 or self.max_segments < 1:
            raise InputError(f"window must be in [max_frame, 1 GiB] bytes, got {self.window}")
        for name in ("peer_timeout", "connect_timeout"):
            v = getattr(self, name)
            if v is not None and not v > 0:
                raise InputError(f"{name} must be > 0 or None, got {v}")
        if not 0 < self.rto_min <= self.rto_initial and self.rto_min <= self.rto_max:
            raise InputError("need 0 < rto_min <= rto_initial and rto_min <= rto_max")
        if not (self.keepalive > 0 and self.hello_interval > 0):
            raise InputError("keepalive and hello_interval must be > 0")
        return self


@dataclass(frozen=True)
class DeliveryFailure:
    """A message that was not delivered, and why."""

    seq: int  # the message id returned by send()
    message_type: str
    reason: str


class Refusal(NamedTuple):
    """A message from the peer this side refused: its type code (None where its header did not say), the reason,
    when (``time.monotonic()``), its place among the messages received (``order``, as :class:`Received`'s: one
    count per message, taken or refused; times tie within one read) and the frame seqs it answered when its
    body said them (a Result that failed the schema, not the decoder: ``None`` otherwise). Its owner can tell
    which answer it was, or which answers came before it, though refusals and messages reach it apart."""

    type_code: int | None
    reason: str
    t: float
    order: int = 0
    frame_seqs: tuple[int, int] | None = None


@dataclass(frozen=True)
class Received:
    """A message as it came off the line: first segment seq, reception start/end, wire bytes."""

    message: Message
    seq: int  # stream position of its record (-1: a datagram)
    t_first: float
    t_done: float
    nbytes: int
    epoch: int
    order: int = 0  # its place among the messages received, refused ones counted too (:class:`Refusal`)

    @property
    def line_s(self) -> float:
        """Time from the first to the last segment of this message at the receiver."""
        return self.t_done - self.t_first


@dataclass
class MessageTimes:
    """Send-side timeline of one message (monotonic seconds; None = not yet)."""

    submitted: float
    first_tx: float | None = None  # first byte of its first segment handed to the line
    written: float | None = None  # its last segment written for the first time
    delivered: float | None = None  # every segment acknowledged
    last_tx: float | None = None  # the last write of any of its bytes, a retransmission's included
    # last_tx is the moment that write was handed to the writer, not yet its end on the line (the writer's record,
    # written(), had not come: under load the peer's ACK can be read first)
    last_tx_pending: bool = False

    @property
    def line_s(self) -> float | None:
        """Its first byte on the line to its last (retransmissions included), once every segment is acknowledged.

        Not to the acknowledgement: on a busy line the ACK waits behind the peer's own data (a ground streaming the
        next pair), which is no part of this message's line time. A link that cannot see its writes (ZeroMQ) ends
        it at ``delivered``, and so does a message whose last write the writer has not recorded yet (the peer's ACK
        was read first): that write ended before the ACK came, which bounds it."""
        if self.first_tx is None or self.delivered is None:
            return None
        if self.last_tx is None or self.last_tx <= self.first_tx or self.last_tx_pending:
            return self.delivered - self.first_tx
        return self.last_tx - self.first_tx

    @property
    def queue_s(self) -> float | None:
        """Submitted to its first byte on the line: its wait behind the messages queued before it."""
        return None if self.first_tx is None else max(0.0, self.first_tx - self.submitted)


@dataclass
class _Out:
    id: int
    type_code: int
    name: str
    record: bytes  # type:u8 | length:u32 | body (dropped once the record is in the stream)
    submitted: float
    start: int = -1  # stream position of the record (-1: waiting for a session)
    end: int = -1


@dataclass
class _Seg:
    start: int
    end: int
    tx: int = 0
    sent_at: float | None = None  # last write completed
    order: int = 0  # transmission number of its latest transmission
    queued: bool = True  # waiting for (re)transmission or being written
    acked: bool = False
    refused: bool = False  # queued again because a full peer dropped it unread: its resend is no retransmission
    # (start, end, times) of the messages it carries bytes of, from its first transmission: an ACK that beats the
    # writer's written() delivers them (they leave _msgs), and their line times must still see the write's end
    msgs: list[tuple[int, int, MessageTimes]] = field(default_factory=list)


@dataclass(frozen=True)
class Skipping:
    """A record whose header says it will be refused (over the size limit or of an unknown type): its bytes are
    skipped as they come, and it is REJECTed once they have all gone by. Until then nothing behind it in the stream
    can be read."""

    type_code: int
    length: int  # the body length its header declares
    pos: int  # stream position of its header
    reason: str
    oversize: bool  # declared over the size limit (else: an unknown type)


REFUSALS_KEPT = 64  # refused messages whose reasons an Arq keeps for its owner (take_refusals)


@dataclass
class _Event:
    kind: str  # "established" | "lost" | "restarted" | "closed" | "echo" | "foreign"
    text: str
    epoch: int


ECHO_TEXT = (
    "the line returns this side's own frames (a loopback plug, serial:loop://, or a device that echoes); "
    "they are dropped"
)
ECHO_EVENT_S = 10.0  # echoes are counted each, and said as an event once per this many seconds
HELD_HELLO_IDS = 16  # session ids whose held-back HELLOs are counted apart (a stranger may send any number of ids)
FOREIGN_HELLO_TEXT = (
    "a HELLO of another session ({:08x}) while the peer of this one is still talking: ignored (another device on "
    "the line?); a restarted peer's old session falls silent, and its HELLO is then taken"
)

STAT_KEYS = (
    "bytes_sent",
    "bytes_received",
    "frames_sent",
    "frames_received",
    "data_frames_sent",
    "retransmits",
    "retransmit_bytes",  # payload bytes resent: the frames shrink on a noisy line, so a count alone reads large
    "probes",  # one-byte probes of a peer's zero window: not line loss, so not counted as retransmissions
    "refused_resends",  # what a full peer dropped unread, sent again when its window reopened: not line loss either
    "timeouts",
    "crc_errors",
    "malformed",
    "oversize",
    "resyncs",
    "bytes_discarded",
    "duplicates_dropped",
    "out_of_window",
    "rx_full_drops",  # stream bytes refused while this side's application was not taking messages
    "peer_full",  # times the peer said window 0 (its application not taking messages)
    "acks_sent",
    "acks_received",
    "messages_sent",
    "messages_received",
    "delivered",
    "failures",
    "decode_errors",
    "dgrams_dropped",
    "dgrams_superseded",
    "rejected_sent",
    "rejected_received",
    "reassembly_errors",
    "old_session_frames",
    "foreign_frames",
    "echoed_frames",
    "foreign_hellos",
    "sessions",
    "peer_restarts",
    "peer_losses",
)


class Arq(SessionView):
    """One endpoint's sessions, segmentation, selective repeat and reassembly (see module doc)."""

    def __init__(self, config: ArqConfig | None = None, *, session_id: int | None = None, now: float = 0.0) -> None:
        self.cfg = (config or ArqConfig()).validate()
        self.sess = SessionState(session_id)
        self.decoder = StreamDecoder(self.cfg.max_frame)
        self.stats: dict[str, float] = dict.fromkeys(STAT_KEYS, 0)
        self.peer_max_frame = MIN_FRAME
        self.peer_window = self.cfg.max_frame
        self._bad_acks = 0  # ACKs beyond what was sent, which the decoder's malformed count does not hold
        # flow control (section 3.2): this side's application is not taking messages (the link's queue is full):
        # new stream bytes are refused and every ACK says window 0, while ACKs, HELLOs and keepalives go on
        self.rx_full = False
        self.peer_full = False  # the peer's last ACK said window 0: one probe at a time, and no stall is its fault
        self._last_ack_at = -math.inf  # when the last ACK was built (re-said while full)
        self._reopened = False  # the window reopened and no in-order byte has come since
        self._reopened_at = -math.inf
        self.closed = False
        self._events: list[_Event] = []
        self._echo_said = -math.inf
        self._foreign_said = -math.inf
        # HELLOs held back per session id: a restarted peer's first ones come while its old session still reads as
        # alive, and were counted as "another device on the line?" once the restart was taken (QA 64a)
        self._held_hellos: dict[int, int] = {}
        self._received: list[Received] = []
        self._failures: deque[DeliveryFailure] = deque(maxlen=4096)
        # (type code, reason) of the latest messages refused from the peer: the REJECT tells the peer why, this
        # tells the owner (a supervisor reports what its flight process sent that was refused); bounded
        self._refusals: deque[Refusal] = deque(maxlen=REFUSALS_KEPT)
        self._arrivals = 0  # messages received, taken or refused: their order (Received.order, Refusal.order)
        self._outcomes: OrderedDict[int, str] = OrderedDict()
        self._times: OrderedDict[int, MessageTimes] = OrderedDict()
        self._pos_id: OrderedDict[int, tuple[int, str]] = OrderedDict()  # record position -> (id, name)
        self._next_id = 1
        self._control: deque[bytes] = deque()
        self._queued_hello: bytes | None = None  # the HELLO in _control, if one is (at most one waits)
        self._dgrams: deque[tuple[int, bytes]] = deque()
        self._dgram_turn = True  # datagrams and DATA alternate while both wait
        self._pending: deque[_Out] = deque()  # reliable messages waiting for a session
        self._pending_bytes = 0
        # line estimates survive session changes (the line is the same)
        self._srtt: float | None = None
        self._rttvar = 0.0
        self._rto = self.cfg.rto_initial  # from RTT samples (RFC 6298)
        self._backoff = 1.0  # doubled per timeout, reset by progress
        self._last_timeout = -math.inf
        self._loss = 0.0  # EWMA of the frame loss fraction
        self._mean_frame = float(self.cfg.max_frame)
        self._frame = self.cfg.max_frame
        self._last_keepalive = now
        self._reset_session_state(now)
        self._queue_hello()
        self._last_hello = now

    # ------------------------------------------------------------------ session state
    def _reset_session_state(self, now: float) -> None:
        # sending: the stream [una, end) is in _sbuf; [una, nxt) has been transmitted
        self._sbuf = bytearray()
        # positions start at 0 again: a REJECT of this session must not name a record of an earlier one
        self._pos_id.clear()
        self._una = 0
        self._nxt = 0
        self._msgs: deque[_Out] = deque()  # in the stream, not yet delivered
        self._segs: dict[int, _Seg] = {}
        self._keys: list[int] = []  # sorted segment starts
        self._retx: deque[int] = deque()
        self._txid = 0  # transmission number of the last DATA frame built
        self._last_echo = 0  # highest transmission number an ACK has echoed
        self._txmap: OrderedDict[int, _Seg] = OrderedDict()  # transmission number -> segment
        self._last_progress = now
        self._was_busy = False
        self.peer_full = False  # a new peer (or session) has said nothing of its window yet
        self._reopened = False  # nothing to re-say to a new session
        # receiving
        self._cum = 0
        self._ooo: dict[int, bytes] = {}
        self._ooo_keys: list[int] = []
        self._ack_due = False
        self._echo = 0  # transmission number of the latest DATA received (echoed in ACKs)
        self._last_pos = 0  # stream position of the latest DATA received
        self._rhead = bytearray()
        self._rtype = 0
        self._rlen: int | None = None
        self._rgot = 0
        self._rbuf = bytearray()
        self._rskip: Skipping | None = None  # the record whose bytes are being skipped (to be refused)
        self._rpos = 0
        self._rt0 = now
        self._rlast = now
        # liveness
        self._last_heard = now
        self._forgave_at: float | None = None  # _last_heard as a stop's forgiveness left it (forgive)
        self._peer_writing = -math.inf  # the last bytes of a peer's frame not (yet) whole: only a stranger's test
        self._last_sent = now
        self._writing = False  # a frame from next_frame is being written (its written() has not come)
        self._last_hello = -math.inf
        self._dgrams.clear()

    def take_events(self) -> list[_Event]:
        out, self._events = self._events, []
        return out

    def take_received(self) -> list[Received]:
        out, self._received = self._received, []
        return out

    def failures(self) -> list[DeliveryFailure]:
        return list(self._failures)

    def outcome(self, msg_id: int) -> str | None:
        return self._outcomes.get(msg_id)

    def times(self, msg_id: int) -> MessageTimes | None:
        return self._times.get(msg_id)

    @property
    def queued_bytes(self) -> int:
        """Bytes of reliable messages accepted by :meth:`submit` and not yet delivered or failed."""
        return self._pending_bytes + len(self._sbuf)

    @property
    def idle(self) -> bool:
        """Nothing queued or unacknowledged."""
        return not self._pending and not self._sbuf

    def _remember(self, table: OrderedDict, key: int, value: object, cap: int = 8192) -> None:
        table[key] = value
        table.move_to_end(key)
        while len(table) > cap:
            table.popitem(last=False)

    def _fail(self, msg: _Out, reason: str) -> None:
        self._remember(self._outcomes, msg.id, f"failed: {reason}")
        self._failures.append(DeliveryFailure(msg.id, msg.name, reason))
        self.stats["failures"] += 1

    def _drop_all(self, reason: str, now: float) -> None:
        """The session ended: every message in its stream not yet delivered fails with ``reason``."""
        for m in self._msgs:
            self._fail(m, reason)
        self._reset_session_state(now)

    def _lose(self, reason: str, now: float, kind: str = "lost", notify: bool = True) -> None:
        self.stats["peer_losses"] += 1
        if notify and not self.closed and self.sess.peer:  # best effort: tell the peer why, so its error says so
            self._control.clear()
            lost = close_frame(
                self.sess.local,
                self.sess.peer,
                self._cum % POS_MOD,
                f"session lost: {reason}",
                CLOSE_LOST,
                self.peer_max_frame,
            )
            self._control.append(lost)
        self._drop_all(f"session lost: {reason}", now)
        self.sess.lose()
        self._events.append(_Event(kind, reason, self.sess.epoch))
        self._queue_hello()
        self._last_hello = now

    # ------------------------------------------------------------------ application side
    def submit(
        self, type_code: int, body: bytes, name: str, now: float, reliable: bool = True, epoch: int | None = None
    ) -> int:
        """Queue an encoded message; returns its id. Unreliable messages that fit one frame go as DGRAM.

        ``epoch``: the message belongs to that session; if it is not the one up now, the message
        fails at once instead of going to whichever peer connects next.
        """
        if self.closed:
            raise InputError("link is closed")
        mid = self._next_id
        self._next_id += 1
        if not reliable and (not self.sess.established or (epoch is not None and epoch != self.sess.epoch)):
            # unreliable by definition: no session, no heartbeat. Not a delivery failure: a board between grounds
            # counted 4 a second and pushed real failures out of failures() (review of stop 66)
            self.stats["dgrams_dropped"] += 1
            return mid
        if epoch is not None and (epoch != self.sess.epoch or not self.sess.established):
            self._remember(self._outcomes, mid, "failed: its session has ended")
            self._failures.append(DeliveryFailure(mid, name, f"session {epoch} has ended"))
            self.stats["failures"] += 1
            return mid
        if not reliable and len(body) + OVERHEAD + 1 <= min(self.cfg.max_frame, self.peer_max_frame):
            if self.sess.established:
                stale = [d for d in self._dgrams if d[0] == type_code]
                for d in stale:
                    self._dgrams.remove(d)
                self.stats["dgrams_superseded"] += len(stale)
                self._dgrams.append((type_code, body))
            else:
                self.stats["dgrams_dropped"] += 1  # unreliable by definition: no session, no heartbeat
            return mid
        if len(body) > self.cfg.limits.max_message_bytes:
            raise InputError(f"message of {len(body)} bytes exceeds the {self.cfg.limits.max_message_bytes}-byte limit")
        msg = _Out(mid, type_code, name, RECORD.pack(type_code, len(body)) + body, now)
        self._remember(self._outcomes, mid, "pending")
        self._remember(self._times, mid, MessageTimes(now))
        self.stats["messages_sent"] += 1
        if self.sess.established:
            self._append(msg)
        else:
            self._pending.append(msg)
            self._pending_bytes += len(msg.record)
        return mid

    def _append(self, msg: _Out) -> None:
        msg.start = self._una + len(self._sbuf)
        msg.end = msg.start + len(msg.record)
        self._sbuf += msg.record
        msg.record = b""
        self._msgs.append(msg)
        self._remember(self._pos_id, msg.start, (msg.id, msg.name))

    def can_accept(self, nbytes: int) -> bool:
        q = self.queued_bytes
        return q == 0 or q + nbytes <= self.cfg.send_buffer

    def held_bytes(self) -> dict[str, int]:
        """Memory held on the receive side (the bounds the fuzz campaign checks)."""
        return {
            "frame": self.decoder.pending_bytes,
            "out_of_order": sum(len(v) for v in self._ooo.values()),
            "reassembly": len(self._rbuf),
        }

    @property
    def ack_pending(self) -> bool:
        """An ACK for what was received is due or a frame is being written: the peer may not yet know all of it."""
        return self._ack_due or self._writing

    @property
    def control_pending(self) -> bool:
        """Control frames (HELLO, CLOSE, REJECT) not yet handed to the line."""
        return bool(self._control)

    def fail_all(self, reason: str) -> None:
        """Fail every message not yet delivered (the link is going away)."""
        for m in list(self._msgs) + list(self._pending):
            self._fail(m, reason)
        self._msgs.clear()
        self._pending.clear()
        self._pending_bytes = 0

    def transport_failed(self, reason: str, now: float) -> None:
        """The byte stream itself is gone: end the session, fail everything, accept nothing more."""
        self._lose(f"transport failed: {reason}", now, notify=False)
        self.fail_all(f"transport failed: {reason}")
        self.closed = True
        self._events.clear()

    def close(self, reason: str = "its program ended, or was stopped") -> None:
        """Queue a CLOSE for the peer (if any) and stop accepting messages."""
        if self.closed:
            return
        self.closed = True
        if self.sess.peer:
            self._control.append(
                close_frame(self.sess.local, self.sess.peer, self._cum % POS_MOD, reason, max_frame=self.peer_max_frame)
            )

    # ------------------------------------------------------------------ transmitting
    def _queue_hello(self) -> None:
        """Queue a HELLO, or bring the one still queued up to date: at most one waits. Below ~1040 baud a HELLO takes
        longer than the 0.25 s between them while a side waits for its peer, and the queue grew without bound; once
        the session was up, the stale HELLOs went ahead of ACKs and DATA and lost it (stop 60's review)."""
        frame = hello_frame(self.sess.local, self.sess.peer, self.cfg.max_frame, self.cfg.window)
        for i, queued in enumerate(self._control):
            if queued is self._queued_hello:
                self._control[i] = self._queued_hello = frame
                return
        self._control.append(frame)
        self._queued_hello = frame

    def _ack(self) -> bytes:
        ranges: list[tuple[int, int]] = []
        for k in self._ooo_keys:
            e = k + len(self._ooo[k])
            if ranges and ranges[-1][1] >= k:
                ranges[-1] = (ranges[-1][0], max(ranges[-1][1], e))
            else:
                ranges.append((k, e))
        # RFC 2018: the first block holds the most recently received data, so over successive ACKs the
        # sender learns of every range even when there are more than 16; then the lowest ones
        recent = next((r for r in ranges if r[0] <= self._last_pos < r[1]), None)
        if recent is not None:
            ranges.remove(recent)
            ranges.insert(0, recent)
        self.stats["acks_sent"] += 1
        # a small-frame peer drops a longer ACK (section 1)
        sacks = [(a % POS_MOD, b % POS_MOD) for a, b in ranges[: ack_sack_room(self.peer_max_frame)]]
        window = 0 if self.rx_full else self.cfg.window
        return ack_frame(self.sess.local, self.sess.peer, self._cum % POS_MOD, window, sacks, self._echo)

    def set_rx_full(self, full: bool, now: float) -> None:
        """The owner's receive queue is full (True) or has room again (False). While full, new stream bytes are
        dropped unread and acknowledged with window 0 (the peer holds its data and probes, and does not take the
        pause for a stalled session); when room returns, an ACK with the window goes at once."""
        if full != self.rx_full:
            self.rx_full = full
            self._reopened = not full  # re-said until in-order bytes come again, for a peer timeout at most (poll)
            self._reopened_at = now
            self._ack_due = True
            self._rlast = now  # a record held half read meanwhile waited on this side: its clock starts again

    def _payload_size(self) -> int:
        return max(self.cfg.min_frame, min(self._frame, self.cfg.max_frame, self.peer_max_frame)) - DATA_OVERHEAD

    def _bytes(self, a: int, b: int) -> bytes:
        return bytes(self._sbuf[a - self._una : b - self._una])

    def _insert_seg(self, seg: _Seg) -> None:
        self._segs[seg.start] = seg
        if not self._keys or seg.start > self._keys[-1]:
            self._keys.append(seg.start)
        else:
            bisect.insort(self._keys, seg.start)

    def _sendable(self) -> int:
        """How many new stream bytes may go now: those waiting, within the window; 0 when closed or at the
        segment limit."""
        if self.closed or len(self._segs) >= self.cfg.max_segments:
            return 0
        inflight = self._nxt - self._una
        room = min(self.cfg.window, self.peer_window) - inflight
        if self.peer_full:  # a zero window: one small probe in flight, whose ACK says when the peer has room
            room = PROBE_BYTES if inflight == 0 else 0
        return max(0, min(room, self._una + len(self._sbuf) - self._nxt))

    def _data_ready(self) -> bool:
        """A DATA frame could go now: a retransmission is due, or new bytes may go."""
        return bool(self._retx) or self._sendable() > 0

    def next_frame(self, now: float) -> tuple[bytes, int | None] | None:
        """The next frame to write and a token for :meth:`written` (a DATA transmission number, or None)."""
        out = self._next_frame(now)
        self._writing = self._writing or out is not None
        return out

    def _next_frame(self, now: float) -> tuple[bytes, int | None] | None:
        if self._control:
            return self._control.popleft(), None
        if not self.sess.established:
            return None
        if self._ack_due:
            self._ack_due = False
            self._last_ack_at = now
            return self._ack(), None
        if self._dgrams and (self._dgram_turn or not self._data_ready()):
            self._dgram_turn = False
            t, body = self._dgrams.popleft()
            return dgram_frame(self.sess.local, self.sess.peer, t, body), None
        self._dgram_turn = True
        if self._txid >= POS_MOD - 1 and self._data_ready():  # a u32 txid: 4 TiB of 1 kB frames in one session
            self._lose("transmission numbers exhausted (2**32 DATA frames in one session)", now)
            return None
        k = self._payload_size()
        while self._retx:
            start = self._retx.popleft()
            seg = self._segs.get(start)
            if seg is None or seg.acked or not seg.queued:
                continue
            if self.peer_full:  # the probe: the range's first bytes alone, the scoreboard unchanged (a cum landing
                # inside the range trims it); the whole range goes again when the window reopens (_on_ack). Review of
                # stop 69: splitting the range instead fragmented it
                self.stats["probes"] += 1
                return self._transmit(seg, now, min(seg.end, seg.start + PROBE_BYTES)), self._txid
            if seg.end - seg.start > k:  # the line got worse: resend the range in smaller frames
                tail = _Seg(seg.start + k, seg.end, tx=seg.tx, queued=True, refused=seg.refused)
                seg.end = seg.start + k
                self._insert_seg(tail)
                self._retx.appendleft(tail.start)
            if seg.refused:  # the HIL reads retransmits as what mended line noise: a pause's resends are apart
                seg.refused = False
                self.stats["refused_resends"] += 1
            else:
                self.stats["retransmits"] += 1
                self.stats["retransmit_bytes"] += seg.end - seg.start
            return self._transmit(seg, now), self._txid
        sendable = self._sendable()
        if sendable <= 0:
            return None
        n = min(k, sendable, POS_MOD - self._nxt % POS_MOD)  # no frame crosses 2**32: its pos + len fits a u32
        if self.peer_full:  # new data as the probe, nothing being in flight
            self.stats["probes"] += 1
        seg = _Seg(self._nxt, self._nxt + n)
        self._insert_seg(seg)
        self._nxt += n
        self._stamp(seg, now, now)  # provisional times: the ack may beat written()
        return self._transmit(seg, now), self._txid

    def _transmit(self, seg: _Seg, now: float, upto: int | None = None) -> bytes:
        """A DATA frame for ``seg`` under a new transmission number (echoed back by the receiver's ACK); ``upto``:
        its bytes below that position only (a zero-window probe)."""
        self._txid += 1
        seg.order = self._txid
        seg.tx += 1
        seg.sent_at = now  # provisional until written()
        self._last_write(seg, now, pending=True)  # likewise: the ack may beat written()
        self._txmap[self._txid] = seg
        if len(self._txmap) > 8192:
            self._txmap.popitem(last=False)
        end = seg.end if upto is None else upto
        return data_frame(self.sess.local, self.sess.peer, seg.start % POS_MOD, self._bytes(seg.start, end), self._txid)

    def _carried(self, seg: _Seg) -> list[tuple[int, int, MessageTimes]]:
        """(start, end, times) of the messages ``seg`` carries bytes of, remembered on it at its first call and
        kept to its current range (a split for retransmission or a partial ACK narrows it)."""
        if not seg.msgs:
            for m in self._msgs:
                if m.start >= seg.end:
                    break
                t = self._times.get(m.id)
                if m.end > seg.start and t is not None:
                    seg.msgs.append((m.start, m.end, t))
        return [m for m in seg.msgs if m[0] < seg.end and m[1] > seg.start]

    def _stamp(self, seg: _Seg, started: float, now: float) -> None:
        """First transmission of ``seg``: the line times of the messages it starts or ends."""
        for m_start, m_end, t in self._carried(seg):
            if seg.start <= m_start and (t.first_tx is None or t.first_tx < started):
                t.first_tx = started
            if seg.start < m_end <= seg.end:
                t.written = now

    def _last_write(self, seg: _Seg, now: float, pending: bool = False) -> None:
        """Any write of ``seg``: the latest line time of the messages it carries bytes of (``pending``: handed to
        the writer, which has not recorded the write's end yet)."""
        for _, _, t in self._carried(seg):
            t.last_tx = now
            t.last_tx_pending = pending

    def written(
        self, token: int | None, nbytes: int, now: float, ok: bool = True, started: float | None = None
    ) -> None:
        """The frame from :meth:`next_frame` has been written (``ok``) or its write timed out.

        ``started``: when its first byte went onto the line (default ``now``), for line times.
        """
        self._last_sent = now
        self._writing = False
        self.stats["frames_sent"] += 1
        self.stats["bytes_sent"] += nbytes
        if token is None:
            return
        self.stats["data_frames_sent"] += 1
        seg = self._txmap.get(token)
        if seg is None or seg.order != token:
            return  # acknowledged already, or transmitted again since
        seg.sent_at = now if ok else now - self._rto * self._backoff  # a timed-out write counts as lost at once
        self._last_write(seg, now)
        if seg.tx == 1:  # even when the ACK beat this call: the messages' line times end with the write
            self._stamp(seg, now if started is None else started, now)
        if seg.acked:
            return
        seg.queued = False

    # ------------------------------------------------------------------ receiving
    def receive(self, data: bytes, now: float) -> None:
        """Feed bytes read from the line."""
        self.stats["bytes_received"] += len(data)
        frames = self.decoder.feed(data)
        if self.sess.peer and self.sess.peer in self.decoder.claimed:
            self._peer_writing = now  # a frame of the peer's on the line, not whole yet
        for f in frames:
            self._on_frame(f, now)
        for k in ("crc_errors", "malformed", "oversize", "resyncs", "bytes_discarded"):
            self.stats[k] = self.decoder.stats[k]
        self.stats["malformed"] += self._bad_acks  # the frames well formed but acknowledging what was never sent

    def _on_frame(self, f: WireFrame, now: float) -> None:
        self.stats["frames_received"] += 1
        if self.closed:  # we said CLOSE: whatever the peer says now is not for this link
            return
        if f.src == self.sess.local:  # our own frame came back: the line echoes; a HELLO taken would be a session
            self.stats["echoed_frames"] += 1  # with ourselves (a ground then waited out deadlines on its own frames)
            if now - self._echo_said >= ECHO_EVENT_S:  # an event per frame would push others out of the event queue
                self._echo_said = now
                self._events.append(_Event("echo", ECHO_TEXT, self.sess.epoch))
            return
        if f.kind == HELLO:
            if self.sess.retired(f.src):
                self.stats["old_session_frames"] += 1
                return
            heard = max(self._last_heard, self._peer_writing)
            if self.sess.established and f.src != self.sess.peer and now - heard < self._live_peer_s():
                # a new session's HELLO while the peer of this one still talks: not a restart (a restarted peer's
                # old session falls silent, and it repeats its HELLO until answered), another device on the line.
                # One such frame took the session over, cost the pair in flight and blamed the board (stop 60's QA)
                self.stats["foreign_hellos"] += 1
                if f.src in self._held_hellos or len(self._held_hellos) < HELD_HELLO_IDS:  # bounded: ids are free
                    self._held_hellos[f.src] = self._held_hellos.get(f.src, 0) + 1
                if now - self._foreign_said >= ECHO_EVENT_S:
                    self._foreign_said = now
                    self._events.append(_Event("foreign", FOREIGN_HELLO_TEXT.format(f.src), self.sess.epoch))
                return
            ended = self.epoch  # the "restarted" event names the session that ended, not the one starting
            was_up = self.sess.established
            replaced, reply, newly = self.sess.on_hello(f.src, f.dst)
            if replaced is not None:
                self._drop_all(
                    f"peer started a new session {f.src:08x} (it restarted, or gave up on session {replaced:08x})", now
                )
            # a session that never completed its handshake is no restart: a board opening a line that still held a
            # dead ground's HELLOs said "the peer restarted" before it served anything
            held = self._held_hellos.pop(f.src, 0) if replaced is not None else 0
            self._held_hellos.clear()
            if held:  # they were this restart's, not a stranger's: no longer counted as foreign
                self.stats["foreign_hellos"] -= held
            if replaced is not None and was_up:
                self.stats["peer_restarts"] += 1
                waited = f"; the {held} HELLO(s) held back as the old session's last seconds ran were its own"
                waited = waited if held else ""
                self._events.append(
                    _Event(
                        "restarted",
                        f"the peer started a new link session (it restarted, or gave up the last one) "
                        f"(session {replaced:08x} -> {f.src:08x}){waited}",
                        ended,
                    )
                )
            self.peer_max_frame = f.max_frame
            self.peer_window = max(f.window, MIN_FRAME)
            self._last_heard = now
            if newly:
                self._on_established(now)
            elif reply and now - self._last_hello >= self.cfg.hello_interval / 2:
                self._queue_hello()
                self._last_hello = now
            return
        verdict = self.sess.classify(f.src, f.dst)
        if verdict != "ok":
            self.stats["old_session_frames" if verdict == "old" else "foreign_frames"] += 1
            if verdict == "old" and f.src == self.sess.peer and now - self._last_hello >= self.cfg.hello_interval:
                self._queue_hello()  # the peer addresses an earlier incarnation of us: tell it who we are
                self._last_hello = now
            return
        self._last_heard = now
        if self.sess.confirm():
            self._on_established(now)
        if f.kind == DATA:
            self._on_data(f, now)
        elif f.kind == ACK:
            self._on_ack(f, now)
        elif f.kind == DGRAM:
            if self.rx_full:  # unreliable by definition: not held while the application takes nothing
                self.stats["dgrams_dropped"] += 1
            elif f.type_code != Heartbeat.TYPE:  # section 4: only a Heartbeat travels so; a Result as a datagram
                # would reach the application out of order with the stream (review of stop 66)
                self.stats["decode_errors"] += 1
                self._arrivals += 1
                why = f"a datagram of message type {f.type_code}: only Heartbeats (type {Heartbeat.TYPE}) go so"
                self._refusals.append(Refusal(f.type_code, why, now, self._arrivals, None))
            else:
                self._deliver(f.type_code, f.payload, -1, now, now, f.wire_bytes)
        elif f.kind == CLOSE:  # its cum acknowledges what the peer received before closing
            cum = max(unwrap(f.cum, self._una), self._una) % POS_MOD
            self._on_ack(WireFrame(ACK, f.src, f.dst, cum=cum, window=self.peer_window), now)
            if f.code == CLOSE_LOST:  # it gave up on this session and will start a new one
                self._lose(f"peer gave up on the session ({f.reason or 'no reason given'})", now, notify=False)
            else:
                self._lose(f"peer closed the link ({f.reason or 'no reason given'})", now, "closed", notify=False)
        elif f.kind == REJECT:
            self.stats["rejected_received"] += 1
            hit = self._pos_id.get(unwrap(f.pos, self._una))
            if hit is not None and not str(self._outcomes.get(hit[0], "")).startswith("failed"):
                self._remember(self._outcomes, hit[0], f"failed: peer rejected: {f.reason}")
                self._failures.append(DeliveryFailure(hit[0], hit[1], f"peer rejected: {f.reason}"))
                self.stats["failures"] += 1

    def _live_peer_s(self) -> float:
        """How recently the peer must have been heard for another session's HELLO to be a stranger's: it sends a
        keepalive HELLO whenever it has sent nothing for ``keepalive`` s. "Heard" counts the bytes of a frame still
        arriving that names the peer (``StreamDecoder.claimed``): on a slow line one frame outlasts this."""
        return 1.5 * self.cfg.keepalive

    def _on_established(self, now: float) -> None:
        self.stats["sessions"] = self.sess.epoch
        self._last_heard = now
        self._last_progress = now
        text = f"session {self.sess.local:08x} <-> {self.sess.peer:08x}"
        self._events.append(_Event("established", text, self.epoch))
        self._queue_hello()  # so the other side establishes too
        self._last_hello = now
        while self._pending:
            m = self._pending.popleft()
            self._pending_bytes -= len(m.record)
            self._append(m)

    def _on_data(self, f: WireFrame, now: float) -> None:
        s = unwrap(f.pos, self._cum)
        e = s + len(f.payload)
        self._ack_due = True
        self._echo = max(self._echo, f.txid)
        self._last_pos = s
        if e <= self._cum:
            self.stats["duplicates_dropped"] += 1
            return
        lo, hi = max(s, self._cum), min(e, self._cum + (0 if self.rx_full else self.cfg.window))
        if lo >= hi:
            self.stats["rx_full_drops" if self.rx_full else "out_of_window"] += 1
            return
        data = f.payload[lo - s : hi - s]
        if lo == self._cum:
            self._consume(data, now)
            while self._ooo_keys and self._ooo_keys[0] <= self._cum:
                k = self._ooo_keys.pop(0)
                d = self._ooo.pop(k)
                if k + len(d) > self._cum:
                    self._consume(d[self._cum - k :], now)
            return
        if not self._ooo and self._rlen is None and not self._rhead:
            self._rlast = now  # nothing was pending: the reassembly clock starts now, not at the last message
        pieces = [(lo, hi)]
        i = max(0, bisect.bisect_right(self._ooo_keys, lo) - 1)
        while i < len(self._ooo_keys) and self._ooo_keys[i] < hi:  # keep only what is not held yet
            a, b = self._ooo_keys[i], self._ooo_keys[i] + len(self._ooo[self._ooo_keys[i]])
            pieces = [q for p0, p1 in pieces for q in ((p0, min(p1, a)), (max(p0, b), p1)) if q[0] < q[1]]
            i += 1
        if not pieces:
            self.stats["duplicates_dropped"] += 1
        for a, b in pieces:
            self._ooo[a] = data[a - lo : b - lo]
            bisect.insort(self._ooo_keys, a)

    def _consume(self, data: bytes, now: float) -> None:
        """In-order stream bytes -> records -> messages (bounded: a record over the limit is skipped)."""
        self._reopened = False
        pos = self._cum
        self._cum += len(data)
        self._rlast = now
        i = 0
        while i < len(data):
            if self._rlen is None:
                if not self._rhead:
                    self._rpos, self._rt0 = pos + i, now
                take = data[i : i + RECORD.size - len(self._rhead)]
                self._rhead += take
                i += len(take)
                if len(self._rhead) < RECORD.size:
                    break
                self._rtype, n = RECORD.unpack(self._rhead)
                self._rhead.clear()
                self._rlen, self._rgot, self._rbuf, self._rskip = n, 0, bytearray(), None
                limit = self.cfg.limits.max_message_bytes
                if n > limit or self._rtype not in MESSAGE_TYPES:
                    why = (
                        f"message of {n} bytes exceeds the {limit}-byte limit"
                        if n > limit
                        else f"unknown message type code {self._rtype}"
                    )
                    self._rskip = Skipping(self._rtype, n, self._rpos, why, oversize=n > limit)
            take_n = min(len(data) - i, self._rlen - self._rgot)
            if self._rskip is None:
                self._rbuf += data[i : i + take_n]
            self._rgot += take_n
            i += take_n
            if self._rgot == self._rlen:
                if self._rskip is not None:
                    self.stats["reassembly_errors"] += 1
                    self._reject(self._rpos, self._rskip.reason, self._rtype, now)
                else:
                    self._deliver(self._rtype, bytes(self._rbuf), self._rpos, self._rt0, now, self._rlen)
                self._rlen, self._rbuf, self._rskip = None, bytearray(), None

    def _reject(self, pos: int, reason: str, type_code: int, now: float, seqs: tuple[int, int] | None = None) -> None:
        self.stats["rejected_sent"] += 1
        self._arrivals += 1
        self._refusals.append(Refusal(type_code, reason, now, self._arrivals, seqs))
        self._control.append(reject_frame(self.sess.local, self.sess.peer, pos % POS_MOD, reason, self.peer_max_frame))

    def take_refusals(self) -> list[Refusal]:
        """Each message refused from the peer since the last call (the latest
        :data:`REFUSALS_KEPT`; ``stats`` counts them all): a record over the size limit or of an unknown type,
        a body that fails to decode or the schema. Refused datagrams are listed too (they get no REJECT)."""
        out = []
        while self._refusals:  # popped one by one: the link's I/O thread may append meanwhile
            out.append(self._refusals.popleft())
        return out

    @property
    def refusing(self) -> str | None:
        """Why the record arriving now will be refused once its last byte is in (it is over the size limit or of
        an unknown type: its bytes are skipped as they come), or None."""
        skip = self._rskip
        return skip.reason if skip is not None else None

    @property
    def skipping(self) -> Skipping | None:
        """The record arriving now that will be refused once its last byte is in, or None (one read: safe from
        another thread). Until then nothing behind it in the stream can be read."""
        return self._rskip

    def abandon(self, reason: str, now: float) -> None:
        """The owner gives up on the session (e.g. the peer's stream is held by a record over the size limit, which
        cannot be resynchronised short of skipping all of it): the peer is told (CLOSE code 1), every message in
        flight fails with ``reason``, and a new session starts as after any loss."""
        if self.closed or not self.sess.established:
            return
        self._lose(reason, now)

    def _deliver(self, type_code: int, body: bytes, pos: int, t_first: float, now: float, nbytes: int) -> None:
        try:
            msg = decode_parts(body, (), self.cfg.limits, expect_type=type_code)
        except InputError as exc:
            self.stats["decode_errors"] += 1
            seqs = getattr(exc, "frame_seqs", None)
            if pos >= 0:
                self._reject(pos, str(exc), type_code, now, seqs)
            else:
                self._arrivals += 1
                self._refusals.append(Refusal(type_code, str(exc), now, self._arrivals, seqs))
            return
        self.stats["messages_received"] += 1
        self._arrivals += 1
        self._received.append(Received(msg, pos, t_first, now, nbytes, self.epoch, self._arrivals))

    def _on_ack(self, f: WireFrame, now: float) -> None:
        self.stats["acks_received"] += 1
        cum = unwrap(f.cum, self._una)
        sacks = [(unwrap(a, cum), unwrap(b, cum)) for a, b in f.sacks]  # each above cum (framing checks it)
        if cum > self._nxt or any(b > self._nxt for _, b in sacks) or f.echo > self._txid:
            self._bad_acks += 1  # acknowledges what was never sent: counted as malformed (receive())
            self.stats["malformed"] += 1
            return
        if f.window == 0:  # its application is not reading: a pause, not a stall (set_rx_full)
            if not self.peer_full:
                self.stats["peer_full"] += 1
            self.peer_full = True
            self._last_progress = now
            # what waits for retransmission does not go now (one probe at a time, chosen by poll): held as sent, it
            # goes when the window reopens (review of stop 69: each went as a probe of its own, back to back)
            writing = self._txmap.get(self._txid) if self._writing else None
            for start in self._retx:
                seg = self._segs.get(start)
                if seg is not None and seg.queued and not seg.acked and seg is not writing:
                    seg.queued = False
                    if seg.sent_at is None:  # a tail cut off for resending, never sent in its own frame
                        seg.sent_at = now
            self._retx.clear()
        else:
            if self.peer_full:  # the window reopens: what went while it was shut was dropped unread, so it goes
                # again now, not after a backed-off timeout; still as refused, not lost: the frame size stays
                # (cleared after the loop, it fell 1024 -> 229 B on a clean line; review of stop 66)
                for seg in self._segs.values():
                    if not seg.acked and not seg.queued and seg.sent_at is not None:
                        seg.refused = True
                        self._retransmit(seg)
                self.peer_full = False
                self._backoff = 1.0
                self._last_progress = now  # the stall clock starts with the window, not at the last probe
            self.peer_window = max(MIN_FRAME, f.window)
        newly: list[_Seg] = []
        if cum > self._una:
            n = 0
            for k in self._keys:
                seg = self._segs[k]
                if seg.start >= cum:
                    break
                if seg.end <= cum:
                    del self._segs[k]
                    n += 1
                    if not seg.acked:
                        seg.acked = True
                        newly.append(seg)
                else:  # straddles cum: keep the unacknowledged tail
                    del self._segs[k]
                    seg.start = cum
                    self._segs[seg.start] = seg
                    self._keys[n] = seg.start
                    if seg.queued:
                        self._retx.append(seg.start)
                    break
            del self._keys[:n]
            del self._sbuf[: cum - self._una]
            self._una = cum
            while self._msgs and self._msgs[0].end <= self._una:
                self._delivered(self._msgs.popleft(), now)
        for a, b in sacks:
            i = bisect.bisect_left(self._keys, a)
            while i < len(self._keys) and self._keys[i] < b:
                seg = self._segs[self._keys[i]]
                if seg.end <= b and not seg.acked:
                    seg.acked = True
                    newly.append(seg)
                i += 1
        if f.echo > self._last_echo:  # the DATA frame that triggered this ACK: one exact RTT sample
            self._last_echo = f.echo
            hit = self._txmap.get(f.echo)
            if hit is not None and hit.order == f.echo and hit.sent_at is not None:
                self._rtt(max(now - hit.sent_at, 0.0))
        for seg in newly:
            self._loss_sample(0.0, seg.end - seg.start + DATA_OVERHEAD)
        if newly:
            self._last_progress = now
            self._backoff = 1.0
        # RACK with exact ordering: a segment whose latest transmission went out before the frame the
        # receiver just reported (a serial line does not reorder) and is still unacknowledged was lost. Not while
        # the window is 0: the receiver refused them, and resending each on every ACK kept the line 65-95 % busy
        # (review of stop 66); one probe goes on its timer (poll)
        if not self.peer_full:
            for seg in self._segs.values():
                if not seg.acked and not seg.queued and seg.order < f.echo:
                    self._retransmit(seg)

    def _delivered(self, m: _Out, now: float) -> None:
        if not str(self._outcomes.get(m.id, "")).startswith("failed"):  # a REJECTed one is a failure, not both
            self.stats["delivered"] += 1
            self._remember(self._outcomes, m.id, "delivered")
        t = self._times.get(m.id)
        if t is not None:
            t.delivered = now

    def _retransmit(self, seg: _Seg) -> None:
        seg.queued = True
        self._retx.append(seg.start)
        if not self.peer_full:  # refused by a full peer is not lost on the line: the frame size stays
            self._loss_sample(1.0, seg.end - seg.start + DATA_OVERHEAD)

    def _rtt(self, r: float) -> None:
        if self._srtt is None:
            self._srtt, self._rttvar = r, r / 2
        else:
            self._rttvar = 0.75 * self._rttvar + 0.25 * abs(self._srtt - r)
            self._srtt = 0.875 * self._srtt + 0.125 * r
        self._rto = min(self.cfg.rto_max, max(self.cfg.rto_min, self._srtt + 4 * self._rttvar))

    def _loss_sample(self, lost: float, size: int) -> None:
        a = 1.0 / 32
        self._loss = (1 - a) * self._loss + a * lost
        self._mean_frame = (1 - a) * self._mean_frame + a * size
        if not self.cfg.adaptive:
            return
        if self._loss <= 1e-6:
            self._frame = self.cfg.max_frame
            return
        e = -math.log(1.0 - min(self._loss, 0.999)) / max(self._mean_frame, 1.0)
        h = float(DATA_OVERHEAD + 2)
        f = (e * h + math.sqrt(e * e * h * h + 4 * e * h)) / (2 * e)
        self._frame = int(max(self.cfg.min_frame, min(self.cfg.max_frame, f)))

    # ------------------------------------------------------------------ timers
    def forgive(self, gap: float) -> bool:
        """This process was not scheduled for ``gap`` s (SIGSTOP, a paused VM, a starved host): the peer's silence
        meanwhile is this side's. Its liveness, progress and reassembly clocks restart, so that the peer's frames,
        sent once it too runs again, are heard before it is judged (a 3 s stop of a process holding both ends of a
        2 s link lost both sessions on waking, 3 of 3). As on ZeroMQ (:mod:`protocol.links`), the silence is forgiven
        once between two hearings of the peer (:func:`protocol.stall.forgiven_hearing`). The connect timeout of what
        waits for a session is this side's own clock and moves with every stop, as on ZeroMQ. True when forgiven."""
        for m in self._pending:
            m.submitted += gap
        heard = forgiven_hearing(self._last_heard, self._forgave_at, gap)
        if heard is None:
            return False
        self._last_heard = self._forgave_at = heard
        self._last_progress += gap
        self._rlast += gap
        return True

    def poll(self, now: float) -> None:
        """Timers: retransmission, keepalive, handshake, liveness, reassembly, connect timeout."""
        if self.closed:
            return
        cfg = self.cfg
        if not self.sess.established:
            if now - self._last_hello >= cfg.hello_interval:
                self._queue_hello()
                self._last_hello = now
            if cfg.connect_timeout is not None:
                while self._pending and now - self._pending[0].submitted > cfg.connect_timeout:
                    m = self._pending.popleft()
                    self._pending_bytes -= len(m.record)
                    self._fail(m, f"no session with the peer within {cfg.connect_timeout:g} s")
            return
        # only when the line is idle (the module doc): at 300 baud a 1 kB frame is written for 34 s, and one keepalive
        # a second queued meanwhile, each 0.8 s on the line and ahead of DATA, starved the stream ("peer stopped
        # acknowledging ... 0 bytes unacknowledged", stop 60's QA)
        idle = not self._writing and not self._control
        if self._reopened and now - self._reopened_at > (cfg.peer_timeout or 4.0):
            self._reopened = False  # a peer with nothing more to send: the window was said often enough
        if (self.rx_full or self._reopened) and now - self._last_ack_at >= cfg.keepalive / 2:
            # while full, and after until the stream moves again, the window is said twice a keepalive: the peer's
            # probes slow to one per 2 s, and on a noisy line a pause must not read as silence to it, nor a lost
            # window update hold it (review of stop 66)
            self._ack_due = True
        # during a pause little else goes either way: keepalives twice as often, so that a noisy line's lost frames
        # do not add up to a peer's silence
        keepalive = cfg.keepalive / 2 if (self.rx_full or self.peer_full) else cfg.keepalive
        if idle and now - max(self._last_keepalive, self._last_sent) >= keepalive:
            self._last_keepalive = now
            self._queue_hello()
        busy = bool(self._sbuf)
        if busy and not self._was_busy:
            self._last_progress = now
        self._was_busy = busy
        pt = cfg.peer_timeout
        if pt is not None:
            if now - self._last_heard > pt:
                self._lose(f"no frame from the peer for {now - self._last_heard:.1f} s (timeout {pt:g} s)", now)
                return
            if busy and not self.peer_full and now - self._last_progress > pt:
                self._lose(
                    f"peer stopped acknowledging: no progress for {now - self._last_progress:.1f} s "
                    f"({self._nxt - self._una} bytes unacknowledged, {len(self._sbuf)} in the stream; "
                    f"timeout {pt:g} s)",
                    now,
                )
                return
            partial = self._rlen is not None or bool(self._rhead) or bool(self._ooo)
            # a noisy line may hold a gap for a few RTOs; a sender that stopped is caught by silence anyway
            if partial and not self.rx_full and now - self._rlast > 2 * pt:
                held = sum(len(v) for v in self._ooo.values())
                what = (
                    f"record at {self._rpos}: {self._rgot} of {self._rlen} bytes"
                    if self._rlen is not None
                    else f"{len(self._rhead)} header bytes"
                )
                self._lose(
                    f"reassembly stalled: nothing in order for {2 * pt:g} s ({what}; stream at {self._cum}, "
                    f"{held} bytes held beyond a gap)",
                    now,
                )
                return
        rto = min(cfg.rto_max, self._rto * self._backoff)
        expired = [
            s
            for s in self._segs.values()
            if not s.acked and not s.queued and s.sent_at is not None and now - s.sent_at > rto
        ]
        if self.peer_full:  # window 0: the lowest unacknowledged segment alone is the probe, on its own timer
            lowest = min((seg for seg in self._segs.values() if not seg.acked), key=lambda seg: seg.start, default=None)
            expired = [lowest] if lowest is not None and lowest in expired else []
        if expired:
            self.stats["timeouts"] += 1
            for seg in expired:
                self._retransmit(seg)
            if now - self._last_timeout >= rto:  # back off once per timeout period, not per segment
                self._backoff = min(self._backoff * 2, 64.0)
                self._last_timeout = now

    def snapshot(self) -> dict[str, float]:
        out = dict(self.stats)
        out.update(
            rto_s=min(self.cfg.rto_max, self._rto * self._backoff),
            srtt_s=self._srtt if self._srtt is not None else math.nan,
            frame_bytes=float(self._payload_size() + DATA_OVERHEAD),
            loss_rate=self._loss,
            queued_bytes=float(self.queued_bytes),
            unacked_bytes=float(self._nxt - self._una),
            established=float(self.sess.established),
            sessions=float(self.sess.epoch),
        )
        return out
