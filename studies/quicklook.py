"""``hazard-hil process`` against the pair's ground truth: its outputs scored as ``hazard-hil score`` scores them.

DESIGN.md puts scoring on the ground side: the flight software never sees ground truth. ``process`` runs the
flight pipeline on the pair read without its truth (:mod:`flight_sw.cli`) and hands the outputs it wrote to
:class:`TruthLook`, which reads the truth, scores the output directory with :func:`studies.score.score_output`
(the same function, area and site rule as ``score``, ``evaluate`` and the HIL's grid scores), and writes:

* ``score.json``: ``{"summary": ..., "rows": [row]}``, the layout of ``score --json``;
* ``confusion.png``: frame 0 with the sites judged (green truly safe, red not, black not confirmed), the
  pixel scores and the true hazard;
* ``dem_error.png``: the true elevation and the error of the computed one.

The two pictures are not drawn with ``process --no-figures`` (``TruthLook(figures=False)``).

A pair whose truth ``score`` cannot use (no ``gt_depth_i1.npy``, say, so its true overlap is unknown) is scored
over the pixels the map covers instead, and said so: the DEM error where both elevations are finite, and the
pixel scores where ``gt_hazard_i1.npy`` gives a value, in ``confusion.png`` too; its sites are not judged, and
``score.json``'s summary says ``"scored_over": "covered"`` and why. A truth that gives none of this writes no
``score.json``, and says so.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from flight_sw.pictures import Appendix

SCOPE = (
    "Scored as `hazard-hil score PAIR OUT` scores this output (docs/design.md): over the pixels of frame 0 whose "
    "true ground the last frame sees, where the truth is known; a pixel the map left without a value counts as "
    "not called safe. A site is truly safe when every truth pixel whose true ground lies within 1.5 m of it is "
    "safe; a footprint frame 0 does not wholly see is not confirmed, and counts as not safe."
)
COVERED_SCOPE = (
    "Scored over the pixels this map covers, and its sites not judged: `hazard-hil score` cannot score this pair "
    "as docs/design.md does"
)


class TruthLook:
    """The :class:`flight_sw.cli.Scorer` of ``process``: the pair's ground truth, read by :meth:`prepare`."""

    def __init__(self, pair_dir: str | Path, fp_limit_pct: float | None = None, figures: bool = True) -> None:
        from studies.score import FP_LIMIT_PCT

        self.figures = figures  # confusion.png and dem_error.png (off: process --no-figures)
        self.pair_dir = Path(pair_dir)
        self.fp_limit_pct = FP_LIMIT_PCT if fp_limit_pct is None else fp_limit_pct
        self._pair: Any = None

    def prepare(self) -> None:
        """Read the pair with its truth: a truth file that cannot be read refuses the run before any work."""
        from protocol.pairdir import read_pair
        from studies.score import check_read_memory

        check_read_memory(self.pair_dir)
        self._pair = read_pair(self.pair_dir)

    def score(self, out: Path, title: str, m_per_px: float | None) -> Appendix | None:
        """Score ``out`` and write score.json and the pictures there; None when the pair has no truth."""
        from protocol.pairdir import pair_fingerprint
        from studies.score import ScoreError, read_output

        pair = self._pair
        if pair is None or not pair.truth:
            return None
        output = read_output(out, pair.images[0].shape, None, pair_fingerprint(pair.images))
        label = title.removesuffix(": ")
        try:
            return self._scored(pair, output, out, label, m_per_px)
        except ScoreError as exc:  # the truth lacks what `score` needs (gt_depth, say): what it allows instead
            return self._covered(pair, output, out, label, m_per_px, str(exc))

    def _scored(self, pair: Any, output: Any, out: Path, label: str, m_per_px: float | None) -> Appendix:
        from reports.html import write_atomic
        from reports.jsondoc import json_text
        from studies.score import json_row, score_output, summarise

        row: dict[str, Any] = {
            "pair": self.pair_dir.name,
            "pair_dir": str(self.pair_dir),
            "output_dir": str(out),
            "error": None,
        }
        drawn = out / "confusion.png" if self.figures else None
        row.update(score_output(pair, output, str(self.pair_dir), drawn, label))
        notes = []
        if row.get("figure_error"):  # a full disk: said, and the run fails as any refused write does
            raise OSError(row["figure_error"])
        figures = []
        if drawn is not None:
            row["figure"] = str(drawn)
            figures.append(CONFUSION_FIGURE)
        if self.figures and _dem_error_figure(output.elevation, pair.truth.get("elevation"), out, label, m_per_px, row):
            figures.append(DEM_FIGURE)
        doc = {"summary": summarise([row], self.fp_limit_pct), "rows": [json_row(row)]}
        write_atomic(out / "score.json", json_text(doc))
        if row.get("truth_note"):
            notes.append(f"note: {self.pair_dir}: {row['truth_note']}")
        if row.get("truth_poses") == "reported":
            notes.append(
                f"note: {self.pair_dir}: pair.json has no true_frames, so its frames' reported poses are taken as "
                "true when scoring: the sites are placed on the ground through them"
            )
        return Appendix(
            line=_line(row, self.fp_limit_pct),
            notes=notes,
            sections=[_section(row, SCOPE, figures, self.fp_limit_pct, "the scores, in the layout of score --json")],
            headline=_headline(row, self.fp_limit_pct),
        )

    def _covered(self, pair: Any, output: Any, out: Path, label: str, m_per_px: float | None, problem: str) -> Appendix:
        """What a truth `score` cannot use allows: the scores over the map's covered pixels, no sites."""
        from ground_sim import scoring
        from reports.html import write_atomic
        from reports.jsondoc import json_text
        from studies.score import json_row, pixel_scores

        why = problem.removesuffix(": nothing to score against")
        covered = np.isfinite(output.hazard)
        row: dict[str, Any] = {
            "pair": self.pair_dir.name,
            "pair_dir": str(self.pair_dir),
            "output_dir": str(out),
            "error": None,
            "scored_over": "covered",
            "truth_problem": why,
        }
        gt_h, gt_z = pair.truth.get("hazard"), pair.truth.get("elevation")
        figures = []
        if gt_h is not None:  # the pixel scores over the map
            c = scoring.confusion(output.hazard, gt_h, covered)
            if c["n"]:
                row.update(pixel_scores(c))
        if gt_z is not None and output.elevation is not None:
            d = scoring.dem_error_stats(output.elevation, gt_z.astype(np.float32), covered)
            if d["n"]:
                row.update(dem_mean_abs_m=d["mean_abs"], dem_median_m=d["median"], dem_mad_m=d["mad"])
        row = {k: None if isinstance(v, float) and math.isnan(v) else v for k, v in row.items()}
        if row.get("fp_pct") is None and row.get("dem_mean_abs_m") is None:  # nothing to say: no file either
            return Appendix(notes=[f"note: nothing of this output could be scored against the truth: {why}"])
        if row.get("fp_pct") is not None and self.figures:
            _covered_confusion_figure(output.hazard, gt_h, covered, out, label, m_per_px, row)
            figures.append(COVERED_CONFUSION_FIGURE)
        if self.figures and _dem_error_figure(output.elevation, gt_z, out, label, m_per_px, row):
            figures.append(DEM_FIGURE)
        summary = {"pairs": 1, "scored_over": "covered", "truth_problem": why}
        write_atomic(out / "score.json", json_text({"summary": summary, "rows": [json_row(row)]}))
        return Appendix(
            line=_line(row, self.fp_limit_pct) + " of the map's covered pixels",
            notes=[f"note: scored over the map's covered pixels, not as `hazard-hil score` scores it: {why}"],
            sections=[
                _section(
                    row,
                    f"{COVERED_SCOPE} ({why}).",
                    figures,
                    self.fp_limit_pct,
                    "the scores over the map's covered pixels (hazard-hil score cannot score this pair)",
                )
            ],
            headline=_headline(row, self.fp_limit_pct),
        )


