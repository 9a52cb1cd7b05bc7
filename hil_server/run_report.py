"""The report page of an HIL run (``OUT/report.html``), in the shared page design of :mod:`reports.html`.

Headline: the deadline verdict (judged end to end at the ground, docs/hil.md),
results, latency. Then the per-pair table; the telemetry figures (where each
pair's time went, latency against the deadline over the descent, CPU fraction
and peak RSS against the budget); and per pair the maps a person wants, from
what actually came back over the link: the upper image, the pixel scores against
the truth (positive = safe) and the DEM against the truth. Figures are PNG files
in ``OUT/figures``.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from protocol.plan import plan_note
from reports.console import printable
from reports.html import NO_FIGURES_NOTE, Column, Figure, Headline, Section, Table, file_links, write_page
from reports.plots import (
    Panel,
    Site,
    confusion_codes,
    dem_panels,
    latency_figure,
    map_figure,
    resources_figure,
    save,
    timeline_figure,
)
from reports.style import HAZARD_CMAP

PAIR_COLUMNS = [
    Column("label", "pair", 0),
    Column("altitude_m", digits=0),
    Column("outcome", "outcome"),
    Column("e2e_latency_s"),
    Column("flight_latency_s"),
    Column("result_line_s"),
    Column("deadline_verdict"),
    Column("fp_pct"),
    Column("cdi_pct"),
    Column("dem_mean_abs_m"),
    Column("top_site"),
    Column("pose_cell"),
]


def _first(r: dict, *keys: str) -> Any:
    """The first of ``keys`` that ``r`` holds (not None); "" names ``r["link"]["result_link_s"]``, the sender's
    figure in an old record. A 0.0 is a figure: the Result's line time cut to 0 is not replaced by the uncut one."""
    for k in keys:
        v = (r.get("link") or {}).get("result_link_s") if k == "" else r.get(k)
        if v is not None:
            return v
    return None


def level_text(r: dict) -> str:
    """A Result's level, the stages it skipped and, when its Telemetry says, why: "coarse (skipped full_dem;
    full_dem not started: 3.1 s left, 38.0 s kept for the work after it (x254, from the first stages))"."""
    text = str(r.get("level"))
    why = plan_note(r.get("plan"), r.get("skipped"))
    if r.get("skipped"):
        text += f" (skipped {', '.join(r['skipped'])}" + (f"; {why})" if why else ")")
    return text


def pair_row(r: dict) -> dict[str, Any]:
    """One row of the per-pair table from a run record."""
    sc = r.get("scores", {}) or {}
    ok = r.get("status") == "result"
    return {
        "label": r.get("label"),
        "altitude_m": r.get("altitude_m"),
        # an error says why, as the console does (the page showed its code alone); the text is escaped by the page
        "outcome": ("degraded " if r.get("degraded") else "") + level_text(r)
        if ok
        else f"error: {r.get('code')}" + (f": {printable(r['text'], 300)}" if r.get("text") else ""),
        "e2e_latency_s": _first(r, "e2e_latency_s", "latency_s") if ok else None,
        "flight_latency_s": r.get("flight_latency_s") if ok else None,
        "result_line_s": _first(r, "result_line_s", "result_link_s", "") if ok else None,
        "deadline_verdict": ("met" if r.get("deadline_met") else "MISSED") if ok else "no result",
        "fp_pct": sc.get("fp_pct"),
        "cdi_pct": sc.get("cdi_pct"),
        "dem_mean_abs_m": _first(sc, "dem_mean_abs", "dem_mean_abs_m"),
        "top_site": _site_cell(r) if ok else None,
        "pose_cell": pose_cell(r) if ok else None,
    }


def pose_cell(r: dict) -> str | None:
    """The pair's pose refinement from its Telemetry (revision 5): "refined (relative 0.01 deg, attitude 0.15 deg)",
    "kept", "degenerate", ...; None when it did not say. The corrections (the relative rotation's; the larger of the
    two frames' own attitudes) are shown only when they were applied."""
    verdict = r.get("pose_verdict")
    if not verdict:
        return None
    pose = r.get("pose") or {}
    att = [float(v) for v in (pose.get("att1_deg"), pose.get("att2_deg")) if isinstance(v, (int, float))]
    said = [
        f"{name} {v:.2f} deg"
        for name, v in (("relative", pose.get("rot_deg")), ("attitude", max(att) if att else None))
        if isinstance(v, (int, float))
    ]
    return printable(verdict, 40) + (f" ({', '.join(said)})" if pose.get("applied") and said else "")


