"""msgpack codec with hard resource budgets; numpy arrays without pickle.

Wire body of a message: msgpack ``[type, {field: value}]`` (see
:mod:`protocol.messages`). An ``np.ndarray`` is a msgpack ext value::

    ext 1 (inline):     dtype:u8 | ndim:u8 | shape:u32[ndim] (big-endian) | raw little-endian bytes
    ext 2 (out of band, ZeroMQ): dtype:u8 | ndim:u8 | shape:u32[ndim] | buffer index:u32
    ext 3 (compressed): dtype:u8 | ndim:u8 | shape:u32[ndim] | filter:u8 | zlib stream (RFC 1950)
                        filter = how many trailing axes were differenced (integer dtypes only):
                        0 = none, 1 = the last axis, 2 = the last axis then the one before,
                        two's-complement wrap-around; decode = cumulative sums in the same dtype

Only the dtypes in :data:`DTYPES` are accepted (never object/void, never
pickle) and ``prod(shape) * itemsize`` must equal the byte count.

Resource budget, enforced *before* msgpack allocates anything: :func:`scan`
walks the body once without building objects and refuses it when it is
truncated, has trailing bytes, holds more than ``Limits.max_objects`` values
in total (every scalar, string, container and map key counts), a container
longer than ``max_items``, nesting deeper than ``max_depth``, a string longer
than ``max_str``, or compressed arrays whose declared sizes add up to more than
``max_decoded_bytes``. A compressed array is inflated with ``max_length`` =
its declared size, so a zlib bomb costs at most that many bytes. Per-message
memory is therefore bounded by ``len(body) + max_decoded_bytes +
max_objects * ~100 B``, and decoding time by the same quantities.
"""

from __future__ import annotations

import re
import struct
import zlib
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import msgpack
import numpy as np

from protocol.errors import InputError
from protocol.messages import Compressed, Message, SchemaError, message_class

EXT_INLINE = 1
EXT_REF = 2
EXT_ZLIB = 3
FILTER_NONE = 0
FILTER_DELTA = 1  # difference along the last axis
FILTER_DELTA2 = 2  # difference along the last axis, then along the one before (a smooth 2-D field's residual)
ZLIB_LEVEL = 6  # level 9 saves ~12 % on the grids but costs ~10x the CPU: a throttled flight CPU pays that
_WIRE_DTYPES = ("|u1", "|i1", "<u2", "<i2", "<u4", "<i4", "<u8", "<i8", "<f4", "<f8", "|b1", "<f2")
DTYPES: dict[int, np.dtype] = {code: np.dtype(s) for code, s in enumerate(_WIRE_DTYPES, start=1)}
_DTYPE_CODES = {dt: code for code, dt in DTYPES.items()}
_U32 = struct.Struct(">I")


class CodecError(InputError):
    """Bytes that are not a valid, in-limits encoding of a known message."""


@dataclass(frozen=True)
class Limits:
    """Hard caps applied while decoding (bytes / items)."""

    max_message_bytes: int = 32 << 20  # encoded body (after reassembly)
    max_array_bytes: int = 16 << 20  # one array, decoded
    max_decoded_bytes: int = 48 << 20  # all compressed arrays of one message, decoded
    max_str: int = 64 << 10
    max_items: int = 4096  # msgpack array / map length
    max_objects: int = 16384  # msgpack values in one message, all levels together
    max_depth: int = 8
    max_ndim: int = 4


DEFAULT_LIMITS = Limits()

# msgpack first byte -> bytes that follow for fixed-size scalars; -1 = needs a closer look
_SCALAR = [-1] * 256
for _b in list(range(0x80)) + list(range(0xE0, 0x100)) + [0xC0, 0xC2, 0xC3]:
    _SCALAR[_b] = 0
for _b, _n in ((0xCA, 4), (0xCB, 8), (0xCC, 1), (0xCD, 2), (0xCE, 4), (0xCF, 8)):
    _SCALAR[_b] = _n
