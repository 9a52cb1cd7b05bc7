"""Round-trip and hostile-input tests for the message schema and msgpack codec."""

from __future__ import annotations

import math
import zlib
from dataclasses import fields, replace

import msgpack
import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp
from resultrev import old_ground_decode, small_result

from protocol.codec import (
    CodecError,
    Limits,
    decode_message,
    decode_parts,
    delta_encode,
    encode_message,
    encode_parts,
    scan,
)
from protocol.fuzz import nested_map_bomb
from protocol.grids import (
    decimate_mean,
    elevation_from_wire,
    elevation_to_wire,
    psafe_from_wire,
    psafe_to_wire,
)
from protocol.messages import (
    MESSAGE_TYPES,
    RESULT_REV,
    Config,
    Error,
    Frame,
    Heartbeat,
    Hello,
    Result,
    SchemaError,
    Site,
    Telemetry,
)

finite = st.floats(allow_nan=False, allow_infinity=False, width=64)
duration = st.floats(min_value=0.0, allow_nan=False, allow_infinity=False, width=64)
nan_or_finite = st.one_of(st.floats(allow_nan=False, allow_infinity=False), st.just(float("nan")))  # "NaN allowed"
names = st.text(max_size=20)
u32 = st.integers(0, 2**32 - 1)


def f32_grid(max_side: int = 12) -> st.SearchStrategy[np.ndarray]:
    return hnp.arrays(
        np.float32,
        hnp.array_shapes(min_dims=2, max_dims=2, min_side=0, max_side=max_side),
        elements=st.floats(width=32),
    )  # includes NaN and +-inf


# a hazard map's values (NaN outside the covered area) and an elevation map's (NaN where none was recovered)
unit_or_nan = st.one_of(st.floats(0.0, 1.0, width=32), st.just(float("nan")))
finite_or_nan = st.one_of(st.floats(width=32, allow_infinity=False), st.just(float("nan")))
unit = st.floats(0.0, 1.0)
nonneg = st.floats(0.0, 1e12)
nonneg_or_nan = st.one_of(nonneg, st.just(float("nan")))
# a site's fields in their ranges (docs/protocol.md 5.4): NaN where allowed, never an infinity
sites = st.lists(
    st.builds(Site, finite, finite, finite_or_nan, unit, unit, nonneg, unit_or_nan, nonneg_or_nan), max_size=5
)


def flags(shape: tuple[int, int]) -> st.SearchStrategy[np.ndarray]:
    return hnp.arrays(np.uint8, shape, elements=st.integers(0, 1))


