"""Encoded size of the compact Result per grid step, on the demo's three pairs (docs/benchmarks/protocol.md).

Renders the vertical 600/300, 300/150 and 200/100 pairs (thesis scene, seed 0, 512 px) into ``--cache``,
runs the `fast` pipeline on each and encodes the Result as the flight process builds it, for each
(P(safe) step, elevation step) the ground can pick (``ground_sim.stream.auto_grid_steps``).

    .venv/bin/python bench/bench_result_size.py [--cache /tmp/demo_pairs]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

STEPS = ((1, 1), (1, 2), (2, 2), (2, 4), (4, 8))


def result_bytes(res, camera, kp: int, k: int) -> int:
    """Encoded size of the Result the flight process builds from pipeline result ``res`` at steps (``kp``, ``k``)."""
    from flight_sw.flight_main import FlightProcess
    from protocol.codec import encode_message
    from protocol.messages import Config

    cfg = Config(
        camera=camera.to_dict(), budget="host", deadline_s=2.0, options={"psafe_step": kp, "elevation_step": k}
    )
    msg = FlightProcess._result_message(res, (1, 2), cfg, res.grid, res.sites, res.info.get("no_site_reason"))
    return len(encode_message(msg))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cache", default="/tmp/demo_pairs", help="where the demo pairs are rendered (reused)")
    args = ap.parse_args(argv)
    from flight_sw.pipeline import run_pipeline
    from ground_sim.descent import render_scenario
    from protocol.pairdir import read_pair

    out = Path(args.cache)
    if not (out / "manifest.json").is_file():
        render_scenario("vertical", out, pairs=["600/300", "300/150", "200/100"], progress=False)
    manifest = json.loads((out / "manifest.json").read_text())
    print("| pair | " + " | ".join(f"({kp}, {k})" for kp, k in STEPS) + " |")
    print("|---|" + "---:|" * len(STEPS))
    for e in manifest["pairs"]:
        pair = read_pair(out / e["path"])
        res = run_pipeline(pair.images[0], pair.images[-1], pair.poses[0], pair.poses[-1], pair.camera, preset="fast")
        print(
            f"| {e['label']} | " + " | ".join(f"{result_bytes(res, pair.camera, kp, k):,} B" for kp, k in STEPS) + " |",
            flush=True,
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
