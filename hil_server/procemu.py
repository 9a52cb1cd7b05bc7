"""The emulated flight processor: one pinned core, a CPU duty cycle, a memory ceiling.

The flight process is an ordinary child process; everything is imposed from
the parent side, because flight_sw must not import hil_server:

* **One core.** ``sched_setaffinity`` to one core in ``preexec_fn`` (before the
  child starts any thread, so every thread inherits it) and the thread-pool
  variables of :func:`thread_env` in its environment, which numpy/OpenBLAS/
  OpenMP/MKL/OpenCV read at import. (The flight main should still call
  ``cv2.setNumThreads(1)``; the affinity alone already keeps it on one core.)
* **Memory ceiling.** ``memory_mib`` caps the private resident set (``RssAnon +
  RssShmem``; mapped library code is not counted, see :func:`private_rss_bytes`):
  a watchdog thread polls ``/proc/PID/status`` and kills the child when it exceeds it; the
  processes it starts count too, by proportional shares (:func:`tree_private_bytes`). The
  hard stop is ``RLIMIT_AS`` = measured address-space baseline of a Python with
  numpy/cv2/zmq/msgpack/serial imported + ``memory_mib`` + headroom; an
  allocation past it fails in the child (``MemoryError``).
* **CPU duty cycle** (the cpulimit technique, closed loop). A throttle thread
  SIGSTOPs/SIGCONTs the child. Let f be the target fraction and

      credit = f * t_avail - cpu,   t_avail = wall - contention,

  where ``cpu`` is the child's on-CPU time (sum of the first field of
  ``/proc/PID/task/*/schedstat``, ns) and ``contention`` its run-queue wait
  (second field): time it was runnable but the *host* ran something else. The
  child is stopped when credit <= 0 and resumed when credit >= f * P, so each
  cycle is ~P stopped and ~f P / (1 - f) running. Credit is capped at f * P so
  the child cannot bank idle time (a slow processor that waited for I/O is not
  faster afterwards).

**Achieved fraction** = cpu / (wall - contention): the share of a core the
emulated processor delivered while the host was not preempting it. On an idle
host it equals cpu / wall; on a loaded host the raw cpu / wall (``raw_fraction``)
drops, but the emulated processor is then simply paused for the stolen time,
which ``stats()['contention_s']`` reports so deadline accounting can subtract it.

**The core to itself.** The emulated core is the highest one allowed to us (:func:`flight_core`); the HIL's own
processes (the ground streamer and the HIL server, with all their threads, and the loopback line's relay) keep to
the other cores when there are any (:func:`hil_cores`, :func:`keep_off_core`). Until stop 81 they ran on any core,
the flight's too: on this idle 2-core host a host-budget 128 px run over ZeroMQ then waited 5.9 % of its flight time
for its core (median of 8 runs), 3.6 % since; over loopback serial 5.5 and 5.2 % (the rest is the flight process's
own threads and the kernel's). On a loaded host the share kept is larger.

**Process group.** The child leads its own process group (anything it spawns
is killed with it) and gets SIGKILL if the thread that started it dies
(``PR_SET_PDEATHSIG``): a supervisor that is killed outright leaves no flight
process behind, even one the throttle holds stopped.

**Processes it starts** run on the same budget: the throttle stops and resumes the whole group and counts its
CPU, the memory ceiling counts their private RSS too, and they die with the flight process. The watchdog finds
them every ``MEMBER_SCAN_S`` through ``/proc/PID/task/TID/children``, so one that left the group with ``setsid``
is throttled and killed as well (by PID and start time, after it is reparented). Before stop 52 a flight
program's worker process ran outside the budget: 400 MiB under a 128 MiB ceiling, and 75 % of the pinned core
on a 33 % budget.

Exit reports distinguish: normal exit ("ok"), error exit ("error"), crash by
signal ("crash"), memory-ceiling breach by the watchdog or a failed allocation
("memory"), a kill requested through :meth:`EmulatedProcessor.kill` ("killed"),
and a kill from outside ("external").
"""

from __future__ import annotations

import atexit
import collections
import ctypes
import math
import os
import resource
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from typing import Any

from flight_sw.memory import private_rss_bytes, proportional_private_bytes
from protocol.errors import EXIT_MEMORY, InputError

MIB = 1 << 20
PAGE = os.sysconf("SC_PAGE_SIZE")

# Thread pools of every numeric library the flight software may load.
THREAD_VARS = (
    "OMP_NUM_THREADS",
    "OPENBLAS_NUM_THREADS",
    "MKL_NUM_THREADS",
    "NUMEXPR_NUM_THREADS",
    "VECLIB_MAXIMUM_THREADS",
    "BLIS_NUM_THREADS",
    "OPENCV_FOR_THREADS_NUM",
)

# Markers of a failed allocation in the child's stderr: Python/numpy MemoryError,
# OpenCV's Insufficient memory, a failed thread stack under RLIMIT_AS.
_MEMORY_MARKERS = (
    b"MemoryError",
    b"Insufficient memory",
    b"Failed to allocate",
    b"std::bad_alloc",
    b"can't start new thread",
    b"Cannot allocate memory",
)

# EXIT_MEMORY (protocol.errors): the status a flight main uses to say "allocation failed".

