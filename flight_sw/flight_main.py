"""The flight process: the hazard-detection software as it runs on the emulated processor.

Started by the HIL supervisor (``hil_server.supervisor``) as a separate OS
process, pinned, throttled and memory-capped from outside; it only talks to
the supervisor over an inherited socket using the protocol's framing.

Message flow (one pair = two ``Frame``s sharing a ``pair_id``)::

    supervisor -> flight : Config, Frame, Frame, Frame, ...; Hello when a new ground session begins
    flight -> supervisor : Hello, Heartbeat (periodic), Result + Telemetry per pair,
                           Error (bad frame, pipeline failure) - never silence

The Result is the compact one of docs/protocol.md (grids as uint8/int16, sites);
full-resolution image maps only when ``Config.options["full_maps"]`` is 1.

Fusion over the descent (issue 10, :mod:`flight_sw.fusion`): the process keeps one world-grid
map that every pair's result refines (log-odds of "safe", a hazard is only overturned by the
documented amount of later evidence); each Result reports the fused map on the newest pair's
grid and the sites chosen on it. ``Config.options["fusion"] = 0`` reports each pair alone.
The map starts afresh with a new descent; a new ground session (a Hello passed on by the
HIL server, or a board's own) whose Config is the last one's, naming the same ``descent_id``,
keeps it, and drops the old session's half-received pairs.

Deadline planning (docs/hil.md): the deadline runs from the ground's last frame
to the ground holding the whole Result, so the Result's own line time counts.
The anytime pipeline gets ``arrival + deadline_s - expected result line time``
in this process's clock, and ``after_s`` (encoding and handing over the Result,
``output_reserve_s`` of the Result's expected size, plus ``FUSION_RESERVE_S`` for fusing and choosing sites
when fusion is on; unthrottled seconds) to reserve at the slowdown it measures,
which at low duty cycles exceeds ``time_scale``. The line time comes from the
Result's expected size (the largest of the last few Results, or a prior from the camera
and the grid steps for the first) and the rate ``Config.options["link_baud"]``
announces; a longer measured output time of the last pair is kept back as well.
The reserves themselves are planned from what the reserved work cost on the last
pairs with a DEM (``anytime.measured_reserve_ratio``, the largest of the last
``RESERVE_HISTORY``).

``--fault`` injects test faults (the NOS Engine idea: fault injection belongs
to the test harness, not to hand-edited code): ``crash@N``, ``hang@N``,
``oom@N`` act on the N-th pair (0-based) this process receives.
"""

from __future__ import annotations

import argparse
import functools
import math
import os
import socket
import sys
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

# loaded at boot, before Hello: not inside the first deadline
from flight_sw.anytime import measured_reserve_ratio
from flight_sw.fusion import MAX_KEPT_HAZARDS, FusedMap, FusionParams, fuse, params_for, to_hazard_grid
from flight_sw.mapping import HazardGrid
from flight_sw.memory import private_rss_bytes
from flight_sw.pair_report import ground_words, pair_notes, pose_figures, pose_verdict
from flight_sw.pipeline import PRESETS, run_pipeline
from flight_sw.sites import Site as SiteResult
from flight_sw.sites import select_safe_sites
from protocol.codec import Encoded, encode
from protocol.errors import EXIT_MEMORY, InputError
from protocol.grids import elevation_to_wire, filled_to_wire, psafe_to_wire
from protocol.messages import (
    MAX_NOTE_CHARS,
    MAX_NOTES,
    MAX_RSS_BYTES,
    MAX_SKIPPED,
    RESULT_FIELD_REV,
    RESULT_REV,
    TELEMETRY_FIELD_REV,
    Config,
    Error,
    Frame,
    Heartbeat,
    Hello,
    Result,
    Site,
    Telemetry,
)
from protocol.pairdir import STATE_SAFE, Camera, PairFormatError, Pose, check_altimeter

