"""End to end on small cameras: render -> pipeline -> score, resume, pose errors, Dask == local."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from protocol.pairdir import read_pair
from studies import evaluate as ev

PX = 96


@pytest.fixture(scope="module")
def cache(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("render_cache")


def test_scenario_rows_score_against_truth_and_resume(tmp_path: Path, cache: Path):
    rows = ev.evaluate_scenario(
        "vertical",
        tmp_path,
        presets=["fast"],
        seeds=[0],
        cache_dir=cache,
        camera_px=PX,
        altitudes=[300],
        workers=1,
        progress=False,
        figures=False,
    )
    (r,) = rows
    assert r["scenario"] == "vertical" and r["altitude_m"] == 300 and r["label"] == "600/300"
    # a DEM from a 96 px pair at 300 m: GSD ~0.8 m in i1, so metres of error at worst, not tens
    assert 0 < r["dem_mean_abs_m"] < 5.0 and r["dem_n"] > 500
    assert r["tp_pct"] + r["tn_pct"] + r["fp_pct"] + r["fn_pct"] == pytest.approx(100.0)
    assert r["cdi_pct"] == pytest.approx(r["tp_pct"] + r["tn_pct"])
    assert 0 < r["hazards_in_scene_pct"] < 100 and r["slope_mean_abs_deg"] is not None
    # hazards in scene is the scene's (over the truly covered area, as the renderer recorded it), not the
    # flight software's covered area
    from protocol.pairdir import read_pair

    meta = read_pair(r["pair"]).meta  # a truth key: read with the truth
    assert r["hazards_in_scene_pct"] == pytest.approx(meta["hazards_in_scene_pct"], abs=0.05)
    assert 0 < r["hazards_in_scored_pct"] < 100
    fn_parts = [
        r[k]
        for k in (
            "fn_unmapped_pct",
            "fn_dem_invalid_pct",
            "fn_rock_pct",
            "fn_slope_pct",
            "fn_rough_pct",
            "fn_shadow_pct",
            "fn_other_pct",
        )
    ]
    assert sum(fn_parts) == pytest.approx(r["fn_pct"])
    assert r["fp_steep_pct"] + r["fp_rough_pct"] + r["fp_other_pct"] == pytest.approx(r["fp_pct"])
    header = (tmp_path / "metrics.csv").read_text().splitlines()[0].split(",")
    for col in (
        "scenario",
        "altitude_m",
        "preset",
        "dem_mean_abs_m",
        "dem_median_m",
        "dem_mad_m",
        "slope_mean_abs_deg",
        "fp_pct",
        "fn_pct",
        "tp_pct",
        "tn_pct",
        "hazards_detected_pct",
        "safe_detected_pct",
        "cdi_pct",
        "pipeline_s",
    ):
        assert col in header
    log = tmp_path / "runs" / "evaluate.jsonl"
    before = log.read_text()
    again = ev.evaluate_scenario(
        "vertical",
        tmp_path,
        presets=["fast"],
        seeds=[0],
        cache_dir=cache,
        camera_px=PX,
        altitudes=[300],
        workers=1,
        progress=False,
        figures=False,
    )
    assert log.read_text() == before and again == rows  # nothing re-ran


def test_the_true_slope_is_computed_once_per_render_and_again_when_what_it_comes_from_changes(
    tmp_path: Path, cache: Path, monkeypatch
):
    """The true slope and roughness (the scene rastered at the renderer's footprint cell: 8 of a 2400 m pair's 9 s)
    were computed again for every preset scored on a pair, and on every run."""
    kw = dict(seeds=[0], cache_dir=cache, camera_px=PX, altitudes=[300], workers=1, progress=False)
    (one,) = ev.evaluate_scenario("vertical", tmp_path / "one", presets=["thesis"], **kw, figures=False)
    pair = Path(one["pair"])
    kept = pair / ev.TRUTH_KEPT
    assert kept.is_file()
    rows = ev.evaluate_scenario("vertical", tmp_path / "both", presets=["fast", "thesis"], **kw, figures=False)
    drop = ("pipeline_s", "timings", "pair", "figures")
    assert {k: v for k, v in rows[1].items() if k not in drop} == {k: v for k, v in one.items() if k not in drop}

    calls = []
    real = ev.truth_slope_roughness
    monkeypatch.setattr(ev, "truth_slope_roughness", lambda *a, **k: calls.append(1) or real(*a, **k))
    fresh = ev.evaluate_pair(str(pair), "fast")
    read = ev.evaluate_pair(str(pair), "fast", keep_truth=True)
    assert len(calls) == 1, "the kept layers were computed again"
    assert {k: v for k, v in read.items() if k not in drop} == {k: v for k, v in fresh.items() if k not in drop}
    assert read["slope_mean_abs_deg"] is not None and read["rough_mean_abs_m"] is not None
    # another scene seed is other truth: computed, and kept in their place
    other = ev.evaluate_pair(str(pair), "fast", keep_truth=True, scene_seed=7)
    assert len(calls) == 2 and other["slope_mean_abs_deg"] != read["slope_mean_abs_deg"]
    again7 = ev.evaluate_pair(str(pair), "fast", keep_truth=True, scene_seed=7)
    assert len(calls) == 2 and again7["slope_mean_abs_deg"] == other["slope_mean_abs_deg"]
    # a file cut off (a worker stopped while writing) is not read: they are computed again
    kept.write_bytes(kept.read_bytes()[:100])
    again = ev.evaluate_pair(str(pair), "fast", keep_truth=True)
    assert len(calls) == 3 and again["slope_mean_abs_deg"] == read["slope_mean_abs_deg"]
    assert not list(pair.glob(".*.tmp"))


def test_a_copied_out_reads_its_own_render_cache(tmp_path: Path):
    """The copy of an --out resumed from the original's pairs (absolute paths in runs/render.jsonl) for as long as
    the original existed."""
    import shutil

    kw = dict(presets=["fast"], seeds=[0], camera_px=64, altitudes=[300], workers=1, progress=False)
    (a,) = ev.evaluate_scenario("vertical", tmp_path / "a", **kw, figures=False)
    shutil.copytree(tmp_path / "a", tmp_path / "b")
    (b,) = ev.evaluate_scenario("vertical", tmp_path / "b", **kw, figures=False)
    assert Path(a["pair"]).is_relative_to(tmp_path / "a") and Path(b["pair"]).is_relative_to(tmp_path / "b")
    assert {k: v for k, v in a.items() if k != "pair"} == {k: v for k, v in b.items() if k != "pair"}


def test_pose_knowledge_errors_raise_dem_error(cache: Path):
    (e,) = ev.render_cache("vertical", 0, cache, camera_px=PX, altitudes=[300])
    perfect = ev.evaluate_pair(e["pair_dir"], "fast", truth_slope=False)
    alt = ev.evaluate_pair(
        e["pair_dir"], "fast", truth_slope=False, pose_error={"frames": [{"dz_m": 0.0}, {"dz_m": 3.0}]}
    )
    att = ev.evaluate_pair(
        e["pair_dir"], "fast", truth_slope=False, pose_error={"frames": [{"pitch_deg": 0.3}, {"pitch_deg": 0.3}]}
    )
    assert alt["dem_mean_abs_m"] > 1.5 * perfect["dem_mean_abs_m"]
    assert att["dem_mean_abs_m"] > 1.5 * perfect["dem_mean_abs_m"]
    assert perfect["slope_mean_abs_deg"] is None  # truth slope skipped on request


def test_raster_cap_renders_are_kept_apart_and_bad_caps_refused(tmp_path: Path, cache: Path):
    """A non-default terrain raster cap renders other pairs: own cache directory and task ids, its cap in them."""
    (default,) = ev.render_cache("vertical", 0, cache, camera_px=PX, altitudes=[300])
    rows = ev.evaluate_scenario(
        "vertical",
        tmp_path / "e",
        seeds=[0],
        cache_dir=tmp_path / "c",
        camera_px=PX,
        altitudes=[300],
        progress=False,
        max_cells=20_000,
        raster="view",
        figures=False,
    )
    capped = Path(rows[0]["pair"])
    assert capped.parent.name.endswith("_cells20000") and capped != Path(default["pair_dir"])
    # the default is tiled: its renders carry the tag, so caches of capped renders are never taken for them
    assert Path(default["pair_dir"]).parent.name.endswith("_tiles")
    meta = read_pair(capped).meta
    assert all(v["raster_cell_over_target"] > 1.0 for v in meta["render"])
    log = (tmp_path / "e" / "runs" / "evaluate.jsonl").read_text()
    assert "_cells20000" in log
    (tiled,) = ev.render_cache("vertical", 0, tmp_path / "c", camera_px=PX, altitudes=[300])
    assert Path(tiled["pair_dir"]).parent.name.endswith("_tiles")
    assert all("raster_tiles" in v for v in read_pair(tiled["pair_dir"]).meta["render"])
    with pytest.raises(ev.EvaluationError, match="--max-raster-cells must be"):
        ev.render_cache("vertical", 0, tmp_path / "c", camera_px=PX, altitudes=[300], max_cells=5)
    with pytest.raises(ev.EvaluationError, match="raster must be one of"):
        ev.render_cache("vertical", 0, tmp_path / "c", camera_px=PX, altitudes=[300], raster="mosaic")


def test_sample_pose_errors_are_seeded_and_bounded():
    a = ev.sample_pose_error("altitude", 3, 7)
    assert a == ev.sample_pose_error("altitude", 3, 7) != ev.sample_pose_error("altitude", 3, 8)
    assert all(abs(f["dz_m"]) <= 0.5 for f in a["frames"])
    levels = [ev.sample_pose_error("attitude", 0, i)["frames"][0]["pitch_deg"] for i in range(6)]
    assert levels == list(ev.ATTITUDE_LEVELS_DEG)
    with pytest.raises(ev.EvaluationError):
        ev.sample_pose_error("sideways", 0, 0)


def test_sensitivity_dask_matches_local(tmp_path: Path, cache: Path):
    from distributed import Client, LocalCluster

    kw = dict(samples=2, seeds=[0], presets=["fast"], cache_dir=cache, camera_px=PX, altitudes=[250], progress=False)
    local = ev.sensitivity_campaign("altitude", tmp_path / "local", workers=1, **kw)
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None) as cl, Client(cl):
        dask = ev.sensitivity_campaign("altitude", tmp_path / "dask", scheduler=cl.scheduler_address, **kw)

    def strip(rows):
        return [{k: v for k, v in r.items() if k != "pipeline_s"} for r in rows]

    assert len(local) == 3 and [r["sample"] for r in local] == [-1, 0, 1]
    assert {r["seed_set"] for r in local} == {"tuning"}  # the CSV says which set, as evaluate's metrics do
    assert strip(local) == strip(dask)
    assert local[0]["dem_mean_rel_pct"] == 0.0
    assert all(math.isfinite(r["dem_mean_rel_pct"]) for r in local)
    assert local[0]["dem_detrended_rel_pct"] == 0.0
    assert all(0.0 < r["dem_detrended_mean_abs_m"] < 2.0 * r["dem_mean_abs_m"] for r in local)
    summ = ev.sensitivity_summary(local)
    assert summ[0]["detrended_max_rel_pct"] == max(r["dem_detrended_rel_pct"] for r in local[1:])
    assert (tmp_path / "dask" / "sensitivity_altitude.csv").is_file()
    lines = (tmp_path / "dask" / "runs" / "sensitivity-altitude.jsonl").read_text().splitlines()
    assert sorted(json.loads(x)["id"] for x in lines) == [
        "altitude-fast-s0-250-0_tiles",  # tiled renders (the default) carry their tag in the task ids
        "altitude-fast-s0-250-1_tiles",
        "altitude-fast-s0-250-ref_tiles",
    ]


def test_cli_bad_input_is_one_clean_line(tmp_path: Path, capsys):
    from hil_server.cli import main

    assert (
        main(["evaluate", "--scenario", "vertical", "--altitudes", "33", "--camera-px", "64", "--out", str(tmp_path)])
        == 2
    )
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no pair at altitude(s) [33]" in err[0]


@pytest.mark.slow
def test_evaluate_dask_matches_local_processes_and_workers_draw_the_figures(tmp_path: Path, cache: Path):
    from distributed import Client, LocalCluster

    kw = dict(
        presets=["fast", "thesis"],
        seeds=[1000],  # two presets at two altitudes: four tasks on the two workers and on the cluster
        cache_dir=cache,
        camera_px=PX,
        altitudes=[150, 300],
        progress=False,
    )
    local = ev.evaluate_scenario("vertical", tmp_path / "local", workers=2, **kw)
    # the first seed's figures of the first preset were drawn by the workers, before any report is built
    assert {p.name for p in (tmp_path / "local" / "report").glob("*.png")} >= {
        "vertical_150m_hazard.png",
        "vertical_300m_dem.png",
    }
    with LocalCluster(n_workers=1, threads_per_worker=2, processes=False, dashboard_address=None) as cl, Client(cl):
        dask = ev.evaluate_scenario("vertical", tmp_path / "dask", scheduler=cl.scheduler_address, **kw)

    def strip(rows):
        return [{k: v for k, v in r.items() if k not in ("pipeline_s", "timings")} for r in rows]

    assert len(local) == 4 and strip(local) == strip(dask)
    assert {(r["seed_set"], r["scene"]) for r in local} == {("held-out", "thesis")}


def test_multiframe_evaluation_scores_every_policy_against_the_best_pair(tmp_path: Path, cache: Path):
    """``evaluate --multi-frame``'s core: with two frames the multi-baseline run is the pair bit for bit, so
    it must score exactly as the best (only) pair; with three, every policy is scored on the same pixels."""
    from studies import multiframe as mf

    (two,) = mf.evaluate_multiframe("vertical", tmp_path, [0], frames=(300, 200), cache_dir=cache, camera_px=PX)
    rows = two["rows"]
    assert rows["best pair"]["k"] == 1
    for key in ("fp", "fn", "cdi", "dem", "coverage"):
        assert rows["multi"][key] == rows["pair 0-1"][key] == rows["best pair"][key]
    (three,) = mf.evaluate_multiframe("vertical", tmp_path, [0], frames=(300, 250, 200), cache_dir=cache, camera_px=PX)
    rows = three["rows"]
    assert rows["best pair"]["cdi"] == max(rows[f"pair 0-{k}"]["cdi"] for k in (1, 2))
    for name in ("best pair", *mf.POLICIES):
        r = rows[name]
        assert r["fp"] + r["fn"] + r["cdi"] == pytest.approx(100.0)  # the same confusion over the same pixels
        assert 0 < r["coverage"] <= 100 and 0 < r["dem"] < 5.0
    md = (tmp_path / "report" / "multiframe_vertical.md").read_text()
    assert all(f"| {name} | 1 |" in md for name in ("best pair", *mf.POLICIES))


def test_multiframe_evaluation_resumes_from_the_descents_it_scored(tmp_path: Path, cache: Path, capsys, monkeypatch):
    """An interrupted ``evaluate --multi-frame`` used to score every descent again (1-2 min of CPU each)."""
    from studies import multiframe as mf

    kw = {"frames": (300, 200), "cache_dir": cache, "camera_px": PX}
    (first,) = mf.evaluate_multiframe("vertical", tmp_path, [0], **kw)
    capsys.readouterr()

    def no_scoring(*a, **k):
        raise AssertionError("a scored descent was scored again")

    monkeypatch.setattr(mf, "evaluate_descent", no_scoring)
    (again,) = mf.evaluate_multiframe("vertical", tmp_path, [0], **kw)
    assert again == first and "reusing 1 of 1 results" in capsys.readouterr().err


def test_multiframe_descents_run_on_a_dask_cluster_as_they_do_locally(tmp_path: Path, cache: Path):
    """``evaluate --multi-frame --scheduler`` ran its descents in the calling process whatever --scheduler said."""
    from distributed import Client, LocalCluster

    from studies import multiframe as mf

    kw = {"frames": (300, 200), "cache_dir": cache, "camera_px": PX}
    (local,) = mf.evaluate_multiframe("vertical", tmp_path / "local", [0], **kw)
    from distributed.diagnostics.plugin import SchedulerPlugin

    class TaskNames(SchedulerPlugin):
        def __init__(self) -> None:
            self.keys: list[str] = []

        def update_graph(self, scheduler, *, keys=(), **kw):
            self.keys.extend(str(k) for k in keys)

    seen = TaskNames()
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None) as cl, Client(cl):
        cl.scheduler.add_plugin(seen)
        (dask,) = mf.evaluate_multiframe("vertical", tmp_path / "dask", [0], scheduler=cl.scheduler_address, **kw)
    assert any("descent_task" in k for k in seen.keys), seen.keys  # the scheduler ran it (its worker is a thread here)

    def strip(rec):
        return {
            **rec,
            "dir": None,
            "rows": {k: {m: v for m, v in r.items() if m != "cpu_s"} for k, r in rec["rows"].items()},
        }

    assert strip(local) == strip(dask)


def test_cli_multi_frame_report_and_bad_frames(tmp_path: Path, cache: Path, capsys):
    from hil_server.cli import main

    base = ["evaluate", "--scenario", "vertical", "--altitudes", "300", "--camera-px", str(PX), "--preset", "fast"]
    base += ["--seed-set", "tuning", "--seeds", "1", "--workers", "1", "--no-progress", "--cache", str(cache)]
    assert main([*base, "--multi-frame", "--frames", "300,350", "--out", str(tmp_path / "bad")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "strictly decreasing" in err[0]
    assert main([*base, "--multi-frame", "--frames", "300,250,200", "--out", str(tmp_path / "ok")]) == 0
    out = capsys.readouterr().out
    assert "multi-frame descents (300/250/200 m) against the best pair" in out and "| fused window 2 | 1 |" in out
    # where its renders are kept, and their size: only the tables and the page were named (QA of stop 74)
    assert f"renders: {cache} (" in out and "MiB; a rerun reuses them" in out, out[-300:]
    page = (tmp_path / "ok" / "report" / "index.html").read_text()
    assert "multi-frame descents" in page and "vertical_multiframe.png" in page
    assert (tmp_path / "ok" / "report" / "vertical_multiframe.png").stat().st_size > 5000


def test_a_rerun_with_other_seeds_leaves_no_map_or_figure_of_the_earlier_one(tmp_path: Path, cache: Path):
    """An --out reused with other seeds kept the earlier seed's maps and figures, and the report drew the first
    map of an altitude it found: another seed's than the rows it showed (stop 57's studies QA)."""
    kw = dict(presets=["fast"], cache_dir=cache, camera_px=PX, altitudes=[300], workers=1, progress=False)
    ev.evaluate_scenario("vertical", tmp_path, seeds=[0, 1], **kw)  # maps of seed 0 only (maps_seeds=1)
    maps = tmp_path / "maps"
    (mine,) = maps.glob("vertical-fast-s0-*.npz")
    other = maps / "approach-fast-s0-300.npz"  # another scenario's, kept
    other.write_bytes(b"x")
    stale_figure = tmp_path / "report" / "vertical_150m_dem.png"  # an altitude this run does not evaluate
    stale_figure.parent.mkdir(exist_ok=True)
    stale_figure.write_bytes(b"x")
    keep = tmp_path / "report" / "notes.png"
    keep.write_bytes(b"x")
    (row,) = ev.evaluate_scenario("vertical", tmp_path, seeds=[1], **kw)
    assert not mine.exists() and not stale_figure.exists() and other.exists() and keep.exists()
    # seed 1 was scored in the first run without maps: scored again, so its maps exist for the report
    (new,) = maps.glob("vertical-fast-s1-*.npz")
    assert row["seed"] == 1 and (tmp_path / "report" / "vertical_300m_hazard.png").is_file()