MAX_FORWARDED_BYTES = 4 << 20  # of a flight process's output passed on to the supervisor's log; the rest counted
MEMBER_SCAN_S = 0.1  # how often the watchdog rescans the processes a flight process started
MAX_DESCENDANTS = 256  # a fork bomb is not walked forever; the ceiling catches it by the memory it holds
MIN_ON_SLICE_S = 0.001  # below ~1 ms, signal and sleep latency dominate a slice

PR_SET_PDEATHSIG = 1  # linux/prctl.h


def libc_prctl() -> Any:
    """libc's prctl, loaded before fork (loading a library in the forked child is not safe); None if absent."""
    try:
        return ctypes.CDLL(None, use_errno=True).prctl
    except (OSError, AttributeError):
        return None


_BASELINE_MODULES = ("numpy", "cv2", "zmq", "msgpack", "serial")


class ProcessorError(InputError):
    """A processor spec is invalid, or the emulator was used out of order."""


def thread_env() -> dict[str, str]:
    """Environment that limits every thread pool to one thread (set before imports)."""
    env = {k: "1" for k in THREAD_VARS}
    # glibc gives each new thread that mallocs a 64 MiB arena of address space;
    # two arenas keep the address-space baseline small and predictable.
    env["MALLOC_ARENA_MAX"] = "2"
    return env


def measure_baseline_vms_mib(python: str = sys.executable, modules: tuple[str, ...] = _BASELINE_MODULES) -> float:
    """Peak address space (VmPeak, MiB) of ``python`` after importing ``modules`` single-threaded.

    The flight process pays this before doing any work, so the address-space
    rlimit is set on top of it. A ZeroMQ context is created too (its I/O thread
    has a stack).
    """
    code = (
        "import importlib, sys\n"
        "for m in sys.argv[1:]:\n"
        "    try: importlib.import_module(m)\n"
        "    except ImportError: pass\n"
        "try:\n"
        "    import zmq; zmq.Context().socket(zmq.PAIR)\n"
        "except ImportError: pass\n"
        "print([l.split()[1] for l in open('/proc/self/status') if l.startswith('VmPeak')][0])\n"
    )
    env = {**os.environ, **thread_env()}
    out = subprocess.run([python, "-c", code, *modules], env=env, capture_output=True, text=True, timeout=120)
    if out.returncode != 0:
        raise ProcessorError(f"could not measure the address-space baseline: {out.stderr.strip()[-300:]}")
    return int(out.stdout.split()[-1]) / 1024.0


@dataclass(frozen=True)
class ProcessorSpec:
    """What the emulated processor imposes on the flight process.

    cpu_fraction: duty cycle in (0, 1]; 1.0 means no throttling.
    memory_mib: RSS ceiling (MiB) enforced by the watchdog; None = no ceiling.
    core: the host core to pin to; None = the highest-numbered core allowed to us.
    throttle_period_s: P, the stopped time per duty cycle (raised so that the
        running slice f P / (1 - f) is at least 1 ms).
    rss_poll_s: watchdog polling interval.
    address_space_mib: RLIMIT_AS in MiB; None = baseline + memory_mib + as_headroom_mib
        (no rlimit when memory_mib is None); 0 = no rlimit.
    as_headroom_mib: address space allowed beyond baseline + memory_mib (thread
        stacks, allocator slack) so that the RSS watchdog, not the rlimit, trips first.
    """

    cpu_fraction: float = 1.0
    memory_mib: float | None = None
    core: int | None = None
    throttle_period_s: float = 0.02
    rss_poll_s: float = 0.005
    address_space_mib: float | None = None
    as_headroom_mib: float = 256.0

    def __post_init__(self) -> None:
        f = self.cpu_fraction
        if isinstance(f, bool) or not isinstance(f, (int, float)) or not (MIN_CPU_FRACTION <= f <= 1.0):
            raise ProcessorError(f"cpu_fraction must be in [{MIN_CPU_FRACTION:g}, 1], got {f!r}")
        if self.memory_mib is not None and not (self.memory_mib > 0):
            raise ProcessorError(f"memory_mib must be > 0 or None, got {self.memory_mib!r}")
        if not (0.001 <= self.throttle_period_s <= 1.0):
            raise ProcessorError(f"throttle_period_s must be in [0.001, 1] s, got {self.throttle_period_s!r}")
        if not (0.0005 <= self.rss_poll_s <= 1.0):
            raise ProcessorError(f"rss_poll_s must be in [0.0005, 1] s, got {self.rss_poll_s!r}")
        if self.address_space_mib is not None and self.address_space_mib < 0:
            raise ProcessorError(f"address_space_mib must be >= 0 or None, got {self.address_space_mib!r}")
        if self.core is not None:
            allowed = os.sched_getaffinity(0)
            if self.core not in allowed:
                raise ProcessorError(f"core {self.core} is not available; allowed cores: {sorted(allowed)}")


@dataclass(frozen=True)
class ExitReport:
    """How the flight process ended.

    kind: "ok" | "error" | "crash" | "memory" | "killed" | "external".
    reason: one line for people; memory breaches start with "memory ceiling".
    """

    returncode: int
    signal: int | None
    reason: str
    peak_rss_mib: float
    cpu_s: float
    wall_s: float
    kind: str = "ok"
    stderr_tail: str = ""

    def __str__(self) -> str:
        return f"{self.kind}: {self.reason}"


