"""What the flight process tells the ground of a pair beyond its maps: the pose refinement's outcome and warnings.

`process` says these from the pipeline's ``info`` on its console and in result.json; under the HIL they went
nowhere, so a run whose poses fell back to navigation, or whose altimeter disagreed with its images, looked like
any other (issue 10: "fall back to the navigation poses, saying so"; "pose-quality telemetry: inliers,
reprojection error, the correction applied"). The Telemetry carries them (revision 5, docs/protocol.md):

- :func:`pose_figures`: numbers only, for ``Telemetry.pose``;
- :func:`pose_verdict`: the refinement's outcome in one word (``flight_sw.pose_refine.VERDICTS``);
- :func:`pair_notes`: a few short sentences for ``Telemetry.notes``, the most telling first.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping, Sequence
from typing import Any

from .pose_refine import CHECK_MIN_SIDE, DEGENERATE, FEW_MATCHES, NO_OVERLAP, REPEATED, unchecked

# the refinement's figures the ground gets, under the short names it gets them by: they share a slow line with the
# next Result (these ten add ~190 B to a ~760 B Telemetry; result.json's names added 300 B); its time is in stages
_FIGURES = (
    ("inliers", "inliers"),
    ("reproj_rms_px", "reproj_rms_px"),
    ("relative_rotation_correction_deg", "rot_deg"),
    ("translation_dir_change_deg", "dir_deg"),
)
_AXES = ("x", "y", "z")


def _number(v: Any) -> float | None:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return None
    return float(v) if math.isfinite(v) else None


# the pipeline's words point `process` users to result.json; the HIL ground has the pair's Telemetry instead
_POINTERS = ((" (info.pose_refinement)", " (the pair's Telemetry: pose)"),)
# a pair's frames by their role: the flight process cannot name them by the ground's seqs (the HIL server forwards
# them renumbered), and the ground shows each note beside its pair's label
_FRAME = re.compile(r"\bframe ([01])\b")
_ROLES = ("the upper frame", "the lower frame")


def ground_words(text: str) -> str:
    """``text`` (words the pipeline wrote for `process`, of a pair run with the default frame numbers) as the HIL
    ground reads them: "frame 0" and "frame 1" become "the upper frame" and "the lower frame" (under the HIL server
    the flight process sees other seqs than the ground's), and pointers into result.json's ``info`` point to the
    pair's Telemetry."""
    for old, new in _POINTERS:
        text = text.replace(old, new)
    return _FRAME.sub(lambda m: _ROLES[int(m.group(1))], text)


def pose_figures(info: Mapping[str, Any]) -> dict[str, float | int]:
    """The relative-pose refinement's figures for ``Telemetry.pose`` ({} when none ran).

    ``applied`` is 1 when the images' pose replaced navigation's (verdict ``refined``), else 0: the other figures
    are then what the fit asked for, not what was applied. ``inliers`` and ``reproj_rms_px`` (px) are the fit's
    matches and their reprojection RMS, ``rot_deg`` the relative rotation's correction angle, ``rot_{x,y,z}_deg``
    its signed components about the lower frame's camera axes (R <- exp(w) R), ``att1_deg`` and ``att2_deg`` the
    upper (i1) and lower (i2) frame's own attitude corrections, ``dir_deg`` the baseline direction's change
    (flight_sw.pose_refine, module doc)."""
    pr = info.get("pose_refinement")
    if not isinstance(pr, Mapping):
        return {}
    out: dict[str, float | int] = {"applied": int(bool(pr.get("refined")))}
    for key, name in _FIGURES:
        v = _number(pr.get(key))
        if v is not None:
            out[name] = int(v) if key == "inliers" else v
    att = pr.get("rotation_correction_deg")  # each frame's own attitude: a pitch common to both moves no relative
    if isinstance(att, Sequence) and len(att) == 2:
        for k, c in zip((1, 2), att):
            v = _number(c)
            if v is not None:
                out[f"att{k}_deg"] = v
    vec = pr.get("relative_rotation_correction_vec_deg")
    if isinstance(vec, Sequence) and len(vec) == 3:
        for axis, c in zip(_AXES, vec):
            v = _number(c)
            if v is not None:
                out[f"rot_{axis}_deg"] = v
    return out


def pose_verdict(info: Mapping[str, Any]) -> str:
    """The refinement's outcome (``refined``, ``kept``, ``degenerate``, ...), or "" when none ran."""
    pr = info.get("pose_refinement")
    return str(pr.get("verdict") or "") if isinstance(pr, Mapping) else ""


def pair_notes(
    info: Mapping[str, Any],
    side: int,
    max_notes: int | None = None,
    max_chars: int | None = None,
) -> tuple[str, ...]:
    """The flight side's warnings on a pair of images ``side`` px a side (the smaller), at most ``max_notes`` of at
    most ``max_chars`` characters each (None: all of them, whole), in the ground's words (:func:`ground_words`).
    ``info`` is the pipeline's, run on the pair (upper frame 0, lower frame 1).

    In order: altimeter readings that were no range (``altimeter_readings_ignored``, the flight process's), sensors
    that disagree (the altimeter against the positions or the images), poses the images could not check, that they
    contradict, or whose geometry they cannot fix (the maps then rest on navigation's), and images that read blank
    or noisy. Each says its conclusion first and its figures last, so that a note cut at ``max_chars`` loses the
    figures. As `process` judges them: a refined or kept pose is no note (its figures are in :func:`pose_figures`),
    and below ``pose_refine.CHECK_MIN_SIDE`` px only a repeated image is, since there clean pairs fail the
    refinement's checks too. The pair's fit is of both frames: a fallback is not laid on the lower frame alone. Sites
    withheld for any of these are not repeated here: the Result's ``no_site_reason`` says it."""
    notes: list[str] = [str(n) for n in info.get("altimeter_readings_ignored", ())]
    if info.get("altimeter_disagreement"):
        notes.append(str(info["altimeter_disagreement"]))
    verdict = pose_verdict(info)
    if unchecked(verdict, side) or (verdict == DEGENERATE and side >= CHECK_MIN_SIDE):
        why = str(info["pose_refinement"].get("reason") or "no reason given")
        if verdict == REPEATED:
            notes.append(f"frame 1's image repeats another, so the images cannot check the poses; the maps rest on "
                         f"them as navigation reports them ({why})")  # fmt: skip
        elif verdict in (NO_OVERLAP, FEW_MATCHES):  # geometry or bland ground: nothing in the images is against them
            notes.append(f"the images could not check the pair's poses; the maps rest on them as navigation reports "
                         f"them ({verdict}: {why})")  # fmt: skip
        elif verdict == DEGENERATE:
            notes.append(f"the images matched but cannot fix the pair's poses; the maps rest on them as navigation "
                         f"reports them ({why})")  # fmt: skip
        else:  # unmatched, disagrees: evidence against them
            notes.append(f"the images contradict the pair's navigation poses, which the maps rest on ({verdict}: "
                         f"{why})")  # fmt: skip
    for kind, what in (("blank", "its pixel-scale detail"), ("noisy", "its pixel noise")):
        for f in info.get(f"{kind}_frames", ()):
            others = ", ".join(f"{v:.1f}" for v in f.get("others_dn", ()))
            notes.append(
                f"frame {f.get('frame')}'s image is {kind}: {what} reads {float(f.get('noise_dn', math.nan)):.1f} "
                f"grey levels against {others} in the other frame"
            )
    notes = [ground_words(n) for n in notes]
    if max_chars is not None:
        notes = [n if len(n) <= max_chars else n[: max_chars - 3] + "..." for n in notes]
    if max_notes is not None and len(notes) > max_notes:  # said, not dropped: the flight log has every note
        notes = [*notes[: max_notes - 1], f"{len(notes) - max_notes + 1} more notes in the flight log"]
    return tuple(notes)