for _b, _n in ((0xD0, 1), (0xD1, 2), (0xD2, 4), (0xD3, 8)):
    _SCALAR[_b] = _n
_FIXEXT = {0xD4: 1, 0xD5: 2, 0xD6: 4, 0xD7: 8, 0xD8: 16}  # marker -> data bytes (after the type byte)
# variable-length: marker -> (length bytes, kind)
_VAR = {
    0xC4: (1, "bin"),
    0xC5: (2, "bin"),
    0xC6: (4, "bin"),
    0xD9: (1, "str"),
    0xDA: (2, "str"),
    0xDB: (4, "str"),
    0xC7: (1, "ext"),
    0xC8: (2, "ext"),
    0xC9: (4, "ext"),
    0xDC: (2, "array"),
    0xDD: (4, "array"),
    0xDE: (2, "map"),
    0xDF: (4, "map"),
}


def scan(body: bytes | memoryview, limits: Limits = DEFAULT_LIMITS) -> int:
    """Check the budget of a msgpack body without decoding it; returns the object count.

    Cost is O(objects) with objects <= ``limits.max_objects`` (the walk stops at
    the first violation), independent of how many bytes a hostile body has.
    """
    mv = memoryview(body).cast("B") if not isinstance(body, bytes) else body
    n = len(mv)
    if n > limits.max_message_bytes:
        raise CodecError(f"message of {n} bytes exceeds the {limits.max_message_bytes}-byte limit")
    pos = 0
    objects = 0
    decoded = 0
    stack = [1]  # values still expected at each open level; the top level holds one value
    max_objects, max_items, max_depth, max_str = limits.max_objects, limits.max_items, limits.max_depth, limits.max_str
    while stack:
        if stack[-1] == 0:
            stack.pop()
            continue
        stack[-1] -= 1
        if pos >= n:
            raise CodecError("malformed msgpack: truncated body")
        b = mv[pos]
        pos += 1
        objects += 1
        if objects > max_objects:
            raise CodecError(f"message holds more than {max_objects} values (object budget)")
        size = _SCALAR[b]
        if size >= 0:
            pos += size
            continue
        if 0x80 <= b <= 0x9F:  # fixmap / fixarray
            count = (b & 0x0F) * 2 if b < 0x90 else b & 0x0F
        elif 0xA0 <= b <= 0xBF:  # fixstr
            pos += b & 0x1F
            continue
        elif b in _FIXEXT:
            length = _FIXEXT[b]
            if pos + 1 + length > n:
                raise CodecError("malformed msgpack: truncated ext")
            if mv[pos] == EXT_ZLIB:
                decoded += _declared_bytes(mv[pos + 1 : pos + 1 + length], limits)
                if decoded > limits.max_decoded_bytes:
                    raise CodecError(f"compressed arrays declare more than {limits.max_decoded_bytes} bytes in total")
            pos += 1 + length
            continue
        elif b in _VAR:
            width, kind = _VAR[b]
            if pos + width > n:
                raise CodecError("malformed msgpack: truncated length")
            length = int.from_bytes(mv[pos : pos + width], "big")
            pos += width
            if kind in ("array", "map"):
                if length > max_items:
                    raise CodecError(f"malformed msgpack: container of {length} items (limit {max_items})")
                count = 2 * length if kind == "map" else length
            else:
                if kind == "str" and length > max_str:
                    raise CodecError(f"malformed msgpack: string of {length} bytes (limit {max_str})")
                if kind == "ext":
                    if pos + 1 + length > n:
                        raise CodecError("malformed msgpack: truncated ext")
                    if mv[pos] == EXT_ZLIB:
                        decoded += _declared_bytes(mv[pos + 1 : pos + 1 + length], limits)
                        if decoded > limits.max_decoded_bytes:
                            raise CodecError(
                                f"compressed arrays declare more than {limits.max_decoded_bytes} bytes in total"
                            )
                    pos += 1  # the ext type byte
                pos += length
                continue
        else:  # 0xC1 (never used)
            raise CodecError(f"malformed msgpack: reserved byte 0x{b:02x}")
        if count:
            if len(stack) > max_depth:
                raise CodecError(f"message nesting deeper than {max_depth}")
            stack.append(count)
    if pos != n:
        why = "truncated body" if pos > n else f"{n - pos} extra bytes"
        raise CodecError(f"malformed msgpack: {why}")
    return objects


