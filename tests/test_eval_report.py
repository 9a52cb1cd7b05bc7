"""Thesis reference values, side-by-side tables and the HTML report, on synthetic metric rows."""

from __future__ import annotations

import math
import re
from pathlib import Path

import cv2
import numpy as np
import pytest
from browser import browser_available, check_page

from reports import plots
from studies import evaluate as ev
from studies import report


def test_thesis_csv_spot_values_and_derived_rates():
    vals = ev.load_thesis()
    idx = ev.thesis_index(vals)
    assert idx[("6.2", "vertical", 500, "dem_mean_abs_m")] == 3.8769
    assert idx[("6.9", "approach", 125, "dem_mean_abs_m")] == 0.72354
    assert idx[("6.11", "approach", 150, "fp_pct")] == 0.75
    assert idx[("6.19", "approach", 300, "dev+0.05.dem_mean_rel_pct")] == 20.06
    assert idx[("6.12", "approach", 125, "s20.h2_m")] == 125.2749
    assert {v.table for v in vals} == {f"6.{k}" for k in range(1, 20)}
    # TN%/TP%/CDI derived from Table 6.4 with the formulas that reproduce Table 6.7's own columns
    for a in (300, 400, 500):
        tp, tn, fp, fn = (idx[("6.7", "vertical", a, m)] for m in ("tp_pct", "tn_pct", "fp_pct", "fn_pct"))
        assert 100 * tp / (tp + fn) == pytest.approx(idx[("6.7", "vertical", a, "safe_detected_pct")], abs=0.02)
        assert 100 * tn / (tn + fp) == pytest.approx(idx[("6.7", "vertical", a, "hazards_detected_pct")], abs=0.02)
    assert idx[("Fig. 6.6", "vertical", 500, "cdi_pct")] == pytest.approx(63.06 + 19.98)
    # the sensitivity tables' relative errors are relative to Table 6.9 (perfect knowledge)
    mu, rel = (
        idx[("6.12", "approach", 125, "s01.dem_mean_abs_m")],
        idx[("6.12", "approach", 125, "s01.dem_mean_rel_pct")],
    )
    assert mu / (1 + rel / 100) == pytest.approx(idx[("6.9", "approach", 125, "dem_mean_abs_m")], rel=1e-3)


def _rows():
    rows = []
    for preset, k in (("fast", 0.5), ("thesis", 1.0)):
        for alt in (300, 500):
            for seed in (0, 1):
                r = {c: None for c in ev.METRIC_COLUMNS}
                r.update(
                    scenario="vertical",
                    altitude_m=alt,
                    label=f"{2 * alt}/{alt}",
                    preset=preset,
                    seed=seed,
                    pair="x",
                    dem_mean_abs_m=k * alt / 100 + seed,
                    fp_pct=k,
                    fn_pct=10.0,
                    tp_pct=60.0,
                    tn_pct=30.0 - k,
                    cdi_pct=90.0 - k,
                    hazards_detected_pct=90.0,
                    safe_detected_pct=85.0,
                    pipeline_s=0.5,
                    level="full",
                    degraded=False,
                )
                rows.append(r)
    return rows


def test_summary_is_median_over_seeds_and_comparison_pairs_thesis_cells():
    s = ev.summarise(_rows())
    assert s[("vertical", "fast", 300)]["dem_mean_abs_m"] == pytest.approx(2.0)  # median of 1.5, 2.5
    fps = [r["fp_pct"] for r in _rows() if (r["scenario"], r["preset"], r["altitude_m"]) == ("vertical", "fast", 300)]
    assert s[("vertical", "fast", 300)]["fp_pct_worst"] == max(fps)  # the worst seed beside the median
    assert s[("vertical", "fast", 300)]["dem_mean_abs_m_worst"] == pytest.approx(2.5)  # and the DEM's
    cells = ev.comparison(s, "vertical")
    c = next(c for c in cells if c["metric"] == "dem_mean_abs_m" and c["altitude_m"] == 500)
    assert c["thesis"] == 3.8769 and c["ours_fast"] == pytest.approx(3.0) and c["ours_thesis"] == pytest.approx(5.5)
    md = report.comparison_markdown(cells)
    assert re.search(r"\| 500 \| 3.88 \| 3.00 \| [\d.]+ \| 5.50 \| [\d.]+ \|", md), md  # each beside its worst seed
    for block in md.split("\n\n"):  # every row of every table has as many cells as its header
        rows = [ln for ln in block.splitlines() if ln.startswith("|")]
        assert len({ln.count("|") - ln.count("\\|") for ln in rows}) <= 1, block  # escaped pipes are text