def _site_cell(r: dict) -> str:
    from hil_server.run import top_site_text

    text = top_site_text(r)
    why = r.get("no_site_reason")
    return f"{text}: {printable(why, 200)}" if not r.get("sites") and why else text


def _site_marks(r: dict, pair: Any) -> list[Site]:
    """The Result's sites where i1 sees their ground, each a 3 m footprint, coloured by the truth's verdict."""
    from ground_sim.gridscore import site_verdict

    depth = pair.truth.get("depth")
    out = []
    for rank, j in enumerate(r.get("site_truth") or [], 1):
        if j.get("uv") is None or depth is None:
            continue
        u, v = j["uv"]
        z = float(depth[v, u])
        radius = 1.5 * pair.camera.fx / z if np.isfinite(z) and z > 0 else 2.0
        # what this image cannot judge (its footprint not wholly in view, nothing unsafe seen) is drawn black, not red
        out.append(Site(float(u), float(v), radius, rank, site_verdict(j)))
    return out


def _ground_step(pair: Any) -> float | None:
    """i1's median ground step between neighbouring pixels (a scale bar's metres per pixel), from the truth
    depth and the true pose; None without a truth depth."""
    from ground_sim.gridscore import pixel_ground_xy, true_pose_upper
    from reports.plots import ground_step_m

    depth = pair.truth.get("depth")
    if depth is None:
        return None
    return ground_step_m(np.stack(pixel_ground_xy(pair.camera, true_pose_upper(pair), depth), axis=-1))


def _telemetry_records(records: list[dict]) -> list[dict]:
    """Records with the key names the telemetry figures read (line times under either name)."""
    out = []
    for r in records:
        t = dict(r)
        t.setdefault("frames_link_s", r.get("frames_line_s"))
        t["result_link_s"] = _first(r, "result_line_s", "result_link_s", "")
        if t.get("e2e_latency_s") is None and r.get("status") == "result":
            t["e2e_latency_s"] = r.get("latency_s")
        t.setdefault("deadline_s", r.get("deadline_s"))
        out.append(t)
    return out


def _pixel_states(r: dict, out: Path, pair: Any) -> np.ndarray | None:
    """The Result's safe/unsafe/unknown call at each pixel of frame 0: its full-resolution state map (``run
    --full-maps``), else its world grid read at each pixel's true ground point (which the truth's depth gives);
    None when neither is at hand (QA of stop 72: the run's figure showed no state at all)."""
    if (out / "state.npy").is_file():
        return np.load(out / "state.npy")
    if not (out / "state_grid.npy").is_file() or "depth" not in pair.truth or r.get("grid_cell_m") is None:
        return None
    from ground_sim.gridscore import pixel_ground_xy, states_at_pixels, true_pose_upper

    x, y = pixel_ground_xy(pair.camera, true_pose_upper(pair), pair.truth["depth"])
    ox, oy = (float(v) for v in r["grid_origin_xy"])
    origin = (ox, oy)
    return states_at_pixels(np.load(out / "state_grid.npy"), origin, float(r["grid_cell_m"]), x, y)


def _map_source(summary: dict, answered: list[str]) -> str:
    """What a pair's returned map rests on, for its picture: the pair alone, or the map fused over the Results so
    far (a fused and an unfused run's pictures had the same titles and captions; QA round 2 of stop 78)."""
    if summary.get("fusion") is None:
        return ""
    if not summary["fusion"]:
        return "of this pair alone"
    over = ", ".join(answered) if len(answered) <= 4 else f"{answered[0]}, ..., {answered[-1]}"
    from hil_server.run import flight_decides_fusion

    return f"fused over {len(answered)} pair{'s' if len(answered) > 1 else ''} ({over})" + (
        ", where the flight side fuses" if flight_decides_fusion(summary) else ""
    )


