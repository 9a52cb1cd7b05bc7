"""Run embarrassingly parallel evaluation tasks locally or on a Dask cluster, resumably.

A campaign is a list of :class:`Task` (a deterministic id plus keyword
arguments) and one module-level function. Every finished task is appended to a
JSON-lines file as ``{"id": ..., "result": {...}}`` and flushed at once, so an
interrupted campaign (Ctrl-C, a lost node, a killed job) resumes by skipping
the ids already in the file. A truncated last line - the write that was cut
off - is ignored and its task simply runs again.

A record also carries the ``code`` it was computed by (:func:`code_fingerprint`,
a hash of the source of the packages the task runs). A rerun skips only the
ids whose record has this run's fingerprint: after the flight software changes,
a resumed study recomputes its results instead of reporting the old code's,
and says how many it recomputed.

Backends: ``workers == 1`` runs inline (no process start-up cost, easiest to
debug); ``workers > 1`` uses a local pool of single-threaded processes
(:mod:`ground_sim.parallel`: one OpenCV and one BLAS thread each, so N workers
use N cores, no more); ``scheduler`` (an address such as ``tcp://host:8786`` or
a ``distributed.Client``) ships the same function to a Dask distributed
cluster. Results do not depend on the backend because each task is a pure
function of its arguments. A caller with several campaigns in a row passes one
``pool`` (:func:`local_pool`) so the workers import their libraries once.
"""

from __future__ import annotations

import hashlib
import json
import os
import sys
import threading
from collections.abc import Callable, Iterable
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from protocol.errors import InputError
from reports.progress import Progress


@dataclass(frozen=True)
class Task:
    """One unit of work: ``fn(**kwargs)`` recorded under ``id``."""

    id: str
    kwargs: dict[str, Any] = field(default_factory=dict)


class CampaignError(RuntimeError):
    """Some tasks raised; the others are saved and a rerun retries only the failures."""

    def __init__(self, failures: dict[str, str]):
        self.failures = failures
        first = next(iter(failures.items()))
        super().__init__(f"{len(failures)} task(s) failed, first {first[0]}: {first[1]}")


SOURCE_SUFFIXES = (".py", ".json", ".c", ".toml")  # .toml: the scene presets decide the renders
MAX_LISTED_FAILURES = 20  # failed tasks listed one per line on stderr; the rest are counted


def code_fingerprint(packages: Iterable[str], suffixes: tuple[str, ...] = SOURCE_SUFFIXES) -> str:
    """SHA-256 (16 hex digits) over the source files (``suffixes``) of the named packages.

    Paths and bytes both count, in sorted order, so a renamed, added or edited module, or a refitted
    model file or scene preset (.toml), gives another fingerprint; compiled kernels are covered by their C source.
    """
    import importlib.util

    h = hashlib.sha256()
    for name in sorted(set(packages)):
        spec = importlib.util.find_spec(name)
        roots = list(spec.submodule_search_locations or []) if spec is not None else []
        if not roots:
            raise InputError(f"code fingerprint: {name!r} is not an importable package")
        root = Path(roots[0])
        files = sorted(
            f for f in root.rglob("*") if f.suffix in suffixes and "__pycache__" not in f.parts and f.is_file()
        )
        for f in files:
            h.update(f"{name}/{f.relative_to(root).as_posix()}\0".encode())
            h.update(f.read_bytes())
            h.update(b"\0")
    return h.hexdigest()[:16]


def load_results(path: str | Path, code: str | None = None, inputs: str | None = None) -> dict[str, dict[str, Any]]:
    """Finished results in a JSON-lines file, by id (unparsable lines, e.g. a cut-off write, are skipped).

    With ``code``, only records computed by that fingerprint count, and with ``inputs`` only records made
    from those inputs; the last record of an id wins.
    """
    p = Path(path)
    out: dict[str, dict[str, Any]] = {}
    if not p.is_file():
        return out
    with p.open() as fh:
        for line in fh:
            try:
                rec = json.loads(line)
            except json.JSONDecodeError:
                continue
            ok = isinstance(rec, dict) and "id" in rec and isinstance(rec.get("result"), dict)
            if ok and (code is None or rec.get("code") == code) and (inputs is None or rec.get("inputs") == inputs):
                out[str(rec["id"])] = rec["result"]
    return out


