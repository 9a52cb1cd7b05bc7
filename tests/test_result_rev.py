"""Result schema revisions: a newer flight side must not break an older ground (version skew on a real board).

A decoder refuses unknown fields, so a ground announces the highest Result revision it decodes in
``Config.options["result_rev"]`` and the flight side leaves every newer optional field off the wire; a Config
without it means the baseline, the Result of stop 41 (protocol.messages.RESULT_FIELD_REV).
"""

from __future__ import annotations

from dataclasses import MISSING, fields, replace

import numpy as np
import pytest
from resultrev import STOP41_RESULT_FIELDS, old_ground_decode, small_result, wire_keys

from ground_sim.stream import plan_note
from protocol.codec import decode_message, encode_message
from protocol.messages import RESULT_FIELD_REV, RESULT_REV, TELEMETRY_FIELD_REV, Result, SchemaError, Telemetry

# written out, as STOP41_RESULT_FIELDS: a Telemetry field added without a revision fails the test below
STOP41_TELEMETRY_FIELDS = {
    "frame_seqs",
    "stages",
    "queue_wait_s",
    "total_latency_s",
    "cpu_fraction",
    "peak_rss_bytes",
    "deadline_s",
    "deadline_met",
    "link",
}


def _full_result() -> Result:
    """A Result with every post-baseline field filled."""
    return small_result(
        degraded=True,
        skipped=("rocks", "shading_slope"),
        elevation_image=np.zeros((3, 4), np.float32),
        elevation_filled=np.array([[0, 1], [0, 0]], np.uint8),
        elevation_filled_image=np.eye(3, 4, dtype=np.uint8),
    )


def test_the_baseline_is_the_result_of_stop_41_and_every_later_field_has_a_revision():
    names = {f.name for f in fields(Result)}
    assert names - set(RESULT_FIELD_REV) == STOP41_RESULT_FIELDS
    assert set(RESULT_FIELD_REV) <= names
    assert sorted(set(RESULT_FIELD_REV.values())) == [1, 2, 3]
    # revisions 4 and 5 are the Telemetry's
    assert TELEMETRY_FIELD_REV == {"plan": 4, "pose": 5, "pose_verdict": 5, "notes": 5} and RESULT_REV == 5
    assert {f.name for f in fields(Telemetry)} - set(TELEMETRY_FIELD_REV) == STOP41_TELEMETRY_FIELDS
    for name in RESULT_FIELD_REV:  # only optional fields can be left out: each has a default the decoder restores
        f = next(f for f in fields(Result) if f.name == name)
        assert f.default is not MISSING or f.default_factory is not MISSING


def test_an_old_ground_refuses_the_new_fields_and_takes_the_result_at_its_revision():
    full = _full_result()
    body = encode_message(full)
    new_fields = r"unknown fields \['elevation_filled', 'elevation_filled_image', 'skipped'\]"
    with pytest.raises(SchemaError, match=new_fields):
        old_ground_decode(body)  # what a stop-41 ground did with every Result of a newer flight side
    for rev in range(RESULT_REV + 1):
        cut = full.for_rev(rev)
        want = STOP41_RESULT_FIELDS | {n for n, r in RESULT_FIELD_REV.items() if r <= rev}
        assert wire_keys(encode_message(cut)) <= want
        got = old_ground_decode(encode_message(cut), rev)
        # the fields that ground knows come through filled; it has no attribute for the others
        assert {f.name for f in fields(got)} == want  # type: ignore[arg-type]
        assert getattr(got, "skipped", None) == (full.skipped if rev >= 2 else None)
        assert (getattr(got, "elevation_filled", None) is not None) == (rev >= 1)
        assert (getattr(got, "elevation_filled_image", None) is not None) == (rev >= 3)
        back = decode_message(encode_message(cut))  # today's ground reads it too, the omitted fields at default
        assert isinstance(back, Result) and back.elevation_image is not None and back.degraded
    assert full.for_rev(RESULT_REV) is full and full.for_rev(RESULT_REV + 5) is full
    with pytest.raises(SchemaError, match="unknown fields"):
        old_ground_decode(encode_message(full.for_rev(2)), 1)  # skipped is newer than revision 1


def test_an_old_ground_refuses_the_telemetrys_plan_and_takes_it_at_its_revision():
    """Telemetry.plan (revision 4): a ground of revision 3 refused the whole Telemetry (its pair then completes
    without the flight's figures), so a flight side told revision 3 leaves it off."""
    tel = Telemetry(frame_seqs=(4, 5), plan={"budget_s": 41.5, "full_dem_left_s": 3.1, "full_dem_need_s": 38.0})
    with pytest.raises(SchemaError, match=r"Telemetry: unknown fields \['plan'\]"):
        old_ground_decode(encode_message(tel), 3)
    assert old_ground_decode(encode_message(tel), 4).plan == tel.plan  # type: ignore[attr-defined]
    for rev in range(4):
        cut = tel.for_rev(rev)
        assert cut.plan == {} and "plan" not in wire_keys(encode_message(cut))
        assert old_ground_decode(encode_message(cut), rev).frame_seqs == (4, 5)  # type: ignore[attr-defined]
    assert tel.for_rev(RESULT_REV) is tel
    back = decode_message(encode_message(tel))
    assert isinstance(back, Telemetry) and back.plan == tel.plan
    with pytest.raises(SchemaError, match="expected a number"):
        encode_message(replace(tel, plan={"budget_s": "soon"}))


