"""Figures for people, drawn with matplotlib in the colours of :mod:`reports.style`.

Map figures are rows of panels: the input image, scalar layers with a colour
bar and unit, three-state maps and pixel-score (confusion) maps with a legend,
and landing sites drawn as footprint circles numbered by rank. Telemetry
figures show where each pair's time went and how the run sat against its
deadline and its processor budget.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from reports.style import (
    CONFUSION_COLOURS,
    CONFUSION_NAMES,
    ELEVATION_CMAP,
    ELEVATION_RANGE,
    ERROR_CMAP,
    ERROR_COLOURS,
    HAZARD_CMAP,
    HAZARD_COLOURS,
    MISSED,
    OUTSIDE,
    PSAFE_CMAP,
    PSAFE_COLOURS,
    SAFE,
    STATE_COLOURS,
    STATE_NAMES,
    UNKNOWN,
)


def _plt() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    # our titles carry people's labels and paths, never math: a '$' in a pair's name was read as mathtext, and a
    # '$^$' crashed `process` with a traceback before its pictures (QA of stop 66)
    matplotlib.rcParams["text.parse_math"] = False
    import matplotlib.pyplot as plt

    return plt


def save(fig: Any, path: str | Path, dpi: int = 100, **kw: Any) -> Path:
    """Write ``fig`` as a PNG (creating the folder) and release it. Rendered in memory, then written beside and
    renamed (:func:`reports.html.write_atomic`): a stop inside ``savefig`` left a truncated picture under its
    final name, listed as the run's (review of stop 63). ``kw`` goes to ``savefig`` (default: a tight box)."""
    import io

    from reports.html import write_atomic

    plt = _plt()
    buf = io.BytesIO()
    try:
        fig.savefig(buf, format="png", dpi=dpi, **({"bbox_inches": "tight"} | kw))
    finally:
        plt.close(fig)
    return write_atomic(path, buf.getvalue())


@dataclass
class Site:
    """A landing site in image pixels of the panel (u = column, v = row), its footprint radius in px."""

    u: float
    v: float
    radius_px: float
    rank: int
    safe: bool | None = None  # truly safe (when ground truth is known)


@dataclass
class Panel:
    """One map panel. ``kind``: ``image`` (gray), ``scalar`` (colour bar), ``state``, ``truth`` (safe or unsafe:
    :func:`truth_panel`) or ``confusion``."""

    kind: str
    data: np.ndarray
    title: str
    unit: str = ""
    cmap: str = "viridis"
    vmin: float | None = None
    vmax: float | None = None
    sites: list[Site] = field(default_factory=list)
    # scalar panels: pixels drawn grey (the unknown state) over the colour scale, with a legend entry - a
    # hazard score writes unknown as 1.0, which the colour scale alone cannot tell from a measured hazard
    unknown: np.ndarray | None = None
    # scalar panels: a value the colour scale turns at (TwoSlopeNorm), marked on the colour bar with its name: a
    # P(safe) panel green from 0.5 read as "mostly safe" on a pair that called 0.4 % safe (QA of stop 72)
    centre: float | None = None
    centre_label: str = ""
    empty_text: str = "no values here"  # said in a scalar panel with no finite value (not an empty box with a bar)
    # categorical panels: what the legend's shares are of (default by kind: a state map's mapped pixels, a
    # confusion map's scored ones); a hazard-state legend of the mapped area beside scores of the scored area
    # read as a disagreement (safe 10.8 % against TP + FP 9.9 %; QA of stop 85)
    share_of: str = ""


def confusion_codes(called_safe: np.ndarray, truly_safe: np.ndarray, covered: np.ndarray) -> np.ndarray:
    """Per pixel 0 TP, 1 TN, 2 FP, 3 FN, 255 outside (DESIGN.md: positive = safe)."""
    cs, ts = np.asarray(called_safe, bool), np.asarray(truly_safe, bool)
    out = np.full(cs.shape, 255, np.uint8)
    cov = np.asarray(covered, bool)
    out[cov & cs & ts] = 0
    out[cov & ~cs & ~ts] = 1
    out[cov & cs & ~ts] = 2
    out[cov & ~cs & ts] = 3
    return out


def truth_panel(
    true_hazard: np.ndarray,
    title: str = "true hazard where scored (unsafe: >= 1)",
    scored: np.ndarray | None = None,
) -> Panel:
    """The true hazard as its two classes (safe below 1, unsafe at 1; NaN outside), keyed with their shares. On the
    continuous scale, safe ground at 0.7-0.9 looked as dark as a hazard at 1.0 beside the scores that called it safe
    (QA round 2 of stop 78). ``scored``: the pixels the scores beside it count; the rest are left white, so the
    shares are over the same pixels (whole-frame shares read 23.5 % unsafe beside scores whose 29.2 % were; QA of
    stop 84)."""
    h = np.asarray(true_hazard, np.float32)
    if scored is not None:
        h = np.where(np.asarray(scored, bool), h, np.float32(np.nan))
    codes = np.where(np.isnan(h), np.uint8(255), np.where(h < 1.0, np.uint8(0), np.uint8(1))).astype(np.uint8)
    return Panel("truth", codes, title, share_of="scored area" if scored is not None else "area with truth")


