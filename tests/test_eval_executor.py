"""Executor: same numbers on every backend, incremental results, resume after failure."""

from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np
import pytest

from protocol.errors import InputError
from reports.progress import Progress
from studies.executor import CampaignError, Task, load_results, run_tasks


def noisy_mean(seed: int, n: int = 2000) -> dict:
    x = np.random.default_rng(seed).normal(size=n)
    return {"seed": seed, "mean": float(x.mean()), "p90": float(np.percentile(x, 90))}


def counted(seed: int, log: str, fail_on: int = -1) -> dict:
    with open(log, "a") as fh:
        fh.write(f"{seed}\n")
    if seed == fail_on:
        raise ValueError(f"boom {seed}")
    return noisy_mean(seed, 50)


TASKS = [Task(f"s{k:02d}", {"seed": k}) for k in range(5)]


def test_inline_pool_and_dask_give_identical_results(tmp_path: Path):
    from distributed import Client, LocalCluster

    inline = run_tasks(noisy_mean, TASKS, tmp_path / "a.jsonl", workers=1, progress=False)
    pool = run_tasks(noisy_mean, TASKS, tmp_path / "b.jsonl", workers=2, progress=False)
    with (
        LocalCluster(n_workers=1, threads_per_worker=2, processes=False, dashboard_address=None) as cl,
        Client(cl) as client,
    ):
        dask = run_tasks(noisy_mean, TASKS, tmp_path / "c.jsonl", scheduler=client, progress=False)
        # by address too, as the CLI passes it
        dask2 = run_tasks(noisy_mean, TASKS[:2], tmp_path / "d.jsonl", scheduler=cl.scheduler_address, progress=False)
    assert list(inline) == [t.id for t in TASKS]
    assert inline == pool == dask
    assert dask2 == {k: inline[k] for k in ("s00", "s01")}
    assert inline["s03"]["mean"] == noisy_mean(3)["mean"]


def test_results_are_incremental_and_a_rerun_only_redoes_failures(tmp_path: Path):
    log = tmp_path / "calls.txt"
    out = tmp_path / "r.jsonl"
    tasks = [Task(t.id, {"seed": t.kwargs["seed"], "log": str(log), "fail_on": 3}) for t in TASKS]
    with pytest.raises(CampaignError, match="s03"):
        run_tasks(counted, tasks, out, workers=1, progress=False)
    assert sorted(load_results(out)) == ["s00", "s01", "s02", "s04"]
    with out.open("a") as fh:  # a write cut off by the interruption
        fh.write('{"id": "s03", "resu')
    log.write_text("")
    fixed = [Task(t.id, {**t.kwargs, "fail_on": -1}) for t in tasks]
    res = run_tasks(counted, fixed, out, workers=1, progress=False)
    assert log.read_text().split() == ["3"]  # only the missing task ran
    assert res["s03"] == noisy_mean(3, 50)
    lines = [json.loads(x) for x in out.read_text().splitlines() if x.startswith('{"id"') and x.endswith("}")]
    assert sorted(r["id"] for r in lines) == [t.id for t in TASKS]


def test_duplicate_ids_rejected(tmp_path: Path):
    with pytest.raises(InputError, match="duplicate"):
        run_tasks(noisy_mean, [Task("a", {"seed": 1}), Task("a", {"seed": 2})], tmp_path / "x.jsonl")


def test_progress_bar_counts_to_total():
    buf = io.StringIO()
    bar = Progress(4, 1, "demo", stream=buf)
    for _ in range(3):
        bar.update()
    last = buf.getvalue().strip().splitlines()[-1]
    assert "4/4" in last and "100%" in last and last.startswith("demo [")


def test_a_result_of_other_code_is_computed_again_and_said_so(tmp_path: Path, capsys):
    log = tmp_path / "calls.txt"
    out = tmp_path / "r.jsonl"
    tasks = [Task(t.id, {"seed": t.kwargs["seed"], "log": str(log)}) for t in TASKS]
    run_tasks(counted, tasks[:3], out, workers=1, progress=False, code="old")
    log.write_text("")
    res = run_tasks(counted, tasks, out, workers=1, progress=False, code="old")
    assert log.read_text().split() == ["3", "4"]  # resumed: the same code's results are kept
    log.write_text("")
    capsys.readouterr()
    res = run_tasks(counted, tasks, out, workers=1, progress=False, code="new")
    assert log.read_text().split() == ["0", "1", "2", "3", "4"]  # the flight software changed: all again
    assert "5 of 5 saved results" in capsys.readouterr().err
    assert res["s02"] == noisy_mean(2, 50)
    assert sorted(load_results(out, "new")) == [t.id for t in TASKS] and len(load_results(out, "old")) == 5
    log.write_text("")
    run_tasks(counted, tasks, out, workers=1, progress=False, code="new")
    assert log.read_text() == ""


