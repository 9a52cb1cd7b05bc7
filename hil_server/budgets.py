"""Processor budgets and per-host calibration.

A budget names a flight computer by absolute single-core speed in DMIPS
(``budgets.toml`` says where each figure comes from). To emulate it here the
flight process gets a CPU duty cycle

    duty = min(1, cpu_dmips / host_dmips),
    host_dmips = anchor_dmips * host_rate / anchor_rate,

where ``host_rate`` is this host's single-core rate on the reference workload
(:mod:`hil_server.calibrate`) and the anchor is a machine of known speed on which
the same workload was measured (recorded in ``budgets.toml``). So a budget means
the same on any host; a faster host simply gets a smaller duty cycle.

That ``duty`` is the *effective* fraction of this core the budget stands for. The
throttle's stop-and-go slices make each CPU-second it grants worth only
``eta(f) < 1`` of a full-speed one (cold caches after every stop;
:mod:`hil_server.calibrate`, "Throttle efficiency"), so the duty cycle applied is
the ``f`` with ``f eta(f) = duty`` (:meth:`Budget.duty`), ``eta`` interpolated in
log f between the calibration's measured points. The flight is told the
slowdown ``1 / duty``, what a real computer of that speed would show.

``hazard-hil calibrate`` measures ``host_rate`` and stores it per host (hostname
+ CPU model) in ``$HAZARD_HIL_HOME/calibration.json`` (default
``~/.cache/hazard-hil/``). Without a calibration the host is assumed to be as
fast as the anchor, with an :class:`UncalibratedWarning`.
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import itertools
import json
import math
import os
import platform
import socket
import sys
import tomllib
import warnings
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from importlib import resources
from pathlib import Path

from protocol.errors import InputError
from protocol.linkspec import BAUD_MAX, BAUD_MIN, DEFAULT_BAUD

LINKS = ("zmq", "serial")


class BudgetError(InputError):
    """A budget or calibration file is malformed, or a budget name is unknown."""


class UncalibratedWarning(UserWarning):
    """Duty cycles are computed without a calibration of this host."""


# set to "1" in the environment of a run's own processes (its supervisor and ground): the run has said the host is
# uncalibrated once, and each of them said it again (three warnings per run; QA of stop 73)
UNCALIBRATED_SAID = "HAZARD_HIL_UNCALIBRATED_SAID"


@dataclass(frozen=True)
class Anchor:
    """The reference machine: its speed in DMIPS and its reference-workload rate."""

    description: str
    dmips: float
    units_per_s: float
    coremark: float | None = None
    coremark_per_dmips: float | None = None


@dataclass(frozen=True)
class HostCalibration:
    """This host's single-core rate on the reference workload."""

    key: str  # hostname|cpu model: what the calibration is valid for
    hostname: str
    cpu_model: str
    units_per_s: float  # median reference-workload rate, units per CPU-second
    spread: float  # (p90 - p10) / median over the measurement batches
    seconds: float  # CPU seconds measured
    measured_at: str  # ISO 8601, UTC
    # the libraries the reference workload ran on ("" in calibrations stored before they were recorded): the
    # workload is OpenCV and numpy code, so a new version of either can change the rate on the same core
    libraries: str = ""
    # (duty cycle, eta) measured by the calibration, ascending (module doc); () in calibrations stored before
    # stop 47, which then run slow budgets up to ~1.8x slower than they stand for
    throttle_efficiency: tuple[tuple[float, float], ...] = ()

    def host_dmips(self, anchor: Anchor) -> float:
        """host_dmips = anchor.dmips * units_per_s / anchor.units_per_s."""
        return anchor.dmips * self.units_per_s / anchor.units_per_s

    def efficiency(self, fraction: float) -> float:
        """eta(fraction): linear in log f between the measured points made non-decreasing in f
        (:func:`monotone_efficiency`) and (1, 1), the end value beyond them; 1 when nothing was measured."""
        pts = monotone_efficiency([(f, e) for f, e in self.throttle_efficiency if f < 1.0]) + [(1.0, 1.0)]
        if fraction >= 1.0 or len(pts) == 1:
            return 1.0
        if fraction <= pts[0][0]:
            return pts[0][1]
        for (f0, e0), (f1, e1) in itertools.pairwise(pts):
            if fraction <= f1:
                w = math.log(fraction / f0) / math.log(f1 / f0)
                return e0 + w * (e1 - e0)
        return 1.0  # unreachable: the last point is f = 1

    def rescaled(self, fraction: float, eta: float) -> HostCalibration:
        """This calibration with its efficiency curve scaled so that ``efficiency(fraction) = eta`` (each point
        x ``eta / efficiency(fraction)``, clipped to [0.05, 1]). What else the host runs changes how cold every
        slice starts, at every duty cycle alike; :class:`ThrottleCheck` measures it at one. Unchanged when nothing
        was calibrated."""
        if not self.throttle_efficiency or not (math.isfinite(eta) and eta > 0):
            return self
        k = eta / self.efficiency(fraction)
        pts = tuple((f, min(1.0, max(0.05, e * k))) for f, e in self.throttle_efficiency)
        return replace(self, throttle_efficiency=pts)


# Below this duty cycle a run checks the throttle's efficiency first (ThrottleCheck): above it a throttled
# CPU-second loses a few % at most (docs/benchmarks/throttle.md section 5), and the check would cost more than
# it corrects.
THROTTLE_CHECK_MAX_DUTY = 0.1
# Adopted only beyond this relative difference, confirmed by a second round (THROTTLE_CHECK_ROUNDS)
THROTTLE_CHECK_TOLERANCE = 0.1
# Rounds a check may measure: a first one beyond the tolerance is measured again, and adopted only when the second
# confirms it. One round of 3 units read eta 0.55, 0.76, 0.73 and 0.55 at rad750's duty within 25 minutes of one
# idle host (calibration: 0.76); each low reading adopted ran rad750 1.6x faster than the others, and faster than it
# stands for (stop 56's budget QA): a single round's spread is as wide as the tolerance.
THROTTLE_CHECK_ROUNDS = 2
# the host's full-speed rate now against its calibration's: beyond this the run says the budget runs that much faster or
# slower than it stands for (this VM's rate moved 2.3x between two calibrations, docs/hil.md section 4; one probe
# batch of 3 units reads within about 12 % of the calibration's median on a quiet host)
HOST_RATE_TOLERANCE = 0.2