def _read_schedstat(pid: int, per_task: dict[int, tuple[int, int]]) -> tuple[int, int]:
    """Total (on-CPU ns, run-queue-wait ns) over the threads of ``pid``.

    Threads that have exited keep their last reading in ``per_task``, so the sum
    never goes backwards when a worker thread ends.
    """
    try:
        tids = os.listdir(f"/proc/{pid}/task")
    except OSError:
        tids = []
    for tid in tids:
        try:
            with open(f"/proc/{pid}/task/{tid}/schedstat", "rb") as fh:
                run, wait, _ = fh.read().split()
            per_task[int(tid)] = (int(run), int(wait))
        except (OSError, ValueError):
            continue
    run_ns = sum(v[0] for v in per_task.values())
    wait_ns = sum(v[1] for v in per_task.values())
    return run_ns, wait_ns


def _runnable(pid: int) -> bool:
    """Whether a thread of ``pid`` is running or waiting for a CPU (state ``R`` in ``/proc/PID/task/TID/stat``).

    schedstat's run-queue wait grows only when a waiting task gets the CPU back: a child queued behind other
    jobs shows neither CPU nor wait progress for a while, as an idle one does; its state tells them apart."""
    try:
        tids = os.listdir(f"/proc/{pid}/task")
    except OSError:
        return False
    return any(_stat_fields(f"/proc/{pid}/task/{tid}/stat")[:1] == [b"R"] for tid in tids)


def tree_private_bytes(pid: int, mem: tuple[int, int], members: list[int]) -> tuple[int, int, int]:
    """(the flight process's share, its child processes' share, the tree's peak estimate) of private memory, in
    bytes; ``mem`` is :func:`private_rss_bytes` of ``pid``.

    With children the shares are proportional (:func:`flight_sw.memory.proportional_private_bytes`): a forked
    child's RssAnon holds every page it still shares with the flight process, and a 48 MiB program that forked
    was read as 122 MiB. A child caught between ``vfork`` and ``exec`` shares the flight process's whole address
    space and is still read twice, for the microseconds it lasts. Where the kernel gives no proportional split,
    the children's RssAnon is added as it is.
    """
    if not members:
        return mem[0], 0, mem[1]
    shares = [proportional_private_bytes(p) for p in (pid, *members)]
    if shares[0] is None:  # no smaps_rollup split here (or the process just left): the plain sum
        extra = sum((private_rss_bytes(p) or (0, 0))[0] for p in members)
        return mem[0], extra, mem[1] + extra
    own, extra = shares[0], sum(s or 0 for s in shares[1:])
    return own, extra, max(mem[1], own + extra)


class TreeMemory:
    """:func:`tree_private_bytes` at most every ``every_s``: ``smaps_rollup`` costs ~0.7 ms of CPU a process
    (``status`` 0.03 ms), which at the watch's 5 ms poll took 15-20 % of a core for each child (review of stop 79).
    Between two readings the plain RssAnon figures' change since the last one is added to its shares: a page
    touched since is private until a fork shares it. Other children than at the last reading are read at once (a
    new fork's RssAnon holds every page it shares)."""

    def __init__(self, every_s: float) -> None:
        self.every_s = every_s
        self.at = -math.inf
        self.last: tuple[int, int, int, int] | None = None  # (own share, children's, own RssAnon, children's)
        self.members: list[int] = []

    def read(self, pid: int, mem: tuple[int, int], members: list[int], now: float) -> tuple[int, int, int]:
        """(the flight process's share, its children's, the tree's peak estimate) in bytes, as
        :func:`tree_private_bytes`."""
        if not members:
            self.last = None
            return mem[0], 0, mem[1]
        plain = sum((private_rss_bytes(p) or (0, 0))[0] for p in members)
        if self.last is None or now - self.at >= self.every_s or members != self.members:
            own, extra, peak = tree_private_bytes(pid, mem, members)
            self.last, self.at, self.members = (own, extra, mem[0], plain), now, list(members)
            return own, extra, peak
        own0, extra0, plain_own0, plain0 = self.last
        own, extra = max(0, own0 + mem[0] - plain_own0), max(0, extra0 + plain - plain0)
        return own, extra, max(mem[1], own + extra)


def descendants(pid: int) -> list[int]:
    """The processes ``pid`` started, and theirs, from ``/proc/PID/task/TID/children`` (a flight program's worker
    processes run on its budget too; one that left the process group with ``setsid`` is still found here while
    its parent lives)."""
    out: list[int] = []
    todo = [pid]
    while todo and len(out) < MAX_DESCENDANTS:
        p = todo.pop()
        try:
            tids = os.listdir(f"/proc/{p}/task")
        except OSError:
            continue
        for tid in tids:
            try:
                with open(f"/proc/{p}/task/{tid}/children", "rb") as fh:
                    kids = [int(k) for k in fh.read().split()]
            except (OSError, ValueError):
                continue
            out.extend(kids)
            todo.extend(kids)
    return out[:MAX_DESCENDANTS]


