"""The report page of an HIL run: the summary table, then per pair the pictures a person wants.

Per pair, from what actually came back over the link: i1 | computed hazard |
true hazard | confusion overlay (DESIGN.md: positive = safe), and the DEM
triptych (computed | truth | error) - the same panels as the evaluation
report (:mod:`reports.figures`). Everything is PNG next to ``report.html``.
"""

from __future__ import annotations

import html
from pathlib import Path

import numpy as np

from hil_server.run import summary_table
from reports.figures import hazard_figure, triptych, write_png


def _status(r: dict) -> str:
    if r.get("status") != "result":
        return f"error {r.get('code')}: {r.get('text')}"
    return (
        f"{r.get('level')}{' (degraded)' if r.get('degraded') else ''} · latency {r['latency_s']:.2f} s · "
        f"deadline {'met' if r.get('deadline_met') else 'MISSED'} · "
        f"result link {r['link'].get('result_link_s', 0):.2f} s"
    )


def write_run_report(summary: dict, path: Path) -> Path:
    from protocol.pairdir import read_pair

    path = Path(path)
    fig = path.parent / "figures"
    blocks = []
    for r in summary["records"]:
        pid = r["pair_id"]
        imgs = []
        out = Path(r.get("out_dir", ""))
        # the full-resolution map when the run asked for it, else the compact grid's call per pixel
        hz_file = next((out / n for n in ("hazard.npy", "called_i1.npy") if (out / n).is_file()), None)
        if r.get("status") == "result" and hz_file is not None:
            pair = read_pair(r["pair_dir"])
            hazard = np.load(hz_file)
            if "hazard" in pair.truth:
                imgs.append(
                    write_png(
                        fig / f"{pid}_hazard.png",
                        hazard_figure(pair.images[0], hazard, pair.truth["hazard"], ~np.isnan(hazard)),
                    )
                )
            if (out / "elevation.npy").is_file() and "elevation" in pair.truth:
                imgs.append(
                    write_png(
                        fig / f"{pid}_dem.png",
                        triptych(
                            np.load(out / "elevation.npy"),
                            pair.truth["elevation"],
                            ("computed DEM", "true DEM", "error"),
                            "m",
                        ),
                    )
                )
        pics = "".join(f'<img src="figures/{html.escape(p.name)}">' for p in imgs)
        blocks.append(f"<h3>{html.escape(str(r['label']))} — {html.escape(_status(r))}</h3><div>{pics}</div>")
    s = summary
    page = f"""<!doctype html><meta charset=utf-8><title>hazard-hil run</title>
<style>body{{font-family:sans-serif;margin:2em;max-width:1300px}} img{{display:block;margin:4px 0}}
pre{{background:#f4f4f4;padding:1em;overflow-x:auto}}</style>
<h1>HIL run: {html.escape(s["scenario"])} over {html.escape(s["link"])} on {html.escape(s["budget"])}</h1>
<p>Latency is "last frame in -> result out" at the HIL server; the result's own line time is listed separately.
Scores are per pixel of i1 against ground truth (positive = safe; FP = undetected hazard).</p>
<pre>{html.escape(summary_table(s))}</pre>
{"".join(blocks)}
"""
    path.write_text(page)
    return path
