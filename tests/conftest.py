"""Each pytest-xdist worker (`make test` runs two) keeps to a core of its own; the workers share one cache of
the small descents the HIL tests render (tests/hilkit.py).

The emulated flight processor pins its process to the highest core the run may use (hil_server.procemu). Two
workers that could both use every core would pin two flight processes to the same one, and each would run at half
the budget's speed while the other ran. A worker pinned to its own core pins its flight processes there too, so
the two never share a core. Without xdist (a plain `pytest`) nothing changes.
"""

from __future__ import annotations

import os

import hilkit
import pytest


def pytest_configure(config) -> None:
    worker = os.environ.get("PYTEST_XDIST_WORKER", "")
    if not worker.startswith("gw") or not hasattr(os, "sched_setaffinity"):
        return
    cores = sorted(os.sched_getaffinity(0))
    os.sched_setaffinity(0, {cores[int(worker[2:]) % len(cores)]})


@pytest.fixture(scope="session", autouse=True)
def _descent_cache(tmp_path_factory):
    """The session's render cache: beside the workers' own temporary directories, so that they share it."""
    base = tmp_path_factory.getbasetemp()
    hilkit.DESCENT_CACHE[:] = [(base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base) / "descent-cache"]
    yield
    hilkit.DESCENT_CACHE.clear()
