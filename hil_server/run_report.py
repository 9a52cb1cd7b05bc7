"""The report page of an HIL run: the summary table, then per pair the picture a person wants.

Per pair: the upper image, the returned hazard map (green safe -> red unsafe,
grey where not covered) and, with ground truth, the confusion overlay
(DESIGN.md convention: positive = safe; FP = undetected hazard in red).
Everything is PNG next to ``report.html``; no external assets.
"""
from __future__ import annotations

import html
import math
from pathlib import Path

import cv2
import numpy as np

from hil_server.run import summary_table

# BGR colours of the confusion overlay
CONFUSION_BGR = {"tp": (80, 180, 60), "tn": (170, 170, 170), "fp": (40, 40, 230), "fn": (30, 200, 240)}


def hazard_picture(hazard: np.ndarray) -> np.ndarray:
    """Hazard in [0,1] -> BGR: green (0) to yellow to red (>= 1); NaN dark grey."""
    h = np.clip(np.nan_to_num(hazard, nan=0.0), 0.0, 1.0)
    bgr = np.empty(hazard.shape + (3,), np.uint8)
    bgr[..., 0] = 40
    bgr[..., 1] = (220 * np.clip(2.0 - 2.0 * h, 0, 1)).astype(np.uint8)
    bgr[..., 2] = (230 * np.clip(2.0 * h, 0, 1)).astype(np.uint8)
    bgr[hazard >= 1.0] = (30, 30, 200)
    bgr[np.isnan(hazard)] = (50, 50, 50)
    return bgr


def confusion_picture(hazard: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Per-pixel TP/TN/FP/FN colours (positive = safe); uncovered pixels black."""
    covered = ~np.isnan(hazard)
    est_safe = np.nan_to_num(hazard, nan=1.0) < 1.0
    true_safe = truth < 1.0
    out = np.zeros(hazard.shape + (3,), np.uint8)
    out[covered & est_safe & true_safe] = CONFUSION_BGR["tp"]
    out[covered & ~est_safe & ~true_safe] = CONFUSION_BGR["tn"]
    out[covered & est_safe & ~true_safe] = CONFUSION_BGR["fp"]
    out[covered & ~est_safe & true_safe] = CONFUSION_BGR["fn"]
    return out


def _save(path: Path, img: np.ndarray, size: int = 256) -> str:
    if img.shape[0] != size:
        img = cv2.resize(img, (size, size), interpolation=cv2.INTER_NEAREST)
    cv2.imwrite(str(path), img)
    return path.name


def write_run_report(summary: dict, path: Path) -> Path:
    from protocol.pairdir import read_pair

    path = Path(path)
    fig = path.parent / "figures"
    fig.mkdir(parents=True, exist_ok=True)
    blocks = []
    for r in summary["records"]:
        pid = r["pair_id"]
        cells = []
        try:
            pair = read_pair(r["pair_dir"])
        except Exception:  # the report must not die on one unreadable pair
            pair = None
        if pair is not None:
            cells.append(("upper image i1", _save(fig / f"{pid}_i1.png", pair.images[0])))
        hz = Path(r.get("out_dir", "")) / "hazard.npy"
        if r.get("status") == "result" and hz.is_file():
            hazard = np.load(hz)
            cells.append(("hazard map (flight)", _save(fig / f"{pid}_hazard.png", hazard_picture(hazard))))
            if pair is not None and "hazard" in pair.truth:
                cells.append(("truth hazard", _save(fig / f"{pid}_truth.png", hazard_picture(pair.truth["hazard"]))))
                cells.append(("confusion: TP green, TN grey, FP red, FN yellow",
                              _save(fig / f"{pid}_confusion.png", confusion_picture(hazard, pair.truth["hazard"]))))
        status = (f"{r.get('level')} · latency {r.get('latency_s', math.nan):.2f} s · deadline "
                  f"{'met' if r.get('deadline_met') else 'MISSED'}" if r.get("status") == "result"
                  else f"error {r.get('code')}: {r.get('text')}")
        imgs = "".join(f'<figure><img src="figures/{html.escape(src)}"><figcaption>{html.escape(cap)}</figcaption></figure>'
                       for cap, src in cells)
        blocks.append(f"<h3>{html.escape(str(r['label']))} — {html.escape(status)}</h3><div class=row>{imgs}</div>")
    table = summary_table(summary)
    page = f"""<!doctype html><meta charset=utf-8><title>hazard-hil run</title>
<style>body{{font-family:sans-serif;margin:2em;max-width:1200px}} .row{{display:flex;gap:8px;flex-wrap:wrap}}
figure{{margin:0}} figcaption{{font-size:12px;color:#555}} pre{{background:#f4f4f4;padding:1em;overflow-x:auto}}</style>
<h1>HIL run: {html.escape(summary['scenario'])} / {html.escape(summary['link'])} / {html.escape(summary['budget'])}</h1>
<pre>{html.escape(table)}</pre>
{''.join(blocks)}
"""
    path.write_text(page)
    return path