@dataclass(frozen=True)
class ThrottleCheck:
    """The throttle's efficiency measured again at one duty cycle, just before a run (docs/hil.md section 4).

    The loss a throttled slice suffers depends on what else the host runs, so it drifts: on one idle host the
    calibration measured eta 0.79-0.83 at 0.5-1 % duty and, half an hour later, 0.62-0.66, and rad750 then ran our
    pipeline 1.26x slower than it stands for (stop 48). A run on a slow budget measures eta at its duty cycle
    first. When a round differs from the calibration by more than :data:`THROTTLE_CHECK_TOLERANCE`, a second round
    is measured; when both do, on the same side, the budget runs on the calibration rescaled to their mean
    (:meth:`HostCalibration.rescaled`). One round alone is as noisy as the tolerance is wide."""

    duty: float  # the duty cycle checked: the one the calibration gives the budget
    calibrated: float  # eta there by the stored calibration
    rounds: tuple[float, ...]  # eta there now, per round measured
    # the reference workload's full-speed rate (units per CPU-second) the probe measured now, and the calibration's:
    # eta is a ratio of the two speeds of one minute, so it cannot see the host itself run faster or slower
    host_rate: float = math.nan
    calibrated_rate: float = math.nan

    @property
    def rate_ratio(self) -> float:
        """The host's full-speed rate now over its calibration's (:func:`rate_ratio`)."""
        return rate_ratio(self.host_rate, self.calibrated_rate)

    @property
    def measured(self) -> float:
        """The mean of the rounds."""
        return sum(self.rounds) / len(self.rounds) if self.rounds else math.nan

    def beyond(self, eta: float) -> int:
        """+1 / -1 when ``eta`` lies beyond the tolerance above / below the calibration, else 0."""
        r = eta / self.calibrated - 1.0
        return 0 if abs(r) <= THROTTLE_CHECK_TOLERANCE else (1 if r > 0 else -1)

    @property
    def confirmed(self) -> bool:
        """True when another round would not change the verdict: one within the tolerance, or the rounds' limit."""
        return len(self.rounds) >= THROTTLE_CHECK_ROUNDS or (len(self.rounds) == 1 and not self.beyond(self.rounds[0]))

    @property
    def adopted(self) -> bool:
        sides = {self.beyond(e) for e in self.rounds}
        return len(self.rounds) >= THROTTLE_CHECK_ROUNDS and len(sides) == 1 and 0 not in sides

    def calibration(self, cal: HostCalibration) -> HostCalibration:
        """``cal`` rescaled to the measured efficiency when it is adopted, else ``cal``."""
        return cal.rescaled(self.duty, self.measured) if self.adopted else cal

    def to_dict(self) -> dict[str, float | bool | list[float] | None]:
        return {
            "duty": self.duty,
            "calibrated": self.calibrated,
            "measured": self.measured,
            "rounds": list(self.rounds),
            "adopted": self.adopted,
            # null when not measured (JSON has no NaN)
            "host_rate": self.host_rate if math.isfinite(self.host_rate) else None,
            "calibrated_rate": self.calibrated_rate if math.isfinite(self.calibrated_rate) else None,
        }

    @classmethod
    def from_dict(cls, d: dict) -> ThrottleCheck:
        """What :meth:`to_dict` wrote; a record from before stop 57 holds one round, adopted alone (``adopted``)."""
        measured = float(d["measured"])
        rounds = tuple(float(e) for e in d.get("rounds", ()))
        if not rounds:
            rounds = (measured,) * (THROTTLE_CHECK_ROUNDS if d.get("adopted") else 1)
        rates = (  # since stop 82
            math.nan if d.get("host_rate") is None else float(d["host_rate"]),
            math.nan if d.get("calibrated_rate") is None else float(d["calibrated_rate"]),
        )
        return cls(float(d["duty"]), float(d["calibrated"]), rounds, *rates)


def calibration_drift(
    old: HostCalibration | None, new: HostCalibration, fractions: tuple[float, ...] = (0.01, 0.05)
) -> str:
    """One line on what moved since the last calibration of this host, "" when nothing moved beyond
    :data:`THROTTLE_CHECK_TOLERANCE`: the reference rate, and eta at ``fractions`` (rad750's and gr740's duty cycles
    lie near 0.01). A user who re-calibrates learns that a stored calibration can be off by that much."""
    if old is None or old.key != new.key:
        return ""
    moved = []
    if abs(new.units_per_s / old.units_per_s - 1.0) > THROTTLE_CHECK_TOLERANCE:
        moved.append(f"the reference rate {old.units_per_s:.1f} -> {new.units_per_s:.1f} units/s")
    if old.throttle_efficiency and new.throttle_efficiency:
        for f in fractions:
            e0, e1 = old.efficiency(f), new.efficiency(f)
            if abs(e1 / e0 - 1.0) > THROTTLE_CHECK_TOLERANCE:
                moved.append(f"eta at {f:.0%} duty {e0:.2f} -> {e1:.2f}")
    if not moved:
        return ""
    return (
        f"since the last calibration ({old.measured_at}): {', '.join(moved)}. What else the host runs moves them; "
        "`run` re-checks eta before a slow budget (docs/hil.md section 4)"
    )


def needs_throttle_check(budget: Budget, cal: HostCalibration | None) -> bool:
    """True when a run on ``budget`` checks the throttle first: a throttled budget below
    :data:`THROTTLE_CHECK_MAX_DUTY` on a host whose calibration measured the throttle's efficiency."""
    return (
        cal is not None
        and bool(cal.throttle_efficiency)
        and not budget.is_host
        and budget.duty(cal).applied < THROTTLE_CHECK_MAX_DUTY
    )


# What a throttle check's throttled units may take (s): rad750 and gr740 get the calibration's 3 units (3.5 and
# 7 s on a 82 units/s host); a board slower than gr740 gets fewer, down to 1 (a 10-DMIPS board: ~40 s)
THROTTLE_CHECK_TARGET_S = 8.0


