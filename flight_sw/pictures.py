"""Pictures and the report page of ``hazard-hil process`` (the CLI's only use of ground truth is here).

Figures follow the one colour convention of :mod:`reports.style` (green safe,
purple hazard, red only an undetected hazard, orange a false alarm, grey
unknown) and carry titles, colour bars with units, legends, and the ranked
landing sites as 3 m footprint circles. Pixel scoring follows docs/design.md:
positive = safe, a pixel is called safe when its hazard is < 1, scored over
the covered pixels where the truth is known.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

FOOTPRINT_RADIUS_M = 1.5  # the lander's 3 m footprint (docs/design.md, thesis Table 2.1)
# Gap fills on the DEM panel: darkened (they lie in dark shadow; no colour of the terrain map is this dark) so that
# a rim of a few pixels shows, and hatched so that a wide one reads as "not measured" with its colour still seen
FILL_VEIL = (0.0, 0.0, 0.0, 0.55)
FILL_HATCH = "////"
FILL_HATCH_COLOUR = "#1a1a1a"
FILL_LABEL = "gap fill (not matched)"


def confusion(hazard: np.ndarray, truth_hazard: np.ndarray, covered: np.ndarray) -> dict[str, np.ndarray]:
    """Masks TP/TN/FP/FN over covered pixels with known truth; called safe = finite hazard < 1."""
    known = np.asarray(covered, bool) & np.isfinite(truth_hazard)
    called_safe = np.isfinite(hazard) & (np.nan_to_num(hazard, nan=1.0) < 1)
    is_safe = np.nan_to_num(truth_hazard, nan=1.0) < 1
    return {
        "TP": known & called_safe & is_safe,
        "TN": known & ~called_safe & ~is_safe,
        "FP": known & called_safe & ~is_safe,
        "FN": known & ~called_safe & is_safe,
    }


def site_pixels(world_xy: np.ndarray, sites: list[Any]) -> list[tuple[float, float, float]]:
    """Per site ``(u, v, footprint radius px)``: the pixel whose world X, Y is nearest the site's centre.

    The radius is 1.5 m divided by the local ground sample distance (the mean
    world distance between neighbouring pixels there).
    """
    out: list[tuple[float, float, float]] = []
    xy = np.asarray(world_xy, np.float64)
    finite = np.isfinite(xy).all(axis=2)
    if not finite.any():
        return out
    for s in sites:
        d2 = np.where(finite, (xy[..., 0] - s.x) ** 2 + (xy[..., 1] - s.y) ** 2, np.inf)
        v, u = np.unravel_index(int(np.argmin(d2)), d2.shape)
        v1, u1 = min(v + 1, xy.shape[0] - 1), min(u + 1, xy.shape[1] - 1)
        steps = [float(np.linalg.norm(xy[v, u1] - xy[v, u])), float(np.linalg.norm(xy[v1, u] - xy[v, u]))]
        gsd = float(np.nanmean([g for g in steps if np.isfinite(g) and g > 0] or [np.nan]))
        out.append((float(u), float(v), FOOTPRINT_RADIUS_M / gsd if gsd > 0 else 2.0))
    return out


def fill_veil(filled: np.ndarray) -> np.ndarray:
    """HxWx4 float32 RGBA layer: :data:`FILL_VEIL` on the gap-fill pixels, transparent elsewhere."""
    m = np.asarray(filled, bool)
    rgba = np.zeros(m.shape + (4,), np.float32)
    rgba[m] = FILL_VEIL
    return rgba


def mark_fills(ax: Any, filled: np.ndarray) -> bool:
    """Darken and hatch the gap-fill pixels over a DEM panel, with a legend entry; nothing at all when there are
    none (the panel then reads as before). Returns whether anything was drawn."""
    from matplotlib.patches import Patch

    m = np.asarray(filled, bool)
    if not m.any():
        return False
    ax.imshow(fill_veil(m), interpolation="nearest")
    if min(m.shape) >= 2:  # the hatch follows the mask's outline (pixel edges); contourf needs 2 x 2 values
        cs = ax.contourf(m.astype(np.float32), levels=[0.5, 1.5], colors="none", hatches=[FILL_HATCH])
        cs.set_hatchcolor(FILL_HATCH_COLOUR)
        cs.set_hatch_linewidth(0.8)
    handle = Patch(facecolor=FILL_VEIL, edgecolor=FILL_HATCH_COLOUR, hatch=FILL_HATCH, label=FILL_LABEL)
    ax.legend(handles=[handle], loc="upper center", bbox_to_anchor=(0.5, -0.02), fontsize=7, frameon=False)
    return True


def dem_figure(
    elevation: np.ndarray,
    truth: np.ndarray | None = None,
    sigma: np.ndarray | None = None,
    filled: np.ndarray | None = None,
    fill_fraction: float | None = None,
    m_per_px: float | None = None,
    title: str = "Elevation (DEM)",
) -> Any:
    """The DEM picture of ``process``: computed elevation (its gap fills ``filled`` darkened and hatched, their
    share ``fill_fraction`` in its title), the elevation's ``sigma``, and with ``truth`` the true elevation
    and the error; a scale bar of ``m_per_px``. Returns the matplotlib figure (:func:`reports.plots.save`)."""
    from reports.plots import Panel, dem_panels, map_figure

    dem = dem_panels(elevation, truth)
    if fill_fraction:  # the pipeline's own share, of the covered pixels, as process prints it
        dem[0].title += f" ({100.0 * fill_fraction:.1f} % gap fill)"
    if not np.isfinite(elevation).any():  # an image-only result drew empty panels with colour bars (QA of stop 66)
        dem[0].title += ": no elevation recovered"
    if sigma is not None:
        dem.insert(1, Panel("scalar", sigma, "elevation uncertainty sigma", "m", "viridis"))
    fig = map_figure(dem, title, m_per_px=m_per_px)
    if filled is not None:  # fig.axes[0] is the computed elevation: the panels' axes come before their colour bars
        mark_fills(fig.axes[0], np.asarray(filled, bool) & np.isfinite(elevation))
    return fig


def write_process_report(
    out: Path,
    image: np.ndarray,
    res: Any,
    truth: dict[str, np.ndarray],
    doc: dict[str, Any],
) -> list[Path]:
    """``dem.png``, ``hazard.png`` (and ``confusion.png`` with a true hazard map) and ``report.html`` in ``out``.

    ``res`` is a :class:`flight_sw.pipeline.PipelineResult`, ``doc`` the
    ``result.json`` document (its ``vs_truth`` block feeds the page's table).
    Sites are marked safe/unsafe against the true hazard map when there is one.
    """
    from reports.html import Column, Figure, Headline, Section, Table, write_page
    from reports.plots import Panel, Site, confusion_codes, ground_step_m, map_figure, save
    from reports.style import HAZARD_CMAP, PSAFE_CMAP

    gt_z, gt_h = truth.get("elevation"), truth.get("hazard")
    px = site_pixels(res.world_xy, res.sites)
    truly_safe = None
    if gt_h is not None:
        safe_px = np.nan_to_num(gt_h, nan=1.0) < 1
        yy, xx = np.mgrid[: safe_px.shape[0], : safe_px.shape[1]]
        truly_safe = [bool(safe_px[(xx - u) ** 2 + (yy - v) ** 2 <= r * r].all()) for u, v, r in px]
    marks = [Site(u, v, r, i + 1, None if truly_safe is None else truly_safe[i]) for i, (u, v, r) in enumerate(px)]
    written: list[Path] = []
    figures: list[Figure] = []

    gsd = ground_step_m(res.world_xy)
    # a saved PNG names its pair: only its folder did
    name = Path(str(doc.get("pair_dir", ""))).name
    head = f"{name}: " if name else ""
    fills = res.info.get("dem_filled_fraction")
    fig = dem_figure(res.elevation, gt_z, res.sigma, res.filled, fills, gsd, f"{head}Elevation (DEM)")
    written.append(save(fig, out / "dem.png"))
    figures.append(
        Figure(
            "dem.png",
            "Computed elevation, its uncertainty; with truth, the true one and the error. White: no elevation "
            "(outside the area both images cover, or not recovered). Darkened and hatched in the computed "
            "elevation: gap fills carried into dark shadow, not matched (filled.npy; they have a larger sigma).",
        )
    )

    # the P(safe) a pixel needs at least to be called safe: the colour scale turns green only above it (green from 0.5
    # read as "mostly safe" on a pair that called 0.4 % safe, QA of stop 72)
    floor = float((res.info.get("psafe_call") or {}).get("psafe_min", res.params.get("psafe_min", 0.5)))
    hz = [
        Panel("image", image, "upper image (i1)", sites=marks),
        Panel("state", res.state, "hazard state", sites=marks),
        Panel(
            "scalar",
            res.psafe,
            "P(safe)",
            "probability",
            PSAFE_CMAP,
            0.0,
            1.0,
            centre=floor,
            centre_label=f"floor {floor:g}",
        ),
        Panel(
            "scalar",
            res.hazard,
            "hazard score (>= 1 unsafe)",
            "score",
            HAZARD_CMAP,
            0.0,
            1.0,
            unknown=np.asarray(res.state) == 2,  # written as 1.0 in hazard.npy; drawn grey, not as a hazard
        ),
    ]
    written.append(save(map_figure(hz, f"{head}Hazards and landing sites", m_per_px=gsd), out / "hazard.png"))
    figures.append(
        Figure(
            "hazard.png",
            (
                "Numbered circles are the ranked landing sites' 3 m footprints "
                "(green truly clear, red not, black without truth; a footprint smaller than 1.5 % of the panel "
                "is drawn at that size; sites too close to label apart share one label, e.g. 1,2,4). "
                if res.sites
                else "No landing site was offered (the reason is above). "  # circles explained on a map without any
            )
            + "Grey in the hazard score: unknown, written as 1.0 in hazard.npy. P(safe) turns green only above the "
            "floor marked on its bar: a pixel is called safe only above it (and above the pair's own cut, set by its "
            "FP budget), with a measured slope under the cap, so ground without an elevation stays unknown however "
            "high its P(safe).",
        )
    )

    rows: list[dict[str, Any]] = []
    (out / "confusion.png").unlink(missing_ok=True)  # an earlier run's scores must not pass for this one's
    if gt_h is not None:
        masks = confusion(res.hazard, gt_h, res.covered)
        scored = masks["TP"] | masks["TN"] | masks["FP"] | masks["FN"]
        codes = confusion_codes(masks["TP"] | masks["FP"], masks["TP"] | masks["FN"], scored)
        conf = [
            Panel("confusion", codes, "pixel scores, % of the map's covered pixels", sites=marks),
            Panel("scalar", gt_h, "true hazard (>= 1 unsafe)", "score", HAZARD_CMAP, 0.0, 1.0),
        ]
        written.append(save(map_figure(conf, f"{head}Against ground truth", m_per_px=gsd), out / "confusion.png"))
        figures.append(Figure("confusion.png", "Pixel scores against the true hazard map (positive = safe)."))
        c = doc.get("vs_truth", {}).get("confusion", {})
        d = doc.get("vs_truth", {}).get("dem_error", {})
        rows.append(
            {
                "fp_pct": c.get("FP_pct"),
                "fn_pct": c.get("FN_pct"),
                "tp_pct": c.get("TP_pct"),
                "tn_pct": c.get("TN_pct"),
                "cdi_pct": c.get("CDI_pct"),
                "dem_mean_abs_m": d.get("mean_abs_m"),
                "dem_median_m": d.get("median_m"),
                "dem_mad_m": d.get("mad_m"),
            }
        )
    site_rows = [
        {
            "rank": i + 1,
            "x_m": s.x,
            "y_m": s.y,
            "p_safe_site": s.p_safe,
            "clearance": s.clearance_m,
            **({"truly_clear": "yes" if truly_safe[i] else "NO"} if truly_safe is not None else {}),
        }
        for i, s in enumerate(res.sites)
    ]
    site_cols = [
        Column("rank", "rank", 0),
        Column("x_m", "X [m]", 1),
        Column("y_m", "Y [m]", 1),
        Column("p_safe_site", "site P(safe)", 3),
        Column("clearance", "clearance [m]", 2),
    ]
    if truly_safe is not None:
        site_cols.append(Column("truly_clear", "footprint truly clear"))
    sections = [
        Section(
            "Landing sites",
            paragraphs=[doc.get("no_site_reason") or ""] if not res.sites else [],
            tables=[Table(site_cols, site_rows)] if site_rows else [],
        ),
        Section("Maps", figures=figures),
    ]
    if rows:
        keys = ["fp_pct", "fn_pct", "tp_pct", "tn_pct", "cdi_pct", "dem_mean_abs_m", "dem_median_m", "dem_mad_m"]
        scope = (  # the same labels in `score`'s output count other pixels: said where both are read
            "Scored over the pixels this map covers. `hazard-hil score` scores the same output over the truth's "
            "overlap of the two frames and counts a pixel the map left out as not called safe, so its figures "
            "differ by the edge band."
        )
        sections.insert(
            0, Section("Against ground truth", paragraphs=[scope], tables=[Table([Column(k) for k in keys], rows)])
        )
    total = res.timings.get("total", {})
    headline = [
        Headline("level", res.level + (" (degraded)" * res.degraded), "warn" if res.degraded else "ok", "level"),
        Headline("valid_pct", 100.0 * res.valid_fraction),
        Headline("sites", len(res.sites), "ok" if res.sites else "warn", "landing sites"),
        Headline("compute_cpu_s", total.get("cpu_s"), label="compute CPU [s]"),
    ]
    if rows and rows[0]["fp_pct"] is not None:
        fp = rows[0]["fp_pct"]
        headline.append(Headline("fp_pct", fp, "ok" if fp <= 1.0 else "bad"))
    warnings = [str(w) for w in doc.get("warnings") or []]
    if warnings:  # said on the console only, the page showed a run on swapped frames as a green "full" (QA of stop 66)
        headline.insert(1, Headline("warnings", len(warnings), "warn", "warnings"))
        sections.insert(0, Section("Warnings", paragraphs=warnings))
    written.append(
        write_page(
            out / "report.html",
            f"process: {Path(doc.get('pair_dir', '')).name}",
            sections,
            subtitle=f"preset {doc.get('preset', '')}, {doc.get('frames', 2)} frames",
            headline=headline,
        )
    )
    return written
