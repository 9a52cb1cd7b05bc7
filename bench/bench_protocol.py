"""Protocol benchmarks (docs/benchmarks/protocol.md): codec, compact Result, decoder bombs, link throughput
against line rate, noisy lines, stall/close detection, and the fuzz campaigns.

    .venv/bin/python bench/bench_protocol.py                # everything but the fuzz campaigns
    .venv/bin/python bench/bench_protocol.py --fuzz         # + 100 000 noise and 100 000 hostile inputs
    .venv/bin/python bench/bench_protocol.py --only bombs,links --json out/protocol.json

Reports medians of repeated runs (the machine is shared; timings are noisy, CPU
times are given beside wall times where it matters). Line-rate figures do not
depend on the host's speed: the links pace themselves at the baud rate.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import signal
import socket
import statistics
import subprocess
import sys
import time
import tracemalloc
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from _cli import out_path, positive_int, run, unknown, write_out  # noqa: E402

from protocol.arq import ArqConfig  # noqa: E402
from protocol.codec import decode_message, encode_message  # noqa: E402
from protocol.errors import comma_items  # noqa: E402
from protocol.faults import CorruptingChannel, PtyBridge  # noqa: E402
from protocol.fuzz import fuzz_hostile, fuzz_noise, nested_map_bomb  # noqa: E402
from protocol.links import LOCAL_CONFIG, SerialLink, StreamLink, ZmqLink  # noqa: E402
from protocol.messages import Error, Frame, Hello  # noqa: E402
from protocol.zmqauth import generate_keys  # noqa: E402

RESULTS: dict = {}


def frame(i: int, side: int = 512) -> Frame:
    img = np.random.default_rng(i).integers(0, 256, (side, side), dtype=np.uint8)
    return Frame(
        seq=i, capture_time_s=float(i), position_m=(0.0, 0.0, 1e3), R_world_to_cam=np.eye(3), altimeter_m=1e3, image=img
    )


def timeit(fn, n: int) -> tuple[float, float]:
    """(median wall s, median CPU s) of ``n`` calls."""
    ws, cs = [], []
    for _ in range(n):
        t0, c0 = time.perf_counter(), time.process_time()
        fn()
        ws.append(time.perf_counter() - t0)
        cs.append(time.process_time() - c0)
    return statistics.median(ws), statistics.median(cs)


# ----------------------------------------------------------------------------------- codec, Result
def bench_codec() -> None:
    f = frame(0)
    body = encode_message(f)
    enc = timeit(lambda: encode_message(f), 30)
    dec = timeit(lambda: decode_message(body), 30)
    print(f"512x512 Frame: body {len(body)} B; encode {1e3 * enc[0]:.3f} ms, decode {1e3 * dec[0]:.3f} ms")
    RESULTS["frame"] = {"body_bytes": len(body), "encode_ms": 1e3 * enc[0], "decode_ms": 1e3 * dec[0]}


def _demo_pairs() -> Path:
    d = ROOT / "out" / "bench_protocol_pairs"
    if not (d / "manifest.json").is_file():
        from ground_sim.descent import render_scenario

        print("rendering the demo pairs once (out/bench_protocol_pairs) ...", flush=True)
        render_scenario("vertical", d, pairs=["600/300", "300/150", "200/100"], progress=False)
    return d


def bench_result() -> None:
    """The compact Result of the real pipeline on the demo pairs: bytes and line time per elevation step."""
    from flight_sw.flight_main import FlightProcess
    from flight_sw.pipeline import run_pipeline
    from protocol.messages import RESULT_REV, Config
    from protocol.pairdir import read_pair

    rows = []
    for label in ("600_300", "300_150", "200_100"):
        pair = read_pair(_demo_pairs() / label, load_truth=False)
        res = run_pipeline(pair.images[0], pair.images[-1], pair.poses[0], pair.poses[-1], pair.camera, preset="fast")
        row: dict[str, Any] = {"pair": label, "grid": list(res.grid.state.shape)}
        for pstep, step in ((1, 1), (1, 2), (2, 4), (4, 8)):  # ground_sim.stream.auto_grid_steps by line rate
            opts = {"elevation_step": step, "psafe_step": pstep, "result_rev": RESULT_REV}  # as our ground asks
            cfg = Config(camera=pair.camera.to_dict(), budget="b", deadline_s=2.0, options=opts)
            msg = FlightProcess._result_message(res, (0, 1), cfg, res.grid, res.sites, res.info.get("no_site_reason"))
            b = encode_message(msg)
            row[f"p{pstep}e{step}_bytes"] = len(b)
            if step == 8:
                row["encode_ms"] = 1e3 * timeit(lambda m=msg: encode_message(m), 10)[1]
                row["decode_ms"] = 1e3 * timeit(lambda b=b: decode_message(b), 10)[1]
        cfg = Config(
            camera=pair.camera.to_dict(), budget="b", deadline_s=2.0, options={"full_maps": 1, "result_rev": RESULT_REV}
        )
        full = FlightProcess._result_message(res, (0, 1), cfg, res.grid, res.sites, res.info.get("no_site_reason"))
        row["full_maps_bytes"] = len(encode_message(full))
        rows.append(row)
        print(
            f"Result {label}: grid {row['grid']}, steps (P(safe), elevation) (1,1) {row['p1e1_bytes']} B, "
            f"(1,2) {row['p1e2_bytes']} B, (2,4) {row['p2e4_bytes']} B, (4,8) {row['p4e8_bytes']} B; "
            f"with full maps {row['full_maps_bytes']} B; encode {row['encode_ms']:.1f} ms CPU, "
            f"decode {row['decode_ms']:.1f} ms CPU"
        )
    RESULTS["result"] = rows


# ----------------------------------------------------------------------------------- bombs
def bench_bombs(repeat: int = 20) -> None:
    from protocol.codec import CodecError

    out = {}
    for mib in (4, 32):
        body = nested_map_bomb(mib << 20)

        def refuse(body=body) -> None:
            try:
                decode_message(body)
            except CodecError:
                return
            raise AssertionError("bomb accepted")

        rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        wall, cpu = timeit(refuse, repeat)
        rss1 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        tracemalloc.start()
        refuse()
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        out[f"{mib}MiB"] = {
            "body_bytes": len(body),
            "wall_ms": 1e3 * wall,
            "cpu_ms": 1e3 * cpu,
            "traced_peak_kib": peak / 1024,
            "maxrss_delta_mib": (rss1 - rss0) / 1024,
        }
        print(
            f"bomb {mib} MiB ({len(body)} B): refused in {1e3 * wall:.2f} ms wall / {1e3 * cpu:.2f} ms CPU "
            f"(median of {repeat}); allocations {peak / 1024:.1f} KiB, max RSS +{(rss1 - rss0) / 1024:.1f} MiB"
        )
    RESULTS["bombs"] = out


# ----------------------------------------------------------------------------------- links
def _goodput(a, b, msgs) -> tuple[float, float, float]:
    """(payload bytes, seconds from the first send to the last delivery, bytes on the wire)."""
    assert a.wait_established(10) and b.wait_established(10)
    b0 = a.stats["bytes_sent"]
    payload = sum(len(encode_message(m)) for m in msgs)
    t0 = time.monotonic()
    ids = [a.send(m) for m in msgs]
    for _ in msgs:
        assert b.recv(600) is not None
    assert a.flush(60) and all(a.outcome(i) == "delivered" for i in ids)
    t = max(a.times(i).delivered for i in ids) - t0
    return payload, t, a.stats["bytes_sent"] - b0


def bench_links(repeat: int = 3) -> None:
    print("link throughput against line rate (8N1: baud / 10 bytes per second), medians of", repeat)
    rows = []
    for baud, msgs in ((921600, [frame(i, 512) for i in range(2)]), (115200, [frame(i, 256) for i in range(1)])):
        effs = []
        for _ in range(repeat):
            with PtyBridge() as br, SerialLink(br.paths[0], baud=baud) as a, SerialLink(br.paths[1], baud=baud) as b:
                payload, t, wire = _goodput(a, b, msgs)
            effs.append((payload / t / (baud / 10), wire / payload - 1))
        eff = statistics.median(e for e, _ in effs)
        rows.append({"link": f"pty {baud} baud", "payload_bytes": payload, "goodput_of_line": eff})
        print(f"  pty bridge at {baud} baud: {payload} B payload, goodput {100 * eff:.1f} % of the line rate "
              f"(framing+ack overhead on the wire {100 * effs[0][1]:.1f} %)")  # fmt: skip
    for label, cfg in (("socketpair, 1 KiB frames", ArqConfig()), ("socketpair, local (64 KiB)", LOCAL_CONFIG)):
        rates = []
        for _ in range(repeat):
            s1, s2 = socket.socketpair()
            with StreamLink(s1, config=cfg) as a, StreamLink(s2, config=cfg) as b:
                payload, t, _ = _goodput(a, b, [frame(i, 512) for i in range(10)])
            rates.append(payload / t / 1e6)
        rows.append({"link": label, "MB_per_s": statistics.median(rates)})
        print(f"  {label}: {statistics.median(rates):.1f} MB/s (unpaced: CPU-bound)")
    keys = generate_keys(ROOT / "out" / f"bench_keys_{os.getpid()}")
    for label, kw in (("ZeroMQ tcp, CURVE", {"keys": keys}), ("ZeroMQ tcp, insecure", {"insecure": True})):
        rates = []
        for _ in range(repeat):
            with ZmqLink("tcp://127.0.0.1:*", bind=True, **kw) as s, ZmqLink(s.endpoint, bind=False, **kw) as c:
                assert c.wait_established(10) and s.wait_established(10)
                msgs = [frame(i, 512) for i in range(20)]
                t0 = time.monotonic()
                for m in msgs:
                    c.send(m)
                for _ in msgs:
                    assert s.recv(60) is not None
                rates.append(sum(len(encode_message(m)) for m in msgs) / (time.monotonic() - t0) / 1e6)
        rows.append({"link": label, "MB_per_s": statistics.median(rates)})
        print(f"  {label}: {statistics.median(rates):.1f} MB/s")
    import shutil

    shutil.rmtree(keys, ignore_errors=True)
    RESULTS["links"] = rows


def bench_noise(baud: int = 921600) -> None:
    """Two SerialLinks over a pty bridge with drop, flip and duplicate at rate r per byte, both directions."""
    print(f"noisy pty line at {baud} baud: 8 x 128x128 Frames (16.4 kB each) one way")
    rows = []
    for r in (1e-4, 1e-3, 1e-2):
        chans = [CorruptingChannel(seed=k, drop=r, flip=r, dup=r) for k in (1, 2)]
        msgs = [frame(i, 128) for i in range(8)]
        with PtyBridge(*chans) as br, SerialLink(br.paths[0], baud=baud) as a, SerialLink(br.paths[1], baud=baud) as b:
            assert a.wait_established(30) and b.wait_established(30)
            t0 = time.monotonic()
            ids = [a.send(m) for m in msgs]
            deadline = t0 + 120
            while time.monotonic() < deadline and any(a.outcome(i) == "pending" for i in ids):
                time.sleep(0.05)
            outs = [a.outcome(i) or "?" for i in ids]
            got = 0
            while b.recv(0.2) is not None:
                got += 1
            st = a.stats
        delivered = sum(o == "delivered" for o in outs)
        failed = [o for o in outs if o.startswith("failed")]
        dt = time.monotonic() - t0
        row: dict[str, Any] = {
            "rate": r,
            "delivered": delivered,
            "received": got,
            "failed": len(failed),
            "pending": sum(o == "pending" for o in outs),
            "seconds": dt,
            "goodput_of_line": delivered * len(encode_message(msgs[0])) / dt / (baud / 10),
            "retransmits": st["retransmits"],
            "frame_bytes": st["frame_bytes"],
            "first_failure": failed[0] if failed else None,
            "bytes_hit": sum(c.stats["dropped"] + c.stats["flipped"] + c.stats["duplicated"] for c in chans),
        }
        rows.append(row)
        print(
            f"  r={r:g}: {delivered}/8 delivered ({got} received), {len(failed)} failed, {row['pending']} pending "
            f"after {dt:.1f} s; goodput {100 * row['goodput_of_line']:.1f} % of line; "
            f"{int(st['retransmits'])} retransmissions, frame size now {int(st['frame_bytes'])} B"
            + (f"; {failed[0][:90]}" if failed else "")
        )
    RESULTS["noise"] = rows


def _paused_line(baud: int, pause_s: float) -> dict[str, Any]:
    """One window-0 pause of ``pause_s`` on a simulated line at ``baud`` (see :func:`bench_pause`)."""
    from protocol.linesim import paused_receiver

    rate = baud / 10
    a, b, line = paused_receiver(rate, 40)
    t, before = line.now, dict(a.stats)
    t = line.run(t + pause_s)
    sent = a.stats["bytes_sent"] - before["bytes_sent"]
    b.set_rx_full(False, t)
    line.run(t + 600.0, stop=lambda s: a.idle)
    got = [r.message.text[:6] for r in line.received[1]]
    return {
        "baud": baud,
        "line_busy_pct": 100.0 * sent / (pause_s * rate),
        "probes": a.stats["probes"] - before["probes"],
        "frames": a.stats["frames_sent"] - before["frames_sent"],
        "in_order": got == [f"{i:06d}" for i in range(40)],
        "after_s": line.now - t,
        "session_losses": a.stats["peer_losses"] + b.stats["peer_losses"],
    }


def bench_pause(pause_s: float = 20.0) -> None:
    """A receiver that reads nothing for ``pause_s`` (window 0, docs/protocol.md section 3.2) with 40 kB in flight,
    on a simulated line (protocol.linesim, 0.1 s latency): the sender direction's use of the line meanwhile, and
    the time to deliver everything once it reads again. Deterministic: no wall clock."""
    print(f"a {pause_s:g} s pause of the receiving application, 40 x 0.9 kB in flight (simulated line)")
    rows = [_paused_line(baud, pause_s) for baud in (921600, 115200, 9600)]
    for row in rows:
        print(
            f"  {row['baud']} baud: sender's direction {row['line_busy_pct']:.1f} % busy during the pause "
            f"({row['probes']} probes, {row['frames']} frames); all delivered in order: {row['in_order']}, "
            f"{row['after_s']:.1f} s after reading resumed; sessions lost: {row['session_losses']}"
        )
    RESULTS["pause"] = rows


PEER = ROOT / "tests" / "protocol_peer.py"


def bench_timeouts(repeat: int = 3) -> None:
    """A peer process on a pty bridge freezes (SIGSTOP), dies (SIGKILL) or closes: time to an explicit error."""
    print("far-end failure -> explicit error (pty bridge: the line stays open, only the protocol can tell)")
    rows = {}
    for how in ("stop", "kill", "close"):
        times = []
        for _ in range(repeat):
            with PtyBridge() as br:
                env = dict(os.environ, PYTHONPATH=str(ROOT))
                peer = subprocess.Popen([sys.executable, str(PEER), "serial", br.paths[1]], env=env)
                try:
                    with SerialLink(br.paths[0], baud=921600) as g:
                        assert g.wait_established(60) and isinstance(g.recv(60), Hello)
                        if how == "close":
                            g.send(Error(code="done", text=""))  # the peer answers, sends Telemetry, closes
                            t0 = time.monotonic()
                            while g.established and time.monotonic() - t0 < 30:
                                g.recv(0.01)
                        else:
                            mid = g.send(frame(0, 512))
                            time.sleep(0.5)
                            os.kill(peer.pid, signal.SIGSTOP if how == "stop" else signal.SIGKILL)
                            t0 = time.monotonic()
                            while g.outcome(mid) == "pending" and time.monotonic() - t0 < 30:
                                time.sleep(0.005)
                        times.append(time.monotonic() - t0)
                finally:
                    if peer.poll() is None:
                        os.kill(peer.pid, signal.SIGKILL)
                    peer.wait(10)
        rows[how] = {"median_s": statistics.median(times), "max_s": max(times)}
        print(f"  peer {how}: explicit error after {statistics.median(times):.2f} s median, {max(times):.2f} s max")
    RESULTS["timeouts"] = rows


PROGRESS_S = 10.0  # a fuzz campaign's progress line on stderr at least this often (and at each tenth of it)


def fuzz_progress(label: str, n: int, every_s: float = PROGRESS_S) -> Callable[[int], None]:
    """A fuzz campaign's ``progress`` callback: how far it is, on stderr, every ``every_s`` seconds and at each
    tenth of its ``n`` inputs."""
    t0 = last = time.monotonic()
    tenth = max(1, n // 10)

    def say(done: int) -> None:
        nonlocal last
        if done and (done % tenth == 0 or time.monotonic() - last >= every_s):
            last = time.monotonic()
            print(f"  {label}: {done}/{n} inputs, {last - t0:.0f} s", file=sys.stderr, flush=True)

    return say


def bench_fuzz(n: int, seed: int) -> None:
    t0 = time.perf_counter()
    rep = fuzz_noise(n, seed, progress=fuzz_progress("noise fuzz", n))
    dt = time.perf_counter() - t0
    print(f"noise fuzz: {rep['inputs']} inputs, {rep['bytes'] / 1e6:.1f} MB in {dt:.0f} s: {rep}")
    t0 = time.perf_counter()
    host = fuzz_hostile(n, seed, progress=fuzz_progress("hostile fuzz", n))
    dt2 = time.perf_counter() - t0
    print(f"hostile fuzz: {host['inputs']} inputs, {host['bytes'] / 1e6:.1f} MB in {dt2:.0f} s: {host}")
    RESULTS["fuzz"] = {"noise": rep, "noise_s": dt, "hostile": host, "hostile_s": dt2}
    if rep["spurious"] or rep["missed"] or host["violations"]:
        raise SystemExit("FUZZ FAILURE")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--fuzz", action="store_true", help="run the fuzz campaigns")
    ap.add_argument("--fuzz-inputs", type=positive_int, default=100_000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--only", default="", help="comma-separated: codec,result,bombs,links,noise,pause,timeouts")
    ap.add_argument("--json", type=out_path, default=None, help="also write the figures as JSON")
    args = ap.parse_args()
    steps = {
        "codec": bench_codec,
        "result": bench_result,
        "bombs": bench_bombs,
        "links": bench_links,
        "noise": bench_noise,
        "pause": bench_pause,
        "timeouts": bench_timeouts,
    }
    wanted = comma_items(args.only, "--only") or list(steps)
    unknown("--only", wanted, steps)  # before any step runs
    load = os.getloadavg()[0]
    print(f"host load average {load:.2f} on {os.cpu_count()} cores")
    RESULTS["load"] = load
    for name in wanted:
        steps[name]()
    if args.fuzz:
        bench_fuzz(args.fuzz_inputs, args.seed)
    if args.json:
        write_out(args.json, json.dumps(RESULTS, indent=1, default=float) + "\n")
    return 0


if __name__ == "__main__":
    run(main)
