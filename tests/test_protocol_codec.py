"""Round-trip and hostile-input tests for the message schema and msgpack codec."""

from __future__ import annotations

import math

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from protocol.codec import CodecError, Limits, decode_message, decode_parts, encode_message, encode_parts
from protocol.messages import (
    MESSAGE_TYPES,
    Ack,
    Config,
    Error,
    Frame,
    Heartbeat,
    Hello,
    Nack,
    Result,
    SchemaError,
    Site,
    Telemetry,
)

finite = st.floats(allow_nan=False, allow_infinity=False, width=64)
anyfloat = st.floats(width=64)
names = st.text(max_size=20)
u32 = st.integers(0, 2**32 - 1)


def f32_grid(max_side: int = 12) -> st.SearchStrategy[np.ndarray]:
    return hnp.arrays(
        np.float32,
        hnp.array_shapes(min_dims=2, max_dims=2, min_side=0, max_side=max_side),
        elements=st.floats(width=32),
    )  # includes NaN and +-inf


sites = st.lists(st.builds(Site, finite, finite, finite, finite, finite, finite), max_size=5)

messages = st.one_of(
    st.builds(Hello, role=names, protocol_version=st.integers(0, 255), software=names),
    st.builds(
        Config,
        camera=st.fixed_dictionaries(
            {
                "width": st.integers(1, 4096),
                "height": st.integers(1, 4096),
                "fx": finite,
                "fy": finite,
                "cx": finite,
                "cy": finite,
            }
        ),
        budget=names,
        deadline_s=finite,
        preset=names,
        options=st.dictionaries(st.text(max_size=8), st.one_of(finite, st.integers(-5, 5)), max_size=4),
    ),
    st.builds(
        Frame,
        seq=u32,
        capture_time_s=finite,
        position_m=st.tuples(finite, finite, finite),
        R_world_to_cam=hnp.arrays(np.float64, (3, 3), elements=finite),
        altimeter_m=anyfloat,
        image=hnp.arrays(np.uint8, hnp.array_shapes(min_dims=2, max_dims=2, min_side=0, max_side=16)),
        pair_id=st.none() | names,
        frame_index=st.none() | u32,
    ),
    st.builds(
        Result,
        frame_seqs=st.tuples(u32, u32),
        hazard_grid=f32_grid(),
        elevation_grid=f32_grid(),
        grid_origin_xy=st.tuples(finite, finite),
        grid_cell_m=finite,
        hazard_image=st.none() | f32_grid(),
        elevation_image=st.none() | f32_grid(),
        sites=sites,
        degraded=st.booleans(),
        level=names,
    ),
    st.builds(
        Telemetry,
        frame_seqs=st.tuples(u32, u32),
        stages=st.dictionaries(
            st.text(max_size=10), st.fixed_dictionaries({"wall_s": finite, "cpu_s": finite}), max_size=5
        ),
        queue_wait_s=finite,
        total_latency_s=finite,
        cpu_fraction=anyfloat,
        peak_rss_bytes=st.integers(0, 2**40),
        deadline_s=anyfloat,
        deadline_met=st.booleans(),
        link=st.dictionaries(st.text(max_size=10), st.integers(0, 10**9) | finite, max_size=6),
    ),
    st.builds(Heartbeat, time_s=finite, counter=st.integers(0, 2**40)),
    st.builds(Error, code=names, text=st.text(max_size=200), seq=st.none() | u32),
    st.builds(Ack, seq=u32),
    st.builds(Nack, seq=u32, reason=names),
)


def same(a, b) -> bool:
    """Field-wise equality with NaN == NaN and arrays compared bitwise."""
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return (
            isinstance(a, np.ndarray)
            and isinstance(b, np.ndarray)
            and a.dtype == b.dtype
            and a.shape == b.shape
            and a.tobytes() == b.tobytes()
        )
    if isinstance(a, float) and isinstance(b, float):
        return a == b or (math.isnan(a) and math.isnan(b))
    if isinstance(a, (list, tuple)):
        return type(a) is type(b) and len(a) == len(b) and all(same(x, y) for x, y in zip(a, b))
    if isinstance(a, dict):
        return isinstance(b, dict) and a.keys() == b.keys() and all(same(a[k], b[k]) for k in a)
    if hasattr(a, "__dataclass_fields__"):
        return type(a) is type(b) and all(same(getattr(a, k), getattr(b, k)) for k in a.__dataclass_fields__)
    return a == b


def test_every_message_type_is_covered():
    assert set(MESSAGE_TYPES) == set(range(1, 10))


@settings(max_examples=150, deadline=None)
@given(messages)
def test_roundtrip_inline(msg):
    out = decode_message(encode_message(msg))
    assert same(msg.validated(), out)


@settings(max_examples=100, deadline=None)
@given(messages, st.sampled_from([0, 16, 1 << 20]))
def test_roundtrip_out_of_band(msg, threshold):
    body, bufs = encode_parts(msg, threshold)
    copies = [bytes(b) for b in bufs]  # what actually crosses a socket
    assert same(msg.validated(), decode_parts(body, copies))


def test_nan_arrays_and_empty_sites_survive_bitwise():
    grid = np.array([[np.nan, 1.5], [-np.inf, 0.0]], np.float32)
    r = Result(
        frame_seqs=(4, 5),
        hazard_grid=grid,
        elevation_grid=grid.T.copy(),
        grid_origin_xy=(-10.0, 3.0),
        grid_cell_m=0.5,
        sites=[],
        degraded=True,
        level="coarse",
    )
    out = decode_message(encode_message(r))
    assert out.sites == [] and out.degraded is True
    assert out.hazard_grid.tobytes() == grid.tobytes() and out.elevation_grid.tobytes() == grid.T.tobytes()
    assert not out.hazard_grid.flags.writeable  # zero-copy view on the received bytes


