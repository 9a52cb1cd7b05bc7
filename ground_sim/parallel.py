"""A pool of single-threaded worker processes for embarrassingly parallel work.

Each worker runs with one OpenCV thread and one BLAS/OpenMP thread: the pool
itself fills the cores, and nested thread pools would only fight over them (on
a 2-core machine two 2-thread processes are slower than two 1-thread ones).
Workers are spawned, not forked (OpenCV and BLAS thread pools do not survive a
fork reliably); the thread limits are set in the environment before the child
imports numpy, and again in the worker initialiser for OpenCV.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from contextlib import contextmanager
from typing import Any, TypeVar

T = TypeVar("T")
THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS")


@contextmanager
def single_threaded_env() -> Iterator[None]:
    """Children started inside this block get one BLAS/OpenMP thread (restored afterwards)."""
    old = {k: os.environ.get(k) for k in THREAD_VARS}
    os.environ.update({k: "1" for k in THREAD_VARS})
    try:
        yield
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def worker_init() -> None:
    """One OpenCV thread in this worker (a pool's process, or a task on a Dask worker)."""
    import cv2

    cv2.setNumThreads(1)


def _pool_worker_init(parent: int) -> None:
    """Initialiser of :func:`process_pool`'s processes: :func:`worker_init`, and a Ctrl-C left to the parent.

    A terminal's Ctrl-C reaches the whole process group. A worker that took it died in the middle of the pool's
    protocol, and the parent's shutdown could then wait for it for good (seen with ``evaluate``); the parent
    decides instead, and :func:`process_pool` ends its workers when it leaves on an exception."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    # started with SIGINT blocked (_Pool.submit): a Ctrl-C sent while it started is discarded here, ignored
    signal.pthread_sigmask(signal.SIG_UNBLOCK, (signal.SIGINT,))
    _die_with_parent(parent)
    worker_init()


class _Pool(ProcessPoolExecutor):
    """A pool whose workers start with SIGINT blocked until their initialiser ignores it: a Ctrl-C that reached
    a worker still starting its interpreter (a loaded host takes seconds) was a KeyboardInterrupt traceback in
    the middle of the pool's start-up. Workers are started by ``submit``, in the submitting thread, whose mask
    they inherit; the parent's own Ctrl-C waits, pending, for the few milliseconds of a submit."""

    def submit(self, fn, /, *args, **kwargs):  # type: ignore[no-untyped-def]
        import signal

        held = signal.pthread_sigmask(signal.SIG_BLOCK, (signal.SIGINT,))
        try:
            return super().submit(fn, *args, **kwargs)
        finally:
            signal.pthread_sigmask(signal.SIG_SETMASK, held)


def _die_with_parent(parent: int) -> None:
    """SIGKILL this worker when the process that started it dies (Linux ``PR_SET_PDEATHSIG``; elsewhere nothing).

    A pool's workers wait on its queue for good once their parent is gone (a ``kill -9``, the OOM killer): they
    went on rendering, then idled, holding their memory. If the parent is already gone, exit now."""
    import ctypes

    try:
        ctypes.CDLL(None, use_errno=True).prctl(1, 9, 0, 0, 0)  # PR_SET_PDEATHSIG, SIGKILL
    except (OSError, AttributeError):
        return
    if os.getppid() != parent:  # the parent died before the prctl could take effect
        os._exit(1)


@contextmanager
def one_thread_here() -> Iterator[None]:
    """Run the block with one OpenCV thread and one BLAS thread in this process (an inline 'worker'), then
    restore. The BLAS pool is numpy's, started at import before any environment variable could cap it: left
    alone, ``render --workers 1`` burned 5.2 s of CPU for 2.7 s of work (its threads spin while they wait)."""
    import cv2
    from threadpoolctl import threadpool_limits

    n = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        with threadpool_limits(limits=1):
            yield
    finally:
        cv2.setNumThreads(n)


def resolve_workers(workers: int | None, n_items: int) -> int:
    """``workers`` (default: CPU count) capped by the number of items, at least 1."""
    w = int(workers) if workers else (os.cpu_count() or 1)
    return max(1, min(w, n_items))


@contextmanager
def process_pool(workers: int) -> Iterator[ProcessPoolExecutor]:
    """A spawned pool of ``workers`` single-threaded processes."""
    import multiprocessing as mp

    with single_threaded_env():
        ctx = mp.get_context("spawn")
        _tracker_deaf_to_hangup()
        pool = _Pool(max_workers=workers, mp_context=ctx, initializer=_pool_worker_init, initargs=(os.getpid(),))
        try:
            yield pool
        except BaseException:  # an interrupt or a failure: the running tasks' results are not wanted
            stop_workers(pool)
            raise
        finally:
            pool.shutdown(wait=True, cancel_futures=True)


def _tracker_deaf_to_hangup() -> None:
    """Start multiprocessing's resource tracker with SIGHUP ignored, as it ignores SIGINT and SIGTERM itself. In the
    terminal's process group a closed terminal killed it, and the workers' shared-memory bookkeeping then printed
    "resource_tracker: process died unexpectedly" and five KeyError tracebacks after the run's own clean stop. An
    ignored signal stays ignored across the tracker's exec."""
    import signal
    import threading
    from multiprocessing import resource_tracker

    if threading.current_thread() is not threading.main_thread():  # signal.signal: the main thread's only
        resource_tracker.ensure_running()
        return
    old = signal.signal(signal.SIGHUP, signal.SIG_IGN)
    try:
        resource_tracker.ensure_running()
    finally:
        signal.signal(signal.SIGHUP, old)


def in_flight(workers: int) -> int:
    """How many tasks a pool holds submitted at once: enough to keep every worker busy and its call queue fed.

    With every task submitted up front, a Ctrl-C during `sensitivity --samples 10000` (80 008 tasks) left Python
    3.11's pool shutting down with tens of thousands of pending futures, and it hung for good, its workers
    defunct, on 2 of 2 tries; so did one `landings --n 1000000` (QA of stop 74). The cause inside the pool was not
    pinned down (CPython has fixed hangs of this kind in its shutdown, e.g. gh-94440). With a window, 3 of 3 such
    Ctrl-Cs ended at once. Fewer tasks in flight also keep the pending tasks' arguments out of memory."""
    return 2 * max(1, workers) + 2


def submit_windowed(
    pool: ProcessPoolExecutor, calls: Iterable[tuple[Callable[..., Any], tuple[Any, ...]]], window: int
) -> Iterator[tuple[int, Future]]:
    """Submit ``calls`` (``(fn, args)``) keeping at most ``window`` unfinished; yield ``(index, future)`` as each
    finishes, in the order they finish. Closing the generator (an interrupt) cancels what has not started.

    A pool broken by a worker that died (the OOM killer, a crash) refuses further submits: each call not yet
    submitted is then yielded as a future holding that error, as the submitted ones hold it, so that the caller
    records every task as failed (with all submitted up front, each future failed this way)."""
    from concurrent.futures import BrokenExecutor

    todo = iter(enumerate(calls))
    running: dict[Future, int] = {}
    window = max(1, int(window))
    try:
        while True:
            while len(running) < window:
                nxt = next(todo, None)
                if nxt is None:
                    break
                i, (fn, args) = nxt
                try:
                    running[pool.submit(fn, *args)] = i
                except BrokenExecutor as exc:
                    yield from _failed(i, exc)
                    for j, _ in todo:
                        yield from _failed(j, exc)
            if not running:
                return
            done, _ = wait(running, return_when=FIRST_COMPLETED)
            for f in sorted(done, key=running.__getitem__):
                yield running.pop(f), f
    finally:
        for f in running:
            f.cancel()


def _failed(i: int, exc: BaseException) -> Iterator[tuple[int, Future]]:
    """``(i, a future that failed with exc)``."""
    f: Future = Future()
    f.set_exception(exc)
    yield i, f


def stop_workers(pool: ProcessPoolExecutor) -> None:
    """Terminate the pool's worker processes now (the executor has no public way; they ignore SIGINT)."""
    for proc in list((getattr(pool, "_processes", None) or {}).values()):
        try:
            proc.terminate()
        except (OSError, ValueError):  # already gone, or closed
            pass


def pool_map(
    fn: Callable[..., T],
    items: Iterable[Any],
    workers: int | None = None,
    on_done: Callable[[int], None] | None = None,
) -> list[T]:
    """``[fn(*item) for item in items]`` in order; inline (one OpenCV thread) when one worker suffices.

    ``on_done(i)`` is called as item ``i`` finishes, in the order the items finish (a progress bar)."""
    items = list(items)
    n = resolve_workers(workers, len(items))
    if n <= 1:
        out_inline = []
        with one_thread_here():
            for i, it in enumerate(items):
                out_inline.append(fn(*it))
                if on_done is not None:
                    on_done(i)
        return out_inline
    with process_pool(n) as pool:
        out: list[Any] = [None] * len(items)
        for i, f in submit_windowed(pool, ((fn, tuple(it)) for it in items), in_flight(n)):
            out[i] = f.result()
            if on_done is not None:
                on_done(i)
        return out
