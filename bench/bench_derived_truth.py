"""The truth hazard derived from DESIGN.md's own truth files against the renderer's (docs/design.md,
"Ground-truth hazard").

    .venv/bin/python bench/bench_derived_truth.py [--out /tmp/derived_truth] [--seed 1000] [--image-size 512]
    .venv/bin/python bench/bench_derived_truth.py --synthetic 2048     # time and peak memory only

Renders the vertical descent's 600/300, 300/150 and 200/100 pairs and the approach's 600/300, 300/150 and
250/125 (seed ``--seed``, held-out 1000 by default), runs `fast` on each (`hazard-hil process`), and compares per pair:

- the two truths pixel by pixel: agreement on unsafe (hazard >= 1) over the pixels both know, the share the
  derived truth calls safe where the renderer's raster calls it unsafe, and how much of frame 0 it resolves;
- `hazard-hil score` of the same output against each: FP, CDI, pixels scored and the top site's verdict;
- the derivation's time (median of 3).

Where frame 0 samples the ground too coarsely for any footprint's slope (the approach's 600/300 at 256 px), no
truth can be derived: the pair's row says so, with the reason, and keeps the scores against the renderer's truth.

Nothing here is tuned: the derivation has no free parameter but the footprint (3 m) and the half-seen disk rule.
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from _cli import InputError, bounded_int, out_dir, positive_int, run  # noqa: E402

from ground_sim.gridscore import complete_truth  # noqa: E402
from protocol.pairdir import IMAGE_SIZE_MAX, IMAGE_SIZE_MIN, read_pair  # noqa: E402

CASES = {"vertical": ["600/300", "300/150", "200/100"], "approach": ["600/300", "300/150", "250/125"]}


def hh(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "hil_server.cli", *args], cwd=ROOT, capture_output=True, text=True)


def score(pair: Path, out: Path, js: Path) -> dict:
    js.unlink(missing_ok=True)  # never an earlier pair's scores (exit 1 only says a pair is over the FP limit)
    scored = hh("score", str(pair), str(out), "--json", str(js))
    if not js.is_file():
        why = (scored.stderr.strip().splitlines() or [f"exit status {scored.returncode}"])[-1]
        raise SystemExit(f"bench_derived_truth: score {pair}: {why}")
    (row,) = json.loads(js.read_text())["rows"]
    return row


def check_reused(out: Path, seed: int, size: int) -> None:
    """Refuse an ``--out`` whose renders (reused: renders are looked up by scenario only) are of another seed or
    image size than asked for."""
    for scenario, pairs in CASES.items():
        if not (out / scenario / "manifest.json").is_file():
            continue
        for label in pairs:
            meta = out / scenario / label.replace("/", "_") / "pair.json"
            if not meta.is_file():
                continue
            m = json.loads(meta.read_text())
            have = (m.get("scene_seed"), (m.get("camera") or {}).get("width"))
            if have != (seed, size):
                raise InputError(
                    f"--out {out} holds {scenario} renders of seed {have[0]} at {have[1]} px, not seed {seed} at "
                    f"{size} px: give another --out"
                )


def table(rows: list[dict[str, Any]]) -> list[str]:
    """The Markdown table; a pair whose truth could not be derived says so in its row, with the reason."""
    head = ("pair", "resolved %", "agree %", "derived safe, raster unsafe %", "FP % raster / derived", "CDI %")
    out = ["| " + " | ".join(head) + " | top site | s |", "|---|---:|---:|---:|---|---|---|---:|"]
    for r in rows:
        if r.get("not_derived"):
            out.append(
                f"| {r['pair']} | 0.0 | no truth derived: {r['not_derived']} | - | {r['fp'][0]:.2f} / - | "
                f"{r['cdi'][0]:.1f} / - | {r['top'][0]} / - | {r['s']:.3f} |"
            )
            continue
        out.append(
            f"| {r['pair']} | {r['resolved_pct']:.1f} | {r['agree_pct']:.1f} | {r['missed_pct']:.2f} | "
            f"{r['fp'][0]:.2f} / {r['fp'][1]:.2f} | {r['cdi'][0]:.1f} / {r['cdi'][1]:.1f} | "
            f"{r['top'][0]} / {r['top'][1]} | {r['s']:.3f} |"
        )
    return out


def synthetic(n: int) -> None:
    """Time and peak memory of the derivation alone on an n x n oblique lattice (rows 7x coarser far out)."""
    import resource

    from ground_sim.truth import hazard_from_points

    v, u = np.arange(n), np.arange(n)
    spread = 1 + 6.0 * (v[:, None] / n) ** 3
    yy = np.repeat(np.cumsum(0.13 * (1 + 6.0 * (v / n) ** 3))[:, None], n, 1)
    P = np.dstack([(u[None, :] - n / 2) * 0.13 * spread * 0.5, yy, np.random.default_rng(0).normal(0, 0.05, (n, n))])
    del yy
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    t0 = time.perf_counter()
    h = hazard_from_points(P)
    dt = time.perf_counter() - t0
    grew = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before) * 1024 / (n * n)
    print(f"{n}x{n} oblique lattice: {dt:.2f} s, peak grew {grew:.0f} B per pixel, {np.isfinite(h).mean():.0%} known")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=out_dir, default=Path("/tmp/derived_truth"))
    ap.add_argument("--seed", type=int, default=1000, help="a held-out seed by default (the project's seed sets)")
    ap.add_argument(
        "--image-size",
        type=bounded_int(IMAGE_SIZE_MIN, IMAGE_SIZE_MAX),
        default=512,
        help=f"px, {IMAGE_SIZE_MIN}..{IMAGE_SIZE_MAX}",
    )
    ap.add_argument("--synthetic", type=positive_int, default=None, metavar="N", help="time an N x N lattice instead")
    args = ap.parse_args()
    if args.synthetic:
        synthetic(args.synthetic)
        return 0
    check_reused(args.out, args.seed, args.image_size)
    rows: list[dict[str, Any]] = []
    for scenario, pairs in CASES.items():
        d = args.out / scenario
        if not (d / "manifest.json").is_file():
            rendered = hh("render", "--scenario", scenario, "--pairs", ",".join(pairs), "--seed", str(args.seed),
                          "--image-size", str(args.image_size), "--out", str(d))  # fmt: skip
            if rendered.returncode:
                sys.exit(rendered.stderr)
        for label in pairs:
            pair = d / label.replace("/", "_")
            out = args.out / "outputs" / f"{scenario}_{pair.name}"
            if not (out / "hazard.npy").is_file():
                hh("process", str(pair), "--out", str(out))
            mine = args.out / "nogt" / f"{scenario}_{pair.name}"
            shutil.rmtree(mine, ignore_errors=True)
            shutil.copytree(pair, mine)
            (mine / "gt_hazard_i1.npy").unlink()
            p = read_pair(mine)
            times, note = [], None
            for _ in range(3):
                p.truth.pop("hazard", None)
                t0 = time.perf_counter()
                note = complete_truth(p)
                times.append(time.perf_counter() - t0)
            a = score(pair, out, args.out / "a.json")
            if "hazard" not in p.truth:  # the files give no footprint's hazard (ground sampled too coarsely, ...)
                rows.append(
                    {
                        "pair": f"{scenario} {label}",
                        "not_derived": note or "no truth could be derived",
                        "fp": (a["fp_pct"], None),
                        "cdi": (a["cdi_pct"], None),
                        "pixels": (a["pixels"], None),
                        "top": (a["top_site_truly_safe"], None),
                        "s": statistics.median(times),
                    }
                )
                print(f"{scenario} {label}: no truth derived: {note}", file=sys.stderr, flush=True)
                continue
            g, h = read_pair(pair).truth["hazard"], p.truth["hazard"]
            both = np.isfinite(g) & np.isfinite(h)
            b = score(mine, out, args.out / "b.json")
            rows.append(
                {
                    "pair": f"{scenario} {label}",
                    "resolved_pct": 100 * float(np.mean(np.isfinite(h))),
                    "agree_pct": 100 * float(np.mean((g[both] >= 1) == (h[both] >= 1))),
                    "missed_pct": 100 * float(np.mean((g[both] >= 1) & (h[both] < 1))),
                    "fp": (a["fp_pct"], b["fp_pct"]),
                    "cdi": (a["cdi_pct"], b["cdi_pct"]),
                    "pixels": (a["pixels"], b["pixels"]),
                    "top": (a["top_site_truly_safe"], b["top_site_truly_safe"]),
                    "s": statistics.median(times),
                }
            )
    print("\n".join(table(rows)))
    return 0


if __name__ == "__main__":
    run(main)