def _covered_confusion_figure(
    hazard: np.ndarray,
    truth: np.ndarray,
    covered: np.ndarray,
    out: Path,
    label: str,
    m_per_px: float | None,
    row: dict[str, Any],
) -> None:
    """``confusion.png`` over the map's covered pixels where the truth is known: the pixel scores, the true hazard
    (no sites: without gt_depth their ground is unknown)."""
    from ground_sim import scoring
    from reports.plots import Panel, confusion_codes, map_figure, save, truth_panel

    gt = np.asarray(truth, np.float32)
    scored = covered & np.isfinite(gt)
    codes = confusion_codes(~scoring.unsafe_estimate(hazard), gt < 1.0, scored)
    panels = [
        Panel("confusion", codes, "pixel scores, over the map's covered pixels"),
        truth_panel(gt, scored=scored),
    ]
    title = f"{label}: FP {row['fp_pct']:.2f} %, CDI {row['cdi_pct']:.1f} % of the map's covered pixels"
    save(map_figure(panels, title, m_per_px=m_per_px), out / "confusion.png")


def _dem_error_figure(
    elevation: np.ndarray | None,
    truth: np.ndarray | None,
    out: Path,
    label: str,
    m_per_px: float | None,
    row: dict[str, Any],
) -> bool:
    """``dem_error.png``: the computed elevation, the true one on the same colour scale, and the error; False when
    there is no pair of elevations to draw."""
    from reports.plots import dem_panels, map_figure, save

    if elevation is None or truth is None:
        return False
    err = row.get("dem_mean_abs_m")
    title = f"{label}: elevation against ground truth" + ("" if err is None else f", mean |error| {err:.3f} m")
    panels = dem_panels(np.asarray(elevation, np.float32), np.asarray(truth, np.float32))
    save(map_figure(panels, title, m_per_px=m_per_px), out / "dem_error.png")
    return True