# Building, fitting and encoding the Result happen after the pipeline returns: unthrottled seconds, scaled like the
# pipeline's reserves by the slowdown it measures. They grow with the Result: OUTPUT_BASE_S + OUTPUT_PER_BYTE_S x its
# expected size, the upper envelope of 18 flight-process Results of 18-193 kB on one core (host budget, approach and
# vertical descents over serial and ZeroMQ: 8-29 ms, stop 45). A fixed 0.04 s reserved 2.5x the 0.015 s that rad750's
# 25-40 kB Results took, and with it rad750 returned the first approach pairs image-only with 13 s of 30 unused
OUTPUT_BASE_S = 0.014
OUTPUT_PER_BYTE_S = 1.05e-7
# Line time of the Result = bytes x LINE_OVERHEAD x 10 / baud + LINE_LATENCY_S: framing (26 B per 1 KiB
# frame) and byte stuffing (~1 % of compressed bytes) on top of the 8N1 bits, plus relay and scheduling slack.
LINE_OVERHEAD = 1.05
LINE_LATENCY_S = 0.05
# Prior for the first Result's size, bytes per cell of the world grid (~1 cell per 2x2 pixels): zlib'd state
# grid <= 0.13, P(safe) <= 0.55 / kp^2, int16 elevation <= 1.4 / k^2 (docs/protocol.md measured 72-106 kB at
# (1, 1), 7-11 kB at (4, 8) on 512 px), sites and fields ~2 kB; the full image maps ~1.6 B per pixel.
PRIOR_STATE_B, PRIOR_PSAFE_B, PRIOR_ELEV_B, PRIOR_FIXED_B, PRIOR_MAPS_B = 0.13, 0.55, 1.4, 2048, 1.6
# An elevation unit of u cm drops log2(u) bits of noise per value: the prior takes the grid as shrunk by
# 1 - PRIOR_UNIT_SHRINK log2(u), 0.67 at u = 10; measured 0.41-0.61 (with filter 2) on the held-out fused maps
# (docs/benchmarks/protocol.md): a prior on the large side, as a line-time plan should be
PRIOR_UNIT_SHRINK, PRIOR_UNIT_FLOOR = 0.1, 0.25
PRIOR_FLOOR = 0.5  # after the first Result, plan for at least this share of the prior (a full-level Result)
# Config.options understood here: full_maps (0/1: add the full-resolution image maps to each Result),
# elevation_step and psafe_step (k >= 1: that grid is the world grid decimated by k; docs/protocol.md),
# elevation_unit_cm (u in [1, 1000]: the elevation grid's unit; a coarser unit compresses better),
# link_baud (the ground link's rate, 0 = none to plan for), time_scale (the emulated slowdown) and result_rev (the
# newest Result schema revision the ground decodes, protocol.messages.RESULT_FIELD_REV; absent = 0, the baseline:
# every Result leaves the newer optional fields out, so that a ground older than them does not refuse it).
DEFAULT_ELEVATION_STEP = 1
DEFAULT_ELEVATION_UNIT_CM = 1
DEFAULT_PSAFE_STEP = 1
DEFAULT_FUSION = 1  # fusion (0/1): Results report the map fused over the descent (docs/benchmarks/multiframe.md)
# Fusing and choosing sites on the fused map happen after the pipeline returns: unthrottled seconds
# (x time_scale) kept for them (a 450x360 approach grid: 9-17 ms to fuse and choose sites since stop 33)
FUSION_RESERVE_S = 0.03
# The plan ends this share of the deadline early: the line's pacing, the ground's clock and the duty cycle's
# phase move the end by a few ms either way. Aimed at the deadline itself, the stop-38 code ended held-out
# snapdragon801 approach pairs 2-5 ms inside it in 2 of 3 runs, and stop 39's +1-4 ms of fusion 4 and 14 ms
# past it in 2 of 6 (docs/hil.md, stop 39)
DEADLINE_GUARD = 0.01
# the reserves of the next pair are planned from the largest of the last few pairs' measured costs
# (anytime.measured_reserve_ratio): one fast pair does not shrink them
RESERVE_HISTORY = 3
RESULT_HISTORY = 3  # the next Result's line time is planned from the largest of the last this many Results
# ... times this. 1.2 until stop 33; since a Result that outgrows its plan is sent with coarser grids (fit_to_line),
# no margin: on the held-out approach (5 runs) 12 full-level Results instead of 1.5 per run, 40 of 40 deadlines met
RESULT_MARGIN = 1.0
# A Result that would still be on the line at its deadline goes out with its elevation grid, then its P(safe) grid,
# decimated twice as much, up to this step: the size plan is only a plan (a first full-level Result after coarse
# ones is larger than any before it). Measured only when the time left is under SHRINK_CHECK x the planned line.
MAX_SHRINK_STEP = 16
SHRINK_CHECK = 2.0


# half-received pairs held at once: a pair whose other frame never comes (a ground reconnected mid-pair, a frame
# refused as bad_frame) was held for good, 256 KiB a 512 px frame (review of stop 64: 200 held 50 MiB)
MAX_PENDING_PAIRS = 8


@dataclass
class PendingPair:
    frames: dict[int, Frame] = field(default_factory=dict)
    arrival: float = 0.0  # monotonic time the last frame arrived


@dataclass
class FaultPlan:
    kind: str | None = None
    pair_index: int = -1

    @classmethod
    def parse(cls, spec: str | None) -> FaultPlan:
        if not spec:
            return cls()
        kind, _, idx = spec.partition("@")
        if kind not in ("crash", "hang", "oom") or not idx.isdigit():
            raise InputError(f"--fault must be crash@N, hang@N or oom@N, got {spec!r}")
        return cls(kind, int(idx))

    def trigger(self, pair_index: int, settle: Callable[[], object] | None = None) -> None:
        """Inject the fault if this is its pair. ``settle`` runs before a crash: the frames' ACKs go out first, as
        they would before a crash inside the pipeline (without it, on a loaded core the abort could beat them,
        and the supervisor rightly took the pair as never received and sent it to the next incarnation)."""
        if pair_index != self.pair_index:
            return
        if self.kind == "crash":
            if settle is not None:
                settle()
            os.abort()
        if self.kind == "hang":  # a hang in native code: no heartbeats, no progress
            time.sleep(1e6)
        if self.kind == "oom":
            hog = []
            while True:
                hog.append(np.ones(16 << 20, dtype=np.uint8))


def output_reserve_s(nbytes: float) -> float:
    """Unthrottled CPU s to build, fit and encode a Result of ``nbytes`` on the wire:
    ``OUTPUT_BASE_S + OUTPUT_PER_BYTE_S x nbytes``."""
    return OUTPUT_BASE_S + OUTPUT_PER_BYTE_S * max(0.0, float(nbytes))


def expected_line_s(nbytes: float, baud: float) -> float:
    """Line time of ``nbytes`` at ``baud`` (8N1 + framing); 0 when the link announces no rate (ZeroMQ, unpaced)."""
    if not baud > 0:
        return 0.0
    return nbytes * LINE_OVERHEAD * 10.0 / baud + LINE_LATENCY_S


