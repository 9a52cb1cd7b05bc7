"""End-to-end HIL runs: ground simulator -> link -> supervisor -> emulated flight processor.

``run_descent`` renders (or reuses) a scenario's pairs, starts the supervisor
and the ground streamer as separate OS processes connected over a pty pair
(serial) or ZeroMQ on loopback, waits for the descent to finish, scores every
result against ground truth and writes::

    OUT/pairs/...            rendered pair directories + manifest.json
    OUT/keys/                CURVE keys of this run (ZeroMQ; files mode 0600)
    OUT/ground.log           the ground simulator's console lines (its last one is the reason if it fails)
    OUT/received/            what came back: results.jsonl + arrays per pair; ground.json, the ground's counters
                             (``refused_messages`` from the flight side, the last one's type and reason, and
                             ``line``: the damaged frames its link dropped and its retransmissions)
    OUT/telemetry.jsonl      per pair, measured at the ground: e2e_latency_s, the deadline verdict, the flight
                             latency, the frames' and the Result's line times, the flight's stages
    OUT/supervisor.jsonl     the HIL server's own log: its view of each pair, restarts, hangs, counters
    OUT/summary.json         e2e and flight latency p50/p95/max, deadline hit rate, per-pair scores;
                             ``complete`` false with a ``reason`` when the run was cut short
    OUT/summary.md           the same as a table
    OUT/report.html          tables and pictures for people

The deadline is judged at the ground on ``e2e_latency_s`` (docs/hil.md). The flight side is one of:

* ``flight="emulated"`` (default): our flight software, or the user's program given by ``flight_cmd``,
  under the supervisor on the budget's emulated processor;
* ``flight="external"``: a flight computer outside, reached through ``link`` given as a full spec
  (``serial:/dev/ttyUSB0@115200``, ``zmq:tcp://HOST:PORT``); no supervisor, no budget.

Shutdown: SIGINT and SIGTERM end the run at once: the ground, then the supervisor (each leads its own
process group; SIGTERM, then SIGKILL after :data:`GRACE_S`), the supervisor takes its flight process with
it. Every output file is written beside and renamed; ``summary.json`` exists from the start (``complete``
false until the run has ended normally).
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
import warnings
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, replace
from itertools import pairwise
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from flight_sw.kernels import kernels_note, missing_kernels
from ground_sim.results_file import read_results
from hil_server.budgets import (
    HOST_RATE_TOLERANCE,
    THROTTLE_CHECK_TOLERANCE,
    UNCALIBRATED_SAID,
    Budget,
    Duty,
    HostCalibration,
    ThrottleCheck,
    UncalibratedWarning,
    rate_ratio,
)
from hil_server.procemu import PR_SET_PDEATHSIG, hil_cores, libc_prctl
from protocol.errors import InputError, os_error_text
from protocol.links import BITS_PER_BYTE
from protocol.messages import SITES_WITHHELD
from protocol.stall import StallClock

if TYPE_CHECKING:
    from protocol.pairdir import Camera

EXIT_LINK_LOST = 3  # ground_sim.stream: a link session was lost (its pairs are recorded as link_down)
EXIT_NO_HELLO = 5  # ground_sim.stream: the flight side never said Hello (every pair recorded as not_run)
# How long the ground waits for the flight side's first Hello, link session included. An external board answers
# within seconds once it is up: 2 min covers its boot. Our emulated flight process boots at the budget's duty
# cycle: its imports and warm-up, ~0.4 s of CPU, said Hello ~33 s after the start on rad750 (1.3 % duty) and ~68 s
# on gr740 (0.6 %) on the 2026-12-03 host; a user's program may need more, and the HIL server ends a run whose
# flight program cannot come up (exit 4), so the long wait is only a backstop there.
EXTERNAL_HELLO_TIMEOUT_S = 120.0
BOOT_CPU_S = 0.26  # our flight process's imports and warm-up in full-speed CPU s: booted in 20-30 s on rad750
# (0.0111 of full speed) and 40-50 s on gr740 (0.0054), stop 47
EMULATED_HELLO_TIMEOUT_S = 900.0
GRACE_S = 10.0  # a child asked to stop (SIGTERM) gets this long before SIGKILL
SUPERVISOR_POLL_S = 0.5  # how often the run checks that the HIL server is still up while the ground streams
SUPERVISOR_EXIT_S = 3.0  # after the ground's clean end, the HIL server's time to end its session and log its counters


def throttle_note(check: ThrottleCheck, applied: float) -> str:
    """One line on a run's throttle check: what each round measured and whether the duty cycle moved."""
    etas = ", then ".join(f"{e:.2f}" for e in check.rounds)
    what = (
        f"a throttled CPU-second does {etas} of a full-speed one at {check.duty:.2%} duty "
        f"(the calibration: {check.calibrated:.2f})"
    )
    tol = f"{THROTTLE_CHECK_TOLERANCE:.0%}"
    if check.adopted:
        return (
            f"{what}, beyond {tol} in each round: the duty cycle becomes {applied:.2%} for the same share in this "
            "run (the stored calibration is unchanged; `hazard-hil calibrate` measures it again)"
        )
    if len(check.rounds) > 1:
        return f"{what}; the second round did not confirm the first beyond {tol}, so the calibration stands"
    return f"{what}; within {tol}, the calibration stands"


def host_rate_note(summary: dict) -> str:
    """'WARNING: this host ran ...' from a run summary's ``host_rate_check`` when the host's full-speed rate just
    before the run was off its calibration's by more than :data:`~hil_server.budgets.HOST_RATE_TOLERANCE` ("" when
    it was not, or not measured): the budget then ran that much faster or slower than it stands for, and the
    throttle check's eta cannot show it (docs/hil.md section 4)."""
    rec = summary.get("host_rate_check") or {}
    now, then = rec.get("host_rate"), rec.get("calibrated_rate")
    r = rate_ratio(now, then)
    if not abs(r - 1.0) > HOST_RATE_TOLERANCE:  # NaN too: not measured
        return ""
    how = f"{r:.2g}x as fast as" if r > 1 else f"{1 / r:.2g}x slower than"
    return (
        f"WARNING: this host ran the reference workload {how} when it was calibrated ({now:.1f} "
        f"against {then:.1f} units per CPU-second) just before the run, so the budget ran about "
        f"that much {'faster' if r > 1 else 'slower'} than it stands for: `hazard-hil calibrate` in this hour"
    )


def budget_speed(budget: Budget, cal: HostCalibration | None, duty: Duty) -> dict:
    """What a budget stands for on this host, for the summary (``budget_speed``): its DMIPS, this core's, the share
    and slowdown, and the calibration they rest on (``calibrated_at`` None: an uncalibrated host, taken as fast as
    the anchor)."""
    if budget.is_host:
        return {"cpu_dmips": None, "share": 1.0}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UncalibratedWarning)  # said on the console already
        host = budget.host_dmips(cal)
    return {
        "cpu_dmips": budget.cpu_dmips,
        "host_dmips": host,
        "share": duty.effective,
        "slowdown": 1.0 / duty.effective,
        "duty": duty.applied,
        "faster_than_host": budget.outruns(host),
        "calibrated_at": None if cal is None else cal.measured_at,
        "calibration_key": None if cal is None else cal.key,
    }


def budget_note(summary: dict) -> str:
    """One sentence on what the run's budget stood for here, from a summary's ``budget_speed`` ("" without one)."""
    b = summary.get("budget_speed")
    name = summary.get("budget")
    if not b or not name:
        return ""
    own = f" (from {summary['budget_file']})" if summary.get("budget_file") else ""
    if b.get("cpu_dmips") is None:
        return f"budget {name}{own}: one core of this host at full speed"
    dmips, host = float(b["cpu_dmips"]), float(b["host_dmips"])
    when = (
        f"by the calibration of {b['calibrated_at']}"
        if b.get("calibrated_at")
        else "UNCALIBRATED: this host was taken as fast as the anchor; `hazard-hil calibrate` measures it"
    )
    if b.get("faster_than_host"):
        return (
            f"budget {name}{own} ({dmips:,.0f} DMIPS) is faster than this host's core ({host:,.0f} DMIPS, {when}): "
            "it ran at this core's full speed, so its verdict is pessimistic"
        )
    return (
        f"budget {name}{own}: {dmips:,.0f} DMIPS = {100 * float(b['share']):.3g} % of this host's core "
        f"({host:,.0f} DMIPS, {when}), {float(b['slowdown']):.3g}x slower than it; the throttle's duty cycle "
        + (
            f"{100 * float(b['duty']):.3g} % delivers that share"
            if b.get("calibrated_at")
            else f"{100 * float(b['duty']):.3g} % assumes a throttled CPU-second does a full one's work, not measured "
            "here (a calibration measures it, and run then checks it)"
        )
    )


def throttle_check_note(summary: dict) -> str:
    """'throttle check: ...' from a run summary's ``throttle_check`` ("" when the run did not check)."""
    check = summary.get("throttle_check")
    if not check:
        return ""
    c = ThrottleCheck.from_dict(check)
    return "throttle check: " + throttle_note(c, float(summary.get("cpu_fraction", math.nan)))


def boot_hint(fraction: float) -> str:
    """'; it boots in about 48 s at this speed (...)' when our flight process's boot (``BOOT_CPU_S``) takes long
    enough at ``fraction`` (of full speed, :class:`hil_server.budgets.Duty`) that the wait for its Hello would
    otherwise look like a hang; else ''."""
    if not fraction > 0:
        return ""
    boot_s = BOOT_CPU_S / fraction
    if boot_s < 10.0:
        return ""
    # a process busy on the same core halves what the duty cycle buys: the QA's loaded host took 2x this
    cpu = f"~{BOOT_CPU_S:g} s of full-speed CPU; longer when another process shares its core"
    return f"; it boots in about {boot_s:.0f} s at this speed (imports and warm-up, {cpu})"


@dataclass
class RunConfig:
    scenario: str = "vertical"
    link: str = "serial"  # serial | zmq; with flight="external" a full spec: serial:DEVICE[@BAUD] | zmq:ENDPOINT
    budget: str = "host"
    budget_file: Path | None = None  # a user's budget file (budgets.toml's format); None: the packaged one
    out: Path = Path("out/run")
    pairs: list[str] | None = None  # labels such as "600/300"; None = all
    seed: int = 0
    scene: str | None = None
    preset: str = "fast"
    pace: str = "lockstep"
    deadline_s: float | None = None  # None = the budget's
    baud: int | None = None  # None = the budget's (serial only)
    fault: str | None = None  # flight fault injection (tests)
    image_size: int | None = None  # render a smaller camera with the same FOV (tests, quick looks)
    manifest: Path | None = None  # stream these already-rendered pairs instead of rendering
    corrupt: float = 0.0  # serial only: per-byte drop, flip and duplicate rate on the line
    timeout_s: float = 900.0
    full_maps: bool = False  # Results also carry the full-resolution image maps
    fusion: bool = True  # True: Results report the map fused over the descent (flight_sw.fusion); False: each alone
    elevation_step: int | None = None  # elevation grid decimation; None = by line rate (ground_sim.stream)
    psafe_step: int | None = None  # P(safe) grid decimation; None = by line rate
    elevation_unit_cm: int | None = None  # elevation grid unit; None = by link (ground_sim.stream)
    insecure: bool = False  # zmq without CURVE (loopback debugging)
    link_timeout_s: float = 4.0  # a peer silent or stalled this long ends the link session
    # the ground's wait for the flight side's first Hello (s); None: EXTERNAL_/EMULATED_HELLO_TIMEOUT_S
    hello_timeout_s: float | None = None
    # after a lost session, the ground's wait for a new one, from the loss (ground_sim.stream)
    reconnect_timeout_s: float = 10.0
    link_fault: str | None = None  # supervisor test fault on the ground link: stall@N | exit@N
    # tests: the base of the ground's wait for a Result's Telemetry (s); None: ground_sim.stream.TELEMETRY_GRACE_S
    telemetry_grace_s: float | None = None
    # tests: how often the ground says the first Hello is still awaited (s); None: ground_sim.stream.HELLO_NOTE_S
    hello_note_s: float | None = None
    flight: str = "emulated"  # emulated (under the supervisor) | external (a flight computer on `link`)
    flight_cmd: str | None = None  # the user's flight program instead of ours (emulated only; docs/hil.md)
    keys: Path | None = None  # external zmq: the ground's CURVE key directory
    min_hit_rate: float | None = None  # exit code: pass at this deadline hit rate instead of every pair
    progress: bool = True  # the render progress bar (off: --no-progress)
    figures: bool = True  # report.html's pictures (off: --no-figures, the tables alone)
    # measure the throttle's efficiency at a slow budget's duty cycle before the run (budgets.ThrottleCheck)
    throttle_check: bool = True


def _free_tcp_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _render(cfg: RunConfig, pairs_dir: Path, log: Callable[[str], None]) -> Path:
    """The run's descent rendered into ``pairs_dir``. Stopped, it says what the directory holds: an earlier run's
    pairs stayed there unnamed, to be taken for this run's by a later ``--manifest`` (QA of stop 85)."""
    kwargs: dict = {}
    if cfg.scene:
        kwargs["scene"] = cfg.scene
    if cfg.image_size:
        kwargs["camera"] = scaled_camera(cfg.image_size)
    earlier: list[str] | None = None
    written: list[str] = []
    try:  # the line and the import too: a stop during either is a stop before the render wrote anything
        log(f"run: rendering {cfg.scenario} pairs into {pairs_dir}")
        from ground_sim.descent import earlier_render, render_scenario

        earlier = earlier_render(pairs_dir) if pairs_dir.is_dir() else []
        return Path(
            render_scenario(
                cfg.scenario,
                pairs_dir,
                seed=cfg.seed,
                pairs=cfg.pairs,
                progress=cfg.progress,
                written=written,
                **kwargs,
            )
        )
    except (KeyboardInterrupt, OSError, _Interrupted):  # a stop, or a full disk
        from ground_sim.descent import earlier_render, kept_after_stop

        if earlier is None:  # stopped before the render began: what the directory holds is all earlier
            earlier = earlier_render(pairs_dir) if pairs_dir.is_dir() else []
        log(kept_after_stop(pairs_dir, written, earlier))
        raise


def scaled_camera(size: int) -> Camera:
    """The thesis camera's 30 deg FOV on a ``size`` x ``size`` sensor (``--image-size``)."""
    from protocol.pairdir import square_camera

    return square_camera(size)


def percentile(values: list[float], q: float) -> float:
    return float(np.percentile(values, q)) if values else float("nan")


DERIVED_TRUTH_FILE = "truth_hazard_derived.npy"  # in a pair's received/ directory: the truth its scores used


