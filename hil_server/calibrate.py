"""Reference workload: a fixed slice of the flight software's own operation mix.

One *unit* is eight steps of a plane sweep on a 512x512 image pair (the thesis
camera, DESIGN.md): per step a plane-induced homography built in numpy with
ordinary Python overhead (H = K (R - t n^T / d) K^-1, DESIGN.md / thesis eq. 3.8),
``cv2.warpPerspective`` with bilinear interpolation (thesis section 4.2),
``cv2.absdiff`` and a 17x17 un-normalised ``cv2.boxFilter`` (the SAD window of
thesis section 4.3), then a winner-take-all update of the best cost and plane
index. The speed of a core is its rate in units per CPU-second on one thread.

The rate is measured on CPU time (``time.process_time``), not wall time, so
that other processes sharing the host shift it little; the median over many
units rejects the odd slow unit (cache eviction, frequency change).

**Throttle efficiency.** The emulated processor delivers a duty cycle of this
core in stop-and-go slices (:mod:`hil_server.procemu`): about 1 ms running
after 20-200 ms stopped at the slow budgets' duty cycles. Each slice starts
with its data evicted from the caches by whatever ran meanwhile, so a
CPU-second inside the throttle does less work than one at full speed:
on the 2026-12-04 host the reference workload took 1.20x its CPU at duty 0.2
with 1 ms slices, 1.51x at 0.05, 1.70x at 0.013 and 1.75x at 0.0063, and the
flight pipeline 1.43x at 0.05 (one run; the loss at short stops varies with the host's other
work, docs/hil.md section 4). A real flight
computer does not stop every millisecond, so
:func:`measure_throttle_efficiency` measures ``eta(f)`` = (CPU per unit at
full speed) / (CPU per unit throttled at duty f) over a grid of duty cycles,
and a budget's duty cycle is raised until ``f eta(f)`` is the fraction of
this core it stands for (:meth:`hil_server.budgets.Budget.duty`).
"""

from __future__ import annotations

import json
import math
import signal
import statistics
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

IMAGE_SIZE = 512
PLANES_PER_UNIT = 8
SAD_WINDOW = 17
_SEED = 20240611
# the duty cycles whose throttle efficiency `hazard-hil calibrate` measures (gr740's raised duty is ~0.011)
EFFICIENCY_FRACTIONS = (0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5)
MIN_EFFICIENCY_DUTY = 0.001  # `calibrate --duty-cycles`: a grid probe's wall time grows as 1 / duty, 1e-9 never ends
PROBE_UNITS = 3  # units per measurement; about 26 s for the whole grid, most of it at the lowest duty


@dataclass(frozen=True)
class WorkloadRate:
    """Result of a reference-workload run."""

    units_per_s: float  # median rate, units per CPU-second
    spread: float  # (p90 - p10) / median of the per-batch rates
    units: int  # units executed
    cpu_s: float  # CPU time spent
    checksum: int  # proves the work was done identically each time


