"""Each pytest-xdist worker keeps to one core; the workers share one cache of the small descents the HIL tests
render (tests/hilkit.py).

The emulated flight processor pins its process to the highest core the run may use (hil_server.procemu). Workers
that could all use every core would pin all their flight processes to the same one, and each would run at a
fraction of the budget's speed while the others ran. A worker pinned to a core pins its flight processes there
too. `make test` runs two workers per core (the end-to-end tests mostly wait on lines and timers), so
two workers share a core: worker k takes core k mod n. A test marked ``exclusive_core`` (a throttled budget's
run, a timing bound) has its core to itself: the other workers there finish their tests and start no other
until it ends. Without xdist (a plain `pytest`) nothing changes.
"""

from __future__ import annotations

import fcntl
import json
import os

import pytest


def pytest_configure(config) -> None:
    # the longest files first (pytest_collection_modifyitems), not pytest-xdist's most-tests-first: a 180 s file of
    # waits handed out late left one worker running 35 s after the others had finished (stop 80)
    if hasattr(config.option, "loadscopereorder"):
        config.option.loadscopereorder = False
    worker = os.environ.get("PYTEST_XDIST_WORKER", "")
    if not worker.startswith("gw") or not hasattr(os, "sched_setaffinity"):
        return
    cores = sorted(os.sched_getaffinity(0))
    os.sched_setaffinity(0, {cores[int(worker[2:]) % len(cores)]})


def pytest_collection_modifyitems(session, config, items) -> None:
    """Order the files longest first, the tests in a file as written: the workers then end together."""
    from file_seconds import TABLE, longest_first

    try:
        seconds = json.loads(TABLE.read_text())
    except (OSError, ValueError):
        seconds = {}
    order = longest_first([item.nodeid for item in items], seconds)
    items[:] = [items[i] for i in order]


def _shared_root(tmp_path_factory):
    """What the session's workers share: the parent of their own temporary directories (one per session)."""
    base = tmp_path_factory.getbasetemp()
    return base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base


@pytest.fixture(scope="session", autouse=True)
def _descent_cache(tmp_path_factory):
    """The session's render caches (tests/hilkit.py's descents, tests/evalpairs.py's pairs), shared by the workers."""
    # here, not at the top: numpy, which they import, starts its threads after the worker is pinned
    import evalpairs
    import hilkit

    hilkit.DESCENT_CACHE[:] = [_shared_root(tmp_path_factory) / "descent-cache"]
    evalpairs.PAIR_CACHE[:] = [_shared_root(tmp_path_factory) / "eval-pairs"]
    yield
    hilkit.DESCENT_CACHE.clear()
    evalpairs.PAIR_CACHE.clear()


@pytest.fixture(autouse=True)
def _core_turn(request, tmp_path_factory):
    """Every test holds its core's lock shared, an ``exclusive_core`` test holds it alone. A turnstile taken before
    the lock keeps the tests that share it from starving one that waits for it alone."""
    if not os.environ.get("PYTEST_XDIST_WORKER", "").startswith("gw") or not hasattr(os, "sched_getaffinity"):
        yield
        return
    core = min(os.sched_getaffinity(0))
    root = _shared_root(tmp_path_factory)
    alone = request.node.get_closest_marker("exclusive_core") is not None
    with open(root / f"core{core}.turnstile", "a") as gate, open(root / f"core{core}.lock", "a") as lock:
        fcntl.flock(gate, fcntl.LOCK_EX)
        try:
            fcntl.flock(lock, fcntl.LOCK_EX if alone else fcntl.LOCK_SH)
        finally:
            fcntl.flock(gate, fcntl.LOCK_UN)
        yield