_CONF_ORDER = ("TP", "TN", "FP", "FN")


SHARE_OF = {"state": "mapped area", "confusion": "scored area", "truth": "area with truth"}


def _categorical(
    ax: Any, codes: np.ndarray, colours: dict[int, str], names: dict[int, str], show_pct: bool, share_of: str = ""
) -> None:
    from matplotlib.colors import to_rgb
    from matplotlib.patches import Patch

    rgb = np.ones(codes.shape + (3,), np.float32)
    inside = codes != 255
    n_in = max(1, int(inside.sum()))
    handles = []
    for code, colour in colours.items():
        m = codes == code
        rgb[m] = to_rgb(colour)
        if code == 255:
            continue
        share = 100.0 * m.sum() / n_in
        # an FP of 0.01 % read "0.0 %" beside a table saying 0.01 (QA of stop 66): small shares keep two decimals
        pct = (f" {share:.1f} %" if share >= 1.0 or share == 0.0 else f" {share:.2f} %") if show_pct else ""
        handles.append(Patch(facecolor=colour, edgecolor="#555", label=f"{names[code]}{pct}"))
    ax.imshow(rgb, interpolation="nearest")
    # two columns of long labels ran under the next panel and into its legend (the run's state beside its scores)
    ncol = 1 if max((len(str(h.get_label())) for h in handles), default=0) > 24 else 2
    title = f"share of the {share_of}" if show_pct and share_of else None
    ax.legend(
        handles=handles,
        loc="upper center",
        bbox_to_anchor=(0.5, -0.02),
        fontsize=7,
        ncol=ncol,
        frameon=False,
        title=title,
        title_fontsize=7,
    )


def _unknown_overlay(ax: Any, mask: np.ndarray, n_in: int) -> None:
    """Grey the ``mask`` pixels over a scalar map and say so in a legend (with their share of the map)."""
    from matplotlib.colors import to_rgba
    from matplotlib.patches import Patch

    rgba = np.zeros(mask.shape + (4,), np.float32)
    rgba[mask] = to_rgba(UNKNOWN)
    ax.imshow(rgba, interpolation="nearest")
    pct = 100.0 * mask.sum() / max(1, n_in)
    label = f"unknown {pct:.1f} % (not enough evidence; scored as not safe)"
    handle = Patch(facecolor=UNKNOWN, edgecolor="#555", label=label)
    ax.legend(handles=[handle], loc="upper center", bbox_to_anchor=(0.5, -0.02), fontsize=7, frameon=False)


def _draw_sites(ax: Any, sites: Sequence[Site]) -> list[Any]:
    """Footprint circles numbered by rank, with a white halo so they read on dark and light maps alike.

    A footprint smaller than 1.5 % of the panel is drawn at that size (a 3 m circle at 600 m is ~2 px). Returns
    the labels in rank order, for :func:`_unclash_labels` once the figure's layout is final.
    """
    import matplotlib.patheffects as pe
    from matplotlib.patches import Circle

    halo: list[pe.AbstractPathEffect] = [pe.withStroke(linewidth=3.2, foreground="white")]
    x0, x1 = ax.get_xlim()
    floor = 0.015 * abs(x1 - x0)
    for s in sites:
        colour = "#000000" if s.safe is None else (SAFE if s.safe else MISSED)
        # the top-ranked site, the one a lander would take, drawn heavier than the others
        circle = Circle((s.u, s.v), max(s.radius_px, floor), fill=False, lw=2.8 if s.rank == 1 else 1.4, color=colour)
        circle.set_path_effects(halo)
        ax.add_patch(circle)
    labels = []
    for group in site_label_groups(sites, 3.0 * floor):
        s = group[0]  # the best-ranked site of the cluster carries the label
        colour = "#000000" if s.safe is None else (SAFE if s.safe else MISSED)
        label = ax.annotate(
            ",".join(str(g.rank) for g in group),
            (s.u, s.v),
            xytext=LABEL_OFFSETS[0],
            textcoords="offset points",
            fontsize=8,
            color=colour,
            weight="bold",
            path_effects=halo,
            arrowprops={"arrowstyle": "-", "lw": 0.7, "color": colour, "shrinkA": 0, "shrinkB": 0},
        )
        label.arrow_patch.set_visible(False)  # a leader only for a label moved off its place
        labels.append(label)
    return labels


# Where a site's label may go, in points from its centre: up-right first, then ever further above and below.
LABEL_OFFSETS = [(5.0, 5.0)] + [(5.0, 5.0 + sign * 11.0 * k) for k in range(1, 7) for sign in (-1, 1)]


def _unclash_labels(fig: Any, labels: Sequence[Any]) -> None:
    """Move each site label, best rank first, to the first place in :data:`LABEL_OFFSETS` where it overprints no
    label placed before it, with a leader line back to its circle.

    Labels of nearby clusters ("1,3" beside "2,4,5") overprinted into "1,:2,4,5" and lost a rank (stop 85's
    QA). Placed after the layout is final, since tight layout rescales the axes under labels set in points.
    """
    if not labels:
        return
    from matplotlib.text import Text

    r = fig.canvas.get_renderer()
    placed: list[Any] = []
    for label in labels:
        for dx, dy in LABEL_OFFSETS:
            label.xyann = (dx, dy)
            box = Text.get_window_extent(label, r)  # the text alone: an annotation's own extent holds its leader
            if not any(box.overlaps(b) for b in placed):
                break
        label.arrow_patch.set_visible(label.xyann != LABEL_OFFSETS[0])
        placed.append(box)