def _ends_with_newline(path: Path) -> bool:
    with path.open("rb") as fh:
        fh.seek(-1, os.SEEK_END)
        return fh.read(1) == b"\n"


def _json_default(o: Any) -> Any:
    import numpy as np

    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def _call(fn: Callable[..., dict[str, Any]], kwargs: dict[str, Any]) -> dict[str, Any]:
    # one OpenCV thread per task, also on Dask workers: the workers already fill the cores
    from ground_sim.parallel import worker_init

    worker_init()
    return fn(**kwargs)


def local_pool(workers: int | None, n_tasks: int | None = None) -> Any:
    """A context manager yielding a pool of single-threaded processes, or None when one worker suffices."""
    from contextlib import nullcontext

    from ground_sim.parallel import process_pool, resolve_workers

    n = resolve_workers(workers, n_tasks if n_tasks is not None else 1 << 30)
    return process_pool(n) if n > 1 else nullcontext(None)


def check_scheduler_address(address: str) -> str:
    """``address`` if Dask can read it as a scheduler address (``tcp://host:8786``, ``host:8786``, ``tls://...``);
    :class:`InputError` otherwise. Only its form: whether a scheduler answers there is found when connecting."""
    try:
        from distributed.comm.addressing import parse_address, parse_host_port
    except ImportError:
        return address  # refused when used, with the install hint
    try:
        scheme, loc = parse_address(str(address))
        if scheme in ("tcp", "tls"):
            _, port = parse_host_port(loc)
            if not 0 < int(port) < 65536:
                raise ValueError(f"port {port} out of range")
    except (ValueError, TypeError) as exc:
        raise InputError(
            f"--scheduler {address!r} is not a Dask scheduler address such as tcp://host:8786: {exc}"
        ) from None
    return address


SCHEDULER_PROBE_S = 10.0  # a Dask scheduler sends its handshake on accept, within milliseconds
MAX_HANDSHAKE_BYTES = 1 << 16


NO_DASK = "--scheduler needs dask.distributed: pip install 'hazard-hil[cluster]'"


def probe_scheduler(address: str, timeout_s: float = SCHEDULER_PROBE_S) -> None:
    """Refuse, in one line, a plain-TCP address where no Dask scheduler answers: Dask's own connect waited forever
    on a port that accepted and said nothing, and read an HTTP server's reply as a message of 3 EiB ("out of
    memory: use a smaller camera", exit 1; QA of stop 73). A scheduler writes its handshake as soon as it accepts:
    a u64 (little-endian) byte count, then msgpack naming ``compression`` and ``pickle-protocol``. Other schemes
    (tls://, inproc://) are left to Dask."""
    import socket
    import struct

    try:
        from distributed.comm.addressing import parse_address, parse_host_port
    except ImportError:
        raise InputError(NO_DASK) from None

    scheme, loc = parse_address(str(address))
    if scheme != "tcp":
        return
    host, port = parse_host_port(loc)
    where = f"Dask scheduler {address!r}"
    try:
        sock = socket.create_connection((host, int(port)), timeout=timeout_s)
    except TimeoutError:  # a firewall dropping the connection's packets: nothing took it
        raise InputError(f"cannot reach {where}: no answer to the connection in {timeout_s:g} s") from None
    except OSError as exc:
        raise InputError(f"cannot reach {where}: {exc.strerror or exc}") from None
    try:
        with sock:
            sock.settimeout(timeout_s)
            head = _read_exactly(sock, 8)
            (n,) = struct.unpack("<Q", head)
            if not 0 < n <= MAX_HANDSHAKE_BYTES:
                raise InputError(f"{where}: not a Dask scheduler (it answered in another protocol: {head!r})")
            body = _read_exactly(sock, n)
    except TimeoutError:
        raise InputError(
            f"{where}: not a Dask scheduler (it took the connection and sent nothing in {timeout_s:g} s)"
        ) from None
    except OSError as exc:
        raise InputError(f"cannot reach {where}: {exc.strerror or exc}") from None
    if b"pickle-protocol" not in body and b"compression" not in body:
        raise InputError(f"{where}: not a Dask scheduler (its first message is not Dask's handshake)")


