"""End-to-end HIL runs: ground simulator -> link -> supervisor -> emulated flight processor.

``run_descent`` renders (or reuses) a scenario's pairs, starts the supervisor
and the ground streamer as separate OS processes connected over a pty pair
(serial) or ZeroMQ on loopback, waits for the descent to finish, scores every
result against ground truth and writes::

    OUT/pairs/...            rendered pair directories + manifest.json
    OUT/keys/                CURVE keys of this run (ZeroMQ; files mode 0600)
    OUT/received/            what came back: results.jsonl + arrays per pair
    OUT/telemetry.jsonl      the supervisor's telemetry lines
    OUT/summary.json         latency p50/p95/max, deadline hit rate, per-pair scores
    OUT/summary.md           the same as a table
    OUT/report.html          tables and pictures for people
"""

from __future__ import annotations

import json
import math
import os
import signal
import socket
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from protocol.errors import InputError

EXIT_LINK_LOST = 3  # ground_sim.stream: a link session was lost (its pairs are recorded as link_down)


@dataclass
class RunConfig:
    scenario: str = "vertical"
    link: str = "serial"  # serial | zmq
    budget: str = "host"
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
    elevation_step: int | None = None  # elevation grid decimation; None = by line rate (ground_sim.stream)
    psafe_step: int | None = None  # P(safe) grid decimation; None = by line rate
    insecure: bool = False  # zmq without CURVE (loopback debugging)
    link_timeout_s: float = 4.0  # a peer silent or stalled this long ends the link session
    link_fault: str | None = None  # supervisor test fault on the ground link: stall@N | exit@N


def _free_tcp_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _render(cfg: RunConfig, pairs_dir: Path) -> Path:
    from ground_sim.descent import render_scenario

    kwargs: dict = {}
    if cfg.scene:
        kwargs["scene"] = cfg.scene
    if cfg.image_size:
        kwargs["camera"] = scaled_camera(cfg.image_size)
    return Path(render_scenario(cfg.scenario, pairs_dir, seed=cfg.seed, pairs=cfg.pairs, progress=True, **kwargs))


def scaled_camera(size: int):
    """The thesis camera's 30 deg FOV on a ``size`` x ``size`` sensor."""
    from protocol.pairdir import Camera

    if not 32 <= size <= 4096:
        raise InputError(f"--image-size must be in [32, 4096], got {size}")
    f = Camera.thesis().fx * size / 512.0
    return Camera(size, size, f, f, (size - 1) / 2.0, (size - 1) / 2.0)


def percentile(values: list[float], q: float) -> float:
    return float(np.percentile(values, q)) if values else float("nan")


def score_records(records: list[dict]) -> list[dict]:
    """Add detection and DEM scores (ground truth of each pair) to the received records.

    ``scores``: from the compact Result's world grids, per pixel of i1 through its true ground
    point (:mod:`ground_sim.gridscore`); ``scores_full``: from the full-resolution image maps,
    when the run asked for them (``--full-maps``).
    """
    from ground_sim.gridscore import score_grids
    from ground_sim.scoring import confusion, dem_error_stats
    from protocol.pairdir import read_pair

    for rec in records:
        if rec.get("status") != "result" or "out_dir" not in rec:
            continue
        d = Path(rec["out_dir"])
        pair = read_pair(rec["pair_dir"])
        truth = pair.truth
        if (d / "state_grid.npy").is_file() and "depth" in truth and "hazard" in truth:
            elev = np.load(d / "elevation_grid.npy") if (d / "elevation_grid.npy").is_file() else None
            scores, called = score_grids(
                pair,
                np.load(d / "state_grid.npy"),
                tuple(rec["grid_origin_xy"]),
                float(rec["grid_cell_m"]),
                elev,
                tuple(rec.get("elevation_origin_xy") or rec["grid_origin_xy"]),
                float(rec.get("elevation_cell_m") or rec["grid_cell_m"]),
            )
            rec["scores"] = scores
            np.save(d / "called_i1.npy", called)  # per-pixel call (0 safe, 1 not, NaN unscored) for the report
        if (d / "hazard.npy").is_file() and "hazard" in truth:
            hazard = np.load(d / "hazard.npy")
            c = confusion(hazard, truth["hazard"], ~np.isnan(hazard))
            full = {f"{k}_pct" if k in ("tp", "tn", "fp", "fn", "cdi") else k: float(v) for k, v in c.items()}
            if (d / "elevation.npy").is_file() and "elevation" in truth:
                st = dem_error_stats(np.load(d / "elevation.npy"), truth["elevation"])
                full.update({f"dem_{k}": float(v) for k, v in st.items()})
            rec["scores_full"] = full
    return records