def test_the_chosen_sites_share_says_how_many_seeds_offered_a_site():
    """A seed without a site has no share of clear sites: the median is over the others, and their count goes
    beside it (the vertical 100 m thesis row was 3 of 5 seeds, read as 5; QA of stop 75)."""
    rows = _rows()
    for r, v in zip(rows, (100.0, math.nan, 50.0, None), strict=False):
        r["chosen_sites_safe_pct"] = v
    s = ev.summarise(rows)[("vertical", "fast", 300)]
    assert s["chosen_sites_seeds"] == 1 and s["chosen_sites_safe_pct"] == 100.0 and s["n_seeds"] == 2
    assert ev.summarise(rows)[("vertical", "fast", 500)]["chosen_sites_seeds"] == 1
    md = report.comparison_markdown(ev.comparison(ev.summarise(rows), "vertical"))
    assert re.search(r"\| 300 \| 100 \| [^|]+ \| 100 \| [^|]+ \| 1 \| ", md), md  # a count, not "1.00"


def test_metrics_csv_roundtrip(tmp_path: Path):
    rows = _rows()
    rows[0]["cdi_pct"] = float("nan")
    p = ev.write_metrics_csv(rows, tmp_path / "metrics.csv")
    header = p.read_text().splitlines()[0].split(",")
    assert header[: len(ev.METRIC_COLUMNS)] == list(ev.METRIC_COLUMNS)
    back = ev.read_metrics_csv(p)
    assert back[1]["dem_mean_abs_m"] == pytest.approx(rows[1]["dem_mean_abs_m"])
    assert back[0]["cdi_pct"] is None and back[0]["altitude_m"] == 300 and back[0]["scenario"] == "vertical"


def test_confusion_codes_follow_positive_is_safe():
    est = np.array([[0.0, 1.0, 0.0, 1.0, np.nan]])
    tru = np.array([[0.0, 1.0, 1.0, 0.0, 0.0]])
    codes = plots.confusion_codes(est < 1, tru < 1, np.array([[1, 1, 1, 1, 0]], bool))
    assert codes.tolist() == [[0, 1, 2, 3, 255]]  # TP, TN, FP (undetected hazard), FN, outside


def test_html_report_from_synthetic_rows_and_maps(tmp_path: Path):
    rng = np.random.default_rng(1)
    h = w = 64
    truth = rng.normal(0, 1, (h, w)).astype(np.float32)
    cov = np.zeros((h, w), bool)
    cov[16:48, 16:48] = True
    maps = tmp_path / "maps"
    maps.mkdir()
    for alt in (300, 500):
        np.savez_compressed(
            maps / f"vertical-fast-s0-{alt}.npz",
            image=(rng.random((h, w)) * 255).astype(np.uint8),
            est_elevation=truth + 0.1,
            true_elevation=truth,
            est_hazard=np.clip(truth, 0, 1),
            true_hazard=np.clip(truth + 0.2, 0, 1),
            est_slope=np.abs(truth) * 5,
            true_slope=np.abs(truth) * 6,
            est_rough=np.abs(truth) * 0.1,
            true_rough=np.abs(truth) * 0.1,
            covered=cov,
            epipole_box=np.zeros((h, w), bool),
            rocks=np.zeros((h, w), bool),
        )
    page = report.evaluation_report(tmp_path, _rows())
    text = page.read_text()
    pngs = sorted(p.name for p in page.parent.glob("*.png"))
    assert "vertical_detection.png" in pngs and "vertical_500m_dem.png" in pngs and len(pngs) == 9
    for name in pngs:
        assert f'src="{name}"' in text
        assert cv2.imread(str(page.parent / name)) is not None
    assert "3.88" in text and "<table>" in text
    # labels from the glossary: unique, explained, no Markdown left on the page
    assert "FP % (undetected hazard): thesis" in text and "DEM error excess kurtosis" in text and "**" not in text
    assert "kurtosis*" not in text and "TN% excl" not in text
    assert "_worst" not in text  # the worst-seed metrics have glossary labels too
    if browser_available():
        check = check_page(page)
        assert check.ok and check.images == 9, check
    assert math.isclose(ev.summarise(_rows())[("vertical", "thesis", 500)]["fp_pct"], 1.0)


