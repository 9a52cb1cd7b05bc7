"""The Result's full-resolution fill mask (``elevation_filled_image``): which pixels of ``elevation_image`` are
gap fills, compact on the wire, refused when it does not fit, saved by the ground as ``elevation_filled_image.npy``.
"""

from __future__ import annotations

import dataclasses
import json

import msgpack
import numpy as np
import pytest
from hilkit import run_hil, small_descent

from protocol.codec import EXT_INLINE, _array_header, decode_message, encode_message
from protocol.grids import filled_to_wire
from protocol.messages import Result, SchemaError


def _elevation_and_fills(h: int, w: int, seed: int = 5) -> tuple[np.ndarray, np.ndarray]:
    """A float32 elevation with NaN holes and a fill mask of shadow-like blobs on its finite pixels."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[:h, :w]
    z = (0.01 * xx + 0.02 * yy + rng.normal(0.0, 0.05, (h, w))).astype(np.float32)
    z[rng.random((h, w)) < 0.1] = np.nan
    blobs = np.zeros((h, w), bool)
    for cy, cx, r in rng.uniform(0, 1, (6, 3)) * (h, w, 0.08 * min(h, w)) + (0, 0, 2):
        blobs |= (yy - cy) ** 2 + (xx - cx) ** 2 < r * r
    return z, blobs & np.isfinite(z)


def _result(h: int, w: int, **kw) -> Result:
    base = dict(
        frame_seqs=(4, 5),
        state_grid=np.zeros((2, 2), np.uint8),
        psafe_grid=np.full((2, 2), 254, np.uint8),
        elevation_grid=np.zeros((2, 2), np.int16),
        grid_origin_xy=(-10.0, 3.0),
        grid_cell_m=0.5,
        hazard_image=np.zeros((h, w), np.float32),
        elevation_image=np.zeros((h, w), np.float32),
        state_image=np.zeros((h, w), np.uint8),
    )
    base.update(kw)
    return Result(**base)


def test_the_fill_mask_crosses_the_wire_intact_and_compact():
    z, fills = _elevation_and_fills(512, 512)
    assert 0.002 < fills.mean() < 0.2  # a few shadows, not nothing and not everything
    r = _result(512, 512, elevation_image=z, elevation_filled_image=filled_to_wire(fills))
    out = decode_message(encode_message(r))
    assert isinstance(out, Result)
    got = out.elevation_filled_image
    assert got is not None and got.dtype == np.uint8 and not got.flags.writeable
    assert np.array_equal(got.astype(bool), fills) and set(np.unique(got)) <= {0, 1}
    assert np.array_equal(out.elevation_image, z, equal_nan=True)
    # compressed on the wire: far under the 32 kB a bit-packed 512 x 512 mask would take, let alone 256 kB of bytes
    added = len(encode_message(r)) - len(encode_message(dataclasses.replace(r, elevation_filled_image=None)))
    assert 0 < added < 512 * 512 // 8 // 4


def _wire_map(msg: Result) -> dict:
    """The msgpack map a peer puts on the wire for ``msg``, its arrays left as the codec's ext values."""
    obj = msgpack.unpackb(encode_message(msg), raw=False, ext_hook=msgpack.ExtType)
    return obj[1]


def _decode_map(body: dict) -> Result:
    msg = decode_message(msgpack.packb([Result.TYPE, body], use_bin_type=True))
    assert isinstance(msg, Result)
    return msg


def test_a_result_without_the_mask_still_reads():
    """An older flight program never puts the field on the wire: its Result reads as before, with no mask. Ours
    leaves it off too when there is none (a field newer than the baseline revision, at its default)."""
    body = _wire_map(_result(6, 7))
    assert "elevation_filled_image" not in body and "elevation_image" in body
    old = _decode_map(body)
    assert (
        old.elevation_filled_image is None and old.elevation_image is not None and old.elevation_image.shape == (6, 7)
    )
    # nor one without any image maps (no full_maps)
    body = _wire_map(_result(6, 7, hazard_image=None, elevation_image=None, state_image=None))
    assert "elevation_filled_image" not in body
    assert _decode_map(body).elevation_filled_image is None


@pytest.mark.parametrize(
    "kw, match",
    [
        (dict(elevation_filled_image=np.zeros((6, 8), np.uint8)), r"elevation_filled_image: shape \(6, 8\) != "),
        (dict(elevation_filled_image=np.zeros((7, 7), np.uint8)), r"elevation_filled_image: shape \(7, 7\) != "),
        (
            dict(
                hazard_image=None,
                elevation_image=None,
                state_image=None,
                elevation_filled_image=np.zeros((6, 7), np.uint8),
            ),
            "sent without elevation_image",
        ),
        (dict(elevation_filled_image=np.full((6, 7), 2, np.uint8)), "0 or 1"),
        (dict(elevation_filled_image=np.zeros((6, 7, 1), np.uint8)), "2-D"),
    ],
)
def test_a_mask_that_does_not_fit_the_elevation_image_is_refused(kw, match):
    bad = _result(6, 7, **kw)
    with pytest.raises(SchemaError, match=match):
        bad.validated()  # the sender's check
    with pytest.raises(SchemaError, match=match):
        encode_message(bad)


