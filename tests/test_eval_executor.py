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
