"""The HIL run judges the landing sites a Result offers against the truth, and says so in every report.

The run report used to show no site at all: a pair that offered none, or whose top site was on a hazard, looked
like any other. Sites here are placed by hand on a rendered pair's truth, so each verdict is known in advance.
"""

from __future__ import annotations

import json

import numpy as np
from hilkit import small_descent

from ground_sim.gridscore import judge_site, pixel_ground_xy, true_pose_upper
from hil_server.run import score_records, site_note, site_summary, summary_table, top_site_text
from hil_server.run_report import write_run_report
from protocol.pairdir import STATE_UNKNOWN, read_pair


def _spots(pair) -> tuple[tuple[float, float], tuple[float, float]]:
    """The ground X, Y of one footprint the truth calls clear and one it does not, both well inside i1."""
    world = np.stack(pixel_ground_xy(pair.camera, true_pose_upper(pair), pair.truth["depth"]), axis=-1)
    h, w = pair.truth["hazard"].shape
    clear = unsafe = None
    for v in range(h // 4, 3 * h // 4, 3):
        for u in range(w // 4, 3 * w // 4, 3):
            xy = (float(world[v, u, 0]), float(world[v, u, 1]))
            safe = judge_site(xy, world, pair.truth["hazard"])["safe"]
            if safe and clear is None:
                clear = xy
            if not safe and unsafe is None and pair.truth["hazard"][v, u] >= 1.0:
                unsafe = xy
    assert clear is not None and unsafe is not None
    return clear, unsafe


def _record(pair_dir, out_dir, label: str, sites: list[tuple[float, float]], reason: str | None = None) -> dict:
    out_dir.mkdir(parents=True)
    np.save(out_dir / "state_grid.npy", np.full((4, 4), STATE_UNKNOWN, np.uint8))
    return {
        "status": "result",
        "label": label,
        "pair_id": label.replace("/", "_"),
        "altitude_m": 300.0,
        "pair_dir": str(pair_dir),
        "out_dir": str(out_dir),
        "grid_origin_xy": [0.0, 0.0],
        "grid_cell_m": 1.0,
        "sites": [{"x": x, "y": y, "z": 0.0} for x, y in sites],
        "no_site_reason": reason,
        "deadline_met": True,
        "deadline_s": 2.0,
        "e2e_latency_s": 0.5,
        "level": "full",
    }


def test_each_site_is_judged_on_the_truth_and_the_reports_say_so(tmp_path):
    manifest = small_descent(tmp_path / "pairs", ["600/300"])
    pair_dir = manifest.parent / json.loads(manifest.read_text())["pairs"][0]["path"]
    clear, unsafe = _spots(read_pair(pair_dir))
    records = [
        _record(pair_dir, tmp_path / "a", "a", [clear, unsafe]),
        _record(pair_dir, tmp_path / "b", "b", [unsafe, clear]),
        _record(pair_dir, tmp_path / "c", "c", [], "no 3 m footprint with a 1 m margin is entirely known safe"),
        # a fused site on ground an earlier, higher pair saw: this image cannot judge it (it called it NOT clear)
        _record(pair_dir, tmp_path / "d", "d", [(1e4, 1e4), clear]),
    ]
    score_records(records)
    a, b, c, d = records
    # sites the flight side's own checks withheld: not "none offered", which read as a normal result (QA 74)
    from protocol.messages import SITES_WITHHELD

    assert top_site_text({**c, "no_site_reason": f"{SITES_WITHHELD}: its frames disagree"}) == "withheld"
    assert (
        "top_site_clear" not in d["scores"] and d["site_truth"][0]["incomplete"] and not d["site_truth"][0]["n_unsafe"]
    )
    assert [j["safe"] for j in a["site_truth"]] == [True, False] and a["scores"]["top_site_clear"] == 1.0
    assert b["scores"]["top_site_clear"] == 0.0 and b["scores"]["sites_truly_clear"] == 1.0
    assert c["scores"]["sites_n"] == 0.0 and "top_site_clear" not in c["scores"] and c["site_truth"] == []
    assert [top_site_text(r) for r in records] == [
        "clear (2 sites)",
        "NOT clear (2 sites)",
        "none offered",
        "not judged (2 sites)",
    ]

    summary = {"records": records, "sites": site_summary(records), "pairs": 4, "results": 4, "deadline_met": 4}
    assert summary["sites"] == {
        "pairs": 4,
        "with_site": 3,
        "top_clear": 1,
        "top_not_clear": ["b"],
        "top_not_judged": ["d"],
        "no_site": [{"label": "c", "reason": "no 3 m footprint with a 1 m margin is entirely known safe"}],
    }
    assert site_note(summary) == (
        "landing sites: the top site truly clear on 1 of 2 pairs that offered one (NOT clear: b); 1 not judged, its "
        "footprint not wholly in the pair's upper image (d); 1 offered none (c: no 3 m footprint with a 1 m margin is "
        "entirely known safe)"
    )
    table = summary_table({**summary, "scenario": "v", "link": "l", "flight": "f", "budget": None, "degraded": 0,
                           "errors": 0, "e2e_latency_p50_s": 0.5, "e2e_latency_max_s": 0.5,
                           "flight_latency_p50_s": 0.4, "deadline_hit_rate": 1.0})  # fmt: skip
    assert "| top site |" in table and "| NOT clear (2 sites) |" in table and "Landing sites: the top site" in table

    page = write_run_report(summary, tmp_path / "report.html").read_text()
    assert "top landing site truly clear" in page and "NOT clear (2 sites)" in page
    assert "none offered: no 3 m footprint with a 1 m margin" in page
    assert (tmp_path / "figures" / "a_hazard.png").is_file()
    assert "Circles: the landing sites it offered" in page
    # the card counts the pairs that offered none: a green "1/1" stood for a run where 7 of 8 offered none (QA of
    # stop 78); amber when most offered none, even with every top site clear
    only_a = [a, c, c, c]
    few = {**summary, "records": only_a, "sites": site_summary(only_a)}
    page = write_run_report(few, tmp_path / "few.html", figures=False).read_text()
    import re

    card = re.search(r'<div class="card (\w*)"[^>]*><div class="v">[^<]*</div><div class="l">top landing site', page)
    assert card is not None and card.group(1) == "warn", card
    assert "top landing site truly clear (1 of 4 pairs offered one)" in page


def test_a_site_that_is_not_a_point_on_the_ground_is_not_clear(tmp_path):
    world = np.zeros((8, 8, 2))
    assert judge_site((float("nan"), 0.0), world, np.zeros((8, 8)))["safe"] is False
    assert judge_site((1e12, 0.0), world, np.zeros((8, 8))) == {
        "safe": False, "n_px": 0, "n_unsafe": 0, "incomplete": True, "uv": None
    }  # fmt: skip


def test_a_run_where_no_pair_offered_a_site_says_so_plainly():
    """It read "the top site truly clear on 0 of 0 pairs that offered one; 2 offered none"."""
    none = [{"label": "600/300", "reason": "every cell is unknown"}, {"label": "300/150", "reason": None}]
    s = {"pairs": 2, "with_site": 0, "top_clear": 0, "top_not_clear": [], "top_not_judged": [], "no_site": none}
    assert (
        site_note({"sites": s}) == "landing sites: no pair offered a site (600/300: every cell is unknown, and 1 more)"
    )


def test_a_map_whose_sites_the_flight_side_withheld_is_named_first():
    """A safety refusal hid behind "and 2 more" in the run's summary (stop 60's QA)."""
    from flight_sw.flight_main import _clip

    why = "no site is offered on this map: it rests on frame 1, whose navigation pose the images contradict"
    none = [
        {"label": "600/300", "reason": "no 3 m footprint with a 1 m margin is entirely known safe"},
        {"label": "300/150", "reason": why},
        {"label": "200/100", "reason": None},
    ]
    s = {"pairs": 3, "with_site": 0, "top_clear": 0, "top_not_clear": [], "top_not_judged": [], "no_site": none}
    said = site_note({"sites": s})
    assert "withheld the sites of 1 map(s) its own checks doubt (300/150: it rests on frame 1, whose" in said, said
    long = "no site is offered on this map: " + "the DEM puts the ground under frame 0's axis " * 8
    cut = _clip(long, 256)
    assert len(cut) <= 256 and cut.endswith("…") and long.startswith(cut[:-1]) and cut[-2] != " "
    assert _clip(why, 256) == why


def test_a_fused_site_the_pair_cannot_see_is_judged_on_a_pair_of_the_same_render_that_does(tmp_path):
    """The fused map's top site may lie on ground only an earlier, higher pair saw: the HIL called it NOT clear,
    then 'not judged'; another pair of the same render holds its footprint, and its truth can judge it."""
    manifest = small_descent(tmp_path / "pairs", ["600/300", "300/150"])
    dirs = [manifest.parent / e["path"] for e in json.loads(manifest.read_text())["pairs"]]
    high, low = read_pair(dirs[0]), read_pair(dirs[1])
    world_low = np.stack(pixel_ground_xy(low.camera, true_pose_upper(low), low.truth["depth"]), axis=-1)
    world_high = np.stack(pixel_ground_xy(high.camera, true_pose_upper(high), high.truth["depth"]), axis=-1)
    h, w = high.truth["hazard"].shape
    spot = next(  # a clear footprint of the high pair that the low pair's upper image does not hold
        xy
        for v in range(4, h - 4, 2)
        for u in range(4, w - 4, 2)
        if judge_site(xy := (float(world_high[v, u, 0]), float(world_high[v, u, 1])), world_high, high.truth["hazard"])[
            "safe"
        ]
        and judge_site(xy, world_low, low.truth["hazard"])["n_px"] == 0
    )
    records = [_record(dirs[0], tmp_path / "a", "600/300", []), _record(dirs[1], tmp_path / "b", "300/150", [spot])]
    score_records(records)
    low_rec = records[1]
    assert low_rec["site_truth"][0]["incomplete"] and low_rec["top_site_judged_on"] == "600/300"
    assert low_rec["scores"]["top_site_clear"] == 1.0 and top_site_text(low_rec) == "clear (1 site, judged on 600/300)"


def test_a_footprint_with_unknown_truth_is_not_confirmed_and_one_truly_unsafe_pixel_still_decides():
    """A derived truth is NaN where too little ground was seen: such a footprint was judged NOT safe (drawn red, a
    detector's good site counted as an unsafe landing) instead of not confirmed (stop 58's QA)."""
    from ground_sim.gridscore import site_verdict

    g = np.arange(20, dtype=float) * 0.5
    world = np.stack(np.meshgrid(g, g), axis=-1)  # 0.5 m pixels
    hazard = np.zeros((20, 20), np.float32)
    hazard[9:11, 9:11] = np.nan
    j = judge_site((5.0, 5.0), world, hazard)
    assert not j["safe"] and j["incomplete"] and j["n_unsafe"] == 0 and site_verdict(j) is None
    hazard[10, 8] = 1.0  # and a truly unsafe pixel in the same footprint: NOT safe, known
    assert site_verdict(judge_site((5.0, 5.0), world, hazard)) is False
    hazard[9:11, 9:11] = 0.0
    hazard[10, 8] = 0.0
    assert site_verdict(judge_site((5.0, 5.0), world, hazard)) is True


def test_a_footprint_beside_pixels_without_a_ground_point_is_not_confirmed():
    """A pixel with NaN true depth has no ground point, so it was never in the footprint: a rock whose pixels had no
    depth left the site over it judged clear (review of stop 66). Such a footprint is now not confirmed."""
    from ground_sim.geometry import look_rotation
    from ground_sim.gridscore import site_verdict
    from protocol.pairdir import Camera, Pose

    cam = Camera(64, 64, 640.0, 640.0, 31.5, 31.5)  # 0.156 m a pixel at 100 m
    pose = Pose(np.array([0.0, 0.0, 100.0]), look_rotation(0.0))
    depth = np.full((64, 64), 100.0)
    hazard = np.zeros((64, 64), np.float32)
    hazard[28:36, 28:36] = 1.0  # a 1.25 m rock under the site
    whole = np.stack(pixel_ground_xy(cam, pose, depth), -1)
    site = tuple(whole[32, 32])
    assert site_verdict(judge_site(site, whole, hazard)) is False
    depth[28:36, 28:36] = np.nan  # the truth has no depth where the rock is
    holed = np.stack(pixel_ground_xy(cam, pose, depth), -1)
    j = judge_site(site, holed, hazard)
    assert j["incomplete"] and not j["safe"] and site_verdict(j) is None
    far = tuple(whole[48, 16])  # a footprint clear of the hole is judged as before
    assert site_verdict(judge_site(far, holed, hazard)) is True


def test_full_maps_without_grids_are_scored_over_the_true_overlap_and_not_at_all_without_depth(tmp_path):
    """The full image maps of a Result without grids were scored over the map's own coverage: a map of less ground
    scored a higher CDI (review of stop 66). They are scored over the true overlap, as the grids are; a pair with no
    true depth, whose overlap is unknown, is not scored, and its record says so."""
    from ground_sim.gridscore import pixel_ground, scored_area

    manifest = small_descent(tmp_path / "pairs", ["600/300"], px=64)
    pair_dir = manifest.parent / json.loads(manifest.read_text())["pairs"][0]["path"]
    pair = read_pair(pair_dir)
    truth = np.asarray(pair.truth["hazard"], np.float32)
    half = np.where(np.arange(64)[None, :] < 32, np.where(np.isfinite(truth), np.minimum(truth, 1.0), 1.0), np.nan)
    out = tmp_path / "out"
    out.mkdir()
    np.save(out / "hazard.npy", half.astype(np.float32))  # right where it maps, and only half of the image mapped
    rec = {"status": "result", "out_dir": str(out), "pair_dir": str(pair_dir), "sites": []}
    score_records([rec])
    area = scored_area(pair, pixel_ground(pair.camera, true_pose_upper(pair), pair.truth["depth"]))
    f = rec["scores_full"]
    assert f["n"] == area.sum() and f["fp_pct"] == 0.0 and f["fn_pct"] > 10  # the unmapped half is not called safe
    (pair_dir / "gt_depth_i1.npy").unlink()
    rec = {"status": "result", "out_dir": str(out), "pair_dir": str(pair_dir), "sites": []}
    score_records([rec])
    assert "scores_full" not in rec and "no true depth" in rec["scores_full_note"]


def test_a_full_map_without_true_depth_is_drawn_unscored_as_its_scores_are(tmp_path):
    """The scores withhold a full map's pixel scores when the pair has no true depth (the overlap is unknown); the
    run page's picture still drew them over the map's own pixels, captioned "scored against the truth" (review of
    stop 66)."""
    from hil_server.run_report import _pair_figures

    manifest = small_descent(tmp_path / "pairs", ["600/300"], px=64)
    pair_dir = manifest.parent / json.loads(manifest.read_text())["pairs"][0]["path"]
    out = tmp_path / "out"
    out.mkdir()
    np.save(out / "hazard.npy", np.zeros((64, 64), np.float32))
    rec = {"status": "result", "out_dir": str(out), "pair_dir": str(pair_dir), "pair_id": "p000", "label": "a"}
    (fig,) = _pair_figures(rec, tmp_path / "figures")
    assert "scored against the truth" in fig.caption
    (pair_dir / "gt_depth_i1.npy").unlink()
    (fig,) = _pair_figures(rec, tmp_path / "figures")
    assert "not scored: the pair has no true depth" in fig.caption
