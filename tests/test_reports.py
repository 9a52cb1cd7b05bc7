"""The shared report kit: pages render every label once with its explanation, figures load in a real browser."""

import os

import numpy as np
import pytest
from browser import check_page, chromium_path
from hypothesis import given, settings
from hypothesis import strategies as st

from reports import plots
from reports.html import Column, Figure, Headline, Section, Table, fmt_value, render_page, write_page
from reports.style import GLOSSARY


@pytest.fixture(autouse=True)
def _close_figures():
    """Figures a test inspects and does not save stay open: past 20 matplotlib warned of the memory held."""
    yield
    plots._plt().close("all")


def _page(tmp_path, broken: bool = False):
    rng = np.random.default_rng(0)
    img = rng.integers(0, 255, (64, 64), dtype=np.uint8)
    truth_safe = rng.random((64, 64)) > 0.3
    called_safe = truth_safe ^ (rng.random((64, 64)) > 0.9)
    covered = np.ones((64, 64), bool)
    covered[:, :8] = False
    state = np.where(called_safe, 0, 1).astype(np.uint8)
    state[20:30, 20:30] = 2
    state[~covered] = 255
    fig = plots.map_figure(
        [
            plots.Panel("image", img, "i1"),
            plots.Panel("state", state, "hazard states", sites=[plots.Site(40, 40, 5, 1, True)]),
            plots.Panel("confusion", plots.confusion_codes(called_safe, truth_safe, covered), "scores"),
            plots.Panel("scalar", rng.normal(size=(64, 64)), "elevation", "m", "terrain"),
        ]
    )
    plots.save(fig, tmp_path / "maps.png")
    recs = [
        {
            "label": "600/300",
            "frames_link_s": 0.2,
            "stages": {"sweep": {"wall_s": 0.3}, "hazard": {"wall_s": 0.1}},
            "result_link_s": 0.05,
            "e2e_latency_s": 0.45,
            "deadline_s": 2.0,
            "deadline_met": True,
            "cpu_fraction": 0.3,
            "peak_rss_mib": 150.0,
        },
        {"label": "300/150", "status": "error"},
    ]
    plots.save(plots.timeline_figure(recs), tmp_path / "timeline.png")
    plots.save(plots.latency_figure(recs), tmp_path / "latency.png")
    plots.save(plots.resources_figure(recs, 0.35, 256), tmp_path / "resources.png")
    figs = [
        Figure("maps.png", "maps"),
        Figure("timeline.png", "timeline"),
        Figure("latency.png", "latency"),
        Figure("resources.png", "resources"),
    ]
    if broken:
        (tmp_path / "gone.png").write_bytes(b"not a png")
        figs.append(Figure("gone.png", "broken on purpose"))
    table = Table(
        [Column("label", "pair"), Column("fp_pct"), Column("cdi_pct")],
        [{"label": "600/300", "fp_pct": 0.41, "cdi_pct": 81.234}],
    )
    return write_page(
        tmp_path / "report.html",
        "test report",
        [Section("maps", ["text"], [table], figs)],
        headline=[Headline("fp_pct", 0.41, "ok")],
    )


def test_page_labels_are_unique_and_explained(tmp_path):
    html = _page(tmp_path).read_text()
    assert html.count(GLOSSARY["fp_pct"].label) >= 2  # header and glossary
    assert GLOSSARY["cdi_pct"].explanation in html
    labels = [t.label for t in GLOSSARY.values()]
    assert len(labels) == len(set(labels)) and len({lab.replace(" ", "") for lab in labels}) == len(labels)
    assert "81.2" in html and "**" not in html


def test_missing_figure_is_refused(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"nothere\.png"):
        write_page(tmp_path / "r.html", "t", [Section("s", figures=[Figure("nothere.png", "x")])])


def test_values_are_formatted_for_people():
    assert fmt_value(None) == "–" and fmt_value(float("nan")) == "–"
    assert fmt_value(0.000179) == "<0.001" and fmt_value(-0.000012) == ">-0.001" and fmt_value(0.0) == "0"
    assert fmt_value(81.2345) == "81.2" and fmt_value(2.5e6) == "2.50e+06" and fmt_value(True) == "yes"
    assert "<script>" not in render_page("<script>", [Section("x")])


# make test installs chromium and sets HAZARD_HIL_REQUIRE_BROWSER, so a missing browser fails there, not skips
needs_browser = pytest.mark.skipif(
    chromium_path() is None and not os.environ.get("HAZARD_HIL_REQUIRE_BROWSER"),
    reason="chromium not installed (make test installs it)",
)


@needs_browser
def test_report_opens_in_a_real_browser(tmp_path):
    good = check_page(_page(tmp_path))
    assert good.ok, good
    assert good.images == 4 and good.title == "test report"
    bad = check_page(_page(tmp_path / "b", broken=True))
    assert not bad.ok and bad.broken_images == ["gone.png"]


