"""Input audit of the ground side: each bad input is one line naming the file/option, exit 2, no traceback.

Covers garbled image headers (and a streamed descent going on past such a pair), non-numeric trajectory
fields, two pairs rendered to one directory, out-of-range seeds, ``scenes --table``/``--workers`` checked
before measuring, non-finite sun angles, and implausible altimeter readings.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import struct
import zlib
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from hilkit import one_line_error, run_hil, small_descent

from protocol.pairdir import PairFormatError, Pose, check_altimeter, image_header_size, png_damage, read_pair

NADIR = np.diag([1.0, -1.0, -1.0])  # camera looking straight down


@pytest.fixture(scope="module")
def descent(tmp_path_factory) -> Path:
    """A 128 px vertical descent of two pairs; returns its manifest."""
    return small_descent(tmp_path_factory.mktemp("pairs"), ["600/300", "300/150"])


def copy_pair(descent: Path, tmp_path: Path, label_dir: str = "600_300") -> Path:
    d = tmp_path / label_dir
    shutil.copytree(descent.parent / label_dir, d)
    return d


def edit_json(path: Path, change: Callable[[dict], object]) -> None:
    doc = json.loads(path.read_text())
    change(doc)
    path.write_text(json.dumps(doc))


# --------------------------------------------------------------------------- 1. image headers
PNG_SIG = b"\x89PNG\r\n\x1a\n"
HEADERS = {
    "png cut in IHDR": PNG_SIG + b"\x00\x00\x00\x0dIHDR\x00\x00",
    "png without IHDR": PNG_SIG + b"\x00" * 40,
    "pgm letters for size": b"P5\nabc def\n255\n",
    "pgm without size": b"P5\n# only a comment\n",
    "tiff of 4 bytes": b"II*\x00",
    "tiff directory past the end": b"MM\x00*\x00\x00\xff\xff",
    "tiff without size tags": b"II*\x00\x08\x00\x00\x00\x00\x00",
    "bmp cut": b"BM" + b"\x00" * 10,
    "jpeg without frame header": b"\xff\xd8\xff\xe0\x00\x10" + b"\x00" * 20,
}


@pytest.mark.parametrize("data", HEADERS.values(), ids=HEADERS.keys())
def test_garbled_image_header_is_a_pair_format_error_naming_the_file(tmp_path, data):
    p = tmp_path / "img.bin"
    p.write_bytes(data)
    with pytest.raises(PairFormatError, match=r"img\.bin: not a readable image \(") as exc:
        image_header_size(p)
    assert "\n" not in str(exc.value)


@pytest.mark.parametrize("depth", [np.uint8, np.uint16])
def test_a_tiff_whose_directory_follows_its_pixels_is_read(tmp_path, depth):
    """libtiff (OpenCV, GDAL, ImageMagick) writes the image directory after the pixels: every such TIFF over
    64 kB, a 512 x 512 one among them, was refused as "not a readable image" (stop 58's QA)."""
    import cv2

    p = tmp_path / "i1.tif"
    img = (np.arange(300 * 512) % 251).reshape(300, 512).astype(depth)
    assert cv2.imwrite(str(p), img, [cv2.IMWRITE_TIFF_COMPRESSION, 1])  # uncompressed: the directory far out
    assert int.from_bytes(p.read_bytes()[4:8], "little") > 64 * 1024
    assert image_header_size(p) == (512, 300)


@pytest.mark.parametrize("off", [1000, 65000, 65520, 70000])
def test_a_tiff_directory_is_read_wherever_it_starts(tmp_path, off):
    """One whose directory began just inside the first 64 kB read, its size tags past them, had "no width/height
    tags" (stop 58's review)."""
    tags = [(256, 3, 16), (257, 3, 12), (258, 3, 8), (259, 3, 1), (262, 3, 1), (273, 4, 8), (277, 3, 1),
            (278, 3, 12), (279, 4, 192), (284, 3, 1)]  # fmt: skip
    b = bytearray(b"II*\x00" + struct.pack("<I", off))
    b += bytes(off - len(b)) + struct.pack("<H", len(tags))
    for tag, typ, v in tags:
        b += struct.pack("<HHI", tag, typ, 1) + (struct.pack("<HH", v, 0) if typ == 3 else struct.pack("<I", v))
    p = tmp_path / "i.tif"
    p.write_bytes(bytes(b + struct.pack("<I", 0)))
    assert image_header_size(p) == (16, 12)


def test_process_with_a_truncated_png_is_one_line_and_exit_2(descent, tmp_path, capsys):
    d = copy_pair(descent, tmp_path)
    (d / "i2.png").write_bytes((d / "i2.png").read_bytes()[:20])  # `head -c 20`
    err = one_line_error(capsys, ["process", str(d), "--out", str(tmp_path / "out")])
    assert "i2.png: not a readable image" in err


def test_process_with_a_damaged_png_says_why_in_one_line_and_libpng_says_nothing(descent, tmp_path, capfd):
    d = copy_pair(descent, tmp_path)
    data = bytearray((d / "i2.png").read_bytes())
    data[len(data) // 2 : len(data) // 2 + 40] = bytes(40)  # a burst of zeros inside the pixel data
    (d / "i2.png").write_bytes(data)
    # capfd, not capsys: libpng writes to the C stderr, which capsys never sees
    err = one_line_error(capfd, ["process", str(d), "--out", str(tmp_path / "out")])
    assert "i2.png: not a readable image (chunk 'IDAT' fails its CRC: the file is damaged)" in err


def png(width: int, height: int, idat: bytes, colour: int = 0, interlace: int = 0) -> bytes:
    def chunk(kind: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))

    ihdr = struct.pack(">IIBBBBB", width, height, 8, colour, 0, 0, interlace)
    return PNG_SIG + chunk(b"IHDR", ihdr) + chunk(b"IDAT", idat) + chunk(b"IEND", b"")


def adam7(img: np.ndarray) -> bytes:
    """An 8-bit grey image's interlaced pixel stream, filter 0 on every row (PNG spec sec 8.2)."""
    passes = ((0, 0, 8, 8), (4, 0, 8, 8), (0, 4, 4, 8), (2, 0, 4, 4), (0, 2, 2, 4), (1, 0, 2, 2), (0, 1, 1, 2))
    return b"".join(b"\0" + row.tobytes() for x0, y0, dx, dy in passes for row in img[y0::dy, x0::dx] if row.size)


def test_a_png_is_checked_whole_before_it_is_decoded(tmp_path):
    import cv2

    img = np.random.default_rng(3).integers(0, 256, (11, 13), dtype=np.uint8)
    plain = b"".join(b"\0" + row.tobytes() for row in img)
    good = {  # each decodes to img: a damage check must never refuse a sound file
        "plain": png(13, 11, zlib.compress(plain)),
        "interlaced": png(13, 11, zlib.compress(adam7(img)), interlace=1),
    }
    for name, data in good.items():
        (tmp_path / f"{name}.png").write_bytes(data)
        assert png_damage(data) is None, name
        assert np.array_equal(cv2.imread(str(tmp_path / f"{name}.png"), cv2.IMREAD_UNCHANGED), img), name
    cv2.imwrite(str(tmp_path / "rgb16.png"), np.random.default_rng(4).integers(0, 65535, (9, 7, 3), dtype=np.uint16))
    assert png_damage((tmp_path / "rgb16.png").read_bytes()) is None
    garbled = bytearray(zlib.compress(plain))
    garbled[8:16] = b"\xff" * 8
    bad = {
        "fails its CRC": good["plain"][:40] + bytes([good["plain"][40] ^ 1]) + good["plain"][41:],
        "cut off: the file is truncated": good["plain"][:-30],
        "no IEND chunk": good["plain"][:-12],
        "does not inflate": png(13, 11, bytes(garbled)),
        "holds more than the 154 bytes": png(13, 11, zlib.compress(bytes(100 << 20))),  # a zlib bomb, not inflated
        "stops short": png(13, 11, zlib.compress(plain)[:-9]),
        "holds 140 bytes, the header's size needs 154": png(13, 11, zlib.compress(plain[:140])),
        "unknown filter type": png(13, 11, zlib.compress(b"\7" + plain[1:])),
        "colour type 5": png(13, 11, zlib.compress(plain), colour=5),
    }
    for why, data in bad.items():
        got = png_damage(data)
        assert got is not None and why in got, (why, got)
    assert png_damage(b"P5\n1 1\n255\n\0") is None  # not a PNG: left to its own decoder
    # libpng's own policy: a damaged IEND CRC is only warned about, and the image decodes
    iend_flipped = good["plain"][:-1] + bytes([good["plain"][-1] ^ 1])
    assert png_damage(iend_flipped) is None
    assert png_damage(good["plain"], size=(13, 12)) == "its IHDR says 13x11, not 13x12"
    assert png_damage(png(13, 11, b"")[:33] + png(13, 11, b"")[-12:], inflate=False) == (
        "no IDAT chunk: the file holds no pixels"
    )


def test_streamed_descent_reports_a_pair_with_a_garbled_image_and_goes_on(descent, tmp_path):
    pairs = tmp_path / "pairs"
    shutil.copytree(descent.parent, pairs)
    (pairs / "600_300" / "i2.png").write_bytes(b"P5\nabc def\n255\n")  # garbled header, same name
    s = run_hil(pairs / "manifest.json", tmp_path / "run", "zmq")
    got = [(r["label"], r["status"], r.get("code")) for r in s["records"]]
    assert got == [("600/300", "error", "bad_input"), ("300/150", "result", None)]
    assert "i2.png: not a readable image" in s["records"][0]["text"]


# --------------------------------------------------------------------------- 2. trajectory fields
def trajectory(tmp_path: Path, pair: dict, frame0: dict | None = None) -> Path:
    frames = [{"position_m": [0, 0, 600], **(frame0 or {})}, {"position_m": [0, 0, 300]}]
    p = tmp_path / "traj.json"
    p.write_text(json.dumps({"pairs": [{"label": "x", "frames": frames, **pair}]}))
    return p


BAD_FIELDS = [
    ({"altitude_m": "abc"}, None, "altitude_m must be a number"),
    ({"altitude_m": None}, None, "altitude_m must be a number"),
    ({"altitude_m": True}, None, "altitude_m must be a number"),
    ({"altitude_m": float("inf")}, None, "altitude_m must be finite"),
    ({"altitude_m": -300}, None, "altitude_m must be positive"),
    ({}, {"off_nadir_deg": "x"}, "frame 0: off_nadir_deg must be a number"),
    ({}, {"heading_deg": None}, "frame 0: heading_deg must be a number"),
    ({}, {"time_s": "abc"}, "frame 0: time_s must be a number"),
    ({}, {"time_s": float("nan")}, "frame 0: time_s must be finite"),
    ({}, {"position_m": [0, 0, "high"]}, "frame 0: position_m must be [x, y, z]"),
    # said by the renderer and the pair's check with no file, pair or frame (QA of stop 73)
    ({}, {"off_nadir_deg": 85}, "frame 0: camera sees the sky or the horizon"),
    ({}, {"time_s": 99}, "frame 1 is earlier than frame 0 (time_s 0 vs 99)"),
    # a typo was dropped without a word and frame 0 rendered looking straight down (QA of stop 78)
    ({}, {"off_nadir": 20}, "frame 0: unknown key 'off_nadir' (known: position_m, R_world_to_cam, off_nadir_deg"),
    ({"lable": "y"}, None, "unknown key 'lable' (known: label, altitude_m, frames)"),
    (
        {},
        {"R_world_to_cam": [[1, 0, 0], [0, -1, 0], [0, 0, -1]], "off_nadir_deg": 20},
        "frame 0: give R_world_to_cam or off_nadir_deg, not both",
    ),
]


@pytest.mark.parametrize("pair, frame0, message", BAD_FIELDS, ids=[m for *_, m in BAD_FIELDS])
def test_non_numeric_trajectory_field_is_one_line_naming_file_pair_and_field(tmp_path, capsys, pair, frame0, message):
    path = trajectory(tmp_path, pair, frame0)
    err = one_line_error(capsys, ["render", "--scenario", str(path), "--out", str(tmp_path / "out")])
    assert f"trajectory file {path} pair #0" in err and message in err, err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize(
    "extra, message",
    [
        ({"nmae": "x"}, "unknown key 'nmae' (known: name, camera, pairs)"),
        (
            {"camera": {"width": 64, "height": 64, "fx": 60, "fy": 60, "cx": 31.5, "cy": 31.5, "k1": 0.1}},
            "camera: unknown key 'k1' (known: width, height, fx, fy, cx, cy)",
        ),
    ],
)
def test_a_trajectory_files_unknown_key_is_refused_not_dropped(tmp_path, capsys, extra, message):
    path = trajectory(tmp_path, {})
    path.write_text(json.dumps({**json.loads(path.read_text()), **extra}))
    err = one_line_error(capsys, ["render", "--scenario", str(path), "--out", str(tmp_path / "out")])
    assert f"trajectory file {path}" in err and message in err, err
    assert not (tmp_path / "out").exists()


# --------------------------------------------------------------------------- 3. one directory, two pairs
def test_trajectory_labels_sharing_a_directory_are_refused_up_front(tmp_path, capsys):
    frames = [[{"position_m": [0, 0, h]}, {"position_m": [0, 0, h / 2]}] for h in (600, 400)]
    path = tmp_path / "traj.json"
    path.write_text(
        json.dumps({"pairs": [{"label": "a/b", "frames": frames[0]}, {"label": "a_b", "frames": frames[1]}]})
    )
    err = one_line_error(capsys, ["render", "--scenario", str(path), "--out", str(tmp_path / "out")])
    assert "labels 'a/b' and 'a_b'" in err and "same directory 'a_b'" in err
    assert not (tmp_path / "out").exists()  # refused before anything is rendered


@pytest.mark.parametrize("label", ["..", ".", "", "manifest.json", ["a"]])
def test_trajectory_label_that_is_no_pair_directory_is_refused(tmp_path, capsys, label):
    path = trajectory(tmp_path, {"label": label})
    err = one_line_error(capsys, ["render", "--scenario", str(path), "--out", str(tmp_path / "out")])
    assert "pair #0: label must be a non-empty name" in err


@pytest.mark.parametrize(
    "args, message",
    [
        (["--pairs", "600/300,600/300"], "--pairs: label '600/300' twice"),
        (["--frames", "300,150", "--frames", "300.0,150"], "--frames: label '300/150' twice"),
    ],
)
def test_repeated_pairs_or_frames_are_refused(tmp_path, capsys, args, message):
    err = one_line_error(capsys, ["render", "--scenario", "vertical", *args, "--out", str(tmp_path / "out")])
    assert message in err
    assert not (tmp_path / "out").exists()


# --------------------------------------------------------------------------- 4. seeds
@pytest.mark.parametrize("seed", ["99999999999999999999999", str(2**32), "-1"])
def test_render_seed_out_of_range_is_one_line(tmp_path, capsys, seed):
    err = one_line_error(capsys, ["render", "--scenario", "vertical", "--seed", seed, "--out", str(tmp_path / "out")])
    assert f"--seed must be in [0, 2**32), got {seed}" in err
    assert not (tmp_path / "out").exists()


def test_largest_accepted_seed_renders(tmp_path):
    from ground_sim.cli import MAX_SEED, check_seed
    from ground_sim.descent import render_scenario
    from hil_server.run import scaled_camera

    check_seed(MAX_SEED - 1)
    # the scene hashes seed + small offsets as int64: the bound leaves room for them
    out = render_scenario(
        "vertical", tmp_path, pairs=["100/50"], camera=scaled_camera(32), seed=MAX_SEED - 1, progress=False
    )
    assert read_pair(out / "100_50").meta["seed"] == MAX_SEED - 1


# --------------------------------------------------------------------------- 5. scenes --table / --workers
@pytest.fixture
def no_measuring(monkeypatch):
    """Fail the test if a measurement starts: every refusal here must come before it."""
    from ground_sim import library

    def measure(*args, **kw):
        raise AssertionError("measured before the input was checked")

    monkeypatch.setattr(library, "measure", measure)


@pytest.mark.parametrize(
    "table, extra, message",
    [
        ("nodir/x/tab.json", [], "directory {tmp}/nodir/x does not exist"),
        ("adir", [], "--table {tmp}/adir: is a directory"),
        ("list.json", [], "--table {tmp}/list.json: not a hazard-share table"),
        ("broken.json", [], "{tmp}/broken.json: unreadable hazard-share table"),
        ("tab.json", ["--workers", "0"], "--workers must be >= 1, got 0"),
        ("tab.json", ["--workers", "-3"], "--workers must be >= 1, got -3"),
    ],
)
def test_scenes_measure_checks_table_and_workers_before_measuring(
    tmp_path, capsys, no_measuring, table, extra, message
):
    (tmp_path / "adir").mkdir()
    (tmp_path / "list.json").write_text("[1, 2]")
    (tmp_path / "broken.json").write_text("{")
    argv = ["scenes", "thesis", "--measure", "--seeds", "1", "--table", str(tmp_path / table), *extra]
    err = one_line_error(capsys, argv)
    assert message.format(tmp=tmp_path) in err, err


def test_scenes_listing_of_a_missing_table_is_an_error(tmp_path, capsys):
    err = one_line_error(capsys, ["scenes", "--table", str(tmp_path / "nonexist.json")])
    assert f"--table {tmp_path / 'nonexist.json'}: no such file" in err


# --------------------------------------------------------------------------- 6. sun
@pytest.mark.parametrize("key", ["elevation_deg", "azimuth_deg"])
def test_non_finite_sun_in_pair_json_is_an_error_not_a_dropped_sun(descent, tmp_path, capsys, key):
    d = copy_pair(descent, tmp_path)
    edit_json(d / "pair.json", lambda doc: doc["sun"].update({key: float("nan")}))
    err = one_line_error(capsys, ["process", str(d), "--out", str(tmp_path / "out")])
    assert f"{d / 'pair.json'}: sun angles must be finite" in err and f"{key} nan" in err


@pytest.mark.parametrize(
    "sun, message",
    [
        ("nan,30", "--sun: azimuth must be a finite number of degrees, got nan"),
        ("30,inf", "elevation must be a finite"),
    ],
)
def test_render_sun_names_the_non_finite_value(tmp_path, capsys, sun, message):
    err = one_line_error(capsys, ["render", "--scenario", "vertical", "--sun", sun, "--out", str(tmp_path / "out")])
    assert message in err and "got 30.0" not in err


# --------------------------------------------------------------------------- 7. altimeter
@pytest.mark.parametrize(
    "reading, message",
    [
        (1e9, "frame 0: altimeter_m 1e+09 m is implausible for a camera at z = 600 m"),
        (0.6, "frame 0: altimeter_m 0.6 m is implausible"),  # km, not m
        (6000.0, "frame 0: altimeter_m 6000 m is implausible"),  # 5.4 km off
        (0.0, "frame 0: altimeter_m must be a positive range"),
        (float("inf"), "frame 0: altimeter_m must be a positive range"),
    ],
)
def test_implausible_altimeter_reading_is_refused(descent, tmp_path, capsys, reading, message):
    d = copy_pair(descent, tmp_path)
    edit_json(d / "pair.json", lambda doc: doc["frames"][0].update(altimeter_m=reading))
    err = one_line_error(capsys, ["process", str(d), "--out", str(tmp_path / "out")])
    assert f"{d / 'pair.json'}: {message}" in err, err


def test_altimeter_readings_terrain_can_explain_are_accepted(descent):
    for entry in json.loads(descent.read_text())["pairs"]:  # the renderer's own ranges
        assert read_pair(descent.parent / entry["path"]).altimeter_m == pytest.approx(entry["altimeter_m"])
    check_altimeter(50.0, Pose([0, 0, 20.0], NADIR), "low over a 30 m deep crater floor")  # 2.5x, 30 m
    check_altimeter(12.0, Pose([0, 0, 40.0], NADIR), "over a 28 m hill")
    check_altimeter(math.nan, Pose([0, 0, 600.0], NADIR), "no reading")
    from ground_sim.geometry import look_rotation

    # the approach's camera, 49 deg off nadir: the range to the datum is z / cos 49 deg = 1.52 z, not z
    check_altimeter(1.52 * 2400 - 300, Pose([0, -2400.0, 2400.0], look_rotation(49.0, 0.0)), "approach")
    with pytest.raises(PairFormatError, match="implausible"):
        check_altimeter(2 * 600 + 101, Pose([0, 0, 600.0], NADIR), "frame 0")


# --------------------------------------------------------------------------- 8. frames
def test_a_frame_with_both_attitudes_or_earlier_than_the_one_before_is_refused(descent, tmp_path, capsys):
    """A frame with R_world_to_cam and q_world_to_cam had its q ignored (an upward q too); frames are ordered by
    time, and a time that runs backwards was accepted."""
    d = copy_pair(descent, tmp_path)
    edit_json(d / "pair.json", lambda doc: doc["frames"][1].update({"q_world_to_cam": [1.0, 0.0, 0.0, 0.0]}))
    err = one_line_error(capsys, ["process", str(d), "--out", str(tmp_path / "out")])
    assert "frame 1: give R_world_to_cam or q_world_to_cam, not both" in err
    d = copy_pair(descent, tmp_path / "t")

    def backwards(doc: dict) -> None:
        doc["frames"][0]["time_s"], doc["frames"][1]["time_s"] = 5.0, 2.0

    edit_json(d / "pair.json", backwards)
    err = one_line_error(capsys, ["process", str(d), "--out", str(tmp_path / "out")])
    assert "frame 1 is earlier than frame 0 (time_s 2 vs 5)" in err


def test_render_scenario_refuses_two_pairs_with_one_directory_before_writing(tmp_path):
    """The Python entry point as well as the CLI: the later pair would overwrite the earlier."""
    from ground_sim.descent import render_scenario
    from protocol.errors import InputError

    with pytest.raises(InputError, match="label '600/300' twice"):
        render_scenario("vertical", tmp_path / "out", pairs=["600/300", "600/300"])
    assert not (tmp_path / "out").exists()


def test_the_ground_streamer_refuses_a_malformed_manifest_before_opening_its_link(tmp_path, capsys):
    """`python -m ground_sim.stream` (what `run` starts, and what a user may start against a board) read the
    manifest without checks: a traceback, after the link was up."""
    from ground_sim.stream import main as stream_main

    bad = tmp_path / "manifest.json"
    bad.write_text('{"pairs": [{"label": "x"}]}')
    argv = ["--link", "serial:/nonexistent/tty@115200", "--manifest", str(bad), "--out", str(tmp_path / "o")]
    assert stream_main([*argv, "--budget", "host", "--deadline", "2"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("ground: error: manifest") and 'has no "path"' in err, err


# --------------------------------------------------------------------------- pose errors, before rendering
def test_a_pose_error_the_altimeter_check_would_refuse_is_refused_before_rendering(tmp_path, capsys):
    """The pair's altimeter check refused such a pair when it was written, after the frames were rendered."""
    out = tmp_path / "r"
    argv = ["render", "--scenario", "vertical", "--pairs", "600/300", "--pose-error", "alt=2000", "--out", str(out)]
    err = one_line_error(capsys, argv + ["--no-progress"])
    assert "pair 600/300 frame 0 with the injected pose error" in err and "600.0 m truly" in err
    assert not out.exists()  # nothing rendered, nothing written


def test_process_refuses_an_out_where_it_would_replace_the_pairs_own_files(descent, tmp_path, capsys):
    """`process PAIR --out PAIR` wrote hazard.png and dem.png over frames of those names."""
    d = copy_pair(descent, tmp_path)
    (d / "i1.png").rename(d / "hazard.png")
    (d / "i2.png").rename(d / "dem.png")
    edit_json(
        d / "pair.json", lambda doc: [f.update(image=n) for f, n in zip(doc["frames"], ("hazard.png", "dem.png"))]
    )
    before = {n: (d / n).read_bytes() for n in ("hazard.png", "dem.png")}
    err = one_line_error(capsys, ["process", str(d), "--out", str(d)])
    assert "would replace the pair's own dem.png, hazard.png" in err
    assert {n: (d / n).read_bytes() for n in before} == before


def test_process_refuses_to_write_through_a_hard_link_to_a_pair_file(descent, tmp_path, capsys):
    """Another directory whose hazard.png is a hard link to frame 0: the same file under another name."""
    d = copy_pair(descent, tmp_path)
    out = tmp_path / "out"
    out.mkdir()
    os.link(d / "i1.png", out / "hazard.png")
    before = (d / "i1.png").read_bytes()
    err = one_line_error(capsys, ["process", str(d), "--out", str(out)])
    assert "would replace the pair's own hazard.png" in err and (d / "i1.png").read_bytes() == before


def three_frames(descent: Path, d: Path) -> Path:
    """600_300's frames and 300_150's lower one as a third frame (150 m): a three-frame directory."""
    shutil.copytree(descent.parent / "600_300", d)
    low = json.loads((descent.parent / "300_150" / "pair.json").read_text())
    shutil.copy(descent.parent / "300_150" / low["frames"][1]["image"], d / "i3.png")
    doc = json.loads((d / "pair.json").read_text())
    doc["frames"].append({**low["frames"][1], "image": "i3.png", "time_s": doc["frames"][1]["time_s"] + 10.0})
    doc["true_frames"].append({**low["true_frames"][1], "image": "i3.png"})
    (d / "pair.json").write_text(json.dumps(doc))
    return d


def test_the_hil_streams_a_directory_of_more_frames_as_frames_0_and_last(descent, tmp_path):
    """DESIGN.md: tools that need a pair use frames 0 and the last. The ground streamed frames 0 and 1 of a
    four-frame directory: the Result of 300/250 m labelled 300/250/200/150 (stop 59's QA)."""
    from ground_sim.stream import _frame_from_pair

    pair = read_pair(three_frames(descent, tmp_path / "three"), load_truth=False)
    lower = _frame_from_pair(pair, 1, 1, "p")
    assert lower.frame_index == 1 and lower.position_m[2] == pytest.approx(150.0, abs=1.0)
    assert np.array_equal(lower.image, pair.images[2])
    assert _frame_from_pair(pair, 0, 0, "p").position_m[2] == pytest.approx(600.0, abs=1.0)


def test_a_pair_of_another_camera_in_a_descent_is_refused_at_once_and_the_descent_goes_on(descent, tmp_path):
    """The Config names the camera once per descent. A 96 px pair after 128 px ones got the flight side's error
    unattributed and waited 63 s for `no_response` (stop 59's QA)."""
    import time

    pairs = tmp_path / "pairs"
    shutil.copytree(descent.parent, pairs)
    small_descent(tmp_path / "small", ["600/300"], px=96)
    shutil.copytree(tmp_path / "small" / "600_300", pairs / "small")
    three_frames(descent, pairs / "three")
    doc = json.loads((pairs / "manifest.json").read_text())
    doc["pairs"] = [
        doc["pairs"][0],
        {**doc["pairs"][0], "path": "small", "label": "96px"},
        {**{k: v for k, v in doc["pairs"][0].items() if k != "altitude_m"}, "path": "three", "label": "600/300/150"},
    ]
    (pairs / "manifest.json").write_text(json.dumps(doc))
    t0 = time.monotonic()
    s = run_hil(pairs / "manifest.json", tmp_path / "run", "zmq")
    got = [(r["label"], r["status"], r.get("code")) for r in s["records"]]
    assert got == [("600/300", "result", None), ("96px", "error", "bad_input"), ("600/300/150", "result", None)]
    assert (
        "its camera (96x96 px" in s["records"][1]["text"] and "not the descent's (128x128 px" in s["records"][1]["text"]
    )
    assert time.monotonic() - t0 < 60.0
    # the scores are of the fused map, and the summary says so (it said nothing of fusion)
    assert s["fusion"] is True and s["fusion_sources"] == ["scene thesis seed 0"]  # the scene from pair.json
    md = (tmp_path / "run" / "summary.md").read_text()
    assert "The Results report the map fused over the descent" in md and "fused as one descent" not in md
    # the three-frame directory streamed as a pair is said in the record and the summary, not on stderr alone (QA 74)
    assert [r.get("frames_in_dir") for r in s["records"]] == [None, None, 3]
    # without altitude_m in the manifest, the row reads the lower frame's height (it read "—"; QA 74)
    assert s["records"][2]["altitude_m"] == pytest.approx(150.0, abs=1.0)
    assert "1 pair directory holds more than two frames (600/300/150: 3): the HIL streams a pair" in md, md


def test_the_summary_says_when_pairs_of_other_ground_are_fused_as_one_descent():
    from hil_server.run import fusion_note, fusion_sources

    sources = fusion_sources([{"seed": 0}, {"seed": 0}, {"seed": 1}, {"label": "no seed"}])
    assert sources == ["seed 0", "seed 1"]
    said = fusion_note({"fusion": True, "fusion_sources": sources})
    assert "its pairs come from 2 scenes or seeds (seed 0, seed 1), fused as one descent" in said
    assert fusion_note({"fusion": False}) == "each Result reports its pair alone (`--no-fusion`)"
    assert "asked of the flight side" in fusion_note({"fusion": True, "flight": "external"})
    assert "asked of the flight side" in fusion_note({"fusion": True, "flight": "command: ./mine {port}"})
    assert fusion_note({"fusion": True, "flight": "emulated"}).startswith("the Results report the map fused")


def test_fusion_sources_read_what_the_manifest_leaves_out_from_each_pair(tmp_path):
    """render's manifest names the scene once, at its top: a thesis and a mare pair merged into one manifest read
    as one "seed 0", and a manifest in DESIGN.md's minimal form (label, path, altitude_m) said nothing at all
    (stop 62's QA M1). What an entry leaves out is read from its pair.json."""
    from hil_server.run import fusion_sources

    for name, scene, seed in (("a", "thesis", 0), ("b", "mare", 0), ("c", "thesis", 5)):
        (tmp_path / name).mkdir()
        (tmp_path / name / "pair.json").write_text(json.dumps({"scene_spec": scene, "scene_seed": seed}))
    (tmp_path / "d").mkdir()
    (tmp_path / "d" / "pair.json").write_text("{not json")
    merged = [{"path": "a", "seed": 0}, {"path": "b", "seed": 0}]
    assert fusion_sources(merged, tmp_path) == ["scene thesis seed 0", "scene mare seed 0"]
    minimal = [{"label": "x", "path": "a", "altitude_m": 300}, {"label": "y", "path": "c", "altitude_m": 150}]
    assert fusion_sources(minimal, tmp_path) == ["scene thesis seed 0", "scene thesis seed 5"]
    assert fusion_sources([{"path": "d"}, {"path": "missing"}, {"path": "a"}], tmp_path) == ["scene thesis seed 0"]
    assert fusion_sources([{"scene": "mine", "seed": 7, "path": "a"}], tmp_path) == ["scene mine seed 7"]  # given
    # a hostile pair.json is read as nothing, never waited on or read whole (the summary is written meanwhile)
    import os

    for name in ("fifo", "zero", "big", "flag"):
        (tmp_path / name).mkdir()
    os.mkfifo(tmp_path / "fifo" / "pair.json")
    (tmp_path / "zero" / "pair.json").symlink_to("/dev/zero")
    (tmp_path / "big" / "pair.json").write_text(json.dumps({"scene_spec": "x", "pad": "y" * (1 << 21)}))
    (tmp_path / "flag" / "pair.json").write_text(json.dumps({"scene_spec": "", "scene": "mare", "scene_seed": True}))
    hostile = [{"path": n} for n in ("fifo", "zero", "big")]
    assert fusion_sources(hostile, tmp_path) == []
    assert fusion_sources([{"path": "flag"}], tmp_path) == ["scene mare"]  # no "seed True", no empty scene


def test_an_hil_pair_whose_dem_the_altimeter_contradicts_offers_no_site_even_fused(descent, tmp_path):
    """The lower frame reported 40 m high: the images scale the DEM with it, and frame 0's altimeter says the
    ground is elsewhere. No site is offered on that map, nor on the map it is fused into (the flight process
    chose sites on the fused map whatever the pair's own said)."""
    pairs = tmp_path / "pairs"
    shutil.copytree(descent.parent, pairs)
    edit_json(pairs / "300_150" / "pair.json", lambda d: d["frames"][1]["position_m"].__setitem__(2, 190.0))
    s = run_hil(pairs / "manifest.json", tmp_path / "run", "zmq", deadline_s=30.0)
    rec = {r["label"]: r for r in s["records"]}["300/150"]
    assert rec["status"] == "result" and rec["sites"] == [], rec.get("sites")
    assert rec["no_site_reason"].startswith("no site is offered on this map: the frames' altimeters"), rec


def test_the_summary_says_when_a_fused_stream_goes_back_up():
    """Pairs streamed 200/100, 600/300, 300/150 were fused as one descent without a word (QA of stop 74)."""
    from hil_server.run import fusion_note

    recs = [{"label": "200/100", "altitude_m": 100.0, "status": "result"},
            {"label": "600/300", "altitude_m": 300.0, "status": "result"},
            {"label": "300/150", "altitude_m": 150.0, "status": "result"}]  # fmt: skip
    said = fusion_note({"fusion": True, "flight": "emulated", "records": recs})
    assert "pair 600/300 (300 m) comes after 200/100 (100 m): the stream goes back up" in said, said
    assert "fused across it all the same" in said and "where it fuses" not in said
    board = fusion_note({"fusion": True, "flight": "external", "records": recs})  # a board decides for itself
    assert "goes back up, and where it fuses, the map is fused across it all the same" in board, board
    down = [recs[1], recs[2], recs[0], {"label": "x", "altitude_m": None}, {"label": "bad", "altitude_m": 900.0}]
    assert "back up" not in fusion_note({"fusion": True, "flight": "emulated", "records": down})
    assert "back up" not in fusion_note({"fusion": False, "records": recs})  # each pair alone: nothing fused