def summarize(records: list[dict], cfg: RunConfig, extra: dict) -> dict:
    lat = [r["latency_s"] for r in records if r.get("status") == "result"]
    e2e = [r["e2e_latency_s"] for r in records if r.get("status") == "result" and r.get("e2e_latency_s") is not None]
    line = [r["result_line_s"] for r in records if r.get("status") == "result" and r.get("result_line_s") is not None]
    n = len(records)
    met = sum(1 for r in records if r.get("status") == "result" and r.get("deadline_met"))
    return {
        "scenario": cfg.scenario,
        "link": cfg.link,
        "budget": cfg.budget,
        "preset": cfg.preset,
        "pairs": n,
        "results": sum(r.get("status") == "result" for r in records),
        "degraded": sum(bool(r.get("degraded")) for r in records),
        "errors": sum(r.get("status") != "result" for r in records),
        "deadline_hit_rate": met / n if n else float("nan"),
        "latency_p50_s": percentile(lat, 50),
        "latency_p95_s": percentile(lat, 95),
        "latency_max_s": max(lat) if lat else float("nan"),
        "e2e_latency_p50_s": percentile(e2e, 50),
        "e2e_latency_max_s": max(e2e) if e2e else float("nan"),
        "result_line_max_s": max(line) if line else float("nan"),
        "result_bytes_max": max((r.get("result_bytes", 0) for r in records), default=0),
        "link_errors": sum(r.get("code") == "link_down" for r in records),
        **extra,
        "records": records,
    }


def _fmt(v, spec: str = ".2f") -> str:
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "—"
    return format(v, spec)