def score_records(records: list[dict]) -> list[dict]:
    """Add detection and DEM scores (ground truth of each pair) to the received records.

    ``scores``: from the compact Result's world grids, per pixel of i1 through its true ground
    point (:mod:`ground_sim.gridscore`), with the landing sites judged by the design's site rule
    (``sites_n``, ``sites_truly_clear``, ``top_site_clear`` 1/0; each site's verdict in the record's
    ``site_truth``). A top site the pair's own upper image cannot judge (its footprint not wholly in view, no hazard
    seen: the fused map's site may lie on ground only an earlier pair saw) is judged on the truth of another pair of
    the same rendered scene that holds it (``top_site_judged_on``, that pair's label), else left without
    ``top_site_clear`` (not judged). ``scores_full``: from the full-resolution image maps, when the run asked for them
    (``--full-maps``).
    """
    from ground_sim.gridscore import (
        complete_truth,
        judge_sites,
        pixel_ground,
        score_grids,
        scored_area,
        site_verdict,
        true_pose_upper,
    )
    from ground_sim.scoring import confusion, dem_error_stats
    from protocol.pairdir import PairFormatError, read_pair
    from reports.html import save_npy_atomic  # whole or not at all, named when the disk refuses it

    scored: list[tuple[dict, Any]] = []  # (record, its pair) of the Results judged, for the sites of the others
    for rec in records:
        if rec.get("status") != "result" or "out_dir" not in rec:
            continue
        d = Path(rec["out_dir"])
        try:
            pair = read_pair(rec["pair_dir"])
        except PairFormatError as exc:  # read after the whole descent flew: it cost the run its summary (QA 71)
            rec["truth_note"] = f"its pair directory could not be read again for scoring: {exc}"
            continue
        try:  # after the whole descent flew: a derivation that fails costs this pair's scores, not the summary
            if note := complete_truth(pair):
                rec["truth_note"] = note
                if "hazard" in pair.truth:
                    rec["truth"] = "derived"
                    # kept for the report's figures, which would otherwise derive it again
                    save_npy_atomic(d / DERIVED_TRUTH_FILE, pair.truth["hazard"])
        except (MemoryError, ValueError, ArithmeticError) as exc:
            rec["truth_note"] = f"no gt_hazard_i1.npy, and deriving one failed ({type(exc).__name__}: {exc})"
        truth = pair.truth
        area = None  # the pixels scored (score_grids'): the full maps are scored over the same
        if (d / "state_grid.npy").is_file() and "depth" in truth and "hazard" in truth:
            elev = np.load(d / "elevation_grid.npy") if (d / "elevation_grid.npy").is_file() else None
            fills = d / "elevation_filled_grid.npy"
            scores, called = score_grids(
                pair,
                np.load(d / "state_grid.npy"),
                tuple(rec["grid_origin_xy"]),
                float(rec["grid_cell_m"]),
                elev,
                tuple(rec.get("elevation_origin_xy") or rec["grid_origin_xy"]),
                float(rec.get("elevation_cell_m") or rec["grid_cell_m"]),
                np.load(fills) if elev is not None and fills.is_file() else None,
            )
            sites = rec.get("sites") or []
            judged = judge_sites(pair, [(float(s["x"]), float(s["y"])) for s in sites])
            scores["sites_n"] = float(len(sites))
            scores["sites_truly_clear"] = float(sum(j["safe"] for j in judged))
            top = judged[0] if judged else None
            # the one a lander would take; one this image cannot judge (not wholly in view, nothing unsafe seen) is
            # neither clear nor not: the fused map's site may lie on ground an earlier pair saw
            if top is not None and site_verdict(top) is not None:
                scores["top_site_clear"] = float(top["safe"])
            rec["site_truth"] = judged
            rec["scores"] = scores
            scored.append((rec, pair))
            # the call per pixel for the report: 0 safe, 1 not, CALLED_UNSCORED unscored; uint8 where float32 was
            # 1 MiB at 512², most of a pair's output (stop 63's soak QA)
            save_npy_atomic(d / CALLED_FILE, np.where(np.isnan(called), CALLED_UNSCORED, called).astype(np.uint8))
            area = np.isfinite(called)  # called_map: NaN exactly off the scored area
        if (d / "hazard.npy").is_file() and "hazard" in truth:
            hazard = np.load(d / "hazard.npy")
            # over the ground the last frame sees, a NaN not called safe, as the grid's scores and `score` (it was
            # over the map's own coverage: a map of less scored a higher CDI; review of stop 64)
            if area is None and "depth" in truth:  # no grid scored: the same true overlap, from the truth
                area = scored_area(pair, pixel_ground(pair.camera, true_pose_upper(pair), truth["depth"]))
            if area is None:
                # without a true depth the overlap is unknown; the map's own coverage in its place scored a map of
                # less ground higher (review of stop 66), so nothing is scored, and the record says why
                rec["scores_full_note"] = "not scored: the pair has no true depth, so the area to score is unknown"
                continue
            c = confusion(hazard, truth["hazard"], area)
            full = {f"{k}_pct" if k in ("tp", "tn", "fp", "fn", "cdi") else k: float(v) for k, v in c.items()}
            if (d / "elevation.npy").is_file() and "elevation" in truth:
                st = dem_error_stats(np.load(d / "elevation.npy"), truth["elevation"], area)
                full.update({f"dem_{k}": float(v) for k, v in st.items()})
            rec["scores_full"] = full
    _judge_elsewhere(scored)
    return records


def _judge_elsewhere(scored: list[tuple[dict, Any]]) -> None:
    """Judge each top site its own pair could not on another pair of the same scene render (see score_records)."""
    from ground_sim.gridscore import judge_sites, site_verdict

    def scene(pair: Any) -> tuple | None:
        meta = pair.meta if isinstance(pair.meta, dict) else {}
        key = (meta.get("scene_spec"), meta.get("scene_seed"), meta.get("render_version"))
        return key if None not in key else None  # a hand-made pair: no other pair is known to share its ground

    for rec, pair in scored:
        if not rec.get("sites") or "top_site_clear" in rec["scores"] or scene(pair) is None:
            continue
        top = rec["sites"][0]
        for other, other_pair in scored:
            if other is rec or scene(other_pair) != scene(pair):
                continue
            (j,) = judge_sites(other_pair, [(float(top["x"]), float(top["y"]))])
            if site_verdict(j) is not None:
                rec["scores"]["top_site_clear"] = float(j["safe"])
                rec["top_site_judged_on"] = other["label"]
                break


def skipped_counts(records: list[dict]) -> dict[str, int]:
    """How many Results skipped each pipeline stage (a Result at level full can be degraded by these alone)."""
    out: dict[str, int] = {}
    for r in records:
        for name in r.get("skipped") or ():
            out[name] = out.get(name, 0) + 1
    return dict(sorted(out.items()))


def degraded_note(summary: dict) -> str:
    """'2 at a coarser level, 1 full with stages skipped (rocks, shading_slope)', or '' when none was degraded.

    A Result is degraded when it stopped below the full level or skipped a stage that no longer fitted; the two
    are told apart, since a full DEM without the rock cue is a different answer from no DEM."""
    n, coarser = int(summary.get("degraded") or 0), summary.get("coarser")
    if not n:
        return ""
    if coarser is None:  # a summary written before the two were counted apart
        return f"{n} degraded"
    parts = [f"{coarser} at a coarser level"] if coarser else []
    if n - coarser:
        full = [r for r in summary.get("records") or () if r.get("status") == "result" and r.get("level") == "full"]
        names = ", ".join(skipped_counts(full)) or "unnamed"
        parts.append(f"{n - coarser} full with stages skipped ({names})")
    return ", ".join(parts)


# the reference flight software's stages (flight_sw/pipeline.py, flight_main.py) by phase; a user's own flight
# program names its stages as it likes, and those count as "other". "mapping" is anytime.MAPPING_STAGES (what the
# plan's mapping reserve covers; tests/test_hil_run.py keeps the two in step)
STAGE_PHASES: dict[str, tuple[str, ...]] = {
    "before the DEM": ("validate", "pose_refine", "prepare", "rocks", "shadow", "range", "coverage"),
    "DEM": ("coarse_dem", "full_dem", "lower_dem", "gap_fill"),
    "mapping": ("georef", "grid", "slope", "shading_slope", "hazard", "sites"),
    "fusion": ("fusion",),
    "output": ("output",),
}


def phase_times(records: list[dict]) -> dict[str, float]:
    """Median wall seconds per phase of the flight's work (``STAGE_PHASES``, then "other") over the Results whose
    Telemetry timed their stages; {} when none did. Where a budget's time goes: on gr740 the mapping after the
    DEM, not the DEM (docs/hil.md section 1)."""
    phase_of = {stage: phase for phase, stages in STAGE_PHASES.items() for stage in stages}
    per_pair = []
    for r in records:
        stages = r.get("stages") if r.get("status") == "result" else None
        if not stages or set(stages) <= {"total"}:  # a flight that timed no stage: no phase to make up zeros for
            continue
        t = dict.fromkeys([*STAGE_PHASES, "other"], 0.0)
        for name, v in stages.items():
            if name != "total":
                t[phase_of.get(name, "other")] += float(v.get("wall_s", 0.0))
        per_pair.append(t)
    if not per_pair:
        return {}
    out = {k: percentile([t[k] for t in per_pair], 50) for k in per_pair[0]}
    return {k: v for k, v in out.items() if v > 0 or k in STAGE_PHASES}


def phase_note(summary: dict) -> str:
    """'flight time per pair, each phase's median: before the DEM 12.60 s, DEM 3.10 s, mapping 27.90 s (56 % of
    their sum), ...' (the largest phase with its share) or ''. Medians of phases need not add up to the median
    flight time: the note says so."""
    ph: dict[str, float] = summary.get("flight_phases_p50_s") or {}
    total = sum(ph.values())
    if not total > 0:
        return ""
    top = max(ph, key=lambda k: ph[k])
    parts = [f"{k} {v:.2f} s" + (f" ({100 * v / total:.0f} % of their sum)" if k == top else "") for k, v in ph.items()]
    return "flight time per pair, each phase's median (they need not add up to the median flight time): " + ", ".join(
        parts
    )


def site_summary(results: list[dict]) -> dict | None:
    """The landing sites of the Results judged against the truth (None when none could be): ``pairs`` judged,
    ``with_site``, ``top_clear`` (the top site's whole footprint truly clear), and the labels of the pairs whose top
    site was not clear and of those that offered none, with the flight side's reason."""
    judged = [r for r in results if "sites_n" in (r.get("scores") or {})]
    if not judged:
        return None
    offered = [r for r in judged if r["scores"]["sites_n"] > 0]
    return {
        "pairs": len(judged),
        "with_site": len(offered),
        "top_clear": sum(r["scores"].get("top_site_clear") == 1.0 for r in offered),
        "top_not_clear": [r["label"] for r in offered if r["scores"].get("top_site_clear") == 0.0],
        "top_not_judged": [r["label"] for r in offered if "top_site_clear" not in r["scores"]],
        "no_site": [{"label": r["label"], "reason": r.get("no_site_reason")} for r in judged if r not in offered],
    }


def site_note(summary: dict) -> str:
    """'landing sites: the top site truly clear on 2 of 2 pairs that offered one; 1 offered none (200/100: ...)'."""
    s = summary.get("sites")
    if not s:
        return ""
    judged = s["with_site"] - len(s.get("top_not_judged", []))
    parts = []
    if judged:
        clear = f"the top site truly clear on {s['top_clear']} of {judged} pairs that offered one"
        parts.append(clear + (f" (NOT clear: {', '.join(s['top_not_clear'])})" if s["top_not_clear"] else ""))
    if s.get("top_not_judged"):
        parts.append(
            f"{len(s['top_not_judged'])} not judged, its footprint not wholly in the pair's upper image "
            f"({', '.join(s['top_not_judged'])})"
        )
    withheld = [x for x in s["no_site"] if str(x.get("reason") or "").startswith(SITES_WITHHELD)]
    if withheld:  # a safety refusal is named first, each pair: it hid behind "and 2 more" (stop 60's QA)
        parts.append(
            f"the flight side withheld the sites of {len(withheld)} map(s) its own checks doubt ("
            + "; ".join(f"{x['label']}: {str(x['reason'])[len(SITES_WITHHELD) :].lstrip(': ')}" for x in withheld[:3])
            + (f"; and {len(withheld) - 3} more" if len(withheld) > 3 else "")
            + ")"
        )
    if s["no_site"]:
        first = s["no_site"][0]
        why = f": {first['reason']}" if first.get("reason") else ""
        more = f", and {len(s['no_site']) - 1} more" if len(s["no_site"]) > 1 else ""
        n = len(s["no_site"])
        parts.append(
            f"{'no pair offered a site' if n == s['pairs'] else f'{n} offered none'} ({first['label']}{why}{more})"
        )
    return "landing sites: " + "; ".join(parts)


def summarize(records: list[dict], cfg: RunConfig, extra: dict) -> dict:
    """Counts, deadline hit rate and latency percentiles over the records (the deadline judged on e2e)."""
    ok = [r for r in records if r.get("status") == "result"]

    def vals(key: str) -> list[float]:
        return [float(r[key]) for r in ok if r.get(key) is not None]

    e2e, flight, line = vals("e2e_latency_s"), vals("flight_latency_s"), vals("result_line_s")
    n = len(records)
    met = sum(1 for r in ok if r.get("deadline_met"))
    return {
        "scenario": cfg.scenario,
        "link": cfg.link,
        "flight": cfg.flight if not cfg.flight_cmd else f"command: {cfg.flight_cmd}",
        "budget": cfg.budget if cfg.flight == "emulated" else None,
        "budget_file": str(Path(cfg.budget_file).resolve()) if cfg.budget_file and cfg.flight == "emulated" else None,
        "preset": cfg.preset,
        "fusion": cfg.fusion,  # asked of the flight side (Config option): the scores are of what it reported
        # --corrupt: the per-byte drop, flip and duplicate rate injected on the line (0: a clean line)
        "line_corrupt_rate": cfg.corrupt,
        "full_maps_asked": bool(cfg.full_maps),
        "pairs": n,
        "results": len(ok),
        "degraded": sum(bool(r.get("degraded")) for r in ok),
        "coarser": sum(r.get("level") not in (None, "full") for r in ok),
        "stages_skipped": skipped_counts(ok),
        "errors": n - len(ok),
        "not_run": sum(r.get("code") == "not_run" for r in records),  # the run ended before their frames went
        "deadline_met": met,
        "deadline_missed": len(ok) - met,
        "deadline_hit_rate": met / n if n else float("nan"),
        "e2e_latency_p50_s": percentile(e2e, 50),
        "e2e_latency_p95_s": percentile(e2e, 95),
        "e2e_latency_max_s": max(e2e) if e2e else float("nan"),
        "flight_latency_p50_s": percentile(flight, 50),
        "flight_latency_p95_s": percentile(flight, 95),
        "flight_latency_max_s": max(flight) if flight else float("nan"),
        "result_line_max_s": max(line) if line else float("nan"),
        "result_bytes_max": max((r.get("result_bytes", 0) for r in records), default=0),
        "flight_phases_p50_s": phase_times(ok),
        **contention(ok),
        "sites": site_summary(ok),
        "pose": pose_summary(ok),
        "link_errors": sum(r.get("code") == "link_down" for r in records),
        **extra,
        "records": records,
    }