@pytest.mark.parametrize("shape", [(6, 8), (7, 7), (1, 42)])
def test_a_received_mask_of_another_shape_is_refused(shape):
    """A peer that sends a mask of another shape than its elevation_image: the ground refuses the Result."""
    body = _wire_map(_result(6, 7))
    mask = np.zeros(shape, np.uint8)
    body["elevation_filled_image"] = _wire_map(_result(*shape, elevation_filled_image=mask))["elevation_filled_image"]
    with pytest.raises(
        SchemaError, match=rf"elevation_filled_image: shape \({shape[0]}, {shape[1]}\) != elevation_image"
    ):
        _decode_map(body)
    for k in ("hazard_image", "elevation_image", "state_image"):  # a mask of no elevation_image at all
        body[k] = None
    with pytest.raises(SchemaError, match="sent without elevation_image"):
        _decode_map(body)


@pytest.mark.slow
def test_a_hil_run_with_full_maps_saves_the_pipelines_fill_mask(tmp_path):
    """The ground's elevation_filled_image.npy is the flight pipeline's ``filled``, pixel for pixel."""
    from flight_sw.pipeline import run_pipeline
    from protocol.pairdir import read_pair

    manifest = small_descent(tmp_path / "pairs", ["200/100"])  # 128 px: this pair has gap fills
    s = run_hil(manifest, tmp_path / "run", "zmq", full_maps=True, deadline_s=30.0)
    assert s["results"] == 1 and s["errors"] == 0, [r.get("text") for r in s["records"]]
    (rec,) = s["records"]
    assert rec["level"] == "full" and not rec["degraded"]  # a generous deadline: the pipeline's own answer
    d = tmp_path / "run" / "received" / rec["pair_id"]
    fills, elev = np.load(d / "elevation_filled_image.npy"), np.load(d / "elevation.npy")
    assert fills.dtype == bool and fills.shape == elev.shape
    assert fills.any() and np.isfinite(elev[fills]).all()  # a fill always has an elevation
    entry = json.loads(manifest.read_text())["pairs"][0]
    pair = read_pair(manifest.parent / entry["path"])
    res = run_pipeline(
        pair.images[0],
        pair.images[1],
        pair.poses[0],
        pair.poses[1],
        pair.camera,
        preset="fast",
        altimeter_m=pair.altimeter_m[0],
        sun_elevation_deg=pair.sun.elevation_deg,
        sun_azimuth_deg=pair.sun.azimuth_deg,
    )
    assert res.filled is not None and np.array_equal(fills, res.filled)
    assert np.array_equal(elev, res.elevation, equal_nan=True)  # the same DEM the mask marks
    assert np.load(d / "elevation_filled_grid.npy").dtype == bool  # the grid's own mask still comes beside it


@pytest.mark.parametrize(
    "kw, match",
    [
        (dict(hazard_image=np.full((6, 7), 5.0, np.float32)), r"hazard_image: values must lie in \[0, 1\]"),
        (dict(hazard_image=np.full((6, 7), -1.0, np.float32)), r"hazard_image: values must lie in \[0, 1\]"),
        (dict(hazard_image=np.full((6, 7), np.inf, np.float32)), r"hazard_image: values must lie in \[0, 1\]"),
        (dict(elevation_image=np.full((6, 7), -np.inf, np.float32)), "elevation_image: holds inf"),
    ],
)
def test_image_maps_out_of_their_range_are_refused_on_both_sides(kw, match):
    """A hazard_image of 5, -1 or inf passed the HIL (a -1 reads as called safe) and `score` then refused the map
    the run had saved; a state_image out of its codes was refused all along."""
    bad = _result(6, 7, **kw)
    with pytest.raises(SchemaError, match=match):
        bad.validated()
    good = _result(6, 7, hazard_image=np.full((6, 7), np.nan, np.float32))  # NaN: outside, allowed
    assert np.isnan(decode_message(encode_message(good)).hazard_image).all()  # type: ignore[attr-defined]
    body = _wire_map(_result(6, 7))
    key, value = next(iter(kw.items()))
    body[key] = msgpack.ExtType(EXT_INLINE, _array_header(value) + value.tobytes())  # as a peer could send it
    with pytest.raises(SchemaError, match=match):
        _decode_map(body)  # the receiver's check
