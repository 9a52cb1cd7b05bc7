"""The pair-directory format (shared/DESIGN.md) round-trips and rejects bad input."""

import dataclasses
import json
import time

import numpy as np
import pytest

from protocol.pairdir import Camera, Pair, PairFormatError, Pose, Sun, read_pair, write_pair

NADIR = np.diag([1.0, -1.0, -1.0])  # camera looking straight down, x east, y south


def make_pair(seed: int = 0) -> Pair:
    rng = np.random.default_rng(seed)
    cam = Camera.thesis()
    imgs = tuple(rng.integers(0, 256, (512, 512), dtype=np.uint8) for _ in range(2))
    poses = (Pose([0, 0, 600.0], NADIR, 0.0), Pose([0, 0, 300.0], NADIR, 12.5))
    truth = {"elevation": rng.normal(size=(512, 512)).astype(np.float32), "shadow": rng.random((512, 512)) > 0.5}
    return Pair(cam, poses, imgs, Sun(135.0, 20.0), truth, {"scenario": "vertical"})


def test_thesis_camera_matches_eq_3_16():
    cam = Camera.thesis()
    assert cam.fx == pytest.approx(955.405, abs=1e-3)
    assert (cam.cx, cam.cy) == (255.5, 255.5)


def test_round_trip_is_exact(tmp_path):
    pair = make_pair()
    write_pair(tmp_path, pair)
    back = read_pair(tmp_path)
    assert back.camera == pair.camera
    for a, b in zip(back.images, pair.images):
        np.testing.assert_array_equal(a, b)
    for a, b in zip(back.poses, pair.poses):
        np.testing.assert_array_equal(a.position, b.position)
        np.testing.assert_array_equal(a.R, b.R)
        assert a.time_s == b.time_s
    np.testing.assert_array_equal(back.truth["elevation"], pair.truth["elevation"])
    assert back.truth["shadow"].dtype == np.bool_
    assert back.meta == {"scenario": "vertical"}
    assert back.sun == pair.sun


def test_sun_direction_convention():
    # azimuth clockwise from +Y (north) toward +X (east)
    np.testing.assert_allclose(Sun(90.0, 0.0).direction(), [1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(Sun(0.0, 90.0).direction(), [0, 0, 1], atol=1e-12)


@pytest.mark.parametrize(
    "mutate, message",
    [
        (lambda d: d["frames"][0].update(position_m=[0, 0, float("nan")]), "finite"),
        (lambda d: d["frames"][1].update(R_world_to_cam=[[1, 0, 0], [0, 2, 0], [0, 0, 1]]), "orthonormal"),
        (lambda d: d["frames"][1].update(position_m=[0, 0, 900.0]), "below"),
        (lambda d: d.update(format="other/1"), "format"),
        (lambda d: d["camera"].update(width=640), "does not match"),
    ],
)
def test_bad_metadata_is_named(tmp_path, mutate, message):
    write_pair(tmp_path, make_pair())
    doc = json.loads((tmp_path / "pair.json").read_text())
    mutate(doc)
    (tmp_path / "pair.json").write_text(json.dumps(doc))
    with pytest.raises(PairFormatError, match=message):
        read_pair(tmp_path)


def test_missing_files_are_named(tmp_path):
    with pytest.raises(PairFormatError, match=r"pair\.json"):
        read_pair(tmp_path)
    write_pair(tmp_path, make_pair())
    (tmp_path / "i2.png").unlink()
    with pytest.raises(PairFormatError, match=r"i2\.png"):
        read_pair(tmp_path)


def _rewrite(d, fn):
    doc = json.loads((d / "pair.json").read_text())
    fn(doc)
    (d / "pair.json").write_text(json.dumps(doc))


def test_multi_frame_round_trip_with_altimeter(tmp_path):
    rng = np.random.default_rng(3)
    cam = Camera(64, 64, 120.0, 120.0, 31.5, 31.5)
    alts = (400.0, 300.0, 200.0, 150.0)
    poses = tuple(Pose([0, 0, h], NADIR, float(k)) for k, h in enumerate(alts))
    imgs = tuple(rng.integers(0, 256, (64, 64), dtype=np.uint8) for _ in alts)
    pair = Pair(cam, poses, imgs, altimeter_m=(401.0, float("nan"), 201.5, 150.2))
    write_pair(tmp_path, pair)
    assert sorted(p.name for p in tmp_path.glob("i*.png")) == ["i1.png", "i2.png", "i3.png", "i4.png"]
    back = read_pair(tmp_path)
    assert back.n_frames == 4
    np.testing.assert_array_equal(back.lower[0], imgs[-1])
    assert back.lower[1].position[2] == 150.0
    assert back.altimeter_m[0] == 401.0 and np.isnan(back.altimeter_m[1]) and back.altimeter_m[3] == 150.2


def test_frames_must_descend_and_count_is_bounded(tmp_path):
    write_pair(tmp_path, make_pair())
    _rewrite(tmp_path, lambda d: d.update(frames=d["frames"] * 9))
    with pytest.raises(PairFormatError, match="2 to 16 frames, got 18"):
        read_pair(tmp_path)
    write_pair(tmp_path, make_pair())
    _rewrite(tmp_path, lambda d: d.update(frames=d["frames"][:1]))
    with pytest.raises(PairFormatError, match="got 1"):
        read_pair(tmp_path)


def test_quaternion_and_rounded_rotation_are_accepted(tmp_path):
    write_pair(tmp_path, make_pair())
    # NADIR = diag(1, -1, -1) is a 180 deg turn about x: q = [0, 1, 0, 0]
    _rewrite(
        tmp_path, lambda d: (d["frames"][0].pop("R_world_to_cam"), d["frames"][0].update(q_world_to_cam=[0, 1, 0, 0]))
    )
    np.testing.assert_allclose(read_pair(tmp_path).poses[0].R, NADIR, atol=1e-12)
    c, s = np.cos(np.radians(7)), np.sin(np.radians(7))
    R = np.round(np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]) @ NADIR, 4)  # written to 4 decimals
    _rewrite(tmp_path, lambda d: d["frames"][1].update(R_world_to_cam=R.tolist()))
    back = read_pair(tmp_path)
    assert np.abs(back.poses[1].R @ back.poses[1].R.T - np.eye(3)).max() < 1e-12
    assert any("re-orthonormalised" in n for n in back.notes)