def throttle_check_units(budget: Budget, cal: HostCalibration) -> int:
    """Reference units the check times under the throttle: the calibration's (``PROBE_UNITS``) while they take
    at most :data:`THROTTLE_CHECK_TARGET_S` at the budget's share, else fewer, at least 1."""
    from hil_server.calibrate import PROBE_UNITS

    per_unit_s = 1.0 / cal.units_per_s / max(budget.duty(cal).effective, 1e-9)
    return max(1, min(PROBE_UNITS, int(THROTTLE_CHECK_TARGET_S / per_unit_s)))


# the slowest shipped budget's duty cycle is ~0.75 %: a curve that stops above this leaves it extrapolated
LOWEST_CALIBRATED_DUTY = 0.01
LOADED_PER_CPU = 0.5  # a 1-minute load average above this per CPU: another job shares the core being emulated


def host_load_note() -> str | None:
    """A warning when this host is loaded, for a run about to emulate a throttled budget; None when it is quiet.
    The throttle's efficiency follows the other load: on a host at a 1-minute load of 1.3-4.6 on 2 CPUs, rad750
    ran a 256 px pair 1.3-1.9x slower than it stands for, and eleven throttle checks within 6 minutes read
    0.48-0.92 (QA of stop 66; docs/hil.md section 4)."""
    import os

    try:
        load1, cores = os.getloadavg()[0], os.cpu_count() or 1
    except OSError:
        return None
    if load1 <= LOADED_PER_CPU * cores:
        return None
    return (
        f"this host is loaded (1-minute load {load1:.1f} on {cores} CPUs): a throttled budget's emulated speed "
        "follows the other load (up to 1.9x slower, measured on such a host); emulate slow budgets on a quiet host"
    )


def check_throttle(budget: Budget, cal: HostCalibration) -> ThrottleCheck:
    """Measure the throttle's efficiency now at the duty cycle ``cal`` gives ``budget``: one round on a probe process
    on the emulated core (:class:`hil_server.calibrate.EfficiencyProbe`, :func:`throttle_check_units` units), a
    second when the first lies beyond the tolerance (:class:`ThrottleCheck`); about :func:`throttle_check_seconds`
    per round."""
    from hil_server.calibrate import EfficiencyProbe

    f = budget.duty(cal).applied
    check = ThrottleCheck(f, cal.efficiency(f), (), calibrated_rate=cal.units_per_s)
    with EfficiencyProbe(throttle_check_units(budget, cal)) as probe:
        while not (check.rounds and check.confirmed):
            check = replace(check, rounds=(*check.rounds, probe.eta(f)))
        return replace(check, host_rate=probe.units_per_s)


def rate_ratio(host_rate: float | None, calibrated_rate: float | None) -> float:
    """The host's full-speed rate on the reference workload now over its calibration's; NaN when either is unknown.
    Beyond :data:`HOST_RATE_TOLERANCE` from 1, a budget runs that much faster or slower than it stands for."""
    if host_rate is None or calibrated_rate is None or not (calibrated_rate > 0 and math.isfinite(host_rate)):
        return math.nan
    return host_rate / calibrated_rate


def measure_host_rate() -> float:
    """The reference workload's full-speed rate now, in units per CPU-second, as the calibration measures it: a probe
    process on the emulated core, :data:`~hil_server.calibrate.PROBE_UNITS` units after its warm-up (about 0.5 s)."""
    from hil_server.calibrate import PROBE_UNITS, EfficiencyProbe

    with EfficiencyProbe(PROBE_UNITS) as probe:
        return probe.units_per_s


def throttle_check_seconds(budget: Budget, cal: HostCalibration) -> float:
    """About how long one round of :func:`check_throttle` takes, with the probe's start and warm-up (~2 s)."""
    units = throttle_check_units(budget, cal)
    return 2.0 + units / cal.units_per_s / max(budget.duty(cal).effective, 1e-9)


def monotone_efficiency(points: list[tuple[float, float]]) -> list[tuple[float, float]]:
    """The measured ``(f, eta)`` made non-decreasing in f by pooling adjacent violators (equal weights).

    A slice after a longer stop starts colder, so eta cannot fall as f rises; a measured dip is noise (repeated
    calibrations on one host spread by about +-5 %, once by 20 %, docs/hil.md section 4).
    """
    pts = sorted(points)
    blocks: list[list[float]] = []  # [sum of eta, count]
    for _, e in pts:
        blocks.append([e, 1.0])
        while len(blocks) > 1 and blocks[-2][0] / blocks[-2][1] > blocks[-1][0] / blocks[-1][1]:
            total, n = blocks.pop()
            blocks[-1][0] += total
            blocks[-1][1] += n
    values = [b[0] / b[1] for b in blocks for _ in range(int(b[1]))]
    return [(f, v) for (f, _), v in zip(pts, values, strict=True)]


@dataclass(frozen=True)
class Duty:
    """How a budget runs here: ``applied`` is the throttle's duty cycle, ``effective = applied x efficiency``
    the fraction of this core's full-speed work it delivers (the budget's ``cpu_dmips / host_dmips``)."""

    applied: float
    effective: float
    efficiency: float