def _top(row: dict[str, Any]) -> str:
    if row.get("top_site_confirmed") is False:
        return "top site not confirmed"
    return {True: "top site truly safe", False: "top site NOT safe", None: "no site"}[row.get("top_site_truly_safe")]


def _line(row: dict[str, Any], limit: float) -> str:
    """What the summary line adds: the pixel scores, the DEM error and the top site."""
    parts = []
    if row.get("fp_pct") is not None:
        over = f" (over the {limit:g} % limit)" if row["fp_pct"] > limit else ""
        parts.append(f"FP {row['fp_pct']:.2f} %{over}, CDI {row['cdi_pct']:.1f} %")
    if row.get("dem_mean_abs_m") is not None:
        parts.append(f"DEM mean |error| {row['dem_mean_abs_m']:.3f} m")
    if "top_site_truly_safe" in row:
        parts.append(_top(row))
    return f"; against the truth: {', '.join(parts)}" if parts else ""


def _headline(row: dict[str, Any], limit: float) -> list[Any]:
    from reports.html import Headline

    cards = []
    if row.get("fp_pct") is not None:
        cards.append(Headline("fp_pct", row["fp_pct"], "ok" if row["fp_pct"] <= limit else "bad"))
        cards.append(Headline("cdi_pct", row["cdi_pct"]))
    if "top_site_truly_safe" in row and row["top_site_truly_safe"] is not None:
        cards.append(
            Headline("top site", _top(row).removeprefix("top site "), "ok" if row["top_site_truly_safe"] else "bad")
        )
    return cards


CONFUSION_FIGURE = (
    "confusion.png",
    "Frame 0 with the sites judged against the truth (green truly safe, red not, black not confirmed), the pixel "
    "scores (positive = safe) and the true hazard.",
)
COVERED_CONFUSION_FIGURE = ("confusion.png", "The pixel scores over the map's covered pixels, and the true hazard.")
DEM_FIGURE = (
    "dem_error.png",
    "The computed elevation and the true one on one colour scale, and the error (computed - true).",
)


def _section(row: dict[str, Any], scope: str, figures: list[tuple[str, str]], limit: float, link: str) -> Any:
    from reports.html import Column, Figure, Section, Table

    keys = ["fp_pct", "fn_pct", "tp_pct", "tn_pct", "cdi_pct", "dem_mean_abs_m", "dem_median_m", "dem_mad_m"]
    tables = [Table([Column(k) for k in keys], [{k: row.get(k) for k in keys}])]
    verdicts = row.get("site_verdicts") or []
    if verdicts:
        words = {True: "yes", False: "NO", None: "not confirmed"}
        tables.append(
            Table(
                [Column("rank", "rank", 0), Column("truly_clear", "footprint truly clear")],
                [{"rank": i + 1, "truly_clear": words[v]} for i, v in enumerate(verdicts)],
            )
        )
    status = "" if row.get("fp_pct") is None else ("ok" if row["fp_pct"] <= limit else "bad")
    return Section(
        "Against ground truth",
        paragraphs=[scope],
        tables=tables,
        figures=[Figure(src, caption) for src, caption in figures],
        status=status,
        links=[("score.json", link)],
    )
