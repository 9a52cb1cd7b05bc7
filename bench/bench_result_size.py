"""Encoded size of the compact Result per grid step and elevation unit (docs/benchmarks/protocol.md).

By default renders the demo's vertical 600/300, 300/150 and 200/100 pairs (thesis scene, seed 0, 512 px)
into ``--cache``; ``--manifest`` takes any rendered descent instead (``hazard-hil render``). Runs the `fast`
pipeline on each pair and encodes the Result as the flight process builds it, for each (P(safe) step,
elevation step) the ground can pick (``ground_sim.stream.auto_grid_steps``) and each elevation unit in cm
(``auto_elevation_unit_cm``). ``--fused`` folds the pairs into one map, highest first, as the flight
process does in a HIL run, and encodes the fused map (its Results grow with the area the descent saw);
it also times that fold with the sites chosen on it (CPU ms, median of 5 from the same earlier map).

    .venv/bin/python bench/bench_result_size.py [--cache /tmp/demo_pairs]
    .venv/bin/python bench/bench_result_size.py --manifest DIR/manifest.json --fused --steps 2,2 --units 1,10
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from flight_sw.mapping import HazardGrid
    from flight_sw.sites import Site

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from _cli import InputError, run  # noqa: E402

STEPS = ((1, 1), (1, 2), (2, 2), (2, 4), (4, 8))


def result_bytes(res, camera, kp: int, k: int, unit: int = 1, grid=None, sites=None, reason=None) -> int:
    """Encoded size of the Result the flight process builds from pipeline result ``res`` at steps (``kp``, ``k``)
    and elevation unit ``unit`` cm; ``grid``/``sites``/``reason``: a fused map's instead of the pair's own."""
    from flight_sw.flight_main import FlightProcess
    from protocol.codec import encode_message
    from protocol.messages import RESULT_REV, Config

    # as the reference ground asks: every field of this schema (a Config without result_rev gets the baseline)
    options = {"psafe_step": kp, "elevation_step": k, "elevation_unit_cm": unit, "result_rev": RESULT_REV}
    cfg = Config(camera=camera.to_dict(), budget="host", deadline_s=2.0, options=options)
    if grid is None:
        grid, sites, reason = res.grid, res.sites, res.info.get("no_site_reason")
    msg = FlightProcess._result_message(res, (1, 2), cfg, grid, sites, reason)
    return len(encode_message(msg))


def _counts(text: str, option: str, n: int | None = None) -> tuple[int, ...]:
    """``text``'s comma-separated whole numbers >= 1 (exactly ``n`` of them if given)."""
    from protocol.errors import comma_items

    items = comma_items(text, option)
    try:
        values = tuple(int(v) for v in items)
    except ValueError:
        values = ()
    if not values or min(values) < 1 or (n is not None and len(values) != n):
        what = f"{n} comma-separated whole numbers >= 1" if n else "comma-separated whole numbers >= 1"
        raise InputError(f"{option}: expected {what}, got {text!r}")
    return values


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cache", default="/tmp/demo_pairs", help="where the demo pairs are rendered (reused)")
    ap.add_argument("--manifest", type=Path, default=None, help="a rendered descent's manifest.json instead")
    ap.add_argument("--fused", action="store_true", help="encode the map fused over the descent, as in a HIL run")
    ap.add_argument("--steps", default=None, help="kp,k pairs such as 2,2;2,4 (default: every auto choice)")
    ap.add_argument("--units", default="1", help="elevation units in cm, comma-separated (default 1)")
    args = ap.parse_args(argv)
    # every argument checked before a pair is rendered or run
    steps = STEPS if args.steps is None else tuple(_counts(s, "--steps", 2) for s in args.steps.split(";"))
    units = _counts(args.units, "--units")
    if args.manifest is not None and not args.manifest.is_file():
        raise InputError(f"--manifest {args.manifest}: no such file")
    from flight_sw.flight_main import FaultPlan, FlightProcess
    from flight_sw.pipeline import run_pipeline
    from ground_sim.descent import render_scenario
    from protocol.pairdir import read_pair

    if args.manifest is not None:
        out = args.manifest.parent
    else:
        out = Path(args.cache)
        if not (out / "manifest.json").is_file():
            render_scenario("vertical", out, pairs=["600/300", "300/150", "200/100"], progress=False)
    manifest = json.loads((out / "manifest.json").read_text())
    cols = [(kp, k, u) for kp, k in steps for u in units]
    fuse_col = " fuse + sites CPU |" if args.fused else ""
    print("| pair | level | " + " | ".join(f"({kp}, {k}) {u} cm" for kp, k, u in cols) + " |" + fuse_col)
    print("|---|---|" + "---:|" * (len(cols) + bool(args.fused)))
    flight = FlightProcess(None, FaultPlan())  # only its fusion: no link
    for e in sorted(manifest["pairs"], key=lambda e: -e["altitude_m"]):
        pair = read_pair(out / e["path"])
        sun = pair.sun
        res = run_pipeline(
            pair.images[0],
            pair.images[-1],
            pair.poses[0],
            pair.poses[-1],
            pair.camera,
            preset="fast",
            sun_elevation_deg=sun.elevation_deg if sun else None,
            sun_azimuth_deg=sun.azimuth_deg if sun else None,
        )
        fused: tuple[HazardGrid | None, list[Site] | None, str | None] = (None, None, None)  # the pair's own map
        cpu = ""
        if args.fused:
            before, times = flight.fused, []
            for _ in range(5):
                flight.fused = before
                t0 = time.process_time()
                fused = flight._fuse(res)
                times.append(time.process_time() - t0)
            cpu = f" {1e3 * statistics.median(times):.1f} ms |"
        sizes = [result_bytes(res, pair.camera, kp, k, u, *fused) for kp, k, u in cols]
        print(f"| {e['label']} | {res.level} | " + " | ".join(f"{b:,} B" for b in sizes) + " |" + cpu, flush=True)
    return 0


if __name__ == "__main__":
    run(main)
