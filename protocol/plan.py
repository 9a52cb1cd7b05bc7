"""The Telemetry's ``plan`` (revision 4, docs/protocol.md section 5.4), read for people.

The flight side's deadline plan sends, per DEM stage it weighed, the time left at the stage's start
(``<stage>_left_s``), the time kept for the work after it (``<stage>_need_s``), optionally the least the stage
itself takes (``<stage>_min_s``), ``<stage>_started`` (1) for a stage that did start, and the slowdown these
were planned at (``scale``, ``measured``). Both the
ground (its progress lines, run tables and reports) and ``hazard-hil process --deadline`` say with
:func:`plan_note` why a Result stopped below the full level.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping

DEM_STAGES = ("coarse_dem", "full_dem")  # the stages whose plan figures say why a Result stopped at its level


def plan_note(plan: Mapping[str, float] | None, skipped: Iterable[str] | None) -> str:
    """Why a Result stopped below the full level; "" without such figures (an older flight side, a Result at the
    full level, a run without a deadline).

    For the first DEM stage that did not complete: the time left at its start against the time the plan kept for
    the mapping, fusion and output after it, and the slowdown that was planned at, e.g. "full_dem not started:
    3.1 s left, 38.0 s kept for the work after it (x254, from the first stages)"; or, with ``<stage>_min_s``, the
    least the stage takes, when the time between the two was shorter than that. A stage that started and still
    did not finish was cut at its own deadline (taken as such when the flight side does not say which started).
    Seconds are in hundredths when the time left and the time kept are both under 10 s. A stage reached past the
    deadline says so: "coarse_dem not started: the deadline had passed (0.07 s over) (x1, from the first stages)"."""
    plan = plan or {}
    skipped = set(skipped or ())
    for stage in DEM_STAGES:
        left, need = plan.get(f"{stage}_left_s"), plan.get(f"{stage}_need_s")
        if stage not in skipped or left is None or need is None:
            continue
        # in hundredths when both are below 10 s: at a 2 s deadline "1.0 s left, 1.0 s kept" said nothing
        digits = 2 if max(abs(left), abs(need)) < 10 else 1

        def sec(x: float, digits: int = digits) -> str:
            t = f"{x:.{digits}f}"
            return t[1:] if t.startswith("-") and float(t) == 0 else t  # "-0.00 s left" said nothing more

        how = "measured on the previous pairs" if plan.get("measured") else "from the first stages"
        scale = f" (x{plan['scale']:.0f}, {how})" if "scale" in plan else ""
        if left <= 0:  # "-0.07 s left" read as a fault in the figures (QA of stop 84)
            line = plan.get("line_s")
            if line is not None and left + line > 0:  # the deadline was ahead: the Result's line time took it all
                return (
                    f"{stage} not started: the Result's expected time on the line ({sec(line)} s) left no time for "
                    f"it before the deadline ({sec(-left)} s short){scale}"
                )
            return f"{stage} not started: the deadline had passed ({sec(-left)} s over){scale}"
        if left <= need:
            return f"{stage} not started: {sec(left)} s left, {sec(need)} s kept for the work after it{scale}"
        least = plan.get(f"{stage}_min_s")
        if least is not None and left - need < least:  # it would have been cut: not started
            return (
                f"{stage} not started: {sec(left - need)} s for it ({sec(left)} s left, {sec(need)} s kept after it"
                f"{scale}), and it takes at least {sec(least)} s"
            )
        if any(k.endswith("_started") for k in plan) and not plan.get(f"{stage}_started"):
            # a flight side that says which stages started, and not this one: left out for another reason
            return f"{stage} not started: {sec(left)} s left, {sec(need)} s kept for the work after it{scale}"
        return f"{stage} cut at its deadline: {sec(left)} s left at its start, {sec(need)} s kept after it{scale}"
    return ""