def test_colour_and_16bit_images_are_converted_with_a_note(tmp_path):
    import cv2

    pair = make_pair()
    write_pair(tmp_path, pair)
    cv2.imwrite(str(tmp_path / "i1.png"), cv2.cvtColor(pair.images[0], cv2.COLOR_GRAY2BGR))
    cv2.imwrite(str(tmp_path / "i2.png"), pair.images[1].astype(np.uint16) * 16)  # a 12-bit sensor
    back = read_pair(tmp_path)
    np.testing.assert_array_equal(back.images[0], pair.images[0])
    np.testing.assert_array_equal(back.images[1], pair.images[1])  # >> 4 restores the 8-bit values
    assert any("colour" in n for n in back.notes) and any("shifted right by 4" in n for n in back.notes)


def _png_header(w: int, h: int) -> bytes:
    import struct
    import zlib

    ihdr = struct.pack(">IIBBBBB", w, h, 8, 0, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + struct.pack(">I", 13) + b"IHDR" + ihdr + struct.pack(">I", zlib.crc32(b"IHDR" + ihdr))


@pytest.mark.parametrize(
    "attack, message",
    [
        (lambda d: (d / "i2.png").write_bytes(_png_header(65535, 65535)), "65535x65535 does not match"),
        (lambda d: (d / "pair.json").write_text(" " * (2 << 20)), "more than a pair.json can be"),
        (lambda d: (d / "pair.json").write_text("[" * 100_000 + "]" * 100_000), "nested too deeply"),
        (lambda d: _rewrite(d, lambda doc: doc["frames"][1].update(image="../../etc/passwd")), "outside the pair"),
        (lambda d: (d / "gt_elevation_i1.npy").write_bytes(b""), "gt_elevation_i1.npy: not a readable .npy file"),
        (lambda d: _rewrite(d, lambda doc: doc["frames"][0].update(R_world_to_cam=np.eye(3).tolist())), "cannot see"),
        (lambda d: _rewrite(d, lambda doc: doc["frames"][1].update(altimeter_m=-3)), "altimeter_m"),
        (lambda d: _rewrite(d, lambda doc: doc["camera"].update(width=65535)), "1..8192"),
        # a dangling symlink read "lies outside the pair directory"
        (lambda d: ((d / "i2.png").unlink(), (d / "i2.png").symlink_to("/nonexistent/x.png")), "a broken symlink"),
    ],
)
def test_hostile_or_broken_input_is_one_clear_error(tmp_path, attack, message):
    write_pair(tmp_path, make_pair())
    attack(tmp_path)
    with pytest.raises(PairFormatError, match=message):
        read_pair(tmp_path)


def test_positions_in_km_are_flagged(tmp_path):
    """A warning naming pair.json, not a note: the caller records warnings with its outputs (`process` printed the
    notes on stderr alone, and a pair in km left a DEM in km with an empty result.json warnings; QA of stop 75)."""
    pair = make_pair()
    pair.poses = (Pose([0, 0, 0.6], NADIR, 0.0), Pose([0, 0, 0.3], NADIR, 12.5))
    write_pair(tmp_path, pair)
    back = read_pair(tmp_path)
    said = [w for w in back.warnings if "positions must be in metres" in w]
    assert len(said) == 1 and said[0].startswith(f"{tmp_path / 'pair.json'}: frame "), back.warnings
    write_pair(tmp_path, make_pair())  # a pair in metres has none
    assert read_pair(tmp_path).warnings == []
    # a small camera sees over 1 mm per pixel from 0.3 m: km positions passed at 128 px (QA of stop 79)
    pair.camera = dataclasses.replace(pair.camera, fx=240.0, fy=240.0)
    write_pair(tmp_path, pair)
    (said,) = read_pair(tmp_path).warnings
    assert "frame 1 is 0.3 m above the datum (expected at least 1 m): positions must be in metres" in said, said


def test_atomic_write_keeps_a_concurrent_copy_and_leaves_no_partial(tmp_path):
    """Two studies rendering into one cache: the second writer of a finished directory keeps the first's
    copy (no 'Directory not empty' failure), and neither leaves a half-written directory behind."""
    from protocol.pairdir import write_pair_atomic

    dest = tmp_path / "600_300"
    write_pair_atomic(dest, make_pair(0))
    first = (dest / "i1.png").read_bytes()
    assert write_pair_atomic(dest, make_pair(1)) == dest  # another process got there first: its copy stays
    assert (dest / "i1.png").read_bytes() == first
    assert sorted(p.name for p in tmp_path.iterdir()) == ["600_300"]
    junk = tmp_path / "not_a_pair"
    junk.mkdir()
    (junk / "x.txt").write_text("x")
    with pytest.raises(OSError):  # a non-empty directory that is not a pair is not silently kept
        write_pair_atomic(junk, make_pair(2))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["600_300", "not_a_pair"]


def test_a_partial_pair_a_killed_writer_left_goes_with_the_next_write(tmp_path):
    """A render killed outright mid-write left `<pair>.partialPID` beside the pair, and a rerun neither removed nor
    named it (stop 63's QA). The next write of that pair removes it when its writer is dead, not when it lives."""
    import os
    import subprocess

    from protocol.pairdir import PARTIAL_STALE_S, write_pair_atomic

    dead = subprocess.Popen(["true"])
    dead.wait()
    stale, live = tmp_path / f"600_300.partial{dead.pid}", tmp_path / f"600_300.partial{os.getppid()}"
    # a PID that names nothing here, its files still being written: a writer in another container or on another
    # host sharing the cache (review of stop 63: its directory was removed mid-write)
    elsewhere = tmp_path / "600_300.partial999999999"
    for d in (stale, live, elsewhere):
        d.mkdir()
        (d / "i1.png").write_bytes(b"half")
    old = time.time() - PARTIAL_STALE_S - 60
    for d in (stale, live):
        os.utime(d / "i1.png", (old, old))
        os.utime(d, (old, old))
    write_pair_atomic(tmp_path / "600_300", make_pair(0))
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(["600_300", elsewhere.name, live.name])


def test_a_replaced_pair_keeps_the_users_own_files_and_drops_the_old_renders(tmp_path, monkeypatch):
    """Re-rendering over a pair directory removed it whole: a user's notes and a `process --out PAIR/out` went with
    it, silently. A render's own files (an earlier 3-frame pair's i3.png) go; a failed swap puts the old one back."""
    import os

    from protocol import pairdir
    from protocol.pairdir import is_render_file, is_write_leftover, write_pair_atomic

    dest = tmp_path / "600_300"
    write_pair_atomic(dest, make_pair(0))
    (dest / "notes.txt").write_text("mine")
    (dest / "out").mkdir()
    (dest / "out" / "state.npy").write_bytes(b"x")
    (dest / "i3.png").write_bytes(b"an earlier render's frame")
    kept: list[str] = []
    write_pair_atomic(dest, make_pair(1), replace=True, kept=kept)
    assert kept == ["notes.txt", "out"]  # said by render
    assert (dest / "notes.txt").read_text() == "mine" and (dest / "out" / "state.npy").read_bytes() == b"x"
    assert not (dest / "i3.png").exists() and (dest / "pair.json").is_file()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["600_300"]
    assert is_render_file("i12.png") and is_render_file("gt_hazard_i1.npy") and not is_render_file("i0.png")
    assert is_write_leftover("600_300.old123") and is_write_leftover("600_300.partial9") and not is_write_leftover("a")

    real_replace = os.replace

    def refuse_the_swap(src, dst):
        if ".partial" in str(src):
            raise PermissionError(13, "Permission denied")
        return real_replace(src, dst)

    monkeypatch.setattr(pairdir.os, "replace", refuse_the_swap)
    with pytest.raises(PermissionError):
        write_pair_atomic(dest, make_pair(2), replace=True)
    assert (dest / "pair.json").is_file() and (dest / "notes.txt").read_text() == "mine"  # never neither
    assert sorted(p.name for p in tmp_path.iterdir()) == ["600_300"]


def test_a_stopped_writes_leftover_is_not_taken_for_anearlier_renders_pair(tmp_path):
    from ground_sim.descent import earlier_render

    for name in ("600_300", "600_300.old41", "300_150.partial7"):
        (tmp_path / name).mkdir()
        (tmp_path / name / "pair.json").write_text("{}")
    assert earlier_render(tmp_path) == ["600_300"]  # no manifest: the directories with a pair.json


def test_positions_in_km_are_noted_on_whichever_frame_shows_it():
    """Only frame 0 was checked: a 256 px pair at 0.6 / 0.3 "m" (km written as m) sees 1.3 mm per pixel from frame
    0, within the bounds, and 0.63 mm from frame 1, and went without a note (stop 59's QA)."""
    f = 128 / np.tan(np.radians(15.0))
    cam = Camera(256, 256, f, f, 127.5, 127.5)
    nadir = np.diag([1.0, -1.0, -1.0])
    img = np.zeros((256, 256), np.uint8)
    km = Pair(cam, (Pose([0, 0, 0.6], nadir), Pose([0, 0, 0.3], nadir, 1.0)), (img, img))
    notes = km.scale_notes()
    assert any(n.startswith("frame 1 sees 0.00063 m per pixel") and "metres" in n for n in notes), notes
    m = Pair(cam, (Pose([0, 0, 600.0], nadir), Pose([0, 0, 300.0], nadir, 1.0)), (img, img))
    assert m.scale_notes() == []


def test_truth_depth_and_elevation_must_be_finite_and_a_focal_length_in_mm_is_named(tmp_path):
    """A negative gt_depth was read, and `score` then said the frames share no ground; an inf in either truth passed
    without a word; a focal length of 0.5 px was blamed on the positions' units (QA of stop 66)."""
    import dataclasses

    for name, value, what in (("depth", -600.0, "finite z-depth > 0"), ("depth", np.inf, "finite z-depth > 0"),
                              ("elevation", np.inf, "finite Z")):  # fmt: skip
        pair = make_pair()
        layer = np.full((512, 512), 600.0 if name == "depth" else 0.0, np.float32)
        layer[3, 4] = value
        pair.truth = {**pair.truth, name: layer}
        d = tmp_path / f"{name}{value}"
        write_pair(d, pair)
        with pytest.raises(PairFormatError, match=f"ground truth {name} must be a {what}.*1 pixels"):
            read_pair(d)
    pair = make_pair()
    pair.truth["depth"] = np.where(np.eye(512, dtype=bool), np.nan, 600.0).astype(np.float32)  # NaN: unknown, fine
    write_pair(tmp_path / "nan", pair)
    assert np.isnan(read_pair(tmp_path / "nan").truth["depth"]).sum() == 512
    pair = make_pair()
    pair.camera = dataclasses.replace(pair.camera, fx=0.5, fy=0.5)
    # since stop 71 refused outright: under 0.05 of the side (fx = 1e-300 was mapped, with numpy overflow warnings)
    with pytest.raises(PairFormatError, match=r"camera: fx 0.5 px is under 0.05 of the image's 512 px .*169 deg"):
        write_pair(tmp_path / "f", pair)
    doc = json.loads((tmp_path / "nan" / "pair.json").read_text())
    for fx in (1e-300, 25.0):
        doc["camera"].update(fx=fx, fy=fx)
        (tmp_path / "nan" / "pair.json").write_text(json.dumps(doc))
        with pytest.raises(PairFormatError, match=f"camera: fx {fx:.4g} px is under 0.05"):
            read_pair(tmp_path / "nan")
    doc["camera"].update(fx=26.0, fy=26.0)  # a 169 deg field of view: read
    (tmp_path / "nan" / "pair.json").write_text(json.dumps(doc))
    assert read_pair(tmp_path / "nan").camera.fx == 26.0


def test_quoted_sun_angles_are_refused_as_every_other_quoted_number(tmp_path):
    """sun.azimuth_deg "135" passed through float() unnoticed, where every other field refuses a quoted number (QA
    of stop 66)."""
    write_pair(tmp_path, make_pair())
    doc = json.loads((tmp_path / "pair.json").read_text())
    doc["sun"]["azimuth_deg"] = "135"
    (tmp_path / "pair.json").write_text(json.dumps(doc))
    with pytest.raises(PairFormatError, match=r"sun\.azimuth_deg must be a number, got '135'"):
        read_pair(tmp_path)


def test_a_field_the_format_does_not_have_is_warned_with_the_one_meant(tmp_path):
    """A frame's "altimeter_range_m" was ignored without a word, and with it the DEM's check against the altimeter;
    so was a camera's distortion model (QA of stop 84). Each is a warning naming the field, and the one meant."""
    write_pair(tmp_path, make_pair())
    assert read_pair(tmp_path).warnings == []  # what the writer writes is all the format's

    def typo(doc):
        doc["frames"][0]["altimeter_range_m"] = 640.0
        doc["camera"]["k1"] = -0.3
        doc["sun"]["elevation"] = 20.0

    _rewrite(tmp_path, typo)
    warned = read_pair(tmp_path).warnings
    assert len(warned) == 3, warned
    assert (
        "frame 0: 'altimeter_range_m' is not a field of the format and was ignored (did you mean 'altimeter_m'?)"
        in (warned[1])
    )
    assert "camera: 'k1' is not a field" in warned[0] and "sun: 'elevation' is not a field" in warned[2], warned


@pytest.mark.parametrize("sun", ["135,25", [135, 25], 5])
def test_a_sun_that_is_no_object_is_said_in_the_formats_words(tmp_path, sun):
    """Python's "string indices must be integers" came through as the reason (QA of stop 84)."""
    write_pair(tmp_path, make_pair())
    _rewrite(tmp_path, lambda doc: doc.update(sun=sun))
    with pytest.raises(PairFormatError, match=r'sun must be an object \{"azimuth_deg": ..., "elevation_deg": ...\}'):
        read_pair(tmp_path)


def test_a_hot_pixel_does_not_set_a_16_bit_images_scale(tmp_path):
    """One pixel at 65535 in a 12-bit image shifted it by 8 bits, not 4, and left ~9 grey levels: coverage 96 % ->
    41 % with a note only (QA of stop 73). The scale comes from a high percentile; the hot pixel saturates, said."""
    import cv2

    pair = make_pair()
    write_pair(tmp_path, pair)
    for k, name in enumerate(("i1.png", "i2.png")):
        deep = pair.images[k].astype(np.uint16) * 16
        if k == 0:
            deep[0, 0] = 65535
        cv2.imwrite(str(tmp_path / name), deep)
    back = read_pair(tmp_path)
    assert any("shifted right by 4" in n and "1 of their brightest pixels saturated" in n for n in back.notes)
    expect = pair.images[0].copy()
    expect[0, 0] = 255
    np.testing.assert_array_equal(back.images[0], expect)
    np.testing.assert_array_equal(back.images[1], pair.images[1])


def test_gray_with_alpha_is_said_as_such_and_a_descent_is_not_a_pair(tmp_path):
    """A gray+alpha PNG was said "colour converted to gray"; `process DESCENT` said only "missing pair.json" (QA of
    stop 73)."""
    import cv2

    pair = make_pair()
    write_pair(tmp_path / "p", pair)
    ga = np.dstack([pair.images[0]] * 3 + [np.full_like(pair.images[0], 200)])
    cv2.imwrite(str(tmp_path / "p" / "i1.png"), ga)
    back = read_pair(tmp_path / "p")
    np.testing.assert_array_equal(back.images[0], pair.images[0])
    assert any("gray with an alpha channel: the alpha left out" in n for n in back.notes), back.notes
    (tmp_path / "manifest.json").write_text("{}")
    with pytest.raises(PairFormatError, match=r"rendered descent, manifest\.json: give one of its pair directories"):
        read_pair(tmp_path)


def test_a_hot_pixel_does_not_set_a_small_16_bit_frames_scale_either():
    """At 100 px and below the 99.99th percentile is the maximum: one hot pixel still set the scale (review of stop
    73)."""
    from protocol.pairdir import to_gray8

    img = (np.arange(64 * 64, dtype=np.uint16).reshape(64, 64) % 4000).astype(np.uint16)
    img[0, 0] = 65535
    (out,), notes, warned = to_gray8([img], ["i1.png"])
    assert warned == {}
    assert "shifted right by 4" in notes[0] and out[0, 0] == 255 and out[0, 32] == 32 >> 4  # 12-bit, by 4 bits


def test_frames_at_one_time_but_different_heights_are_said(tmp_path):
    """Time must not run backwards; two frames 300 m apart in height at one time_s were taken without a word (a
    tool that writes 0 for each; QA of stop 74). Said as a note naming the frames; distinct times say nothing."""
    pair = make_pair()
    write_pair(tmp_path, pair)
    assert not any("time_s" in n for n in read_pair(tmp_path).notes)

    def same_time(doc):
        doc["frames"][1]["time_s"] = doc["frames"][0]["time_s"]

    _rewrite(tmp_path, same_time)
    said = [n for n in read_pair(tmp_path).notes if "same time_s" in n]
    assert len(said) == 1 and "frames 0 and 1 have the same time_s (0 s) 300 m apart in height" in said[0], said
    assert str(tmp_path / "pair.json") in said[0]


def test_a_16_bit_frame_the_common_shift_crushes_is_warned_naming_its_file(tmp_path):
    """i1.png a 16-bit file of 12-bit values, i2.png of full 16-bit range: the one shift (8 bits) every frame gets
    left i1 ~16 grey levels, and the flight software then called it a blank, "black, saturated or lost" image (QA of
    stop 75). The reader keeps the one shift (docs/design.md) and says the cause in one line naming the file."""
    import cv2

    pair = make_pair()
    write_pair(tmp_path, pair)
    cv2.imwrite(str(tmp_path / "i1.png"), pair.images[0].astype(np.uint16) * 16)
    cv2.imwrite(str(tmp_path / "i2.png"), pair.images[1].astype(np.uint16) * 257)
    back = read_pair(tmp_path)
    np.testing.assert_array_equal(back.images[1], pair.images[1])  # one shift for both: 8 bits
    np.testing.assert_array_equal(back.images[0], pair.images[0] >> 4)
    assert back.shallow_frames == (0,)
    (said,) = back.warnings
    assert said.startswith(f"{(tmp_path / 'i1.png').resolve()}: after the common 8-bit shift"), said
    assert "keeps only 16 grey levels: its values span 12 bits, i2.png's 16" in said and "\n" not in said, said
    # frames of one depth, however deep, are not warned: 12-bit values in both, or a hot pixel in one
    cv2.imwrite(str(tmp_path / "i2.png"), pair.images[1].astype(np.uint16) * 16)
    same = read_pair(tmp_path)
    assert same.warnings == [] and same.shallow_frames == ()


def test_a_float_tiff_is_refused_naming_its_path(tmp_path):
    """Every refusal names the file's path; the float-TIFF one gave the bare name (QA of stop 75)."""
    import cv2

    pair = make_pair()
    write_pair(tmp_path, pair)
    for k in (0, 1):
        cv2.imwrite(str(tmp_path / f"i{k + 1}.tif"), pair.images[k].astype(np.float32) / 255)
    _rewrite(tmp_path, lambda doc: [f.update(image=f["image"].replace(".png", ".tif")) for f in doc["frames"]])
    with pytest.raises(PairFormatError) as exc:
        read_pair(tmp_path)
    assert str(exc.value) == f"{(tmp_path / 'i1.tif').resolve()}: float32 pixels (need 8- or 16-bit unsigned)"
