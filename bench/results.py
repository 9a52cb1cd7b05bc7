"""Regenerate the measured parts of docs/RESULTS.md from `evaluate` and `landings` output directories.

`make results` runs the campaigns and then this script; it copies the tables, per-pair metrics and a few
figures into docs/results/ and replaces the text between ``<!-- BEGIN name -->`` and ``<!-- END name -->``
markers in docs/RESULTS.md (blocks: ``vertical``, ``approach``, ``multiframe`` when the evaluations ran with
``--multi-frame``, ``landings``, ``landings_perfect_nav``, ``provenance``). Prose
outside the markers is left alone: read the new numbers and update it by hand.

Usage: ``.venv/bin/python bench/results.py OUT [--results docs/RESULTS.md]`` with OUT holding
``eval_vertical/``, ``eval_approach/``, ``landings/`` (and optionally ``landings_perfect_nav/``).
"""

from __future__ import annotations

import argparse
import json
import re
import shutil
from pathlib import Path

from _cli import InputError, out_path, run

ROOT = Path(__file__).resolve().parents[1]
FIGURES = {"vertical": (50, 300), "approach": (125, 300)}


def _block(text: str, name: str, body: str) -> str:
    pat = re.compile(rf"(<!-- BEGIN {name} -->\n).*?(<!-- END {name} -->)", re.S)
    if not pat.search(text):
        raise SystemExit(f"RESULTS.md has no <!-- BEGIN {name} --> ... <!-- END {name} --> block")
    return pat.sub(lambda m: m.group(1) + body.rstrip("\n") + "\n" + m.group(2), text)


def _seeds(metrics_csv: Path) -> tuple[str, list[int], str]:
    import csv

    with metrics_csv.open() as fh:
        rows = list(csv.DictReader(fh))
    seeds = sorted({int(r["seed"]) for r in rows})
    return rows[0].get("seed_set", "?"), seeds, rows[0].get("scene", "?")


def _landings_md(doc: dict) -> str:
    camp = doc["campaign"]
    seeds = doc.get("seeds_used") or camp["seeds"]
    nav = (
        f"navigation errors per frame `{camp['pose_error']}`."
        if camp["pose_error"]
        else "perfect navigation knowledge (no pose errors)."
    )
    lines = [
        f"{camp['n_landings']} landings per preset ({camp['n_renders']} renders × {camp['per_render']} aim points) "
        f"over {', '.join(camp['scenes'])}; {camp['seed_set']} seeds {min(seeds)}-{max(seeds)}; " + nav,
        "",
        "| preset | P(safe landing) | 95 % Wilson interval | P(no site) | P(unsafe site) | P(aim point safe) | "
        "divert p50 / p90 m |",
        "|---|---:|---|---:|---:|---:|---|",
    ]
    for p, st in doc["per_preset"].items():
        lo, hi = st["p_safe_ci95"]
        d = st["divert_m"]
        lines.append(
            f"| {p} | **{st['p_safe']:.3f}** | {lo:.3f}-{hi:.3f} | {st['p_no_site']:.3f} | {st['p_unsafe']:.3f} | "
            f"{st['p_aim_safe']:.3f} | {_f(d['p50'])} / {_f(d['p90'])} |"
        )
    lines += ["", "| scene | preset | n | P(safe) [95 % CI] | P(no site) | P(unsafe site) | P(aim point safe) |"]
    lines.append("|---|---|---:|---|---:|---:|---:|")
    for s, per in doc["per_scene"].items():
        for p, st in per.items():
            lo, hi = st["p_safe_ci95"]
            lines.append(
                f"| {s} | {p} | {st['n']} | {st['p_safe']:.3f} [{lo:.3f}, {hi:.3f}] | {st['p_no_site']:.3f} | "
                f"{st['p_unsafe']:.3f} | {st['p_aim_safe']:.3f} |"
            )
    return "\n".join(lines) + "\n"


def _f(v: float | None) -> str:
    return "-" if v is None else f"{v:.1f}"