def fit_to_line(
    result: Result, rebuild: Callable[[tuple[int, int]], Result], baud: float, due: float, planned_s: float
) -> tuple[Result, float, float, Encoded | None]:
    """``(result, its expected line time, grown, encoded)``: the Result with its grids decimated further while it
    would still be on the line at ``due`` (monotonic s); ``rebuild((elevation step, P(safe) step))`` makes it at
    other steps. ``grown`` = the size at the Config's steps over the size sent (1 when nothing changed), so
    that the next pair plans for the size its Result will have. ``encoded`` is the Result with the body its size
    was measured on, for the link to send as it is (None when it was not measured).

    The elevation step doubles first (up to ``MAX_SHRINK_STEP``), then the P(safe) step; the state grid and
    the sites are never touched, and the Result carries its own steps, so the ground reads it as sent. The line
    time must fit in what is left once the Result is encoded: at 23 % duty one encoding took 0.09 s, and a 56 kB
    approach Result that fitted the line time alone ended 22 ms past its 2 s deadline (stop 47). The body is
    kept, so sending does not encode it again (that took as long once more). A Result that fits with
    ``SHRINK_CHECK`` x its planned line time to spare is not measured (encoding costs CPU). Without a line rate
    (``baud`` 0) nothing is changed.
    """
    if baud <= 0 or due - time.monotonic() > SHRINK_CHECK * planned_s:
        return result, planned_s, 1.0, None
    step, pstep = int(result.elevation_step), int(result.psafe_step)
    encoded = encode(result)
    full = nbytes = len(encoded.body)
    line_s = expected_line_s(nbytes, baud)
    while line_s > due - time.monotonic() and (step < MAX_SHRINK_STEP or pstep < MAX_SHRINK_STEP):
        if step < MAX_SHRINK_STEP:
            step = min(2 * step, MAX_SHRINK_STEP)
        else:
            pstep = min(2 * pstep, MAX_SHRINK_STEP)
        result = rebuild((step, pstep))
        encoded = encode(result)
        nbytes = len(encoded.body)
        line_s = expected_line_s(nbytes, baud)
    return result, line_s, full / nbytes, encoded


def _is_int(v: float) -> bool:
    """An option value that is a whole number (options are numbers; NaN and infinities are not, and int() of them
    raised out of the Config's check, ending the flight process instead of answering bad_config)."""
    return math.isfinite(v) and v == int(v)


def result_rev(cfg: Config) -> int:
    """The newest Result revision the ground decodes: ``Config.options["result_rev"]`` (0, the baseline, when the
    ground does not say; one newer than this flight software's gets everything it has)."""
    return int(cfg.options.get("result_rev", 0))


def baud_mismatch_note(ground_baud: float, own_baud: int | None) -> str:
    """A board's port set to another rate than the ground paces its line at ("" when they agree, or either side is
    unpaced). A real UART garbles the bytes then, and the ground says "another baud?"; a pty or a USB gadget that
    ignores the rate carries them, and the board planned for the ground's rate and called its own miss "met"."""
    if not ground_baud or not own_baud or int(ground_baud) == int(own_baud):
        return ""
    return (
        f"the ground paces this line at {int(ground_baud)} baud, this side's port is set to {own_baud}: on a real "
        "UART the two must match; the deadline plan follows the ground's rate"
    )


def left_out_note(cfg: Config) -> str:
    """'' when the ground decodes every Result field; otherwise one line naming the fields its Results go without,
    and saying so when the Config asked for what they carry (``full_maps``: the image maps' gap-fill mask)."""
    rev = result_rev(cfg)
    dropped = [name for name, r in RESULT_FIELD_REV.items() if r > rev]
    dropped_t = [name for name, r in TELEMETRY_FIELD_REV.items() if r > rev]
    if not dropped and not dropped_t:
        return ""
    without = []
    if dropped:
        without.append(f"every Result goes without {', '.join(dropped)}")
    if dropped_t:
        without.append(f"every Telemetry without {', '.join(dropped_t)}")
    note = f"the ground decodes Result revision {rev} (this flight software sends {RESULT_REV}): " + ", ".join(without)
    if cfg.options.get("full_maps", 0) and "elevation_filled_image" in dropped:
        note += "; full_maps was asked for, but the image maps go without their gap-fill mask"
    return note


def link_stats(link: Any) -> dict:
    """A link's counters (a property on some links, a method on others; none before one is open)."""
    stats = getattr(link, "stats", None) or {}
    return dict(stats() if callable(stats) else stats)


def line_damage(stats: dict) -> dict[str, float]:
    """What this side's byte-stream line dropped so far, for Telemetry's ``link`` (empty when nothing): frames that
    failed their checks and the bytes of noise around them. A board's line noise reached no summary: the ground
    counts only its own side's (QA of stop 72)."""
    bad = float(stats.get("crc_errors", 0) or 0) + float(stats.get("malformed", 0) or 0)
    if not bad:
        return {}
    return {"flight_rx_damaged": bad, "flight_rx_noise_bytes": float(stats.get("bytes_discarded", 0) or 0)}


def plan_telemetry(info: dict, budget_s: float, line_s: float) -> dict[str, float]:
    """The Telemetry's ``plan``: what the deadline plan had and decided on, in wall seconds on this processor.

    ``budget_s``: from the pipeline's start to the time it aimed to be done by (the deadline less the Result's
    planned ``line_s`` and the guard); then, from ``info["plan"]`` (``anytime.Clock.decide``), for each DEM
    stage that was weighed, the time left at its start and the time kept for the work after it (the DEM stage
    runs only while the first exceeds the second), and the slowdown they were planned at (``measured`` 1 when
    from the previous pairs' measured cost, 0 when from the first stages' slowdown)."""
    plan = {"budget_s": float(budget_s), "line_s": float(line_s)}
    for k, v in (info.get("plan") or {}).items():
        if isinstance(v, (int, float)) and math.isfinite(v):
            plan[str(k)] = v
    return plan