def test_the_detection_chart_names_its_curves_as_the_page_does(tmp_path, monkeypatch):
    """Its curves were labelled "TN%" and "TP%", which the page's tables use for shares of all pixels: the chart
    showed ~100 % and ~10 % beside a CDI of ~42 % defined as TP % + TN %."""
    seen = []
    monkeypatch.setattr(report, "save_figure", lambda fig, path: seen.append(fig) or Path(path))
    summary = {("vertical", "fast", a): {"hazards_detected_pct": 99.0, "safe_detected_pct": 10.0, "cdi_pct": 42.0,
                                         "fp_pct": 0.1} for a in (300, 400)}  # fmt: skip
    report.plot_vs_altitude(summary, "vertical", ev.thesis_index(ev.load_thesis()), tmp_path / "d.png")
    labels = [t.get_text() for t in seen[0].axes[0].get_legend().get_texts()]
    assert "hazards detected % ours-fast" in labels and "safe recognised % ours-fast" in labels, labels
    assert not any(x.startswith(("TN%", "TP%")) for x in labels), labels
    red = [ln.get_label() for ln in seen[0].axes[0].get_lines() if ln.get_color() in ("tab:red", "#d62728")]
    assert red == []  # red is only an undetected hazard


def test_a_split_table_says_which_part_and_no_site_is_not_a_dash():
    """Three tables were captioned "Table 6.2" alike, and "-" meant both "the thesis has no value" and "no site
    was offered"."""
    cells = [
        {"table": "6.2", "metric": m, "altitude_m": 300, "thesis": 1.0, "ours_fast": 0.5}
        for m in ("dem_mean_abs_m", "dem_median_m", "dem_mad_m", "slope_mean_abs_deg")
    ] + [
        {"table": "-", "metric": "chosen_sites_safe_pct", "altitude_m": a, "thesis": None, "ours_fast": None}
        for a in (300, 400)
    ]
    tables = report.comparison_tables(cells)
    assert [t.caption for t in tables] == ["Table 6.2 (1 of 2)", "Table 6.2 (2 of 2)", "Not in the thesis"]
    rows = {r["altitude_m"]: r for r in tables[-1].rows}
    assert rows[300]["chosen_sites_safe_pct|fast"] == "no site"
    assert rows[400]["chosen_sites_safe_pct|fast"] is None  # nothing ran there: no site is not the answer


def test_the_multiframe_chart_draws_no_policy_in_red(tmp_path):
    """QA 61a: matplotlib's colour cycle drew "fused window 2", the fourth series, in red (the undetected hazard's)."""
    from hilkit import reddish
    from matplotlib.image import imread

    from studies import multiframe as mf

    names = ["best pair", *mf.POLICIES]
    per_descent = [
        {"scenario": "vertical", "seed": s, "rows": {n: {"cdi": 40.0 + k, "fp": 0.5 + 0.1 * k} for k, n in
                                                      enumerate(names)}}
        for s in (1000, 1001)
    ]  # fmt: skip
    png = imread(report.plot_multiframe(per_descent, mf.POLICIES, tmp_path / "m.png"))
    red = sum(reddish(px) for px in png.reshape(-1, png.shape[-1])[::3])
    assert red == 0, red


def test_the_kurtosis_is_called_excess_and_set_beside_no_thesis_value_with_the_reason_in_the_caption():
    """The glossary said "3 for a normal distribution" of an excess kurtosis (0 for one), and Table 6.3 set the
    thesis's "kurtosis" (its skewness minus 3) beside ours with no note, which RESULTS.md says are not comparable
    (QA 65b M2)."""
    from reports.style import term

    assert (
        "0 for a normal distribution" in term("dem_kurtosis").explanation
        and "3 for a normal" not in term("dem_kurtosis").explanation
    )
    assert "excess" in term("dem_kurtosis").label
    cells = ev.comparison(ev.summarise(_rows()), "vertical")
    assert all(c["thesis"] is None for c in cells if c["metric"] == "dem_kurtosis")
    (t63,) = [t for t in report.comparison_tables(cells) if t.caption.startswith("Table 6.3")]
    keys = [c.key for c in t63.columns]
    assert "dem_skewness|reference" in keys and "dem_kurtosis|reference" not in keys and "dem_kurtosis|fast" in keys
    assert "not comparable" in t63.caption
    md = report.comparison_markdown(cells)
    (block,) = [b for b in md.split("\n\n") if b.startswith("**Table 6.3")]
    assert "not comparable" in block.splitlines()[0] and "kurtosis: thesis" not in block