def check_inputs(out: Path, results: Path) -> None:
    """Refuse, before anything is copied or written, what would stop this script part way: no directory ``out``,
    a file it reads missing (those of an optional part present included), a block ``results`` lacks."""
    if not out.is_dir():
        raise InputError(f"{out}: no such directory (the `evaluate` and `landings` output directories' parent)")
    need, blocks = [results], ["vertical", "approach", "landings", "provenance"]
    for scen in ("vertical", "approach"):
        rep = out / f"eval_{scen}" / "report"
        need += [rep / f"tables_{scen}.md", out / f"eval_{scen}" / "metrics.csv"]
        if (rep / f"multiframe_{scen}.md").is_file():
            need.append(rep / f"{scen}_multiframe.png")
            blocks.append("multiframe")
    lp, pn = out / "landings", out / "landings_perfect_nav"
    need += [
        lp / "landings.json",
        *(lp / "report" / f for f in ("p_safe_by_scene.png", "outcomes.png", "divert_cdf.png")),
    ]
    if (pn / "landings.json").is_file():
        need.append(pn / "report" / "p_safe_by_scene.png")
        blocks.append("landings_perfect_nav")
    missing = [str(f) for f in need if not f.is_file()]
    if missing:
        raise InputError(f"missing {', '.join(missing)}")
    text = results.read_text()
    lacking = [
        b for b in dict.fromkeys(blocks) if not re.search(rf"<!-- BEGIN {b} -->\n.*?<!-- END {b} -->", text, re.S)
    ]
    if lacking:
        raise InputError(f"{results} has no <!-- BEGIN name --> ... <!-- END name --> block for {', '.join(lacking)}")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("out", type=Path)
    ap.add_argument("--results", type=out_path, default=ROOT / "docs" / "RESULTS.md")
    ap.add_argument("--wall", default="", help="free text on the wall times, put in the provenance block")
    args = ap.parse_args()
    check_inputs(args.out, args.results)
    dest = args.results.parent / "results"
    dest.mkdir(parents=True, exist_ok=True)
    text = args.results.read_text()
    prov = []
    for scen in ("vertical", "approach"):
        src = args.out / f"eval_{scen}"
        rep = src / "report"
        tables = (rep / f"tables_{scen}.md").read_text()
        shutil.copy(rep / f"tables_{scen}.md", dest / f"tables_{scen}.md")
        shutil.copy(src / "metrics.csv", dest / f"metrics_{scen}.csv")
        for f in [rep / f"{scen}_detection.png"] + [
            rep / f"{scen}_{a}m_{k}.png" for a in FIGURES[scen] for k in ("dem", "hazard", "slope", "rough")
        ]:
            if f.is_file():
                shutil.copy(f, dest / f.name)
        seed_set, seeds, scene = _seeds(src / "metrics.csv")
        prov.append(f"- {scen}: scene `{scene}`, {seed_set} seeds {', '.join(map(str, seeds))}")
        text = _block(text, scen, tables)
    mf = []
    for scen in ("vertical", "approach"):
        rep = args.out / f"eval_{scen}" / "report"
        if (rep / f"multiframe_{scen}.md").is_file():
            shutil.copy(rep / f"{scen}_multiframe.png", dest / f"{scen}_multiframe.png")
            mf.append(f"**{scen}**\n\n" + (rep / f"multiframe_{scen}.md").read_text())
            alt = f"{scen}: per descent, best pair against the multi-frame policies"
            mf.append(f"![{alt}](results/{scen}_multiframe.png)\n")
    if mf:
        text = _block(text, "multiframe", "\n".join(mf))
    lp = args.out / "landings"
    doc = json.loads((lp / "landings.json").read_text())
    for f in ("p_safe_by_scene.png", "outcomes.png", "divert_cdf.png"):
        shutil.copy(lp / "report" / f, dest / f"landings_{f}")
    shutil.copy(lp / "landings.json", dest / "landings.json")
    text = _block(text, "landings", _landings_md(doc))
    pn = args.out / "landings_perfect_nav"
    if (pn / "landings.json").is_file():
        doc = json.loads((pn / "landings.json").read_text())
        shutil.copy(pn / "landings.json", dest / "landings_perfect_nav.json")
        shutil.copy(pn / "report" / "p_safe_by_scene.png", dest / "landings_perfect_nav_p_safe_by_scene.png")
        text = _block(text, "landings_perfect_nav", _landings_md(doc))
    if args.wall:
        prov.append(f"- wall times: {args.wall}")
    text = _block(text, "provenance", "\n".join(prov) + "\n")
    args.results.write_text(text)
    print(f"updated {args.results} and {dest}")


if __name__ == "__main__":
    run(main)