def _declared_bytes(data: bytes | memoryview, limits: Limits) -> int:
    dt, shape, _ = _parse_array_header(data, limits)
    return dt.itemsize * _prod(shape)


def _prod(shape: tuple[int, ...]) -> int:
    out = 1
    for s in shape:
        out *= s
    return out


def _array_header(arr: np.ndarray) -> bytes:
    dt = arr.dtype.newbyteorder("<") if arr.dtype.byteorder == ">" else arr.dtype
    code = _DTYPE_CODES.get(np.dtype(dt.str))
    if code is None:
        raise CodecError(
            f"array dtype {arr.dtype} is not allowed on the wire (allowed: "
            f"{', '.join(sorted(d.str for d in DTYPES.values()))})"
        )
    if arr.ndim > 255:
        raise CodecError(f"array with {arr.ndim} dimensions")
    return bytes((code, arr.ndim)) + b"".join(_U32.pack(s) for s in arr.shape)


def _wire_array(arr: np.ndarray) -> np.ndarray:
    """C-contiguous, little-endian view or copy of ``arr``."""
    if arr.dtype.byteorder == ">":
        arr = arr.astype(arr.dtype.newbyteorder("<"))
    return np.ascontiguousarray(arr)


def _parse_array_header(data: bytes | memoryview, limits: Limits) -> tuple[np.dtype, tuple[int, ...], int]:
    if len(data) < 2:
        raise CodecError("array header truncated")
    code, ndim = data[0], data[1]
    dt = DTYPES.get(code)
    if dt is None:
        raise CodecError(f"array dtype code {code} is not allowed")
    if ndim > limits.max_ndim:
        raise CodecError(f"array has {ndim} dimensions (limit {limits.max_ndim})")
    end = 2 + 4 * ndim
    if len(data) < end:
        raise CodecError("array shape truncated")
    shape = tuple(_U32.unpack_from(data, 2 + 4 * i)[0] for i in range(ndim))
    nbytes = dt.itemsize * _prod(shape)
    if nbytes > limits.max_array_bytes:
        raise CodecError(f"array of {nbytes} bytes exceeds the {limits.max_array_bytes}-byte limit")
    return dt, shape, end


def _make_array(raw: bytes | memoryview, dt: np.dtype, shape: tuple[int, ...]) -> np.ndarray:
    expected = dt.itemsize * _prod(shape)
    if len(raw) != expected:
        raise CodecError(f"array {dt.str}{list(shape)} needs {expected} bytes, got {len(raw)}")
    arr = np.frombuffer(raw, dtype=dt).reshape(shape)
    if dt.kind == "b" and arr.size and arr.view(np.uint8).max() > 1:
        raise CodecError("bool array holds bytes other than 0/1")
    return arr


def delta_encode(arr: np.ndarray, axes: int) -> np.ndarray:
    """Differences along the last ``axes`` axes, last axis first, in the array's own integer type (wrapping).

    ``d[..., i] = a[..., i] - a[..., i - 1]`` with ``a[..., -1] = 0``; with two axes the rows of ``d`` are
    then differenced the same way, so ``d[i, j] = a[i, j] - a[i, j-1] - a[i-1, j] + a[i-1, j-1]``: the
    residual of the planar (gradient) predictor of lossless image coding, zero on a plane. The inverse is
    a cumulative sum per axis in the reverse order (:func:`_inflate`).
    """
    for axis in range(-1, -1 - axes, -1):
        zero = np.zeros((*arr.shape[: arr.ndim + axis], 1, *arr.shape[arr.ndim + axis + 1 :]), arr.dtype)
        arr = np.diff(arr, axis=axis, prepend=zero)
    return arr