def pose_summary(records: list[dict]) -> dict:
    """What the flight side's Telemetry said of its pose refinement (revision 5) over the pairs with a Result:
    each verdict's count, the largest corrections applied (the relative rotation's, and a frame's own attitude's),
    and the flight side's notes per pair (its own judgement of which verdicts matter: below 256 px clean pairs fail
    the checks too). Empty when no Telemetry said (a flight side of revision 4 or below, a preset without
    refinement)."""
    said = [r for r in records if r.get("pose_verdict")]
    noted = [r for r in records if r.get("flight_notes")]
    if not said and not noted:
        return {}
    verdicts: dict[str, int] = {}
    for r in said:
        verdicts[r["pose_verdict"]] = verdicts.get(r["pose_verdict"], 0) + 1

    def largest(*keys: str) -> float | None:
        got = [
            float(v)
            for r in said
            if (r.get("pose") or {}).get("applied")
            for k in keys
            if isinstance(v := r["pose"].get(k), (int, float))
        ]
        return max(got) if got else None

    return {
        "verdicts": verdicts,
        "max_rotation_applied_deg": largest("rot_deg"),
        "max_attitude_applied_deg": largest("att1_deg", "att2_deg"),
        "noted": [{"label": r["label"], "notes": list(r["flight_notes"])} for r in noted],
    }


def pose_note(summary: dict) -> str:
    """'pose refinement: refined 2, kept 1 (largest correction applied: relative rotation 0.03 deg, a frame's
    attitude 0.15 deg); the flight side noted 2 thing(s) on 1 pair(s) (first, 200/100: ...)' ("" when no Telemetry
    said)."""
    p = summary.get("pose")
    if not p:
        return ""
    parts = []
    if p.get("verdicts"):
        counts = ", ".join(f"{v} {n}" for v, n in sorted(p["verdicts"].items(), key=lambda kv: -kv[1]))
        big = [
            f"{what} {v:.2f} deg"
            for what, v in (
                ("relative rotation", p.get("max_rotation_applied_deg")),
                ("a frame's attitude", p.get("max_attitude_applied_deg")),
            )
            if v is not None
        ]
        parts.append(f"pose refinement: {counts}" + (f" (largest correction applied: {', '.join(big)})" * bool(big)))
    if noted := p.get("noted"):
        n = sum(len(x["notes"]) for x in noted)
        first = noted[0]
        parts.append(
            f"the flight side noted {n} thing(s) on {len(noted)} pair(s) (first, {first['label']}: {first['notes'][0]})"
        )
    return "; ".join(parts)


CONTENTION_SHOWN_PCT = 5.0  # a run whose flight process waited this share of its flight time for its core says so


def contention(records: list[dict]) -> dict:
    """The flight process's wait for its core while other processes held it, over the pairs the HIL server measured
    it for (its ``flight_contention_s``): the seconds, and their share of those pairs' flight time. A latency
    regression on a busy host looked exactly like a slower program (QA of stop 73). Empty without a measurement
    (a board: its core is its own)."""
    got = [r for r in records if isinstance((r.get("link") or {}).get("flight_contention_s"), (int, float))]
    if not got:
        return {}
    wait = sum(float(r["link"]["flight_contention_s"]) for r in got)
    flight = sum(float(r.get("flight_latency_s") or 0.0) for r in got)
    return {"flight_contention_s": wait, "flight_contention_pct": 100.0 * wait / flight if flight > 0 else 0.0}


def contention_note(summary: dict) -> str:
    """A sentence when the flight process waited a notable share of its flight time for its core ("" otherwise)."""
    pct = summary.get("flight_contention_pct")
    if not isinstance(pct, (int, float)) or pct < CONTENTION_SHOWN_PCT:
        return ""
    return (
        # three significant figures: "waited 0.00 s ... 8 % of its flight time" read as a contradiction (QA of stop 78)
        f"host contention: the flight process waited {summary['flight_contention_s']:.3g} s for its core while other "
        f"processes held it, {pct:.0f} % of its flight time: its latencies read that much higher than the budget's "
        "alone (a loaded host, not the flight software)" + _shared_core(summary)
    )


def _shared_core(summary: dict) -> str:
    """'; ...' when the HIL's own processes ran on the flight's core (one core allowed to the run), else ''."""
    cores = summary.get("host_cores") or {}
    flight = cores.get("flight")
    names = {"ground": "ground", "hil_server": "HIL server", "line_relay": "serial line's relay"}
    shared = [n for k, n in names.items() if flight is not None and flight in (cores.get(k) or ())]
    if not shared:
        return ""
    return (
        f"; the {' and the '.join(shared)} shared its core (one core allowed to the run: `taskset -c A,B` gives "
        "them another)"
    )


# the returned summary's key (not in summary.json) for signal N that came while the summary was written
LATE_SIGNAL = "late_signal"


def exit_code(summary: dict, min_hit_rate: float | None = None) -> int:
    """0 only when every pair returned a result within its deadline (or the hit rate reaches ``min_hit_rate``);
    1 when a pair missed, was lost or failed, or the run did not complete; 128 + N when signal N cut it short or
    came while its summary was written (:data:`LATE_SIGNAL`)."""
    if summary.get("interrupted_by") or summary.get(LATE_SIGNAL):
        return 128 + int(summary.get("interrupted_by") or summary[LATE_SIGNAL])
    if not summary.get("complete") or not summary.get("pairs"):
        return 1
    if min_hit_rate is None:
        return 0 if summary["deadline_met"] == summary["pairs"] else 1
    return 0 if summary["deadline_hit_rate"] >= min_hit_rate - 1e-12 else 1


def verdict_line(summary: dict, min_hit_rate: float | None = None) -> str:
    s = summary
    if not s.get("complete"):
        head = f"INCOMPLETE ({s.get('reason')})"
    elif exit_code({k: v for k, v in s.items() if k != LATE_SIGNAL}, min_hit_rate) == 0:  # the run's own verdict
        head = "PASS"
    else:
        head = "FAIL"
    need = "every pair" if min_hit_rate is None else f"hit rate >= {min_hit_rate:.0%}"
    return (
        f"{head}: {s['deadline_met']}/{s['pairs']} pairs returned a result within the "
        f"{_fmt(s.get('deadline_s'), 'g')} s deadline end to end "
        f"({s['deadline_missed']} late, {_errors(s)}; needed: {need})"
        # a met deadline with a degraded answer is not the full answer: said beside the verdict, not only in the table
        + (f"; {degraded_note(s)}" if s.get("degraded") else "")
    )


def _errors(summary: dict) -> str:
    """'2 errors', '3 errors, 2 of them not run', or '2 not run' when every error is a pair the run never reached (an
    interrupt, a lost ground): "2 errors: 2 not run" called pairs that never ran errors first (QA of stop 80)."""
    e, n = int(summary.get("errors") or 0), int(summary.get("not_run") or 0)
    if n and n == e:
        return f"{n} not run"
    return f"{e} error{'s' * (e != 1)}" + (f", {n} of them not run" if n else "")


def _fmt(v, spec: str = ".2f") -> str:
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "—"
    return format(v, spec)


def _vs_deadline(v: float | None, deadline_s: float | None) -> str:
    """A latency beside its deadline with the decimals that keep their order (:func:`reports.console.apart`): at two
    decimals 0.5485 s "met" a 0.549 s deadline as 0.55, and 0.2046 s "MISSED" a 0.2 s one as 0.20 (QA of stop 85)."""
    if v is None or deadline_s is None or not (math.isfinite(v) and math.isfinite(deadline_s)):
        return _fmt(v)
    from reports.console import apart

    return apart(v, deadline_s)[0]


CALLED_FILE = "called_i1.npy"
CALLED_UNSCORED = 255  # called_i1.npy's value where the grid scores no pixel


def read_called(path: Path) -> np.ndarray:
    """``called_i1.npy`` as the float map the scores used: 0 safe, 1 not, NaN unscored (runs before stop 64 saved
    that float32 map itself)."""
    a = np.load(path)
    if a.dtype == np.uint8:
        return np.where(a == CALLED_UNSCORED, np.float32(np.nan), a.astype(np.float32))
    return a


# supervisor.jsonl events the summary keeps
FLIGHT_EVENTS = (
    "restart",
    "refused",
    "missing_telemetry",
    "stale_result",
    "stale_error",
    "stale_telemetry",
    "unexpected_message",
)
MAX_FLIGHT_EVENTS = 100  # a program that crashes or misbehaves on every pair: the summary keeps the last ones


def full_maps_note(summary: dict) -> str:
    """Said when ``--full-maps`` asked for the image maps and Results came without them ("" otherwise): a flight
    program that sends none passed without a word, and `score` on received/ then told the user to give the option
    already given (QA 64a, M3)."""
    if not summary.get("full_maps_asked"):
        return ""
    got = [r for r in summary.get("records", []) if r.get("status") == "result"]
    without = [r for r in got if not r.get("full_maps")]
    if not without:
        return ""
    return (
        f"--full-maps asked for the full-resolution image maps, and {len(without)} of {len(got)} Result(s) came "
        "without them (the flight program sends none?): `hazard-hil score` has no image map of those pairs"
    )


# a Result whose grid maps less of the scored ground than this (%) is said: the rest counts as not called safe.
# Ours leaves the overlap's rim unmapped (its overlap is from the reported poses, with an edge band): 91-97 % of
# the scored ground at 128 px, which is no news
MAPPED_SAID_PCT = 80.0


def off_map_note(summary: dict) -> str:
    """Results whose world grid maps none, or only part, of the scored ground ("" when every one maps it all): a
    flight program's grid origin with a sign error passed without a word, and a grid over part of the ground
    scored only that part until stop 64 (QA 64a); the unmapped rest now counts as not called safe."""
    scored = [r for r in summary.get("records", []) if r.get("scores") is not None]
    off = [r for r in scored if not r["scores"].get("mapped_pct", r["scores"].get("n"))]
    part = [r for r in scored if r not in off and r["scores"].get("mapped_pct", 100.0) < MAPPED_SAID_PCT]
    said = []
    if off:
        which = ", ".join(str(r.get("label")) for r in off[:5])
        said.append(
            f"{len(off)} Result(s) mapped none of the scored ground ({which}): every cell is marked outside, or the "
            "grid lies elsewhere (its origin, cell size or axes?), so all of it counts as not called safe"
        )
    if part:
        low = min(part, key=lambda r: r["scores"]["mapped_pct"])
        said.append(
            f"{len(part)} Result(s) mapped only part of the scored ground (least: {low.get('label')}, "
            f"{low['scores']['mapped_pct']:.1f} %); the rest counts as not called safe"
        )
    return "; ".join(said)


TSTP_NOTE = (
    "run: Ctrl-Z ignored: this run relays its loopback serial line itself, and stopped it would cut the line "
    "(Ctrl-C ends the run; a stalled ground: stop the ground_sim.stream process)\n"
)


def _relay_holds_tstp() -> Callable[[int, Any], None]:
    """A SIGTSTP handler for a run that relays its loopback serial line itself: a Ctrl-Z would stop the line with
    the run, and every pair then on it failed as link_down, the run recorded complete and FAIL (stop 63's QA).
    It says so on stderr with one ``os.write`` per Ctrl-Z: a ``print`` from the handler re-entered a print the
    main thread was blocked in (stdout piped to a stopped ``tee``) and raised there (review of stop 63)."""

    def hold(signum: int, frame: Any) -> None:
        with contextlib.suppress(OSError):
            os.write(2, TSTP_NOTE.encode())

    return hold


def noise_note(summary: dict) -> str:
    """Said when the run injected line noise (``--corrupt``): nothing in the outputs recorded the rate, and the
    retransmissions and refused frames it caused read as a bad line (stop 63's soak QA). "" on a clean line."""
    rate = float(summary.get("line_corrupt_rate") or 0.0)
    if rate <= 0:
        return ""
    faults = summary.get("line_faults") or {}
    kinds = ("dropped", "flipped", "duplicated")
    hit = sum(int(d.get(k) or 0) for d in faults.values() if isinstance(d, dict) for k in kinds)
    return (
        f"line noise was injected (--corrupt {rate:g}: each byte dropped, flipped or duplicated at that rate, both "
        f"ways; {hit} faults): the retransmissions and refused frames are its doing"
    )


def relay_stop_note(summary: dict) -> str:
    """Said when the run process was stopped (SIGSTOP, a paused VM) while it relayed the loopback serial line:
    the line stopped with it, so a link failure then is that stop's, not the line's ("" otherwise)."""
    stopped = float(summary.get("relay_stopped_s") or 0.0)
    if stopped <= 0:
        return ""
    return (
        f"the run process itself was not scheduled for {stopped:.1f} s while it relayed the loopback serial line "
        "(SIGSTOP, a paused VM): the line stopped with it, and pairs lost to the link meanwhile are that stop's"
    )


def server_stop_note(summary: dict) -> str:
    """Said when the HIL server itself went unscheduled (SIGSTOP, a starved host): the flight process's answers
    waited unread meanwhile, so a pair late or a Result ignored then is that stop's, not the flight software's ("" when
    it ran throughout; supervisor.log said it, the summary did not: QA of stop 72)."""
    stopped = float((summary.get("supervisor_counters") or {}).get("server_stopped_s") or 0.0)
    if stopped < 0.5:  # a scheduling hiccup, not a stop
        return ""
    return (
        f"the HIL server itself was not scheduled for {stopped:.1f} s in all (SIGSTOP, a starved host): the flight "
        "process's answers waited unread meanwhile, so pairs late or Results ignored then are that stop's"
    )


def ground_stop_note(summary: dict) -> str:
    """The pairs whose latency includes a stop of the ground process itself ("" when none): measured at the
    ground, an answer that came in time then reads as late."""
    hit = [r for r in summary.get("records", []) if r.get("ground_stopped_s")]
    if not hit:
        return ""
    most = max(float(r["ground_stopped_s"]) for r in hit)
    timed = [r for r in hit if r.get("e2e_latency_s") is not None]
    # a pair the stop left without a Result has no latency to include it (QA of stop 84: a link_down pair was said so)
    told = []
    if timed:
        told.append(f"{_labels(timed)}: {'its' if len(timed) == 1 else 'their'} end-to-end latency includes it")
    if len(timed) < len(hit):
        told.append(f"{_labels([r for r in hit if r not in timed])}: no Result, whose loss may be that stop's")
    return (
        f"the ground process itself was not scheduled for up to {most:.1f} s while {len(hit)} pair(s) were in "
        f"flight ({'; '.join(told)})"
    )


