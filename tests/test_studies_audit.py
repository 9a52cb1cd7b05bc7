"""What a user of ``evaluate``, ``sensitivity`` and ``landings`` relies on, found missing by a user audit:

- a rerun into the same ``--out`` with another ``--camera-px`` scored nothing and reported the other
  camera's numbers (task ids left the camera out);
- the evaluation page never showed the map figures of the default (tiled) renders;
- a resumed run did not say how many results it reused, an interrupted one how many it kept;
- only the first failed task had its reason printed;
- an interrupted landing campaign left no summary;
- contradictory or unusable options ran (or failed in a worker with "rerun to retry") instead of exit 2.
"""

from __future__ import annotations

import html
import json
import signal
import statistics
from pathlib import Path

import pytest

from hil_server.cli import main
from protocol.errors import InputError
from reports.html import NO_FIGURES_NOTE
from studies import landings as ld
from studies.executor import CampaignError, Task, run_tasks


def square(k: int) -> dict:
    return {"k": k, "sq": k * k}


def square_or_fail(k: int) -> dict:
    if k in (1, 3):
        raise ValueError(f"bad input {k}")
    return square(k)


class Stop:
    """``square`` that raises KeyboardInterrupt (a Ctrl-C) at task ``at``."""

    def __init__(self, at: int):
        self.at = at

    def __call__(self, k: int) -> dict:
        if k == self.at:
            raise KeyboardInterrupt
        return square(k)


TASKS = [Task(f"t{k}", {"k": k}) for k in range(5)]


def test_interrupt_says_what_is_kept_and_the_rerun_what_it_reuses(tmp_path, capsys):
    log = tmp_path / "runs.jsonl"
    with pytest.raises(KeyboardInterrupt):
        run_tasks(Stop(2), TASKS, log, workers=1, progress=False, desc="demo")
    assert "interrupted: demo: 2 of 5 results saved in" in capsys.readouterr().err
    res = run_tasks(square, TASKS, log, workers=1, progress=False, desc="demo")
    assert "note: demo: reusing 2 of 5 results saved in" in capsys.readouterr().err
    assert res == run_tasks(square, TASKS, tmp_path / "fresh.jsonl", workers=1, progress=False)
    run_tasks(square, TASKS, log, workers=1, progress=False, desc="demo")
    assert "reusing 5 of 5" in capsys.readouterr().err


def test_every_failed_task_is_listed_with_its_reason_and_counted(tmp_path, capsys):
    with pytest.raises(CampaignError) as exc:
        run_tasks(square_or_fail, TASKS, tmp_path / "r.jsonl", workers=1, progress=False, desc="demo")
    err = capsys.readouterr().err
    assert set(exc.value.failures) == {"t1", "t3"}
    assert "failed: demo: t1: ValueError: bad input 1" in err and "failed: demo: t3: ValueError: bad input 3" in err
    assert "demo: 3 of 5 done, 2 failed" in err


def _eval(tmp_path: Path, out: str, px: int) -> list[str]:
    return [
        "evaluate",
        "--scenario",
        "vertical",
        "--seed-list",
        "1000",
        "--altitudes",
        "300",
        "--preset",
        "fast",
        "--workers",
        "1",
        "--no-progress",
        "--camera-px",
        str(px),
        "--cache",
        str(tmp_path / "cache"),
        "--out",
        str(tmp_path / out),
    ]


def _metrics(path: Path) -> dict:
    from studies.evaluate import read_metrics_csv

    (row,) = read_metrics_csv(path)
    return {k: v for k, v in row.items() if k not in ("pipeline_s", "pair")}  # timing and the out dir


def test_another_camera_into_the_same_out_is_scored_not_reused_and_its_maps_are_on_the_page(
    tmp_path, capsys, monkeypatch
):
    from studies import report

    with monkeypatch.context() as m:  # the reused --out's pictures are not what this test reads (b's page is)
        m.setattr(report, "figures_from_maps", lambda maps_path, out_dir, stem, px=0: [])
        assert main(_eval(tmp_path, "a", 48)) == 0
        assert main(_eval(tmp_path, "a", 64)) == 0  # same --out, another camera
    assert main(_eval(tmp_path, "b", 64)) == 0  # fresh
    capsys.readouterr()
    assert _metrics(tmp_path / "a" / "metrics.csv") == _metrics(tmp_path / "b" / "metrics.csv")
    assert len((tmp_path / "a" / "runs" / "evaluate.jsonl").read_text().splitlines()) == 2
    page = (tmp_path / "b" / "report" / "index.html").read_text()
    for kind in ("dem", "hazard", "slope", "rough"):  # drawn for the tiled renders, and now shown
        assert f'src="vertical_300m_{kind}.png"' in page