def summary_table(summary: dict) -> str:
    rows = [
        "| pair | altitude m | outcome | level | latency s | deadline | FP % | CDI % | DEM mean abs m |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in summary["records"]:
        sc = r.get("scores", {})
        if r.get("status") == "result":
            outcome = "degraded" if r.get("degraded") else "result"
            dl = "met" if r.get("deadline_met") else "MISSED"
            rows.append(
                f"| {r['label']} | {_fmt(r['altitude_m'], '.0f')} | {outcome} | {r.get('level')} | "
                f"{_fmt(r.get('latency_s'))} | {dl} | {_fmt(sc.get('fp_pct'))} | {_fmt(sc.get('cdi_pct'))} | "
                f"{_fmt(sc.get('dem_mean_abs'))} |"
            )
        else:
            rows.append(
                f"| {r['label']} | {_fmt(r['altitude_m'], '.0f')} | error: {r.get('code')} | — | — | — | — | — | — |"
            )
    s = summary
    head = (
        f"**{s['scenario']}** over **{s['link']}** on budget **{s['budget']}** "
        f"(CPU fraction {_fmt(s.get('cpu_fraction'), '.4f')}, deadline {_fmt(s.get('deadline_s'))} s): "
        f"{s['results']}/{s['pairs']} results ({s['degraded']} degraded), {s['errors']} errors; "
        f"latency p50 {_fmt(s['latency_p50_s'])} s, p95 {_fmt(s['latency_p95_s'])} s, "
        f"max {_fmt(s['latency_max_s'])} s; deadline hit rate {_fmt(100 * s['deadline_hit_rate'], '.0f')} %"
    )
    return head + "\n\n" + "\n".join(rows) + "\n"


def run_descent(cfg: RunConfig, log=print) -> dict:
    """Run one end-to-end HIL descent; returns the summary (also written under ``cfg.out``)."""
    from hil_server.budgets import get_budget, load_calibration

    budget = get_budget(cfg.budget)
    fraction = budget.duty_fraction(load_calibration())
    deadline = float(cfg.deadline_s if cfg.deadline_s is not None else budget.deadline_s)
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    if cfg.link not in ("serial", "zmq"):
        raise InputError(f"--link must be serial or zmq, got {cfg.link!r}")
    if cfg.corrupt and (cfg.link != "serial" or not 0 <= cfg.corrupt <= 0.05):
        raise InputError("--corrupt applies to the serial link only, as a per-byte rate in [0, 0.05]")

    if cfg.manifest is not None:
        manifest = Path(cfg.manifest)
        if not manifest.is_file():
            raise InputError(f"manifest {manifest} does not exist (render pairs with `hazard-hil render`)")
    else:
        log(f"run: rendering {cfg.scenario} pairs into {out / 'pairs'}")
        manifest = _render(cfg, out / "pairs") / "manifest.json"

    bridge = None
    channels: dict = {}  # serial line faults by direction (--corrupt)
    if cfg.link == "serial":
        from protocol.faults import PtyBridge

        # Two raw ptys joined by a relay: each process opens a real serial device path.
        baud = cfg.baud if cfg.baud is not None else budget.baud
        if cfg.corrupt > 0:  # a noisy line in both directions, seeded: retransmission must hide it
            from protocol.faults import CorruptingChannel

            channels = {
                d: CorruptingChannel(seed=cfg.seed * 2 + k, drop=cfg.corrupt, flip=cfg.corrupt, dup=cfg.corrupt)
                for k, d in enumerate(("a_to_b", "b_to_a"))
            }
        bridge = PtyBridge(**channels)
        suffix = f"@{baud}" if baud else ""
        server_spec, ground_spec = f"serial:{bridge.paths[0]}{suffix}", f"serial:{bridge.paths[1]}{suffix}"
    else:
        port = _free_tcp_port()
        server_spec = ground_spec = f"zmq:tcp://127.0.0.1:{port}"
    security: list[str] = []
    if cfg.link == "zmq":
        if cfg.insecure:
            security = ["--insecure"]
        else:  # fresh CURVE keys for every run, private to its output directory
            import shutil

            from protocol.zmqauth import generate_keys

            shutil.rmtree(out / "keys", ignore_errors=True)
            security = ["--keys", str(generate_keys(out / "keys"))]

    env = dict(os.environ)
    telemetry = out / "telemetry.jsonl"
    telemetry.unlink(missing_ok=True)
    sup_cmd = [
        sys.executable,
        "-m",
        "hil_server.supervisor",
        "--link",
        server_spec,
        "--budget",
        cfg.budget,
        "--telemetry",
        str(telemetry),
        "--link-timeout",
        str(cfg.link_timeout_s),
        *security,
    ]
    if cfg.fault:
        sup_cmd += ["--fault", cfg.fault]
    if cfg.link_fault:
        sup_cmd += ["--link-fault", cfg.link_fault]
    ground_cmd = [
        sys.executable,
        "-m",
        "ground_sim.stream",
        "--link",
        ground_spec,
        "--manifest",
        str(manifest),
        "--out",
        str(out / "received"),
        "--budget",
        cfg.budget,
        "--deadline",
        str(deadline),
        "--preset",
        cfg.preset,
        "--pace",
        cfg.pace,
        "--link-timeout",
        str(cfg.link_timeout_s),
        "--elevation-step",
        str(cfg.elevation_step) if cfg.elevation_step else "auto",
        "--psafe-step",
        str(cfg.psafe_step) if cfg.psafe_step else "auto",
        *security,
    ]
    if cfg.full_maps:
        ground_cmd.append("--full-maps")
    log(
        f"run: budget {budget.name}: CPU fraction {fraction:.4f}, memory {budget.memory_mib} MiB, "
        f"deadline {deadline:g} s, link {server_spec}"
    )
    t0 = time.monotonic()
    with open(out / "supervisor.log", "w") as sup_log:
        sup = subprocess.Popen(sup_cmd, stdout=sup_log, stderr=subprocess.STDOUT, env=env)
        try:
            ground = subprocess.Popen(ground_cmd, env=env)
            try:
                rc = ground.wait(timeout=cfg.timeout_s)
            except subprocess.TimeoutExpired:
                ground.kill()
                raise TimeoutError(f"ground simulator did not finish within {cfg.timeout_s:.0f} s") from None
            if rc not in (0, EXIT_LINK_LOST):
                raise RuntimeError(f"ground simulator exited with {rc}; see {out / 'supervisor.log'}")
        finally:
            if sup.poll() is None:
                sup.send_signal(signal.SIGCONT)  # a supervisor frozen by a stall test must wake to terminate
                sup.send_signal(signal.SIGTERM)
                try:
                    sup.wait(timeout=15)
                except subprocess.TimeoutExpired:
                    sup.kill()
                    sup.wait()
            if bridge is not None:
                bridge.close()
    wall = time.monotonic() - t0

    records = [json.loads(line) for line in (out / "received" / "results.jsonl").read_text().splitlines() if line]
    score_records(records)
    counters = {}
    if telemetry.is_file():
        for line in telemetry.read_text().splitlines():
            rec = json.loads(line)
            if rec.get("event") == "summary":
                counters = {k: v for k, v in rec.items() if k != "event"}
    line_faults = {d: ch.stats for d, ch in channels.items()}
    summary = summarize(
        records,
        cfg,
        {
            "cpu_fraction": fraction,
            "deadline_s": deadline,
            "line_faults": line_faults,
            "memory_mib": budget.memory_mib,
            "wall_s": wall,
            "supervisor_counters": counters,
            "ground_exit": rc,
        },
    )
    (out / "summary.json").write_text(json.dumps(summary, indent=1, sort_keys=True, default=float) + "\n")
    table = summary_table(summary)
    (out / "summary.md").write_text(table)
    from hil_server.run_report import write_run_report

    write_run_report(summary, out / "report.html")
    log(table)
    return summary