def site_label_groups(sites: Sequence[Site], min_sep: float) -> list[list[Site]]:
    """Sites whose labels would overprint (centres closer than ``min_sep`` px) share one label, "1,2,4".

    Drawn one label per site, a cluster showed only its worst rank on top of the others (five sites within a
    few pixels read as one site "5"). Groups are in rank order, each led by its best-ranked site.
    """
    groups: list[list[Site]] = []
    for s in sorted(sites, key=lambda t: t.rank):
        for g in groups:
            if (g[0].u - s.u) ** 2 + (g[0].v - s.v) ** 2 < min_sep**2:
                g.append(s)
                break
        else:
            groups.append([s])
    return groups


def colormap(name: str) -> Any:
    """A matplotlib colour map by name, the reports' own (``reports.style``: elevation, P(safe), error) included."""
    plt = _plt()
    from matplotlib.colors import LinearSegmentedColormap

    if name == ELEVATION_CMAP:
        return LinearSegmentedColormap.from_list(name, plt.get_cmap("terrain")(np.linspace(*ELEVATION_RANGE, 256)))
    if name == PSAFE_CMAP:
        return LinearSegmentedColormap.from_list(name, PSAFE_COLOURS)
    if name == ERROR_CMAP:
        return LinearSegmentedColormap.from_list(name, ERROR_COLOURS)
    if name == HAZARD_CMAP:
        return LinearSegmentedColormap.from_list(name, HAZARD_COLOURS)
    return plt.get_cmap(name)


ZOOM_BELOW = 0.8  # a map that covers less of its frame than this is shown zoomed to what it covers
ZOOM_PAD = 0.04  # of the frame's side, around the mapped box


def mapped_box(panels: Sequence[Panel]) -> tuple[int, int, int, int] | None:
    """``(row0, row1, col0, col1)`` around the pixels the maps cover, padded; None when they cover most of the frame.

    The maps of a pair cover only where both frames see the ground (a quarter of the upper image for a 300/150
    pair), and drawn whole they spent three quarters of each panel on white. What a map covers: the pixels not
    "outside" on its state and confusion panels, else the pixels finite on every scalar panel (a truth panel is
    finite everywhere; the computed one only where it mapped).
    """
    cats = [np.asarray(p.data) != 255 for p in panels if p.kind in ("state", "truth", "confusion")]
    scal = [np.isfinite(np.asarray(p.data, np.float64)) for p in panels if p.kind == "scalar"]
    masks = cats or scal
    if not masks or len({m.shape for m in masks}) != 1:
        return None
    mask = np.logical_or.reduce(masks) if cats else np.logical_and.reduce(masks)
    for s in [s for p in panels for s in p.sites]:  # a site outside the mapped area (the top one, too) was cut off
        u, v = int(round(s.u)), int(round(s.v))
        if 0 <= v < mask.shape[0] and 0 <= u < mask.shape[1]:
            mask[v, u] = True
    if not mask.any() or mask.mean() >= ZOOM_BELOW:
        return None
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    pad = int(round(ZOOM_PAD * max(mask.shape)))
    r0, r1 = max(0, int(rows[0]) - pad), min(mask.shape[0] - 1, int(rows[-1]) + pad)
    c0, c1 = max(0, int(cols[0]) - pad), min(mask.shape[1] - 1, int(cols[-1]) + pad)
    if (r1 - r0 + 1) * (c1 - c0 + 1) >= ZOOM_BELOW * mask.size:
        return None
    return r0, r1, c0, c1


def ground_step_m(world_xy: np.ndarray) -> float | None:
    """Median ground distance between horizontally neighbouring pixels, ``|(X, Y)[v, u+1] - (X, Y)[v, u]|``, of
    an (H, W, 2) map of each pixel's ground X, Y; None when no two neighbours have one. It is what a horizontal
    scale bar measures (on an oblique view it varies over the image, so the median stands for it)."""
    xy = np.asarray(world_xy, np.float64)
    if xy.ndim != 3 or xy.shape[2] < 2 or xy.shape[1] < 2:
        return None
    step = np.hypot(*(xy[:, 1:, :2] - xy[:, :-1, :2]).transpose(2, 0, 1))
    step = step[np.isfinite(step) & (step > 0)]
    return float(np.median(step)) if step.size else None


def scale_bar_m(visible_m: float) -> float:
    """A round length (1, 2 or 5 x 10^k m) no longer than a fifth of ``visible_m``, the panel's width in metres."""
    target = visible_m / 5.0
    if not (np.isfinite(target) and target > 0):
        raise ValueError(f"a scale bar needs a positive width in metres, got {visible_m!r}")
    unit = 10.0 ** np.floor(np.log10(target))
    return float(next(m * unit for m in (5.0, 2.0, 1.0) if m * unit <= target * (1 + 1e-9)))