def _inflate(data: bytes | memoryview, dt: np.dtype, shape: tuple[int, ...]) -> np.ndarray:
    """ext 3 payload after the shape: filter byte + zlib stream, inflated to exactly the declared size."""
    if len(data) < 1:
        raise CodecError("compressed array: filter byte missing")
    filt = data[0]
    if filt not in (FILTER_NONE, FILTER_DELTA, FILTER_DELTA2) or (filt != FILTER_NONE and dt.kind not in "iu"):
        raise CodecError(f"compressed array: filter {filt} not allowed for dtype {dt.str}")
    if filt > len(shape):
        raise CodecError(f"compressed array: filter {filt} needs at least {filt} axes, got {len(shape)}")
    expected = dt.itemsize * _prod(shape)
    d = zlib.decompressobj()
    try:
        raw = d.decompress(bytes(data[1:]), max(expected, 1))  # never more than declared (+1 to detect excess)
    except zlib.error as exc:
        raise CodecError(f"compressed array: {exc}") from None
    if len(raw) != expected or not d.eof or d.unconsumed_tail or d.unused_data:
        raise CodecError(f"compressed array {dt.str}{list(shape)} does not inflate to exactly {expected} bytes")
    arr = _make_array(raw, dt, shape)
    if arr.size:
        for axis in range(-1, -1 - filt, -1):  # undoes the sender's differences (sums per axis commute)
            arr = np.cumsum(arr, axis=axis, dtype=dt)
    arr.flags.writeable = False
    return arr


def encode_parts(message: Message, oob_min_bytes: int | None = None) -> tuple[bytes, list[memoryview]]:
    """Encode ``message`` to ``(body, buffers)``.

    Arrays of at least ``oob_min_bytes`` go out of band as separate buffers
    (zero-copy ZeroMQ frames); ``None`` keeps everything inline. Fields the
    schema marks compressed always go inline as ext 3.
    """
    buffers: list[memoryview] = []

    def default(obj: Any) -> Any:
        if isinstance(obj, Compressed):
            arr = _wire_array(obj.array)
            head = _array_header(arr)
            filt = min(int(obj.delta), arr.ndim) if arr.dtype.kind in "iu" else FILTER_NONE
            if arr.size:
                arr = delta_encode(arr, filt)
            payload = zlib.compress(memoryview(arr.reshape(-1)).cast("B"), ZLIB_LEVEL)  # type: ignore[arg-type]
            return msgpack.ExtType(EXT_ZLIB, head + bytes((filt,)) + payload)
        if isinstance(obj, np.ndarray):
            arr = _wire_array(obj)
            head = _array_header(arr)
            if oob_min_bytes is not None and arr.nbytes >= oob_min_bytes:
                buffers.append(memoryview(arr.reshape(-1)).cast("B"))  # type: ignore[arg-type]
                return msgpack.ExtType(EXT_REF, head + _U32.pack(len(buffers) - 1))
            return msgpack.ExtType(EXT_INLINE, head + arr.tobytes())
        if isinstance(obj, tuple):
            return list(obj)
        raise CodecError(f"cannot encode {type(obj).__name__}")

    try:
        body = msgpack.packb([message.TYPE, message.to_wire()], default=default, use_bin_type=True)
    except (TypeError, ValueError, OverflowError) as exc:
        if isinstance(exc, InputError):
            raise
        raise CodecError(f"cannot encode {type(message).__name__}: {exc}") from None
    return body, buffers


def encode_message(message: Message) -> bytes:
    """msgpack body of ``message`` with all arrays inline."""
    return encode_parts(message, None)[0]


@dataclass(frozen=True)
class Encoded:
    """A message with its body (all arrays inline), made once by :func:`encode` and sent as it is.

    The links take one in place of a message, so a sender that had to encode to learn the size does not pay for
    the encoding again: a 37 kB Result's zlib grids cost 7 ms of full-speed CPU, 0.7 s at rad750's share
    (docs/hil.md, section 7)."""

    message: Message
    body: bytes