def test_the_sensitivity_tables_on_the_page_read_as_labels_not_metric_keys():
    """The report page's sensitivity tables showed raw keys (median_rel_pct, rel_pct@+0.15, ...; stop 66's note)."""
    from reports.style import term

    row = {
        "kind": "attitude",
        "preset": "fast",
        "altitude_m": 300,
        "n": 4,
        "n_no_dem": 0,
        "median_rel_pct": 12.0,
        "max_rel_pct": 30.0,
        "within_15pct": 50.0,
        "detrended_median_rel_pct": 5.0,
        "detrended_max_rel_pct": 9.0,
        "rel_pct@+0.15": 30.0,
        "thesis_median_rel_pct": 100.0,
        "thesis_rel_pct@-0.05": 40.0,
    }
    (t,) = report.markdown_tables(report.rows_markdown([row], list(row)))
    labels = [c.label or term(c.glossary_key).label for c in t.columns]
    assert not [lb for lb in labels if "_" in lb or "@" in lb], labels
    assert "pitch +0.15°, DEM error increase %" in labels and "thesis: pitch -0.05°, DEM error increase %" in labels
    assert t.rows[0]["rel_pct@+0.15"] == "30.0"  # the cells stay keyed by the column
    # a header that is already a label stays itself
    (t2,) = report.markdown_tables("| FP % worst seed: ours (fast) | policy |\n|---:|---|\n| 0.5 | x |\n")
    assert [c.label or term(c.glossary_key).label for c in t2.columns] == ["FP % worst seed: ours (fast)", "policy"]


def test_the_evaluation_page_heads_with_each_presets_worst_fp_marked_against_one_percent():
    """The page put ~20 tables before any figure and flagged the thesis preset's 8.67 % FP nowhere (QA of stop 72)."""
    from studies.report import preset_cards

    rows = [
        {"preset": "fast", "fp_pct": 0.2, "cdi_pct": 55.0},
        {"preset": "fast", "fp_pct": 0.6, "cdi_pct": 65.0},
        {"preset": "thesis", "fp_pct": 8.67, "cdi_pct": 40.0},
        {"preset": "thesis", "fp_pct": None, "cdi_pct": float("nan")},
    ]
    cards = {c.label: c for c in preset_cards(rows)}
    assert cards["worst FP %, fast"].value == 0.6 and cards["worst FP %, fast"].status == "ok"
    assert cards["worst FP %, thesis"].value == 8.67 and cards["worst FP %, thesis"].status == "bad"
    assert cards["median CDI %, fast"].value == 60.0 and cards["median CDI %, thesis"].value == 40.0


def test_the_worst_seed_stands_beside_the_median_in_the_thesis_tables():
    """Table 6.4's FP and CDI and Table 6.2's DEM error were medians alone; their worst seed stood some 60 lines
    below, in "Not in the thesis" (QA of stop 73; the brief: the worst case beside the median)."""
    cells = ev.comparison(ev.summarise(_rows()), "vertical")
    tables = report.comparison_tables(cells)
    t64 = next(t for t in tables if t.caption.startswith("Table 6.4"))
    keys = [c.key for c in t64.columns]
    assert keys.index("fp_pct_worst|fast") == keys.index("fp_pct|fast") + 1
    worst = {c["altitude_m"]: c["ours_fast"] for c in cells if c["metric"] == "fp_pct_worst"}
    assert worst and all(r["fp_pct_worst|fast"] == worst[r["altitude_m"]] for r in t64.rows)
    label = next(c.label for c in t64.columns if c.key == "fp_pct_worst|fast")
    assert label.endswith("ours (fast), worst seed")
    md = report.comparison_markdown(cells)
    assert "ours (fast), worst seed" in md