def _scale_bar(ax: Any, m_per_px: float) -> None:
    """A bar of :func:`scale_bar_m` metres in the panel's lower left, on a dark backing that reads on any map."""
    from matplotlib.font_manager import FontProperties
    from mpl_toolkits.axes_grid1.anchored_artists import AnchoredSizeBar

    x0, x1 = ax.get_xlim()
    width_px = abs(x1 - x0)
    length = scale_bar_m(width_px * m_per_px)
    label = f"{length:g} m"
    bar = AnchoredSizeBar(
        ax.transData,
        length / m_per_px,
        label,
        "lower left",
        pad=0.25,
        borderpad=0.4,
        sep=2,
        color="white",
        frameon=True,
        size_vertical=0.012 * width_px,
        fontproperties=FontProperties(size=7),
    )
    bar.patch.set(facecolor="black", alpha=0.55, edgecolor="none")
    ax.add_artist(bar)


def map_figure(
    panels: Sequence[Panel],
    title: str = "",
    panel_in: float = 3.4,
    zoom: bool = True,
    m_per_px: float | None = None,
) -> Any:
    """A row of map panels; returns the matplotlib figure (see :func:`save`). With ``zoom`` every panel shows the
    box the maps cover (:func:`mapped_box`) when they cover little of the frame, and the title says so. With
    ``m_per_px`` (the ground sample distance of the maps' frame; its median for an oblique view) each panel of
    that frame gets a scale bar."""
    plt = _plt()
    n = len(panels)
    box = mapped_box(panels) if zoom else None
    shape = next((np.shape(p.data)[:2] for p in panels if p.kind != "image"), None)  # the maps' frame
    fig, axes = plt.subplots(1, n, figsize=(panel_in * n, panel_in * 1.25), squeeze=False)
    labels: list[Any] = []
    for ax, p in zip(axes[0], panels):
        ax.set_title(p.title, fontsize=9)
        ax.set_xticks([])
        ax.set_yticks([])
        if p.kind == "image":
            ax.imshow(p.data, cmap="gray", interpolation="nearest")
        elif p.kind == "scalar":
            d = np.asarray(p.data, np.float64)
            fin = d[np.isfinite(d)]
            vmin = p.vmin if p.vmin is not None else (float(np.percentile(fin, 2)) if fin.size else 0.0)
            vmax = p.vmax if p.vmax is not None else (float(np.percentile(fin, 98)) if fin.size else 1.0)
            cmap = colormap(p.cmap).with_extremes(bad=OUTSIDE)
            if not fin.size:  # an empty box under a colour bar read as a map of nothing in particular
                ax.imshow(np.ma.masked_invalid(d), cmap=cmap, vmin=vmin, vmax=vmax, interpolation="nearest")
                ax.text(0.5, 0.5, p.empty_text, ha="center", va="center", fontsize=8, color="#555555",
                        transform=ax.transAxes, wrap=True)  # fmt: skip
            else:
                _scalar(fig, ax, p, d, fin, cmap, vmin, vmax)
        elif p.kind in ("state", "truth"):  # the truth has no unknown: its key would read "unknown 0.0 %"
            keep = STATE_COLOURS if p.kind == "state" else {k: v for k, v in STATE_COLOURS.items() if k != 2}
            _categorical(ax, np.asarray(p.data, np.uint8), keep, STATE_NAMES, True, p.share_of or SHARE_OF[p.kind])
        elif p.kind == "confusion":
            names = {i: CONFUSION_NAMES[k] for i, k in enumerate(_CONF_ORDER)} | {255: "outside"}
            colours = {i: CONFUSION_COLOURS[k] for i, k in enumerate(_CONF_ORDER)} | {255: OUTSIDE}
            _categorical(ax, np.asarray(p.data, np.uint8), colours, names, True, p.share_of or SHARE_OF[p.kind])
        else:
            raise ValueError(f"unknown panel kind {p.kind!r}")
        if box is not None and np.shape(p.data)[:2] == shape:
            ax.set_xlim(box[2] - 0.5, box[3] + 0.5)
            ax.set_ylim(box[1] + 0.5, box[0] - 0.5)  # rows down, as the image
        labels += _draw_sites(ax, p.sites)
        if m_per_px is not None and np.isfinite(m_per_px) and m_per_px > 0 and np.shape(p.data)[:2] == shape:
            _scale_bar(ax, float(m_per_px))
    if box is not None:  # on a line of its own: after a long title it ran off the figure's edge
        # a score's confusion panel covers the scored pixels, which a detector may have mapped beyond
        area = "scored" if any(p.kind == "confusion" for p in panels) else "mapped"
        title = (
            title + "\n" if title else ""
        ) + f"(zoomed to the {area} area: rows {box[0]}-{box[1]}, columns {box[2]}-{box[3]})"
    if title:
        fig.suptitle(title, fontsize=11)
    sites = [s for p in panels for s in p.sites]
    if sites:  # the circles' colours and weights were explained nowhere
        key = "circles: landing sites, numbered by rank (the top one drawn heaviest)"
        if any(s.safe is not None for s in sites):
            # one wording for every page: `process` draws black for no truth, the runs for a footprint off frame 0
            key += "; green truly safe, red not, black not judged (no truth there, or its footprint leaves frame 0)"
        note = fig.text(0.5, 0.005, key, ha="center", va="bottom", fontsize=7.5, color="#333333")
    fig.tight_layout(rect=(0, 0.03, 1, 1) if sites else (0, 0, 1, 1))
    if sites:  # a tall legend below a panel (the pixel scores' four rows) ran over the key: lift the panels clear
        r = fig.canvas.get_renderer()
        top = note.get_window_extent(r).y1 / fig.bbox.height
        low = min((g.get_window_extent(r).y0 / fig.bbox.height for a in fig.axes if (g := a.get_legend())), default=1.0)
        if low < top + 0.005:  # taller by the overlap, the panels kept at their size
            w, h = fig.get_size_inches()
            lift = min(0.5, top + 0.01 - low) * h
            fig.set_size_inches(w, h + lift)
            fig.tight_layout(rect=(0, (0.03 * h + lift) / (h + lift), 1, 1))
    _unclash_labels(fig, labels)
    return fig