@pytest.mark.parametrize(
    "argv, message",
    [
        (["sensitivity", "--kind", "altitude", "--camera-px", "16"], "--camera-px must be >= 32"),  # was exit 1
        (["evaluate", "--scenario", "vertical", "--seed-set", "tuning", "--seed-list", "1000"], "not in the tuning"),
        (["evaluate", "--scenario", "vertical", "--altitudes", ","], "--altitudes is empty"),
        (["landings", "--scenes", "thesis", "--n", "1", "--workers", "2", "--scheduler", "x:1"], "--workers sets"),
        (["landings", "--scenes", "all,mare", "--n", "1"], "'all' already names every library scene"),
        # was a traceback from distributed after the work had begun
        (["evaluate", "--scenario", "vertical", "--scheduler", "garbage"], "not a Dask scheduler address"),
        (["sensitivity", "--kind", "altitude", "--scheduler", ""], "not a Dask scheduler address"),
        (["landings", "--scenes", "mare", "--n", "1", "--scheduler", "tcp://h:99999"], "port 99999 out of range"),
        # no scheduler there: said after a render's progress bar, with an OUT left behind (QA of stop 78)
        (["evaluate", "--scenario", "vertical", "--scheduler", "tcp://127.0.0.1:1"], "cannot reach Dask scheduler"),
        (["landings", "--scenes", "mare", "--n", "1", "--scheduler", "tcp://127.0.0.1:1"], "cannot reach Dask"),
        # sized before the renders: 8 M pipeline runs were accepted, and their tasks would not have fitted in memory
        (
            ["sensitivity", "--kind", "attitude", "--seeds", "100", "--samples", "10000", "--preset", "both"],
            "8000800 pipeline runs (2 preset(s) x 100 seed(s) x 4 altitude(s) x (10000 samples + 1 reference))",
        ),
        (
            ["evaluate", "--scenario", "vertical", "--camera-px", "8192"],
            "--camera-px must be >= 32 and <= 4096, got 8192",
        ),
        (["landings", "--scenes", "thesis", "--n", "1", "--pose-error", " "], "--pose-error is empty"),
        (["evaluate", "--scenario", "vertical", "--altitudes", "300.9"], "whole metres, got 300.9"),
    ],
)
def test_unusable_or_contradictory_options_exit_2_before_any_work(tmp_path, capsys, argv, message):
    try:
        code = main([*argv, "--out", str(tmp_path / "out")])
    except SystemExit as exc:  # argparse's own refusal (a bad --camera-px) exits from parse_args
        code = exc.code
    assert code == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def _campaign() -> ld.Campaign:
    return ld.Campaign(("thesis", "mare"), 4, (1000, 1001), "held-out", ("fast",), 1, None, 64)


def test_an_interrupted_landing_campaign_leaves_a_partial_summary_and_resumes_to_the_same_numbers(
    tmp_path, monkeypatch
):
    real = _ctrl_c_at_third_group(monkeypatch)
    with pytest.raises(KeyboardInterrupt):
        ld.run_campaign(_campaign(), tmp_path / "a", workers=1, progress=False, figures=False)
    part = json.loads((tmp_path / "a" / "landings.json").read_text())
    assert part["complete"] is False and part["incomplete_reason"] == "interrupted"
    assert part["n_landings_flown"] == 2 and part["per_preset"]["fast"]["n"] == 2
    assert "INCOMPLETE" in (tmp_path / "a" / "report" / "index.html").read_text()
    # a `kill PID` is named as the console names it ("stopped by SIGTERM"), not as a Ctrl-C
    from hil_server.cli import Terminated

    def killed(plan, presets, cache_dir=None):
        raise Terminated(signal.SIGTERM)

    monkeypatch.setattr(ld, "land_group", killed)
    with pytest.raises(Terminated):
        ld.run_campaign(_campaign(), tmp_path / "k", workers=1, progress=False, figures=False)
    assert json.loads((tmp_path / "k" / "landings.json").read_text())["incomplete_reason"] == "stopped by SIGTERM"

    monkeypatch.setattr(ld, "land_group", real)
    ld.run_campaign(_campaign(), tmp_path / "a", workers=1, progress=False, figures=False)
    ld.run_campaign(_campaign(), tmp_path / "b", workers=1, progress=False, figures=False)
    done, fresh = (json.loads((tmp_path / d / "landings.json").read_text()) for d in ("a", "b"))
    assert done["complete"] is True and done["n_landings_flown"] == 4
    for s in (done, fresh):
        s.pop("wall_s_this_run")
    assert done == fresh


def test_a_lost_campaign_json_does_not_let_another_campaigns_landings_pass_as_this_ones(tmp_path):
    """The task ids (g00000, ...) name no scene: with campaign.json gone, a `mare` campaign into the same --out
    reused a `thesis` landing and reported it as its own."""
    other = ld.Campaign(("thesis",), 1, (1000,), "held-out", ("fast",), 1, None, 64)
    mine = ld.Campaign(("mare",), 1, (1000,), "held-out", ("fast",), 1, None, 64)
    ld.run_campaign(other, tmp_path / "a", workers=1, progress=False, figures=False)
    (tmp_path / "a" / "campaign.json").unlink()
    rows, summary = ld.run_campaign(mine, tmp_path / "a", workers=1, progress=False, figures=False)
    assert {r["scene"] for r in rows} == {"mare"}
    fresh_rows, _ = ld.run_campaign(mine, tmp_path / "b", workers=1, progress=False, figures=False)
    untimed = [[{k: v for k, v in r.items() if k != "pipeline_s"} for r in rs] for rs in (rows, fresh_rows)]
    assert untimed[0] == untimed[1]
    assert ld.campaign_key(mine) != ld.campaign_key(other)
    assert ld.campaign_key(mine) == ld.campaign_key(
        ld.Campaign(("mare",), 7, (1000,), "held-out", ("fast",), 1, None, 64)
    )