def _stat_fields(path: str) -> list[bytes]:
    """The fields of a ``/proc/.../stat`` file after the command name (field 3, the state, first); [] when it is
    gone. The name sits in parentheses and may hold spaces and ')': the fields follow the last ')'."""
    try:
        with open(path, "rb") as fh:
            return fh.read().rsplit(b")", 1)[1].split()
    except (OSError, IndexError):
        return []


def _start_ticks(pid: int) -> int | None:
    """The process's start time (clock ticks since boot, /proc/PID/stat field 22): tells it from a reused PID."""
    fields = _stat_fields(f"/proc/{pid}/stat")
    try:
        return int(fields[19])
    except (ValueError, IndexError):
        return None


class _Child:
    """State of one started child; replaced on every start()."""

    def __init__(self, popen: subprocess.Popen, core: int, t0: float, group: bool = False) -> None:
        self.popen = popen
        self.pid = popen.pid
        self.group = group  # the child leads its own process group: signals go to the group
        # (pid, start ticks) of the processes it started, as the watchdog last saw them: they are throttled, their
        # memory counts, and they are killed with it (a reparented orphan is found again by its start time)
        self.members: tuple[tuple[int, int | None], ...] = ()
        self.core = core
        self.t0 = t0
        self.lock = threading.Lock()  # guards signals vs. reaping (no PID reuse races)
        self.exited = threading.Event()
        self.stop_threads = threading.Event()
        self.per_task: dict[int, tuple[int, int]] = {}
        self.cpu0_ns = self.wait0_ns = 0  # where the throttle's accounting starts
        self.cpu_ns = 0
        self.wait_ns = 0
        self.stopped = False
        self.stops = 0
        self.peak_rss = 0
        self.rss = 0
        self.kill_reason: str | None = None
        self.kill_kind: str | None = None
        self.report: ExitReport | None = None
        self.t_end: float | None = None
        self.stderr_tail: collections.deque[bytes] = collections.deque(maxlen=64)
        self.threads: list[threading.Thread] = []

    def kill(self, reason: str, kind: str) -> None:
        """SIGKILL the child (resumed first, so it never stays stopped); the first reason given is its exit's."""
        if self.kill_reason is None:
            self.kill_reason, self.kill_kind = reason, kind
        self.stop_threads.set()
        self.signal(signal.SIGCONT)
        self.signal(signal.SIGKILL)

    def sample(self) -> tuple[int, int]:
        for pid, _ in self.members:  # their tasks join per_task; the sum below covers them
            _read_schedstat(pid, self.per_task)
        run, wait = _read_schedstat(self.pid, self.per_task)
        self.cpu_ns = max(self.cpu_ns, run)
        self.wait_ns = max(self.wait_ns, wait)
        return self.cpu_ns, self.wait_ns

    def runnable(self) -> bool:
        """Whether the child or a process it started has a thread running or queued for the CPU (:func:`_runnable`)."""
        return any(_runnable(pid) for pid in (self.pid, *(p for p, _ in self.members)))

    def signal(self, sig: int) -> bool:
        """Send ``sig`` unless the child has been reaped (its PID may be reused then).

        SIGKILL goes to the child's whole process group (what it spawned dies with it).
        """
        with self.lock:
            if self.exited.is_set():
                return False
            try:
                if sig == signal.SIGKILL or (self.group and sig in (signal.SIGSTOP, signal.SIGCONT)):
                    os.killpg(self.pid, sig)  # the processes it started stop, run and die with it
                else:
                    os.kill(self.pid, sig)
            except ProcessLookupError:
                return False
            if self.group:
                self._signal_members(sig)
            if sig == signal.SIGSTOP:
                self.stopped, self.stops = True, self.stops + 1
            elif sig == signal.SIGCONT:
                self.stopped = False
            return True

    def _signal_members(self, sig: int) -> None:
        """``sig`` to the processes it started that left its group (``setsid``); the group got it already."""
        for pid, ticks in self.members:
            try:
                if os.getpgid(pid) != self.pid and _start_ticks(pid) == ticks:
                    os.kill(pid, sig)
            except (ProcessLookupError, PermissionError):
                continue


def on_slice_s(fraction: float, period_s: float = 0.02) -> tuple[float, float]:
    """(running slice, stopped time) per duty cycle at ``fraction``: P = max(period_s, MIN_ON_SLICE_S (1 - f) / f)
    stopped, then f P / (1 - f) running; (inf, 0) when not throttled."""
    if fraction >= 1.0:
        return math.inf, 0.0
    period = max(period_s, MIN_ON_SLICE_S * (1.0 - fraction) / fraction)
    return fraction * period / (1.0 - fraction), period


# A 1-DMIPS budget (budgets.MIN_CPU_DMIPS) on the fastest host a calibration may claim (budgets.MAX_UNITS_PER_S) is
# a duty of ~4e-8; its stops (a slice / f, ~1e5 s) are still far inside what time.sleep takes. A duty of 1e-299 (from
# an absurd calibration, refused now) overflowed it and killed the throttle thread.
MIN_CPU_FRACTION = 1e-8
LONG_STOP_S = 0.5  # a throttle stop longer than this ends early when the throttle is asked to stop