def test_the_timeline_draws_the_stages_in_the_order_they_ran():
    """The ground's JSON lines sort keys, so ``stages`` reads alphabetically; the record's ``stage_order`` is the
    order the flight listed them in (pose refinement drew after the output before). A stage only some pairs ran
    keeps its place in the sequence."""
    from reports.plots import stage_sequence

    assert stage_sequence([["pose_refine", "coarse_dem", "hazard", "total", "output"]]) == [
        "pose_refine",
        "coarse_dem",
        "hazard",
        "output",
    ]
    image_only = ["validate", "pose_refine", "coarse_dem", "hazard", "fusion", "output"]
    full = ["validate", "pose_refine", "coarse_dem", "full_dem", "slope", "hazard", "fusion", "output"]
    assert stage_sequence([image_only, full]) == full
    assert stage_sequence([]) == []
    rec = {
        "label": "1000/500",
        "stages": {k: {"wall_s": 1.0} for k in sorted(full)},  # as read back from the JSON lines
        "stage_order": full,
        "deadline_s": 60.0,
    }
    fig = plots.timeline_figure([rec])
    ax = fig.axes[0]
    starts = {c.get_label(): c.patches[0].get_x() for c in ax.containers if c.get_label() in full}
    assert sorted(starts, key=starts.get) == full
    # with the flight's plan: when it aimed to be done, and when its DEM had to stop to leave the mapping's reserve
    rec |= {"queue_wait_s": 0.5, "plan": {"budget_s": 58.0, "coarse_dem_need_s": 44.0, "full_dem_need_s": 40.0}}
    ax = plots.timeline_figure([rec]).axes[0]
    marks = {ln.get_label(): ln.get_xdata()[0] for ln in ax.lines if ln.get_label().startswith("plan:")}
    assert marks == {"plan: done by": 58.5, "plan: DEM stop-by (then the mapping's reserve)": 18.5}


def test_a_stage_keeps_its_colour_whatever_else_ran():
    """Colours were handed out by position among the stages present: brown was `full_dem` in a full run's timeline
    and `georef` in a degraded one's. A DEM stop-by before the frames were in was drawn left of 0."""
    full = list(plots.KNOWN_STAGES)
    degraded = [k for k in full if k not in ("pose_refine", "coarse_dem", "full_dem")]

    def colours(order, plan=None):
        rec = {"label": "p", "stages": {k: {"wall_s": 0.1} for k in order}, "stage_order": order, "deadline_s": 9.0}
        ax = plots.timeline_figure([rec | ({"plan": plan} if plan else {})]).axes[0]
        return {c.get_label(): c.patches[0].get_facecolor() for c in ax.containers if c.get_label() in order}, ax

    a, _ = colours(full)
    b, _ = colours(degraded + ["my_stage"])
    assert all(a[k] == b[k] for k in degraded)
    assert len(set(a.values())) == len(full)  # each stage its own colour
    assert b["my_stage"] not in [a[k] for k in degraded]  # a stage of one's own takes one no known stage shown has
    _, ax = colours(degraded, {"budget_s": 1.0, "coarse_dem_need_s": 3.8})
    assert [ln.get_label() for ln in ax.lines if ln.get_label().startswith("plan:")] == ["plan: done by"]


def test_the_maps_colours_keep_their_meaning():
    """Elevation ended in white, the colour of "no elevation"; P(safe) put red, the undetected hazard's colour, on
    ground correctly called unsafe."""
    from matplotlib.colors import to_rgb

    from reports.style import ELEVATION_CMAP, MISSED, OUTSIDE, PSAFE_CMAP

    def far(a, b) -> float:
        return float(np.abs(np.subtract(a[:3], to_rgb(b))).max())

    ramp = np.linspace(0.0, 1.0, 101)
    assert min(far(c, OUTSIDE) for c in plots.colormap(ELEVATION_CMAP)(ramp)) > 0.25
    assert min(far(c, MISSED) for c in plots.colormap(PSAFE_CMAP)(ramp)) > 0.3
    assert plots.colormap("viridis").name == "viridis"  # any other name is matplotlib's


def test_maps_that_cover_a_quarter_of_the_frame_are_shown_zoomed_to_it():
    """A 300/150 pair's maps cover the middle quarter of the upper image; drawn whole, three quarters of every
    panel was white."""
    state = np.full((100, 100), 255, np.uint8)
    state[25:75, 30:70] = 0
    img = np.zeros((100, 100), np.uint8)
    panels = [plots.Panel("image", img, "i1"), plots.Panel("state", state, "states")]
    assert plots.mapped_box(panels) == (21, 78, 26, 73)  # padded by 4 % of the side
    fig = plots.map_figure(panels, "t")
    for ax in fig.axes[:2]:  # the image too, so the two read side by side
        assert ax.get_xlim() == (25.5, 73.5) and ax.get_ylim() == (78.5, 20.5)
    assert "zoomed to the mapped area" in fig._suptitle.get_text()
    # a score's confusion panel shows the scored pixels, whatever the detector mapped beyond them
    conf = np.where(state == 0, 0, 255).astype(np.uint8)
    fig = plots.map_figure([plots.Panel("image", img, "i1"), plots.Panel("confusion", conf, "scores")], "t")
    assert "zoomed to the scored area" in fig._suptitle.get_text()
    assert plots.mapped_box([plots.Panel("state", np.zeros((100, 100), np.uint8), "all mapped")]) is None
    # scalars: where every panel is finite (a truth panel is finite everywhere, the computed one where it mapped)
    dem = np.full((100, 100), np.nan)
    dem[40:60, 40:60] = 1.0
    truth = np.ones((100, 100))
    assert plots.mapped_box([plots.Panel("scalar", dem, "dem"), plots.Panel("scalar", truth, "truth")]) == (
        36, 63, 36, 63
    )  # fmt: skip
    assert plots.map_figure(panels, zoom=False).axes[1].get_xlim() == (-0.5, 99.5)


