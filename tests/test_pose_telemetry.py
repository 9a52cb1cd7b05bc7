"""The pose refinement's outcome reaches the HIL ground (Telemetry revision 5: ``pose``, ``pose_verdict``, ``notes``).

Until stop 76 only `process` said what the refinement did; under the HIL a pose that fell back to navigation, or an
altimeter that disagreed with the images, reached no output (issue 10: "fall back to the navigation poses, saying
so"; "pose-quality telemetry: inliers, reprojection error, the correction applied").
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from synthetic import NADIR_R, Texture, camera_fov30, frames_of, plane, render
from test_result_rev import _Link

from flight_sw.pair_report import pair_notes, pose_figures, pose_verdict
from flight_sw.twoview import rot_exp
from protocol.codec import decode_message, encode_message
from protocol.messages import MAX_NOTE_CHARS, MAX_NOTES, RESULT_REV, Config, Result, Telemetry
from protocol.pairdir import Pose

PX = 256
SEQ0 = 10


def _rolled(pose: Pose, deg: float) -> Pose:
    """``pose`` turned ``deg`` about its own optical axis (the camera's z)."""
    return Pose(pose.position, rot_exp(math.radians(deg) * np.array([0.0, 0.0, 1.0])) @ pose.R, pose.time_s)


def _fly(pose_img: list, cam, altimeter_m: tuple[float, float] = (math.nan, math.nan)) -> Telemetry:
    """One pair through the reference flight process as the HIL runs it, as frames 10 and 11 (seqs that are not the
    frames' positions, as under the HIL server, which renumbers them); its Telemetry as the ground decodes it."""
    return _fly_both(pose_img, cam, altimeter_m)[1]


def _fly_both(pose_img: list, cam, altimeter_m: tuple[float, float] = (math.nan, math.nan)) -> tuple[Result, Telemetry]:
    """:func:`_fly`'s pair: its Result and its Telemetry, as the ground decodes them."""
    import flight_sw.flight_main as fm

    link = _Link()
    fp = fm.FlightProcess(link, fm.FaultPlan())
    fp.handle(Config(camera=cam.to_dict(), budget="host", deadline_s=60.0, preset="fast",
                     options={"result_rev": RESULT_REV, "descent_id": 1}))  # fmt: skip
    for f, a in zip(frames_of("p0", SEQ0, pose_img), altimeter_m):
        fp.handle(dataclasses.replace(f, altimeter_m=a))
    assert [type(m).__name__ for m in link.sent] == ["Result", "Telemetry"], link.sent
    result, tel = (decode_message(encode_message(m)) for m in link.sent)
    assert isinstance(result, Result) and isinstance(tel, Telemetry)
    return result, tel


@pytest.fixture(scope="module")
def nadir():
    cam = camera_fov30(PX)
    p1, p2 = Pose(np.array([0.0, 0.0, 300.0]), NADIR_R), Pose(np.array([0.0, 0.0, 150.0]), NADIR_R, 10.0)
    tex = Texture.random(300.0, 150.0 / cam.fx, 4, blur_cells=2.0)
    i1, _ = render(cam, p1, plane(-2.0), tex)
    i2, _ = render(cam, p2, plane(-2.0), tex)
    return cam, p1, p2, _sensor(i1, 1), _sensor(i2, 2)


def _sensor(img: np.ndarray, seed: int) -> np.ndarray:
    """A real sensor's 2 DN of noise: a noise-free render reads as a blank image (its pixel-scale detail ~0.5 DN)."""
    noisy = img.astype(float) + np.random.default_rng(seed).normal(0.0, 2.0, img.shape)
    return np.clip(np.rint(noisy), 0, 255).astype(np.uint8)


def test_a_rolled_lower_frame_reaches_the_ground_as_refined_with_its_signed_correction(nadir):
    """The lower frame reported 0.5 deg turned about its optical axis: the ground learns that the images refined it
    (``applied`` 1), by how much and which way, on how many inliers, with no note; on exact poses, "kept" with
    nothing applied."""
    cam, p1, p2, i1, i2 = nadir
    tel = _fly([(p1, i1), (_rolled(p2, 0.5), i2)], cam)
    assert tel.pose_verdict == "refined" and tel.notes == ()
    pose = tel.pose
    assert pose["applied"] == 1 and pose["inliers"] >= 40 and 0 <= pose["reproj_rms_px"] < 1.0
    assert pose["rot_z_deg"] == pytest.approx(-0.5, abs=0.02)  # turned back
    assert abs(pose["rot_x_deg"]) < 0.02 and abs(pose["rot_y_deg"]) < 0.02
    assert pose["att2_deg"] == pytest.approx(0.5, abs=0.02) and pose["att1_deg"] < 0.02  # the lower frame's own
    assert pose["rot_deg"] == pytest.approx(0.5, abs=0.02)
    exact = _fly([(p1, i1), (p2, i2)], cam)
    assert exact.pose_verdict == "kept" and exact.pose["applied"] == 0 and exact.notes == ()


@pytest.mark.parametrize("upper, lower", [(0.0, math.nan), (-150.0, 0.0), (math.nan, -1.0)])
def test_an_altimeter_reading_that_is_no_range_is_mapped_without_and_said(nadir, upper, lower):
    """A reading of 0 or negative (an altimeter without lock; the wire refuses an infinite one) in the upper frame
    refused the whole pair as bad input, and one in the lower frame was dropped unsaid: now the pair is mapped
    without it, and the ground is told which reading was set aside."""
    cam, p1, p2, i1, i2 = nadir
    tel = _fly([(p1, i1), (p2, i2)], cam, (upper, lower))
    said = [f"{k}'s altimeter reading {a:g} m is no range: the pair is mapped without it"
            for k, a in zip(("the upper frame", "the lower frame"), (upper, lower)) if not math.isnan(a)]  # fmt: skip
    assert list(tel.notes) == said and tel.pose_verdict == "kept"


def test_a_camera_the_psafe_trees_were_not_fitted_for_is_said_once_on_the_flight_log(capsys):
    """`process` warned of the Gaussian fallback; our flight software on a board said nothing (QA of stop 79)."""
    import flight_sw.flight_main as fm

    cam = camera_fov30(96)  # the trees are fitted for 512, 256 and 128 px cameras
    p1, p2 = Pose(np.array([0.0, 0.0, 300.0]), NADIR_R), Pose(np.array([0.0, 0.0, 150.0]), NADIR_R, 10.0)
    tex = Texture.random(300.0, 150.0 / cam.fx, 4, blur_cells=2.0)
    i1, i2 = (_sensor(render(cam, p, plane(-2.0), tex)[0], s) for p, s in ((p1, 1), (p2, 2)))
    link = _Link()
    fp = fm.FlightProcess(link, fm.FaultPlan())
    fp.handle(Config(camera=cam.to_dict(), budget="host", deadline_s=60.0, preset="fast",
                     options={"result_rev": RESULT_REV, "descent_id": 1}))  # fmt: skip
    for k in range(2):  # two pairs of one descent
        for f in frames_of(f"p{k}", SEQ0 + 2 * k, [(p1, i1), (p2, i2)]):
            fp.handle(f)
    assert [type(m).__name__ for m in link.sent] == ["Result", "Telemetry"] * 2, link.sent
    said = [line for line in capsys.readouterr().err.splitlines() if "falls back to the Gaussian rule" in line]
    assert said == [
        "flight: calibrated P(safe) not fitted for 96x96 images: P(safe) falls back to the Gaussian rule, whose FP is "
        "higher (docs/benchmarks/pipeline.md)"
    ]


def test_a_lower_frame_of_other_ground_is_said_in_the_telemetrys_notes(nadir):
    """The lower image is of other ground than its pose says: the refinement cannot match it, the maps rest on the
    navigation pose, and the ground is told so in words (it was told nothing)."""
    cam, p1, p2, i1, _ = nadir
    other = Texture.random(300.0, 150.0 / cam.fx, 99, blur_cells=2.0)
    i2, _ = render(cam, p2, plane(-2.0), other)
    tel = _fly([(p1, i1), (p2, _sensor(i2, 3))], cam)
    assert tel.pose_verdict in ("unmatched", "few_matches", "disagrees") and tel.pose["applied"] == 0
    if tel.pose_verdict == "few_matches":
        assert tel.notes[0].startswith(
            "the images could not check the pair's poses; the maps rest on them as navigation reports them "
            "(few_matches: "
        )
        assert len(tel.notes) == 1, tel.notes
    else:  # evidence against it: the map offers no site, which the Result says (not repeated in the notes)
        assert tel.notes[0].startswith(
            f"the images contradict the pair's navigation poses, which the maps rest on ({tel.pose_verdict}: "
        )
        assert len(tel.notes) == 1, tel.notes
    assert not any(ch in "".join(tel.notes) for ch in ("frame 0", "frame 1"))  # roles, not numbers


def test_notes_are_the_flights_judgement_few_and_short_and_none_is_dropped_unsaid():
    info = {
        "pose_refinement": {"verdict": "degenerate", "refined": False, "reason": "too little parallax", "inliers": 12},
        "altimeter_disagreement": "the altimeter reads 310 m where the images put the ground at 296 m",
        "sites_withheld": "no site is offered on this map: its sensors disagree",
        "blank_frames": [{"frame": 1, "noise_dn": 0.2, "others_dn": [3.1]}],
    }
    # below 256 px the refinement fails clean pairs too: a degenerate fit there is no note (as in `process`)
    assert pair_notes(info, 128)[0] == info["altimeter_disagreement"]
    assert len(pair_notes(info, 128)) == 2  # the disagreement and the blank image
    notes = pair_notes(info, 512)
    assert notes[1] == (
        "the images matched but cannot fix the pair's poses; the maps rest on them as navigation reports them (too "
        "little parallax)"
    )
    # frames by their role in the pair; the withheld sites are the Result's to say
    assert notes[2].startswith("the lower frame's image is blank: its pixel-scale detail reads 0.2 grey levels")
    assert len(notes) == 3
    many = {**info, "noisy_frames": [{"frame": 0, "noise_dn": 9.0, "others_dn": [1.0]}] * 4}
    capped = pair_notes(many, 512, MAX_NOTES, MAX_NOTE_CHARS)
    assert len(capped) == MAX_NOTES and capped[-1] == "4 more notes in the flight log"
    long = pair_notes({"altimeter_disagreement": "x" * 400}, 512, MAX_NOTES, MAX_NOTE_CHARS)
    assert len(long[0]) == MAX_NOTE_CHARS and long[0].endswith("...")
    Telemetry(frame_seqs=(7, 8), notes=capped).validated()  # the wire takes what the flight side sends
    # numbers only, and nothing when no refinement ran (the thesis preset)
    assert pose_figures({}) == {} and pose_verdict({}) == ""
    assert pose_figures(info) == {"applied": 0, "inliers": 12}
    unreached = {"refined": True, "reproj_rms_px": None, "translation_dir_change_deg": math.nan}
    assert pose_figures({"pose_refinement": unreached}) == {"applied": 1}


def test_the_ground_counts_the_verdicts_and_names_the_notes():
    """What a run's summary and page say from the records' Telemetry (revision 5); nothing from a flight side that
    did not say."""
    from hil_server.run import pose_note, pose_summary
    from hil_server.run_report import pose_cell

    records = [
        {"label": "600/300", "pose_verdict": "refined", "pose": {"applied": 1, "rot_deg": 0.31, "att2_deg": 0.4}},
        {"label": "300/150", "pose_verdict": "kept", "pose": {"applied": 0, "rot_deg": 0.02}},
        {"label": "200/100", "pose_verdict": "degenerate", "pose": {"applied": 0}, "flight_notes": ["pose of ..."]},
    ]
    s = {"pose": pose_summary(records)}
    assert s["pose"]["verdicts"] == {"refined": 1, "kept": 1, "degenerate": 1}
    assert pose_note(s) == (
        "pose refinement: refined 1, kept 1, degenerate 1 (largest correction applied: relative rotation 0.31 deg, "
        "a frame's attitude 0.40 deg); the flight side noted 1 thing(s) on 1 pair(s) (first, 200/100: pose of ...)"
    )
    cells = ["refined (relative 0.31 deg, attitude 0.40 deg)", "kept", "degenerate"]
    assert [pose_cell(r) for r in records] == cells
    assert pose_summary([{"label": "a"}]) == {} and pose_note({"pose": {}}) == "" and pose_cell({}) is None


def test_an_image_sent_twice_is_named_by_the_grounds_frame_numbers(nadir):
    """The lower frame carries the upper frame's image again: the note names both frames by their role (the
    pipeline's reason said "frame 0's", the upper frame's position, whatever the ground called it)."""
    cam, p1, p2, i1, _ = nadir
    result, tel = _fly_both([(p1, i1), (p2, i1.copy())], cam)
    # no site on a map resting on it, and why, pointing to what the ground has (it said "info.pose_refinement", a
    # key of `process`'s result.json)
    assert result.sites == [] and result.no_site_reason == (
        "no site is offered on this map: it rests on the lower frame, whose image is an earlier frame's, pixel for "
        "pixel "
        "(the pair's Telemetry: pose)"
    )
    assert tel.pose_verdict == "repeated"
    assert tel.notes == (
        "the lower frame's image repeats another, so the images cannot check the poses; the maps rest on them as "
        "navigation reports them (its image is the upper frame's, pixel for pixel: the "
        "same image twice (a camera that sent an image again))",
    )


def test_an_altimeter_the_images_disagree_with_is_said_of_the_grounds_frames(nadir):
    """The upper frame's altimeter reads 30 m long: the notes name frames 10 and 11, the ground's (the pipeline's
    words said "frame 0's" of the altimeter whatever the ground called the frame)."""
    from flight_sw.rangefind import altimeter_dem_disagreement, altimeter_dem_gap

    cam, p1, p2, i1, i2 = nadir
    tel = _fly([(p1, i1), (p2, i2)], cam, (332.0, math.nan))  # the ground 302 m down the axis
    assert tel.notes and any("the upper frame's altimeter" in n for n in tel.notes), tel.notes
    assert not any("frame 0" in n or "frame 1'" in n for n in tel.notes), tel.notes
    # the DEM's own check of the reading names the frame it is given
    assert "under frame 10's optical axis +30.0 m" in altimeter_dem_disagreement(30.0, 300.0, 10)
    blank = np.full((cam.height, cam.width), np.nan, np.float32)
    assert altimeter_dem_gap(blank, cam, p1, 302.0, 10)[1].startswith("frame 10's altimeter was not checked")
