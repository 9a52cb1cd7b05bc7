"""Stream a rendered descent to the flight side and collect what comes back.

The ground half of an HIL run: reads the pair directories listed in a
``manifest.json`` (written by ``hazard-hil render``), sends ``Config`` then two
``Frame``s per pair (upper = frame_index 0, lower = 1, sharing a ``pair_id``)
over the link, and records every ``Result``, ``Telemetry`` and ``Error``.

Pacing: ``lockstep`` (default) sends a pair, waits for its outcome, then sends
the next - clean per-pair latency. ``asap`` sends everything at once and shows
queueing on a slow processor. Every pair ends in ``results.jsonl`` as
``result`` or ``error`` with a reason; a pair with no answer within the
ground's own timeout is recorded as ``error: no_response`` - nothing is lost.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from protocol.errors import InputError
from protocol.messages import Config, Error, Frame, Heartbeat, Hello, Result, Telemetry
from protocol.pairdir import read_pair


@dataclass
class PairOutcome:
    pair_id: str
    label: str
    altitude_m: float
    pair_dir: str
    seqs: tuple[int, int]
    sent_at: float = 0.0
    result: Result | None = None
    telemetry: Telemetry | None = None
    error: Error | None = None
    link_s: float = 0.0
    notes: list[str] = field(default_factory=list)

    @property
    def finished(self) -> bool:
        return self.error is not None or (self.result is not None and self.telemetry is not None)


def _frame_from_pair(pair, index: int, seq: int, pair_id: str) -> Frame:
    pose = pair.poses[index]
    return Frame(
        seq=seq,
        capture_time_s=float(pose.time_s),
        position_m=tuple(float(v) for v in pose.position),
        R_world_to_cam=np.asarray(pose.R, dtype="<f8"),
        altimeter_m=float(pair.altimeter_m[index]),
        image=np.ascontiguousarray(pair.images[index]),
        pair_id=pair_id,
        frame_index=index,
    )


def write_outcome(out_dir: Path, o: PairOutcome) -> dict:
    """Save arrays of a finished pair under ``out_dir/<pair_id>/`` and return its JSON record."""
    rec: dict = {
        "pair_id": o.pair_id,
        "label": o.label,
        "altitude_m": o.altitude_m,
        "pair_dir": o.pair_dir,
        "frame_seqs": list(o.seqs),
        "link_s": o.link_s,
    }
    if o.error is not None:
        rec.update(status="error", code=o.error.code, text=o.error.text)
        return rec
    assert o.result is not None and o.telemetry is not None
    d = out_dir / o.pair_id
    d.mkdir(parents=True, exist_ok=True)
    r, t = o.result, o.telemetry
    np.save(d / "hazard_grid.npy", np.asarray(r.hazard_grid, dtype=np.float32))
    np.save(d / "elevation_grid.npy", np.asarray(r.elevation_grid, dtype=np.float32))
    if r.hazard_image is not None:
        np.save(d / "hazard.npy", np.asarray(r.hazard_image, dtype=np.float32))
    if r.elevation_image is not None:
        np.save(d / "elevation.npy", np.asarray(r.elevation_image, dtype=np.float32))
    rec.update(
        status="result",
        degraded=bool(r.degraded),
        level=r.level,
        grid_origin_xy=list(r.grid_origin_xy),
        grid_cell_m=r.grid_cell_m,
        sites=[[s.x, s.y, s.z, s.hazard, s.margin, s.distance_m] for s in r.sites],
        latency_s=t.total_latency_s,
        deadline_s=t.deadline_s,
        deadline_met=bool(t.deadline_met),
        queue_wait_s=t.queue_wait_s,
        cpu_fraction=t.cpu_fraction,
        peak_rss_mib=t.peak_rss_bytes / 2**20,
        stages=t.stages,
        link=t.link,
        out_dir=str(d),
    )
    return rec


def stream_descent(
    link,
    manifest_path: Path,
    out_dir: Path,
    *,
    budget: str,
    deadline_s: float,
    preset: str = "fast",
    pace: str = "lockstep",
    response_timeout_s: float | None = None,
    hello_timeout_s: float = 900.0,
    progress=None,
) -> list[dict]:
    """Run the ground side of a descent; returns one record per pair (also in ``results.jsonl``)."""
    manifest = json.loads(Path(manifest_path).read_text())
    base = Path(manifest_path).parent
    entries = manifest["pairs"]
    out_dir.mkdir(parents=True, exist_ok=True)
    timeout = response_timeout_s if response_timeout_s is not None else 3.0 * deadline_s + 30.0

    link.send(Hello(role="ground"))
    t0 = time.monotonic()
    next_note = t0 + 5.0
    while True:  # the server answers Hello once its flight process has booted
        msg = link.recv(timeout=0.5)
        if isinstance(msg, Hello):
            break
        now = time.monotonic()
        if now - t0 > hello_timeout_s:
            raise TimeoutError(f"no Hello from the HIL server within {hello_timeout_s:.0f} s")
        if now > next_note:  # a slow emulated processor boots slowly: show that we are waiting
            print(f"ground: waiting for the flight process to boot ({now - t0:.0f} s)", file=sys.stderr, flush=True)
            next_note = now + 10.0

    outcomes: dict[tuple[int, int], PairOutcome] = {}
    by_lower_seq: dict[int, PairOutcome] = {}
    records: list[dict] = []
    seq = 0
    config_sent = False
    results_path = out_dir / "results.jsonl"
    results_file = results_path.open("w")

    def collect(until: float, want: set[tuple[int, int]]) -> None:
        while want and time.monotonic() < until:
            msg = link.recv(timeout=0.2)
            if msg is None or isinstance(msg, (Heartbeat, Hello)):
                continue
            key = tuple(getattr(msg, "frame_seqs", ()) or ())
            o = outcomes.get(key) if key else None
            if isinstance(msg, Error):
                o = by_lower_seq.get(msg.seq) if msg.seq is not None else None
                if o is None:
                    o = next((x for x in outcomes.values() if msg.seq in x.seqs), None)
                if o is None:
                    print(f"ground: unattributed error from flight side: {msg.code}: {msg.text}", file=sys.stderr)
                    continue
                o.error = msg
            elif isinstance(msg, Result) and o is not None:
                o.result = msg
            elif isinstance(msg, Telemetry) and o is not None:
                o.telemetry = msg
            if o is not None and o.finished and o.seqs in want:
                want.discard(o.seqs)
                record(o)

    def record(o: PairOutcome) -> None:
        rec = write_outcome(out_dir, o)
        records.append(rec)
        results_file.write(json.dumps(rec, sort_keys=True) + "\n")
        results_file.flush()
        if progress:
            progress(rec)

    def give_up(o: PairOutcome, code: str, text: str) -> None:
        o.error = Error(code=code, seq=o.seqs[1], text=text)
        record(o)

    try:
        for i, entry in enumerate(entries):
            pair_dir = base / entry["path"]
            pair_id = f"p{i:03d}-{entry.get('label', i)}".replace("/", "_")
            o = PairOutcome(
                pair_id,
                str(entry.get("label", i)),
                float(entry.get("altitude_m", float("nan"))),
                str(pair_dir),
                (seq, seq + 1),
            )
            outcomes[o.seqs] = o
            by_lower_seq[seq + 1] = o
            seq += 2
            try:  # a bad pair (NaN pose, wrong size, unreadable file) is reported, the descent goes on
                pair = read_pair(pair_dir, load_truth=False)
                frames = [_frame_from_pair(pair, k, o.seqs[k], pair_id).validated() for k in (0, 1)]
            except InputError as exc:
                give_up(o, "bad_input", str(exc))
                continue
            if not config_sent:
                link.send(
                    Config(camera=pair.camera.to_dict(), budget=budget, deadline_s=float(deadline_s), preset=preset)
                )
                config_sent = True
            o.sent_at = time.monotonic()
            link_seqs = {link.send(f) for f in frames}
            link.flush(timeout=timeout)  # both frames on the far side: their line time is the link time
            o.link_s = time.monotonic() - o.sent_at
            failed = [f for f in link.failures() if f.seq in link_seqs]
            if failed:  # the link gave up on a frame: the pair cannot be processed, say so
                give_up(o, "link_failure", "; ".join(f"{f.message_type} not delivered: {f.reason}" for f in failed))
                continue
            if pace == "lockstep":
                collect(time.monotonic() + timeout + o.link_s, {o.seqs})
        pending = {
            s for s, o in outcomes.items() if not o.finished and not any(r["frame_seqs"] == list(s) for r in records)
        }
        if pending:
            collect(time.monotonic() + timeout * max(1, len(pending)), pending)
        for s, o in outcomes.items():
            if not any(r["frame_seqs"] == list(s) for r in records):
                o.error = Error(code="no_response", text=f"no result or error within {timeout:.0f} s", seq=s[1])
                rec = write_outcome(out_dir, o)
                records.append(rec)
                results_file.write(json.dumps(rec, sort_keys=True) + "\n")
    finally:
        results_file.close()
    return records


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m ground_sim.stream", description=__doc__.splitlines()[0])
    ap.add_argument("--link", required=True, help="serial:PATH[@BAUD] or zmq:ENDPOINT (connect)")
    ap.add_argument("--manifest", type=Path, required=True)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--budget", required=True)
    ap.add_argument("--deadline", type=float, required=True)
    ap.add_argument("--preset", default="fast")
    ap.add_argument("--pace", choices=("lockstep", "asap"), default="lockstep")
    args = ap.parse_args(argv)
    from protocol.linkspec import open_link

    link = open_link(args.link, server=False)

    def show(rec: dict) -> None:
        if rec["status"] == "result":
            flag = "met" if rec["deadline_met"] else "MISSED"
            print(
                f"ground: {rec['label']:>10}  {rec['level']:<10} latency {rec['latency_s']:7.2f} s  deadline {flag}",
                file=sys.stderr,
                flush=True,
            )
        else:
            print(f"ground: {rec['label']:>10}  ERROR {rec['code']}: {rec['text']}", file=sys.stderr, flush=True)

    try:
        records = stream_descent(
            link,
            args.manifest,
            args.out,
            budget=args.budget,
            deadline_s=args.deadline,
            preset=args.preset,
            pace=args.pace,
            progress=show,
        )
    finally:
        link.close()
    failed = sum(r["status"] != "result" for r in records)
    print(f"ground: {len(records)} pairs, {len(records) - failed} results, {failed} errors", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