def test_a_long_uplink_does_not_take_the_timeline():
    """6 s of frames at 921600 baud against ~1 s of compute took 70 % of the axis."""
    recs = [
        {"label": "600/300", "frames_link_s": 6.0, "stages": {"sweep": {"wall_s": 0.8}}, "result_link_s": 0.2,
         "e2e_latency_s": 1.1, "deadline_s": 2.0, "result_queue_s": 0.001},
    ]  # fmt: skip
    fig = plots.timeline_figure(recs)
    ax = fig.axes[0]
    assert ax.get_xlim()[0] == pytest.approx(-1.02)
    assert any(t.get_text().strip().startswith("frames 6.0 s") for t in ax.texts)
    labels = ax.get_legend_handles_labels()[1]
    assert "result queued behind earlier messages" not in labels  # a millisecond is no cause
    plots.timeline_figure([{"label": "x", "status": "error"}])  # no Result: no cut, no error (review)


def test_a_page_links_the_data_files_beside_it_that_exist(tmp_path):
    from reports.html import file_links

    (tmp_path / "summary.json").write_text("{}")
    links = file_links(tmp_path, [("summary.json", "the figures"), ("gone.csv", "never written")])
    assert links == [("summary.json", "the figures")]
    page = render_page("t", [Section("Files", links=links)])
    assert '<li><a href="summary.json">summary.json</a>: the figures</li>' in page and "gone.csv" not in page


def test_scale_bar_is_a_round_length_of_the_panels_ground():
    """A scale bar of 1, 2 or 5 x 10^k m, at most a fifth of the panel's width in metres."""
    assert [plots.scale_bar_m(w) for w in (3.0, 10.0, 100.0, 160.5, 999.0, 0.7)] == [0.5, 2, 20, 20, 100, 0.1]
    with pytest.raises(ValueError):
        plots.scale_bar_m(float("nan"))
    # a ground 0.5 m per pixel along u (and 0.8 along v, which a horizontal bar does not measure), one hole
    v, u = np.mgrid[0:40, 0:60].astype(np.float64)
    xy = np.stack([0.5 * u, 0.8 * v], axis=-1)
    xy[3, 3] = np.nan
    assert plots.ground_step_m(xy) == pytest.approx(0.5)
    assert plots.ground_step_m(np.full((4, 4, 2), np.nan)) is None
    state = np.zeros((60, 60), np.uint8)
    fig = plots.map_figure([plots.Panel("image", state, "i1"), plots.Panel("state", state, "s")], m_per_px=0.5)
    # 60 px x 0.5 m = 30 m wide: a 5 m bar, 10 px long, on both panels of the maps' frame
    bars = [a for ax in fig.axes for a in ax.artists if type(a).__name__ == "AnchoredSizeBar"]
    assert len(bars) == 2
    texts = {t.get_text() for b in bars for t in b.findobj(lambda o: hasattr(o, "get_text"))}
    assert texts == {"5 m"}, texts
    assert [b.size_bar.get_children()[0].get_width() for b in bars] == [10.0, 10.0]  # 5 m at 0.5 m per px
    assert not [a for ax in plots.map_figure([plots.Panel("state", state, "s")]).axes for a in ax.artists]


def test_the_zoomed_box_keeps_every_site_in_view():
    """A score figure zoomed to the mapped area left out the sites outside it, the top one included."""
    from reports.plots import Panel, Site, mapped_box

    codes = np.full((200, 200), 255, np.uint8)
    codes[80:120, 80:120] = 0
    inside = mapped_box([Panel("confusion", codes, "")])
    far = Site(10.0, 190.0, 2.0, 1, True)
    box = mapped_box([Panel("confusion", codes, "", sites=[far])])
    assert inside is not None and inside[2] > 10 and box is not None
    assert box[0] <= 190 <= box[1] and box[2] <= 10 <= box[3]


def test_the_error_maps_and_series_colours_are_not_red():
    """QA 61a: the DEM error map's RdBu put red on the positive errors, red being only an undetected hazard."""
    from hilkit import reddish
    from matplotlib.colors import to_rgb

    from reports.style import ERROR_CMAP, MISSED, SERIES_COLOURS

    assert reddish(to_rgb(MISSED)) and reddish(to_rgb("#d62728"))  # the check sees matplotlib's red
    ramp = np.linspace(0.0, 1.0, 101)
    assert not [c for c in plots.colormap(ERROR_CMAP)(ramp) if reddish(c)]
    assert not [c for c in SERIES_COLOURS if reddish(to_rgb(c))]


def test_a_long_descents_pair_labels_are_thinned_to_stay_legible():
    """At 32 pairs the per-pair labels ran into one band, at 200 a smear (stop 63's soak QA): every pair keeps its
    tick, and at most PAIR_TICKS_MAX of them a label."""
    recs = [
        {"label": f"r{i}-300/150", "e2e_latency_s": 0.5, "deadline_s": 2.0, "deadline_met": True, "cpu_fraction": 0.3}
        for i in range(200)
    ]
    for fig in (plots.latency_figure(recs), plots.resources_figure(recs, 0.35, 256)):
        for ax in fig.axes:
            said = [t.get_text() for t in ax.get_xticklabels() if t.get_text()]
            assert len(ax.get_xticks()) == 200 and 0 < len(said) <= plots.PAIR_TICKS_MAX and said[0] == "r0-300/150"
    short = plots.latency_figure(recs[:8])
    assert [t.get_text() for t in short.axes[0].get_xticklabels()] == [r["label"] for r in recs[:8]]


