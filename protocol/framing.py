"""Self-synchronising frames for serial lines and byte streams (wire version 2).

One frame on the wire (HDLC-style byte stuffing, RFC 1662 section 4.2)::

    0x7E | stuff( header | body | CRC32 ) | 0x7E
    header = version:u8 (=2) | kind:u8 | flags:u16 (=0) | src_session:u32 | dst_session:u32  (big-endian)
    CRC32  = zlib.crc32(header + body) (CRC-32/ISO-HDLC), big-endian
    stuff  : 0x7D -> 0x7D 0x5D, 0x7E -> 0x7D 0x5E   (so 0x7E only ever delimits)

Kinds and their bodies (all integers big-endian; docs/protocol.md is the spec):

=========  ====  =============================================================
DATA       1     pos:u32 (stream byte position of the first byte) | txid:u32 | stream bytes
ACK        2     cum:u32 | window:u32 | echo:u32 | n:u8 | n x (start:u32, end:u32)  (SACK)
DGRAM      3     type:u8 | whole message body (unreliable, e.g. Heartbeat)
HELLO      4     max_frame:u32 | window:u32
CLOSE      5     cum:u32 (as in ACK) | code:u8 (0 closed, 1 session lost) | reason (UTF-8, <= 256 bytes)
REJECT     6     pos:u32 (stream position of the refused message's record) | reason (UTF-8)
=========  ====  =============================================================

The reliable stream of a session is a sequence of records
``type:u8 | length:u32 | message body`` (:mod:`protocol.arq`). Stream positions
(``pos``, ``cum``, SACK ranges) are carried modulo 2**32 and compared in
serial-number order (RFC 1982), so a session's stream may run past 4 GiB; no
DATA frame crosses a multiple of 2**32 (``pos + len <= 2**32``).

Why stuffing with a flag byte rather than a start word plus length (F Prime):
a frame whose tail was lost is closed by the next frame's opening flag, so the
decoder resynchronises at once instead of waiting for bytes that never come.
Stuffing and unstuffing are ``bytes.replace`` calls (C speed); for random data
the overhead is ~2/256.

:class:`StreamDecoder` splits the byte stream on flags and checks each piece
(escape validity, length, CRC, header fields); anything wrong is counted and
dropped, never raised. It does not decode message bodies: that happens after
reassembly (:mod:`protocol.arq`), under the codec's budget.
"""

from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass, field

from protocol.errors import InputError

FLAG = 0x7E
ESC = 0x7D
WIRE_VERSION = 2
DATA, ACK, DGRAM, HELLO, CLOSE, REJECT = 1, 2, 3, 4, 5, 6
KIND_NAMES = {DATA: "DATA", ACK: "ACK", DGRAM: "DGRAM", HELLO: "HELLO", CLOSE: "CLOSE", REJECT: "REJECT"}
HEADER = struct.Struct(">BBHII")
DATA_HEAD = struct.Struct(">II")  # pos, txid (the sender's transmission number, echoed in ACKs)
ACK_HEAD = struct.Struct(">IIIB")  # cum, window, echo (txid of the latest DATA received), n
SACK_RANGE = struct.Struct(">II")
HELLO_BODY = struct.Struct(">II")
_U32 = struct.Struct(">I")
_CRC = struct.Struct(">I")
OVERHEAD = HEADER.size + _CRC.size  # unstuffed bytes besides the body
DATA_OVERHEAD = OVERHEAD + DATA_HEAD.size  # 24 bytes around a segment (+ 2 flags + stuffing)
MAX_SACK_RANGES = 16
MAX_REASON = 256
MIN_FRAME = 64  # smallest max_frame a peer may announce
DEFAULT_MAX_FRAME = 1024  # unstuffed bytes, header to CRC


def stuff(body: bytes) -> bytes:
    return body.replace(b"\x7d", b"\x7d\x5d").replace(b"\x7e", b"\x7d\x5e")


def unstuff(data: bytes) -> bytes | None:
    """Inverse of :func:`stuff`; ``None`` if an escape byte is not followed by 0x5D/0x5E."""
    if data.count(b"\x7d") != data.count(b"\x7d\x5d") + data.count(b"\x7d\x5e"):
        return None
    return data.replace(b"\x7d\x5e", b"\x7e").replace(b"\x7d\x5d", b"\x7d")


def _frame(kind: int, src: int, dst: int, body: bytes) -> bytes:
    if not (0 <= src < 2**32 and 0 <= dst < 2**32):
        raise InputError(f"session ids must be u32 (src {src}, dst {dst})")
    raw = HEADER.pack(WIRE_VERSION, kind, 0, src, dst) + body
    return b"\x7e" + stuff(raw + _CRC.pack(zlib.crc32(raw))) + b"\x7e"


def data_frame(src: int, dst: int, pos: int, segment: bytes, txid: int = 0) -> bytes:
    return _frame(DATA, src, dst, DATA_HEAD.pack(pos, txid) + segment)


