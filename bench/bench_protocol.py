"""Protocol benchmarks: codec cost, link throughput/latency (pty, socketpair, ZeroMQ), decoder fuzz.

    .venv/bin/python bench/bench_protocol.py            # codec + links
    .venv/bin/python bench/bench_protocol.py --fuzz     # + >= 100 000 mutated decoder inputs
Reports medians of repeated runs (the machine is shared; timings are noisy).
"""

from __future__ import annotations

import argparse
import socket
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from protocol.codec import decode_message, decode_parts, encode_message, encode_parts
from protocol.faults import PtyBridge
from protocol.framing import StreamDecoder, encode_stream_frame
from protocol.fuzz import fuzz_decoder, sample_messages
from protocol.links import SerialLink, StreamLink, ZmqLink
from protocol.messages import Frame, Heartbeat


def frame(i: int) -> Frame:
    img = np.random.default_rng(i).integers(0, 256, (512, 512), dtype=np.uint8)
    return Frame(
        seq=i,
        capture_time_s=float(i),
        position_m=(0.0, 0.0, 1000.0),
        R_world_to_cam=np.eye(3),
        altimeter_m=1000.0,
        image=img,
    )


def timeit(fn, n: int) -> float:
    ts = []
    for _ in range(n):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts)


def bench_codec(n: int = 50) -> None:
    f = frame(0)
    body = encode_message(f)
    wire = encode_stream_frame(f, 1)
    parts = encode_parts(f, 64 << 10)
    print(
        f"512x512 Frame: body {len(body)} B, stream frame {len(wire)} B "
        f"(overhead {100 * (len(wire) / f.image.nbytes - 1):.2f} %)"
    )
    print(f"  msgpack encode          {1e3 * timeit(lambda: encode_message(f), n):7.3f} ms")
    print(f"  msgpack decode          {1e3 * timeit(lambda: decode_message(body), n):7.3f} ms")
    print(f"  stream frame encode     {1e3 * timeit(lambda: encode_stream_frame(f, 1), n):7.3f} ms")
    print(f"  stream frame decode     {1e3 * timeit(lambda: StreamDecoder().feed(wire), n):7.3f} ms")
    print(f"  zmq parts encode        {1e3 * timeit(lambda: encode_parts(f, 64 << 10), n):7.3f} ms")
    print(f"  zmq parts decode        {1e3 * timeit(lambda: decode_parts(parts[0], parts[1]), n):7.3f} ms")


def _throughput(a, b, label: str, n: int = 20) -> None:
    frames = [frame(i) for i in range(n)]
    t0 = time.perf_counter()
    for f in frames:
        a.send(f)
    for _ in range(n):
        assert b.recv(30.0) is not None
    dt = time.perf_counter() - t0
    nbytes = a.stats["bytes_sent"]
    lat = []
    for i in range(30):  # small-message round trip: one Heartbeat there and back
        t = time.perf_counter()
        a.send(Heartbeat(time_s=float(i)))
        m = b.recv(5.0)
        b.send(m)
        assert a.recv(5.0) is not None
        lat.append(time.perf_counter() - t)
    print(
        f"  {label:28s} {nbytes / dt / 1e6:8.1f} MB/s ({n} frames in {dt:.2f} s); "
        f"heartbeat RTT median {1e3 * statistics.median(lat):.3f} ms, p90 {1e3 * np.percentile(lat, 90):.3f} ms"
    )


def bench_links() -> None:
    print("link throughput, 20 x 512x512 Frames (acked stop-and-wait on byte streams):")
    with PtyBridge() as br, SerialLink(br.paths[0]) as a, SerialLink(br.paths[1]) as b:
        _throughput(a, b, "pty bridge (SerialLink)")
    s1, s2 = socket.socketpair()
    with StreamLink(s1) as a, StreamLink(s2) as b:
        _throughput(a, b, "socketpair (StreamLink)")
    s1, s2 = socket.socketpair()
    with StreamLink(s1, acks=False) as a, StreamLink(s2, acks=False) as b:
        _throughput(a, b, "socketpair, no acks")
    with ZmqLink("tcp://127.0.0.1:*", bind=True) as a, ZmqLink(a.endpoint, bind=False) as b:
        time.sleep(0.2)
        _throughput(a, b, "ZeroMQ tcp://127.0.0.1")
    f = frame(0)
    nbytes = len(encode_stream_frame(f, 1))
    print(
        f"  at 115200 baud a 512x512 Frame costs {nbytes * 10 / 115200:.1f} s of line time (computed; "
        f"pacing verified in tests/test_protocol_links.py)"
    )


def bench_fuzz(n: int, seed: int) -> None:
    t0 = time.perf_counter()
    rep = fuzz_decoder(n, seed, sample_messages(seed, image_side=32))
    dt = time.perf_counter() - t0
    print(f"fuzz: {rep['inputs']} inputs, {rep['bytes'] / 1e6:.1f} MB in {dt:.1f} s: {rep}")
    if rep["spurious"] or rep["missed_intact"] or rep["out_of_order"]:
        raise SystemExit("FUZZ FAILURE")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--fuzz", action="store_true", help="run the decoder fuzz campaign")
    ap.add_argument("--fuzz-inputs", type=int, default=100_000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--skip-links", action="store_true")
    args = ap.parse_args()
    bench_codec()
    if not args.skip_links:
        bench_links()
    if args.fuzz:
        bench_fuzz(args.fuzz_inputs, args.seed)
    return 0


if __name__ == "__main__":
    sys.exit(main())