def test_an_old_ground_refuses_the_telemetrys_pose_and_notes_and_takes_it_at_its_revision():
    """Telemetry.pose, pose_verdict and notes (revision 5): a ground of revision 4 refused the whole Telemetry, so a
    flight side told revision 4 leaves them off; one told 5 sends them, and today's ground reads them back."""
    tel = Telemetry(
        frame_seqs=(4, 5),
        plan={"budget_s": 41.5},
        pose={"applied": 1, "inliers": 430, "rot_deg": 0.31},
        pose_verdict="degenerate",
        notes=("pose of frame 5 degenerate: too little parallax",),
    )
    with pytest.raises(SchemaError, match=r"Telemetry: unknown fields \['notes', 'pose', 'pose_verdict'\]"):
        old_ground_decode(encode_message(tel), 4)
    cut = tel.for_rev(4)
    assert not wire_keys(encode_message(cut)) & {"pose", "pose_verdict", "notes"}
    assert old_ground_decode(encode_message(cut), 4).plan == tel.plan  # type: ignore[attr-defined]
    back = old_ground_decode(encode_message(tel), 5)
    assert (back.pose, back.pose_verdict, back.notes) == (tel.pose, tel.pose_verdict, tel.notes)  # type: ignore
    assert Telemetry(frame_seqs=(4, 5)).for_rev(4) == Telemetry(frame_seqs=(4, 5))  # unsaid: nothing to leave off
    # the notes share a slow line with the next Result: few and short
    with pytest.raises(SchemaError, match="at most 4"):
        encode_message(replace(tel, notes=("a",) * 5))
    with pytest.raises(SchemaError, match="exceeds 256"):
        encode_message(replace(tel, notes=("a" * 257,)))
    with pytest.raises(SchemaError, match="expected a number"):
        encode_message(replace(tel, pose={"verdict": "kept"}))


def test_the_encoder_leaves_only_the_newer_fields_off_and_only_at_their_default():
    r = _full_result().for_rev(0)
    assert r.skipped == () and r.elevation_filled is None and r.elevation_filled_image is None
    assert wire_keys(encode_message(r)) == STOP41_RESULT_FIELDS  # the baseline fields always travel, even at default
    no_fills = replace(r, elevation_filled=np.zeros((2, 2), np.uint8))  # a mask without fills is not "no mask"
    assert wire_keys(encode_message(no_fills)) == STOP41_RESULT_FIELDS | {"elevation_filled"}


class _Link:
    """Collects what the flight process sends."""

    def __init__(self) -> None:
        self.sent: list = []

    def send(self, msg) -> None:
        from protocol.codec import Encoded, encode_message

        if isinstance(msg, Encoded):  # sent with the body it was measured on: that body must be the message's
            assert msg.body == encode_message(msg.message)
            msg = msg.message
        self.sent.append(msg)

    def flush(self, timeout: float | None = None) -> bool:
        return True

    def stats(self) -> dict:
        return {"bytes_sent": 0}


CAMERA = {"width": 128, "height": 128, "fx": 238.9, "fy": 238.9, "cx": 63.5, "cy": 63.5}


def _config(options: dict, deadline_s: float = 30.0):
    from protocol.messages import Config

    return Config(camera=CAMERA, budget="host", deadline_s=deadline_s, preset="fast", options=options)


@pytest.mark.parametrize(
    "options, name",
    [
        ({"elevation_step": float("nan")}, "elevation_step"),
        ({"psafe_step": float("inf")}, "psafe_step"),
        ({"elevation_unit_cm": float("nan")}, "elevation_unit_cm"),
    ],
)
def test_a_config_option_that_is_no_number_is_bad_config_not_a_crash(options, name):
    """A NaN or infinite integer option (the Config's options may carry them) is answered with bad_config; int() of
    it raised out of the check and ended the flight process."""
    import flight_sw.flight_main as fm
    from protocol.messages import Error

    link = _Link()
    fp = fm.FlightProcess(link, fm.FaultPlan())
    fp.handle(decode_message(encode_message(_config(options))))  # as it arrives
    (err,) = link.sent
    assert isinstance(err, Error) and err.code == "bad_config" and name in err.text and "\n" not in err.text
    assert fp.config is None