def test_big_endian_and_noncontiguous_arrays_are_normalised():
    img = np.arange(64 * 64, dtype=np.uint8).reshape(64, 64)[::2, ::2]
    R = np.eye(3).astype(">f8")
    f = Frame(seq=1, capture_time_s=0.0, position_m=(0, 0, 100), R_world_to_cam=R, altimeter_m=100.0, image=img)
    out = decode_message(encode_message(f))
    assert np.array_equal(out.image, img) and out.R_world_to_cam.dtype == np.dtype("<f8")
    assert np.array_equal(out.R_world_to_cam, np.eye(3))


@pytest.mark.parametrize(
    "bad, match",
    [
        (dict(image=np.zeros((4, 4), np.float32) + 0.5), "dtype"),
        (dict(image=np.zeros((4, 4, 3), np.uint8)), "2-D"),
        (dict(R_world_to_cam=np.eye(4)), "shape"),
        (dict(position_m=(1.0, 2.0)), "3 numbers"),
        (dict(capture_time_s=float("nan")), "finite"),
        (dict(seq=-1), "outside"),
        (dict(seq=True), "integer"),
    ],
)
def test_schema_rejects_bad_fields_with_named_error(bad, match):
    kw = dict(
        seq=1,
        capture_time_s=0.0,
        position_m=(0, 0, 1),
        R_world_to_cam=np.eye(3),
        altimeter_m=1.0,
        image=np.zeros((4, 4), np.uint8),
    )
    kw.update(bad)
    with pytest.raises(SchemaError, match=match):
        encode_message(Frame(**kw))


def _ext(code, dtype_code, shape, raw):
    head = bytes((dtype_code, len(shape))) + b"".join(int(s).to_bytes(4, "big") for s in shape)
    return msgpack.ExtType(code, head + raw)


@pytest.mark.parametrize(
    "body, match",
    [
        (msgpack.packb([3, {"seq": 1}]), "missing field"),
        (msgpack.packb([99, {}]), "unknown message type"),
        (msgpack.packb([8, {"seq": 1, "evil": 2}]), "unknown fields"),
        (msgpack.packb({"a": 1}), r"\[type, body\]"),
        (b"\xc1", "malformed"),
        (msgpack.packb([8, {"seq": 1}]) + b"\x00", "malformed"),
        # array claims 10x10 uint8 but carries 3 bytes
        (msgpack.packb([6, {"time_s": 0.0, "x": _ext(1, 1, (10, 10), b"abc")}]), "needs 100 bytes"),
        # dtype code 0 / object arrays are not on the whitelist
        (msgpack.packb([6, {"time_s": 0.0, "x": _ext(1, 0, (1,), b"a")}]), "not allowed"),
        # a shape whose product would need ~16 EiB is refused before any allocation
        (msgpack.packb([6, {"time_s": 0.0, "x": _ext(1, 10, (2**32 - 1, 2**32 - 1), b"")}]), "exceeds"),
        (msgpack.packb([6, {"time_s": 0.0, "x": _ext(2, 1, (1,), b"\0\0\0\0")}]), "missing or reused"),
        (msgpack.packb([6, {"time_s": 0.0, "x": [[[[[[[[[[1]]]]]]]]]]}]), "nesting"),
        (msgpack.packb([6, {"time_s": 0.0, "x": "a" * 70000}]), "malformed"),
        (msgpack.packb([6, {"time_s": 0.0, "x": list(range(5000))}]), "malformed"),
    ],
)
def test_hostile_bodies_raise_codec_errors(body, match):
    with pytest.raises((CodecError, SchemaError), match=match):
        decode_message(body)


def test_limits_cap_array_bytes():
    img = np.zeros((512, 512), np.uint8)
    f = Frame(seq=1, capture_time_s=0.0, position_m=(0, 0, 1), R_world_to_cam=np.eye(3), altimeter_m=1.0, image=img)
    body = encode_message(f)
    with pytest.raises(CodecError):
        decode_message(body, Limits(max_array_bytes=100_000))
    assert decode_message(body, Limits(max_array_bytes=300_000)).image.shape == (512, 512)


def test_unknown_dtype_refused_on_encode():
    with pytest.raises(SchemaError):
        encode_message(
            Frame(
                seq=1,
                capture_time_s=0.0,
                position_m=(0, 0, 1),
                R_world_to_cam=np.eye(3),
                altimeter_m=1.0,
                image=np.array([["a"]], dtype=object),
            )
        )


def test_site_elevation_may_be_unknown_but_position_may_not():
    base = dict(
        frame_seqs=(0, 1),
        hazard_grid=np.zeros((2, 2), np.float32),
        elevation_grid=np.zeros((2, 2), np.float32),
        grid_origin_xy=(0.0, 0.0),
        grid_cell_m=1.0,
    )
    nan_z = Result(**base, sites=[{"x": 1.0, "y": 2.0, "z": math.nan, "hazard": 0.1, "margin": 1.0, "distance_m": 2.2}])
    back = decode_message(encode_message(nan_z))
    assert math.isnan(back.sites[0].z) and back.sites[0].x == 1.0
    with pytest.raises(SchemaError, match=r"Site\.x"):
        encode_message(
            Result(**base, sites=[{"x": math.nan, "y": 2.0, "z": 0.0, "hazard": 0.1, "margin": 1.0, "distance_m": 2.2}])
        )