@dataclass(frozen=True)
class Budget:
    """One processor budget (an entry of ``budgets.toml``)."""

    name: str
    description: str
    cpu_dmips: float | None  # None: one whole core of this host
    memory_mib: int
    deadline_s: float
    link: str  # "zmq" | "serial"
    baud: int | None
    source: str
    anchor: Anchor = field(repr=False, compare=False, default=None)  # type: ignore[assignment]

    @property
    def is_host(self) -> bool:
        return self.cpu_dmips is None

    def host_dmips(self, cal: HostCalibration | None) -> float:
        """This host's single-core speed in DMIPS; the anchor's if uncalibrated (warns)."""
        if cal is not None:
            return cal.host_dmips(self.anchor)
        if os.environ.get(UNCALIBRATED_SAID) != "1":  # a run's supervisor and ground: their starter said it
            warnings.warn(
                "no calibration for this host; assuming it is as fast as the anchor "
                f"({self.anchor.dmips:.0f} DMIPS). Run `hazard-hil calibrate`.",
                UncalibratedWarning,
                stacklevel=3,
            )
        return self.anchor.dmips

    def outruns(self, host_dmips: float) -> bool:
        """True when the budget stands for a core faster than this host's: it can only run at full speed, and its
        verdict is then pessimistic."""
        return self.cpu_dmips is not None and self.cpu_dmips > host_dmips

    def duty(self, cal: HostCalibration | None) -> Duty:
        """The effective fraction ``min(1, cpu_dmips / host_dmips)`` and the duty cycle ``f`` that delivers it,
        ``f eta(f) = effective`` (module doc; bisection in log f, eta from ``cal``); 'host' budgets -> 1.0."""
        if self.cpu_dmips is None:
            return Duty(1.0, 1.0, 1.0)
        want = min(1.0, self.cpu_dmips / self.host_dmips(cal))
        if cal is None or not cal.throttle_efficiency or want >= 1.0:
            return Duty(want, want, 1.0)
        lo, hi = math.log(want), 0.0  # f eta(f) <= want at f = want, and 1 >= want at f = 1
        for _ in range(50):
            mid = 0.5 * (lo + hi)
            f = math.exp(mid)
            lo, hi = (mid, hi) if f * cal.efficiency(f) < want else (lo, mid)
        f = math.exp(hi)
        return Duty(f, want, want / f)

    def duty_fraction(self, cal: HostCalibration | None) -> float:
        """The duty cycle the throttle applies (:meth:`duty`); 'host' budgets -> 1.0."""
        return self.duty(cal).applied

    def effective_fraction(self, cal: HostCalibration | None) -> float:
        """The fraction of this core's full-speed work the budget stands for (:meth:`duty`)."""
        return self.duty(cal).effective


# Peak private resident memory (RssAnon + RssShmem, hil_server.procemu) of our flight process (Python, numpy,
# OpenCV, the link, the `fast` pipeline at its full level, fusion over the descent; docs/hil.md, "Memory"). An oblique
# approach is the largest: its world grid holds up to 2.5x the cells of a nadir pair's. Measured 2026-12-03 (stop 35)
# as the HIL records it (`hazard-hil run --budget host --scenario approach --seed 1000 [--image-size 1024]`, the
# largest `peak_rss_mib` over the 8-pair descent): 77.5 MiB at 512x512, 219.5-221.7 MiB at 1024x1024 (3 runs; the
# vertical descent 212.6). So ~32 MiB + ~192 bytes per pixel. Stop 33 measured 99 and 286 MiB and set 32 MiB + 265 B;
# since then the pipeline holds less (stops 34-35) and the boot prefault touches 180 B per pixel instead of 250
# (flight_sw.warmup.HEAP_BYTES_PER_PIXEL; the heap keeps what it touched). bench/bench_flight_memory.py measures the
# pipeline's part. Mapped library code is not counted: how much of it is resident depends on the host's page cache
# (25-53 MiB for the same `import cv2`), not on the flight software.
# A camera is refused when this estimate plus FLIGHT_RSS_MARGIN does not fit the budget's memory ceiling.
# Stop 71 (a QA pass, then the same command on a 256 MiB budget at host speed, `--image-size 1024`): 245.0 MiB at
# 1024x1024 and 252.3 MiB at 1047x1047 (the largest camera the 192 B model admitted for 256 MiB): the flight process
# had grown ~25 MiB at 1024^2 since stop 35, and only the margin kept those runs under the ceiling. Refitted to
# 215 B per pixel, which covers both.
# Stop 73 (a QA pass: a 36 MiB budget admitted a 32 px camera, then every pair breached its ceiling at 36.6 MiB):
# the line is a fit at 512-1047 px, and below ~300 px the process's own floor rules. `hazard-hil run --budget host
# --image-size PX` peaked at 37.2, 37.2 and 37.4 MiB at 32, 64 and 128 px: the estimate is at least that floor.
FLIGHT_BASE_MIB = 32.0
FLIGHT_BYTES_PER_PIXEL = 215.0
FLIGHT_FLOOR_MIB = 37.5
FLIGHT_RSS_MARGIN = 0.10  # run-to-run spread of the peak and scenes busier than the measured ones


# The slowest share of this core `run` emulates: below it one host-second of flight work takes over 17 min, the
# flight process's start-up (~0.5 s of a core: Python, numpy, OpenCV) as long as the heartbeat watchdog's 500 s,
# and a descent hours (a 1-DMIPS budget ran 100 s without its first Hello)
MIN_RUN_SHARE = 1e-3


def check_runnable(name: str, budget: Budget, duty: Duty) -> None:
    """Refuse a budget too slow to emulate here (:data:`MIN_RUN_SHARE`), naming the slowest one that runs."""
    if duty.effective >= MIN_RUN_SHARE or budget.cpu_dmips is None:
        return
    floor = budget.cpu_dmips * MIN_RUN_SHARE / duty.effective
    raise BudgetError(
        f"budget {name} ({budget.cpu_dmips:g} DMIPS) is {100 * duty.effective:.2g} % of this host's core: one "
        f"host-second of flight work would take {1 / duty.effective / 3600:.1f} h; the slowest budget this host "
        f"emulates is about {math.ceil(floor)} DMIPS ({100 * MIN_RUN_SHARE:g} %)"
    )


def flight_peak_rss_mib(pixels: int) -> float:
    """Expected peak private RSS (MiB) of our flight process for a camera of ``pixels`` pixels, margin included."""
    peak = max(FLIGHT_FLOOR_MIB, FLIGHT_BASE_MIB + FLIGHT_BYTES_PER_PIXEL * pixels / 2**20)
    return peak * (1.0 + FLIGHT_RSS_MARGIN)


def max_image_side(memory_mib: float) -> int:
    """The largest square camera side (px) whose expected peak RSS fits ``memory_mib``."""
    fits = memory_mib / (1.0 + FLIGHT_RSS_MARGIN)
    if fits < FLIGHT_FLOOR_MIB:
        return 0
    room = fits - FLIGHT_BASE_MIB
    return int(math.sqrt(room * 2**20 / FLIGHT_BYTES_PER_PIXEL)) if room > 0 else 0


def default_budgets_path() -> Path:
    return Path(str(resources.files("hil_server").joinpath("budgets.toml")))