def test_a_signal_during_the_final_summary_leaves_whole_files_and_says_which(tmp_path, monkeypatch):
    """The signal can land after every landing is flown: the summary it leaves is whole, and the message says
    what the file holds (it said "partial" whatever the file held)."""
    from studies.cli import _summary_state

    out = tmp_path / "a"
    assert _summary_state(out / "landings.json").startswith("no summary written")

    def signal_in_the_report(*_a, **_k):
        raise KeyboardInterrupt

    monkeypatch.setattr(ld, "write_report", signal_in_the_report)
    with pytest.raises(KeyboardInterrupt):
        ld.run_campaign(_campaign(), out, workers=1, progress=False)
    done = json.loads((out / "landings.json").read_text())
    assert done["complete"] is True and done["n_landings_flown"] == 4
    assert _summary_state(out / "landings.json") == f"summary (complete: true): {out / 'landings.json'}"
    assert len((out / "landings.csv").read_text().splitlines()) == 1 + 4
    assert not [p.name for p in out.iterdir() if p.name.startswith(".")]  # no temporary file left behind

    (out / "landings.json").write_text('{"complete": false}')
    assert _summary_state(out / "landings.json").startswith("partial summary (complete: false)")


def test_sensitivity_summary_counts_the_samples_without_a_dem_instead_of_dropping_them(capsys):
    from studies.evaluate import sensitivity_summary

    def row(alt, i, rel):
        return {"kind": "lateral", "preset": "fast", "altitude_m": alt, "sample": i, "dem_mean_rel_pct": rel}

    rows = [row(300, -1, 0.0), row(300, 0, 10.0), row(300, 1, None), row(300, 2, 30.0)]
    rows += [row(150, -1, None), row(150, 0, None)]
    (s,) = sensitivity_summary(rows)
    assert (s["altitude_m"], s["n"], s["n_no_dem"], s["median_rel_pct"]) == (300, 2, 1, 20.0)
    assert "no sample of [('lateral', 'fast', 150)] has a DEM error" in capsys.readouterr().err


def test_a_second_scenario_into_the_same_out_keeps_the_first_ones_rows(tmp_path, capsys):
    """metrics.csv was rewritten with the second scenario's rows alone; the first's vanished without a word."""
    from studies.evaluate import read_metrics_csv

    vertical = [*_eval(tmp_path, "a", 48), "--no-figures"]
    approach = [*vertical]
    approach[approach.index("vertical")] = "approach"
    approach[approach.index("300")] = "1000"
    assert main(vertical) == 0 and main(approach) == 0
    rows = read_metrics_csv(tmp_path / "a" / "metrics.csv")
    assert sorted((r["scenario"], r["altitude_m"]) for r in rows) == [("approach", 1000), ("vertical", 300)]
    assert "metrics.csv also keeps the vertical rows" in capsys.readouterr().err
    assert main(vertical) == 0  # again: one row per scenario still, nothing doubled
    assert len(read_metrics_csv(tmp_path / "a" / "metrics.csv")) == 2


def test_a_tuning_campaign_takes_the_whole_set_when_the_default_count_is_larger():
    """landings' default of 100 seeds refused --seed-set tuning (10 seeds) as "--seeds 100", an option never
    given; a default the set cannot fill now means all of it."""
    import argparse

    from studies.cli import resolve_seeds

    args = argparse.Namespace(seed_list=None, seeds=None, seed_set="tuning")
    assert resolve_seeds(args, 100) == (list(range(10)), "tuning")
    args.seeds = 11  # asked for by name: still refused
    with pytest.raises(InputError, match="--seeds 11: the tuning set has only 10 seeds"):
        resolve_seeds(args, 100)


def test_evaluate_without_figures_keeps_the_maps_and_a_later_run_draws_them(tmp_path, capsys):
    """`evaluate --no-figures`: the tables alone, said on the page; the maps are kept, so the same command
    without it draws the figures from them without scoring any pair again."""
    argv = _eval(tmp_path, "out", 48)
    rep = tmp_path / "out" / "report"
    assert main([*argv, "--no-figures"]) == 0
    page = html.unescape((rep / "index.html").read_text())
    assert NO_FIGURES_NOTE in page and "<img" not in page and not list(rep.glob("*.png"))
    assert list((tmp_path / "out" / "maps").glob("vertical-*-300*.npz"))
    log = (tmp_path / "out" / "runs" / "evaluate.jsonl").read_text()
    assert main(argv) == 0
    assert (tmp_path / "out" / "runs" / "evaluate.jsonl").read_text() == log  # nothing scored again
    drawn = {p.name for p in rep.glob("*.png")}
    assert {"vertical_detection.png", "vertical_300m_hazard.png"} <= drawn, drawn
    assert NO_FIGURES_NOTE not in html.unescape((rep / "index.html").read_text())
    # and back: the figures just drawn go, said as what --no-figures draws, not as another run's leftovers; the maps
    # stay (QA of stop 84: "removed 4 maps and figures ... with other settings", and the chart stayed)
    capsys.readouterr()
    assert main([*argv, "--no-figures"]) == 0
    err = capsys.readouterr().err
    assert f"removed {len(drawn)} figures of vertical an earlier run drew" in err and "other settings" not in err, err
    assert not list(rep.glob("*.png")) and list((tmp_path / "out" / "maps").glob("vertical-*-300*.npz"))


