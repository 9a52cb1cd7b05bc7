"""msgpack codec with hard size limits; numpy arrays without pickle.

Wire body of a message: msgpack map ``{field: value}`` (see
:mod:`protocol.messages`). An ``np.ndarray`` is a msgpack ext value::

    ext 1 (inline):  dtype:u8 | ndim:u8 | shape:u32[ndim] (big-endian) | raw little-endian bytes
    ext 2 (out of band, ZeroMQ): dtype:u8 | ndim:u8 | shape:u32[ndim] | buffer index:u32

Only the dtypes in :data:`DTYPES` are accepted (never object/void, never
pickle) and ``prod(shape) * itemsize`` must equal the byte count. Every msgpack
container and string length is capped by :class:`Limits`, and nesting depth is
checked, so a corrupted or hostile peer cannot make the decoder allocate more
than ``Limits.max_message_bytes``.
"""

from __future__ import annotations

import struct
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import msgpack
import numpy as np

from protocol.errors import InputError
from protocol.messages import Message, message_class

EXT_INLINE = 1
EXT_REF = 2
DTYPES: dict[int, np.dtype] = {
    code: np.dtype(s)
    for code, s in enumerate(("|u1", "|i1", "<u2", "<i2", "<u4", "<i4", "<u8", "<i8", "<f4", "<f8", "|b1"), start=1)
}
_DTYPE_CODES = {dt: code for code, dt in DTYPES.items()}
_U32 = struct.Struct(">I")


class CodecError(InputError):
    """Bytes that are not a valid, in-limits encoding of a known message."""


@dataclass(frozen=True)
class Limits:
    """Hard caps applied while decoding (bytes / items)."""

    max_message_bytes: int = 32 << 20
    max_array_bytes: int = 16 << 20
    max_str: int = 64 << 10
    max_items: int = 4096  # msgpack array / map length
    max_depth: int = 8
    max_ndim: int = 4


DEFAULT_LIMITS = Limits()


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
    nbytes = dt.itemsize
    for s in shape:
        nbytes *= s
    if nbytes > limits.max_array_bytes:
        raise CodecError(f"array of {nbytes} bytes exceeds the {limits.max_array_bytes}-byte limit")
    return dt, shape, end


def _make_array(raw: bytes | memoryview, dt: np.dtype, shape: tuple[int, ...]) -> np.ndarray:
    expected = dt.itemsize * int(np.prod(shape, dtype=np.int64))
    if len(raw) != expected:
        raise CodecError(f"array {dt.str}{list(shape)} needs {expected} bytes, got {len(raw)}")
    arr = np.frombuffer(raw, dtype=dt).reshape(shape)
    if dt.kind == "b" and arr.size and arr.view(np.uint8).max() > 1:
        raise CodecError("bool array holds bytes other than 0/1")
    return arr


def _depth_ok(obj: Any, max_depth: int) -> bool:
    stack = [(obj, 1)]
    while stack:
        o, d = stack.pop()
        if isinstance(o, (list, dict)):
            if d > max_depth:
                return False
            stack.extend((c, d + 1) for c in (o.values() if isinstance(o, dict) else o))
    return True


def encode_parts(message: Message, oob_min_bytes: int | None = None) -> tuple[bytes, list[memoryview]]:
    """Encode ``message`` to ``(body, buffers)``.

    Arrays of at least ``oob_min_bytes`` go out of band as separate buffers
    (zero-copy ZeroMQ frames); ``None`` keeps everything inline.
    """
    buffers: list[memoryview] = []

    def default(obj: Any) -> Any:
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


def decode_parts(
    body: bytes | memoryview,
    buffers: Sequence[bytes | memoryview] = (),
    limits: Limits = DEFAULT_LIMITS,
    expect_type: int | None = None,
) -> Message:
    """Inverse of :func:`encode_parts`; every problem raises :class:`CodecError` (or SchemaError)."""
    if len(body) > limits.max_message_bytes:
        raise CodecError(f"message of {len(body)} bytes exceeds the {limits.max_message_bytes}-byte limit")
    used: set[int] = set()

    def ext_hook(code: int, data: bytes) -> Any:
        dt, shape, end = _parse_array_header(data, limits)
        if code == EXT_INLINE:
            return _make_array(memoryview(data)[end:], dt, shape)
        if code == EXT_REF:
            if len(data) != end + 4:
                raise CodecError("bad out-of-band array reference")
            idx = _U32.unpack_from(data, end)[0]
            if idx >= len(buffers) or idx in used:
                raise CodecError(f"out-of-band buffer {idx} missing or reused ({len(buffers)} given)")
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
        raise CodecError(f"malformed msgpack: {type(exc).__name__}: {exc}") from None
    if not _depth_ok(obj, limits.max_depth):
        raise CodecError(f"message nesting deeper than {limits.max_depth}")
    if not (isinstance(obj, list) and len(obj) == 2 and isinstance(obj[0], int) and not isinstance(obj[0], bool)):
        raise CodecError("message must be [type, body]")
    if expect_type is not None and obj[0] != expect_type:
        raise CodecError(f"frame header says type {expect_type}, body says {obj[0]}")
    if len(used) != len(buffers):
        raise CodecError(f"{len(buffers) - len(used)} unreferenced out-of-band buffers")
    return message_class(obj[0]).from_wire(obj[1])


def decode_message(body: bytes | memoryview, limits: Limits = DEFAULT_LIMITS) -> Message:
    return decode_parts(body, (), limits)