def duty_cycle(child: _Child, f: float, period_s: float) -> None:
    """SIGSTOP/SIGCONT ``child`` until it exits or ``child.stop_threads`` is set (module doc: the closed loop).

    CPU and wait time count from ``child.cpu0_ns`` / ``child.wait0_ns`` and wall time from ``child.t0``.
    """
    # Stopped time per cycle P, raised so the running slice f P / (1 - f) is >= MIN_ON_SLICE_S.
    _, period = on_slice_s(f, period_s)
    cap = f * period
    # Account from the child's start (or from when a Throttle took it over), not this thread's: CPU it used
    # before the first sample (exec, interpreter start-up) is paid back by a longer first stop.
    t0 = child.t0
    offset = 0.0  # credit dropped by the cap, so idle time is not banked
    last_avail = last_cpu = 0.0
    try:
        while not child.stop_threads.is_set() and not child.exited.is_set():
            cpu_ns, wait_ns = child.sample()
            avail = (time.monotonic() - t0) - (wait_ns - child.wait0_ns) / 1e9
            cpu = (cpu_ns - child.cpu0_ns) / 1e9
            credit = f * avail - cpu - offset
            # Cap only credit the child left unused while released and idle; credit
            # gained by our own late wake-ups while it was stopped is kept (no bias).
            # (judged over >= 1 ms: right after SIGCONT it has not had time to run yet).
            span = avail - last_avail
            idle = not child.stopped and span >= 0.001 and (cpu - last_cpu) < 0.5 * span
            last_avail, last_cpu = avail, cpu
            # a child queued behind other jobs looks idle by its counters (the kernel adds its wait only when it runs
            # again): its lost credit made it run under its budget on a busy host; its thread state tells
            if idle and credit > cap and not child.runnable():
                offset += credit - cap
                credit = cap
            if child.stopped:
                if credit >= cap:
                    child.signal(signal.SIGCONT)
                    continue
                # Stopped: credit grows at f per second. A long stop (a very slow budget: ~1 ms / f) waits on the
                # stop request, so that leaving the throttle does not take it whole (53 s at f = 1e-4)
                pause = max((cap - credit) / f, 0.0002)
                if pause > LONG_STOP_S:
                    child.stop_threads.wait(pause)
                else:
                    time.sleep(pause)
            else:
                if credit <= 0.0:
                    child.signal(signal.SIGSTOP)
                    continue
                # Running flat out, credit falls at (1 - f) per second.
                time.sleep(min(max(credit / (1.0 - f), 0.0002), period))
    except Exception as exc:  # a dead throttle would let the child run at full speed: a false pass on its budget
        child.kill(f"the CPU throttle failed ({type(exc).__name__}: {exc})", "crash")
    finally:
        child.signal(signal.SIGCONT)  # never leave it stopped


def flight_core() -> int:
    """The core the flight process is pinned to: the highest-numbered one allowed to this process."""
    return max(os.sched_getaffinity(0))


def hil_cores() -> frozenset[int]:
    """The cores the HIL's own processes keep to: every allowed core but :func:`flight_core`'s (none when only
    one is allowed: they then share it, as on a 1-core host)."""
    return frozenset(os.sched_getaffinity(0) - {flight_core()})


def keep_off_core(core: int) -> frozenset[int]:
    """Move every thread of this process to the allowed cores but ``core`` (threads started later inherit it from
    the one that starts them); returns the cores it now runs on (the allowed ones, unchanged, when ``core`` is the
    only one). ``sched_setaffinity`` sets one thread's mask, so each of ``/proc/self/task`` is set."""
    allowed = os.sched_getaffinity(0)
    rest = allowed - {core}
    if not rest:
        return frozenset(allowed)
    for tid in os.listdir("/proc/self/task"):
        try:
            os.sched_setaffinity(int(tid), rest)
        except (ProcessLookupError, PermissionError):  # a thread that ended meanwhile
            pass
    return frozenset(os.sched_getaffinity(0))


def start_at_full_speed(argv: list[str], **popen_kwargs) -> subprocess.Popen:
    """Start ``argv`` unthrottled on the core :class:`EmulatedProcessor` would use (the highest allowed), with the
    single-threaded environment of :func:`thread_env`: a probe that warms up at full speed before a
    :class:`Throttle` takes it over."""
    core = flight_core()
    env = {**os.environ, **thread_env()}
    prctl = libc_prctl()
    starter = os.getpid()

    def preexec() -> None:  # between fork and exec: async-signal-safe calls only
        # its own process group: stopped by the throttle, in its starter's group it got the kernel's SIGHUP when a
        # launching shell exited and left that group orphaned (`run ... &` from a script; QA of stop 73)
        os.setpgid(0, 0)
        # SIGKILL when its starter dies: a throttled probe is stopped half the time, and a SIGTERM would wait on
        # a SIGCONT that never comes (a `run` killed during its throttle check left it stopped, orphaned; stop 63)
        if prctl is not None:
            prctl(PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0)
            if os.getppid() != starter:  # it died before the death signal was set: nothing would send it
                os._exit(1)
        os.sched_setaffinity(0, {core})

    return subprocess.Popen(argv, env=env, preexec_fn=preexec, **popen_kwargs)