# Upper bounds a budget's figures must stay under: past them a figure is a typo (a unit slip, an exponent), and a huge
# memory ceiling would overflow the address-space rlimit the supervisor derives from it.
MAX_CPU_DMIPS = 1e6  # ~30x this host's core; no single flight core comes near
MIN_CPU_DMIPS = 1.0  # an 8-bit microcontroller; below it the duty rounds to 0 % and the listing misaligns
MAX_MEMORY_MIB = 2**20  # 1 TiB
MAX_DEADLINE_S = 3600.0  # an hour per pair
# a Result cannot cross even a local link sooner: a shorter deadline is a unit slip (ms for s), not a budget
MIN_DEADLINE_S = 0.001
BAUD_RANGE = (BAUD_MIN, BAUD_MAX)  # the rates a paced line takes


def deadline_problem(value: object) -> str | None:
    """Why ``value`` is no deadline in seconds (``None``: it is one), for `run --deadline`, a regress case and
    :class:`~hil_server.run.RunConfig` alike."""
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    if ok and MIN_DEADLINE_S <= value <= MAX_DEADLINE_S:  # type: ignore[operator]
        return None
    # the reason for the bound that was crossed: a deadline of 1e9 s was told that a Result cannot cross a link in less
    # (QA of stop 84)
    number = isinstance(value, (int, float)) and not isinstance(value, bool)
    why = ""
    if number and value > MAX_DEADLINE_S:  # type: ignore[operator]
        why = " (an hour per pair at most)"
    elif number and value < MIN_DEADLINE_S:  # type: ignore[operator]
        why = " (a Result cannot cross even a local link in less)"
    return f"must be a number of seconds in [{MIN_DEADLINE_S:g}, {MAX_DEADLINE_S:g}]{why}, got {value!r}"


def _number(
    entry: dict, key: str, where: str, positive: bool = True, maximum: float | None = None, minimum: float | None = None
) -> float:
    if key not in entry:
        raise BudgetError(f"{where}: missing '{key}'")
    value = entry.get(key)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise BudgetError(f"{where}: '{key}' must be a finite number, got {value!r}")
    if positive and value <= 0:
        raise BudgetError(f"{where}: '{key}' must be > 0, got {value!r}")
    if maximum is not None and value > maximum:
        raise BudgetError(f"{where}: '{key}' must be <= {maximum:.0f}, got {value:g}")
    if minimum is not None and value < minimum:
        raise BudgetError(f"{where}: '{key}' must be >= {minimum:g}, got {value:g}")
    return float(value)


def _string(entry: dict, key: str, where: str) -> str:
    if key not in entry:
        raise BudgetError(f"{where}: missing '{key}'")
    value = entry.get(key)
    if not isinstance(value, str) or not value.strip():
        raise BudgetError(f"{where}: '{key}' must be a non-empty string, got {value!r}")
    if not value.isprintable():  # printed raw in `budgets` and the summaries: no terminal escapes, one line
        raise BudgetError(f"{where}: '{key}' must be printable text on one line, got {value!r:.60}")
    return value


ANCHOR_KEYS = frozenset({"description", "dmips", "units_per_s", "coremark", "coremark_per_dmips"})
TOP_TABLES = frozenset({"anchor", "budget"})


def _parse_anchor(doc: dict, where: str) -> Anchor:
    a = doc.get("anchor")
    if not isinstance(a, dict):
        raise BudgetError(f"{where}: missing [anchor] table")
    w = f"{where} [anchor]"
    unknown = sorted(set(a) - ANCHOR_KEYS)
    if unknown:  # a misspelt key was ignored without a word (QA 66a)
        raise BudgetError(f"{w}: unknown key(s) {', '.join(unknown)}; known: {', '.join(sorted(ANCHOR_KEYS))}")
    # every missing key at once, as a budget's are (hil.md section 4; QA of stop 80 found them named one a round)
    missing = [k for k in ("description", "dmips", "units_per_s") if k not in a]
    if missing:
        raise BudgetError(f"{w}: missing {', '.join(repr(k) for k in missing)}")
    return Anchor(
        description=_string(a, "description", w),
        dmips=_number(a, "dmips", w),
        units_per_s=_number(a, "units_per_s", w),
        coremark=_number(a, "coremark", w) if "coremark" in a else None,
        coremark_per_dmips=_number(a, "coremark_per_dmips", w) if "coremark_per_dmips" in a else None,
    )


MAX_BUDGET_NAME = 40
# what a budget stands for: a user's file may not change them under a shipped name, and regress records them
BUDGET_FIGURES = ("cpu_dmips", "memory_mib", "deadline_s", "link", "baud")
BUDGET_KEYS = frozenset({"description", "cpu_dmips", "memory_mib", "deadline_s", "link", "baud", "source"})