@st.composite
def results(draw, maps: bool = False) -> Result:
    """Compact Results with consistent grid shapes, any elevation step, optional fill masks and optional image maps
    (``maps`` True: always; the gap-fill mask of elevation_image optional beside them)."""
    h, w = draw(st.integers(0, 12)), draw(st.integers(0, 12))
    step, pstep = draw(st.integers(1, 5)), draw(st.integers(1, 5))
    states = draw(hnp.arrays(np.uint8, (h, w), elements=st.sampled_from([0, 1, 2, 255])))
    shape = st.tuples(st.integers(0, 9), st.integers(0, 9))
    img = draw(shape if maps else st.none() | shape)
    elev_shape = (-(-h // step), -(-w // step))
    origin, cell = draw(st.tuples(finite, finite)), draw(st.floats(1e-3, 1e3))
    on_grid = [  # a site is on the grid it was picked from (the schema refuses one off it)
        replace(
            s,
            x=origin[0] + draw(st.integers(0, max(w - 1, 0))) * cell,
            y=origin[1] - draw(st.integers(0, max(h - 1, 0))) * cell,
        )
        for s in draw(sites)
    ]
    return Result(
        frame_seqs=draw(st.tuples(u32, u32)),
        state_grid=states,
        psafe_grid=draw(hnp.arrays(np.uint8, (-(-h // pstep), -(-w // pstep)))),
        psafe_step=pstep,
        elevation_grid=draw(hnp.arrays(np.int16, elev_shape)),
        grid_origin_xy=origin,
        grid_cell_m=cell,
        elevation_step=step,
        elevation_offset_m=draw(finite),
        elevation_unit_cm=draw(st.integers(1, 1000)),
        sites=on_grid,
        no_site_reason=draw(st.none() | names),
        degraded=draw(st.booleans()),
        level=draw(names),
        skipped=tuple(draw(st.lists(names, max_size=4))),
        hazard_image=None if img is None else draw(hnp.arrays(np.float32, img, elements=unit_or_nan)),
        elevation_image=None if img is None else draw(hnp.arrays(np.float32, img, elements=finite_or_nan)),
        state_image=None if img is None else draw(hnp.arrays(np.uint8, img, elements=st.sampled_from([0, 1, 2, 255]))),
        elevation_filled=draw(st.none() | flags(elev_shape)),
        elevation_filled_image=None if img is None else draw(st.none() | flags(img)),
    )


messages = st.one_of(
    st.builds(Hello, role=names, protocol_version=st.integers(0, 255), software=names, session=u32),
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
        altimeter_m=nan_or_finite,
        image=hnp.arrays(np.uint8, hnp.array_shapes(min_dims=2, max_dims=2, min_side=0, max_side=16)),
        pair_id=st.none() | names,
        frame_index=st.none() | u32,
    ),
    results(),
    st.builds(
        Telemetry,
        frame_seqs=st.tuples(u32, u32),
        stages=st.dictionaries(
            st.text(max_size=10), st.fixed_dictionaries({"wall_s": duration, "cpu_s": duration}), max_size=5
        ),
        queue_wait_s=duration,
        total_latency_s=duration,
        cpu_fraction=nan_or_finite,
        peak_rss_bytes=st.integers(0, 2**40),
        deadline_s=nan_or_finite,
        deadline_met=st.booleans(),
        link=st.dictionaries(st.text(max_size=10), st.integers(0, 10**9) | finite, max_size=6),
    ),
    st.builds(Heartbeat, time_s=finite, counter=st.integers(0, 2**40)),
    st.builds(Error, code=names, text=st.text(max_size=200), seq=st.none() | u32),
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
    assert set(MESSAGE_TYPES) == set(range(1, 8))  # 8, 9 (v1 link Ack/Nack) are retired


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


@settings(max_examples=100, deadline=None)
@given(results(), st.integers(0, RESULT_REV + 1))
def test_a_result_at_a_revision_is_what_a_ground_of_that_revision_decodes(msg, rev):
    """``for_rev``: a ground that knows only the fields up to ``rev`` decodes the Result, each field it knows as
    sent; today's ground reads the same Result with the newer fields at their default."""
    cut = msg.for_rev(rev).validated()
    body = encode_message(cut)
    old = old_ground_decode(body, min(rev, RESULT_REV))
    assert all(same(getattr(old, f.name), getattr(cut, f.name)) for f in fields(old))  # type: ignore[arg-type]
    assert same(cut, decode_message(body))


@settings(max_examples=100, deadline=None)
@given(results(maps=True), st.tuples(st.integers(0, 9), st.integers(0, 9)), st.booleans())
def test_a_fill_mask_that_does_not_fit_elevation_image_is_refused_by_sender_and_receiver(msg, shape, no_image):
    """A corrupted fill mask: of another shape than ``elevation_image``, or beside no ``elevation_image``."""
    assume(no_image or shape != msg.elevation_image.shape)
    mask = np.zeros(shape, np.uint8)
    bad = replace(msg, elevation_filled_image=mask, elevation_image=None if no_image else msg.elevation_image)
    match = "sent without elevation_image" if no_image else r"elevation_filled_image: shape \(.*\) != elevation_image"
    with pytest.raises(SchemaError, match=match):
        encode_message(bad)
    # a peer that sends it anyway: the mask (and no elevation_image) spliced into a valid Result's body
    body = msgpack.unpackb(encode_message(msg), raw=False, ext_hook=msgpack.ExtType)[1]
    carrier = small_result(elevation_image=np.zeros(shape, np.float32), elevation_filled_image=mask)
    body["elevation_filled_image"] = msgpack.unpackb(encode_message(carrier), ext_hook=msgpack.ExtType)[1][
        "elevation_filled_image"
    ]
    if no_image:
        del body["elevation_image"]
    with pytest.raises(SchemaError, match=match):
        decode_message(msgpack.packb([Result.TYPE, body], use_bin_type=True))


def test_compact_result_survives_bitwise_and_arrays_are_read_only():
    r = small_result(sites=[], degraded=True, level="coarse", no_site_reason="no footprint is known safe")
    out = decode_message(encode_message(r))
    assert out.sites == [] and out.degraded is True and out.no_site_reason == "no footprint is known safe"
    for name in ("state_grid", "psafe_grid", "elevation_grid"):
        assert getattr(out, name).tobytes() == getattr(r, name).tobytes() and not getattr(out, name).flags.writeable
    assert out.elevation_filled is None  # optional: a flight program that does not fill does not send it
    f = np.array([[0, 1], [0, 0]], np.uint8)
    assert decode_message(encode_message(small_result(elevation_filled=f))).elevation_filled.tobytes() == f.tobytes()


def test_site_p_safe_and_clearance_travel_and_may_be_unknown():
    r = small_result(
        grid_origin_xy=(0.0, 2.0),
        sites=[Site(1.0, 2.0, 3.0, 0.1, 0.9, 4.0, 0.97, 1.25), Site(0.0, 1.5, math.nan, 0.0, 1.0, 0.0)],
    )
    a, b = decode_message(encode_message(r)).sites
    assert (a.p_safe, a.clearance_m) == (0.97, 1.25)
    assert math.isnan(b.p_safe) and math.isnan(b.clearance_m) and math.isnan(b.z)


@pytest.mark.parametrize(
    "kw, match",
    [
        (dict(total_latency_s=-5.0), r"total_latency_s: must be >= 0"),
        (dict(queue_wait_s=-0.1), r"queue_wait_s: must be >= 0"),
        (dict(stages={"dem": {"wall_s": -1.0, "cpu_s": 0.0}}), r"wall_s: must be >= 0"),
        (dict(peak_rss_bytes=2**62), r"peak_rss_bytes: \d+ outside"),
    ],
)
def test_telemetry_figures_no_clock_or_memory_can_read_are_refused(kw, match):
    """A flight latency of -5 s and a peak memory of 2**62 bytes were shown as they came (stop 58's QA)."""
    with pytest.raises(SchemaError, match=match):
        encode_message(Telemetry(frame_seqs=(1, 2), **kw))


def test_a_duration_a_rounding_below_zero_is_taken_as_zero():
    """Two clock reads subtracted can land at -1e-12 s; the whole Telemetry was refused for it (stop 58's note)."""
    t = Telemetry(frame_seqs=(1, 2), total_latency_s=-1e-12, stages={"dem": {"wall_s": -1e-9, "cpu_s": 0.25}})
    got = decode_message(encode_message(t))
    assert got.total_latency_s == 0.0 and got.stages["dem"] == {"wall_s": 0.0, "cpu_s": 0.25}
    with pytest.raises(SchemaError, match=r"queue_wait_s: must be >= 0, got -2e-06"):
        encode_message(Telemetry(frame_seqs=(1, 2), queue_wait_s=-2e-6))


@pytest.mark.parametrize(
    "kw, match",
    [
        (dict(psafe_grid=np.zeros((3, 2), np.uint8)), "psafe_grid"),
        (dict(elevation_grid=np.zeros((1, 1), np.int16)), "decimated"),
        (dict(elevation_step=2, elevation_grid=np.zeros((2, 2), np.int16)), "decimated"),
        (dict(psafe_step=2, psafe_grid=np.zeros((2, 2), np.uint8)), "decimated by 2"),
        (dict(state_grid=np.array([[0, 3], [2, 255]], np.uint8)), "state codes"),
        (dict(grid_cell_m=0.0), "> 0"),
        (dict(hazard_image=np.zeros((4, 4), np.float32), state_image=np.zeros((4, 3), np.uint8)), "one shape"),
        (dict(elevation_filled=np.zeros((3, 2), np.uint8)), "elevation_filled: shape"),
        (dict(elevation_filled=np.array([[0, 2], [1, 0]], np.uint8)), "0 or 1"),
        (dict(skipped=tuple(f"stage{i}" for i in range(33))), "at most 32 names"),
        (dict(skipped=("rocks", 3)), r"skipped\[1\]: expected a string"),
        (dict(skipped=("x" * 65,)), "exceeds 64"),
    ],
)
def test_result_grids_must_agree(kw, match):
    with pytest.raises(SchemaError, match=match):
        encode_message(small_result(**kw))


def test_decimated_elevation_grid_has_the_ceiling_shape():
    r = small_result(
        state_grid=np.zeros((5, 7), np.uint8), psafe_grid=np.zeros((5, 7), np.uint8), elevation_step=3,
        elevation_grid=np.zeros((2, 3), np.int16),
    )  # fmt: skip
    assert decode_message(encode_message(r)).elevation_grid.shape == (2, 3)


def test_compact_result_is_small_on_the_wire():
    """A realistic 255 x 255 grid: mostly large uniform regions, smooth terrain."""
    rng = np.random.default_rng(0)
    state = np.zeros((255, 255), np.uint8)
    state[40:120, 30:200] = 1
    state[:, :5] = 255
    yy, xx = np.mgrid[0:255, 0:255]
    z = (np.sin(xx / 30.0) * 3 + np.cos(yy / 25.0) * 2 + rng.normal(0, 0.05, (255, 255))).astype(np.float32)
    elev, offset = elevation_to_wire(z, 4)
    r = Result(
        frame_seqs=(0, 1),
        state_grid=state,
        psafe_grid=psafe_to_wire(np.where(state == 0, 1.0, 0.0)),
        elevation_grid=elev,
        elevation_step=4,
        elevation_offset_m=offset,
        grid_origin_xy=(0.0, 0.0),
        grid_cell_m=0.6,
    )
    body = encode_message(r)
    assert len(body) < 12_000  # raw: 3 x 65 kB of grids
    back = decode_message(body)
    assert np.array_equal(back.state_grid, state)
    err = np.abs(elevation_from_wire(back.elevation_grid, back.elevation_offset_m) - decimate_mean(z, 4))
    assert np.nanmax(err) <= 0.005 + 1e-6


def test_grid_quantisation_round_trips_within_a_step():
    p = np.array([[0.0, 1.0, 0.5, np.nan], [0.123, 0.999, 1.5, -0.2]], np.float32)
    q = psafe_to_wire(p)
    assert q[0, 3] == 255 and q[0, 0] == 0 and q[0, 1] == 254 and q[1, 2] == 254 and q[1, 3] == 0
    back = psafe_from_wire(q)
    ok = np.isfinite(p) & (p >= 0) & (p <= 1)
    assert np.all(np.abs(back[ok] - p[ok]) <= 0.5 / 254 + 1e-7) and np.isnan(back[0, 3])
    z = np.array([[np.nan, 1.234, 400.0], [-3.0, 0.0, 2.005]], np.float32)
    v, off = elevation_to_wire(z, 1)
    assert v[0, 0] == -32768 and off == 1.0  # the median, rounded to a metre
    back = elevation_from_wire(v, off)
    assert np.isnan(back[0, 0]) and abs(back[0, 1] - 1.234) <= 0.005
    assert back[0, 2] == pytest.approx(328.67)  # saturated 327.67 m above the offset


def test_decimated_psafe_is_the_block_minimum():
    p = np.array([[0.9, 0.2, 1.0], [0.8, np.nan, np.nan], [np.nan, np.nan, 0.5]], np.float32)
    q = psafe_to_wire(p, 2)
    assert q.shape == (2, 2) and q[0, 0] == round(0.2 * 254) and q[0, 1] == 254 and q[1, 1] == 127
    assert q[1, 0] == 255  # a block with no finite value is outside


def test_psafe_of_the_cells_not_called_safe_goes_in_sixteenths():
    """The cells the flight did not call safe carry P(safe) to 1/16 (their state decides; 17 values compress
    better), the others to 1/254 as before; the block minimum is taken after the rounding."""
    rng = np.random.default_rng(3)
    p = rng.uniform(0.0, 1.0, (16, 16)).astype(np.float32)
    p[0, 0] = np.nan
    coarse = rng.random((16, 16)) < 0.6
    back = psafe_from_wire(psafe_to_wire(p, coarse=coarse))
    fine = ~coarse & np.isfinite(p)
    assert np.all(np.abs(back[fine] - p[fine]) <= 0.5 / 254 + 1e-7)  # as without the mask
    c = coarse & np.isfinite(p)
    assert np.all(np.abs(back[c] - p[c]) <= 1 / 32 + 0.5 / 254 + 1e-7)
    assert len(np.unique(psafe_to_wire(p, coarse=coarse)[c])) <= 17 < len(np.unique(psafe_to_wire(p)[c]))
    assert np.isnan(back[0, 0])
    q2 = psafe_to_wire(p, 2, coarse=coarse)  # the block minimum of the rounded values
    rounded = np.where(coarse, np.rint(p * 16) / 16, p)
    assert np.array_equal(q2, psafe_to_wire(rounded, 2))
    with pytest.raises(ValueError, match="levels"):
        psafe_to_wire(p, coarse=coarse, levels=0)


def test_delta_filter_wraps_around_int16():
    e = np.array([[32767, -32768, 0, 12345, -32767], [-32768, 32767, -1, 1, 0], [0, 0, 32767, -32768, 5]], np.int16)
    out = decode_message(encode_message(small_result(
        state_grid=np.zeros((3, 5), np.uint8), psafe_grid=np.zeros((3, 5), np.uint8), elevation_grid=e
    )))  # fmt: skip
    assert np.array_equal(out.elevation_grid, e)


def test_the_elevation_grid_travels_as_the_residual_of_the_planar_predictor():
    """Filter 2: a plane's differences along both axes are zero, so it compresses to almost nothing."""
    yy, xx = np.mgrid[0:200, 0:200]
    plane = (3 * xx - 7 * yy + 11).astype(np.int16)
    assert np.all(delta_encode(plane, 2)[1:, 1:] == 0)
    msg = small_result(
        state_grid=np.zeros((200, 200), np.uint8), psafe_grid=np.zeros((200, 200), np.uint8), elevation_grid=plane
    )
    parts = msgpack.unpackb(encode_message(msg), raw=False, strict_map_key=False)
    ext = parts[1]["elevation_grid"]
    assert ext.code == 3 and ext.data[2 + 4 * 2] == 2  # filter byte after dtype, ndim and two u32 sides
    assert len(ext.data) < 800  # raw: 80 kB
    assert np.array_equal(decode_message(encode_message(msg)).elevation_grid, plane)


def test_a_coarser_elevation_unit_rounds_by_half_a_unit_and_shrinks_the_grid():
    """``elevation_unit_cm`` u: every value decodes within u/2 cm, and noise below u no longer travels."""
    rng = np.random.default_rng(3)
    yy, xx = np.mgrid[0:240, 0:240]
    z = (np.sin(xx / 20.0) * 4 + yy * 0.05 + rng.normal(0, 0.3, (240, 240))).astype(np.float32)
    z[100:130, 50:90] = np.nan
    sizes = {}
    for unit in (1, 10):
        v, off = elevation_to_wire(z, 2, unit)
        msg = small_result(
            state_grid=np.zeros((240, 240), np.uint8),
            psafe_grid=np.zeros((240, 240), np.uint8),
            elevation_grid=v,
            elevation_step=2,
            elevation_offset_m=off,
            elevation_unit_cm=unit,
        )
        body = encode_message(msg)
        back = decode_message(body)
        got = elevation_from_wire(back.elevation_grid, back.elevation_offset_m, back.elevation_unit_cm)
        want = decimate_mean(z, 2)
        assert np.array_equal(np.isnan(got), np.isnan(want))
        assert np.nanmax(np.abs(got - want)) <= unit / 200 + 1e-4
        sizes[unit] = len(body)
    assert sizes[10] < 0.75 * sizes[1]


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
        (msgpack.packb([6, {"time_s": 1.0, "evil": 2}]), "unknown fields"),
        (msgpack.packb([8, {"seq": 1}]), "unknown message type"),  # the retired v1 Ack
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


def test_site_position_must_be_finite():
    with pytest.raises(SchemaError, match=r"Site\.x"):
        encode_message(
            small_result(sites=[{"x": math.nan, "y": 2.0, "z": 0.0, "hazard": 0.1, "margin": 1.0, "distance_m": 2}])
        )


# ---------------------------------------------------------------------------------- budgets
@pytest.mark.parametrize("nbytes", [4 << 20, 32 << 20])
def test_nested_map_bombs_are_refused_by_the_object_budget(nbytes):
    """The issue's bombs pass every per-container limit; the object budget refuses them before msgpack runs.
    Time and memory bounds are measured in bench/bench_protocol.py (not asserted here: shared machine)."""
    import tracemalloc

    body = nested_map_bomb(nbytes)
    assert nbytes * 0.99 < len(body) <= nbytes
    tracemalloc.start()
    with pytest.raises(CodecError, match="object budget"):
        decode_message(body)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    assert peak < 1 << 20  # nothing proportional to the body was allocated


def test_scan_counts_every_value_and_accepts_what_the_encoder_makes():
    body = encode_message(Telemetry(frame_seqs=(1, 2), stages={"a": {"wall_s": 1.0, "cpu_s": 0.5}}))
    assert scan(body) >= 10
    with pytest.raises(CodecError, match="object budget"):
        scan(body, Limits(max_objects=5))


def _ext3(shape, filt, payload, code=1):
    head = bytes((code, len(shape))) + b"".join(int(s).to_bytes(4, "big") for s in shape)
    return msgpack.ExtType(3, head + bytes((filt,)) + payload)


@pytest.mark.parametrize(
    "value, match",
    [
        (_ext3((1024, 1024), 0, zlib.compress(bytes(100))), "does not inflate"),  # shorter than declared
        (_ext3((10, 10), 0, zlib.compress(bytes(1 << 20))), "does not inflate"),  # zlib bomb: longer
        (_ext3((10, 10), 0, zlib.compress(bytes(100)) + b"x"), "does not inflate"),  # trailing bytes
        (_ext3((10, 10), 0, b"not zlib at all"), "compressed array"),
        (_ext3((10, 10), 9, zlib.compress(bytes(100))), "filter"),
        (_ext3((10, 10), 1, zlib.compress(bytes(400)), code=9), "filter"),  # delta on float32
        (_ext3((10, 10), 2, zlib.compress(bytes(400)), code=9), "filter"),
        (_ext3((10,), 2, zlib.compress(bytes(20)), code=4), "at least 2 axes"),  # two axes of a 1-D array
        (_ext3((), 1, zlib.compress(bytes(2)), code=4), "at least 1 axes"),
        (_ext3((8192, 8192), 0, zlib.compress(bytes(10))), "exceeds"),  # over the per-array limit
    ],
)
def test_compressed_arrays_inflate_to_exactly_their_declared_size(value, match):
    with pytest.raises(CodecError, match=match):
        decode_message(msgpack.packb([6, {"time_s": 0.0, "x": value}]))


def test_total_decoded_bytes_budget_counts_declared_sizes_before_inflating():
    zeros = zlib.compress(bytes(4 << 20), 9)
    body = msgpack.packb([6, {f"a{i}": _ext3((2048, 2048), 0, zeros) for i in range(4)}])
    with pytest.raises(CodecError, match="in total"):
        decode_message(body, Limits(max_decoded_bytes=12 << 20))


def test_fixext_sized_compressed_array_is_counted_too():
    # msgpack packs an ext of exactly 16 data bytes as fixext16 (0xd8): the budget must still see it
    val = _ext3((4096, 1024), 0, b"\x78\x9c\x03\x00\x00")  # 10 header + 1 filter + 5 = 16 bytes
    body = msgpack.packb([6, {"time_s": 0.0, "x": val}])
    assert b"\xd8\x03" in body
    with pytest.raises(CodecError, match="in total"):
        decode_message(body, Limits(max_decoded_bytes=1 << 20))


@pytest.mark.parametrize("cell", [1e-300, 0.0009, 1.0e5])
def test_a_result_grid_cell_out_of_range_is_refused(cell):
    """1e-300 m passed the schema: every score of the pair came back empty, with no reason."""
    from resultrev import small_result

    from protocol.messages import SchemaError

    with pytest.raises(SchemaError, match=r"grid_cell_m: must be in \[0\.001, 10000\] m"):
        encode_message(small_result(grid_cell_m=cell))
    encode_message(small_result(grid_cell_m=0.001))  # the limits themselves are cells


def test_a_result_site_off_its_grid_is_refused():
    """A site at (1e12, -1e12) m, far off a 2 x 2-cell grid, was accepted and recorded with its P(safe)."""
    from resultrev import small_result

    from protocol.messages import SchemaError, Site

    def site(x: float, y: float) -> Site:
        return Site(x, y, 0.0, 0.0, 1.0, 0.0, 0.99, 2.0)

    # the grid's cell centres: x -10, -9.5; y 3, 2.5 (cell 0.5 m); its outer edges plus one cell of slack
    for ok in (site(-10.0, 3.0), site(-9.5, 2.5), site(-10.75, 3.75), site(-8.75, 1.75)):
        encode_message(small_result(sites=[ok]))
    for bad in (site(1e12, -1e12), site(-10.8, 3.0), site(-10.0, 1.7)):
        with pytest.raises(
            SchemaError, match=r"Result\.sites\[1\]: .* is off the grid, which spans x -10\.75\.\.-8\.75"
        ):
            encode_message(small_result(sites=[site(-10.0, 3.0), bad]))


def test_an_array_over_the_per_array_limit_is_named_by_the_rule_not_by_msgpack():
    """A Result carrying one 20 MiB array was refused as "20971531 exceeds max_ext_len(16778240)"."""
    import msgpack

    from protocol.codec import CodecError, decode_message

    body = msgpack.packb([4, {"hazard_image": msgpack.ExtType(1, b"x" * (20 << 20))}], use_bin_type=True)
    with pytest.raises(CodecError, match=r"^an array of \d+ bytes exceeds the 16777216-byte per-array limit$"):
        decode_message(body)


def test_a_hello_that_leaves_out_its_name_and_version_is_not_reported_as_ours():
    """A Hello of {"role": "flight"} decoded to software 'hazard-hil', protocol 2, and the ground reported a board
    of one's own as "hazard-hil" (stop 58's review)."""
    from hil_server.run import hello_note

    bare = decode_message(msgpack.packb([Hello.TYPE, {"role": "flight"}]))
    assert bare.omitted == ("protocol_version", "software")
    full = decode_message(encode_message(Hello(role="flight", software="board-7")))
    assert full.omitted == () and Hello(role="x").omitted == ()
    run = {"flight": "external", "ground_counters": {}}
    run["ground_counters"]["flight_hello"] = {
        "role": "flight", "software": None, "protocol_version": 2, "omitted": ["protocol_version", "software"]
    }  # fmt: skip
    said = hello_note(run)
    assert "no name" in said and "'hazard-hil'" not in said and "protocol 2 by default" in said


def test_an_integer_grid_of_another_type_is_taken_only_when_its_values_fit():
    """Another integer dtype was cast with wrap-around: a state grid of int16 256 arrived as 0, "safe" (FP 22 %,
    PASS), and an elevation of int32 40000 as -25536 (QA 64a, H1). Values that fit are still taken."""
    fits = small_result(state_grid=np.array([[0, 1], [2, 255]], np.int16))
    out = decode_message(encode_message(fits))
    assert out.state_grid.dtype == np.uint8 and out.state_grid.tolist() == [[0, 1], [2, 255]]
    for kw, match in (
        (dict(state_grid=np.full((2, 2), 256, np.int16)), r"state_grid: expected dtype uint8, got int16 with values "),
        (dict(psafe_grid=np.full((2, 2), -1, np.int8)), r"psafe_grid: .* values -1..-1 outside its range"),
        (dict(elevation_grid=np.full((2, 2), 40000, np.int32)), r"elevation_grid: .* values 40000..40000 outside"),
    ):
        with pytest.raises(SchemaError, match=match):
            encode_message(small_result(**kw))


@pytest.mark.parametrize(
    "values, match",
    [
        ((0, 0, 0, 0, 1, 0, math.inf, 1), r"Site.p_safe: must be finite or NaN, got inf"),
        ((0, 0, 0, 0, 1, 0, 5.0, 1), r"Site.p_safe: must be in \[0, 1\], got 5"),
        ((0, 0, 0, 0, 1, 0, 0.9, -3), r"Site.clearance_m: must be >= 0, got -3"),
        ((0, 0, 0, 1.5, 1, 0, 0.9, 1), r"Site.hazard: must be in \[0, 1\], got 1.5"),
        ((0, 0, 0, 0, -0.2, 0, 0.9, 1), r"Site.margin: must be in \[0, 1\], got -0.2"),
        ((0, 0, 0, 0, 1, -1, 0.9, 1), r"Site.distance_m: must be >= 0, got -1"),
        ((0, 0, -math.inf, 0, 1, 0, 0.9, 1), r"Site.z: must be finite or NaN, got -inf"),
        ({"x": 1.0, "y": 2.0}, r"Site: expected an array of 8 numbers, or a map .* this map lacks z, hazard"),
    ],
)
def test_a_site_out_of_its_fields_ranges_is_refused(values, match):
    """A flight program's site with P(safe) inf or 5.0, or a clearance of -3 m, was accepted: results.jsonl then
    held "Infinity" (QA of stop 72). "NaN allowed" allows NaN, never an infinity (docs/protocol.md 5.4)."""
    with pytest.raises(SchemaError, match=match):
        Site.from_wire(list(values) if isinstance(values, tuple) else values)
    assert Site.from_wire([0, 0, math.nan, 0, 1, 0, math.nan, math.nan]).p_safe != 0.5  # NaN stays allowed


def test_no_nan_allowed_field_takes_an_infinity():
    t = Telemetry(frame_seqs=(0, 1), deadline_s=math.inf)
    with pytest.raises((SchemaError, CodecError), match=r"Telemetry.deadline_s: must be finite or NaN, got inf"):
        encode_message(t)  # the sender refuses it, as the receiver does