def test_the_latency_picture_names_what_it_draws_and_each_pairs_latency():
    """Its title said "(x: no result)" over a run with a result for every pair, the bars' colours were unnamed, and a
    0.07 s pair under a 2 s deadline was a sliver with no figure (QA of stop 78)."""
    met = {"label": "600/300", "e2e_latency_s": 0.07, "deadline_s": 2.0, "deadline_met": True}

    def said(recs: list[dict]) -> tuple[list[str], list[str]]:
        ax = plots.latency_figure(recs).axes[0]
        return [t.get_text() for t in ax.get_legend().get_texts()], [t.get_text() for t in ax.texts]

    assert said([met, dict(met, label="300/150")]) == (["deadline", "met"], ["0.07 s", "0.07 s"])
    late = dict(met, label="200/100", e2e_latency_s=2.4, deadline_met=False)
    legend, values = said([met, {"label": "300/150", "status": "error"}, late])
    assert legend == ["deadline", "met", "late", "no result"] and values == ["0.07 s", "2.4 s"]
    assert "no result" not in plots.latency_figure([met]).axes[0].get_title()


def test_a_picture_stopped_mid_write_leaves_the_one_before_whole(tmp_path):
    """`savefig` wrote onto the final name: a stop inside it left a truncated PNG there (review of stop 63)."""
    from reports.plots import _plt, save

    plt = _plt()
    path = tmp_path / "dem.png"
    save(plt.figure(figsize=(2, 2)), path)
    before = path.read_bytes()
    assert before.startswith(b"\x89PNG")
    fig = plt.figure(figsize=(3, 3))

    def half_then_stop(target, **kw):
        target.write(before[: len(before) // 2])
        raise KeyboardInterrupt

    fig.savefig = half_then_stop
    with pytest.raises(KeyboardInterrupt):
        save(fig, path)
    assert path.read_bytes() == before and [p.name for p in tmp_path.iterdir()] == ["dem.png"]


def test_a_pages_markdown_code_spans_are_code_and_its_text_stays_escaped(tmp_path):
    """The notes shared with summary.md are Markdown: the pages showed `hazard-hil score` with its backticks."""
    from reports.html import Section, write_page

    page = write_page(
        tmp_path / "p.html", "t", sections=[Section("s", paragraphs=["run `hazard-hil score` <now> & `--full-maps`"])]
    )
    text = page.read_text()
    assert "run <code>hazard-hil score</code> &lt;now&gt; &amp; <code>--full-maps</code>" in text and "`" not in text


def test_hazard_scores_are_drawn_without_the_undetected_hazards_red_or_the_false_alarms_orange():
    """magma_r put red and orange on hazard scores of 0.4-0.8, against the rule that red only ever means an
    undetected hazard (QA 64b)."""
    from reports.plots import colormap
    from reports.style import HAZARD_CMAP

    rgb = colormap(HAZARD_CMAP)(np.linspace(0.0, 1.0, 256))[:, :3]
    r, g, b = rgb.T
    assert not ((r > 0.55) & (g < 0.6) & (b < 0.45)).any()  # no red, orange or brown anywhere on the scale
    assert (np.diff(rgb.sum(axis=1)) <= 1e-9).all()  # pale to dark: a higher score never reads lighter


def test_a_memory_ceiling_far_above_the_peak_is_said_not_drawn_flat():
    """The run report's memory chart scaled its axis to a 2048 MiB ceiling, and the 74 MiB line lay on the floor."""
    from reports.plots import _plt, resources_figure

    recs = [{"label": f"p{i}", "cpu_fraction": 0.3, "peak_rss_mib": 70.0 + i} for i in range(3)]
    far = resources_figure(recs, 0.276, 2048.0).axes[1]
    assert far.get_ylim()[1] < 100.0 and "2048 MiB, is 28x the peak: off the scale" in far.get_title()
    near = resources_figure(recs, 0.276, 256.0).axes[1]
    assert near.get_ylim()[1] >= 256.0 and near.get_title() == "memory against the ceiling"
    _plt().close("all")


def test_a_dollar_in_a_label_is_text_not_math(tmp_path):
    """A pair named m$^$x crashed `process` with a mathtext traceback before its pictures, and "cost $5 or $6" was
    drawn as "cost 5or6" (QA of stop 66). Titles carry people's labels: never math."""
    from reports.plots import _plt, save

    plt = _plt()
    for title in ("m$^$x", "cost $5 or $6"):
        fig, ax = plt.subplots()
        t = fig.suptitle(title)
        ax.set_title(title)
        save(fig, tmp_path / "t.png")
        assert t.get_text() == title and not t._preprocess_math(title)[1]  # drawn as given, not as math


def test_figure_and_file_paths_are_urls_on_the_page(tmp_path):
    """A pair labelled "600/300 #1?" named a figure the browser looked for as "600/300 " with a fragment: a broken
    image (QA of stop 66). Paths on the page are percent-encoded; the text shown stays as named."""
    from reports.html import Figure, Section, write_page

    (tmp_path / "figures").mkdir()
    (tmp_path / "figures" / "p000-600_300 #1?_hazard.png").write_bytes(b"png")
    (tmp_path / "a #1.csv").write_text("x")
    page = write_page(
        tmp_path / "report.html",
        "t",
        [Section("s", figures=[Figure("figures/p000-600_300 #1?_hazard.png", "c")], links=[("a #1.csv", "data")])],
    )
    text = page.read_text()
    assert 'src="figures/p000-600_300%20%231%3F_hazard.png"' in text and 'href="a%20%231.csv"' in text
    assert ">a #1.csv</a>" in text


def test_a_label_cannot_break_the_run_summary_table():
    """summary.md took labels as they were: a '|' added a cell and shifted the columns, '*' and '`' turned into
    formatting and '<b>' passed as HTML (QA of stop 66)."""
    from hil_server.run import summary_table

    rec = {"status": "error", "label": "300|150 *x* `y` <b>", "altitude_m": 300.0, "code": "link_down",
           "text": "a | b"}  # fmt: skip
    nan = float("nan")
    s = {"records": [rec], "scenario": "vertical", "link": "zmq", "flight": "emulated", "budget": "host",
         "results": 0, "pairs": 1, "degraded": 0, "errors": 1, "e2e_latency_p50_s": nan, "e2e_latency_max_s": nan,
         "flight_latency_p50_s": nan, "deadline_hit_rate": 0.0}  # fmt: skip
    text = summary_table(s)
    row = next(line for line in text.splitlines() if line.startswith("| 300"))
    cells = row.replace("\\|", "\x00").split("|")[1:-1]  # an escaped bar is not a cell boundary
    assert len(cells) == 12, cells
    assert r"300\|150 \*x\* \`y\` &lt;b>" in row and "error: link_down (below)" in row, row
    # the reason below the table, by its pair: it sat in the deadline column (QA of stop 73)
    assert cells[7].strip() == "—" and r"- **300\|150 \*x\* \`y\` &lt;b>**: a \| b" in text, text


def test_a_markdown_cell_escapes_markup_only():
    """A memory ceiling's "36.6 MiB > 36 MiB" read "36.6 MiB &gt; 36 MiB" in summary.md and on the console (QA of
    stop 73): only a "<" or "&" that would start a tag, a comment or an entity is written as one."""
    from reports.console import md_cell

    assert md_cell("private RSS 36.6 MiB > 36 MiB, P <0.001, A & B") == "private RSS 36.6 MiB > 36 MiB, P <0.001, A & B"
    assert (
        md_cell("<script>x</script> <!-- c --> &amp; &#60;")
        == "&lt;script>x&lt;/script> &lt;!-- c --> &amp;amp; &amp;#60;"
    )


@settings(max_examples=300, deadline=None)
@given(text=st.text(alphabet=st.sampled_from(list("ab |*`[]~\\<>&#;/!?_")), max_size=40))
def test_the_console_shows_a_markdown_cell_as_written_but_its_column_bars(text):
    """The console printed summary.md's escapes ("(\\`hazard-hil flight\\`, ...)"; QA of stop 84): undone there, a
    cell reads as its text, with only "|" still escaped to keep the table's columns."""
    from reports.console import md_cell, md_console, printable

    assert md_console(md_cell(text)) == printable(text).replace("|", "\\|")


@settings(max_examples=300, deadline=None)
@given(
    limit=st.floats(0.001, 100.0),
    offset=st.floats(-0.02, 0.02),
    digits=st.integers(0, 3),
)
def test_a_number_beside_its_limit_is_shown_on_its_own_side(limit, offset, digits):
    """A pose fallback read "attitude correction 2.00 deg > 2": the value shown must compare with the limit shown
    as the true ones do, so a value just past a limit gets the decimals that show it."""
    from reports.console import apart, past

    value = limit + offset
    side = (value > limit) - (value < limit)
    shown, limit_shown = apart(value, limit, digits)
    assert (float(shown) > float(limit_shown)) - (float(shown) < float(limit_shown)) == side, (shown, limit_shown)
    exact = past(value, limit, digits)
    assert (float(exact) > limit) - (float(exact) < limit) == side, exact
    assert len(exact.partition(".")[2]) >= digits  # never fewer decimals than asked
    assert past(2.004, 2.0) == "2.004" and past(2.5, 2.0) == "2.50" and apart(0.748, 0.746) == ("0.748", "0.746")


def test_evaluates_pixel_score_figure_is_over_the_true_overlap_as_its_table(tmp_path, monkeypatch):
    """The figure's pixel scores were over the map's own pixels while metrics.csv was over the true overlap: TN 42.4 %
    against 42.08 for one pair (QA of stop 66). The maps now carry the scored area and the figure counts over it."""
    from reports import plots
    from studies.report import figures_from_maps

    seen = []
    real = plots.confusion_codes
    monkeypatch.setattr(plots, "confusion_codes", lambda a, b, s: seen.append(s.copy()) or real(a, b, s))
    h = w = 40
    scored = np.zeros((h, w), bool)
    scored[5:35, 5:35] = True
    covered = np.zeros((h, w), bool)
    covered[8:32, 8:32] = True  # the map covers less than the true overlap
    est = np.where(covered, 0.2, np.nan).astype(np.float32)
    z = np.zeros((h, w), np.float32)
    np.savez_compressed(
        tmp_path / "m.npz", image=np.full((h, w), 100, np.uint8), m_per_px=np.float64(1.0), est_elevation=z,
        true_elevation=z, est_hazard=est, true_hazard=np.zeros((h, w), np.float32), est_slope=z,
        true_slope=np.full((h, w), np.nan, np.float32), est_rough=z, true_rough=z, covered=covered, scored=scored,
        epipole_box=np.zeros((h, w), bool), rocks=np.zeros((h, w), bool), est_shadow=np.zeros((h, w), bool),
        true_shadow=np.zeros((h, w), bool),
    )  # fmt: skip
    figures_from_maps(tmp_path / "m.npz", tmp_path, "p")
    assert len(seen) == 1 and seen[0].sum() == scored.sum()  # 900 scored pixels, not the map's 576


def test_a_flight_side_that_reports_no_memory_is_said_so_not_drawn_as_zero(tmp_path):
    """A flight side of one's own may report its CPU fraction and not its memory: the chart said neither until stop
    71, and our own board reports its memory since stop 72 (tests/test_board.py), so this branch is held here."""
    import html

    from hil_server.run_report import write_run_report

    records = [
        {"status": "result", "label": f"{a}/{a // 2}", "pair_id": str(a), "altitude_m": float(a), "level": "full",
         "deadline_met": True, "deadline_s": 2.0, "e2e_latency_s": 0.5, "cpu_fraction": 0.9, "peak_rss_mib": rss}
        for a, rss in ((600, None), (300, float("nan")))
    ]  # fmt: skip
    summary = {"records": records, "pairs": 2, "results": 2, "deadline_met": 2}
    page = html.unescape(write_run_report(summary, tmp_path / "report.html").read_text())
    assert "and its peak private RSS: not reported." in page
    records[1]["peak_rss_mib"] = 81.5
    page = html.unescape(write_run_report(summary, tmp_path / "report.html").read_text())
    assert "and its peak private RSS as it reported it." in page and "not reported" not in page


def test_a_scalar_panel_says_when_it_has_nothing_and_marks_its_clip_and_its_turn(tmp_path):
    """Image-only results drew blank DEM panels under colour bars; a crater floor 6 m below the scale read as its
    lowest colour; and the P(safe) panel was green from 0.5, "mostly safe" on a pair that called 0.4 % safe (QA of
    stop 72)."""
    from reports.plots import Panel, dem_panels, map_figure

    empty = np.full((32, 32), np.nan)
    truth = np.linspace(-5.0, 5.0, 32 * 32).reshape(32, 32)
    fig = map_figure(dem_panels(empty, truth))
    texts = [t.get_text() for ax in fig.axes for t in ax.texts]
    assert any(t.startswith("no computed elevation") for t in texts) and any("no error to show" in t for t in texts)
    assert len(fig.axes) == 4  # three panels and one colour bar: none for the empty ones
    bar = fig.axes[-1]
    assert bar.get_ylim() is not None and fig.axes[1].images[0].colorbar.extend == "both"  # 2nd-98th pct: both clip
    ps = np.linspace(0.0, 1.0, 32 * 32).reshape(32, 32)
    fig = map_figure([Panel("scalar", ps, "P(safe)", "probability", "hh-psafe", 0.0, 1.0, centre=0.99,
                            centre_label="floor 0.99")])  # fmt: skip
    im = fig.axes[0].images[0]
    cb = im.colorbar
    assert "floor 0.99" in [t.get_text() for t in cb.ax.get_yticklabels()]
    # green (the scale's top colour) only above the floor: 0.9 sits below the turn, 0.995 above it
    assert im.norm(0.9) < 0.5 < im.norm(0.995)


def test_a_page_keys_only_the_colours_it_draws(tmp_path):
    """The hazard states' colour key sat atop every run, evaluate and sensitivity page, none of which draws a state
    map (QA of stop 72)."""
    from studies.report import write_html

    page = write_html(tmp_path / "sens", "sensitivity", [("sensitivity: altitude", "| a |\n|---|\n| 1 |", [])])
    text = page.read_text()
    assert "hazard states" not in text and "pixel scores" not in text
    (tmp_path / "ev").mkdir()
    plots.save(plots.map_figure([plots.Panel("image", np.zeros((8, 8)), "i1")]), tmp_path / "ev" / "m.png")
    page = write_html(
        tmp_path / "ev", "evaluate", [("vertical: maps, preset fast", "", ["m.png"])], legends=("confusion",)
    )
    text = page.read_text()
    assert "pixel scores" in text and "hazard states" not in text


def test_the_timeline_names_what_shows_and_leaves_out_a_plan_before_the_frames():
    """A ZeroMQ pair's 0.1 ms on the link and a stage of no time were named in the legend though nothing showed, and
    a plan "done by" at -0.92 s sat off the axis with its legend entry (QA of stop 72)."""
    recs = [
        {"label": "600/300", "frames_link_s": 0.0001, "e2e_latency_s": 1.2, "deadline_s": 2.0, "queue_wait_s": 0.0,
         "stages": {"sweep": {"wall_s": 0.9}, "georef": {"wall_s": 0.0002}}, "stage_order": ["sweep", "georef"],
         "result_link_s": 0.2, "plan": {"budget_s": -0.92}},
        {"label": "300/150", "frames_link_s": 0.0001, "e2e_latency_s": 1.0, "deadline_s": 2.0, "queue_wait_s": 0.0,
         "stages": {"sweep": {"wall_s": 0.5}, "georef": {"wall_s": 0.3}}, "stage_order": ["sweep", "georef"],
         "result_link_s": 0.2},
    ]  # fmt: skip
    names = plots.timeline_figure(recs).axes[0].get_legend_handles_labels()[1]
    assert "frames on the link" not in names and "plan: done by" not in names
    # georef took no time in the first pair and 0.3 s in the second: named, by the pair where it shows
    assert {"sweep", "georef", "result on the link", "deadline"} <= set(names), names


def test_a_section_can_put_its_pictures_above_its_tables(tmp_path):
    """The evaluation page showed ~20 tables before its first picture (QA of stop 72): its sections lead with the
    plot of their tables."""
    plots.save(plots.map_figure([plots.Panel("image", np.zeros((8, 8)), "i1")]), tmp_path / "p.png")
    table = Table([Column("fp_pct")], [{"fp_pct": 0.5}])
    for first in (True, False):
        text = render_page("t", [Section("s", tables=[table], figures=[Figure("p.png", "c")], figures_first=first)])
        assert (text.index("<figure>") < text.index("<table>")) == first


def test_an_empty_error_panel_names_the_side_that_is_empty():
    """A truth of NaN drew an error panel saying "no computed elevation where the truth is", though the computed
    elevation was there (QA of stop 73)."""
    from reports.plots import dem_panels

    z = np.zeros((8, 8), np.float32)
    nan = np.full((8, 8), np.nan, np.float32)
    assert "the truth holds no elevation" in dem_panels(z, nan)[2].empty_text
    assert "no computed elevation where the truth is" in dem_panels(nan, z)[2].empty_text


def test_the_dem_colour_range_is_the_truth_where_the_dem_is():
    """A deep crater outside the mapped ground stretched the shared range to -44..-3 m while the DEM spanned
    -12..-4 m, and the computed elevation came out one flat colour (QA of stop 85)."""
    from reports.plots import dem_panels

    crater = np.full((64, 16), -44.0, np.float32)  # which the DEM does not reach
    truth = np.hstack([crater, np.tile(np.linspace(-12.0, -4.0, 48, dtype=np.float32), (64, 1))])
    estimate = truth + 0.1
    estimate[:, :16] = np.nan
    computed, true, _ = dem_panels(estimate, truth)
    assert computed.vmin is not None and computed.vmax is not None
    assert -12.0 <= computed.vmin < -11.0 and -5.0 < computed.vmax <= -4.0
    assert (true.vmin, true.vmax) == (computed.vmin, computed.vmax)
    # with no computed elevation at all, the truth's own range
    assert dem_panels(np.full_like(truth, np.nan), truth)[0].vmin == -44.0


def test_a_ticker_speaks_only_while_long_work_runs():
    """`process` on a large pair ran for a minute or more without a word: a line every so often, none for short
    work, and none after the work ended."""
    import io
    import time

    from reports.progress import Ticker

    quick = io.StringIO()
    with Ticker("process: working", stream=quick):
        pass
    assert quick.getvalue() == ""
    slow = io.StringIO()
    with Ticker("process: working", stream=slow, first_s=0.05, every_s=0.05) as t:
        time.sleep(0.5)
    said = slow.getvalue()
    time.sleep(0.15)
    assert slow.getvalue() == said and t.lines >= 2  # stopped with the work
    assert said.splitlines()[0].startswith("process: working: ") and said.splitlines()[0].endswith(" s so far")
    # a Ctrl-C in the work stops it too, and the ticker can time the next piece of work
    stopped = io.StringIO()
    ticker = Ticker("process: writing", stream=stopped, first_s=0.05, every_s=0.05)
    with pytest.raises(KeyboardInterrupt), ticker:
        time.sleep(0.2)
        raise KeyboardInterrupt
    n = stopped.getvalue().count("\n")
    with ticker:
        time.sleep(0.2)
    time.sleep(0.15)
    assert n >= 1 and stopped.getvalue().count("\n") > n and ticker.lines == stopped.getvalue().count("\n")
    said = stopped.getvalue()
    time.sleep(0.15)
    assert stopped.getvalue() == said
    # a second phase counts from the first one's start: two phases just under first_s each are not silent
    began = time.monotonic() - 0.3
    late = io.StringIO()
    with Ticker("process: writing", stream=late, first_s=0.4, every_s=10.0, since=began):
        time.sleep(0.3)
    assert late.getvalue().startswith("process: writing: 0 s so far") or late.getvalue().startswith(
        "process: writing: 1 s so far"
    ), late.getvalue()
    off = io.StringIO()
    with Ticker("process: working", stream=off, enabled=False, first_s=0.01, every_s=0.01):
        time.sleep(0.1)
    assert off.getvalue() == ""


def test_the_true_hazard_is_drawn_as_its_two_classes():
    """On the continuous scale, safe ground at 0.7-0.9 looked as dark as a hazard at 1.0 beside the scores that
    called it safe (QA round 2 of stop 78): the truth is drawn safe or unsafe, keyed with their shares, no unknown."""
    truth = np.array([[0.0, 0.8, 0.99], [1.0, 2.0, np.nan]], np.float32)
    p = plots.truth_panel(truth)
    assert p.kind == "truth" and p.data.tolist() == [[0, 0, 0], [1, 1, 255]]
    fig = plots.map_figure([p])
    labels = [t.get_text() for t in fig.axes[0].get_legend().get_texts()]
    assert labels == ["safe 60.0 %", "unsafe 40.0 %"], labels
    # beside the pixel scores, over the pixels they score: the whole frame's 23.5 % unsafe sat beside scores whose
    # hazards were 29.2 % (QA of stop 84); here the truth's unsafe share is the scores' TN + FP
    scored = np.array([[True, True, False], [True, True, False]])
    called = np.array([[True, False, True], [False, True, True]])
    codes = plots.confusion_codes(called, np.nan_to_num(truth, nan=1.0) < 1.0, scored)
    fig = plots.map_figure([plots.Panel("confusion", codes, "scores"), plots.truth_panel(truth, scored=scored)])
    conf, true = ([t.get_text() for t in ax.get_legend().get_texts()] for ax in fig.axes[:2])
    assert true == ["safe 50.0 %", "unsafe 50.0 %"], true
    shares = {t.split(":")[0]: float(t.split()[-2]) for t in conf}
    assert shares["TN"] + shares["FP"] == 50.0, conf


def test_a_timeline_whose_work_is_a_sliver_of_the_deadline_zooms_to_the_work():
    """A host run's pairs took 0.08 s of a 2 s deadline: every bar a sliver at the left and most stages unnamed (QA
    round 2 of stop 78). The axis ends a quarter past the longest pair, the deadline said at its end."""
    order = ["pose_refine", "coarse_dem", "full_dem", "slope", "hazard", "output"]
    recs = [
        {"label": p, "e2e_latency_s": 0.08, "deadline_s": 2.0, "result_link_s": 0.01, "stage_order": order,
         "stages": {k: {"wall_s": 0.01} for k in order}}
        for p in ("600/300", "300/150")
    ]  # fmt: skip
    ax = plots.timeline_figure(recs).axes[0]
    assert ax.get_xlim()[1] == pytest.approx(0.1)
    assert set(order) <= set(ax.get_legend_handles_labels()[1])  # every stage drawn is named
    assert [t.get_text() for t in ax.texts].count("deadline 2 s \u2192") == 2 and "deadline, 2 s, is off" in (
        ax.get_xlabel()
    )
    recs[0]["e2e_latency_s"] = 1.2  # a pair that took most of its deadline: the deadline is on the axis again
    ax = plots.timeline_figure(recs).axes[0]
    assert ax.get_xlim()[1] > 2.0 and "deadline" in ax.get_legend_handles_labels()[1]


def test_site_labels_of_nearby_clusters_do_not_overprint():
    """Labels "1,2,3" and "4,5" of two clusters 9 px apart printed over each other as "1,4,3,5", and rank 2 was
    lost (QA of stop 85). Every label is now clear of the others and every rank is written."""
    state = np.zeros((170, 170), np.uint8)
    sites = [plots.Site(124.0, 100.0 + k, 2.0, k + 1, True) for k in range(3)]
    sites += [plots.Site(133.0, 100.0 + k, 2.0, k + 4, False) for k in range(2)]
    sites += [plots.Site(126.0, 92.0, 2.0, 6, True)]  # a third cluster, above the first label
    fig = plots.map_figure([plots.Panel("state", state, "hazard states", sites=sites)])
    from matplotlib.text import Text

    r = fig.canvas.get_renderer()
    labels = [t for t in fig.axes[0].texts if t.get_text()[:1].isdigit()]
    boxes = [Text.get_window_extent(t, r) for t in labels]
    assert not any(a.overlaps(b) for i, a in enumerate(boxes) for b in boxes[i + 1 :])
    assert sorted(int(k) for t in labels for k in t.get_text().split(",")) == [1, 2, 3, 4, 5, 6]
    # a moved label keeps a line to its circle; the top site's stays in its place
    assert all(t.arrow_patch.get_visible() == (tuple(t.xyann) != plots.LABEL_OFFSETS[0]) for t in labels)
    assert tuple(labels[0].xyann) == plots.LABEL_OFFSETS[0]


def test_each_share_legend_says_what_its_shares_are_of():
    """A hazard-state legend over the mapped pixels read "safe 10.8 %" beside pixel scores over the scored ones
    whose TP + FP was 9.9 % (QA of stop 85): each legend now names its area, and the shares are of that area."""
    state = np.full((40, 40), 255, np.uint8)
    state[:, :30] = 0  # mapped: 30 columns, all safe
    scored = np.zeros((40, 40), bool)
    scored[:, 10:30] = True
    conf = plots.confusion_codes(np.ones((40, 40), bool), np.ones((40, 40), bool), scored)
    panels = [
        plots.Panel("state", state, "hazard state"),
        plots.Panel("confusion", conf, "pixel scores"),
        plots.truth_panel(np.zeros((40, 40), np.float32), scored=scored),
    ]
    fig = plots.map_figure(panels, zoom=False)
    titles = [ax.get_legend().get_title().get_text() for ax in fig.axes[:3]]
    assert titles == ["share of the mapped area", "share of the scored area", "share of the scored area"]
    assert "safe 100.0 %" in [t.get_text() for t in fig.axes[0].get_legend().get_texts()]
    assert plots.truth_panel(np.zeros((4, 4), np.float32)).share_of == "area with truth"
