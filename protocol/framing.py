"""Self-synchronising stream frames for serial lines and byte streams.

One frame on the wire (HDLC-style byte stuffing, RFC 1662 section 4.2)::

    0x7E | stuff( header | payload | CRC32 ) | 0x7E
    header  = version:u8 | type:u8 | flags:u16 | seq:u32 | payload_len:u32   (big-endian)
    CRC32   = zlib.crc32(header + payload), big-endian
    stuff   : 0x7D -> 0x7D 0x5D, 0x7E -> 0x7D 0x5E   (so 0x7E only ever delimits)

Why stuffing with a flag byte rather than a start word plus length (F Prime):
a frame whose tail was lost is closed by the next frame's opening flag, so the
decoder resynchronises at once instead of waiting for ``payload_len`` bytes
that will never come. Stuffing and unstuffing are ``bytes.replace`` calls
(C speed); for random data the overhead is ~2/256.

:class:`StreamDecoder` splits the byte stream on flags and checks each piece
(escape validity, length, CRC, payload decode); anything wrong is counted and
dropped, never raised. Empty pieces (two adjacent flags) are idle fill.
"""

from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass

from protocol.codec import DEFAULT_LIMITS, Limits, decode_parts, encode_message
from protocol.errors import InputError
from protocol.messages import Message

FLAG = 0x7E
ESC = 0x7D
WIRE_VERSION = 1
FLAG_ACK_REQ = 0x0001  # sender wants an Ack for this sequence number
HEADER = struct.Struct(">BBHII")
_CRC = struct.Struct(">I")
_MIN_BODY = HEADER.size + _CRC.size
DEFAULT_MAX_FRAME = DEFAULT_LIMITS.max_message_bytes


def stuff(body: bytes) -> bytes:
    return body.replace(b"\x7d", b"\x7d\x5d").replace(b"\x7e", b"\x7d\x5e")


def unstuff(data: bytes) -> bytes | None:
    """Inverse of :func:`stuff`; ``None`` if an escape byte is not followed by 0x5D/0x5E."""
    if data.count(b"\x7d") != data.count(b"\x7d\x5d") + data.count(b"\x7d\x5e"):
        return None
    return data.replace(b"\x7d\x5e", b"\x7e").replace(b"\x7d\x5d", b"\x7d")


def frame_payload(type_code: int, seq: int, payload: bytes, flags: int = 0) -> bytes:
    """Wrap an already-encoded message body in a stream frame."""
    if not (0 <= seq < 2**32 and 0 <= flags < 2**16 and 0 <= type_code < 256):
        raise InputError(f"frame header out of range (type {type_code}, seq {seq}, flags {flags})")
    body = HEADER.pack(WIRE_VERSION, type_code, flags, seq, len(payload)) + payload
    return b"\x7e" + stuff(body + _CRC.pack(zlib.crc32(body))) + b"\x7e"


def encode_stream_frame(message: Message, seq: int = 0, flags: int = 0) -> bytes:
    """``message`` as one stream frame with link sequence ``seq``."""
    return frame_payload(message.TYPE, seq, encode_message(message), flags)


@dataclass(frozen=True)
class Packet:
    """A decoded frame: link sequence number, header flags and the message."""

    seq: int
    flags: int
    message: Message

    @property
    def wants_ack(self) -> bool:
        return bool(self.flags & FLAG_ACK_REQ)


@dataclass(frozen=True)
class Rejected:
    """A frame that passed its CRC but whose payload could not be decoded (peer bug/version)."""

    seq: int
    flags: int
    reason: str


class StreamDecoder:
    """Incremental decoder: ``feed(bytes) -> [Message]``; never raises on bad input.

    Counters (attribute ``stats``): ``frames_ok``, ``crc_errors``, ``malformed``
    (bad escape / runt / bad header), ``oversize``, ``decode_errors`` (CRC ok,
    payload invalid), ``resyncs`` (pieces dropped before the next flag),
    ``bytes_discarded``, ``bytes_in``.
    """

    def __init__(self, max_frame_bytes: int = DEFAULT_MAX_FRAME, limits: Limits = DEFAULT_LIMITS) -> None:
        self.max_frame_bytes = max_frame_bytes
        self.limits = limits
        self._buf = bytearray()
        self._skipping = False  # inside an oversize piece: drop until the next flag
        self.rejected: list[Rejected] = []
        self.stats = dict.fromkeys(
            (
                "frames_ok",
                "crc_errors",
                "malformed",
                "oversize",
                "decode_errors",
                "resyncs",
                "bytes_discarded",
                "bytes_in",
            ),
            0,
        )

    @property
    def pending_bytes(self) -> int:
        """Bytes held waiting for a closing flag."""
        return len(self._buf)

    def feed(self, data: bytes) -> list[Message]:
        return [p.message for p in self.feed_packets(data)]

    def take_rejected(self) -> list[Rejected]:
        out, self.rejected = self.rejected, []
        return out

    def expire_partial(self) -> int:
        """Drop a partial frame that has gone stale (a frame timeout); returns bytes dropped."""
        n = len(self._buf)
        if n:
            self._discard(n)
            self._buf.clear()
        return n

    def _discard(self, n: int) -> None:
        self.stats["bytes_discarded"] += n
        self.stats["resyncs"] += 1

    def feed_packets(self, data: bytes) -> list[Packet]:
        self.stats["bytes_in"] += len(data)
        out: list[Packet] = []
        mv = bytes(data)
        start = 0
        max_piece = 2 * (self.max_frame_bytes + _MIN_BODY)
        while True:
            i = mv.find(b"\x7e", start)
            if i < 0:
                rest = mv[start:]
                if self._skipping:
                    self.stats["bytes_discarded"] += len(rest)
                elif len(self._buf) + len(rest) > max_piece:
                    self.stats["oversize"] += 1
                    self._discard(len(self._buf) + len(rest))
                    self._buf.clear()
                    self._skipping = True
                else:
                    self._buf += rest
                return out
            if self._skipping:
                self.stats["bytes_discarded"] += i - start
                self._skipping = False
            elif self._buf:
                self._buf += mv[start:i]
                piece = bytes(self._buf)
                self._buf.clear()
                self._piece(piece, out)
            elif i > start:
                self._piece(mv[start:i], out)
            start = i + 1

    def _piece(self, piece: bytes, out: list[Packet]) -> None:
        if len(piece) > 2 * (self.max_frame_bytes + _MIN_BODY):
            self.stats["oversize"] += 1
            self._discard(len(piece))
            return
        body = unstuff(piece)
        if body is None or len(body) < _MIN_BODY:
            self.stats["malformed"] += 1
            self._discard(len(piece))
            return
        version, type_code, flags, seq, length = HEADER.unpack_from(body)
        if zlib.crc32(memoryview(body)[:-4]) != _CRC.unpack_from(body, len(body) - 4)[0]:
            self.stats["crc_errors"] += 1
            self._discard(len(piece))
            return
        if version != WIRE_VERSION or length != len(body) - _MIN_BODY:
            self.stats["malformed"] += 1
            self._discard(len(piece))
            return
        if length > self.max_frame_bytes:
            self.stats["oversize"] += 1
            self._discard(len(piece))
            return
        try:
            msg = decode_parts(memoryview(body)[HEADER.size : -4], (), self.limits, expect_type=type_code)
        except InputError as exc:
            self.stats["decode_errors"] += 1
            self.rejected.append(Rejected(seq, flags, str(exc)))
            if len(self.rejected) > 64:
                del self.rejected[0]
            return
        self.stats["frames_ok"] += 1
        out.append(Packet(seq, flags, msg))