def _scalar(fig: Any, ax: Any, p: Panel, d: np.ndarray, fin: np.ndarray, cmap: Any, vmin: float, vmax: float) -> None:
    """A scalar panel's image and colour bar."""
    norm = None
    if p.centre is not None and vmin < p.centre < vmax:
        from matplotlib.colors import TwoSlopeNorm

        norm = TwoSlopeNorm(vcenter=p.centre, vmin=vmin, vmax=vmax)
    kw: dict[str, Any] = {"norm": norm} if norm is not None else {"vmin": vmin, "vmax": vmax}
    im = ax.imshow(np.ma.masked_invalid(d), cmap=cmap, interpolation="nearest", **kw)
    # a value past the scale drawn as its end's colour, said with a pointed end (a crater floor 6 m below
    # the scale read as the scale's lowest; QA of stop 72)
    lo, hi = bool(fin.min() < vmin), bool(fin.max() > vmax)
    extend = "both" if lo and hi else "min" if lo else "max" if hi else "neither"
    cb = fig.colorbar(im, ax=ax, fraction=0.046, pad=0.03, extend=extend)
    cb.set_label(p.unit, fontsize=8)
    cb.ax.tick_params(labelsize=7)
    if norm is not None and p.centre is not None:  # the turn: a line across the bar, and a tick named for it
        cb.ax.axhline(p.centre, color=LIMIT, linewidth=1.2)
        below = [v for v in np.linspace(vmin, vmax, 5) if v < p.centre - 0.1 * (p.centre - vmin)]
        ticks = [*below, p.centre, vmax]
        cb.set_ticks(ticks, labels=[f"{v:g}" for v in below] + [p.centre_label or f"{p.centre:g}", f"{vmax:g}"])
    if p.unknown is not None:
        _unknown_overlay(ax, np.asarray(p.unknown, bool) & np.isfinite(d), int(np.isfinite(d).sum()))


def dem_panels(estimate: np.ndarray, truth: np.ndarray | None, what: str = "elevation", unit: str = "m") -> list[Panel]:
    """Estimate | truth | error panels sharing one colour range.

    The range is the truth's 2nd-98th percentile where the estimate has a value (the whole truth when it has
    none): a crater outside the mapped ground would otherwise stretch the range and flatten the estimate into
    one colour (stop 85's QA). Truth beyond the range is drawn at the range's ends.
    """
    ref = truth if truth is not None else estimate
    both = np.isfinite(ref) & np.isfinite(estimate)
    fin = ref[both] if both.any() else ref[np.isfinite(ref)]
    lo, hi = (float(np.percentile(fin, 2)), float(np.percentile(fin, 98))) if fin.size else (0.0, 1.0)
    none = f"no computed {what}\n(none recovered: an image-only result?)"
    panels = [Panel("scalar", estimate, f"computed {what}", unit, ELEVATION_CMAP, lo, hi, empty_text=none)]
    if truth is not None:
        err = estimate - truth
        fe = np.abs(err[np.isfinite(err)])
        lim = float(np.percentile(fe, 95)) if fe.size else 1.0
        panels += [
            Panel("scalar", truth, f"true {what}", unit, ELEVATION_CMAP, lo, hi, empty_text=f"no true {what}"),
            Panel(
                "scalar",
                err,
                f"{what} error (computed - true)",
                unit,
                ERROR_CMAP,
                -lim or -1.0,
                lim or 1.0,
                empty_text=(
                    f"no error to show:\nno computed {what} where the truth is"
                    if np.isfinite(truth).any()
                    else f"no error to show:\nthe truth holds no {what}"
                ),
            ),
        ]
    return panels


# --------------------------------------------------------------------------- telemetry
QUEUE_DRAWN_S = 0.01  # a wait shorter than this is no bar and no legend entry (a millisecond read as a cause)
LIMIT = "#111111"  # a deadline, a budget, a ceiling: one colour in every telemetry figure (red is a miss)


VISIBLE_SHARE = 0.004  # a timeline bar narrower than this share of the axis is not named in the legend
ZOOM_SHARE = 0.25  # the timeline zooms to the work when the longest pair took under this share of the deadline


def _bar(ax: Any, y: float, start: float, width: float, colour: str, label: str | None) -> None:
    if width > 0:
        ax.barh(y, width, left=start, height=0.6, color=colour, edgecolor="none", label=label)