def _labels(records: list[dict], most: int = 5) -> str:
    """The first ``most`` records' pair labels, and how many more."""
    more = f" and {len(records) - most} more" if len(records) > most else ""
    return ", ".join(str(r.get("label")) for r in records[:most]) + more


def session_note(summary: dict) -> str:
    """One line on the link sessions with the flight side ("" when there was one and nothing lost it): a session
    lost or restarted mid-descent (a board stalled, killed and restarted, a line down) was said on the console as it
    happened and nowhere in the outputs, the run a PASS (stop 60's QA)."""
    g = (summary.get("ground_counters") or {}).get("link_sessions") or {}
    sessions, restarts, losses = (int(g.get(k) or 0) for k in ("sessions", "peer_restarts", "peer_losses"))
    server = int((summary.get("supervisor_counters") or {}).get("link_errors") or 0)
    foreign = int(g.get("foreign_hellos") or 0)
    if sessions <= 1 and not (restarts or losses or server or foreign):
        return ""
    many = "" if sessions == 1 else "s"
    parts = [f"{sessions} link session{many} with the flight side (one per descent when nothing fails)"]
    if restarts:
        parts.append(
            f"the flight side started {restarts} of them anew (it restarted, or gave up the last one: a restarted "
            "flight process fuses the later pairs into a new map)"
        )
    if losses:
        parts.append(f"{losses} ended early (the peer fell silent, closed or gave up, or this side did)")
    if foreign:
        parts.append(f"{foreign} HELLO(s) of another session came while the flight side talked, and were ignored "
                     "(another device on the line?)")  # fmt: skip
    if server:
        parts.append(f"the HIL server saw {server} link error{'' if server == 1 else 's'} on its ground link")
    return "; ".join(parts)


def flight_note(summary: dict) -> str:
    """One line on what the HIL server had to do about the flight process ("" when nothing): restarts, refused
    messages, missing Telemetry, dropped line garbage, with the last reason. Crashes between pairs cost no pair
    but are reported here; a run whose server counters are missing says so. Messages the ground itself refused
    (from an external flight computer, ``ground_counters``) are said after."""
    c = summary.get("supervisor_counters") or {}
    g = summary.get("ground_counters") or {}
    refused = int(g.get("refused_messages") or 0)
    ground = ""
    if refused:
        last = g.get("last_refused") or {}
        ground = f"the ground refused {refused} message{'' if refused == 1 else 's'} from the flight side" + (
            f" (last: {last.get('type')}: {last.get('reason')})" if last else ""
        )
    ignored = [
        f"{n} {one if n == 1 else many}"
        for key, one, many in (
            ("ignored_results", "Result", "Results"),
            ("ignored_telemetry", "Telemetry", "Telemetry messages"),
            ("unattributed_errors", "Error about no pair", "Errors about no pair"),
        )
        if (n := int(g.get(key) or 0))
    ]
    if ignored:  # an external flight computer's answers that answer no pair sent (the console said which)
        ignored[0] = "the ground ignored " + ignored[0]
        ignored[-1] += (
            " (a second answer, for no pair sent, before its pair's frames were sent, or after its pair was recorded)"
        )
    if other := int(g.get("ignored_other") or 0):  # the ground's own kinds of message, sent to it
        what = "Config or Frame" if other == 1 else "Configs or Frames"
        ignored.append(("and " if ignored else "the ground ignored ") + f"{other} {what} from the flight side")
    server = _server_note(summary, c)
    parts = (
        server,
        ground,
        ", ".join(ignored),
        _line_note(g.get("line") or {}),
        _flight_line_note(summary.get("records") or []),
        _drops_note(g),
    )
    return "; ".join(x for x in parts if x)


def _flight_line_note(records: list[dict]) -> str:
    """What the flight side's line dropped, as its Telemetry said it ("" when nothing): a board's noise reached no
    summary, since the ground's counters are its own side's (QA of stop 72)."""
    said = [r.get("link") or {} for r in records]
    counts = [float(x.get("flight_rx_damaged") or 0) for x in said if "flight_rx_damaged" in x]
    bad = max(counts, default=0.0)
    if not bad:
        # the emulated flight's line ends at the HIL server, whose link counts its damage as ground_* (the link it
        # holds to the ground): under --corrupt that side's was in summary.json alone (QA of stop 84)
        server = [(float(x.get("ground_crc_errors") or 0) + float(x.get("ground_malformed") or 0), x) for x in said]
        worst, x = max(server, key=lambda t: t[0], default=(0.0, {}))
        if not worst:
            return ""
        return (
            f"the HIL server's end of the line dropped {worst:.0f} damaged frame{'' if worst == 1 else 's'} "
            f"({float(x.get('ground_bytes_discarded') or 0):.0f} bytes of noise); "
            f"{float(x.get('ground_retransmits') or 0):.0f} retransmissions on its side"
        )
    noise = max(float(x.get("flight_rx_noise_bytes") or 0) for x in said)
    # the flight program's count since it started: a board that served earlier grounds counts their damage too, so a
    # second run read as twice as noisy (QA of stop 84); what grew over this run's pairs is said beside it
    grew = f"; {bad - min(counts):.0f} of them after this run's first Result" if len(counts) > 1 else ""
    return (
        f"the flight side's line dropped {bad:.0f} damaged frame{'' if bad == 1 else 's'} ({noise:.0f} bytes of noise) "
        f"since its flight program started, as its Telemetry counts them{grew}"
    )


def _drops_note(g: dict) -> str:
    """The flight side's ZeroMQ frames the ground's link dropped by the session rules ("" when none): each
    one a message meant for it (TCP repeats nothing), which the console named when it first came."""
    d = g.get("session_drops") or {}
    seq, wrong, foreign = (int(d.get(k) or 0) for k in ("duplicates_dropped", "misaddressed_frames", "foreign_frames"))
    if not seq + wrong + foreign:
        return ""
    parts = [
        f"{n} {what}"
        for n, what in (
            (seq, "with a seq that did not rise"),
            (wrong, "addressed to a session not the ground's"),
            (foreign, "from a session that said no HELLO"),
        )
        if n
    ]
    return (
        f"the ground's link dropped messages from the flight side: {', '.join(parts)} (ground.log names the first "
        "of each kind)"
    )


def _line_note(line: dict) -> str:
    """What the ground's line carried besides the descent ("" when nothing): frames that failed their checks (noise,
    a stranger's bytes) and the retransmissions that mended them; every pair's outcome says whether they did."""
    bad = int(line.get("crc_errors") or 0) + int(line.get("malformed") or 0)
    if not bad:
        return ""
    noise, again = int(line.get("bytes_discarded") or 0), int(line.get("retransmits") or 0)
    # frames shrink as the line gets noisier: the count alone read as far more than the bytes resent (soak QA)
    resent = f" ({int(line['retransmit_bytes'])} bytes resent)" if again and "retransmit_bytes" in line else ""
    return (
        f"the ground's line dropped {bad} damaged frame{'' if bad == 1 else 's'} ({noise} bytes of noise); "
        f"{again} retransmission{'' if again == 1 else 's'}{resent} on the ground's side"
    )


def _server_note(summary: dict, c: dict) -> str:
    if summary.get("budget") is not None and not c and summary.get("complete"):
        return "the HIL server's counters are missing (see supervisor.log)"
    parts = []
    for key, one, many in (
        ("crashes", "crash", "crashes"),
        ("exits", "exit with status 0", "exits with status 0"),
        ("hangs", "hang", "hangs"),
        ("memory_ceiling", "memory ceiling breach", "memory ceiling breaches"),
        ("restarts", "restart", "restarts"),
        (
            "flight_sessions",
            "new link session from it (Hello, Config and its unanswered pairs sent again)",
            "new link sessions from it (Hello, Config and its unanswered pairs sent again each time)",
        ),
        ("refused_messages", "refused message", "refused messages"),
        ("missing_telemetry", "Result without Telemetry", "Results without Telemetry"),
        ("flight_line_errors", "corrupted frame dropped", "corrupted frames dropped"),
        (
            "stale_results",
            "Result ignored (a second one, or for no open pair)",
            "Results ignored (second ones, or for no open pair)",
        ),
        ("stale_errors", "Error about no open pair ignored", "Errors about no open pair ignored"),
        (
            "stale_telemetry",
            "Telemetry ignored (a second one, or for no open pair)",
            "Telemetry messages ignored (second ones, or for no open pair)",
        ),
        ("unexpected_messages", "Config or Frame from it ignored", "Configs or Frames from it ignored"),
        (
            "port_refused",
            "connection refused on the HIL server's port (a wrong key or a second peer; supervisor.log)",
            "connections refused on the HIL server's port (wrong keys or second peers; supervisor.log)",
        ),
    ):
        n = int(c.get(key) or 0)
        if n:
            parts.append(f"{n} {one if n == 1 else many}")
    unlogged = int(summary.get("flight_output_unlogged_bytes") or 0)
    if unlogged:  # a program printing in a loop: said only at supervisor.log's end before
        size = f"{unlogged / 2**20:.1f} MiB" if unlogged >= 2**20 else f"{unlogged / 1024:.1f} kB"
        parts.append(f"{size} of its output past supervisor.log's cap, counted, not logged")
    if not parts:
        return ""
    events = summary.get("flight_events") or []
    last = events[-1] if events else None
    why = ""
    if last is not None:
        text = last.get("reason") or last.get("text") or ""
        why = f" (last: {last.get('event')}: {text})"
    return "flight process: " + ", ".join(parts) + why


def top_site_text(r: dict) -> str:
    """A Result's landing sites in a word or two: 'clear (3 sites)', 'NOT clear (1 site)', 'none offered',
    'withheld' (the flight side's own checks doubt the map: a row that read "none offered" beside the fused map's
    scores looked like a normal result; QA 74), or '3 sites' when the truth could not judge them."""
    sc = r.get("scores") or {}
    n = len(r.get("sites") or [])
    if n == 0:
        return "withheld" if str(r.get("no_site_reason") or "").startswith(SITES_WITHHELD) else "none offered"
    count = f"{n} site{'' if n == 1 else 's'}"
    if "top_site_clear" not in sc:
        return f"not judged ({count})" if r.get("site_truth") else count
    on = f", judged on {r['top_site_judged_on']}" if r.get("top_site_judged_on") else ""
    return f"{'clear' if sc['top_site_clear'] == 1.0 else 'NOT clear'} ({count}{on})"


def summary_notes(summary: dict) -> list[str]:
    """What a run's figures rest on and what went wrong beside its verdict, in the order summary.md and the report
    page both give them ("" where one has nothing to say). The page gave only some: a run whose flight process
    waited a quarter of its time for its core said so in summary.md alone (QA of stop 80)."""
    s = summary
    return [
        budget_note(s),
        throttle_check_note(s),
        host_rate_note(s),
        phase_note(s),
        contention_note(s),
        site_note(s),
        pose_note(s),
        flight_note(s),
        session_note(s),
        noise_note(s),
        relay_stop_note(s),
        server_stop_note(s),
        ground_stop_note(s),
        off_map_note(s),
        full_maps_note(s),
        *setting_notes(s),
        fusion_note(s),
    ]