def _read_exactly(sock: Any, n: int) -> bytes:
    """``n`` bytes from ``sock``; OSError when it closes first."""
    buf = bytearray()
    while len(buf) < n:
        got = sock.recv(n - len(buf))
        if not got:
            raise OSError(f"it closed the connection after {len(buf)} bytes")
        buf += got
    return bytes(buf)


# a rendered pair directory on disk per pixel of its camera: two 8-bit PNG frames (~1.3 B), elevation, depth and
# hazard truth as float32 and the shadow as bool (13 B); measured 14.3 B at 512 px, 13.5 B at 4096 px (QA of stop 74)
PAIR_BYTES_PER_PX = 14.5
DISK_NOTE_BYTES = 1 << 30  # work that writes more than this says so before it starts


def check_disk(where: str | Path, need: int, what: str) -> None:
    """Refuse work whose files would not fit the free space of ``where``'s file system (:class:`InputError`), and
    say how much it will write when that is over a GiB: a campaign of 800 renders at 4096 px would have written
    180 GB onto 74 GB free, with no word before it started (QA of stop 74)."""
    import shutil

    if need <= 0:
        return
    place = Path(where).absolute()
    while not place.exists() and place != place.parent:  # the directory is made by the work itself
        place = place.parent
    try:
        free = shutil.disk_usage(place).free
    except OSError:
        return  # nothing to measure against: the writes say for themselves what the disk refuses
    gib = 1 << 30
    held = Path(where).is_dir() and any(Path(where).iterdir())
    if need > free and held:  # a shared cache: the renders already in it are reused, so the need is an upper bound
        print(f"warning: {what} may write up to {need / gib:.1f} GiB under {where}, whose file system has "
              f"{free / gib:.1f} GiB free; the renders it holds already are reused, so it may be less",
              file=sys.stderr, flush=True)  # fmt: skip
        return
    if need > free:
        raise InputError(
            f"{what} would write about {need / gib:.1f} GiB under {where}, and its file system has "
            f"{free / gib:.1f} GiB free: ask for fewer seeds, altitudes or landings or a smaller --camera-px, or "
            "give --cache a directory on a larger disk"
        )
    if need > DISK_NOTE_BYTES:
        print(f"note: {what} will write about {need / gib:.1f} GiB under {where} ({free / gib:.1f} GiB free)",
              file=sys.stderr, flush=True)  # fmt: skip