# The stages our flight software reports, in the order they run (its telemetry's ``stage_order``). Each keeps one
# colour whatever else ran: colours handed out by position among the stages present made brown `full_dem` in a full
# report and `georef` in a degraded one (stop 56's budget QA). Stages of a flight program of one's own take the
# colours left, in the order they appear.
KNOWN_STAGES = (
    "validate",
    "pose_refine",
    "prepare",
    "rocks",
    "shadow",
    "range",
    "coverage",
    "coarse_dem",
    "full_dem",
    "georef",
    "grid",
    "slope",
    "shading_slope",
    "hazard",
    "sites",
    "fusion",
    "output",
)


def stage_colours(stage_names: Sequence[str]) -> dict[str, Any]:
    """A colour per stage: :data:`KNOWN_STAGES` each its own fixed one of 20 distinct colours, other stages the rest
    in turn. tab20's reds (the deadline's colour) and greys (the link's bars) are left out, four of tab20b in their
    place."""
    plt = _plt()
    tab20, tab20b = plt.get_cmap("tab20"), plt.get_cmap("tab20b")
    wide = [tab20(i) for i in range(20) if i not in (6, 7, 14, 15)] + [tab20b(i) for i in (0, 4, 8, 12)]
    colour = {k: wide[i] for i, k in enumerate(KNOWN_STAGES) if k in stage_names}
    spare = [c for i, c in enumerate(wide) if i >= len(KNOWN_STAGES)] + wide[: len(KNOWN_STAGES)]
    others = [k for k in stage_names if k not in colour]
    colour |= {k: spare[i % len(spare)] for i, k in enumerate(others)}
    return colour


def stage_sequence(orders: Sequence[Sequence[str]]) -> list[str]:
    """One order for the stages of several pairs, each listed in the order it ran (``total`` left out): a stage
    first seen in a later pair goes right after the stage that preceded it there, so a stage that only some
    pairs ran (a DEM, the slope fit of a pair that has one) keeps its place in the sequence, not the end."""
    out: list[str] = []
    for order in orders:
        prev: str | None = None
        for k in order:
            if k == "total":
                continue
            if k not in out:
                out.insert(0 if prev is None else out.index(prev) + 1, k)
            prev = k
    return out