def _reading_set_aside(frame: Frame, k: int) -> str | None:
    """Why frame ``k``'s (0 upper, 1 lower) altimeter reading is set aside, or None when it is used or absent (NaN).

    Set aside: no range (0 or negative: a sensor without lock; the wire refuses an infinite one), or one no terrain
    can explain for the frame's pose (:func:`protocol.pairdir.check_altimeter`, the pair reader's rule: a 1e300
    reading failed deep in the range search as a ``pipeline_failure``, and 65535 m at 300 m passed unsaid; QA of
    stop 85). The pair is mapped without it, and said; a 0 in the upper frame once refused the whole pair.
    """
    a = float(frame.altimeter_m)
    if math.isnan(a):
        return None
    if not (math.isfinite(a) and a > 0):
        return f"frame {k}'s altimeter reading {a + 0.0:g} m is no range: the pair is mapped without it"
    try:
        check_altimeter(a, frame_pose(frame), f"frame {k}")
    except PairFormatError as exc:
        return f"{exc}; the pair is mapped without it"
    return None


def _readings_ignored(frames: tuple[Frame, ...]) -> list[str]:
    """A note for each of a pair's frames (upper, lower) whose altimeter reading was set aside, in the pipeline's
    numbering (frame 0, frame 1: :func:`ground_words` names them)."""
    return [note for k, f in enumerate(frames) if (note := _reading_set_aside(f, k)) is not None]


def frame_pose(frame: Frame) -> Pose:
    return Pose(
        np.asarray(frame.position_m, dtype=float),
        np.asarray(frame.R_world_to_cam, dtype=float),
        float(frame.capture_time_s),
    )