def test_a_write_the_system_refuses_is_one_line_and_exit_1(tmp_path, capsys):
    """A full disk or a directory where metrics.csv goes ended evaluate, sensitivity and landings in tracebacks."""
    out = tmp_path / "out"
    (out / "metrics.csv").mkdir(parents=True)  # in the way of the study's last write
    argv = [*_eval(tmp_path, "out", 48), "--no-figures"]
    assert main(argv) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert "Traceback" not in "".join(err)
    assert err[-1].startswith("hazard-hil evaluate: error: cannot use ") and "metrics.csv" in err[-1], err[-1]
    assert err[-1].endswith("Is a directory"), err[-1]


def test_a_failed_multi_frame_descent_is_one_line_and_exit_1(tmp_path, capsys, monkeypatch):
    from studies import multiframe

    def fails(*args, **kwargs):
        raise CampaignError({"mf-vertical-fast-s1000": "ValueError: no room"})

    monkeypatch.setattr(multiframe, "evaluate_multiframe", fails)
    assert main([*_eval(tmp_path, "out", 48), "--multi-frame", "--frames", "300,250"]) == 1
    err = capsys.readouterr().err
    assert "Traceback" not in err
    assert "hazard-hil evaluate: multi-frame: 1 task(s) failed" in err and "rerun the same command" in err


def test_the_tables_say_when_the_camera_is_not_the_thesiss(tmp_path, capsys):
    """... and a study that replaces another's page in a shared --out says so (it replaced it without a word)."""
    (tmp_path / "out" / "report").mkdir(parents=True)
    (tmp_path / "out" / "report" / "index.html").write_text("<title>hazard-hil sensitivity (thesis sec 6.3)</title>")
    assert main([*_eval(tmp_path, "out", 48), "--no-figures"]) == 0
    out, err = capsys.readouterr()
    assert "index.html was the sensitivity page and is now evaluate's; give each study its own --out" in err
    page = html.unescape((tmp_path / "out" / "report" / "index.html").read_text())
    for text in (out, page):
        assert "a 48 px camera, not the thesis's 512 px: not its setup" in text
        # what that camera changes in the detector, said once for the study (`process` says it per pair)
        assert "calibrated P(safe) is not fitted for it" in text and "pose refinement is skipped" in text


def test_a_ctrl_c_while_the_report_is_written_says_a_rerun_only_writes_it(tmp_path, capsys, monkeypatch):
    from studies import report

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    page = tmp_path / "out" / "report" / "index.html"
    page.parent.mkdir(parents=True)
    page.write_text("<title>hazard-hil evaluate</title> an earlier run's page")
    monkeypatch.setattr(report, "evaluation_report", interrupted)
    assert main([*_eval(tmp_path, "out", 48), "--no-figures"]) == 130
    err = capsys.readouterr().err
    assert "interrupted while writing the report, whose page is removed; every result is saved in" in err
    assert "nothing is computed" in err
    assert not page.exists()  # an earlier run's page beside this run's tables read as theirs (stop 63's QA)
    monkeypatch.undo()
    real = report.evaluation_report

    def written_then_pipe_breaks(*args, **kwargs):  # `evaluate ... | head`: the page is whole, the print fails
        real(*args, **kwargs)
        raise BrokenPipeError(32, "Broken pipe")

    monkeypatch.setattr(report, "evaluation_report", written_then_pipe_breaks)
    assert main([*_eval(tmp_path, "out", 48), "--no-figures"]) == 1
    err = capsys.readouterr().err
    assert "stopped while writing the report, its page is this run's; every result is saved in" in err
    assert "rerun" not in err and page.is_file()  # this run's page was removed too (review of stop 63)