def encode(message: Message) -> Encoded:
    """``message`` with its :func:`encode_message` body."""
    return Encoded(message, encode_message(message))


def decode_parts(
    body: bytes | memoryview,
    buffers: Sequence[bytes | memoryview] = (),
    limits: Limits = DEFAULT_LIMITS,
    expect_type: int | None = None,
) -> Message:
    """Inverse of :func:`encode_parts`; every problem raises :class:`CodecError` (or SchemaError)."""
    scan(body, limits)  # the budget, before msgpack allocates anything
    used: set[int] = set()

    def ext_hook(code: int, data: bytes) -> Any:
        dt, shape, end = _parse_array_header(data, limits)
        if code == EXT_INLINE:
            return _make_array(memoryview(data)[end:], dt, shape)
        if code == EXT_ZLIB:
            return _inflate(memoryview(data)[end:], dt, shape)
        if code == EXT_REF:
            if len(data) != end + 4:
                raise CodecError("bad out-of-band array reference")
            idx = _U32.unpack_from(data, end)[0]
            if idx >= len(buffers) or idx in used:
                raise CodecError(f"out-of-band buffer {idx} missing or reused ({len(buffers)} given)")
            if len(buffers[idx]) > limits.max_array_bytes:
                raise CodecError(f"out-of-band buffer of {len(buffers[idx])} bytes exceeds the array limit")
            used.add(idx)
            return _make_array(buffers[idx], dt, shape)
        raise CodecError(f"unknown ext type {code}")

    try:
        obj = msgpack.unpackb(
            body,
            raw=False,
            strict_map_key=True,
            use_list=True,
            ext_hook=ext_hook,
            max_str_len=limits.max_str,
            max_bin_len=limits.max_array_bytes,
            max_array_len=limits.max_items,
            max_map_len=limits.max_items,
            max_ext_len=limits.max_array_bytes + 1024,
        )
    except InputError:
        raise
    except Exception as exc:  # msgpack raises ValueError/FormatError/StackError/ExtraData/UnicodeError
        m = re.fullmatch(r"(\d+) exceeds max_(ext|bin)_len\(\d+\)", str(exc))
        if m:  # msgpack's own words named its option, not the rule (protocol.md 5.3)
            raise CodecError(
                f"an array of {int(m.group(1))} bytes exceeds the {limits.max_array_bytes}-byte per-array limit"
            ) from None
        raise CodecError(f"malformed msgpack: {type(exc).__name__}: {exc}") from None
    if not (isinstance(obj, list) and len(obj) == 2 and isinstance(obj[0], int) and not isinstance(obj[0], bool)):
        raise CodecError("message must be [type, body]")
    if expect_type is not None and obj[0] != expect_type:
        raise CodecError(f"frame header says type {expect_type}, body says {obj[0]}")
    if len(used) != len(buffers):
        raise CodecError(f"{len(buffers) - len(used)} unreferenced out-of-band buffers")
    try:
        return message_class(obj[0]).from_wire(obj[1])
    except SchemaError as exc:  # decoded, but not a valid message: which pair it answered, if it says
        exc.frame_seqs = _said_seqs(obj[1])  # type: ignore[attr-defined]
        raise


def _said_seqs(fields: Any) -> tuple[int, int] | None:
    """A refused message's ``frame_seqs`` when its decoded body holds two plain u32 there (else None)."""
    v = fields.get("frame_seqs") if isinstance(fields, dict) else None
    if isinstance(v, (list, tuple)) and len(v) == 2 and all(type(x) is int and 0 <= x < 2**32 for x in v):
        return int(v[0]), int(v[1])
    return None


def decode_message(body: bytes | memoryview, limits: Limits = DEFAULT_LIMITS) -> Message:
    return decode_parts(body, (), limits)