def _pair_figures(r: dict, fig_dir: Path, source: str = "") -> list[Figure]:
    from hil_server.run import CALLED_FILE, DERIVED_TRUTH_FILE, read_called
    from protocol.pairdir import PairFormatError, read_pair

    out = Path(r.get("out_dir", ""))
    # the full-resolution map when the run asked for it, else the compact grid's call per pixel
    hz_file = next((out / n for n in ("hazard.npy", CALLED_FILE) if (out / n).is_file()), None)
    if r.get("status") != "result" or hz_file is None:
        return []
    try:
        pair = read_pair(r["pair_dir"])
    except PairFormatError:  # its truth unreadable (the record's truth_note says why): the image and the map alone
        try:
            pair = read_pair(r["pair_dir"], load_truth=False)
        except PairFormatError:
            return []
    if (out / DERIVED_TRUTH_FILE).is_file() and "hazard" not in pair.truth:  # as the scores derived it
        pair.truth["hazard"] = np.load(out / DERIVED_TRUTH_FILE)
    hazard = np.load(hz_file) if hz_file.name == "hazard.npy" else read_called(hz_file)
    pid = r["pair_id"]
    figs = []
    marks = _site_marks(r, pair)
    title = "upper image (i1)" + (", landing sites by rank" if marks else "")
    panels = [Panel("image", pair.images[0], title, sites=marks)]
    states = _pixel_states(r, out, pair)
    if states is not None:  # what the flight side called, beside how it scored: the figure showed the scores only
        panels.append(Panel("state", states, "hazard state (the Result's)", sites=marks))
    gt_h = pair.truth.get("hazard")
    if hz_file.name == "hazard.npy" and "depth" not in pair.truth:
        gt_h = None  # the overlap is unknown: the scores withhold the full map's, so the picture does (review 66)
    if gt_h is not None:
        # over the true overlap, as the scores beside it (a full map over its own pixels read TN 47.0 % where the
        # table said 46.5; QA of stop 66); the grid's call per pixel is NaN exactly off it already
        covered = np.isfinite(hazard) & np.isfinite(gt_h)
        if hz_file.name == "hazard.npy":
            from ground_sim.gridscore import pixel_ground, scored_area, true_pose_upper

            covered = scored_area(pair, pixel_ground(pair.camera, true_pose_upper(pair), pair.truth["depth"]))
        called_safe = covered & (np.nan_to_num(hazard, nan=1.0) < 1)
        truly_safe = np.nan_to_num(gt_h, nan=1.0) < 1
        derived = " (truth derived from the other truth files)" if r.get("truth") == "derived" else ""
        panels.append(Panel("confusion", confusion_codes(called_safe, truly_safe, covered), f"pixel scores{derived}"))
    else:
        panels.append(Panel("scalar", hazard, "hazard (>= 1 unsafe)", "score", HAZARD_CMAP, 0.0, 1.0))
    gsd = _ground_step(pair)
    # the level and the deadline in the picture too: an image-only Result that missed looked like a full one there
    met = r.get("deadline_met")
    dl = "" if met is None else "deadline met" if met else "deadline MISSED"
    how = ", ".join(x for x in (str(r.get("level") or ""), dl) if x)
    how = "; ".join(x for x in (how, source.partition(" (")[0]) if x)  # "fused over 5 pairs": the list is below
    title = f"{r.get('label')}: hazards" + (f" ({how})" if how else "")
    save(map_figure(panels, title, m_per_px=gsd), fig_dir / f"{pid}_hazard.png")
    sites = (
        " Circles: the landing sites it offered, numbered by rank; green when the truth says the whole 3 m footprint "
        "is clear, red when it is not, black when this image does not hold the whole footprint."
        if marks
        else ""
    )
    scored = (
        "scored against the truth"
        if gt_h is not None
        else "not scored: the pair has no true depth, so the area to score is unknown"
        if "hazard" in pair.truth
        else "not scored: the pair has no truth hazard"
    )
    came = f"what came back (the map {source})" if source else "what came back"
    figs.append(Figure(f"figures/{pid}_hazard.png", f"{r.get('label')}: {came}, {scored}.{sites}"))
    if (out / "elevation.npy").is_file():
        dem = dem_panels(np.load(out / "elevation.npy"), pair.truth.get("elevation"))
        save(map_figure(dem, f"{r.get('label')}: elevation", m_per_px=gsd), fig_dir / f"{pid}_dem.png")
        figs.append(Figure(f"figures/{pid}_dem.png", f"{r.get('label')}: the returned DEM and its error."))
    return figs