class FlightProcess:
    """Pairs frames, runs the pipeline under the deadline, reports results and telemetry."""

    def __init__(self, link, faults: FaultPlan, heartbeat_s: float = 0.25, prefault: bool = False) -> None:
        self.link = link
        # touch the heap a new camera's pairs will use when its Config arrives (flight_sw.warmup): the frames
        # are still on the line then, and no deadline runs
        self.prefault = prefault
        self.heap_ready_px = 0
        self.faults = faults
        self.heartbeat_s = heartbeat_s
        self.config: Config | None = None
        self.pending: dict[str, PendingPair] = {}
        # the pairs dropped half received, newest last: a late frame of one is said as dropped, not held as a new
        # half pair to be dropped and said a second time (QA of stop 65)
        self.dropped: deque[str] = deque(maxlen=4 * MAX_PENDING_PAIRS)
        # the pairs a frame of which was refused (no_config, bad_frame): their other frame gets no second Error
        # (protocol.md: one Error per pair; two read as two pairs on a board's console; QA of stop 85)
        self.refused: deque[str] = deque(maxlen=4 * MAX_PENDING_PAIRS)
        self.pairs_seen = 0
        # wire sizes (framed) of the last RESULT_HISTORY Results under the current Config, for the next pair's line
        # time: the largest of them, since a degraded Result can be smaller than the full one the next pair may reach
        self.result_bytes: list[int] = []
        self.last_output_s = 0.0  # encoding + handing over the last Result, in this process's clock
        # wall s per reserved unthrottled s of the mapping stages + fusion + output, on the last pairs
        self.reserve_ratios: list[float] = []
        self.fused: FusedMap | None = None  # the map fused over the descent so far
        # the last ground session's Config and fused map, until the new session's Config says whether it goes on
        self.resumable: tuple[Config, FusedMap | None] | None = None
        self.fusion_params = FusionParams()
        # the P(safe) fallback last said: once per camera size, on this process's log (a board's console)
        self.fallback_said = ""
        self._stop = threading.Event()

    def new_ground_session(self) -> None:
        """A new ground session (:mod:`flight_sw.board`): the pairs half received are dropped. The fused map goes
        on only if the session's Config is the last one's with the same ``descent_id`` (the same descent
        reconnected, e.g. after a noisy line lost the session); a ground that sends no ``descent_id`` cannot be
        told from the next run, so its descent starts afresh."""
        self.pending.clear()
        self.dropped.clear()  # the new session may send those pairs again, whole
        self.refused.clear()
        if self.config is not None:
            self.resumable = (self.config, self.fused)
        self.config = None
        self.fused = None

    # -- heartbeat -------------------------------------------------------------------------
    def _heartbeat_loop(self) -> None:
        n = 0
        while not self._stop.wait(self.heartbeat_s):
            n += 1
            try:
                self.link.send(Heartbeat(time_s=time.monotonic(), counter=n))
            except (OSError, InputError):  # the link is closed: nobody to beat for
                return

    # -- message handling ------------------------------------------------------------------
    def handle(self, msg: object) -> None:
        if isinstance(msg, Config):
            try:
                cam = Camera.from_dict(msg.camera)
                for name, default in (("elevation_step", DEFAULT_ELEVATION_STEP), ("psafe_step", DEFAULT_PSAFE_STEP)):
                    step = msg.options.get(name, default)
                    if not _is_int(step) or not 1 <= step <= 1024:
                        raise InputError(f"Config option {name} must be an integer in [1, 1024], got {step}")
                unit = msg.options.get("elevation_unit_cm", DEFAULT_ELEVATION_UNIT_CM)
                if not _is_int(unit) or not 1 <= unit <= 1000:
                    raise InputError(f"Config option elevation_unit_cm must be an integer in [1, 1000], got {unit}")
                if not msg.options.get("time_scale", 1.0) > 0 or not msg.options.get("link_baud", 0) >= 0:
                    raise InputError("Config options time_scale must be > 0 and link_baud >= 0")
                if msg.options.get("fusion", DEFAULT_FUSION) not in (0, 1):
                    raise InputError(f"Config option fusion must be 0 or 1, got {msg.options.get('fusion')}")
                rev = msg.options.get("result_rev", 0)
                if not _is_int(rev) or rev < 0:
                    raise InputError(
                        f"Config option result_rev must be a whole number >= 0 (the newest Result revision the "
                        f"ground decodes), got {rev}"
                    )
            except InputError as exc:
                self.link.send(Error(code="bad_config", text=str(exc)))
                return
            resumed, self.resumable = self.resumable, None
            if resumed is not None and "descent_id" in msg.options and msg == resumed[0]:
                self.config, self.fused = resumed  # the same descent in a new ground session
                if self.fused is not None:
                    print(
                        "flight: the same descent (its descent_id): its fused map goes on", file=sys.stderr, flush=True
                    )
            elif resumed is not None and resumed[1] is not None:  # said: the ground's summary cannot know it
                print(
                    "flight: another descent (or a ground that names none): its fused map starts afresh",
                    file=sys.stderr,
                    flush=True,
                )
            # the same descent only when the Config is the same and names it: a ground that names none and flies
            # a second descent with the same camera and budget had its map fused onto the first's (another
            # world frame; review of stop 64), and its half-received pairs paired with the new descent's frames
            same = self.config is not None and msg == self.config and "descent_id" in msg.options
            if not same:
                if self.fused is not None and self.config is not None and msg == self.config:
                    print(
                        "flight: a Config again, naming no descent_id: its fused map starts afresh (a second descent "
                        "cannot be told from a resend)",
                        file=sys.stderr,
                        flush=True,
                    )
                self.fused = None
                self.dropped.clear()  # a new descent may use the old one's pair ids
                for pid, gone in self.pending.items():  # each said: a ground waiting on them would time out blind
                    self._say_dropped(pid, gone, "a new descent's Config came before its other frame")
                self.pending.clear()
                note = left_out_note(msg)
                if note:  # once per descent, not per Result
                    print(f"flight: {note}", file=sys.stderr, flush=True)
                mismatch = baud_mismatch_note(msg.options.get("link_baud", 0), getattr(self.link, "baud", None))
                if mismatch:
                    print(f"flight: {mismatch}", file=sys.stderr, flush=True)
            self.config = msg
            self.refused.clear()  # refused for want of this Config, or for another camera: they may come again
            if self.prefault and cam.width * cam.height > self.heap_ready_px:
                from flight_sw.warmup import heap_mib_for, prefault_heap

                prefault_heap(heap_mib_for(cam.width, cam.height))
                self.heap_ready_px = cam.width * cam.height
            self.result_bytes = []  # other grid steps or maps: the sizes seen so far no longer apply
            self.reserve_ratios = []  # another budget or camera: what the reserves cost is measured anew
        elif isinstance(msg, Frame):
            self._on_frame(msg)
        elif isinstance(msg, Hello):
            # the HIL server passes on a new ground's Hello: the old session's half pairs can never complete (their
            # ids carry the old session), and the server has recorded them already (QA 65f L1)
            self.new_ground_session()

    @staticmethod
    def _ignore_frame(pid: str, why: str) -> None:
        """A frame of a pair already answered with an Error: logged, not answered again (one Error per pair)."""
        print(f"flight: pair {pid!r}: its other frame ignored: {why}", file=sys.stderr, flush=True)

    def _refuse(self, frame: Frame, code: str, text: str) -> None:
        """One Error per pair for a frame refused before its pair is whole: its other frame is only logged."""
        pid = frame.pair_id
        if pid is not None and pid in self.refused:
            self._ignore_frame(pid, f"the pair was answered with an Error ({code}: {text})")
            return
        if pid is not None:
            self.refused.append(pid)
            self.pending.pop(pid, None)  # a frame of it held whole: the pair is over
        self.link.send(Error(code=code, text=text, seq=frame.seq))

    def _on_frame(self, frame: Frame) -> None:
        now = time.monotonic()
        if self.config is None:
            self._refuse(frame, "no_config", "frame received before Config")
            return
        if frame.pair_id is None or frame.frame_index not in (0, 1):
            self._refuse(frame, "bad_frame", "frame needs pair_id and frame_index 0 (upper) or 1 (lower)")
            return
        if frame.pair_id in self.refused:
            self._ignore_frame(frame.pair_id, "the pair was answered with an Error")
            return
        cam = Camera.from_dict(self.config.camera)
        if frame.image.shape != (cam.height, cam.width):
            self._refuse(frame, "bad_frame", f"image shape {frame.image.shape} != camera {cam.height}x{cam.width}")
            return
        if frame.pair_id in self.dropped:  # its frame_dropped Error went when it was dropped: one per pair
            self._ignore_frame(frame.pair_id, "the pair was dropped half received (Error frame_dropped)")
            return
        if frame.pair_id not in self.pending and len(self.pending) >= MAX_PENDING_PAIRS:
            oldest = min(self.pending, key=lambda k: self.pending[k].arrival)
            self.dropped.append(oldest)
            why = f"its other frame did not come before {MAX_PENDING_PAIRS} newer pairs began"
            self._say_dropped(oldest, self.pending.pop(oldest), why)
        pend = self.pending.setdefault(frame.pair_id, PendingPair())
        pend.frames[frame.frame_index] = frame
        pend.arrival = now
        if len(pend.frames) == 2:
            del self.pending[frame.pair_id]
            self._process(pend)

    def _say_dropped(self, pair_id: str, pend: PendingPair, why: str) -> None:
        """The Error ``frame_dropped`` for a pair dropped half received, about a frame of it the ground sent."""
        seq = next(iter(pend.frames.values())).seq
        self.link.send(Error(code="frame_dropped", seq=seq, text=f"pair {pair_id!r}: {why}"))

    def _process(self, pend: PendingPair) -> None:
        cfg = self.config
        assert cfg is not None
        upper, lower = pend.frames[0], pend.frames[1]
        seqs = (upper.seq, lower.seq)
        start = time.monotonic()
        cpu0 = time.process_time()
        queue_wait = start - pend.arrival
        acknowledged = getattr(self.link, "acknowledged", None)
        self.faults.trigger(self.pairs_seen, None if acknowledged is None else lambda: acknowledged(1.0))
        self.pairs_seen += 1
        time_scale = float(cfg.options.get("time_scale", 1.0))
        fusion = bool(cfg.options.get("fusion", DEFAULT_FUSION))
        baud = float(cfg.options.get("link_baud", 0))
        line_s = expected_line_s(self.expected_result_bytes(cfg), baud)
        # what follows the pipeline, in unthrottled seconds: the pipeline reserves it at the slowdown it
        # measures (which can exceed time_scale at low duty cycles); a longer last measurement counts too
        # building and encoding the Result; fusing and sites on the fused map
        after_s = output_reserve_s(self.expected_result_bytes(cfg)) + (FUSION_RESERVE_S if fusion else 0.0)
        due = pend.arrival + cfg.deadline_s * (1.0 - DEADLINE_GUARD)  # what the plan aims at
        deadline_at = due - line_s - max(0.0, self.last_output_s - after_s * time_scale)
        try:
            aside = [_reading_set_aside(f, k) for k, f in enumerate((upper, lower))]  # judged once, used twice
            res = run_pipeline(
                np.asarray(upper.image),
                np.asarray(lower.image),
                frame_pose(upper),
                frame_pose(lower),
                Camera.from_dict(cfg.camera),
                preset=cfg.preset or "fast",
                deadline_at=deadline_at,
                # NaN: no reading; both, so that a position the lower frame's reading contradicts is said
                altimeter_m=[math.nan if aside[k] else float(f.altimeter_m) for k, f in enumerate((upper, lower))],
                sun_elevation_deg=upper.sun_elevation_deg,  # None: not sent
                sun_azimuth_deg=upper.sun_azimuth_deg,
                # the emulated processor's slowdown (1 / CPU fraction), when the supervisor sends it
                time_scale=time_scale,
                after_s=after_s,
                reserve_measured=max(self.reserve_ratios) if self.reserve_ratios else None,
            )
        except InputError as exc:
            self.link.send(Error(code="bad_input", text=str(exc), seq=lower.seq))
            return
        except Exception as exc:  # a flight bug must not kill the loop: report and go on
            self.link.send(Error(code="pipeline_failure", text=f"{type(exc).__name__}: {exc}", seq=lower.seq))
            return
        if ignored := [note for note in aside if note is not None]:
            res.info["altimeter_readings_ignored"] = ignored
        # the Result has no words: the Telemetry carries the first few (revision 5), the flight log every one
        withheld = ground_words(str(res.info.get("sites_withheld") or ""))
        side = min(np.shape(upper.image)[:2])
        for note in pair_notes(res.info, side):
            if note not in withheld:  # an altimeter disagreement is the withheld sites' reason: said once
                print(f"flight: frames {list(seqs)}: {note}", file=sys.stderr, flush=True)
        fallback = str(res.info.get("psafe_fallback") or "")
        if fallback and fallback != self.fallback_said:  # `process` warned of it, a board said nothing (QA of stop 79)
            self.fallback_said = fallback
            print(f"flight: {fallback}: P(safe) falls back to the Gaussian rule, whose FP is higher "
                  "(docs/benchmarks/pipeline.md)", file=sys.stderr, flush=True)  # fmt: skip
        if withheld:
            print(
                f"flight: frames {list(seqs)}: {withheld}" + ("; it is not fused into the descent's map" * fusion),
                file=sys.stderr,
                flush=True,
            )
        grid, sites, reason = res.grid, res.sites, res.info.get("no_site_reason")
        if fusion:
            w0, c0 = time.perf_counter(), time.thread_time()
            grid, sites, reason = self._fuse(res)
            res.timings["fusion"] = {"wall_s": time.perf_counter() - w0, "cpu_s": time.thread_time() - c0}
        t_out, cpu_out = time.monotonic(), time.thread_time()
        sent0 = self._bytes_sent()
        try:
            rebuild = functools.partial(self._result_message, res, seqs, cfg, grid, sites, reason)
            planned_line_s = line_s  # the plan's, for its Telemetry: the fitted Result's own is below
            result, line_s, grown, encoded = fit_to_line(rebuild(), rebuild, baud, due, line_s)
            result_id = self.link.send(encoded or result)  # encodes here, in this thread, unless fitting it did
        except InputError as exc:  # e.g. a value the schema refuses: report it, keep flying
            self.link.send(Error(code="result_encoding", text=str(exc), seq=lower.seq))
            return
        done = time.monotonic()
        self.last_output_s = done - t_out
        # building, fitting and encoding the Result: in the telemetry, so that its stages add up to the latency
        res.timings["output"] = {"wall_s": self.last_output_s, "cpu_s": time.thread_time() - cpu_out}
        fusion_wall = float(res.timings.get("fusion", {}).get("wall_s", 0.0))
        ratio = measured_reserve_ratio(
            res.timings,
            res.info,
            res.level,
            fusion_wall + self.last_output_s,
            after_s,
            int(np.asarray(upper.image).size),
        )
        if ratio is not None:
            self.reserve_ratios = [*self.reserve_ratios, ratio][-RESERVE_HISTORY:]
        link_info: dict[str, float] = {}
        port_baud = getattr(self.link, "baud", None)  # a board's serial port: the ground notes a rate unlike its own
        if isinstance(port_baud, int) and port_baud > 0:
            link_info["port_baud"] = float(port_baud)
        link_info.update(line_damage(link_stats(self.link)))
        if self.link.flush(timeout=5.0):  # handed over (local link): its framed size plans the next pair
            self.note_result_bytes(int(grown * (self._bytes_sent() - sent0)))  # at the Config's steps
            # a board: the Result's own line time on the ground link, first byte out -> last (under the HIL
            # server the link is the local one, and the server reports the ground link's time in its place)
            times = self.link.times(result_id) if result_id is not None and hasattr(self.link, "times") else None
            if times is not None and times.line_s is not None:
                link_info["result_link_s"] = float(times.line_s)
            queued = times.queue_s if times is not None else None
            if queued is not None:
                link_info["result_queue_s"] = queued
        self.link.send(
            Telemetry(
                frame_seqs=seqs,
                stages={k: {"wall_s": float(v["wall_s"]), "cpu_s": float(v["cpu_s"])} for k, v in res.timings.items()},
                queue_wait_s=queue_wait,
                total_latency_s=done - pend.arrival,
                cpu_fraction=(time.process_time() - cpu0) / max(done - start, 1e-9),
                # a board's own memory (its report said "not reported"); the HIL server puts its watchdog's in place
                peak_rss_bytes=min((private_rss_bytes() or (0, 0))[1], MAX_RSS_BYTES),
                deadline_s=float(cfg.deadline_s),
                # the flight side's own view (compute + expected line time); the ground judges the real one
                deadline_met=(done - pend.arrival) + line_s <= cfg.deadline_s,
                # the line time the plan kept, beside the budget it left: the fitted Result's (0.42 s) beside a
                # budget cut by the planned 9.6 s read as a contradiction (QA of stop 85)
                plan=plan_telemetry(res.info, deadline_at - start, planned_line_s),
                link=link_info,
                pose=pose_figures(res.info),
                pose_verdict=pose_verdict(res.info),
                notes=pair_notes(res.info, side, MAX_NOTES, MAX_NOTE_CHARS),
            ).for_rev(result_rev(cfg))
        )

    def _bytes_sent(self) -> float:
        return float(link_stats(self.link).get("bytes_sent", 0))

    def note_result_bytes(self, nbytes: int) -> None:
        """Remember a Result's framed size; only the last ``RESULT_HISTORY`` plan the next line time."""
        self.result_bytes = [*self.result_bytes, int(nbytes)][-RESULT_HISTORY:]

    def expected_result_bytes(self, cfg: Config) -> float:
        """The next Result's size on the wire: the largest of the last ``RESULT_HISTORY`` (x ``RESULT_MARGIN``), at
        least half the camera prior (bytes).

        The floor matters after a degraded Result: an image-only one is a few kB, and planning the next
        full-level Result's line time from it missed the deadline (demo, 300/150: 2.21 s against 2 s).
        Only the last few count because the size follows the descent: on an approach the fused map of the
        highest pairs (a large oblique grid, with elevations) was 50-63 kB, the lowest pairs' 5-25 kB, and
        planning those with 0.87 s of line time kept them image-only (docs/hil.md, stop 32).
        """
        prior = self._prior_result_bytes(cfg)
        if self.result_bytes:
            return max(RESULT_MARGIN * max(self.result_bytes), PRIOR_FLOOR * prior)
        return prior

    @staticmethod
    def _prior_result_bytes(cfg: Config) -> float:
        cam = cfg.camera
        cells = int(cam["width"]) * int(cam["height"]) / 4.0
        kp = int(cfg.options.get("psafe_step", DEFAULT_PSAFE_STEP))
        k = int(cfg.options.get("elevation_step", DEFAULT_ELEVATION_STEP))
        unit = int(cfg.options.get("elevation_unit_cm", DEFAULT_ELEVATION_UNIT_CM))
        elev = PRIOR_ELEV_B * max(PRIOR_UNIT_FLOOR, 1.0 - PRIOR_UNIT_SHRINK * math.log2(unit))
        maps = PRIOR_MAPS_B * 4 * cells if cfg.options.get("full_maps", 0) else 0.0
        return cells * (PRIOR_STATE_B + PRIOR_PSAFE_B / kp**2 + elev / k**2) + PRIOR_FIXED_B + maps

    def _fuse(self, res) -> tuple[HazardGrid, list[SiteResult], str | None]:
        """Fold one pair's result into the descent's map; the fused grid and the sites chosen on it.

        A pair whose own map offers no site because its sensors disagree or its images contradict a pose
        (``info["sites_withheld"]``) is not folded in: its evidence would stay in the map every later site is
        chosen on. Its Result reports the map fused so far (its own if there is none yet), with no site."""
        p = res.params
        # the fused map decides at the pipeline's own P floor and counts the model's prior once (fusion.py)
        prm = params_for(p, res.info, self.fusion_params)
        withheld = res.info.get("sites_withheld")
        if withheld:
            return (res.grid if self.fused is None else to_hazard_grid(self.fused, prm)), [], str(withheld)
        before = 0 if self.fused is None else self.fused.kept_dropped
        self.fused = fuse(self.fused, res.grid, prm, level=str(res.level))
        if self.fused.kept_dropped > before:  # said, not dropped silently: the map forgets these hazards
            print(
                f"flight: {self.fused.kept_dropped - before} hazard calls kept off the map's grid were dropped, the "
                f"oldest first (at most {MAX_KEPT_HAZARDS} are kept)",
                file=sys.stderr,
                flush=True,
            )
        grid = to_hazard_grid(self.fused, prm)
        footprint = float(p.get("footprint_m", PRESETS["fast"].footprint_m))
        n_sites = int(p.get("n_sites", PRESETS["fast"].n_sites))
        margin = float(p.get("site_margin_m", PRESETS["fast"].site_margin_m))
        relief = float(p.get("site_relief_max_m", PRESETS["fast"].site_relief_max_m))
        window = float(p.get("site_relief_window_m", PRESETS["fast"].site_relief_window_m))
        reach = float(p.get("site_reach_cells", PRESETS["fast"].site_reach_cells))
        sites, reason = select_safe_sites(
            grid, footprint, (0.0, 0.0), n_sites, margin, relief_max_m=relief, relief_window_m=window, reach_cells=reach
        )
        beyond = res.info.get("psafe_beyond_scale")
        if reason and beyond:  # why this pair called nothing safe, as its own map says it (sites QA of stop 75)
            reason = f"{beyond} ({reason})"
        if reason and "sites" in res.info.get("skipped", ()):
            # the pair's own search gave way to the deadline and the fused map's ran: a row listing "sites" among the
            # skipped stages beside a reason about the map read as a contradiction (QA of stop 84)
            reason = f"{reason}, on the descent's fused map (this pair's own site search was skipped for the deadline)"
        return grid, sites, (reason or None)

    @staticmethod
    def _result_message(
        res,
        seqs: tuple[int, int],
        cfg: Config,
        grid: HazardGrid,
        sites: list,
        reason: str | None,
        steps: tuple[int, int] | None = None,
    ) -> Result:
        """The compact Result (docs/protocol.md): uint8 states and P(safe), int16 elevation, sites; ``steps``
        (elevation, P(safe)) instead of the Config's."""
        full = bool(cfg.options.get("full_maps", 0))
        step = int(cfg.options.get("elevation_step", DEFAULT_ELEVATION_STEP))
        pstep = int(cfg.options.get("psafe_step", DEFAULT_PSAFE_STEP))
        if steps is not None:
            step, pstep = steps
        unit = int(cfg.options.get("elevation_unit_cm", DEFAULT_ELEVATION_UNIT_CM))
        elevation, offset = elevation_to_wire(grid.reported_elevation, step, unit)
        fills = None  # the pixels of elevation_image that are gap fills (none from a back-end that does not fill)
        if full:
            fills = filled_to_wire(res.filled if res.filled is not None else np.zeros(np.shape(res.elevation), bool))
        result = Result(
            frame_seqs=seqs,
            state_grid=np.asarray(grid.state, dtype=np.uint8),
            psafe_grid=psafe_to_wire(grid.psafe, pstep, coarse=np.asarray(grid.state) != STATE_SAFE),
            psafe_step=pstep,
            elevation_grid=elevation,
            grid_origin_xy=tuple(float(v) for v in grid.origin_xy),
            grid_cell_m=float(grid.cell_m),
            elevation_step=step,
            elevation_offset_m=offset,
            elevation_unit_cm=unit,
            sites=[
                Site(s.x, s.y, s.z, s.hazard, s.margin, s.distance_m, float(s.p_safe), float(s.clearance_m))
                for s in sites
            ],
            no_site_reason=None if reason is None else _clip(ground_words(str(reason)), 256),
            degraded=bool(res.degraded),
            level=str(res.level),
            # why a Result at level full can still be degraded: the stages that no longer fit
            skipped=tuple(str(n) for n in res.info.get("skipped", ()))[:MAX_SKIPPED],
            hazard_image=np.asarray(res.hazard, dtype=np.float32) if full else None,
            elevation_image=np.asarray(res.elevation, dtype=np.float32) if full else None,
            state_image=np.asarray(res.state, dtype=np.uint8) if full else None,
            # which elevations are gap fills (all 0 from a back-end or a map without any)
            elevation_filled=filled_to_wire(grid.filled, step),
            elevation_filled_image=fills,
        ).for_rev(result_rev(cfg))  # only the fields the ground decodes
        msg = result.validated()
        assert isinstance(msg, Result)
        return msg

    def run(self, watch_parent: bool = True) -> int:
        """Serve until the link closes or, with ``watch_parent``, the supervisor that started this process is gone
        (a board of one's own, :mod:`flight_sw.board`, serves whoever started it)."""
        parent = os.getppid()
        self.link.send(Hello(role="flight"))
        hb = threading.Thread(target=self._heartbeat_loop, name="heartbeat", daemon=True)
        hb.start()
        from protocol.links import LinkClosed

        try:
            while True:
                try:
                    msg = self.link.recv(timeout=1.0)
                except LinkClosed:  # the supervisor closed its end: nobody to report to
                    return 0
                if msg is not None:
                    self.handle(msg)
                elif watch_parent and os.getppid() != parent:  # the supervisor is gone: nobody to report to
                    return 0
        finally:
            self._stop.set()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m flight_sw.flight_main", description=__doc__.splitlines()[0])
    ap.add_argument("--fd", type=int, required=True, help="inherited socket file descriptor to the supervisor")
    ap.add_argument("--heartbeat", type=float, default=0.25, help="heartbeat period (s)")
    ap.add_argument("--fault", default=None, help="test fault injection: crash@N, hang@N, oom@N")
    ap.add_argument(
        "--no-warm-up",
        dest="warm_up",
        action="store_false",
        help="skip the boot warm-up (flight_sw.warmup): the first pair then pays the one-off set-up costs",
    )
    args = ap.parse_args(argv)
    import cv2

    cv2.setNumThreads(1)  # one core, one thread: the emulated processor has no pool
    prefault = False
    if args.warm_up:  # before Hello, so outside every deadline
        from flight_sw.warmup import boot_warm_up

        w = boot_warm_up(PRESETS["fast"])
        prefault = bool(w["allocator_settled"])
        print(
            f"flight: boot warm-up {w['cpu_s']:.3f} s CPU ({w['size_px']} px pair, level {w['level']}, "
            f"allocator settled: {w['allocator_settled']})",
            file=sys.stderr,
            flush=True,
        )
    from protocol.links import LOCAL_CONFIG, StreamLink

    sock = socket.socket(fileno=args.fd)
    link = StreamLink(sock, config=LOCAL_CONFIG, name="supervisor")
    try:
        return FlightProcess(link, FaultPlan.parse(args.fault), args.heartbeat, prefault).run()
    except MemoryError:  # the emulated memory ceiling: say so by exit status, not a traceback
        os._exit(EXIT_MEMORY)
    finally:
        link.close()


def _clip(text: str, n: int) -> str:
    """``text`` in at most ``n`` characters, cut at a word with an ellipsis (one read "... where its al")."""
    if len(text) <= n:
        return text
    return text[: n - 1].rsplit(" ", 1)[0].rstrip(",;:") + "…"


if __name__ == "__main__":
    sys.exit(main())