def test_local_workers_are_sized_to_the_memory_before_any_work(monkeypatch, capsys):
    """An 8192 px camera started rendering and would have needed ~12 GiB per worker: a camera one run cannot fit
    is refused, and no more workers run at once than fit."""
    import argparse

    from flight_sw import validate
    from flight_sw.validate import peak_memory_bytes
    from studies.cli import STUDY_WORKER_EXTRA_BYTES, check_local_room

    # a worker is the pipeline and the renderer, scoring and studies around it (130 MiB resident at 128 px, where
    # the pipeline's model alone said 37)
    each = peak_memory_bytes(512, 512, 2) + STUDY_WORKER_EXTRA_BYTES
    monkeypatch.setattr(validate, "memory_room", lambda: (int(2.5 * each), "of memory is available"))
    args = argparse.Namespace(scheduler=None, workers=8, camera_px=None)
    check_local_room(args)
    assert args.workers == 2 and "8 workers on a 512 px camera would need" in capsys.readouterr().err
    with pytest.raises(InputError, match=r"a 4096 px camera needs ~\d+ MiB per pipeline run \(2 frames\)"):
        check_local_room(argparse.Namespace(scheduler=None, workers=1, camera_px=4096))
    room = peak_memory_bytes(1024, 1024, 2) + 2**20  # one pair fits, a 16-frame descent does not
    monkeypatch.setattr(validate, "memory_room", lambda: (room, "of memory is available"))
    with pytest.raises(InputError, match=r"\(16 frames\)"):  # a multi-frame descent runs in this process
        check_local_room(argparse.Namespace(scheduler=None, workers=1, camera_px=1024), n_frames=16)


def test_a_dask_scheduler_without_workers_is_said_not_waited_on_in_silence(capsys):
    """A scheduler with no workers, or whose only worker died, held `evaluate --scheduler` at 0 % for good without a
    word. A worker still joining (one look without any) is not said; none for ~5 s is, then every ~30 s."""
    import threading

    from studies.executor import _say_when_workerless

    class Looks(threading.Event):  # each wait is one ~5 s look; the run ends after `n`
        def __init__(self, n: int) -> None:
            super().__init__()
            self.left = n

        def wait(self, timeout=None) -> bool:
            self.left -= 1
            return self.left <= 0

    class Client:
        def __init__(self, counts):
            self.counts = iter(counts)

        def scheduler_info(self):
            return {"workers": {f"w{i}": {} for i in range(next(self.counts))}}

    _say_when_workerless(Client([0, 1, 1, 1]), "tcp://s:8786", Looks(4))  # joined at the second look
    assert capsys.readouterr().err == ""
    _say_when_workerless(Client([0] * 15), "tcp://s:8786", Looks(15))
    err = capsys.readouterr().err
    assert err.count("note: the Dask scheduler tcp://s:8786 has no workers") == 3, err  # at looks 2, 8 and 14


def test_sensitivity_sections_of_earlier_runs_state_their_own_seeds_and_camera(tmp_path, monkeypatch, capsys):
    """QA 61a (M1): kinds studied into one --out share its page, whose headline (seeds, camera) was the last run's
    while an earlier kind's section came from another camera and seeds; the CSVs named no camera."""
    import csv

    import studies.executor as ex
    from studies import evaluate as ev

    def render_all(scenario, seeds, cache, **kw):  # the page under test, not the renders or the pipeline
        return [{"pair_dir": str(tmp_path), "seed": s, "altitude_m": 300.0} for s in seeds]

    def run_tasks(fn, tasks, *a, **kw):
        return {t.id: {"dem_mean_abs_m": 1.0 + 0.01 * len(t.id), "dem_mad_m": 0.5} for t in tasks}

    monkeypatch.setattr(ev, "render_all", render_all)
    monkeypatch.setattr(ex, "run_tasks", run_tasks)
    out = tmp_path / "se"
    common = ["--samples", "2", "--preset", "fast", "--altitudes", "300", "--workers", "1", "--no-progress"]
    argv = ["sensitivity", "--kind", "rollyaw", *common, "--seed-list", "1001", "--camera-px", "128"]
    assert main([*argv, "--out", str(out)]) == 0
    capsys.readouterr()
    with (out / "sensitivity_rollyaw.csv").open() as fh:
        header = next(csv.reader(fh))
    assert header[:4] == ["kind", "preset", "seed", "altitude_m"] and header[-1] == "camera_px"  # appended
    argv = ["sensitivity", "--kind", "altitude", *common, "--seeds", "1", "--camera-px", "64"]
    assert main([*argv, "--out", str(out)]) == 0
    said, err = capsys.readouterr()
    # the setting above the table, whose columns carry the page's labels, not raw field names (QA of stop 73)
    first, header = said.splitlines()[:2]
    assert first.startswith("altitude: held-out seeds 1000 (1)") and "a 64 px camera" in first, said
    assert header.startswith("| error kind |") and "median_rel_pct" not in header, header
    page = html.unescape((out / "report" / "index.html").read_text())
    assert "sensitivity: altitude (held-out seeds 1000 (1), a 64 px camera)" in page
    assert "sensitivity: rollyaw (held-out seeds 1001 (1), a 128 px camera)" in page
    # each study's samples linked from the page, not only named on the console (QA of stop 85)
    assert 'href="../sensitivity_altitude.csv"' in page and 'href="../sensitivity_rollyaw.csv"' in page
    assert "../metrics.csv" not in page
    assert "the other sections are earlier runs into this --out with other settings" in page
    assert "note: the page also shows rollyaw (held-out seeds 1001 (1), a 128 px camera)" in err, err
    assert {p.name for p in (out / "report").glob("*.png")} == {"sensitivity_altitude.png", "sensitivity_rollyaw.png"}
    assert main([*argv, "--out", str(out), "--no-figures"]) == 0  # the tables alone, and the page says why
    # the pictures the earlier runs drew go, said: left, they read as this page's (QA of stop 84)
    assert not list((out / "report").glob("*.png"))
    assert "sensitivity: removed 2 figures an earlier run drew" in capsys.readouterr().err
    page = html.unescape((out / "report" / "index.html").read_text())
    assert NO_FIGURES_NOTE in page and "<img" not in page and "sensitivity: rollyaw (held-out" in page