def make_inputs(seed: int = _SEED) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Deterministic textured image pair (float32 in [0, 1]) and intrinsics K."""
    import cv2

    rng = np.random.default_rng(seed)
    noise = rng.random((IMAGE_SIZE, IMAGE_SIZE), dtype=np.float32)
    img1 = cv2.GaussianBlur(noise, (0, 0), 2.0)
    img2 = cv2.GaussianBlur(np.roll(noise, 3, axis=1), (0, 0), 2.0)
    f = 955.405
    c = (IMAGE_SIZE - 1) / 2.0
    K = np.array([[f, 0.0, c], [0.0, f, c], [0.0, 0.0, 1.0]])
    return img1, img2, K


def run_unit(img1: np.ndarray, img2: np.ndarray, K: np.ndarray) -> int:
    """One unit of work; returns a checksum of the winning plane indices."""
    import cv2

    Kinv = np.linalg.inv(K)
    n = np.array([0.0, 0.0, 1.0])
    R = np.eye(3)
    t = np.array([0.0, 0.0, -500.0])  # the lower camera, half the altitude of the upper
    best = np.full(img1.shape, np.inf, dtype=np.float32)
    index = np.zeros(img1.shape, dtype=np.int16)
    for k in range(PLANES_PER_UNIT):
        d = -1000.0 + 0.15 * k  # planes 15 cm apart, as the thesis's depth step
        H = K @ (R - np.outer(t, n) / d) @ Kinv
        H /= H[2, 2]
        warped = cv2.warpPerspective(img2, H, (IMAGE_SIZE, IMAGE_SIZE), flags=cv2.INTER_LINEAR)
        sad = cv2.boxFilter(cv2.absdiff(img1, warped), -1, (SAD_WINDOW, SAD_WINDOW), normalize=False)
        better = sad < best
        best = np.where(better, sad, best)
        index[better] = k
    return int(index.astype(np.int64).sum() % 1_000_003)


def measure_rate(seconds: float = 1.0, batch: int = 2) -> WorkloadRate:
    """Run units on one OpenCV thread for about ``seconds`` of CPU time.

    rate = batch / (CPU time of the batch), median over batches.
    """
    import cv2

    if not seconds > 0:
        raise ValueError(f"seconds must be > 0, got {seconds}")
    img1, img2, K = make_inputs()
    previous_threads = cv2.getNumThreads()
    cv2.setNumThreads(1)  # one emulated core: never let OpenCV fan out
    try:
        checksum = run_unit(img1, img2, K)  # warm-up: caches, lazy init
        rates: list[float] = []
        units = 0
        start = time.process_time()
        while True:
            t0 = time.process_time()
            for _ in range(batch):
                if run_unit(img1, img2, K) != checksum:
                    raise RuntimeError("reference workload is not deterministic")
            dt = time.process_time() - t0
            units += batch
            rates.append(batch / max(dt, 1e-9))
            if time.process_time() - start >= seconds and len(rates) >= 3:
                break
        cpu_s = time.process_time() - start
    finally:
        cv2.setNumThreads(previous_threads)
    rates.sort()
    median = statistics.median(rates)
    p10 = rates[int(0.1 * (len(rates) - 1))]
    p90 = rates[int(round(0.9 * (len(rates) - 1)))]
    return WorkloadRate(median, (p90 - p10) / median, units, cpu_s, checksum)


def _probe(units: int) -> int:
    """The probe process: warm up, then time units (CPU s each, one JSON list per line): ``units`` at once, then
    as many as each line read from stdin says (``units`` when it says none)."""
    import cv2

    cv2.setNumThreads(1)
    img1, img2, K = make_inputs()
    checksum = run_unit(img1, img2, K)

    def batch(n: int) -> list[float]:
        out = []
        for _ in range(n):
            t0 = time.process_time()
            if run_unit(img1, img2, K) != checksum:
                raise RuntimeError("reference workload is not deterministic")
            out.append(time.process_time() - t0)
        return out

    print(json.dumps(batch(units)), flush=True)
    for line in sys.stdin:
        words = line.split()
        print(json.dumps(batch(int(words[1]) if len(words) > 1 else units)), flush=True)
    return 0


# `calibrate` times at least this much throttled wall time per duty cycle: at the high duty cycles the calibration's
# 3 units last 0.1-0.9 s, and one batch that short read eta 0.82-0.95 at f = 0.5 on one idle host (stop 57)
MIN_BATCH_WALL_S = 1.0
MAX_UNITS = 40


class EfficiencyProbe:
    """A probe process for eta, the work a throttled CPU-second does (module doc), as a context manager.

    It runs on the core the emulated processor uses (the highest allowed) and warms up at full speed on entry.
    Each :meth:`eta` is one round: a batch under the throttle, then one at full speed; eta = median CPU per unit at
    full speed (the batches before and after) / median throttled, clipped to [0.05, 1] (above 1 is noise: no
    compensation; a throttle that wasted 95 % would be broken). A drift of the host's speed cancels. The probe is
    killed on exit.
    """

    def __init__(self, units: int = PROBE_UNITS, period_s: float = 0.02) -> None:
        if units < 1:
            raise ValueError(f"units must be >= 1, got {units}")
        self.units, self.period_s = int(units), float(period_s)
        self._popen: subprocess.Popen | None = None
        self._full: list[float] = []

    def __enter__(self) -> EfficiencyProbe:
        from hil_server.procemu import start_at_full_speed

        self._popen = start_at_full_speed(
            [sys.executable, "-m", "hil_server.calibrate", "--probe", str(self.units)],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
        )
        try:
            self._full = self._batch(None)
        except BaseException:
            self.__exit__()
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        if self._popen is not None:
            self._popen.kill()
            self._popen.wait()

    def _batch(self, n: int | None) -> list[float]:
        popen = self._popen
        assert popen is not None and popen.stdin is not None and popen.stdout is not None
        if n is not None:
            popen.stdin.write(f"go {n}\n")
            popen.stdin.flush()
        line = popen.stdout.readline()
        if not line:
            code = popen.wait()
            how = f"killed by {signal.Signals(-code).name}" if code < 0 else f"exit {code}"
            raise RuntimeError(f"the throttle-efficiency probe ended ({how})")
        return [float(x) for x in json.loads(line)]

    @property
    def units_per_s(self) -> float:
        """The reference workload's rate at full speed in the latest batch: units per CPU-second (the median's)."""
        return 1.0 / max(statistics.median(self._full), 1e-9) if self._full else math.nan

    def eta(self, fraction: float, min_wall_s: float = 0.0) -> float:
        """One round at duty cycle ``fraction`` in (0, 1): batches of ``units`` units, more when they would take
        less than ``min_wall_s`` under the throttle (at most :data:`MAX_UNITS`)."""
        from hil_server.procemu import Throttle

        # any duty in (0, 1): `run`'s check of a very slow budget measures at its own duty with few units
        # (budgets.throttle_check_units); MIN_EFFICIENCY_DUTY bounds only `calibrate --duty-cycles`' grid
        if not 0.0 < fraction < 1.0:
            raise ValueError(f"duty cycles must be in (0, 1), got {fraction!r}")
        assert self._popen is not None, "use the probe in a with block"
        per_unit = max(statistics.median(self._full), 1e-6)
        n = max(self.units, min(MAX_UNITS, math.ceil(min_wall_s * fraction / per_unit)))
        with Throttle(self._popen, fraction, self.period_s):
            throttled = self._batch(n)
        after = self._batch(n)
        eta = statistics.median(self._full + after) / statistics.median(throttled)
        self._full = after
        return min(1.0, max(0.05, eta))


def measure_throttle_efficiency(
    fractions: Sequence[float] = EFFICIENCY_FRACTIONS,
    units: int = PROBE_UNITS,
    period_s: float = 0.02,
    progress: Callable[[str], None] | None = None,
    min_wall_s: float = MIN_BATCH_WALL_S,
) -> tuple[tuple[float, float], ...]:
    """``(f, eta(f))`` per duty cycle (module doc): one :meth:`EfficiencyProbe.eta` round each on one probe, the
    quick ones first, each timing at least ``min_wall_s`` under the throttle."""
    if not fractions or not all(0.0 < f < 1.0 for f in fractions):
        raise ValueError(f"duty cycles must be in (0, 1), got {fractions!r}")
    if units < 1:
        raise ValueError(f"units must be >= 1, got {units}")
    out: list[tuple[float, float]] = []
    with EfficiencyProbe(units, period_s) as probe:
        for f in sorted(fractions, reverse=True):
            t0 = time.monotonic()
            eta = probe.eta(f, min_wall_s)
            out.append((float(f), eta))
            if progress is not None:
                took = time.monotonic() - t0
                progress(f"duty {f:g}: a throttled CPU-second does {eta:.2f} of a full-speed one ({took:.0f} s)")
    return tuple(sorted(out))


if __name__ == "__main__":
    if len(sys.argv) == 3 and sys.argv[1] == "--probe":
        import signal

        signal.signal(signal.SIGINT, signal.SIG_IGN)  # a terminal's Ctrl-C is the parent's to act on: it ends us
        sys.exit(_probe(int(sys.argv[2])))
    r = measure_rate(3.0)
    print(f"{r.units_per_s:.3f} units/s (spread {r.spread:.1%}, {r.units} units, checksum {r.checksum})")
