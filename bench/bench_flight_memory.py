"""Peak private memory of the flight process's work per camera size: the figures behind the HIL's memory model.

``hil_server.budgets.flight_peak_rss_mib`` refuses, up front, a camera whose flight process would not fit a
budget's memory ceiling, and ``flight_sw.warmup.HEAP_BYTES_PER_PIXEL`` is the heap the flight process touches
before a new camera's first pair. Both are fitted to what this script measures: each case runs in a fresh
process that does what the flight process does (``boot_warm_up``, then optionally ``prefault_heap`` for the
camera, then ``fast`` on the pair ``--runs`` times, with the altimeter and the sun as HIL frames carry them), while
a thread polls the private RSS every 2 ms with the HIL watchdog's own reader (``hil_server.procemu.private_rss_bytes``:
``RssAnon + RssShmem``, mapped library code not counted; docs/hil.md section 4).

``--scale 2`` upsamples both images (bicubic) and the camera, as a 1024^2 camera over the same ground.

    .venv/bin/python bench/bench_flight_memory.py [--pair DIR ...] [--scale 1 2] [--no-prefault]

Without ``--pair``: the held-out approach 1000/500 of the `thesis` scene (seed 1000, the largest world grid
of the eval pairs), rendered once into ``--cache``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

from _cli import InputError, out_file, positive_int, run, write_out

MIB = 2**20


def _private() -> tuple[int, int]:
    """(private RSS, its peak estimate) of this process, read as the HIL's memory watchdog reads the flight's."""
    from hil_server.procemu import private_rss_bytes

    mem = private_rss_bytes(os.getpid())
    assert mem is not None  # this process is alive
    return mem


class _Poller:
    """Largest private RSS seen by a 2 ms polling thread between start and stop, or the watchdog's peak estimate
    (``VmHWM - RssFile``) at the end, which catches a peak between two polls."""

    def __init__(self) -> None:
        self.peak = _private()[0]
        self._stop = threading.Event()
        self._t = threading.Thread(target=self._loop, daemon=True)

    def _loop(self) -> None:
        while not self._stop.wait(0.002):
            self.peak = max(self.peak, _private()[0])

    def __enter__(self) -> _Poller:
        self._t.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._t.join()
        self.peak = max(self.peak, *_private())


def upsampled(images: Any, camera: Any, scale: int) -> tuple[list[Any], Any]:
    """``images`` resized ``scale`` x (bicubic) and the camera that sees them: a finer camera over the same ground
    (pixel centres: ``u' = (u + 0.5) scale - 0.5``)."""
    import cv2

    from protocol.pairdir import Camera

    c = camera
    cam = Camera(
        c.width * scale, c.height * scale, c.fx * scale, c.fy * scale,
        (c.cx + 0.5) * scale - 0.5, (c.cy + 0.5) * scale - 0.5,
    )  # fmt: skip
    return [cv2.resize(a, None, fx=scale, fy=scale, interpolation=cv2.INTER_CUBIC) for a in images], cam


def child(pair_dir: str, scale: int, prefault: bool, runs: int, heap_bpp: float | None = None) -> dict:
    from flight_sw.pipeline import PRESETS, run_pipeline
    from flight_sw.warmup import HEAP_BYTES_PER_PIXEL, boot_warm_up, prefault_heap
    from protocol.pairdir import read_pair

    boot_warm_up(PRESETS["fast"])
    pair = read_pair(pair_dir)
    i1, i2 = pair.images[0], pair.images[-1]
    cam = pair.camera
    if scale != 1:
        (i1, i2), cam = upsampled((i1, i2), cam, scale)
    sun: dict[str, Any] = {}
    if pair.sun is not None:
        sun = {"sun_azimuth_deg": pair.sun.azimuth_deg, "sun_elevation_deg": pair.sun.elevation_deg}
    base = _private()[0]
    if prefault:
        bpp = HEAP_BYTES_PER_PIXEL if heap_bpp is None else heap_bpp
        prefault_heap(int(bpp * cam.width * cam.height / MIB))
    after_prefault = _private()[0]
    levels = []
    t0 = time.process_time()
    with _Poller() as poll:
        for _ in range(runs):
            r = run_pipeline(
                i1, i2, pair.poses[0], pair.poses[-1], cam, preset="fast", altimeter_m=pair.altimeter_m, **sun
            )
            levels.append(r.level)
            del r
    return {
        "pair": Path(pair_dir).name,
        "px": f"{cam.width}x{cam.height}",
        "pixels": cam.width * cam.height,
        "prefault": prefault,
        "base_mib": base / MIB,
        "after_prefault_mib": after_prefault / MIB,
        "peak_mib": poll.peak / MIB,
        "levels": levels,
        "cpu_s": time.process_time() - t0,
    }


def default_pair(cache: Path) -> Path:
    """The held-out approach 1000/500 (`thesis` scene, seed 1000, its own sun), rendered once into ``cache``."""
    from ground_sim import trajectory
    from ground_sim.descent import render_pair
    from ground_sim.library import scene_sun
    from ground_sim.render_cache import reusable
    from ground_sim.scene import load_scene, load_scene_params
    from ground_sim.seeds import HELD_OUT_SEEDS
    from protocol.pairdir import write_pair_atomic

    seed = HELD_OUT_SEEDS[0]
    d = cache / f"approach_thesis_s{seed}_1000_500"
    # renders from before the fingerprints are trusted (said); a changed scene or render code is drawn again
    if not reusable(d, scene=load_scene_params("thesis", "approach"), trust_unrecorded=True):
        spec = next(s for s in trajectory.approach(None) if s.label == "1000/500")
        scene = load_scene("thesis", seed, "approach")
        write_pair_atomic(d, render_pair(scene, spec, scene_sun(scene, "approach", seed), seed=seed))
    return d


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--pair", nargs="+", help="pair directories (default: the held-out approach 1000/500)")
    ap.add_argument("--cache", default="/tmp/bench_flight_memory", help="where the default pair is rendered")
    ap.add_argument("--scale", nargs="+", type=positive_int, default=[1, 2], help="upsampling factors (default 1 2)")
    ap.add_argument("--no-prefault", action="store_true", help="skip the heap prefault (the pipeline's own need)")
    ap.add_argument("--runs", type=positive_int, default=2, help="pipeline runs per process (default 2)")
    ap.add_argument("--heap-bytes-per-px", type=float, help="prefault this heap (default: flight_sw.warmup's)")
    ap.add_argument("--json", type=out_file, help="write the rows here")
    ap.add_argument("--child", nargs=3, metavar=("PAIR", "SCALE", "PREFAULT"), help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.child:
        print(json.dumps(child(a.child[0], int(a.child[1]), a.child[2] == "1", a.runs, a.heap_bytes_per_px)))
        return 0
    if not a.pair:
        a.pair = [str(default_pair(Path(a.cache)))]
    for d in a.pair:
        if not (Path(d) / "pair.json").is_file():
            raise InputError(f"--pair {d}: not a pair directory (no pair.json)")
    from hil_server.budgets import flight_peak_rss_mib

    rows = []
    print("| pair | camera | prefault | base MiB | after prefault | peak MiB | B/px over base | model MiB | levels |")
    print("|---|---|---|---:|---:|---:|---:|---:|---|")
    for d in a.pair:
        for s in a.scale:
            cmd = [sys.executable, __file__, "--pair", d, "--runs", str(a.runs), "--child", d, str(s)]
            cmd.append("0" if a.no_prefault else "1")
            if a.heap_bytes_per_px is not None:
                cmd += ["--heap-bytes-per-px", str(a.heap_bytes_per_px)]
            p = subprocess.run(cmd, capture_output=True, text=True)
            if p.returncode != 0:
                print(f"error: {d} x{s}: {p.stderr.strip().splitlines()[-1:]}", file=sys.stderr)
                return 1
            row = json.loads(p.stdout.strip().splitlines()[-1])
            row["bytes_per_px"] = (row["peak_mib"] - row["base_mib"]) * MIB / row["pixels"]
            row["model_mib"] = flight_peak_rss_mib(row["pixels"])
            rows.append(row)
            print(
                f"| {row['pair'][:40]} | {row['px']} | {'yes' if row['prefault'] else 'no'} | {row['base_mib']:.1f} | "
                f"{row['after_prefault_mib']:.1f} | {row['peak_mib']:.1f} | {row['bytes_per_px']:.0f} | "
                f"{row['model_mib']:.0f} | {','.join(row['levels'])} |",
                flush=True,
            )
    if a.json:
        write_out(a.json, json.dumps(rows, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    run(main)