def timeline_figure(records: Sequence[dict[str, Any]]) -> Any:
    """Per pair, left to right from the end of the last frame: the frames' line time (before), compute stages,
    the result's line time, and the deadline as a red tick.

    Keys read per record (missing ones are skipped): ``label``, ``frames_link_s``, ``stages``
    ({name: {"wall_s"}}; ``total`` drawn only when a flight reports nothing else), ``stage_order`` (the order the
    stages ran; else the order of ``stages``), ``queue_wait_s``, ``result_queue_s``, ``result_link_s``
    (None with ``outside_flight_s``: e2e less the flight's compute, drawn unsplit), ``e2e_latency_s``,
    ``deadline_s``, ``plan`` (the
    flight's deadline plan, docs/protocol.md: two markers, the time it aimed to be done by and the time its DEM had
    to stop by to leave the reserve for the mapping after it).
    """
    plt = _plt()
    recs = [r for r in records if r.get("status", "result") == "result"]
    stage_names = stage_sequence([r.get("stage_order") or list(r.get("stages") or {}) for r in recs])
    # the legend (a ~17-stage pipeline and the link's entries) in two columns, and tall enough a figure to hold it:
    # in one column it squeezed three pairs' bars into a strip
    entries = len(stage_names) + 8
    ncol = 2 if entries > 12 else 1
    fig, ax = plt.subplots(
        figsize=(11 if ncol == 2 else 9, max(0.45 * max(3, len(recs)) + 1.2, 0.2 * entries / ncol + 1))
    )
    seen: set[str] = set()
    colour = stage_colours(stage_names)

    def once(name: str) -> str | None:
        if name in seen:
            return None
        seen.add(name)
        return name

    # a bar too narrow to see is drawn but not named: a ZeroMQ pair's 0.1 ms "frames on the link" and stages that
    # took no time filled the legend (QA of stop 72); the name waits for a pair where it shows
    work = max([float(r.get("e2e_latency_s") or 0.0) for r in recs], default=0.0)
    deadline = max([float(r.get("deadline_s") or 0.0) for r in recs], default=0.0)
    # a host-budget run's pairs took 0.08 s of a 2 s deadline: every bar a sliver and most stages unnamed (QA round 2
    # of stop 78). Zoomed to the work then, the deadline said at the axis's end
    zoom = work > 0.0 and ZOOM_SHARE * deadline > work
    span = 1.25 * work if zoom else max(work, deadline)

    def bar(y: float, start: float, width: float, colour: str, name: str) -> None:
        _bar(ax, y, start, width, colour, once(name) if width > VISIBLE_SHARE * span else None)

    for i, r in enumerate(recs):
        y = len(recs) - 1 - i
        fl = float(r.get("frames_link_s") or 0.0)
        bar(y, -fl, fl, "#cccccc", "frames on the link")
        t = float(r.get("queue_wait_s") or 0.0)
        if t >= QUEUE_DRAWN_S:
            bar(y, 0.0, t, "#eeeeee", "queued")
        stages = r.get("stages") or {}
        for k in stage_names:
            w = float((stages.get(k) or {}).get("wall_s", 0.0))
            bar(y, t, w, colour[k], k)
            t += w
        if not any(k in stages for k in stage_names) and "total" in stages:  # a flight that reports one figure
            w = float((stages["total"] or {}).get("wall_s", 0.0))
            bar(y, t, w, "#6a8fb5", "flight compute (its total only)")
            t += w
        plan = r.get("plan") or {}
        if "budget_s" in plan:  # the flight's own plan: the time it aimed to be done by, and the DEM's stop-by
            end = float(r.get("queue_wait_s") or 0.0) + float(plan["budget_s"])
            # a budget spent before the frames were in is no point on this axis (the table says it), nor one past a
            # zoomed axis's end
            if end >= 0.0 and not (zoom and end > span):
                ax.plot([end], [y + 0.38], marker="v", color="#222222", ms=5, ls="none", label=once("plan: done by"))
            need = next((plan[f"{k}_need_s"] for k in ("full_dem", "coarse_dem") if f"{k}_need_s" in plan), None)
            # a stop-by before the frames were in (a DEM that could not start: the table says why) is not drawn
            if need is not None and end - float(need) >= 0.0 and not (zoom and end - float(need) > span):
                ax.plot(
                    [end - float(need)], [y + 0.38], marker="v", color="#ffffff", mec="#222222", ms=5, ls="none",
                    label=once("plan: DEM stop-by (then the mapping's reserve)"),
                )  # fmt: skip
        rl = float(r.get("result_link_s") or 0.0)
        e2e = r.get("e2e_latency_s")
        start = (float(e2e) - rl) if e2e is not None else t
        outside = r.get("outside_flight_s")  # ZeroMQ, its sender measured no line time: the rest of e2e, unsplit
        if r.get("result_link_s") is None and outside is not None and e2e is not None:
            bar(y, float(e2e) - float(outside), float(outside), "#bbbbbb", "link and queues (not split)")
        rq = float(r.get("result_queue_s") or 0.0)
        if rq >= QUEUE_DRAWN_S:  # named in the legend only where it happened
            bar(y, start - rq, rq, "#999999", "result queued behind earlier messages")
        bar(y, start, rl, "#7a93ad", "result on the link")  # not the deadline line's near-black (QA 64b)
        if r.get("deadline_s") is not None and not zoom:
            ax.plot([r["deadline_s"]] * 2, [y - 0.4, y + 0.4], color=LIMIT, lw=2, label=once("deadline"))
        elif r.get("deadline_s") is not None:  # off the zoomed axis: said at its end, in the deadline's colour
            ax.text(span, y, f"deadline {float(r['deadline_s']):g} s \u2192", va="center", ha="right", fontsize=7,
                    color=LIMIT)  # fmt: skip
    # the frames' uplink (6 s at 921600 baud against ~1 s of compute) took most of the axis: shown up to half the
    # span after 0, and a longer one is cut there with its length written on it
    after = span  # the longest end to end or deadline (0 with no Result: nothing to cut)
    longest = max([float(r.get("frames_link_s") or 0.0) for r in recs], default=0.0)
    if after > 0 and longest > 0.5 * after:
        left = -0.5 * after
        ax.set_xlim(left=left * 1.02)
        for i, r in enumerate(recs):
            fl = float(r.get("frames_link_s") or 0.0)
            if fl > -left:
                ax.text(left, len(recs) - 1 - i, f" frames {fl:.1f} s \u2190", va="center", ha="left", fontsize=7)
    if zoom:
        ax.set_xlim(right=span)
    ax.set_ylim(-0.6, len(recs) - 0.4 + 0.25)  # room above the top row for its plan markers
    ax.set_yticks(range(len(recs)))
    ax.set_yticklabels([str(r.get("label", i)) for i, r in enumerate(recs)][::-1], fontsize=8)
    ax.axvline(0, color="#888", lw=0.8)
    ax.set_xlabel(
        "seconds since the ground sent the pair's last frame"
        + (f" (zoomed to the work: the deadline, {deadline:g} s, is off the axis)" if zoom else "")
    )
    ax.set_title("where each pair's time went")
    if ax.get_legend_handles_labels()[0]:  # no result with timings: nothing to name
        ax.legend(fontsize=7, loc="center left", bbox_to_anchor=(1.01, 0.5), frameon=False, ncol=ncol)
    else:
        ax.text(0.5, 0.5, "no Result with timings", transform=ax.transAxes, ha="center", va="center")
    fig.tight_layout()
    return fig


PAIR_TICKS_MAX = 16  # pair labels drawn on a per-pair axis: at 32 pairs they ran into one band (stop 63's soak QA)


def _pair_ticks(ax: Any, labels: Sequence[str]) -> None:
    """Every pair's tick, and every k-th its label (k such that at most :data:`PAIR_TICKS_MAX` are written)."""
    k = max(1, math.ceil(len(labels) / PAIR_TICKS_MAX))
    ax.set_xticks(range(len(labels)))
    ax.set_xticklabels([lab if i % k == 0 else "" for i, lab in enumerate(labels)], rotation=30, fontsize=8)