def test_a_cached_pair_damaged_since_its_render_is_rendered_again_on_the_rerun(tmp_path, capsys):
    """runs/render.jsonl vouched for a cached pair whose image was truncated since: every rerun failed on it, though
    the error said "rerun the same command to retry them" (stop 63's QA). It is now found, removed and rendered
    again, and said."""
    assert main([*_eval(tmp_path, "out", 48), "--no-figures"]) == 0
    images = sorted((tmp_path / "cache").rglob("i2.png"))
    assert images
    data = images[0].read_bytes()
    images[0].write_bytes(data[: len(data) // 2])
    capsys.readouterr()
    assert main([*_eval(tmp_path, "out", 48), "--no-figures"]) == 0
    err = capsys.readouterr().err
    assert "rendering again" in err and "failed" not in err
    assert images[0].read_bytes() == data  # the same render again, byte for byte


def _scene_eval(tmp_path: Path, scene: Path, out: str) -> dict:
    from studies import evaluate as ev

    kw = {"seeds": [1000], "altitudes": [300], "camera_px": 48, "workers": 1, "progress": False, "figures": False}
    (row,) = ev.evaluate_scenario("vertical", tmp_path / out, scene=str(scene), cache_dir=tmp_path / "cache", **kw)
    return {k: v for k, v in row.items() if k not in ("pipeline_s", "pair", "timings")}


def test_an_edited_scene_or_render_code_draws_the_renders_again_and_scores_them(tmp_path, capsys, monkeypatch):
    """QA 65b H2: the render cache is keyed by the scene's name, so an edited preset (a) or truth rule (b) was
    scored on the old renders: "reusing 4 of 4", or "computing them again" while the renders were reused. Each
    change now draws the pairs again and scores them: the rerun gives what a fresh --out gives."""
    from ground_sim import render_cache
    from ground_sim.scene import PRESET_DIR

    scene = tmp_path / "thesis_copy.toml"
    text = (PRESET_DIR / "thesis.toml").read_text()
    scene.write_text(text)
    first = _scene_eval(tmp_path, scene, "out")
    scene.write_text(text.replace("rms_relief_m = 9.0", "rms_relief_m = 30.0"))  # (a) the preset edited
    capsys.readouterr()
    again = _scene_eval(tmp_path, scene, "out")
    err = capsys.readouterr().err
    assert "drawn from other scene parameters" in err and "rendering again" in err
    assert again != first and again == _scene_eval(tmp_path, scene, "fresh_a")

    monkeypatch.setattr(render_cache, "render_code_fingerprint", lambda: "0123456789abcdef")  # (b) truth.py edited
    capsys.readouterr()
    _scene_eval(tmp_path, scene, "out")
    err = capsys.readouterr().err
    assert "drawn by other render or truth code" in err and "computing them again" in err
    (pair_json,) = (tmp_path / "cache").rglob("pair.json")
    assert json.loads(pair_json.read_text())["render_code"] == "0123456789abcdef"  # drawn again, not reused


@pytest.mark.parametrize("stop, code", [(KeyboardInterrupt, 130), (ValueError("worker lost"), 1)])
def test_a_rerun_stopped_before_its_report_leaves_no_page_that_reads_as_complete(
    tmp_path, capsys, monkeypatch, stop, code
):
    """A rerun into an existing --out redrew the figures as its tasks ran: stopped (or failed) before its report,
    it left the old page and tables, presented as complete, over the new run's figures, some deleted (QA 65b M1).
    The old page and tables go when the run starts; a rerun writes them."""
    from studies import evaluate as ev

    argv = _eval(tmp_path, "out", 48)
    assert main(argv) == 0
    rep = tmp_path / "out" / "report"
    assert (rep / "index.html").is_file() and (rep / "tables_vertical.md").is_file()

    def stopped(**kwargs):
        raise stop

    monkeypatch.setattr(ev, "evaluate_pair", stopped)
    capsys.readouterr()
    assert main([*argv[:-2], "--preset", "thesis", *argv[-2:]]) == code  # a task to run: the other preset
    err = capsys.readouterr().err
    assert "removed the earlier vertical page (tables_vertical.md, index.html)" in err
    assert not (rep / "index.html").exists() and not (rep / "tables_vertical.md").exists()
    monkeypatch.undo()
    assert main(argv) == 0 and (rep / "index.html").is_file()  # the rerun writes it again


def test_a_partial_landings_page_says_incomplete_in_its_title_headline_figures_and_csv(tmp_path, monkeypatch):
    """The INCOMPLETE notice sat below a title and headline that read as the whole campaign's, the figures were
    unmarked and landings.csv had no marker (QA 65b L2); the interval's caveat was on the page only (L3)."""
    import csv

    from reports.html import page_title

    real = _ctrl_c_at_third_group(monkeypatch)
    seen: list[str] = []
    monkeypatch.setattr(ld, "_plots", lambda out, rows, summary: seen.append(summary["complete"]) or [])
    with pytest.raises(KeyboardInterrupt):
        ld.run_campaign(_campaign(), tmp_path / "a", workers=1, progress=False)
    out = tmp_path / "a"
    assert page_title(out / "report" / "index.html") == (
        "hazard-hil landings: INCOMPLETE landing Monte Carlo (2 of 4 landings flown)"
    )
    page = html.unescape((out / "report" / "index.html").read_text())
    assert "P(safe landing), fast, INCOMPLETE: 2 of 4 landings flown" in page
    assert "2 of 4 landings (4 renders" in page  # not "4 landings", as if all were flown
    assert "a 64 px camera, not the thesis's 512 px" in page  # L1: the camera, said as evaluate says it
    with (out / "landings.csv").open(newline="") as fh:
        rows = list(csv.DictReader(fh))  # still plain CSV
    assert len(rows) == 2 and {r["campaign_complete"] for r in rows} == {"false"}
    part = json.loads((out / "landings.json").read_text())
    assert "aim points of a render share" in part["ci95_note"] and "wider" in part["ci95_note"]
    assert seen == [False]

    monkeypatch.setattr(ld, "land_group", real)
    ld.run_campaign(_campaign(), out, workers=1, progress=False)
    assert page_title(out / "report" / "index.html") == "hazard-hil landings: landing Monte Carlo"
    with (out / "landings.csv").open(newline="") as fh:
        assert {r["campaign_complete"] for r in csv.DictReader(fh)} == {"true"}


def test_the_partial_figures_are_titled_incomplete(tmp_path, monkeypatch):
    """A figure is shown and passed on without its page: a partial campaign's says so in its title (QA 65b L2)."""
    from reports import plots

    rows = [
        {"landing": 0, "group": 0, "preset": "fast", "outcome": "safe", "safe": True, "site_found": True,
         "scene": "mare", "scene_seed": 1000, "aim_safe": True, "divert_m": 2.0, "scenario": "vertical",
         "pair": "300/150"},
    ]  # fmt: skip
    titles: list[str] = []
    monkeypatch.setattr(plots, "save", lambda fig, path, **_: titles.extend(a.get_title() for a in fig.axes) or path)
    summary = ld.summarise(rows)
    ld._plots(tmp_path, rows, summary)
    assert titles and not any("INCOMPLETE" in t for t in titles)
    titles.clear()
    ld._plots(tmp_path, rows, {**summary, "complete": False})
    assert len(titles) == 3 and all(t.startswith("INCOMPLETE: ") for t in titles)


def test_landings_console_says_the_camera_and_the_intervals_caveat(tmp_path, capsys):
    """L1/L3: `landings --camera-px 64` said nothing of the camera on the console, and its interval's caveat was
    on the page only."""
    argv = ["landings", "--scenes", "mare", "--n", "1", "--per-render", "1", "--preset", "fast", "--camera-px", "64"]
    argv += ["--no-figures"]  # the page without its three figures, and it says so
    (tmp_path / "l" / "report").mkdir(parents=True)
    (tmp_path / "l" / "report" / "outcomes.png").write_bytes(b"an earlier run's")  # goes, said (QA of stop 84)
    assert main([*argv, "--seeds", "2", "--workers", "1", "--no-progress", "--out", str(tmp_path / "l")]) == 0
    page = html.unescape((tmp_path / "l" / "report" / "index.html").read_text())
    assert NO_FIGURES_NOTE in page and "<img" not in page and not list((tmp_path / "l" / "report").glob("*.png"))
    out, err = capsys.readouterr()
    assert "a 64 px camera, not the thesis's 512 px: not its setup" in err  # the campaign's opening line
    assert "landings: removed 1 figure an earlier run drew" in err, err
    # one landing draws one of the two seeds asked for: said, and the camera recorded (QA of stop 73)
    assert "asked for but not drawn: 1 landings drew 1 of the 2 seeds" in err, err
    assert json.loads((tmp_path / "l" / "landings.json").read_text())["camera_px_used"] == 64
    assert "a 64 px camera, not the thesis's 512 px" in out
    assert "[lo, hi]: 95 % Wilson interval taking the landings as independent draws; the 1 aim points" in out


@pytest.mark.parametrize(
    "seeds, said",
    [(["--seed-set", "tuning", "--seeds", "1"], "tuning seeds: "), (["--seed-list", "5,1000"], "seed(s) 5 (not held")],
)
def test_tuning_or_mixed_seeds_are_warned_of_and_the_tables_name_seeds_scene_and_camera(tmp_path, capsys, seeds, said):
    """QA 65b M3: --seed-set tuning, or a --seed-list pooling tuning and held-out seeds, was only named; the pasted
    tables_<scenario>.md named neither seeds nor scene nor camera, and metrics.csv had no camera column."""
    from studies.evaluate import read_metrics_csv

    argv = [*_eval(tmp_path, "out", 48), "--no-figures"]
    i = argv.index("--seed-list")
    argv[i : i + 2] = seeds
    assert main(argv) == 0
    err = capsys.readouterr().err
    warning = [ln for ln in err.splitlines() if ln.startswith("warning: ") and "not held-out results" in ln]
    assert len(warning) == 1 and said in warning[0]
    rep = tmp_path / "out" / "report"
    assert "WARNING: " + said in html.unescape((rep / "index.html").read_text())
    first = (rep / "tables_vertical.md").read_text().splitlines()[0]
    for text in ("vertical scenario", "scene thesis", "seeds", "a 48 px camera", "not held-out results"):
        assert text in first, first
    assert {r["camera_px"] for r in read_metrics_csv(tmp_path / "out" / "metrics.csv")} == {48}


def _ctrl_c_at_third_group(monkeypatch):
    """A landings campaign whose third group is stopped by Ctrl-C; returns the real ``land_group``."""
    real, calls = ld.land_group, []

    def ctrl_c_at_third(plan, presets, cache_dir=None):
        calls.append(plan["group"])
        if len(calls) == 3:
            raise KeyboardInterrupt
        return real(plan, presets, cache_dir)

    monkeypatch.setattr(ld, "land_group", ctrl_c_at_third)
    return real


def test_the_sensitivity_summary_sets_the_thesiss_own_figures_beside_ours():
    """The help promised Tables 6.12-6.19, but the summary and page showed our numbers alone (QA 65b L5)."""
    from studies.evaluate import ATTITUDE_LEVELS_DEG, load_thesis, sensitivity_summary, thesis_index

    idx = thesis_index(load_thesis())
    base = {"preset": "fast", "pitch_deg1": 0.05, "dz_m1": 0.1, "dz_m2": 0.1}
    rows = [
        {**base, "kind": kind, "altitude_m": alt, "sample": i, "dem_mean_rel_pct": 10.0 * i}
        for kind in ("altitude", "attitude", "lateral")
        for alt in (125, 400)
        for i in (-1, 0, 1)
    ]
    by = {(s["kind"], s["altitude_m"]): s for s in sensitivity_summary(rows)}
    samples = [v for (t, sc, a, m), v in idx.items() if t == "6.12" and m.endswith(".dem_mean_rel_pct")]
    assert len(samples) == 20
    assert by[("altitude", 125)]["thesis_median_rel_pct"] == pytest.approx(statistics.median(samples))
    att = by[("attitude", 125)]
    assert att["thesis_rel_pct@+0.05"] == idx[("6.16", "approach", 125, "dev+0.05.dem_mean_rel_pct")]
    assert all(f"thesis_rel_pct@{lv:+.2f}" in att for lv in ATTITUDE_LEVELS_DEG)
    assert by[("altitude", 400)]["thesis_median_rel_pct"] is None  # no such table: said as none, same columns
    assert "thesis_median_rel_pct" not in by[("lateral", 125)]  # a study the thesis did not make


def test_a_scheduler_address_where_no_dask_scheduler_answers_is_refused_in_one_line():
    """A port that took the connection and said nothing held `evaluate --scheduler` at 0 % for good; one where a web
    server answered read its reply as a 3 EiB message: "out of memory: use a smaller camera", exit 1 (QA of stop
    73). A Dask scheduler's handshake is read first, with a time limit."""
    import socket
    import threading

    from distributed import LocalCluster

    from studies.executor import probe_scheduler

    def server(reply: bytes | None) -> tuple[socket.socket, str]:
        s = socket.socket()
        s.bind(("127.0.0.1", 0))
        s.listen()

        def serve() -> None:
            held = []
            while True:
                try:
                    c, _ = s.accept()
                except OSError:
                    return
                held.append(c)
                if reply is not None:
                    c.sendall(reply)

        threading.Thread(target=serve, daemon=True).start()
        return s, f"tcp://127.0.0.1:{s.getsockname()[1]}"

    silent, quiet_addr = server(None)
    web, web_addr = server(b"HTTP/1.1 400 Bad Request\r\n\r\n")
    try:
        with pytest.raises(
            InputError, match=r"not a Dask scheduler \(it took the connection and sent nothing in 0.5 s\)"
        ):
            probe_scheduler(quiet_addr, timeout_s=0.5)
        with pytest.raises(InputError, match=r"not a Dask scheduler \(it answered in another protocol"):
            probe_scheduler(web_addr, timeout_s=2.0)
    finally:
        silent.close()
        web.close()
    with LocalCluster(n_workers=0, processes=False, protocol="tcp://", dashboard_address=None) as cl:
        assert cl.scheduler_address.startswith("tcp://")
        probe_scheduler(cl.scheduler_address, timeout_s=5.0)  # a scheduler passes