@pytest.mark.parametrize("rev", [-1, 1.5, float("nan"), float("inf")], ids=["negative", "fraction", "nan", "inf"])
def test_a_bad_result_rev_is_bad_config(rev):
    import flight_sw.flight_main as fm
    from protocol.messages import Error

    link = _Link()
    fp = fm.FlightProcess(link, fm.FaultPlan())
    fp.handle(decode_message(encode_message(_config({"result_rev": rev}))))
    (err,) = link.sent
    assert isinstance(err, Error) and err.code == "bad_config" and "\n" not in err.text
    assert err.text.startswith("Config option result_rev must be a whole number >= 0") and fp.config is None


def test_a_newer_revision_or_an_unknown_option_is_taken():
    """A ground newer than this flight software (a higher revision, options it does not know) is served with all it
    has; the flight side ignores options it does not know, as the older flight sides did (they read options by name)."""
    import flight_sw.flight_main as fm

    link = _Link()
    fp = fm.FlightProcess(link, fm.FaultPlan())
    cfg = _config({"result_rev": RESULT_REV + 4, "an_option_of_tomorrow": 2.5})
    fp.handle(cfg)
    assert link.sent == [] and fp.config == cfg and fm.left_out_note(cfg) == ""


def _frames(pair_id: str, seq0: int):
    """A 128 px nadir pair over a roof (tests/synthetic.py) as the ground sends it; and its camera."""
    from synthetic import frames_of, make_pair, roof

    cam, p1, p2, i1, i2, _ = make_pair(128, 200.0, 100.0, roof(18.0, -2.0), seed=22)
    frames = frames_of(pair_id, seq0, [(p1, i1), (p2, i2)])
    return cam, frames


@pytest.mark.parametrize("rev", [None, 1, RESULT_REV, RESULT_REV + 1], ids=["unsaid", "1", "current", "newer"])
def test_the_flight_fills_only_the_fields_the_grounds_revision_decodes(rev, capsys):
    """Full maps asked for and a deadline too short for the full level (so the Result names skipped stages and
    carries elevation_image with its fill mask): a flight told no revision sends what a stop-41 ground decodes,
    and says once (not per Result) what its Results go without; told a revision, it fills the fields up to it."""
    import flight_sw.flight_main as fm
    from protocol.messages import Config

    cam, frames = _frames("p0", 0)
    # named, as every descent of the reference ground is: a Config naming none starts a new descent's map
    options = {"full_maps": 1, "descent_id": 5} | ({} if rev is None else {"result_rev": rev})
    cfg = Config(camera=cam.to_dict(), budget="host", deadline_s=0.02, preset="fast", options=options)
    link = _Link()
    fp = fm.FlightProcess(link, fm.FaultPlan())
    fp.handle(cfg)
    for f in frames:
        fp.handle(f)
    fp.handle(cfg)  # the same Config again, as after a link reconnection: the same descent
    for f in _frames("p1", 10)[1]:
        fp.handle(f)
    results = [m for m in link.sent if isinstance(m, Result)]
    assert len(results) == 2, link.sent
    seen = min(RESULT_REV, 0 if rev is None else rev)
    for r in results:
        assert r.degraded and r.level != "full" and r.elevation_image is not None  # what the newer fields are about
        assert bool(r.skipped) == (seen >= 2) and (r.elevation_filled is not None) == (seen >= 1)
        assert (r.elevation_filled_image is not None) == (seen >= 3)
        if seen >= 2:
            assert "full_dem" in r.skipped
        body = encode_message(r)
        assert wire_keys(body) <= STOP41_RESULT_FIELDS | {n for n, v in RESULT_FIELD_REV.items() if v <= seen}
        old_ground_decode(body, seen)  # a ground of that revision takes it
    tels = [m for m in link.sent if isinstance(m, Telemetry)]
    assert len(tels) == 2
    for t, r in zip(tels, results):
        old_ground_decode(encode_message(t), seen)
        if seen < 4:
            assert t.plan == {}
            continue
        # the figures the plan decided on: the budget it aimed at, and why the full DEM did not run
        assert 0 < t.plan["budget_s"] < 0.02 and t.plan["line_s"] == 0.0 and t.plan["scale"] > 0
        assert t.plan["measured"] == 0  # no pair with a DEM yet: planned at the first stages' slowdown
        why = plan_note({"skipped": r.skipped, "plan": t.plan})
        assert why.startswith(("coarse_dem not started: ", "full_dem not started: ")), why
        stage = why.split()[0]
        assert t.plan[f"{stage}_left_s"] <= t.plan[f"{stage}_need_s"]
    notes = [line for line in capsys.readouterr().err.splitlines() if line.startswith("flight: the ground decodes")]
    if seen >= RESULT_REV:
        assert notes == []
    else:
        (note,) = notes  # once for the descent
        assert f"Result revision {seen} (this flight software sends {RESULT_REV})" in note
        assert "elevation_filled_image" in note and "full_maps was asked for" in note
        assert ("skipped" in note) == (seen < 2) and "every Telemetry without plan" in note