class Throttle:
    """Duty-cycle a process that is already running, from now on, until the ``with`` block ends.

    :class:`EmulatedProcessor` throttles its child from exec; this is for a probe that must start (import,
    warm up) at full speed first, as the calibration's throttle-efficiency measurement does
    (:func:`hil_server.calibrate.measure_throttle_efficiency`). The process is not reaped here.
    """

    def __init__(self, popen: subprocess.Popen, fraction: float, period_s: float = 0.02) -> None:
        ProcessorSpec(cpu_fraction=fraction, throttle_period_s=period_s)  # the same checks
        self.fraction, self.period_s = float(fraction), float(period_s)
        self._child = _Child(popen, -1, time.monotonic())
        self._thread: threading.Thread | None = None

    def __enter__(self) -> Throttle:
        c = self._child
        c.t0 = time.monotonic()
        c.cpu0_ns, c.wait0_ns = c.sample()
        if self.fraction < 1.0:
            self._thread = threading.Thread(target=duty_cycle, args=(c, self.fraction, self.period_s), daemon=True)
            self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._child.stop_threads.set()
        if self._thread is not None:
            self._thread.join()
        self._child.signal(signal.SIGCONT)


class EmulatedProcessor:
    """Runs one flight process at a time under a :class:`ProcessorSpec`.

    ``start`` may be called again once the previous child has exited (a fresh
    child, fresh statistics). Throttle, RSS watchdog and reaper are daemon
    threads of the calling process; an atexit hook resumes and kills a child
    still running when the supervisor exits.
    """

    def __init__(self, spec: ProcessorSpec) -> None:
        if not isinstance(spec, ProcessorSpec):
            raise ProcessorError(f"spec must be a ProcessorSpec, got {type(spec).__name__}")
        self.spec = spec
        self._child: _Child | None = None
        self._baseline_vms_mib: float | None = None
        self._atexit_registered = False
        self.unlogged_bytes = 0  # the children's output past the log's cap, known once each one's pipe ended

    # --- lifecycle -----------------------------------------------------------------------

    @property
    def pid(self) -> int | None:
        return self._child.pid if self._child else None

    @property
    def alive(self) -> bool:
        return self._child is not None and not self._child.exited.is_set()

    @property
    def core(self) -> int:
        return self.spec.core if self.spec.core is not None else flight_core()

    def address_space_limit_mib(self) -> float | None:
        """RLIMIT_AS the child gets (None: unlimited); measures the baseline once per emulator."""
        s = self.spec
        if s.address_space_mib is not None:
            return s.address_space_mib or None
        if s.memory_mib is None:
            return None
        if self._baseline_vms_mib is None:
            self._baseline_vms_mib = measure_baseline_vms_mib()
        return self._baseline_vms_mib + s.memory_mib + s.as_headroom_mib

    def start(
        self,
        argv: list[str],
        env: dict | None = None,
        pass_fds: tuple[int, ...] = (),
        merge_stdout: bool = False,
        **popen_kwargs,
    ) -> subprocess.Popen:
        """Start ``argv`` on the emulated processor and return its Popen.

        ``env`` (default: this process's environment) is overlaid with
        :func:`thread_env`. stderr is forwarded to ours line by line while its
        tail is kept to classify failed allocations; pass ``stderr=`` to override. At most
        :data:`MAX_FORWARDED_BYTES` are forwarded; the rest is counted. ``merge_stdout`` sends the child's stdout
        the same way (a program of the user's, whose prints would otherwise go unbounded to ours).
        """
        if self.alive:
            raise ProcessorError(f"a flight process (pid {self.pid}) is still running; kill or wait for it first")
        if not argv or not all(isinstance(a, str) for a in argv):
            raise ProcessorError(f"argv must be a non-empty list of strings, got {argv!r}")
        self._join_threads()
        core = self.core
        as_mib = self.address_space_limit_mib()
        as_bytes = int(as_mib * MIB) if as_mib else None
        child_env = dict(os.environ if env is None else env)
        child_env.update(thread_env())
        prctl = libc_prctl()

        def preexec() -> None:  # runs in the child between fork and exec: async-signal-safe calls only
            os.setpgid(0, 0)  # its own process group: killed as a whole, untouched by the terminal's Ctrl-C
            if merge_stdout:  # after Popen's own redirections: stdout joins the captured (and bounded) stderr
                os.dup2(2, 1)
            if prctl is not None:
                prctl(PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0)
            os.sched_setaffinity(0, {core})
            if as_bytes is not None:
                resource.setrlimit(resource.RLIMIT_AS, (as_bytes, as_bytes))

        capture = "stderr" not in popen_kwargs
        if capture and any(popen_kwargs.get(k) for k in ("text", "universal_newlines", "encoding", "errors")):
            raise ProcessorError("text mode would decode the captured stderr too: read bytes and decode them yourself")
        if capture:
            popen_kwargs["stderr"] = subprocess.PIPE
        try:
            popen = subprocess.Popen(
                argv, env=child_env, pass_fds=tuple(pass_fds), preexec_fn=preexec, close_fds=True, **popen_kwargs
            )
        except (OSError, subprocess.SubprocessError) as exc:
            raise ProcessorError(f"cannot start {argv[0]!r}: {exc}") from None
        child = _Child(popen, core, time.monotonic(), group=True)
        self._child = child
        if not self._atexit_registered:
            atexit.register(self._atexit)
            self._atexit_registered = True
        threads = [threading.Thread(target=self._reaper, args=(child,), name=f"procemu-reap-{child.pid}", daemon=True)]
        if capture:
            threads.append(
                threading.Thread(
                    target=self._stderr_pump, args=(child,), name=f"procemu-stderr-{child.pid}", daemon=True
                )
            )
        # The watchdog runs without a ceiling too: it keeps the peak RSS.
        threads.append(
            threading.Thread(target=self._watchdog, args=(child,), name=f"procemu-rss-{child.pid}", daemon=True)
        )
        if self.spec.cpu_fraction < 1.0:
            threads.append(
                threading.Thread(
                    target=self._throttle, args=(child,), name=f"procemu-throttle-{child.pid}", daemon=True
                )
            )
        child.threads = threads
        # the reaper last: a child that exits at once must not find the stderr pump unstarted (it joins it, and
        # a join before start raised, leaving the exit unclassified until the heartbeat watchdog caught it)
        for t in threads[1:] + threads[:1]:
            t.start()
        return popen

    def kill(self, reason: str) -> None:
        """SIGKILL the child (resumed first, so it never stays stopped) and record ``reason``."""
        self._kill(reason, "killed")

    def _kill(self, reason: str, kind: str) -> None:
        child = self._child
        if child is None or child.exited.is_set():
            return
        child.kill(reason, kind)

    def wait(self, timeout: float | None = None) -> ExitReport | None:
        """Wait up to ``timeout`` s for the child to end; its report, or None if still running."""
        child = self._child
        if child is None:
            return None
        if not child.exited.wait(timeout):
            return None
        for t in child.threads:
            if t is not threading.current_thread():
                t.join(timeout=1.0)
        return child.report

    def poll(self) -> ExitReport | None:
        return self.wait(0)

    def close(self) -> None:
        """Stop the helper threads; kill the child if it is still running."""
        child = self._child
        if child is not None and not child.exited.is_set():
            self._kill("closed by supervisor", "killed")
            child.exited.wait(5.0)
        self._join_threads()
        if self._atexit_registered:
            atexit.unregister(self._atexit)
            self._atexit_registered = False

    def _atexit(self) -> None:
        child = self._child
        if child is not None and not child.exited.is_set():
            child.signal(signal.SIGCONT)
            child.signal(signal.SIGKILL)

    def _join_threads(self) -> None:
        child = self._child
        if child is None:
            return
        child.stop_threads.set()
        for t in child.threads:
            if t is not threading.current_thread():
                t.join(timeout=2.0)

    def __enter__(self) -> EmulatedProcessor:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # --- measurements ------------------------------------------------------------------

    def stats(self) -> dict:
        """cpu_s, wall_s, achieved_fraction, peak_rss_mib, rss_mib, core (+ contention_s,
        raw_fraction, stops, stopped, target_fraction). Zeros before the first start."""
        child = self._child
        if child is None:
            return dict(
                cpu_s=0.0,
                wall_s=0.0,
                achieved_fraction=0.0,
                peak_rss_mib=0.0,
                rss_mib=0.0,
                core=self.core,
                contention_s=0.0,
                raw_fraction=0.0,
                stops=0,
                stopped=False,
                target_fraction=self.spec.cpu_fraction,
            )
        if not child.exited.is_set():
            child.sample()
            mem = private_rss_bytes(child.pid)
            if mem is not None:
                child.rss = mem[0]
                child.peak_rss = max(child.peak_rss, mem[1])
        end = child.t_end if child.t_end is not None else time.monotonic()
        wall = end - child.t0
        cpu = child.cpu_ns / 1e9
        contention = min(child.wait_ns / 1e9, wall)
        avail = wall - contention
        return dict(
            cpu_s=cpu,
            wall_s=wall,
            achieved_fraction=cpu / avail if avail > 0 else 0.0,
            peak_rss_mib=child.peak_rss / MIB,
            rss_mib=(0.0 if child.exited.is_set() else child.rss / MIB),
            core=child.core,
            contention_s=contention,
            raw_fraction=cpu / wall if wall > 0 else 0.0,
            stops=child.stops,
            stopped=child.stopped,
            target_fraction=self.spec.cpu_fraction,
        )

    # --- helper threads -------------------------------------------------------------------

    def _throttle(self, child: _Child) -> None:
        duty_cycle(child, self.spec.cpu_fraction, self.spec.throttle_period_s)

    def _watchdog(self, child: _Child) -> None:
        """The memory ceiling's watch (and the member scan); if it fails, the child is killed with the reason: running
        on without its ceiling would pass a budget it never ran on, as a dead throttle would."""
        try:
            self._watch_memory(child)
        except Exception as exc:
            self._kill(f"the memory ceiling's watch failed ({type(exc).__name__}: {exc})", "crash")

    def _watch_memory(self, child: _Child) -> None:
        limit = self.spec.memory_mib * MIB if self.spec.memory_mib is not None else None
        poll = self.spec.rss_poll_s
        every = max(1, round(MEMBER_SCAN_S / poll))
        tree = TreeMemory(MEMBER_SCAN_S)
        n = 0
        while not child.exited.is_set():
            if n % every == 0:  # the process tree changes rarely: rescanned every MEMBER_SCAN_S
                child.members = tuple((pid, _start_ticks(pid)) for pid in descendants(child.pid))
            n += 1
            mem = private_rss_bytes(child.pid)
            if mem is not None:
                # the memory of the processes it started counts against the same ceiling
                own, extra, peak = tree.read(child.pid, mem, [pid for pid, _ in child.members], time.monotonic())
                child.rss = own + extra
                child.peak_rss = max(child.peak_rss, peak)
                if limit is not None and child.rss > limit:
                    who = f" (its {len(child.members)} child process(es) hold {extra / MIB:.1f})" if extra else ""
                    why = f"memory ceiling: private RSS {child.rss / MIB:.1f} MiB{who} > {self.spec.memory_mib:g} MiB"
                    self._kill(why, "memory")
                    return
            if child.stop_threads.wait(poll):
                return

    def _stderr_pump(self, child: _Child) -> None:
        """The flight program's lines to this process's stderr, the first :data:`MAX_FORWARDED_BYTES` of them (a
        program printing in a loop filled an 82 MB log for two pairs), and their tail kept for the report."""
        from hil_server.pump import Sink, pump

        stream = child.popen.stderr
        assert stream is not None  # started with stderr=PIPE
        out = getattr(sys.stderr, "buffer", None)
        cap = MAX_FORWARDED_BYTES
        note = f"procemu: {{}} more bytes of the flight process's output were not logged (the first {cap >> 20} MiB "
        note += "were)\n"

        def over(n: int) -> bytes:
            self.unlogged_bytes += n  # counted here, not read back from the log a flight program writes into
            return note.format(n).encode()

        sinks = [] if out is None else [Sink(out.write, cap, over, out.flush)]
        pump(stream, sinks, on_line=lambda line: child.stderr_tail.append(line[-2000:]))

    def _reaper(self, child: _Child) -> None:
        # Wait without reaping, so no signal can hit a reused PID; then reap under the lock.
        while True:
            try:
                os.waitid(os.P_PID, child.pid, os.WEXITED | os.WNOWAIT)
                break
            except ChildProcessError:
                break
            except InterruptedError:
                continue
        child.sample()
        with child.lock:
            try:
                _, status, usage = os.wait4(child.pid, 0)
            except ChildProcessError:
                status, usage = 0, None
            child.t_end = time.monotonic()
            child.stopped = False
            child.exited.set()
        child.stop_threads.set()
        if usage is not None:
            child.cpu_ns = max(child.cpu_ns, int((usage.ru_utime + usage.ru_stime) * 1e9))
        code = os.waitstatus_to_exitcode(status)
        child.popen.returncode = code  # keep Popen consistent: it must not wait again
        try:  # what the child left behind in its group (the group id stays reserved while any member lives)
            os.killpg(child.pid, signal.SIGKILL)
        except (ProcessLookupError, PermissionError):
            pass
        for pid, ticks in child.members:  # and what left the group (setsid), reparented by now: by start time
            try:
                if _start_ticks(pid) == ticks:
                    os.kill(pid, signal.SIGKILL)
            except (ProcessLookupError, PermissionError):
                continue
        for t in child.threads:
            if t is not threading.current_thread() and t.name.startswith("procemu-stderr"):
                t.join(timeout=2.0)  # the pipe drains once the child is gone
        child.report = self._classify(child, code)

    def _classify(self, child: _Child, code: int) -> ExitReport:
        sig = -code if code < 0 else None
        tail = b"".join(child.stderr_tail)[-4000:]
        if child.kill_reason is not None and sig == signal.SIGKILL:
            kind, reason = child.kill_kind or "killed", child.kill_reason
        elif sig is not None:
            name = signal.Signals(sig).name if sig in signal.Signals._value2member_map_ else f"signal {sig}"
            if sig in (
                signal.SIGSEGV,
                signal.SIGABRT,
                signal.SIGBUS,
                signal.SIGILL,
                signal.SIGFPE,
                signal.SIGSYS,
                signal.SIGTRAP,
            ):
                kind, reason = "crash", f"crash: killed by {name}"
            else:
                kind, reason = "external", f"external kill: {name}"
        elif code == 0:
            kind, reason = "ok", "exited normally"
        elif code == EXIT_MEMORY or any(m in tail for m in _MEMORY_MARKERS):
            marker = next((m.decode() for m in _MEMORY_MARKERS if m in tail), f"exit status {EXIT_MEMORY}")
            kind, reason = "memory", f"memory ceiling: allocation failed ({marker}; exit status {code})"
        else:
            last = tail.strip().splitlines()[-1].decode("utf-8", "replace")[:200] if tail.strip() else ""
            kind, reason = "error", f"error exit: status {code}" + (f" ({last})" if last else "")
        return ExitReport(
            returncode=code,
            signal=sig,
            reason=reason,
            peak_rss_mib=child.peak_rss / MIB,
            cpu_s=child.cpu_ns / 1e9,
            wall_s=(child.t_end or time.monotonic()) - child.t0,
            kind=kind,
            stderr_tail=tail.decode("utf-8", "replace"),
        )