def write_run_report(summary: dict, path: Path, figures: bool = True) -> Path:
    """Write ``report.html`` (and ``figures/``) for a run summary; returns the page's path. Without ``figures``
    the page has its tables and notes and no pictures: drawing them is 0.3-0.5 s each (a three-pair 128 px run
    took 7.7 s with them, 4.8 s without), which a gate reading summary.json does not need."""
    path = Path(path)
    fig_dir = path.parent / "figures"
    s = summary
    records = list(s.get("records", []))
    pairs = int(s.get("pairs", len(records)) or 0)
    results = int(s.get("results", sum(r.get("status") == "result" for r in records)))
    met = s.get("deadline_met")
    hit = s.get("deadline_hit_rate")
    hit_ok = isinstance(hit, (int, float)) and math.isfinite(hit) and hit >= 1.0
    complete = s.get("complete", True)
    said = s.get("verdict") if isinstance(s.get("verdict"), dict) else None
    headline = []
    if said is not None:  # the run's own verdict and exit code: in summary.md and summary.json, not here (QA 80)
        word = "PASS" if said.get("pass") else ("FAIL" if complete else "INCOMPLETE")
        status = "ok" if said.get("pass") else "bad"
        headline.append(Headline("verdict", f"{word} (exit {said.get('exit_code')})", status, "the run's verdict"))
    headline += [
        Headline("deadline_hit_rate", hit, "ok" if hit_ok and complete else "bad"),
        Headline("results", f"{results}/{pairs}", "ok" if results == pairs and pairs else "bad", "results"),
        Headline("e2e_latency_s", _first(s, "e2e_latency_p50_s", "latency_p50_s"), label="end-to-end latency p50 [s]"),
        Headline("e2e_max", _first(s, "e2e_latency_max_s", "latency_max_s"), label="end-to-end latency max [s]"),
    ]
    degraded = sum(bool(r.get("degraded")) for r in records if r.get("status") == "result")
    if results:  # a met deadline with a degraded Result is not the full answer: say how many
        headline.append(
            Headline(
                "degraded",
                f"{degraded}/{results}",
                "warn" if degraded else "ok",
                "Results degraded (a coarser level or stages skipped)",
            )
        )
    judged = s.get("sites")
    unjudged = len(judged.get("top_not_judged", [])) if judged else 0
    n_judged = judged["with_site"] - unjudged if judged else 0
    if judged and judged["with_site"]:  # the answer a lander acts on: red when one is not clear, amber when unjudged
        # or when most pairs offered no site: a green "1/1" stood for a run where 7 of 8 offered none (QA of stop 78)
        few = 2 * judged["with_site"] < judged["pairs"]
        status = "bad" if judged["top_not_clear"] else ("warn" if unjudged or few else "ok")
        headline.append(
            Headline(
                "top_site",
                f"{judged['top_clear']}/{n_judged}" + (f" ({unjudged} not judged)" if unjudged else ""),
                status,
                f"top landing site truly clear ({judged['with_site']} of {judged['pairs']} pairs offered one)",
            )
        )
    fps = [r["scores"]["fp_pct"] for r in records if (r.get("scores") or {}).get("fp_pct") is not None]
    if fps:
        worst = max(fps)
        headline.append(Headline("fp_pct", worst, "ok" if worst <= 1.0 else "bad", "worst FP % (undetected hazard)"))
    where = f"budget {s['budget']}" if s.get("budget") else f"flight {s.get('flight', '?')}"
    subtitle = (
        f"{s.get('scenario')} over {s.get('link')} on {where}; deadline {s.get('deadline_s', '?')} s, judged end "
        "to end: from the ground sending a pair's last frame to the ground holding the whole Result (docs/hil.md)."
    )
    intro = [f"{said['line']} (exit {said.get('exit_code')})."] if said is not None and said.get("line") else []
    if not complete:
        done = sum(r.get("status") == "result" for r in records)
        # the table lists the pairs not run too: "only the pairs below finished" sat above a table of them (QA 72)
        intro.append(
            f"INCOMPLETE: {s.get('reason')}. {done} of {len(records)} pairs returned a result; the table says what "
            "became of each."
        )
    if met is not None and said is None:  # the verdict line says it
        intro.append(f"{met} of {pairs} pairs returned a result within the deadline.")
    from hil_server.run import GRID_SCORES_NOTE, summary_notes

    # every note summary.md gives, in its order: the budget, the throttle, host contention, sites, pose, the flight
    # side's refusals and ignored answers, lost sessions, stops, and what the figures rest on
    intro += [note[0].upper() + note[1:] + ("" if note.endswith(".") else ".") for note in summary_notes(s) if note]
    intro.append("FP, CDI and DEM error are " + GRID_SCORES_NOTE.removeprefix("(grid): "))
    if not figures:
        intro.append(NO_FIGURES_NOTE)
    sections = [
        Section(
            "Pairs",
            paragraphs=intro,
            tables=[Table(PAIR_COLUMNS, [pair_row(r) for r in records])],
            status="ok" if hit_ok and complete else "bad",
        )
    ]
    said = [r for r in records if r.get("flight_notes")]
    if said:  # the flight side's own warnings (Telemetry revision 5): they were in no output before stop 76
        sections.append(
            Section(
                "What the flight side said",
                paragraphs=[f"{r.get('label')}: {printable(n, 300)}" for r in said for n in r["flight_notes"]],
                status="warn",
            )
        )
    tel = _telemetry_records(records)
    tel_figs = []
    if figures and any(r.get("status") == "result" for r in records):
        save(timeline_figure(tel), fig_dir / "timeline.png")
        tel_figs.append(
            Figure(
                "figures/timeline.png",
                "Per pair: frames on the link, compute stages in the order they ran, result line time; the "
                "flight's plan: the time it aimed to be done by (filled triangle) and the time its DEM had to stop "
                "by to leave the reserve for the mapping after it (open triangle).",
            )
        )
    if records and figures:
        save(latency_figure(tel), fig_dir / "latency.png")
        no_result = sum(r.get("status") != "result" for r in records)
        key = "red bars missed the deadline" + ("; a red x at 0: no Result at all" if no_result else "")
        tel_figs.append(Figure("figures/latency.png", f"End-to-end latency over the descent; {key}."))
    said = [r.get(k) for r in records for k in ("cpu_fraction", "peak_rss_mib")]
    if figures and any(v is not None and math.isfinite(float(v)) for v in said):  # an external board may say neither
        duty = d if (d := s.get("cpu_fraction")) is not None and math.isfinite(d) else None
        save(resources_figure(tel, duty, s.get("memory_mib")), fig_dir / "resources.png")
        # a board of one's own has no throttle and no ceiling here: the caption said both (QA of stop 71)
        cpu = (
            "Achieved CPU fraction against the duty cycle the throttle applied"
            if duty is not None
            else "The CPU fraction the flight side reported (no throttle: it runs at its own speed)"
        )
        rss = [r.get("peak_rss_mib") for r in records]
        mem = (
            "its peak private RSS: not reported"
            if not any(v is not None and math.isfinite(float(v)) for v in rss)
            else "the private RSS peak against the budget's memory ceiling"
            if s.get("memory_mib") is not None
            else "its peak private RSS as it reported it"
        )
        tel_figs.append(Figure("figures/resources.png", f"{cpu}, and {mem}."))
    from hil_server.run import phase_note, throttle_check_note

    notes = [n[0].upper() + n[1:] + "." for n in (throttle_check_note(s), phase_note(s)) if n]
    sections.append(Section("Telemetry", paragraphs=notes, figures=tel_figs))
    answered: list[str] = []  # the pairs whose Results came back so far: what a fused map rests on
    for r in records if figures else ():
        if r.get("status") == "result":
            answered.append(str(r.get("label")))
        figs = _pair_figures(r, fig_dir, _map_source(s, answered))
        if figs:
            sections.append(Section(f"Pair {r.get('label')}", figures=figs))
    files = [
        ("summary.json", "every figure of this page, per pair and for the run"),
        ("summary.md", "the pairs' table as text"),
        ("telemetry.jsonl", "a line per pair: the timings, as the ground measured them"),
        ("received/results.jsonl", "the ground's record of each pair, as it came back"),
        ("supervisor.jsonl", "the HIL server's log: each pair, restart and refusal"),
        ("supervisor.log", "the HIL server's and the flight process's output"),
    ]
    links = file_links(path.parent, files)
    if links:
        sections.append(Section("Files", links=links))
    # the per-pair maps draw the states and the pixel scores; a page without them keys neither (QA of stop 72)
    scored = any(f.src.endswith("_hazard.png") for sec in sections for f in sec.figures)
    return write_page(
        path,
        "HIL run",
        sections,
        subtitle=subtitle,
        headline=headline,
        legends=("confusion", "state") if scored else (),
    )