def run_tasks(
    fn: Callable[..., dict[str, Any]],
    tasks: Iterable[Task],
    results_path: str | Path,
    *,
    scheduler: Any = None,
    workers: int | None = None,
    progress: bool = True,
    desc: str = "tasks",
    pool: Any = None,
    code: str | None = None,
    inputs: str | None = None,
    redo: Iterable[str] = (),
    disk: tuple[str | Path, int] | None = None,
) -> dict[str, dict[str, Any]]:
    """Run ``fn(**task.kwargs)`` for every task not yet in ``results_path``, and those of ``redo`` (ids whose
    saved result lacks a file the caller needs); return all results by id.

    ``code`` (:func:`code_fingerprint` of what ``fn`` runs) is stored with each result, and a result
    another fingerprint computed is not reused: the task runs again, and a one-line note on stderr
    says how many did. ``inputs`` (a short text) names what the results depend on beyond their ids, such as
    the camera: a result saved with other ``inputs`` is not reused either.

    The returned dict follows the order of ``tasks``. ``scheduler`` selects
    Dask (address string or ``distributed.Client``); otherwise ``pool`` (an
    open process pool) or ``workers`` local processes (default: CPU count;
    1 = inline, with one OpenCV thread). Raises :class:`CampaignError` after
    the run if any task raised - finished results stay saved - and
    :class:`InputError` for duplicate task ids. ``disk`` = ``(directory, bytes)``: each task to run writes about
    that much there, checked against the free space before any runs (:func:`check_disk`).
    """
    tasks = list(tasks)
    ids = [t.id for t in tasks]
    if len(set(ids)) != len(ids):
        dup = sorted({i for i in ids if ids.count(i) > 1})
        raise InputError(f"duplicate task ids: {dup[:5]}")
    path = Path(results_path)
    path.parent.mkdir(parents=True, exist_ok=True)
    done = load_results(path, code, inputs)
    again = {i for i in redo if done.pop(i, None) is not None}  # saved and current, but lacking their files
    pending = [t for t in tasks if t.id not in done]
    if again:
        print(
            f"note: {desc}: {len(again)} saved results in {path} lack files this run needs (their maps); "
            "computing them again",
            file=sys.stderr,
            flush=True,
        )
    if (code is not None or inputs is not None) and pending:
        stale = (set(load_results(path)) & {t.id for t in pending}) - again
        if stale:
            # which of the two: "by other code or not from camera_px=256, renders ..." left the user to guess
            # (QA of stop 73)
            same_code = set(load_results(path, code)) & stale if code is not None else stale
            causes: list[str] = []
            if len(stale) > len(same_code):
                causes.append(f"{len(stale) - len(same_code)} by other code (the packages' source changed since)")
            if inputs is not None and (from_other := len(same_code - set(load_results(path, code, inputs)))):
                causes.append(f"{from_other} from other inputs than this run's ({inputs})")
            print(
                f"note: {desc}: {len(stale)} of {len(tasks)} saved results in {path} were computed "
                f"{'; '.join(causes) or 'otherwise'}; computing them again",
                file=sys.stderr,
                flush=True,
            )
    if disk is not None:
        check_disk(disk[0], len(pending) * int(disk[1]), f"{desc}: {len(pending)} tasks")
    reused = len(tasks) - len(pending)
    if reused:
        print(
            f"note: {desc}: reusing {reused} of {len(tasks)} results saved in {path}; computing {len(pending)}",
            file=sys.stderr,
            flush=True,
        )
    bar = Progress(len(tasks), reused, desc, enabled=progress)
    failures: dict[str, str] = {}

    try:
        _run_pending(fn, pending, path, done, bar, failures, scheduler, workers, pool, code, inputs)
    except KeyboardInterrupt:
        # say what is kept: the finished results are on disk and a rerun of the same command reuses them
        kept = sum(t.id in done for t in tasks)
        print(
            f"{chr(10) if sys.stderr.isatty() else ''}interrupted: {desc}: {kept} of {len(tasks)} results saved "
            f"in {path}; rerun the same command to resume",
            file=sys.stderr,
            flush=True,
        )
        raise
    if failures:
        # every failure with its reason, one line each (the error names only the first), and the count
        for task_id, why in sorted(failures.items())[:MAX_LISTED_FAILURES]:
            print(f"failed: {desc}: {task_id}: {why}", file=sys.stderr, flush=True)
        if len(failures) > MAX_LISTED_FAILURES:
            print(f"failed: {desc}: ... and {len(failures) - MAX_LISTED_FAILURES} more", file=sys.stderr, flush=True)
        print(
            f"{desc}: {len(tasks) - len(failures)} of {len(tasks)} done, {len(failures)} failed; the finished ones "
            f"are saved in {path}",
            file=sys.stderr,
            flush=True,
        )
        raise CampaignError(failures)
    return {t.id: done[t.id] for t in tasks}


def _run_pending(
    fn: Callable[..., dict[str, Any]],
    pending: list[Task],
    path: Path,
    done: dict[str, dict[str, Any]],
    bar: Progress,
    failures: dict[str, str],
    scheduler: Any,
    workers: int | None,
    pool: Any,
    code: str | None,
    inputs: str | None = None,
) -> None:
    """Run ``pending`` on the chosen backend, appending each result to ``path`` as it arrives."""
    with path.open("a") as fh:
        if path.stat().st_size and not _ends_with_newline(path):
            fh.write("\n")  # close a line cut off by an interruption so the next record starts clean

        def record(task_id: str, result: dict[str, Any]) -> None:
            rec = {"id": task_id, "result": result, **({"code": code} if code is not None else {})}
            if inputs is not None:
                rec["inputs"] = inputs
            fh.write(json.dumps(rec, default=_json_default, sort_keys=True) + "\n")
            fh.flush()
            done[task_id] = json.loads(json.dumps(result, default=_json_default))
            bar.update()

        if pending and scheduler is not None:
            _run_dask(fn, pending, scheduler, record, failures)
        elif pending and pool is not None:
            _drain(pool, fn, pending, record, failures)
        elif pending and (workers or os.cpu_count() or 1) > 1 and len(pending) > 1:
            _run_pool(fn, pending, int(workers or os.cpu_count() or 1), record, failures)
        elif pending:
            from ground_sim.parallel import one_thread_here

            with one_thread_here():
                for t in pending:
                    try:
                        res = fn(**t.kwargs)
                    except (KeyboardInterrupt, SystemExit):
                        raise
                    except Exception as exc:
                        failures[t.id] = f"{type(exc).__name__}: {exc}"
                        continue
                    record(t.id, res)


