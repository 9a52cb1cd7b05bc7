"""The worker pool (ground_sim.parallel) under a terminal's Ctrl-C, which reaches the whole process group."""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

SCRIPT = """
import os, signal, sys, threading, time
sys.path.insert(0, {root!r})
from ground_sim.parallel import pool_map


def slow(k):
    time.sleep(40)
    return k


if __name__ == "__main__":
    # what this process inherited, said when the test fails (a Ctrl-C ignored or blocked by its parent is not one)
    print(f"SIGINT {{signal.getsignal(signal.SIGINT)}}, blocked {{signal.pthread_sigmask(signal.SIG_BLOCK, [])}}",
          file=sys.stderr, flush=True)
    threading.Timer(4.0, lambda: os.killpg(0, signal.SIGINT)).start()  # Ctrl-C: the parent and its workers
    try:
        pool_map(slow, [(1,), (2,)], workers=2)
    except KeyboardInterrupt:
        print("interrupted", flush=True)
        sys.exit(130)
"""


def _run_in_own_session(script: Path, text: str, sig: signal.Signals) -> subprocess.CompletedProcess:
    """``text`` (formatted with the repository root) run as a script in a session of its own, ``sig`` at its
    default disposition whatever this process inherited; its output captured."""
    script.write_text(text.format(root=str(ROOT)))
    return subprocess.run(
        [sys.executable, str(script)],
        capture_output=True,
        text=True,
        timeout=120,
        start_new_session=True,
        preexec_fn=lambda: signal.signal(sig, signal.SIG_DFL),
    )


def test_ctrl_c_ends_a_pool_at_once_with_its_workers(tmp_path):
    """Workers took the Ctrl-C too and died inside the pool's protocol; the parent could then wait for good."""
    t0 = time.monotonic()
    # a terminal's foreground job takes Ctrl-C; a job started in the background by a non-interactive shell
    # (a CI runner's `./.ci/run &`) inherits SIGINT ignored, and Python then never raises KeyboardInterrupt
    done = _run_in_own_session(tmp_path / "pool_ctrl_c.py", SCRIPT, signal.SIGINT)
    took = time.monotonic() - t0
    assert done.returncode == 130 and done.stdout.strip() == "interrupted", done.stderr[-2000:]
    assert took < 30, f"the interrupted pool waited for its 40 s tasks ({took:.0f} s)"  # the workers were ended
    assert "Traceback" not in done.stderr, done.stderr[-2000:]  # no worker died printing one


HUP_SCRIPT = """
import os, signal, sys, threading, time
sys.path.insert(0, {root!r})
from ground_sim.parallel import pool_map


def slow(k):
    time.sleep(40)
    return k


def hung_up(signum, frame):
    raise KeyboardInterrupt


if __name__ == "__main__":
    signal.signal(signal.SIGHUP, hung_up)  # as the studies' commands end on a closed terminal
    threading.Timer(4.0, lambda: os.killpg(0, signal.SIGHUP)).start()  # the terminal closes: the whole group
    try:
        pool_map(slow, [(1,), (2,)], workers=2)
    except KeyboardInterrupt:
        print("hung up", flush=True)
        time.sleep(1.0)  # the resource tracker's complaints came while the process exited
        sys.exit(129)
"""


def test_a_closed_terminal_ends_a_pool_without_the_resource_trackers_tracebacks(tmp_path):
    """SIGHUP to the group also killed multiprocessing's resource tracker, which ignores only SIGINT and SIGTERM:
    after the command's own clean stop, "resource_tracker: process died unexpectedly" and five KeyError
    tracebacks (stop 57's studies QA)."""
    done = _run_in_own_session(tmp_path / "pool_hup.py", HUP_SCRIPT, signal.SIGHUP)
    assert done.returncode == 129 and done.stdout.strip() == "hung up", done.stderr[-2000:]
    assert "Traceback" not in done.stderr and "resource_tracker" not in done.stderr, done.stderr[-2000:]


def _sigint_handler(_: int) -> str:
    return str(signal.getsignal(signal.SIGINT))


def test_pool_workers_leave_ctrl_c_to_the_parent():
    """A worker that died of the Ctrl-C inside the pool's protocol could leave the parent's shutdown waiting for
    good (1 in 13 interrupts of `evaluate`, intermittent): the workers ignore it, the parent ends them."""
    from ground_sim.parallel import pool_map

    assert pool_map(_sigint_handler, [(0,), (1,)], workers=2) == [str(signal.SIG_IGN)] * 2


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGKILL])
def test_a_pool_command_stopped_from_outside_leaves_no_worker(tmp_path, sig):
    """`kill PID` on `hazard-hil render` (or `evaluate`, `landings`): the process died at once and its spawned
    workers rendered on, then waited on the pool's queue for good. Now SIGTERM ends it as a Ctrl-C does (exit
    128 + 15, the workers stopped), and after a SIGKILL, which runs no handler, the workers go with their parent
    (PR_SET_PDEATHSIG)."""
    import psutil

    cmd = [sys.executable, "-m", "hil_server.cli", "render", "--scenario", "vertical", "--workers", "2"]
    proc = subprocess.Popen([*cmd, "--out", str(tmp_path / "r")], cwd=ROOT, stderr=subprocess.PIPE, text=True)
    workers: list = []
    try:
        for _ in range(300):
            workers = [c for c in psutil.Process(proc.pid).children(recursive=True) if "spawn" in " ".join(c.cmdline())]
            if len(workers) >= 2:
                break
            time.sleep(0.1)
        assert len(workers) >= 2, "the pool never started"
        time.sleep(1.0)
        proc.send_signal(sig)  # the main process only, as `kill PID` does
        _, err = proc.communicate(timeout=30)
        _, alive = psutil.wait_procs(workers, timeout=10)
    finally:
        if proc.poll() is None:
            proc.kill()
        for w in workers:  # never leave a pool behind, even when the test fails
            if w.is_running():
                w.kill()
    assert not alive, [p.cmdline() for p in alive]
    if sig == signal.SIGTERM:
        assert proc.returncode == 128 + signal.SIGTERM and "stopped by SIGTERM" in err, err[-2000:]