def latency_figure(records: Sequence[dict[str, Any]]) -> Any:
    """End-to-end latency of each pair against its deadline, in descent order; misses in red, a pair without a
    Result as an x. The legend names only what is drawn, and up to :data:`PAIR_TICKS_MAX` pairs each bar says its
    latency: a 0.07 s pair under a 2 s deadline is a sliver (QA of stop 78)."""
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    plt = _plt()
    fig, ax = plt.subplots(figsize=(8, 3.2))
    xs, ys, cs, labels, lost = [], [], [], [], []
    for i, r in enumerate(records):
        labels.append(str(r.get("label", i)))
        lat = r.get("e2e_latency_s", r.get("latency_s"))
        if r.get("status", "result") != "result" or lat is None:
            lost.append(i)
            continue
        xs.append(i)
        ys.append(float(lat))
        cs.append(SAFE if r.get("deadline_met") else MISSED)
    ax.bar(xs, ys, color=cs)
    if lost:
        ax.plot(lost, [0.0] * len(lost), "x", color=MISSED, ms=8, clip_on=False)
    if len(records) <= PAIR_TICKS_MAX:
        for x, y in zip(xs, ys):
            ax.annotate(f"{y:.2g} s", (x, y), xytext=(0, 2), textcoords="offset points", ha="center", fontsize=7)
    dl = [np.nan if r.get("deadline_s") is None else float(r["deadline_s"]) for r in records]
    handles: list[Any] = []
    if not all(np.isnan(dl)):  # each pair's deadline across its own bar's width
        ax.stairs(dl, np.arange(len(records) + 1) - 0.5, color=LIMIT, lw=1.2, baseline=None)
        handles.append(Line2D([], [], color=LIMIT, lw=1.2, label="deadline"))
    if SAFE in cs:
        handles.append(Patch(color=SAFE, label="met"))
    if MISSED in cs:
        handles.append(Patch(color=MISSED, label="late"))
    if lost:
        handles.append(Line2D([], [], color=MISSED, marker="x", ls="", ms=8, label="no result"))
    if handles:
        ax.legend(handles=handles, fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0), frameon=False)
    _pair_ticks(ax, labels)
    if records:
        ax.set_xlim(-0.5, len(records) - 0.5)
    ax.set_ylabel("end-to-end latency [s]")
    ax.set_title("each pair's end-to-end latency against its deadline, in descent order")
    fig.tight_layout()
    return fig


MEMORY_OFF_SCALE = 4.0  # a memory ceiling this many times the peak RSS is said in the title, not drawn


def resources_figure(records: Sequence[dict[str, Any]], cpu_budget: float | None, memory_mib: float | None) -> Any:
    """Achieved CPU fraction and peak private RSS per pair against the budget's duty cycle and memory ceiling."""
    plt = _plt()
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(10, 3.2))
    recs = [r for r in records if r.get("status", "result") == "result"]
    x = range(len(recs))
    labels = [str(r.get("label", i)) for i, r in enumerate(recs)]
    a1.plot(x, [r.get("cpu_fraction", np.nan) for r in recs], "o-", color="#4c78a8", label="achieved")
    if cpu_budget is not None:
        a1.axhline(cpu_budget, color=LIMIT, lw=1, ls="--", label="duty applied")
    a1.set_ylabel("CPU fraction of one core")
    cpu = [v for r in recs if np.isfinite(v := float(r.get("cpu_fraction", np.nan)))]
    top = max([*cpu, cpu_budget or 0.0], default=0.0)
    a1.set_ylim(0, 1.15 * top if top > 0 else None)  # headroom: the achieved line sits on the budget's
    rss = [np.nan if r.get("peak_rss_mib") is None else float(r["peak_rss_mib"]) for r in recs]  # None: not said
    peak = max((v for v in rss if np.isfinite(v)), default=0.0)
    if any(np.isfinite(v) for v in rss):
        a2.plot(x, rss, "o-", color="#54a24b", label="peak private RSS")
    else:  # a board's own flight program may not say: an empty axis with a legend read as a broken chart (QA 71)
        a2.text(0.5, 0.5, "not reported by the flight side", ha="center", va="center", transform=a2.transAxes)
    # a ceiling far above the peak flattened the RSS line on the floor (74 MiB under 2048; QA 64b): said instead
    far = memory_mib is not None and peak > 0 and memory_mib > MEMORY_OFF_SCALE * peak
    if memory_mib is not None and not far:
        a2.axhline(memory_mib, color=LIMIT, lw=1, ls="--", label="memory ceiling")
    a2.set_ylabel("MiB")
    a2.set_ylim(0, 1.25 * peak if far else None)
    for a in (a1, a2):
        _pair_ticks(a, labels)
        if a.get_legend_handles_labels()[0]:
            a.legend(fontsize=8)
    # a board of one's own has no throttle and no ceiling here: its own figures, titled as such
    a1.set_title("CPU against the throttle's duty cycle" if cpu_budget is not None else "CPU, as the flight side said")
    if far and memory_mib is not None:
        a2.set_title(f"memory (the ceiling, {memory_mib:g} MiB, is {memory_mib / peak:.0f}x the peak: off the scale)")
    else:
        a2.set_title("memory against the ceiling" if memory_mib is not None else "memory, as the flight side said")
    fig.tight_layout()
    return fig