def summary_table(summary: dict, verdict: bool = False) -> str:
    """summary.md: the run's setting, its notes and one row per pair; ``verdict``: the run's verdict line last (the
    file's; the console says it apart)."""
    from hil_server.run_report import level_text
    from reports.console import md_cell

    rows = [
        "| pair | altitude m | outcome | level | end to end s | flight s | result line s | deadline | FP % (grid) "
        "| CDI % (grid) | DEM mean abs m (grid) | top site |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    errors: list[str] = []
    for r in summary["records"]:
        sc = r.get("scores", {})
        if r.get("status") == "result":
            outcome = "degraded" if r.get("degraded") else "result"
            dl = "met" if r.get("deadline_met") else "MISSED"
            level = level_text(r)
            rows.append(
                f"| {md_cell(r['label'])} | {_fmt(r['altitude_m'], '.0f')} | {outcome} | {level} | "
                f"{_vs_deadline(r.get('e2e_latency_s'), summary.get('deadline_s'))} | "
                f"{_fmt(r.get('flight_latency_s'))} | "
                f"{_fmt(r.get('result_line_s'))} | {dl} | {_fmt(sc.get('fp_pct'))} | {_fmt(sc.get('cdi_pct'))} | "
                f"{_fmt(sc.get('dem_mean_abs'))} | {top_site_text(r)} |"
            )
        else:
            # the reason below the table, by the pair: the file said only "error: link_down", the reason was in
            # summary.json alone; then it sat in the deadline column (QA of stop 73)
            errors.append(f"- **{md_cell(r['label'])}**: {md_cell(r.get('text') or 'no result', 400)}")
            rows.append(
                f"| {md_cell(r['label'])} | {_fmt(r['altitude_m'], '.0f')} | error: {md_cell(r.get('code'))} "
                f"(below) | — | — | — | — | — | — | — | — | — |"
            )
    s = summary
    eff = s.get("effective_fraction")
    at_full = f", {_fmt(eff, '.4f')} at full speed" if eff is not None and eff < s.get("cpu_fraction", eff) else ""
    frac = _fmt(s.get("cpu_fraction"), ".4f")
    where = f" on budget **{s['budget']}** (CPU fraction {frac}{at_full})" if s["budget"] else ""
    baud = (s.get("ground_counters") or {}).get("line_baud")
    pace = "" if baud is None else f" ({baud} baud)" if baud else " (unpaced)"
    head = (
        f"**{s['scenario']}** over **{s['link']}**{pace}, flight {s['flight']}{where}, deadline "
        f"{_fmt(s.get('deadline_s'), 'g')} s end to end: {s['results']}/{s['pairs']} results ({s['degraded']} "
        f"degraded), {_errors(s)}; "
        f"end to end p50 {_vs_deadline(s['e2e_latency_p50_s'], s.get('deadline_s'))} s, "
        f"max {_vs_deadline(s['e2e_latency_max_s'], s.get('deadline_s'))} s "
        f"(flight p50 {_fmt(s['flight_latency_p50_s'])} s); "
        f"deadline hit rate {_fmt(100 * s['deadline_hit_rate'], '.0f')} %"
    )
    for note in summary_notes(s):
        if note:
            head += f"\n\n{note[0].upper()}{note[1:]}"
    if not s.get("complete", True):
        head = f"**INCOMPLETE: {s.get('reason')}**\n\n" + head
    table = "\n".join(rows) + ("\n\nErrors:\n\n" + "\n".join(errors) if errors else "")
    said = s.get("verdict")
    tail = f"\n\n**{said['line']}** (exit {said['exit_code']})" if verdict and isinstance(said, dict) else ""
    return head + "\n\n" + table + "\n\n" + GRID_SCORES_NOTE + tail + "\n"


def fusion_sources(entries: list[dict], base: Path | None = None) -> list[str]:
    """The distinct scenes and seeds of a descent's pairs, in order: more than one means pairs of other ground are
    fused as one descent. Each from its manifest entry's ``scene``/``seed``, and what the entry leaves out from
    its pair's ``pair.json`` under ``base`` (``scene_spec``, ``scene_seed``): render's manifest names the scene
    once for all its pairs, so a thesis and a mare pair merged into one manifest read as one "seed 0", and a
    manifest in DESIGN.md's minimal form said nothing at all (stop 62's QA M1)."""
    from reports.console import printable

    seen: list[str] = []
    for e in entries:
        got = {k: e[k] for k in ("scene", "seed") if k in e}
        if base is not None and len(got) < 2 and isinstance(e.get("path"), str):
            doc = _pair_doc(base / e["path"] / "pair.json")
            for k, keys in (("scene", ("scene_spec", "scene")), ("seed", ("scene_seed", "seed"))):
                ok = [doc[n] for n in keys if isinstance(doc.get(n), (str, int)) and not isinstance(doc[n], bool)]
                v = next((x for x in ok if x != ""), None)
                if k not in got and v is not None:
                    got[k] = printable(str(v), 80)
        if got:
            tag = " ".join(f"{k} {got[k]}" for k in ("scene", "seed") if k in got)
            if tag not in seen:
                seen.append(tag)
    return seen


def _pair_doc(path: Path) -> dict:
    """A pair.json's top level, or {} where it cannot be read (the pair's own error is said where it is run):
    a regular file only, read up to the pair reader's cap (a FIFO blocked the summary, a link to /dev/zero
    read until memory ran out; stop 62's review)."""
    import stat

    from protocol.pairdir import MAX_PAIR_JSON_BYTES

    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
    except (OSError, ValueError):
        return {}
    try:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            return {}
        with os.fdopen(os.dup(fd), "rb") as f:
            raw = f.read(MAX_PAIR_JSON_BYTES + 1)
        if len(raw) > MAX_PAIR_JSON_BYTES:
            return {}
        doc = json.loads(raw)
    except (OSError, ValueError, RecursionError):
        return {}
    finally:
        os.close(fd)
    return doc if isinstance(doc, dict) else {}


def flight_decides_fusion(summary: dict) -> bool:
    """Whether the run's flight side fuses as it decides (a board, a --flight-cmd program), not as ours does."""
    return summary.get("flight") not in (None, "emulated")


def fusion_note(summary: dict) -> str:
    """Whether the Results were fused over the descent, which the scores and sites are of."""
    if summary.get("fusion") is None:
        return ""
    if not summary["fusion"]:
        return "each Result reports its pair alone (`--no-fusion`)"
    theirs = flight_decides_fusion(summary)
    if theirs:
        said = "fusion was asked of the flight side (Config option `fusion` 1): where it fuses, a pair's scores are "
    else:
        said = "the Results report the map fused over the descent (flight_sw.fusion; `--no-fusion` reports each "
        said += "pair alone): each pair's scores and sites are "
    said += "of the map fused over the descent so far, which the pair's own evidence refines"
    sources = summary.get("fusion_sources") or []
    if len(sources) > 1:
        said += f"; its pairs come from {len(sources)} scenes or seeds ({', '.join(sources[:4])}), fused as one descent"
    up = climb([r for r in summary.get("records") or [] if r.get("status") == "result"])
    if up:  # fused as one descent all the same, unsaid (QA 74)
        said += f"; {up}, and {'where it fuses, ' if theirs else ''}the map is fused across it all the same"
    return said


def climb(records: list[dict]) -> str:
    """The first pair streamed lower than the one after it ("" when the altitudes never rise): a descent's pairs
    come highest first, and fusion takes each newer one as the finer."""
    alts = [(r.get("label", r.get("pair_id")), r.get("altitude_m")) for r in records]
    known = [(label, float(a)) for label, a in alts if isinstance(a, (int, float)) and math.isfinite(a)]
    for (la, a), (lb, b) in pairwise(known):
        if b > a:
            return f"pair {lb} ({b:g} m) comes after {la} ({a:g} m): the stream goes back up"
    return ""


def hello_note(summary: dict) -> str:
    """Who a flight computer or a ``--flight-cmd`` program of one's own said it is in its Hello ("" for our own
    flight software, or when unknown). A program's Hello went to supervisor.log alone (QA of stop 79)."""
    if summary.get("flight") == "external":
        h, side = (summary.get("ground_counters") or {}).get("flight_hello") or {}, "flight side"
    elif str(summary.get("flight") or "").startswith("command:"):
        h, side = summary.get("flight_program_hello") or {}, "flight program"
    else:
        return ""
    if not h:
        return ""
    who, role, version = h.get("software"), h.get("role"), h.get("protocol_version")
    omitted = h.get("omitted") or []
    said = f"it is {who!r}" if who is not None else "no name (its Hello has no software)"
    proto = f"protocol {version}" + (" by default: its Hello leaves it out" if "protocol_version" in omitted else "")
    return f"the {side} says {said} (role {role!r}, {proto})"


def baud_note(summary: dict) -> str:
    """A board whose serial port is set to another rate than this ground paced the line at ("" when they agree, or
    either is unknown): its Telemetry's ``link.port_baud``. Only the board's console said so, and a pty or a USB
    gadget that ignores the rate passed the run (QA of stop 71); on a real UART the bytes are garbled."""
    line = (summary.get("ground_counters") or {}).get("line_baud")
    if not isinstance(line, (int, float)) or not line:  # unpaced, or unknown: nothing to compare
        return ""
    said = [(r.get("link") or {}).get("port_baud") for r in summary.get("records") or []]
    wrong = sorted({int(p) for p in said if isinstance(p, (int, float)) and p and int(p) != int(line)})
    if not wrong:
        return ""
    return (
        f"the flight side's serial port is set to {', '.join(map(str, wrong))} baud, and this ground paced the line at "
        f"{int(line)} baud: on a real UART the two must match (this line carried the bytes all the same: a pty or a "
        "USB gadget ignores the rate); the flight side planned its Results' line time for the ground's rate"
    )


def setting_notes(summary: dict) -> list[str]:
    """The notes on what a run's figures rest on (its truth, its flight side, its frames, its line and kernels, its
    P(safe)), in the order summary.md and the report page both give them; "" where one has nothing to say."""
    return [
        truth_note(summary),
        hello_note(summary),
        frames_note(summary),
        baud_note(summary),
        unpaced_note(summary),
        kernel_note(summary),
        psafe_note(summary),
    ]


def frames_note(summary: dict) -> str:
    """The pairs whose directories hold more than two frames, of which the HIL streamed two ("" when none): the
    ground said so once, on stderr alone, and a row labelled "300/250/200/150" read as all four used (QA 74)."""
    many = [r for r in summary.get("records") or [] if (r.get("frames_in_dir") or 2) > 2]
    if not many:
        return ""
    named = ", ".join(f"{r.get('label', r.get('pair_id'))}: {r['frames_in_dir']}" for r in many[:4])
    more = f" and {len(many) - 4} more" if len(many) > 4 else ""
    return (
        f"{len(many)} pair director{'y holds' if len(many) == 1 else 'ies hold'} more than two frames ({named}{more}): "
        "the HIL streams a pair, frames 0 and the last (DESIGN.md), not those between; `hazard-hil process` "
        "uses every frame"
    )


# A Result counts as unpaced when it reached the ground in under this share of the time the line's rate needs for
# its bytes (start and stop bits included); the share leaves room for the two sides' clocks and timing jitter
UNPACED_SHARE = 0.5
UNPACED_MIN_LINE_S = 0.002  # a Result shorter on the line than this cannot be told from the clocks' jitter


def unpaced_note(summary: dict) -> str:
    """Results that reached the ground faster than its line rate can carry them ("" when none, or the ground did
    not pace): a board that writes unpaced into a pty (``examples/minimal_flight.py`` in hil.md's recipe) read
    "end to end 0.0011 s, met" for 342 bytes that need 3.7 ms at 921600 baud, and said nothing (QA of stop 74).

    The line time a Result needs is ``t_min = 10 n / baud`` (8N1, :data:`protocol.links.BITS_PER_BYTE`); it had
    ``e2e - flight - queue`` (what the end-to-end latency leaves beside the flight side's compute and its
    queue; all of ``e2e`` when the flight side gave no latency). Below ``UNPACED_SHARE t_min`` the downlink was
    not paced, and the latency misses ``t_min`` minus what it had."""
    baud = (summary.get("ground_counters") or {}).get("line_baud")
    if not isinstance(baud, (int, float)) or isinstance(baud, bool) or baud <= 0:
        return ""
    deadline = summary.get("deadline_s")
    fast, would_miss = [], 0
    for r in summary.get("records") or []:
        e2e, n = r.get("e2e_latency_s"), r.get("result_bytes")
        if not isinstance(e2e, (int, float)) or not isinstance(n, (int, float)) or n <= 0:
            continue
        need = float(n) * BITS_PER_BYTE / float(baud)
        # clipped: a flight latency over the end to end (the two sides' clocks) leaves no line time, not less
        had = max(0.0, float(e2e) - float(r.get("flight_latency_s") or 0.0) - float(r.get("result_queue_s") or 0.0))
        if need < UNPACED_MIN_LINE_S or had >= UNPACED_SHARE * need:
            continue
        fast.append((r, need, had))
        if r.get("deadline_met") and isinstance(deadline, (int, float)) and float(e2e) + need - had > deadline:
            would_miss += 1
    if not fast:
        return ""
    results = sum(isinstance(x.get("e2e_latency_s"), (int, float)) for x in summary.get("records") or [])
    r, need, had = max(fast, key=lambda f: f[1] - f[2])
    miss = (
        f"; with it, {would_miss} of the deadlines met here would have been missed"
        if would_miss
        else "; with it, every deadline met here would still be met"
    )
    return (
        f"{len(fast)} of {results} Results reached this ground faster than {int(baud)} baud "
        f"carries them (pair {r.get('label', r.get('pair_id'))}: {int(r['result_bytes'])} bytes need {need:.4f} s, "
        f"and had at most {had:.4f} s): the flight side writes without pacing its line (a pty carries bytes at once), "
        f"so the end-to-end latencies leave out the downlink a real UART at {int(baud)} baud adds, up to "
        f"{need - had:.4f} s a Result{miss}"
    )


def truth_note(summary: dict) -> str:
    """Which pairs were scored against a truth hazard derived from DESIGN.md's files ("" when none)."""
    recs = summary.get("records") or []

    def names(rs: list[dict]) -> str:
        labels = [str(r.get("label", r.get("pair_id"))) for r in rs]
        return ", ".join(labels[:6]) + (f" and {len(labels) - 6} more" if len(labels) > 6 else "")

    derived = [r for r in recs if r.get("truth") == "derived"]
    without = [r for r in recs if r.get("truth_note") and r.get("truth") != "derived"]
    parts = []
    if derived:
        parts.append(
            f"the scores of {names(derived)} are against a truth hazard derived from gt_elevation and gt_depth (and "
            "gt_shadow where there is one; no gt_hazard_i1.npy): it sees only the relief the camera resolves "
            "(docs/design.md, Ground-truth hazard)"
        )
    if without:
        # "pair(s)" first: the sentence's capital went to a user's own label ("Noderive"; QA of stop 84)
        parts.append(f"pair{'s' * (len(without) > 1)} {names(without)} could not be scored: {without[0]['truth_note']}")
    return "; ".join(parts)


# the run's and `score`'s figures for the same pair differ a little (CDI 25.97 against 25.2): said where both are read
GRID_SCORES_NOTE = (
    "(grid): scored from each Result's world grids, read at each pixel's true ground point; a run with `--full-maps` "
    "keeps the full-resolution image maps, which `hazard-hil score PAIRS OUT/received` then scores, so its figures "
    "differ a little."
)


def _last_words(path: Path, started: str, reason: str | None, failure: str) -> None:
    """Put the reason the summary could not be written into ``path`` in place of the placeholder that says the
    run is in progress. Written over the placeholder's own bytes, not beside it: on a full disk a new file cannot be
    made, while the placeholder's block is already the file's (the note is kept shorter than a block)."""
    from reports.jsondoc import json_text

    why = f"the run's summary could not be written ({failure})" + (f"; before that: {reason}" if reason else "")
    doc = {"complete": False, "reason": why[:3000], "started": started}
    with contextlib.suppress(OSError):  # nothing more can be said in the file: the console says it
        _in_place(path, json_text(doc, sort_keys=True))


def _in_place(path: Path, text: str) -> None:
    """Write ``text`` over ``path``'s own bytes and cut what is left: on a full disk a new file cannot be made, while
    an existing file's blocks are already its own (``text`` no longer than what it replaces)."""
    with open(path, "r+b") as f:
        f.write(text.encode())
        f.truncate()


def _unsaid(table: Path, page: Path, failure: str) -> None:
    """Take back a verdict ``table`` (summary.md) and ``page`` (report.html) gave before ``summary.json`` failed: the
    page goes (freeing its room), the table's bytes are overwritten with the failure, which is shorter."""
    from reports.console import md_cell

    with contextlib.suppress(OSError):  # the table's correction matters more than the page's removal
        page.unlink(missing_ok=True)
    try:
        _in_place(table, f"# HIL run\n\n**INCOMPLETE ({md_cell(failure, 1500)}): see the console; exit 1**\n")
    except FileNotFoundError:
        pass  # never written: nothing claims a verdict
    except OSError:
        table.unlink(missing_ok=True)  # a verdict the run did not end with must not stay


def _write_json(path: Path, doc: dict) -> None:
    from reports.html import write_atomic
    from reports.jsondoc import json_text

    write_atomic(path, json_text(doc, sort_keys=True))  # strict: NaN as null


def _parse_link(cfg: RunConfig) -> tuple[str, str | None]:
    """(kind, full spec or None) of ``cfg.link``, checked against ``cfg.flight``."""
    if cfg.flight not in ("emulated", "external"):
        raise InputError(f"--flight must be emulated or external, got {cfg.flight!r}")
    kind, sep, rest = cfg.link.partition(":")
    if kind not in ("serial", "zmq") or (sep and not rest):
        raise InputError(f"--link must be serial, zmq, serial:DEVICE[@BAUD] or zmq:ENDPOINT, got {cfg.link!r}")
    if cfg.flight_cmd is not None and not cfg.flight_cmd.strip():
        # an unset $FLIGHT_CMD in CI ran our flight software and passed, testing the wrong program
        raise InputError("--flight-cmd is empty (an unset variable?): give the program to run, or leave it out")
    if cfg.flight == "external":
        if not sep:
            raise InputError(
                "--flight external needs the far end in --link: serial:DEVICE[@BAUD] (e.g. serial:/dev/ttyUSB0@115200) "
                "or zmq:tcp://HOST:PORT"
            )
        if cfg.flight_cmd or cfg.fault or cfg.link_fault or cfg.corrupt:
            raise InputError("--flight-cmd, --corrupt and fault injection need the emulated flight processor")
        if kind == "zmq" and not (cfg.keys or cfg.insecure):
            raise InputError(
                "zmq to an external flight computer needs --keys DIR (client.key_secret and server.key, "
                "docs/protocol.md section 7) or --insecure on loopback"
            )
        from protocol.linkspec import check_link_spec, parse_serial

        spec = cfg.link
        if kind == "serial" and cfg.baud is not None:  # the rate goes into the spec: checked and reported with it
            url, named = parse_serial(rest)
            if url != rest and (named or 0) != cfg.baud:  # rest named a rate of its own (None: @0, unpaced)
                raise InputError(f"--baud {cfg.baud} and --link {cfg.link} name two rates: give one")
            spec = f"serial:{url}@{cfg.baud}"
        # a device that is not there, not a device or held, an endpoint libzmq would refuse, --insecure off
        # loopback, a rate too slow for the link timeout: each would fail the ground's open, said now and not after
        # the descent is rendered
        try:
            check_link_spec(spec, server=False, insecure=cfg.insecure, peer_timeout=cfg.link_timeout_s)
        except InputError as exc:
            raise InputError(f"--link {spec}: {exc}") from None
        return kind, spec
    if sep:
        raise InputError(
            f"--link {cfg.link}: a device or endpoint needs --flight external; the emulated flight processor "
            "takes --link serial or zmq"
        )
    if cfg.flight_cmd:
        from hil_server.supervisor import flight_argv

        argv = flight_argv(cfg.flight_cmd, "PORT")
        if shutil.which(argv[0]) is None:
            raise InputError(f"--flight-cmd: program {argv[0]!r} not found (give a path or a command on PATH)")
        if cfg.fault:
            raise InputError("--fault injects faults into our flight software, not into a --flight-cmd program")
    if cfg.fault:  # a bad spec would fail every flight incarnation at start: said now
        from flight_sw.flight_main import FaultPlan

        FaultPlan.parse(cfg.fault)
    if cfg.link_fault:  # said now, not by a supervisor that dies at start
        from hil_server.supervisor import parse_link_fault

        parse_link_fault(cfg.link_fault)
    return kind, None


def _image_side(cfg: RunConfig, manifest: Path | None) -> tuple[int, int]:
    """(width, height) of the largest camera the run streams (from each pair.json's camera; a pair that
    cannot be read is skipped here: the ground reports it as bad input)."""
    if manifest is None:
        s = cfg.image_size or 512
        return s, s
    from protocol.pairdir import Camera

    best = (0, 0)
    for e in _manifest_entries(manifest):
        try:
            cam = Camera.from_dict(json.loads((manifest.parent / e["path"] / "pair.json").read_text())["camera"])
        except (OSError, ValueError, KeyError, TypeError, InputError):
            continue
        if cam.width * cam.height > best[0] * best[1]:
            best = (cam.width, cam.height)
    return best


def psafe_fallback(cfg: RunConfig, manifest: Path | None) -> str | None:
    """Why our flight software's P(safe) falls back to the Gaussian rule on this run's camera (its trees are fitted
    for 512, 256 and 128 px cameras), or None: `process` warned of it and a run said nothing (QA of stop 71). Not
    for a flight program of one's own, nor a preset that does not use the trees."""
    if cfg.flight != "emulated" or cfg.flight_cmd:
        return None
    from flight_sw.pipeline import PRESETS
    from flight_sw.psafe import model_for_image, not_fitted_text

    params = PRESETS.get(cfg.preset)
    if params is None or params.psafe_model != "calibrated":
        return None
    w, h = _image_side(cfg, manifest)
    if not w or model_for_image(params.psafe_model_path or None, (h, w)) is not None:
        return None
    return not_fitted_text((h, w))


def kernel_note(summary: dict) -> str:
    """Our flight process ran without the install's compiled kernels ("" when it had them, or was not ours)."""
    return kernels_note(list(summary.get("kernels_missing") or []))


def psafe_note(summary: dict) -> str:
    """The Gaussian rule in the trees' place, and what it costs ("" when the trees call this camera)."""
    why = summary.get("psafe_fallback")
    if not why:
        return ""
    return (
        f"{why}: the flight software's P(safe) falls back to the Gaussian rule, whose FP is higher (over 1 % on 3 "
        "of 192 held-out pairs at 256 px and 128 px before those sizes had trees; docs/benchmarks/pipeline.md), so "
        "its calls and sites are less trustworthy than at 512, 256 or 128 px"
    )


def check_memory(budget: Budget, width: int, height: int, rendered: bool = False) -> None:
    """Refuse, before anything runs, a camera whose flight pipeline cannot fit the budget's memory ceiling.
    ``rendered``: the pairs exist already (``--manifest``), so ``--image-size`` is no remedy."""
    from hil_server.budgets import flight_peak_rss_mib, max_image_side

    need = flight_peak_rss_mib(width * height)
    if need > budget.memory_mib:
        side = max_image_side(budget.memory_mib)
        remedy = (
            f"no camera fits: the flight process alone needs ~{flight_peak_rss_mib(0):.0f} MiB; give the budget more "
            "memory"
            if side <= 0
            else f"stream pairs of at most {side} x {side} px, or a budget with more memory"
            if rendered
            else f"the largest square camera that fits is {side} px (--image-size)"
        )
        raise InputError(
            # one decimal where whole MiB would read "~256 MiB, over 256 MiB"
            f"a {width}x{height} camera needs ~{need:.{0 if need - budget.memory_mib >= 0.5 else 1}f} MiB peak "
            "private RSS in the flight process, over budget "
            f"{budget.name}'s {budget.memory_mib} MiB; {remedy}, see `hazard-hil budgets`"
        )


def _spawn(
    cmd: list[str], env: dict, *, hold_interrupts: bool = False, cores: frozenset[int] = frozenset(), **kw
) -> subprocess.Popen:
    """A child leading its own process group: stopped as a whole, and the terminal's Ctrl-C reaches us only.

    It gets SIGTERM when the thread that started it dies (``PR_SET_PDEATHSIG``): a run killed outright (SIGKILL,
    the OOM killer) must not leave its ground streamer holding the serial device, or its HIL server the port.
    SIGTERM, not SIGKILL, so each records what it has and closes its link. With ``hold_interrupts`` the child
    starts with SIGINT and SIGTERM blocked (the mask survives exec): one sent before it has a handler stays
    pending until the child unblocks them (``ground_sim.stream.main``). With ``cores`` it runs on those (every
    thread it starts inherits them): off the emulated core (:func:`hil_server.procemu.hil_cores`)."""
    prctl = libc_prctl()

    def preexec() -> None:  # between fork and exec: async-signal-safe calls only
        if prctl is not None:
            prctl(PR_SET_PDEATHSIG, int(signal.SIGTERM), 0, 0, 0)
        if hold_interrupts:
            signal.pthread_sigmask(signal.SIG_BLOCK, (signal.SIGINT, signal.SIGTERM))
        if cores:
            os.sched_setaffinity(0, cores)

    return subprocess.Popen(cmd, env=env, process_group=0, preexec_fn=preexec, **kw)


GROUND_LOG_MAX_BYTES = 16 << 20  # a ground that says more (a flood of refusals) keeps its first 16 MiB, and says so


class _Tee(threading.Thread):
    """A child's stderr, shown on this run's stderr as it comes and kept in ``path`` (up to
    GROUND_LOG_MAX_BYTES): the ground's reason for failing was printed once on the console, while summary.md
    said only "exited with 2". The pipe is read to its end whatever fails (:func:`hil_server.pump.pump`)."""

    def __init__(self, stream: Any, path: Path) -> None:
        super().__init__(name=f"tee {path.name}", daemon=True)
        self.stream, self.path = stream, path

    def run(self) -> None:
        from hil_server.pump import Sink, pump

        def show(line: bytes) -> None:  # sys.stderr looked up per line: a test's capture may replace it meanwhile
            sys.stderr.write(line.decode("utf-8", "replace"))
            sys.stderr.flush()

        sinks = [Sink(show)]
        try:
            f = open(self.path, "wb")  # noqa: SIM115 (closed below)
        except OSError:
            f = None
        if f is not None:
            cap = GROUND_LOG_MAX_BYTES
            note = f"... (the rest, {{}} bytes, not kept: over {cap >> 20} MiB)\n"
            sinks.append(Sink(f.write, cap, lambda n: note.format(n).encode(), f.flush))
        try:
            pump(self.stream, sinks)
        finally:
            if f is not None:
                f.close()


def _ended(who: str, code: int, log_path: Path) -> str:
    """Why a child of the run ended: its exit status and its log's last line, or the signal that killed it (its
    last line is then no reason: "exited with -9: flight: boot warm-up ..." read as if the warm-up had failed)."""
    if code < 0:
        try:
            name = signal.Signals(-code).name
        except ValueError:
            name = f"signal {-code}"
        return f"{who} was killed by {name} (its log: {log_path})"
    last = _last_line(log_path)
    return f"{who} exited with {code}" + (f": {last}" if last else "")


def _last_line(path: Path) -> str:
    """The last non-empty line of a log (``""`` if none or unreadable), for a one-line reason."""
    try:
        lines = [ln.strip() for ln in path.read_text(errors="replace").splitlines() if ln.strip()]
    except OSError:
        return ""
    return lines[-1][:300] if lines else ""


def _wait_ground(
    ground: subprocess.Popen, sup: subprocess.Popen | None, timeout_s: float, sup_log: Path
) -> tuple[int | None, str | None]:
    """Wait for the ground simulator; ``(its exit code or None on timeout, a reason or None)``.

    The HIL server (the supervisor) failing on the way is a reason on its own: without it the ground would
    wait out its link timeout on every pair (8 min for an 8-pair descent whose server failed to start).
    A server that exits 0 or :data:`EXIT_LINK_LOST` has ended its sessions; the ground then ends by itself.
    """
    end = time.monotonic() + timeout_s
    while True:
        try:
            return ground.wait(timeout=min(SUPERVISOR_POLL_S, max(0.0, end - time.monotonic()))), None
        except subprocess.TimeoutExpired:
            pass
        if time.monotonic() >= end:
            return None, None
        code = sup.poll() if sup is not None else None
        if code is not None and code not in (0, EXIT_LINK_LOST):
            return None, _ended("the HIL server (supervisor)", code, sup_log)


def _stop(proc: subprocess.Popen | None, grace_s: float = GRACE_S, how: int = signal.SIGTERM) -> None:
    """SIGCONT + ``how`` (SIGTERM; the run's own interrupting signal, which each child says it was stopped by)
    to the child's group; SIGKILL to the group after ``grace_s``."""
    if proc is None:
        return
    if proc.poll() is None:
        for sig in (signal.SIGCONT, how):  # a child frozen by a stall test must wake to terminate
            try:
                os.killpg(proc.pid, sig)
            except ProcessLookupError:
                break
        try:
            proc.wait(timeout=grace_s)
        except subprocess.TimeoutExpired:
            pass
    try:  # whatever is left of its group (also after a clean exit: nothing may outlive the run)
        os.killpg(proc.pid, signal.SIGKILL)
    except (ProcessLookupError, PermissionError):
        pass
    if proc.poll() is None:
        proc.wait()


class _Interrupted(Exception):
    def __init__(self, signum: int) -> None:
        super().__init__(f"interrupted by {signal.Signals(signum).name}")
        self.signum = signum


class _Signals:
    """SIGINT/SIGTERM/SIGHUP raise :class:`_Interrupted` in the main thread while armed; later ones are only
    noted (a closed terminal or ssh session ends a run with its summary, as Ctrl-C does)."""

    def __init__(self, armed: bool = True) -> None:
        self.arm_on_enter = armed  # False: only noted from the start (a signal between arming and disarming raised)
        self.armed = False
        self.received: int | None = None
        self.saved: dict[int, object] = {}

    def __enter__(self) -> _Signals:
        if threading.current_thread() is threading.main_thread():
            self.armed = self.arm_on_enter
            for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
                if sig == signal.SIGHUP and signal.getsignal(sig) is signal.SIG_IGN:
                    continue  # under nohup a hangup stays ignored
                self.saved[sig] = signal.signal(sig, self._handle)
        return self

    def _handle(self, signum, frame) -> None:
        if self.received is None:
            self.received = signum
        if self.armed:
            self.armed = False  # once: the cleanup that follows must not be interrupted
            raise _Interrupted(signum)

    def disarm(self) -> None:
        self.armed = False

    def __exit__(self, *exc) -> None:
        for sig, old in self.saved.items():
            signal.signal(sig, old)  # type: ignore[arg-type]


def _manifest(manifest: Path | None) -> dict:
    """A descent's manifest.json as a dict ({} when absent or unreadable: the caller reports what is missing)."""
    if manifest is None or not manifest.is_file():
        return {}
    try:
        doc = json.loads(manifest.read_text())
    except (OSError, ValueError):
        return {}
    return doc if isinstance(doc, dict) else {}


def _planned_entries(cfg: RunConfig) -> list[dict]:
    """The pairs a run meant to render, as manifest entries, for a run that ended before its manifest was written
    (interrupted while rendering): each is then recorded as not run with the reason, none vanishes."""
    from ground_sim.trajectory import load_trajectory

    try:
        specs = load_trajectory(cfg.scenario, None)
    except (InputError, OSError, ValueError):  # a scenario that cannot be read ended the run before rendering
        return []
    if cfg.pairs:
        specs = [s for p in cfg.pairs for s in specs if s.label == p]
    return [{"label": s.label, "path": s.label.replace("/", "_"), "altitude_m": s.altitude_m} for s in specs]


def _manifest_entries(manifest: Path | None) -> list[dict]:
    return list(_manifest(manifest).get("pairs", []))


def _supervisor_no_hello(log_path: Path) -> str | None:
    """The HIL server's last diagnosis of a flight process that never said Hello (what its link saw: nothing, frames
    failing their CRC, or a link up with no Hello message), from ``supervisor.log``; None if it logged none."""
    from hil_server.supervisor import NO_HELLO_LOG

    try:
        with open(log_path, "rb") as f:
            f.seek(max(0, f.seek(0, os.SEEK_END) - 256 * 1024))  # its tail: a flight program's output may be long
            text = f.read().decode("utf-8", "replace")
    except OSError:
        return None
    said = [ln for ln in text.splitlines() if ln.startswith(f"supervisor: {NO_HELLO_LOG} ")]
    return said[-1].split(": ", 2)[-1] if said else None


def _no_hello_reason(results: Path) -> str | None:
    """The ground's reason for not running any pair (its not_run records' text, less the prefix), or None."""
    for rec in read_results(results, strict=False):
        if rec.get("code") == "not_run" and isinstance(rec.get("text"), str):
            return rec["text"].removeprefix("not run: ")
    return None


def _blame_server(records: list[dict], why: str) -> list[dict]:
    """The ground's ``link_down`` records after the last Result, re-coded ``server_failed`` with the HIL server's
    own reason when it failed: its link closed because it exited, not because the line failed (a flight program
    that died before its Hello read as a link error). The ground's words are kept in the text."""
    last = max((i for i, r in enumerate(records) if r.get("status") == "result"), default=-1)

    # "interrupted" too: the run stops its ground once the server is gone, and the pair in flight then read
    # "interrupted by SIGTERM", a signal nobody but the run sent
    def blamed(r: dict) -> dict:
        seen = "its answer was not awaited" if r.get("code") == "interrupted" else f"the ground saw: {r.get('text')}"
        return {**r, "code": "server_failed", "text": f"{why} ({seen})"}

    return [
        blamed(r) if i > last and r.get("code") in ("link_down", "interrupted") else r for i, r in enumerate(records)
    ]


def _descent_order(record: dict) -> tuple[int, str]:
    """A record's place in the descent, from its pair id (:func:`ground_sim.stream.descent_index`)."""
    from ground_sim.stream import descent_index

    pid = str(record.get("pair_id", ""))
    i = descent_index(pid)
    return (10**9 if i is None else i, pid)


def _server_saw(events: list[dict]) -> dict[str, str]:
    """What the HIL server had of each pair (``supervisor.jsonl``): "result", "error" or "frames", the furthest."""
    order = {"frames": 0, "error": 1, "result": 2}
    seen: dict[str, str] = {}
    for e in events:
        got = {"frame": "frames"}.get(str(e.get("event")), str(e.get("event")))
        pid = e.get("pair_id")
        if got in order and isinstance(pid, str) and order[got] >= order.get(seen.get(pid, ""), -1):
            seen[pid] = got
    return seen


def _missing(
    entries: list[dict], records: list[dict], base: Path, why: str, server: dict[str, str] | None = None
) -> list[dict]:
    """Records for the manifest's pairs that have none, in descent order: ``not_run`` when the run ended before
    them; ``interrupted`` when the HIL server had their frames (``server``, :func:`_server_saw`) and the ground
    did not record them (killed: a pair on the line read "not run", stop 63's interrupt QA)."""
    from ground_sim.stream import descent_pair_id

    server = server or {}
    have = {r["pair_id"] for r in records}
    full = []
    by_id = {r["pair_id"]: r for r in records}
    for i, e in enumerate(entries):
        pid = descent_pair_id(i, e)
        if pid in have:
            full.append(by_id.pop(pid))
            continue
        code, text = "not_run", why
        if (had := server.get(pid)) is not None:
            what = {"frames": "its frames", "error": "its frames and reported an error on it"}.get(had, "its Result")
            code = "interrupted"
            text = f"{why.removeprefix('not run: ')}; the HIL server had {what}, the ground recorded nothing of it"
        full.append(
            {
                "pair_id": pid,
                "label": str(e.get("label", i)),
                "altitude_m": float(e.get("altitude_m", float("nan"))),
                "pair_dir": str(base / e["path"]),
                "status": "error",
                "code": code,
                "text": text,
                "deadline_met": False,
            }
        )
    return full + list(by_id.values())


@dataclass(frozen=True)
class CheckedRun:
    """What :func:`check_run_config` read from a run's options: the link, the budget, the two timeouts and the
    manifest (``cfg`` names the manifest's scenario when there is one)."""

    cfg: RunConfig
    kind: str
    spec: str | None
    budget: Budget
    deadline: float
    hello: float
    manifest: Path | None


def check_run_config(cfg: RunConfig) -> CheckedRun:
    """Refuse bad options with one line (:class:`InputError`) before anything is calibrated, rendered or run."""
    from hil_server.budgets import OWN_BUDGET_HINT, deadline_problem, get_budget

    emulated = cfg.flight == "emulated"
    kind, spec = _parse_link(cfg)
    if spec is not None and spec != cfg.link:  # --baud folded into an external serial link's spec
        cfg = replace(cfg, link=spec)
    budget = get_budget(cfg.budget, cfg.budget_file, hint=OWN_BUDGET_HINT)
    if cfg.deadline_s is not None and (why := deadline_problem(cfg.deadline_s)):
        raise InputError(f"--deadline {why}")
    deadline = float(cfg.deadline_s if cfg.deadline_s is not None else budget.deadline_s)
    if cfg.corrupt and kind != "serial":
        raise InputError(f"--corrupt applies to the serial link only, not to --link {cfg.link}")
    if cfg.corrupt and not 0 <= cfg.corrupt <= 0.05:
        raise InputError(f"--corrupt is a per-byte fault rate in [0, 0.05], got {cfg.corrupt}")
    if cfg.min_hit_rate is not None and not 0.0 <= cfg.min_hit_rate <= 1.0:
        raise InputError(f"--min-hit-rate must be in [0, 1], got {cfg.min_hit_rate}")
    hello = cfg.hello_timeout_s
    if hello is None:
        hello = EMULATED_HELLO_TIMEOUT_S if emulated else EXTERNAL_HELLO_TIMEOUT_S
    if not (math.isfinite(hello) and hello > 0):
        raise InputError(f"--hello-timeout must be a positive number of seconds, got {hello}")
    from protocol.linkspec import check_reconnect_timeout

    check_reconnect_timeout(cfg.reconnect_timeout_s)
    # link options the link would ignore, or refuse only once the pairs are rendered: said now
    if cfg.baud is not None and kind != "serial":
        raise InputError(f"--baud applies to serial links, not to --link {cfg.link}")
    if kind == "serial" and emulated:
        from protocol.linkspec import check_baud

        check_baud((cfg.baud if cfg.baud is not None else budget.baud) or None, cfg.link_timeout_s)
    if (cfg.insecure or cfg.keys is not None) and kind != "zmq":
        raise InputError(f"--keys and --insecure apply to ZeroMQ links, not to --link {cfg.link}")
    if cfg.insecure and cfg.keys is not None:  # each side used to settle it its own way, and disagree
        raise InputError("--keys and --insecure exclude each other: CURVE with the key directory, or none")
    if cfg.keys is not None:
        from protocol.zmqauth import client_keys, server_keys

        client_keys(cfg.keys)  # the ground connects
        if emulated:
            server_keys(cfg.keys)  # and our HIL server binds
    manifest: Path | None = None
    if cfg.manifest is not None:
        manifest = Path(cfg.manifest)
        if manifest.is_dir() and (manifest / "manifest.json").is_file():  # render's --out, as `score` takes it
            manifest = manifest / "manifest.json"
            cfg = replace(cfg, manifest=manifest)
        elif manifest.is_dir():  # it said "does not exist" of a directory that does (QA of stop 71)
            raise InputError(f"manifest: {manifest} is a directory without a manifest.json (render pairs with "
                             "`hazard-hil render --out DIR`, then give DIR or DIR/manifest.json)")  # fmt: skip
        if not manifest.is_file():
            raise InputError(f"manifest {manifest} does not exist (render pairs with `hazard-hil render`)")
        from protocol.pairdir import read_manifest

        doc = read_manifest(manifest)  # a malformed one is one line now, not the ground's traceback
        # the report names what was streamed: the manifest's scenario (a hand-made one: its path), not the default
        name = doc.get("scenario")
        cfg = replace(cfg, scenario=name if isinstance(name, str) and name else f"pairs of {manifest}")
    if manifest is None:  # what will be rendered: an unknown scenario, pair or scene is one line before any work
        from ground_sim.scene import load_scene_params
        from ground_sim.trajectory import load_trajectory

        specs = load_trajectory(cfg.scenario)
        known = [s.label for s in specs]
        missing = [p for p in cfg.pairs or [] if p not in known]
        if missing:
            raise InputError(f"unknown pair(s) {missing}; the {cfg.scenario} scenario has {known}")
        if cfg.scene:
            load_scene_params(cfg.scene, specs[0].scenario)
    if emulated and not cfg.flight_cmd:  # our pipeline's memory is known; a user's program is on its own
        check_memory(budget, *_image_side(cfg, manifest), rendered=manifest is not None)
    return CheckedRun(cfg, kind, spec, budget, deadline, hello, manifest)


def run_descent(cfg: RunConfig, log: Callable[[str], None] = print) -> dict:
    """Run one end-to-end HIL descent; returns the summary (also written under ``cfg.out``).

    Bad usage raises :class:`InputError` before anything runs, and so does an ``out`` another command is
    writing (:func:`protocol.outdir.claim_out`). Anything that cuts the run short (a signal, a child that fails,
    a timeout) still ends in a summary, with ``complete`` false and the reason.
    """
    from protocol.outdir import claim_out

    checked = check_run_config(cfg)
    with claim_out(checked.cfg.out, "run"):
        return _descend(checked, log)


def _descend(checked: CheckedRun, log) -> dict:
    from hil_server.budgets import (
        calibration_notes,
        check_runnable,
        check_throttle,
        host_load_note,
        load_calibration,
        measure_host_rate,
        needs_throttle_check,
        throttle_check_seconds,
    )

    cfg, kind, spec, budget = checked.cfg, checked.kind, checked.spec, checked.budget
    deadline, hello, manifest = checked.deadline, checked.hello, checked.manifest
    emulated = cfg.flight == "emulated"
    cal = load_calibration() if emulated and not budget.is_host else None  # full speed needs no host speed
    duty = budget.duty(cal) if emulated else None
    if duty is not None:
        check_runnable(cfg.budget, budget, duty)
    fraction = duty.applied if duty is not None else float("nan")
    effective = duty.effective if duty is not None else float("nan")
    # a doubtful host speed is a doubtful emulated processor (no calibration at all warns in duty_fraction)
    doubts = calibration_notes(cal) if cal is not None and not budget.is_host else []
    # our flight process runs this install's kernels: a build without them is slower at every budget, said first
    kernels_missing = missing_kernels() if emulated else []
    if kernels_missing:
        log(f"run: warning: {kernels_note(kernels_missing)}")

    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    started = time.strftime("%Y-%m-%dT%H:%M:%S")
    _write_json(
        out / "summary.json",
        {
            "complete": False,
            "reason": "run in progress (if it stays like this, the run was killed before it could write a summary)",
            "started": started,
        },
    )
    # an earlier run's logs went only once the ground started: a stop before that read its supervisor.jsonl as
    # this run's, and its answered pairs as this run's interrupted ones (review of stop 64); its text logs too,
    # which the report links as this run's (QA of stop 85)
    for stale in ("summary.md", "report.html", "telemetry.jsonl", "supervisor.jsonl", "ground.log", "supervisor.log"):
        (out / stale).unlink(missing_ok=True)
    received = out / "received"
    if received.is_dir():  # a previous run's records must not pass for this one's: cleared, and said
        n = sum(1 for p in received.rglob("*") if p.is_file())
        if n:
            log(f"run: clearing {received}: {n} file(s) of an earlier run (received/ is this run's own)")
    shutil.rmtree(received, ignore_errors=True)
    # the report's pictures are this run's too: an earlier run's pairs' figures stayed beside them (QA of stop 66)
    shutil.rmtree(out / "figures", ignore_errors=True)

    reason: str | None = None
    interrupted: int | None = None
    sup_reason: str | None = None  # the HIL server failed: its reason
    throttle: ThrottleCheck | None = None
    host_rate: dict | None = None  # the host's full-speed rate just before the flight, beside its calibration's
    rc: int | None = None
    channels: dict = {}
    bridge = None
    relay_stall: StallClock | None = None  # this process's own stops while it relays the loopback line
    held_tstp: Any = None
    sup = ground = None
    ground_cores: list[int] | None = None
    # the cores the run's own processes and relay keep to: all but the emulated one (an external flight: any)
    own_cores = hil_cores() if emulated else frozenset()
    ground_tee: _Tee | None = None
    sup_log = None
    t0 = time.monotonic()
    with _Signals() as sigs:
        try:
            if manifest is None:
                manifest = _render(cfg, out / "pairs", log) / "manifest.json"
            security: list[str] = []
            if kind == "serial" and spec is None:
                from protocol.faults import PtyBridge

                # Two raw ptys joined by a relay: each process opens a real serial device path.
                baud = cfg.baud if cfg.baud is not None else budget.baud
                if cfg.corrupt > 0:  # noisy both ways (seeded rates; the bytes hit vary): ARQ must hide it
                    from protocol.faults import CorruptingChannel

                    channels = {
                        d: CorruptingChannel(seed=cfg.seed * 2 + k, drop=cfg.corrupt, flip=cfg.corrupt, dup=cfg.corrupt)
                        for k, d in enumerate(("a_to_b", "b_to_a"))
                    }
                # the relay off the emulated core, with the ground and the HIL server
                bridge = PtyBridge(**channels, cores=own_cores)
                # the relay is this process: stopped, it stops the line, and the pairs then on it fail as link_down
                relay_stall = StallClock()
                if threading.current_thread() is threading.main_thread():
                    held_tstp = signal.signal(signal.SIGTSTP, _relay_holds_tstp())
                suffix = "" if baud is None else f"@{baud}"  # @0: unpaced; none: the default rate
                server_spec, ground_spec = f"serial:{bridge.paths[0]}{suffix}", f"serial:{bridge.paths[1]}{suffix}"
            elif spec is None:
                port = _free_tcp_port()
                server_spec = ground_spec = f"zmq:tcp://127.0.0.1:{port}"
            else:
                server_spec, ground_spec = "", spec
                if cfg.baud is not None and kind == "serial" and "@" not in spec:
                    ground_spec = f"{spec}@{cfg.baud}"
            if kind == "zmq":
                if cfg.insecure:
                    security = ["--insecure"]
                elif cfg.keys is not None:
                    security = ["--keys", str(cfg.keys)]
                else:  # fresh CURVE keys for every run, private to its output directory
                    from protocol.zmqauth import generate_keys

                    shutil.rmtree(out / "keys", ignore_errors=True)
                    security = ["--keys", str(generate_keys(out / "keys"))]

            if emulated and not budget.is_host and (load_note := host_load_note()):
                log(f"run: warning: {load_note}")
            if emulated and cfg.throttle_check and cal is not None and needs_throttle_check(budget, cal):
                # after the render, right before the flight starts: the host as the run will find it
                log(
                    f"run: checking the throttle's efficiency at {budget.name}'s duty cycle {fraction:.2%} "
                    f"(about {throttle_check_seconds(budget, cal):.0f} s, more when a second round must confirm the "
                    "first; --no-throttle-check skips it)"
                )
                try:
                    throttle = check_throttle(budget, cal)
                except (OSError, RuntimeError, ValueError) as exc:  # a probe that could not run: the run goes on
                    log(f"run: warning: the throttle check failed ({exc}); the calibration stands as stored")
                else:
                    host_rate = {k: v for k, v in throttle.to_dict().items() if k in ("host_rate", "calibrated_rate")}
                    cal = throttle.calibration(cal)
                    duty = budget.duty(cal)
                    log(f"run: {throttle_note(throttle, duty.applied)}")
                    fraction, effective = duty.applied, duty.effective
            elif emulated and cfg.throttle_check and cal is not None and not budget.is_host:
                # a fast budget's throttle loses little, but the host's own speed drifts all the same (stop 82)
                try:
                    host_rate = {"host_rate": measure_host_rate(), "calibrated_rate": cal.units_per_s}
                except (OSError, RuntimeError, ValueError) as exc:
                    log(f"run: warning: the host's speed could not be measured ({exc}); the calibration stands")
            if note := host_rate_note({"host_rate_check": host_rate}):
                log(f"run: {note}")
            env = {**os.environ, UNCALIBRATED_SAID: "1"}  # said once, here, not again by each process
            ground_cmd = [
                sys.executable,
                "-m",
                "ground_sim.stream",
                "--link",
                ground_spec,
                "--manifest",
                str(manifest),
                "--out",
                str(received),
                "--telemetry",
                str(out / "telemetry.jsonl"),
                "--budget",
                cfg.budget if emulated else "external",
                "--deadline",
                str(deadline),
                "--preset",
                cfg.preset,
                "--pace",
                cfg.pace,
                "--link-timeout",
                str(cfg.link_timeout_s),
                "--hello-timeout",
                str(hello),
                "--reconnect-timeout",
                str(cfg.reconnect_timeout_s),
                "--elevation-step",
                str(cfg.elevation_step) if cfg.elevation_step else "auto",
                "--psafe-step",
                str(cfg.psafe_step) if cfg.psafe_step else "auto",
                "--elevation-unit-cm",
                str(cfg.elevation_unit_cm) if cfg.elevation_unit_cm else "auto",
                *security,
            ]
            if cfg.full_maps:
                ground_cmd.append("--full-maps")
            if cfg.telemetry_grace_s is not None:
                ground_cmd += ["--telemetry-grace", str(cfg.telemetry_grace_s)]
            if cfg.hello_note_s is not None:
                ground_cmd += ["--hello-note", str(cfg.hello_note_s)]
            ground_cmd.append("--fusion" if cfg.fusion else "--no-fusion")
            ground_cmd.append("--under-run")
            if emulated:
                sup_cmd = [
                    sys.executable,
                    "-m",
                    "hil_server.supervisor",
                    "--link",
                    server_spec,
                    "--budget",
                    cfg.budget,
                    *(["--budget-file", str(Path(cfg.budget_file).resolve())] if cfg.budget_file else []),
                    "--telemetry",
                    str(out / "supervisor.jsonl"),
                    "--link-timeout",
                    str(cfg.link_timeout_s),
                    *security,
                ]
                if cfg.fault:
                    sup_cmd += ["--fault", cfg.fault]
                if cfg.link_fault:
                    sup_cmd += ["--link-fault", cfg.link_fault]
                if cfg.flight_cmd:
                    sup_cmd += ["--flight-cmd", cfg.flight_cmd]
                if throttle is not None and throttle.adopted:
                    sup_cmd += ["--throttle-efficiency", f"{throttle.duty!r}:{throttle.measured!r}"]
                who = f"flight program `{cfg.flight_cmd}`" if cfg.flight_cmd else "our flight software"
                log(
                    f"run: {who} on budget {budget.name}: CPU fraction {fraction:.4f}"
                    + (f" (= {effective:.4f} at full speed)" if effective < fraction else "")
                    + f", memory {budget.memory_mib} MiB, deadline {deadline:g} s end to end, link {server_spec}"
                    # a loopback line has two ends: the ground's "Hello on serial:/dev/pts/1" named another device
                    # than this line's pts/0 (QA of stop 84)
                    + (f" (the ground's end: {ground_spec})" if ground_spec != server_spec else "")
                    + ("" if cfg.flight_cmd else boot_hint(effective))
                )
                for doubt in doubts:
                    log(f"run: warning: {doubt}")
                speed = budget_speed(budget, cal, budget.duty(cal))
                if speed.get("faster_than_host"):
                    log(f"run: warning: {budget_note({'budget': budget.name, 'budget_speed': speed})}")
                sup_log = open(out / "supervisor.log", "w")  # noqa: SIM115 (closed below)
                sup = _spawn(sup_cmd, env, stdout=sup_log, stderr=subprocess.STDOUT)
            else:
                log(
                    f"run: external flight computer on {ground_spec}: deadline {deadline:g} s end to end; "
                    f"waiting up to {hello:g} s for its Hello"
                )
            # the ground off the emulated core (the HIL server moves itself): it shared it with the flight process
            ground = _spawn(
                ground_cmd,
                env,
                hold_interrupts=True,
                stderr=subprocess.PIPE,
                cores=own_cores,
            )
            try:  # as it is, not as asked: read back from the process
                ground_cores = sorted(os.sched_getaffinity(ground.pid))
            except OSError:  # it has already ended
                ground_cores = None
            ground_tee = _Tee(ground.stderr, out / "ground.log")
            ground_tee.start()
            limit = max(cfg.timeout_s, hello + GRACE_S)  # the first Hello may be awaited longer, when asked to
            rc, sup_reason = _wait_ground(ground, sup, limit, out / "supervisor.log")
            if sup is not None and rc in (0, EXIT_LINK_LOST):
                # the ground closed its session: the server ends by itself and writes its counters
                # (restarts, crashes, refused messages); a SIGTERM at once used to cut them short
                try:
                    sup.wait(timeout=SUPERVISOR_EXIT_S)
                except subprocess.TimeoutExpired:
                    pass
                # the server may have failed first and the ground ended on its closed link before that was seen
                code = sup.poll()
                if sup_reason is None and code not in (None, 0, EXIT_LINK_LOST):
                    sup_reason = _ended("the HIL server (supervisor)", code, out / "supervisor.log")
            if sup_reason is not None:
                reason = sup_reason
            elif rc is None:
                reason = f"the ground simulator did not finish within {limit:.0f} s"
            if reason is None and rc == EXIT_NO_HELLO and emulated:
                # the ground's link is to the HIL server, which answers; it is the program it runs that never said
                # Hello (the ground's "its link answers: is its flight software running?" pointed at the wrong thing)
                _stop(sup)  # its last words say what its link to the flight process saw (none while it waits)
                why = _supervisor_no_hello(out / "supervisor.log")
                reason = (
                    f"the flight process never said Hello to the HIL server within {hello:g} s, while it ran (no "
                    f"crash, no hang the watchdogs saw){f': {why}' if why else ''}; its output is in "
                    f"{out / 'supervisor.log'}"
                )
            if reason is None and rc == EXIT_NO_HELLO:  # the ground's reason is on every pair's not_run record
                reason = (
                    _no_hello_reason(received / "results.jsonl") or f"no Hello from the flight side within {hello:g} s"
                )
            if reason is None and rc is not None and rc not in (0, EXIT_LINK_LOST):
                if ground_tee is not None:
                    ground_tee.join(timeout=2.0)  # its last words, which say why
                reason = _ended("the ground simulator", rc, out / "ground.log")
                if "its log:" not in reason:
                    reason += f" (see {out / 'ground.log'})"
        except _Interrupted as exc:
            interrupted, reason = exc.signum, str(exc)
        except InputError as exc:  # e.g. a scene file the renderer refuses: bad usage, after the placeholder
            reason = f"error: {exc}"
            _write_json(out / "summary.json", {"complete": False, "reason": reason, "started": started})
            raise
        finally:
            sigs.disarm()
            if interrupted is not None or reason is not None:
                log(f"run: stopping ({reason})")
            # a Ctrl-C reaches the ground as SIGINT (it handles both), so it says "interrupted by SIGINT"
            _stop(ground, how=signal.SIGINT if interrupted == signal.SIGINT else signal.SIGTERM)
            if ground_tee is not None:
                ground_tee.join(timeout=2.0)  # its last lines before the run's verdict
            _stop(sup)
            if bridge is not None:
                bridge.close()
            if held_tstp is not None:
                signal.signal(signal.SIGTSTP, held_tstp)
            if relay_stall is not None:
                relay_stall.close()
            if sup_log is not None:
                sup_log.close()
        if interrupted is None and sigs.received is not None:  # arrived during the cleanup
            interrupted = sigs.received
            reason = f"interrupted by {signal.Signals(interrupted).name}"
    # a Ctrl-C while the records are scored and the pages written (up to ~3 s) left summary.json saying "in
    # progress" and no report.html: noted, not raised, and said once they are written whole
    with _Signals(armed=False) as late:
        wall = time.monotonic() - t0

        entries = _manifest_entries(manifest) if manifest is not None else _planned_entries(cfg)
        # in descent order: the ground records a pair when it ends, so one given up on came after the next (QA 64a)
        records = sorted(read_results(received / "results.jsonl", strict=False), key=_descent_order)
        server_events = read_results(out / "supervisor.jsonl", strict=False)
        if sup_reason is not None:
            records = _blame_server(records, sup_reason)
        if reason is not None:
            base = manifest.parent if manifest else out / "pairs"
            records = _missing(entries, records, base, f"not run: {reason}", _server_saw(server_events))
        score_records(records)
        counters = {}
        unlogged = 0
        cores: dict | None = None
        program_hello: dict | None = None
        flight_events: deque[dict] = deque(maxlen=MAX_FLIGHT_EVENTS)
        for line in server_events:
            if line.get("event") == "summary":
                counters = {k: v for k, v in line.items() if k != "event"}
            elif line.get("event") == "flight_output":
                unlogged = int(line.get("unlogged_bytes") or 0)
            elif line.get("event") == "cores":
                cores = {"flight": line.get("flight"), "hil_server": line.get("server"), "ground": ground_cores}
                if bridge is not None:  # the loopback serial line's relay, in this process
                    cores["line_relay"] = bridge.relays[0].cores_used
            elif line.get("event") == "flight_program_hello":  # the last incarnation's word stands
                program_hello = {k: v for k, v in line.items() if k != "event"}
            elif line.get("event") in FLIGHT_EVENTS:
                flight_events.append(line)
        summary = summarize(
            records,
            cfg,
            {
                "complete": reason is None,
                "reason": reason,
                "interrupted_by": interrupted,
                "started": started,
                "cpu_fraction": fraction,
                "effective_fraction": effective,
                "budget_speed": None if duty is None else budget_speed(budget, cal, budget.duty(cal)),
                "throttle_check": None if throttle is None else throttle.to_dict(),
                "host_rate_check": host_rate,
                "deadline_s": deadline,
                "line_faults": {d: ch.stats for d, ch in channels.items()},
                "fusion_sources": fusion_sources(entries, None if manifest is None else manifest.parent),
                "memory_mib": budget.memory_mib if emulated else None,
                "wall_s": wall,
                "supervisor_counters": counters,
                # the emulated core and where the HIL's own processes ran (off it, when the host allows another)
                "host_cores": cores,
                # who a --flight-cmd program's Hello says it is (ground_counters.flight_hello is the HIL server's)
                "flight_program_hello": program_hello,
                "flight_output_unlogged_bytes": unlogged,
                "flight_events": list(flight_events),
                # what the ground refused from the flight side (an external flight computer; via the HIL server, none)
                "ground_counters": (read_results(received / "ground.json", strict=False) or [{}])[-1],
                "ground_exit": rc,
                # SIGSTOP cannot be held: the line stopped with this process, and the summary says so
                "relay_stopped_s": None if relay_stall is None else round(relay_stall.total_s, 3),
                "psafe_fallback": psafe_fallback(cfg, manifest),
                "kernels_missing": kernels_missing,
                "figures": cfg.figures,  # False: --no-figures, report.html has no pictures by request
            },
        )
        # the run's own verdict, for a CI that reads files (a signal while they are written still exits 128 + N)
        code = exit_code(summary, cfg.min_hit_rate)
        summary["verdict"] = {
            "exit_code": code,
            "pass": code == 0,
            "line": verdict_line(summary, cfg.min_hit_rate),
            "min_hit_rate": cfg.min_hit_rate,
        }
        # says flight_note's line itself: logged once, with the table below; as a terminal shows markdown
        from reports.console import md_console

        table = md_console(summary_table(summary))
        from hil_server.run_report import write_run_report
        from reports.html import write_atomic

        try:
            write_atomic(out / "summary.md", summary_table(summary, verdict=True))
            try:
                write_run_report(summary, out / "report.html", figures=cfg.figures)
            except Exception as exc:  # a page that fails must not cost the run its summary (it stayed "in progress")
                summary["report_error"] = f"{type(exc).__name__}: {exc}"
                log(
                    f"run: warning: report.html could not be written ({summary['report_error']}); summary.md and "
                    "summary.json hold the run"
                )
            _write_json(out / "summary.json", summary)  # last: complete only once everything else is in place
        except OSError as exc:  # a full disk: the placeholder said "killed" (QA of stop 72)
            _last_words(out / "summary.json", started, reason, os_error_text(exc))
            # summary.md and the page, written first, said PASS (exit 0) while the run ended 1 (QA of stop 78)
            _unsaid(
                out / "summary.md",
                out / "report.html",
                f"the run's summary could not be written ({os_error_text(exc)})",
            )
            log(table)  # the run's figures, which no file holds
            raise
        log(table)
    if late.received is not None:  # written whole; the caller says its verdict, then exits 128 + N
        log(f"run: {signal.Signals(late.received).name} came while the summary was written: it was finished first")
        # returned, not raised: raised, it cost a second Ctrl-C the verdict and report lines (interrupt QA L11)
        summary = {**summary, LATE_SIGNAL: int(late.received)}
    return summary