def ack_frame(src: int, dst: int, cum: int, window: int, sacks: list[tuple[int, int]], echo: int = 0) -> bytes:
    sacks = sacks[:MAX_SACK_RANGES]
    body = ACK_HEAD.pack(cum, window, echo, len(sacks)) + b"".join(SACK_RANGE.pack(a, b) for a, b in sacks)
    return _frame(ACK, src, dst, body)


def dgram_frame(src: int, dst: int, type_code: int, body: bytes) -> bytes:
    return _frame(DGRAM, src, dst, bytes((type_code,)) + body)


def hello_frame(src: int, dst: int, max_frame: int, window: int) -> bytes:
    return _frame(HELLO, src, dst, HELLO_BODY.pack(max_frame, window))


CLOSE_APP, CLOSE_LOST = 0, 1  # the application closed the link / the sender gave up on this session


def _reason(reason: str, room: int) -> bytes:
    """``reason`` in UTF-8, cut to ``room`` bytes (and :data:`MAX_REASON`)."""
    return reason.encode("utf-8", "replace")[: max(0, min(MAX_REASON, room))]


def close_frame(
    src: int, dst: int, cum: int, reason: str, code: int = CLOSE_APP, max_frame: int = OVERHEAD + 5 + MAX_REASON
) -> bytes:
    """A CLOSE no longer than ``max_frame`` (the peer's announced value: section 1), the reason cut to fit."""
    return _frame(CLOSE, src, dst, _U32.pack(cum) + bytes((code,)) + _reason(reason, max_frame - OVERHEAD - 5))


def reject_frame(src: int, dst: int, pos: int, reason: str, max_frame: int = OVERHEAD + 4 + MAX_REASON) -> bytes:
    """A REJECT no longer than ``max_frame`` (the peer's announced value), the reason cut to fit."""
    return _frame(REJECT, src, dst, _U32.pack(pos) + _reason(reason, max_frame - OVERHEAD - 4))