def _parse_budget(name: str, entry: dict, anchor: Anchor, where: str) -> Budget:
    # printed raw in tables and errors; "   " named a budget nobody could see in a table (QA 66a)
    if not name.strip() or name != name.strip() or any(ord(c) < 32 or ord(c) == 127 for c in name):
        raise BudgetError(f"{where}: a budget name must be printable text, got {name!r:.40}")
    if len(name) > MAX_BUDGET_NAME:  # a 300-character name broke every table that lists it
        raise BudgetError(f"{where}: a budget name has at most {MAX_BUDGET_NAME} characters, got {len(name)}")
    w = f"{where} [budget.{name}]"
    if not isinstance(entry, dict):
        raise BudgetError(f"{w}: must be a table")
    unknown = sorted(set(entry) - BUDGET_KEYS)
    if unknown:  # a misspelt key would otherwise leave its default in force, unseen
        raise BudgetError(f"{w}: unknown key(s) {', '.join(unknown)}; a budget has {', '.join(sorted(BUDGET_KEYS))}")
    # every missing key at once: one fixed, the next was named, three rounds to a file that loads (QA of stop 73)
    missing = [k for k in ("description", "cpu_dmips", "memory_mib", "deadline_s", "link") if k not in entry]
    if missing:
        raise BudgetError(
            f"{w}: missing {', '.join(repr(k) for k in missing)} (a budget has {', '.join(sorted(BUDGET_KEYS))}; "
            f"'baud' (default {DEFAULT_BAUD} on a serial link) and 'source' may be left out)"
        )
    cpu = entry.get("cpu_dmips")
    cpu_dmips = None if cpu == "host" else _number(entry, "cpu_dmips", w, maximum=MAX_CPU_DMIPS, minimum=MIN_CPU_DMIPS)
    memory = _number(entry, "memory_mib", w, maximum=MAX_MEMORY_MIB)
    if memory != int(memory):
        raise BudgetError(f"{w}: 'memory_mib' must be a whole number of MiB, got {memory}")
    link = _string(entry, "link", w)
    if link not in LINKS:
        raise BudgetError(f"{w}: 'link' must be one of {', '.join(LINKS)}, got {link!r}")
    baud = None
    if link == "serial":
        baud_f = _number(entry, "baud", w) if "baud" in entry else float(DEFAULT_BAUD)  # as `run --link serial`'s
        if baud_f != int(baud_f) or not BAUD_RANGE[0] <= baud_f <= BAUD_RANGE[1]:
            lo, hi = BAUD_RANGE
            raise BudgetError(f"{w}: 'baud' must be an integer in [{lo}, {hi:.0e}], got {entry['baud']!r}")
        baud = int(baud_f)
    elif "baud" in entry:
        raise BudgetError(f"{w}: 'baud' only applies to link = \"serial\"")
    return Budget(
        name=name,
        description=_string(entry, "description", w),
        cpu_dmips=cpu_dmips,
        memory_mib=int(memory),
        deadline_s=_number(entry, "deadline_s", w, maximum=MAX_DEADLINE_S, minimum=MIN_DEADLINE_S),
        link=link,
        baud=baud,
        source=_string(entry, "source", w) if "source" in entry else "(not given)",
        anchor=anchor,
    )