def test_an_inline_worker_runs_one_blas_thread_too():
    """numpy's BLAS pool starts at import, before any environment variable could cap it: `render --workers 1` spent
    twice its CPU time in spinning BLAS threads."""
    import cv2
    from threadpoolctl import threadpool_info

    from ground_sim.parallel import one_thread_here

    before = [i["num_threads"] for i in threadpool_info()]
    with one_thread_here():
        assert cv2.getNumThreads() == 1
        assert all(i["num_threads"] == 1 for i in threadpool_info())
    assert [i["num_threads"] for i in threadpool_info()] == before


class _CountingPool:
    """A thread pool that records how many submitted tasks were unfinished at once."""

    def __init__(self, workers: int) -> None:
        import threading
        from concurrent.futures import ThreadPoolExecutor

        self._pool = ThreadPoolExecutor(workers)
        self._max_workers = workers
        self._lock = threading.Lock()
        self.open = self.most = self.submitted = 0
        self.futures: list = []

    def submit(self, fn, *args):
        with self._lock:
            self.open += 1
            self.submitted += 1
            self.most = max(self.most, self.open)
        fut = self._pool.submit(fn, *args)
        fut.add_done_callback(self._done)
        self.futures.append(fut)
        return fut

    def _done(self, _fut) -> None:
        with self._lock:
            self.open -= 1


def test_a_pool_holds_a_bounded_window_of_tasks(monkeypatch):
    """Submitting all 80 008 tasks of `sensitivity --samples 10000` at once deadlocked Python 3.11's process pool
    (CPython gh-105829: the wake-up pipe fills under the pool's lock) and a Ctrl-C then hung for good (QA of stop
    74). pool_map and the studies' executor keep at most ``in_flight(workers)`` tasks submitted and unfinished;
    every result still comes back, in order, and an interrupt cancels what had not started."""
    import contextlib

    from ground_sim import parallel
    from studies import executor

    pool = _CountingPool(2)
    monkeypatch.setattr(parallel, "process_pool", lambda n: contextlib.nullcontext(pool))
    done: list[int] = []
    assert parallel.pool_map(pow, [(k, 2) for k in range(500)], workers=2, on_done=done.append) == [
        k * k for k in range(500)
    ]
    assert pool.submitted == 500 and pool.most <= parallel.in_flight(2) and sorted(done) == list(range(500))

    pool2 = _CountingPool(2)
    got: dict[str, dict] = {}
    tasks = [executor.Task(f"t{k:03d}", {"k": k}) for k in range(300)]
    executor._drain(pool2, lambda k: {"k2": k * k}, tasks, got.__setitem__, {})  # type: ignore[arg-type]
    assert got == {f"t{k:03d}": {"k2": k * k} for k in range(300)} and pool2.most <= parallel.in_flight(2)

    pool3 = _CountingPool(1)
    gen = parallel.submit_windowed(pool3, ((time.sleep, (0.5,)) for _ in range(100)), 4)  # type: ignore[arg-type]
    next(gen)
    gen.close()  # an interrupt in the consumer: what had not started is cancelled, nothing more is submitted
    assert pool3.submitted == 4 and sum(f.cancelled() for f in pool3.futures) >= 1, [f._state for f in pool3.futures]


BROKEN = """
import os, sys, time
sys.path.insert(0, {root!r})
from studies.executor import CampaignError, Task, run_tasks


def maybe_die(k):
    if k == 3:
        os._exit(1)  # the OOM killer, a segfault
    time.sleep(0.05)
    return {{"k": k}}


if __name__ == "__main__":
    tasks = [Task(f"t{{k:02d}}", {{"k": k}}) for k in range(30)]
    try:
        run_tasks(maybe_die, tasks, {log!r}, workers=2, progress=False)
    except CampaignError as exc:
        print("CampaignError", len(exc.failures), flush=True)
"""


def test_a_worker_that_dies_fails_the_tasks_left_and_keeps_the_rest(tmp_path):
    """With a window of submitted tasks, a pool broken by a dead worker refused the next submit, and its
    BrokenProcessPool escaped as a traceback: the failures were not listed and no partial summary was written
    (review of stop 74). Every task not done is a failure of the campaign; those done are saved."""
    import json

    script = tmp_path / "broken.py"
    log = tmp_path / "runs.jsonl"
    script.write_text(BROKEN.format(root=str(ROOT), log=str(log)))
    p = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=120)
    assert "Traceback" not in p.stderr, p.stderr[-2000:]
    failed = int(p.stdout.split()[-1]) if p.stdout.startswith("CampaignError") else -1
    saved = [json.loads(line) for line in log.read_text().splitlines()] if log.exists() else []
    assert failed >= 1 and failed + len(saved) == 30, (p.stdout, len(saved))
