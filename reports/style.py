"""One colour convention and one glossary for every report.

Colours (DESIGN.md scoring: positive = safe):

* green  — safe: a safe state, or a TP (safe ground called safe);
* purple — hazard: an unsafe state, or a TN (a hazard not called safe: called unsafe, or unknown);
* red    — only ever an undetected hazard (FP: unsafe ground called safe), the
  error a lander cannot afford;
* orange — a false alarm (FN: safe ground not called safe);
* grey   — unknown (not enough evidence; scored as not called safe);
* white  — outside the area both images cover.

Anything else (a preset, a policy, a signed error) takes colours none of these mean: :data:`SERIES_COLOURS` for
series, blue-white-brown for a signed error (:data:`ERROR_CMAP`).

Metric labels are unique; :data:`GLOSSARY` explains each one, and every page
lists the entries it uses.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

SAFE = "#2e9e44"
HAZARD = "#7b3fa0"
MISSED = "#e3111b"
FALSE_ALARM = "#ff9a1f"
UNKNOWN = "#a6a6a6"
OUTSIDE = "#ffffff"

CONFUSION_COLOURS = {"TP": SAFE, "TN": HAZARD, "FP": MISSED, "FN": FALSE_ALARM}
CONFUSION_NAMES = {
    "TP": "TP: safe, called safe",
    "TN": "TN: hazard, not called safe",  # unsafe or unknown: "called unsafe" read wrong on an all-unknown map
    "FP": "FP: hazard called safe (undetected)",
    "FN": "FN: safe, not called safe (false alarm)",
}
STATE_COLOURS = {0: SAFE, 1: HAZARD, 2: UNKNOWN, 255: OUTSIDE}
STATE_NAMES = {0: "safe", 1: "unsafe", 2: "unknown", 255: "outside"}

# Continuous layers: one colour map per kind of quantity. Two are the reports' own (:func:`reports.plots.colormap`):
# matplotlib's "terrain" ends in white, which is also "no elevation" here, and P(safe) in red-yellow-green put red,
# the undetected hazard's colour, on ground correctly called unsafe.
ELEVATION_CMAP = "hh-elevation"  # matplotlib's "terrain" between ELEVATION_RANGE: green lowlands .. brown highs
ELEVATION_RANGE = (0.22, 0.82)
# diverging, symmetric about zero: negative blue, positive brown (RdBu's red end read as undetected hazards)
ERROR_CMAP = "hh-error"
ERROR_COLOURS = ("#2166ac", "#f7f7f7", "#8c510a")
# 0 = pale (clear) .. the hazard's purple .. 1 = dark (unsafe): magma_r put red and orange, the undetected hazard's
# and the false alarm's colours, on hazard scores of 0.4-0.8 (QA 64b)
HAZARD_CMAP = "hh-hazard"
HAZARD_COLOURS = ("#f7f3e8", "#cdb3df", HAZARD, "#2a0d3a")
PSAFE_CMAP = "hh-psafe"  # 0 = the hazard's purple .. a pale khaki .. 1 = the safe green
PSAFE_COLOURS = (HAZARD, "#e9dc9a", SAFE)
# series of a chart (presets, policies): blue, brown, teal, navy, mustard; matplotlib's default cycle puts the
# undetected hazard's red fourth, the false alarm's orange second and the safe green third
SERIES_COLOURS = ("#4c78a8", "#9d755d", "#72b7b2", "#2f3e6e", "#b8a21f")


@dataclass(frozen=True)
class Term:
    label: str  # column header / axis label, unique across the glossary
    explanation: str
    unit: str = ""


GLOSSARY: dict[str, Term] = {
    "fp_pct": Term(
        "FP % (undetected hazard)",
        "Share of covered pixels that are truly unsafe but called safe. Table 2.1 of the thesis requires <= 1 %.",
        "%",
    ),
    "fn_pct": Term(
        "FN % (false alarm)",
        "Share of covered pixels that are truly safe but not called safe (unsafe or unknown).",
        "%",
    ),
    "tp_pct": Term("TP % (safe called safe)", "Share of covered pixels that are safe and called safe.", "%"),
    "tn_pct": Term(
        "TN % (hazard not called safe)",
        "Share of covered pixels that are unsafe and not called safe (unsafe or unknown).",
        "%",
    ),
    "cdi_pct": Term(
        "CDI % (correct detection)", "Correct detection index: TP % + TN %, the share of pixels called right.", "%"
    ),
    "hazards_detected_pct": Term(
        "hazards detected %", "TN / (TN + FP): of the truly unsafe pixels, the share not called safe.", "%"
    ),
    "safe_detected_pct": Term(
        "safe ground recognised %", "TP / (TP + FN): of the truly safe pixels, the share called safe.", "%"
    ),
    "hazards_in_scene_pct": Term(
        "hazards in scene %",
        "Share of the pixels whose true ground both frames see that are unsafe by the ground-truth rules "
        "(thesis Tables 6.1/6.8; a property of the scene, not of the flight software).",
        "%",
    ),
    "hazards_in_scored_pct": Term(
        "hazards in the scored area %",
        "Share of the scored pixels that are unsafe by the ground-truth rules: the most FP % could be. Every "
        "pixel whose true ground both frames see is scored, so it equals hazards in scene %.",
        "%",
    ),
    "valid_pct": Term(
        "DEM coverage %",
        "Share of the area the flight software takes as seen by both images (by its poses) that got an elevation; "
        "hazard-hil score's DEM coverage is over the true overlap instead (98.2 against 97.6 % on a 512 px "
        "vertical 600/300 pair, 96.5 against 95.5 % at 256 px; a QA pass saw 6 points apart on a small camera).",
        "%",
    ),
    "dem_mean_abs_m": Term("DEM mean |error| [m]", "Mean absolute elevation error over pixels with both values.", "m"),
    "dem_median_m": Term("DEM median error [m]", "Median of the signed elevation error (estimate - truth).", "m"),
    "dem_mad_m": Term(
        "DEM MAD [m]", "Median absolute deviation of the signed elevation error: its spread, blind to an offset.", "m"
    ),
    "dem_kurtosis": Term(
        "DEM error excess kurtosis",
        "Fourth standardised moment of the signed error minus 3 (0 for a normal distribution): heavy tails score "
        "high. Not comparable with the thesis's kurtosis column, which equals its skewness minus 3 (in every "
        "row but one).",
    ),
    "dem_skewness": Term("DEM error skewness", "Third standardised moment of the signed error."),
    "epi_fp_pct": Term(
        "FP % outside epipole box",
        "FP % over the pixels outside the thesis's 80 x 80 px box around the epipole (Table 6.7), where the "
        "plane sweep cannot resolve elevation.",
        "%",
    ),
    "epi_cdi_pct": Term("CDI % outside epipole box", "CDI % over the pixels outside the epipole box.", "%"),
    "e2e_latency_p50_s": Term(
        "e2e latency p50 [s]", "Median end-to-end latency over the pairs that returned a result.", "s"
    ),
    "e2e_latency_p95_s": Term("e2e latency p95 [s]", "95th percentile of the end-to-end latency.", "s"),
    "e2e_latency_s": Term(
        "end-to-end latency [s]",
        "From the moment the ground finished sending a pair's last frame to the moment it holds the whole Result.",
        "s",
    ),
    "flight_latency_s": Term(
        "flight latency [s]",
        "At the flight side: from the pair's last frame arriving to the Result handed to the link.",
        "s",
    ),
    "result_line_s": Term("result line time [s]", "Time the Result took on the link to reach the ground.", "s"),
    "deadline_verdict": Term(
        "deadline", "met when the end-to-end latency is within the deadline; a pair with no result missed it."
    ),
    "deadline_hit_rate": Term(
        "deadline hit rate", "Share of pairs whose Result reached the ground within the deadline."
    ),
    "top_site": Term(
        "top landing site",
        "The site the flight software ranked first, judged on the truth: clear when every pixel whose true ground "
        "lies within its 3 m footprint is safe; none offered when the Result says no site qualified (and why).",
    ),
    "outcome": Term(
        "outcome",
        "The Result's level (full, or the coarser level it stopped at), or the error. A level below full says why "
        "from the flight side's deadline plan: the time left when the DEM stage was due and the time kept for the "
        "work after it; (x5, ...) is the slowdown against this host at full speed that those times were planned at "
        "(the emulated processor's 1 / CPU fraction, raised to what the pair's first stages took, or measured on "
        "the previous pairs).",
    ),
    "pose_cell": Term(
        "pose refinement",
        "What the flight side's relative-pose refinement did, as its Telemetry said: refined (the images' pose "
        "replaced navigation's; the corrections applied: the relative rotation's, and the larger of the two "
        "frames' own attitudes), kept (the images agree with navigation), or why the images could not confirm the "
        "navigation poses, which the maps then rest on; – when the "
        "flight side did not say (an older flight side or one of your own, or a preset without refinement).",
    ),
    "results": Term("results", "Pairs that returned a Result (on time or late), of the pairs asked for."),
    "degraded": Term(
        "Results degraded", "Results at a coarser level, or at the full level with pipeline stages skipped."
    ),
    "p_safe": Term(
        "P(safe landing)",
        "Share of landings whose top-ranked site is truly safe over its whole 3 m footprint; a landing with no "
        "site is not safe.",
    ),
    "p_safe_ci95": Term("95 % interval", "Wilson score interval of P(safe landing)."),
    "p_no_site": Term("P(no site)", "Share of landings for which the flight software offered no site."),
    "p_unsafe": Term(
        "P(unsafe site)", "Share of landings whose top-ranked site is not clear over its whole 3 m footprint."
    ),
    "p_aim_safe": Term(
        "P(aim point safe)", "Share of landings whose aim point itself is clear: landing blind, without a detector."
    ),
    "n_landings": Term("landings", "Landings behind the row (each a drawn aim point, sun, image pair and pose error)."),
    "pairs": Term("pairs flown", "The descent pairs (scenario, altitudes) the scene's landings were flown at."),
    "divert_m": Term("divert [m]", "Distance from the aim point to the chosen site.", "m"),
}


for _what, _unit, _name in (("slope", "deg", "slope"), ("rough", "m", "roughness")):
    GLOSSARY[f"{_what}_mean_abs_{_unit}"] = Term(
        f"{_name} mean |error| [{_unit}]", f"Mean absolute {_name} error over covered pixels with both values.", _unit
    )
    GLOSSARY[f"{_what}_median_{_unit}"] = Term(
        f"{_name} median error [{_unit}]", f"Median of the signed {_name} error (estimate - truth).", _unit
    )
    GLOSSARY[f"{_what}_mad_{_unit}"] = Term(
        f"{_name} MAD [{_unit}]", f"Median absolute deviation of the signed {_name} error.", _unit
    )
# the thesis's Tables 6.4/6.11 also exclude the epipole box; each metric has an "outside epipole box" twin
for _key in ("fn_pct", "tp_pct", "tn_pct", "hazards_detected_pct", "safe_detected_pct"):
    GLOSSARY[f"epi_{_key}"] = Term(
        f"{GLOSSARY[_key].label} outside epipole box",
        f"{GLOSSARY[_key].label} over the pixels outside the 80 x 80 px box around the epipole.",
        GLOSSARY[_key].unit,
    )
GLOSSARY.update(
    {
        "site_fp_pct": Term(
            "site FP % (1.5 m radius at the median GSD)",
            "Share of candidate site centres called safe whose footprint disk is not truly safe. The disk is 1.5 m "
            "at the image's median ground sample: on an oblique view wider than 3 m in the far field.",
            "%",
        ),
        "site_cdi_pct": Term("site CDI %", "CDI computed on footprint disks (as site FP) instead of pixels.", "%"),
        "chosen_sites_safe_pct": Term(
            "chosen sites truly clear %",
            "Share of the offered sites whose footprint is truly clear; over the seeds that offered a site "
            "(seeds that offered a site).",
            "%",
        ),
        "chosen_sites_seeds": Term(
            "seeds that offered a site",
            "How many seeds offered at least one landing site: the chosen-sites figures are over these seeds only.",
            "",
        ),
        "pipeline_s": Term("pipeline time [s]", "Wall time of the flight pipeline for the pair on one core.", "s"),
        "fn_unmapped_pct": Term(
            "false alarm: outside the map %",
            "False alarms on ground both images see that the detector left unmapped (NaN): not called safe.",
            "%",
        ),
        "fn_dem_invalid_pct": Term("false alarm: no DEM %", "False alarms where no elevation was recovered.", "%"),
        "fn_rock_pct": Term("false alarm: rock %", "False alarms caused by a detected rock.", "%"),
        "fn_slope_pct": Term("false alarm: slope %", "False alarms caused by the estimated slope.", "%"),
        "fn_rough_pct": Term("false alarm: roughness %", "False alarms caused by the estimated roughness.", "%"),
        "fn_shadow_pct": Term("false alarm: shadow %", "False alarms caused by a detected shadow.", "%"),
        "fn_other_pct": Term("false alarm: other %", "False alarms with none of the causes above.", "%"),
        "fp_steep_pct": Term("undetected: true slope %", "Undetected hazards that are truly too steep.", "%"),
        "fp_rough_pct": Term("undetected: true roughness %", "Undetected hazards that are truly too rough.", "%"),
        "fp_other_pct": Term("undetected: true shadow %", "Undetected hazards that are truly in shadow.", "%"),
        "fp_in_epipole_box_pct": Term(
            "undetected in epipole box %", "Share of the undetected hazards inside the epipole box.", "%"
        ),
        "fp_near_threshold_pct": Term(
            "undetected near threshold %", "Share of the undetected hazards whose estimated hazard was >= 0.8.", "%"
        ),
        "altitude_m": Term(
            "altitude [m]", "The lower frame's altitude, as in the thesis tables (600/300 is its 300 m row).", "m"
        ),
        "kind": Term("error kind", "Which navigation error the sensitivity study injects (thesis sec 6.3)."),
        "preset": Term(
            "preset",
            "The flight software parameter preset: fast (flight v2, which refines the poses from the images "
            "first), fast_unrefined (fast taking the navigation poses as given), thesis (the thesis's method).",
        ),
        "n": Term("samples", "Number of Monte Carlo samples behind the row."),
        "median_rel_pct": Term(
            "DEM error increase, median %",
            "Median over samples of the DEM mean |error| with the injected error relative to without it, minus 100. "
            "Each preset against its own run on the true poses: fast's reference is refined from them too, so its "
            "rows and fast_unrefined's have different references.",
            "%",
        ),
        "max_rel_pct": Term("DEM error increase, worst %", "Largest DEM error increase over the samples.", "%"),
        "within_15pct": Term(
            "samples within +15 %",
            "Share of samples whose DEM error grew by at most 15 % (the thesis's tolerance).",
            "%",
        ),
        "n_no_dem": Term(
            "samples without a DEM", "Samples left out of the statistics: no DEM with the error, or none without it."
        ),
        "detrended_median_rel_pct": Term(
            "shape error increase, median %",
            "Median DEM error increase after removing the error's best plane (the tilt and datum shift a pose error "
            "leaves): what is left is the DEM's shape.",
            "%",
        ),
        "detrended_max_rel_pct": Term(
            "shape error increase, worst %", "Largest DEM error increase after removing the error's best plane.", "%"
        ),
        "thesis_median_rel_pct": Term(
            "thesis: DEM error increase %",
            "The thesis's own median DEM error increase for this study and altitude, where it has one.",
            "%",
        ),
        "near_diag_median_rel_pct": Term(
            "increase near dh1 = dh2, median %",
            "Median increase over samples whose two altitude errors differ <= 0.15 m.",
            "%",
        ),
        "off_diag_median_rel_pct": Term(
            "increase off dh1 = dh2, median %",
            "Median increase over samples whose altitude errors differ > 0.3 m.",
            "%",
        ),
        # the worst seed beside the median (studies.evaluate.WORST)
        "fp_pct_worst": Term(
            "FP % worst seed", "The highest FP % (undetected hazard) of any seed at this altitude.", "%"
        ),
        "cdi_pct_worst": Term("CDI % worst seed", "The lowest CDI % of any seed at this altitude.", "%"),
        "dem_mean_abs_m_worst": Term(
            "DEM mean abs err worst seed [m]", "The largest DEM mean absolute error of any seed at this altitude.", "m"
        ),
        "hazards_in_scene_pct_worst": Term(
            "hazards in scene % most hazardous seed",
            "The highest hazards in scene % of any seed at this altitude.",
            "%",
        ),
        "chosen_sites_safe_pct_worst": Term(
            "chosen sites truly clear % worst seed",
            "The lowest share of truly clear offered sites of any seed at this altitude.",
            "%",
        ),
    }
)


def term(key: str) -> Term:
    """The glossary entry of ``key``; an unknown key is its own label with no explanation."""
    if key in GLOSSARY:
        return GLOSSARY[key]
    # the attitude study's per-level columns (studies.evaluate.sensitivity_summary): rel_pct@+0.15 and the thesis's
    level = re.fullmatch(r"(thesis_)?rel_pct@([+-]\d+(?:\.\d+)?)", key)
    if level:
        who = "thesis: " if level.group(1) else ""
        return Term(
            f"{who}pitch {level.group(2)}°, DEM error increase %",
            f"Median DEM error increase of the samples whose pitch error was {level.group(2)} degrees"
            + (" in the thesis's attitude study." if level.group(1) else "."),
            "%",
        )
    return Term(key, "")