def load_budgets(path: str | os.PathLike | None = None) -> dict[str, Budget]:
    """All budgets of ``path`` (default: the packaged ``budgets.toml``), in file order."""
    p = Path(path) if path is not None else default_budgets_path()
    try:
        doc = tomllib.loads(p.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise BudgetError(f"budget file not found: {p}") from None
    except (OSError, UnicodeDecodeError) as exc:  # a directory, unreadable, not text
        raise BudgetError(f"{p}: cannot be read as a budget file ({exc})") from None
    except tomllib.TOMLDecodeError as exc:
        raise BudgetError(f"{p}: not valid TOML: {exc}") from None
    extra = sorted(set(doc) - TOP_TABLES)
    if extra:  # [budgets.x] for [budget.x] was ignored, and the file then had no budget of that name (QA 66a)
        raise BudgetError(f"{p}: unknown table(s) or key(s) {', '.join(extra)}; a budget file has [anchor] and "
                          "[budget.NAME] tables")  # fmt: skip
    anchor = _parse_anchor(doc, str(p))
    entries = doc.get("budget")
    if not isinstance(entries, dict) or not entries:
        raise BudgetError(f"{p}: no [budget.NAME] tables")
    budgets = {name: _parse_budget(name, entry, anchor, str(p)) for name, entry in entries.items()}
    folded: dict[str, str] = {}
    for name in budgets:  # myboard beside MyBoard: one processor or two, in a summary that names it?
        if name.casefold() in folded:
            raise BudgetError(f"{p}: budgets {folded[name.casefold()]!r} and {name!r} differ only in case; rename one")
        folded[name.casefold()] = name
    if path is not None and p.resolve() != default_budgets_path().resolve():
        _refuse_other_anchor(anchor, p)
        _refuse_redefined(budgets, p)
    return budgets


def _refuse_other_anchor(anchor: Anchor, p: Path) -> None:
    """A user's file measures its boards against the shipped anchor: another one (``dmips = 1``) made every board
    "faster than the host", and regress's reference seconds incomparable with anyone else's."""
    shipped = next(iter(load_budgets().values())).anchor
    moved = [k for k in ("dmips", "units_per_s") if getattr(anchor, k) != getattr(shipped, k)]
    if moved:
        got = ", ".join(f"{k} = {getattr(anchor, k):g}, shipped {getattr(shipped, k):g}" for k in moved)
        raise BudgetError(
            f"{p} [anchor]: differs from the shipped anchor ({got}): copy the shipped [anchor] table; every budget's "
            "DMIPS are measured against it"
        )


def _refuse_redefined(budgets: dict[str, Budget], p: Path) -> None:
    """A user's file may copy a shipped budget, not change it under the same name: summaries and regression
    baselines name budgets, and ``rad750`` must mean the same processor in all of them."""
    shipped = load_budgets()
    folded = {k.casefold(): k for k in shipped}
    for name, b in budgets.items():
        s = shipped.get(name)
        if s is None and name.casefold() in folded:  # RAD750 beside rad750 in one summary: two processors or one?
            raise BudgetError(
                f"{p} [budget.{name}]: differs from the shipped budget {folded[name.casefold()]!r} only in case; "
                "give your budget another name"
            )
        if s is None:
            continue
        changed = [f for f in BUDGET_FIGURES if getattr(b, f) != getattr(s, f)]  # the anchor: _refuse_other_anchor
        if changed:
            raise BudgetError(
                f"{p} [budget.{name}]: redefines the shipped budget {name!r} ({', '.join(changed)} differ); "
                "give your budget another name"
            )


# what `run --budget NAME` adds when NAME is no budget: a board of one's own lives in a budget file, and the choices
# alone did not say how to name one (QA of stop 80)
OWN_BUDGET_HINT = "a budget of your own: define it in a TOML file and give it with --budget-file, see docs/hil.md"


def get_budget(name: str, path: str | os.PathLike | None = None, *, hint: str = "") -> Budget:
    """The budget called ``name``; :class:`BudgetError` naming the choices otherwise (and ``hint``, said after them,
    where the command offers a way to a budget of one's own)."""
    budgets = load_budgets(path)
    try:
        return budgets[name]
    except KeyError:
        if path is not None:  # `run --budget-file F` alone asked for the default 'host', which F need not define
            raise BudgetError(
                f"budget {name!r} is not in {path}, which defines {', '.join(budgets)}: name one with --budget"
            ) from None
        more = f" ({hint})" if hint else ""
        raise BudgetError(f"unknown budget {name!r}; choose one of: {', '.join(budgets)}{more}") from None


# --- calibration ---------------------------------------------------------------------------


def calibration_path() -> Path:
    """``$HAZARD_HIL_HOME/calibration.json``, else ``$XDG_CACHE_HOME|~/.cache/hazard-hil/``."""
    home = os.environ.get("HAZARD_HIL_HOME")
    if home:
        return Path(home) / "calibration.json"
    cache = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(cache) / "hazard-hil" / "calibration.json"


def cpu_model() -> str:
    """CPU model name plus family/model numbers (the name alone can be vague on VMs)."""
    fields: dict[str, str] = {}
    try:
        with open("/proc/cpuinfo", encoding="utf-8", errors="replace") as fh:
            for line in fh:
                if not line.strip():
                    break  # first processor only
                k, _, v = line.partition(":")
                fields[k.strip()] = v.strip()
    except OSError:
        pass
    name = fields.get("model name") or platform.processor() or platform.machine() or "unknown cpu"
    if "cpu family" in fields and "model" in fields:
        name += f" (family {fields['cpu family']}, model {fields['model']})"
    return name


def host_key() -> str:
    return f"{socket.gethostname()}|{cpu_model()}"


def check_store_writable(path: Path | None = None) -> None:
    """Refuse, before half a minute of measuring, a calibration store that could not be written: its directory a
    file (``HAZARD_HIL_HOME`` set to one), or under a directory this user may not write."""
    p = Path(path) if path is not None else calibration_path()
    if p.parent.exists() and not p.parent.is_dir():
        _read_store(p)  # its one-line error
    # the store is replaced by a temporary file renamed over it, beside a lock file: its directory (or the nearest
    # one that exists, where it will be made) must be writable; the file's own mode does not matter
    existing = next(a for a in (p.parent, *p.parent.parents) if a.exists())
    if not os.access(existing, os.W_OK | os.X_OK):
        raise BudgetError(f"cannot write the calibration store {p}: {existing} is not writable (HAZARD_HIL_HOME?)")


def _read_store(path: Path) -> dict:
    if path.parent.exists() and not path.parent.is_dir():  # e.g. $HAZARD_HIL_HOME set to a file
        raise BudgetError(f"calibration directory {path.parent} is a file, not a directory (HAZARD_HIL_HOME?)")
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        return {}
    except (OSError, ValueError) as exc:
        raise BudgetError(
            f"calibration file {path} is unreadable ({exc}); delete it and run `hazard-hil calibrate`"
        ) from None
    if not isinstance(data, dict):
        raise BudgetError(f"calibration file {path}: expected a JSON object keyed by host")
    return data


def load_calibration(path: str | os.PathLike | None = None) -> HostCalibration | None:
    """This host's stored calibration, or None if it was never calibrated."""
    p = Path(path) if path is not None else calibration_path()
    entry = _read_store(p).get(host_key())
    if entry is None:
        return None
    try:
        if not isinstance(entry, dict):
            raise ValueError("not a JSON object")
        eff = entry.get("throttle_efficiency", ())
        if not isinstance(eff, (list, tuple)) or not all(
            isinstance(pt, (list, tuple))
            and len(pt) == 2
            and all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in pt)
            and 0 < pt[0] < 1
            and 0 < pt[1] <= 1
            for pt in eff
        ):
            raise ValueError(f"throttle_efficiency must be [duty in (0, 1), eta in (0, 1]] pairs, got {eff!r}")
        # named, not as the dataclass's "__init__() missing 7 required positional arguments"
        need = {f.name for f in dataclasses.fields(HostCalibration) if f.default is dataclasses.MISSING}
        missing, unknown = (
            sorted(need - set(entry)),
            sorted(set(entry) - {f.name for f in dataclasses.fields(HostCalibration)}),
        )
        if missing or unknown:
            raise ValueError(
                ", ".join(
                    ([f"missing {', '.join(missing)}"] if missing else [])
                    + ([f"unknown {', '.join(unknown)}"] if unknown else [])
                )
            )
        cal = HostCalibration(**{**entry, "throttle_efficiency": tuple(sorted((float(f), float(e)) for f, e in eff))})
        for name in ("units_per_s", "spread", "seconds"):
            v = getattr(cal, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
                raise ValueError(f"{name} must be a finite number >= 0, got {v!r}")  # units_per_s: bounds below
        if not MIN_UNITS_PER_S <= cal.units_per_s <= MAX_UNITS_PER_S:  # 1e300 passed: the throttle then died
            raise ValueError(
                f"units_per_s must be in [{MIN_UNITS_PER_S:g}, {MAX_UNITS_PER_S:g}] (this machine type does ~50), "
                f"got {cal.units_per_s!r}"
            )
        if not isinstance(cal.libraries, str):
            raise ValueError(f"libraries must be a string, got {cal.libraries!r}")
        calibration_age_days(cal)  # measured_at must be a timestamp
    except (TypeError, ValueError) as exc:
        raise BudgetError(
            f"calibration file {p}: bad entry for this host ({exc}); run `hazard-hil calibrate`"
        ) from None
    return cal


# A host's reference-workload rate, units per CPU-second: this machine type does ~50 (budgets.toml's anchor). A rate
# 1000x either way is no host anyone runs on; 1e300 made every duty cycle 1e-299 and killed the throttle thread.
MIN_UNITS_PER_S = 0.05
MAX_UNITS_PER_S = 5e4
STALE_CALIBRATION_DAYS = 30.0  # a VM's host can change under it (migration, new CPU microcode) in this time


def calibration_age_days(cal: HostCalibration, now: _dt.datetime | None = None) -> float:
    """Days since ``cal`` was measured (ValueError if its ``measured_at`` is not an ISO 8601 time with a zone)."""
    when = _dt.datetime.fromisoformat(str(cal.measured_at))
    if when.tzinfo is None:
        raise ValueError(f"measured_at has no time zone: {cal.measured_at!r}")
    return ((now or _dt.datetime.now(_dt.UTC)) - when).total_seconds() / 86400.0


# `calibrate` measures the rate again (at most REMEASURE_TRIES times) while its batches spread more than this:
# `make demo`'s first-time calibration read 53.7 units/s at a spread of 24.7 %, just under the noisy mark, where
# the same host measured 68-79 at 3-7 % (stop 56's budget QA), and every budget's speed rested on it
REMEASURE_SPREAD = 0.15
REMEASURE_TRIES = 2
NOISY_CALIBRATION_SPREAD = 0.25  # (p90 - p10) / median of the batches: above this, other work shared the core


def workload_libraries() -> str:
    """The versions the reference workload's rate depends on, e.g. ``python 3.11.2, numpy 2.1.3, opencv 4.10.0``."""
    import cv2
    import numpy as np

    return f"python {platform.python_version()}, numpy {np.__version__}, opencv {cv2.__version__}"


def calibration_notes(cal: HostCalibration | None, now: _dt.datetime | None = None) -> list[str]:
    """One line per reason not to trust this host's calibration (none when it is sound).

    A calibration is doubtful when it is missing, older than :data:`STALE_CALIBRATION_DAYS`, measured on other
    library versions than those installed now, or measured with a batch spread over
    :data:`NOISY_CALIBRATION_SPREAD`. Each budget's duty cycle is ``budget DMIPS / host DMIPS``, so an error in the
    host's rate is the same error in every emulated processor's speed.
    """
    if cal is None:
        return [
            f"this host is not calibrated ({calibration_path()} has no entry for it): duty cycles assume it is as "
            "fast as the anchor; run `hazard-hil calibrate`"
        ]
    notes = []
    age = calibration_age_days(cal, now)
    if age > STALE_CALIBRATION_DAYS:
        notes.append(
            f"this host's calibration is {age:.0f} days old ({cal.measured_at}); "
            "re-run `hazard-hil calibrate` if the host may have changed"
        )
    if cal.libraries and cal.libraries != workload_libraries():
        notes.append(
            f"this host was calibrated with {cal.libraries}, and {workload_libraries()} is installed now: "
            "re-run `hazard-hil calibrate`"
        )
    if cal.spread > NOISY_CALIBRATION_SPREAD:
        notes.append(
            f"this host's calibration was noisy (batch spread {cal.spread:.1%} > {NOISY_CALIBRATION_SPREAD:.0%}: "
            "other work shared the core); re-run `hazard-hil calibrate` on a quiet host"
        )
    if not cal.throttle_efficiency:
        notes.append(
            "this host's calibration has no throttle efficiency (stored before it was measured): slow budgets run "
            "up to ~1.8x slower than they stand for; re-run `hazard-hil calibrate`"
        )
    elif min(f for f, _ in cal.throttle_efficiency) > LOWEST_CALIBRATED_DUTY:
        # a `calibrate --duty-cycles 0.5` replaced the whole curve: rad750's 1.6 % then read eta 0.94 from 0.5,
        # where about 0.7 holds, and ran ~1.3x slower than listed without a word (QA of stop 66)
        low = min(f for f, _ in cal.throttle_efficiency)
        notes.append(
            f"this host's throttle efficiency was measured down to {low:.1%} duty only: slower budgets' duty cycles "
            "extrapolate it, and run slower than they stand for; re-run `hazard-hil calibrate` with its default "
            "duty cycles"
        )
    return notes


def calibrate_host(
    seconds: float = 3.0,
    path: str | os.PathLike | None = None,
    save: bool = True,
    efficiency_fractions: tuple[float, ...] | None = None,
    progress: Callable[[str], None] | None = None,
) -> HostCalibration:
    """Measure this host's single-core reference-workload rate and the throttle's efficiency at
    ``efficiency_fractions`` (default :data:`hil_server.calibrate.EFFICIENCY_FRACTIONS`; ``()`` skips it), and (by
    default) store them."""
    from hil_server.calibrate import EFFICIENCY_FRACTIONS, measure_rate, measure_throttle_efficiency

    if not (isinstance(seconds, (int, float)) and math.isfinite(seconds) and 0 < seconds <= 600):
        raise BudgetError(f"calibration time must be in (0, 600] s, got {seconds!r}")
    rate = measure_rate(float(seconds))
    for _ in range(REMEASURE_TRIES):  # a noisy one is measured again, the least noisy kept
        if rate.spread <= REMEASURE_SPREAD:
            break
        if progress is not None:
            progress(f"the reference rate's batches spread {rate.spread:.0%} (other work on the core?): once more")
        rate = min(rate, measure_rate(float(seconds)), key=lambda r: r.spread)
    fractions = EFFICIENCY_FRACTIONS if efficiency_fractions is None else efficiency_fractions
    eff = measure_throttle_efficiency(fractions, progress=progress) if fractions else ()
    cal = HostCalibration(
        key=host_key(),
        hostname=socket.gethostname(),
        cpu_model=cpu_model(),
        units_per_s=rate.units_per_s,
        spread=rate.spread,
        seconds=rate.cpu_s,
        measured_at=_dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
        libraries=workload_libraries(),
        throttle_efficiency=eff,
    )
    if save:
        _store_calibration(Path(path) if path is not None else calibration_path(), cal)
    return cal


def _store_calibration(p: Path, cal: HostCalibration) -> None:
    """Add ``cal`` to the store at ``p``, under an exclusive lock beside it: two calibrations at once (two hosts
    sharing a home directory, two terminals) each keep their entry, the second reading what the first wrote. The
    store is replaced whole (a temporary file of its own, renamed over it): a reader never sees half of it."""
    import fcntl

    from reports.html import write_atomic

    if p.parent.exists() and not p.parent.is_dir():
        _read_store(p)  # its one-line error: the directory is a file (HAZARD_HIL_HOME?)
    p.parent.mkdir(parents=True, exist_ok=True)
    with open(p.with_name(p.name + ".lock"), "a") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        try:
            store = _read_store(p)
        except BudgetError:  # calibrating is the cure for a broken store: keep the old file aside, start afresh
            kept = p.with_name(p.name + ".corrupt")
            os.replace(p, kept)
            print(f"calibrate: {p} was unreadable; kept it as {kept} and started a new one", file=sys.stderr)
            store = {}
        store[cal.key] = asdict(cal)
        write_atomic(p, json.dumps(store, indent=2, sort_keys=True) + "\n")