def ack_sack_room(max_frame: int) -> int:
    """How many SACK ranges an ACK may carry within ``max_frame`` bytes (at most :data:`MAX_SACK_RANGES`)."""
    return max(0, min(MAX_SACK_RANGES, (max_frame - OVERHEAD - ACK_HEAD.size) // SACK_RANGE.size))


@dataclass
class WireFrame:
    """One frame that passed CRC and header checks. Fields not used by a kind keep their defaults."""

    kind: int
    src: int
    dst: int
    pos: int = 0  # DATA, REJECT
    txid: int = 0  # DATA
    echo: int = 0  # ACK
    type_code: int = 0  # DGRAM
    payload: bytes = b""  # DATA stream bytes / DGRAM body
    cum: int = 0  # ACK, CLOSE
    window: int = 0  # ACK, HELLO
    sacks: list[tuple[int, int]] = field(default_factory=list)  # ACK
    max_frame: int = 0  # HELLO
    reason: str = ""  # CLOSE, REJECT
    code: int = 0  # CLOSE
    wire_bytes: int = 0  # stuffed length between the flags (for statistics)


def parse_body(raw: bytes) -> WireFrame | str:
    """Unstuffed ``header | body | CRC`` -> :class:`WireFrame`, or the reason it is not one."""
    if len(raw) < OVERHEAD:
        return "runt"
    if zlib.crc32(memoryview(raw)[:-4]) != _CRC.unpack_from(raw, len(raw) - 4)[0]:
        return "crc"
    version, kind, flags, src, dst = HEADER.unpack_from(raw)
    if version != WIRE_VERSION or flags != 0:
        return "malformed"
    body = raw[HEADER.size : -4]
    f = WireFrame(kind, src, dst)
    if kind == DATA:
        if len(body) <= DATA_HEAD.size:
            return "malformed"
        f.pos, f.txid = DATA_HEAD.unpack_from(body)
        f.payload = body[DATA_HEAD.size :]
        if f.pos + len(f.payload) > 2**32:
            return "malformed"
    elif kind == ACK:
        if len(body) < ACK_HEAD.size:
            return "malformed"
        f.cum, f.window, f.echo, n = ACK_HEAD.unpack_from(body)
        if n > MAX_SACK_RANGES or len(body) != ACK_HEAD.size + n * SACK_RANGE.size:
            return "malformed"
        for k in range(n):
            a, b = SACK_RANGE.unpack_from(body, ACK_HEAD.size + k * SACK_RANGE.size)
            if not 0 < (a - f.cum) % 2**32 < (b - f.cum) % 2**32 < 2**31:  # above cum, in serial-number order
                return "malformed"
            f.sacks.append((a, b))
    elif kind == DGRAM:
        if len(body) < 2:
            return "malformed"
        f.type_code, f.payload = body[0], body[1:]
    elif kind == HELLO:
        if len(body) != HELLO_BODY.size:
            return "malformed"
        f.max_frame, f.window = HELLO_BODY.unpack(body)
        if f.max_frame < MIN_FRAME or f.window < 1 or src == 0:
            return "malformed"
    elif kind == CLOSE:
        if len(body) < 5 or len(body) > 5 + MAX_REASON or body[4] not in (CLOSE_APP, CLOSE_LOST):
            return "malformed"
        f.cum = _U32.unpack_from(body)[0]
        f.code = body[4]
        f.reason = body[5:].decode("utf-8", "replace")
    elif kind == REJECT:
        if len(body) < 4 or len(body) > 4 + MAX_REASON:
            return "malformed"
        f.pos = _U32.unpack_from(body)[0]
        f.reason = body[4:].decode("utf-8", "replace")
    else:
        return "malformed"
    return f


class StreamDecoder:
    """Incremental decoder: ``feed(bytes) -> [WireFrame]``; never raises on bad input.

    ``max_frame`` bounds the unstuffed frame length (header to CRC); a piece
    longer than twice that (the stuffing worst case) is dropped as it arrives,
    so at most ``2 * max_frame + 2`` bytes are ever held.

    Counters (attribute ``stats``): ``frames_ok``, ``crc_errors``, ``malformed``
    (bad escape / runt / bad header), ``oversize``, ``resyncs`` (pieces
    dropped), ``bytes_discarded``, ``bytes_in``.

    ``claimed`` holds, after each :meth:`feed`, the ``src_session`` that the header of the frame still arriving
    claims (its CRC not yet in): a peer is writing to us while its frame is on the line (a 1 kB frame takes
    3.5 s at 2400 baud). Unverified, but a 32-bit id is no risk from noise. Pieces that failed their CRC claim
    nothing: the bytes of one closed by a new session's HELLO arrived before it, and were claimed as they came
    (counting them again at the close made a peer that died mid-frame and restarted wait 1.5 s more).
    """

    def __init__(self, max_frame: int = DEFAULT_MAX_FRAME) -> None:
        self.max_frame = max_frame
        self._buf = bytearray()
        self._skipping = False  # inside an oversize piece: drop until the next flag
        self.stats = dict.fromkeys(
            ("frames_ok", "crc_errors", "malformed", "oversize", "resyncs", "bytes_discarded", "bytes_in"), 0
        )
        self.claimed: set[int] = set()

    @property
    def pending_bytes(self) -> int:
        """Bytes held waiting for a closing flag."""
        return len(self._buf)

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

    def feed(self, data: bytes) -> list[WireFrame]:
        self.stats["bytes_in"] += len(data)
        self.claimed.clear()
        out: list[WireFrame] = []
        mv = bytes(data)
        start = 0
        max_piece = 2 * self.max_frame
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
                    self._claim(self._buf)
                return out
            if self._skipping:
                self.stats["bytes_discarded"] += i - start
                self._skipping = False
            elif self._buf:
                if len(self._buf) + i - start <= max_piece:
                    self._buf += mv[start:i]
                    piece = bytes(self._buf)
                    self._buf.clear()
                    self._piece(piece, out)
                else:
                    self.stats["oversize"] += 1
                    self._discard(len(self._buf) + i - start)
                    self._buf.clear()
            elif i > start:
                self._piece(mv[start:i], out)
            start = i + 1

    def _claim(self, piece: bytes | bytearray) -> None:
        """Note the ``src_session`` a piece's header claims, when its first bytes read as one (see ``claimed``).
        Only the header's bytes are unstuffed: a bad escape in the body after it (noise) does not hide it."""
        raw = bytearray()
        i, n = 0, len(piece)
        while len(raw) < HEADER.size and i < n:
            b = piece[i]
            if b == ESC:
                if i + 1 >= n:  # an escape cut at the end of what has arrived
                    return
                if piece[i + 1] not in (0x5D, 0x5E):
                    return
                raw.append(piece[i + 1] ^ 0x20)
                i += 2
            else:
                raw.append(b)
                i += 1
        if len(raw) == HEADER.size:
            version, kind, _flags, src, _dst = HEADER.unpack(raw)
            if version == WIRE_VERSION and kind in KIND_NAMES:
                self.claimed.add(src)

    def _piece(self, piece: bytes, out: list[WireFrame]) -> None:
        if len(piece) > 2 * self.max_frame:
            self.stats["oversize"] += 1
            self._discard(len(piece))
            return
        raw = unstuff(piece)
        if raw is None:
            self.stats["malformed"] += 1
            self._discard(len(piece))
            return
        if len(raw) > self.max_frame:
            self.stats["oversize"] += 1
            self._discard(len(piece))
            return
        f = parse_body(raw)
        if isinstance(f, str):
            self.stats["crc_errors" if f == "crc" else "malformed"] += 1
            self._discard(len(piece))
            return
        f.wire_bytes = len(piece) + 2
        self.stats["frames_ok"] += 1
        out.append(f)