def _run_pool(
    fn: Callable[..., dict[str, Any]],
    pending: list[Task],
    workers: int,
    record: Callable[[str, dict[str, Any]], None],
    failures: dict[str, str],
) -> None:
    from ground_sim.parallel import process_pool

    # spawned single-threaded workers: OpenCV/numpy thread pools do not survive fork reliably
    with process_pool(min(workers, len(pending))) as pool:
        _drain(pool, fn, pending, record, failures)


def _drain(
    pool: ProcessPoolExecutor,
    fn: Callable[..., dict[str, Any]],
    pending: list[Task],
    record: Callable[[str, dict[str, Any]], None],
    failures: dict[str, str],
) -> None:
    from ground_sim.parallel import in_flight, submit_windowed

    # a bounded window of submitted tasks (ground_sim.parallel.in_flight: with all 80 008 submitted at once, a Ctrl-C
    # hung Python 3.11's pool); on an interrupt the generator cancels what has not started, and the pool's context
    # ends the workers
    window = in_flight(getattr(pool, "_max_workers", 1))
    calls = ((_call, (fn, t.kwargs)) for t in pending)
    for i, f in submit_windowed(pool, calls, window):
        exc = f.exception()
        if exc is not None:
            failures[pending[i].id] = f"{type(exc).__name__}: {exc}"
        else:
            record(pending[i].id, f.result())


def _run_dask(
    fn: Callable[..., dict[str, Any]],
    pending: list[Task],
    scheduler: Any,
    record: Callable[[str, dict[str, Any]], None],
    failures: dict[str, str],
) -> None:
    try:
        from distributed import Client, as_completed
    except ImportError:
        raise InputError(NO_DASK) from None
    own = not isinstance(scheduler, Client)
    if own:
        check_scheduler_address(scheduler)
        probe_scheduler(scheduler)
    try:
        client = Client(scheduler, timeout="20s") if own else scheduler
    except OSError as exc:
        raise InputError(f"cannot reach Dask scheduler {scheduler!r}: {exc}") from None
    done = threading.Event()
    where = scheduler if isinstance(scheduler, str) else getattr(getattr(client, "scheduler", None), "address", "")
    watcher = threading.Thread(target=_say_when_workerless, args=(client, str(where), done), daemon=True)
    watcher.start()
    try:
        futs = {}
        for t in pending:
            f = client.submit(_call, fn, t.kwargs, key=f"{getattr(fn, '__name__', 'task')}-{t.id}", pure=False)
            futs[f.key] = (f, t.id)
        for f in as_completed([v[0] for v in futs.values()]):
            task_id = futs[f.key][1]
            if f.status == "error":
                err = f.exception()
                failures[task_id] = f"{type(err).__name__}: {err}"
            else:
                record(task_id, f.result())
            f.release()
    finally:
        done.set()
        watcher.join(timeout=2.0)
        if own:
            client.close()


def _say_when_workerless(client: Any, where: str, done: threading.Event) -> None:
    """A scheduler with no workers (none started, or the only one died) held the tasks at 0 % for good, without a
    word: said after ~5 s without one, then every ~30 s while it lasts."""
    zero = 0  # looks in a row that found none: a worker still joining is not said
    while True:
        try:
            workers = len(client.scheduler_info().get("workers", {}))
        except Exception:  # the client closing under us: nothing to say
            return
        zero = zero + 1 if workers == 0 else 0
        if zero == 2 or (zero > 2 and zero % 6 == 2):  # after ~5 s without one, then every ~30 s
            print(
                f"note: the Dask scheduler {where} has no workers: the tasks wait until one joins "
                f"(`dask worker {where}`; Ctrl-C keeps what finished)",
                file=sys.stderr,
                flush=True,
            )
        if done.wait(5.0):
            return