def test_the_code_fingerprint_follows_the_source(tmp_path: Path, monkeypatch):
    import importlib

    from studies.executor import code_fingerprint

    pkg = tmp_path / "fp_probe_pkg"
    (pkg / "__pycache__").mkdir(parents=True)
    (pkg / "__init__.py").write_text("X = 1\n")
    (pkg / "model.json").write_text("{}")
    monkeypatch.syspath_prepend(str(tmp_path))
    importlib.invalidate_caches()
    a = code_fingerprint(["fp_probe_pkg"])
    (pkg / "__pycache__" / "x.cpython-311.pyc").write_bytes(b"\0")  # build products do not count
    (pkg / "notes.txt").write_text("not source")
    assert code_fingerprint(["fp_probe_pkg"]) == a
    (pkg / "model.json").write_text('{"refit": 1}')  # a refitted model is other code
    b = code_fingerprint(["fp_probe_pkg"])
    (pkg / "__init__.py").write_text("X = 2\n")
    c = code_fingerprint(["fp_probe_pkg"])
    (pkg / "presets").mkdir()
    (pkg / "presets" / "scene.toml").write_text("rms_relief_m = 30\n")  # a scene preset decides the renders (QA 65b H2)
    assert len({a, b, c, code_fingerprint(["fp_probe_pkg"])}) == 4
    assert code_fingerprint(["studies", "flight_sw"]) == code_fingerprint(["flight_sw", "studies"])
    with pytest.raises(InputError, match="not an importable package"):
        code_fingerprint(["no_such_package_here"])


def test_the_rerun_note_says_which_of_code_and_inputs_changed(tmp_path, capsys):
    """The note "computed by other code or not from camera_px=256, ..." left the user to guess which (QA of stop
    73): each cause is counted apart."""
    path = tmp_path / "r.jsonl"
    run_tasks(noisy_mean, TASKS, path, workers=1, progress=False, code="A", inputs="camera_px=128")
    capsys.readouterr()
    run_tasks(noisy_mean, TASKS, path, workers=1, progress=False, code="A", inputs="camera_px=256")
    err = capsys.readouterr().err
    assert f"{len(TASKS)} from other inputs than this run's (camera_px=256)" in err and "other code" not in err, err
    run_tasks(noisy_mean, TASKS, path, workers=1, progress=False, code="B", inputs="camera_px=256")
    err = capsys.readouterr().err
    assert f"{len(TASKS)} by other code" in err and "other inputs" not in err, err


def test_work_that_would_not_fit_the_disk_is_refused_before_it_starts(tmp_path, monkeypatch, capsys):
    """800 renders at 4096 px would have written 180 GB onto 74 GB free, and nothing said so before it started
    (QA of stop 74): the tasks to run times their size is checked against the free space first, and work over a
    GiB says how much it will write."""
    import shutil
    from collections import namedtuple

    import pytest

    from protocol.errors import InputError
    from studies import executor

    usage = namedtuple("usage", "total used free")
    monkeypatch.setattr(shutil, "disk_usage", lambda p: usage(100 << 30, 90 << 30, 10 << 30))
    ran: list[int] = []
    tasks = [executor.Task(f"t{k}", {"k": k}) for k in range(4)]
    with pytest.raises(InputError, match=r"render: 4 tasks would write about 12\.0 GiB under .*, and its file system "
                                         r"has 10\.0 GiB free"):  # fmt: skip
        executor.run_tasks(lambda k: ran.append(k) or {}, tasks, tmp_path / "r.jsonl", workers=1, desc="render",
                           progress=False, disk=(tmp_path / "not" / "yet", 3 << 30))  # fmt: skip
    assert ran == []  # nothing ran
    executor.run_tasks(lambda k: ran.append(k) or {}, tasks, tmp_path / "r.jsonl", workers=1, desc="render",
                       progress=False, disk=(tmp_path, 1 << 30))  # fmt: skip
    assert ran == [0, 1, 2, 3] and "will write about 4.0 GiB under" in capsys.readouterr().err
    # a cache that holds renders already (shared by studies: "render once, fly many times"): its need is an upper
    # bound, so it is a warning, not a refusal (review of stop 74)
    held = tmp_path / "cache"
    held.mkdir()
    (held / "a_pair").mkdir()
    executor.check_disk(held, 12 << 30, "render: 4 tasks")
    assert "may write up to 12.0 GiB under" in capsys.readouterr().err
    # a rerun has nothing left to write: no check, no note
    executor.run_tasks(lambda k: {}, tasks, tmp_path / "r.jsonl", workers=1, desc="render", progress=False,
                       disk=(tmp_path, 100 << 30))  # fmt: skip
    assert "GiB" not in capsys.readouterr().err
