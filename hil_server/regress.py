"""Latency and deadline regression: re-run fixed scenario x budget cases, compare to a baseline.

Latencies are the flight latency (last frame in at the HIL server -> Result
out of the flight process: the computation the budget's speed governs; the
deadline itself is judged end to end, link included, in the hit rate), stored
in *reference seconds*: ``flight_latency_s x effective_dmips / anchor_dmips``,
where ``effective_dmips`` is the speed the flight process actually had (the
budget's absolute speed when throttled, the calibrated host speed for
``host``) and the anchor is the reference machine of budgets.toml.
A throttled budget means the same absolute speed on any calibrated host, so
its reference seconds are comparable across machines; for ``host`` the factor
removes the host's own speed.

A regression is: deadline hit rate below the baseline's minus
``hit_rate_drop``, or a latency percentile above the baseline's by more than
``latency_rel`` (relative) and ``latency_abs_s`` (absolute, reference seconds,
so tiny latencies do not flap), or more degraded Results (``degraded``: cut to a coarser anytime
level or with stages skipped; they are faster because they did less) when the baseline records
that count, or another number of pairs than recorded (the case's workload changed), or a budget whose figures
changed since ``--update`` recorded them (``budget_recorded``), or a workload that did (``workload_recorded``: the
scenario, pairs, seed, image size, manifest and its digest, deadline and flight side). ``--update`` rewrites the
baseline and records what its numbers rest on (``recorded``: the host's calibration and load; a partial
``--update --cases`` keeps the other cases' sessions under ``recorded.earlier``); it refuses to rewrite the shipped
baseline on an uncalibrated host, and says so when the host is
uncalibrated, stale (``budgets.STALE_CALIBRATION_DAYS``) or loaded. The baseline
file is checked before anything runs: a malformed one is a one-line error.

An unthrottled case (``host``, or a budget of one's own with ``cpu_dmips = "host"``) is judged on the flight
process's CPU seconds per pair, not on wall latency: on a busy host the wall clock of an unthrottled
process measures the other load, not the flight software. Throttled budgets
are judged on latency (the emulator's duty cycle sets their wall time).

A case with ``"flight": "external"`` runs against a board of one's own serving ``hazard-hil flight``
(:mod:`flight_sw.board`) on the case's ``link`` spec, or ``--link``'s; its ``budget`` gives only the
deadline (``deadline_s`` overrides it). Its latencies are the board's own seconds (scale 1): such a
baseline holds for that board only, and is judged on latency like a throttled budget, and also on the end-to-end
latency the ground measures (``e2e_latency_p50_s``, ``e2e_latency_max_s``: the board's own Telemetry may report
no compute time at all, and a slower Result line is no compute).

The baseline shipped with the package (:func:`default_baseline_path`) is used
unless another is given; relative ``manifest`` paths in a baseline are
relative to the baseline file.

Exit codes (``hazard-hil regress``): 0 when no case regressed and every pair of
every case met its deadline end to end (``--min-hit-rate`` relaxes the latter);
1 otherwise (also after ``--update``, which writes the baseline either way, when
a pair missed); 2 on bad usage (missing baseline, unknown case, a case `run` would refuse: every case is
checked before the first runs); 128 + N when signal N cut a case short (no later case runs, the baseline
is not written).
"""

from __future__ import annotations

import hashlib
import json
import math
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from hil_server.budgets import BUDGET_FIGURES
from hil_server.run import CONTENTION_SHOWN_PCT
from reports.console import apart

if TYPE_CHECKING:
    from hil_server.run import RunConfig

# The absolute term keeps tiny latencies from flapping; at 0.25 reference s it dominated every shipped case (the host
# case could grow +95 %, a 256 px snapdragon801 case 4x, before it was flagged: stop 56's budget QA). At 0.1 the
# 35 % governs the shipped cases (host: +38 %).
DEFAULT_TOLERANCES = {"hit_rate_drop": 0.0, "latency_rel": 0.35, "latency_abs_s": 0.1}


def _near_baseline(path: Path) -> Path | None:
    """The JSON file beside ``path`` whose name is closest to its name (difflib's ratio >= 0.8), if any."""
    import difflib

    try:
        names = [p.name for p in path.parent.glob("*.json") if p.is_file()]
    except OSError:
        return None
    near = difflib.get_close_matches(path.name, names, n=1, cutoff=0.8)
    return path.parent / near[0] if near else None


# The cases `regress` runs when the baseline does not exist yet (`--update`).
DEFAULT_CASES: dict[str, dict] = {
    "vertical-host-zmq": {"scenario": "vertical", "budget": "host", "link": "zmq", "pairs": ["600/300", "300/150"]},
    "vertical-snapdragon-serial": {
        "scenario": "vertical",
        "budget": "snapdragon801",
        "link": "serial",
        "pairs": ["600/300", "300/150"],
    },
    # 40 s, not the budget's 30: at 30 the case failed 1 run in 3 (docs/BENCHMARKS.md, stop 64); a baseline recorded
    # into a new file had the 30 s the shipped one left behind (QA of stop 84)
    "approach-rad750-serial": {
        "scenario": "approach",
        "budget": "rad750",
        "link": "serial",
        "pairs": ["500/250"],
        "deadline_s": 40.0,
    },
}
# the flight latency (summary["flight_latency_*_s"]) in reference seconds; the names predate the end-to-end deadline
LATENCY_METRICS = ("latency_p50_ref_s", "latency_p95_ref_s", "latency_max_ref_s")
CPU_METRICS = ("cpu_p50_ref_s", "cpu_p95_ref_s", "cpu_max_ref_s")
# a board's end-to-end latency, measured at the ground, in seconds: its own Telemetry's compute time alone let a
# 12x slower end to end pass (0.044 -> 0.53 s), and a board that reports none has a baseline of 0 (stop 57's QA)
E2E_METRICS = ("e2e_latency_p50_s", "e2e_latency_max_s")


def default_baseline_path() -> Path:
    """The latency baseline shipped with the package (recorded on a quiet, calibrated host)."""
    return Path(__file__).with_name("latency_baseline.json")


def judged_metrics(budget: str, flight: str = "emulated", unthrottled: bool | None = None) -> tuple[str, ...]:
    """CPU seconds for an unthrottled budget (``host``, or a user's with ``cpu_dmips = "host"``: ``unthrottled``),
    latency for throttled ones, and for a board its own latency and the end-to-end latency the ground measured
    (module doc). An emulated case's end-to-end latency is recorded, not judged: it holds the case's own line time,
    and the deadline hit rate judges it already."""
    if flight == "external":
        return LATENCY_METRICS + E2E_METRICS
    if unthrottled is None:
        unthrottled = budget == "host"
    return CPU_METRICS if unthrottled else LATENCY_METRICS


def is_board(case: dict) -> bool:
    """A case run against a flight computer of one's own (``"flight": "external"``) rather than the emulation."""
    return case.get("flight", "emulated") == "external"


@dataclass
class CaseOutcome:
    name: str
    current: dict
    baseline: dict | None
    problems: list[str] = field(default_factory=list)
    metrics: tuple[str, ...] = LATENCY_METRICS
    limits: dict[str, float] = field(default_factory=dict)  # the bound each metric was held to
    recorded: bool = False  # --update: nothing was judged, the current values were written as the baseline
    below_required: bool = False  # its hit rate is under the one the run requires (--min-hit-rate, else every pair)
    previous: dict | None = None  # --update: the metrics it replaces, shown beside the new ones
    loose: list[str] = field(default_factory=list)  # metrics whose limit is at least twice the baseline
    unwritten: str = ""  # --update: measured, and the baseline left unchanged (why: interrupted, refused)
    contention_pct: float | None = None  # the share of its flight time the flight process waited for its core


def effective_speed(budget_name: str, budget_file: Path | None = None) -> tuple[float, float]:
    """(DMIPS the flight process had, the anchor's DMIPS): see budgets.toml for the unit."""
    import warnings

    from hil_server.budgets import UncalibratedWarning, get_budget, load_calibration

    b = get_budget(budget_name, budget_file)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UncalibratedWarning)  # the run itself already warned
        cal = load_calibration()
        host = b.host_dmips(cal)
        return host * b.effective_fraction(cal), b.anchor.dmips


def _pct(values: list[float], q: float) -> float:
    import numpy as np

    return float(np.percentile(values, q)) if values else math.nan


def _path(value: str | None, base_dir: Path | None) -> Path | None:
    """A case's path, relative to the baseline file's directory unless absolute."""
    if not value:
        return None
    p = Path(value)
    return base_dir / p if not p.is_absolute() and base_dir is not None else p


class RegressInterrupted(Exception):
    """A signal cut a case short: regress stops there (exit 128 + N), the cases after it are not run."""

    def __init__(self, signum: int, case: str) -> None:
        import signal

        super().__init__(f"interrupted by {signal.Signals(signum).name} during case {case}")
        self.signum = signum
        self.finished = ""  # the diff table of the cases that had finished (said, not lost: QA of stop 66)
        self.rows: list[dict] = []  # and their rows, for OUT/regress.json


def case_config(
    name: str,
    case: dict,
    out: Path,
    base_dir: Path | None = None,
    hello_timeout_s: float | None = None,
    figures: bool = True,
) -> RunConfig:
    """The :class:`hil_server.run.RunConfig` a case runs with (``figures``: its report.html's pictures)."""
    from hil_server.run import RunConfig

    manifest = _path(case.get("manifest"), base_dir)
    return RunConfig(
        scenario=case["scenario"],
        link=case["link"],
        budget=case["budget"],
        budget_file=_path(case.get("budget_file"), base_dir),
        out=out / name,
        pairs=case.get("pairs"),
        seed=int(case.get("seed", 0)),
        image_size=case.get("image_size"),
        manifest=manifest,
        flight=case.get("flight", "emulated"),
        keys=_path(case.get("keys"), base_dir),
        deadline_s=case.get("deadline_s"),
        hello_timeout_s=hello_timeout_s,
        figures=figures,
    )


def check_cases(
    names: list[str], cases: dict[str, dict], out: Path, base_dir: Path | None, hello: float | None
) -> None:
    """Every case's run options checked as `run` checks its own (link, memory ceiling, scenario, pairs), before
    the first case runs: a bad later case used to be found after the earlier ones had run, and their results lost."""
    from hil_server.budgets import check_runnable, load_calibration
    from hil_server.run import check_run_config
    from protocol.errors import InputError
    from protocol.outdir import refuse_if_held

    cal = None
    for n in names:
        try:
            where = out / n  # each case's run claims it: a file there, or a command holding it, ended regress after
            if where.exists() and not where.is_dir():  # the cases before it had run (QA 66a)
                raise InputError(f"its output {where} is a file, not a directory")
            if where.is_dir():
                refuse_if_held(where, "its output")
            checked = check_run_config(case_config(n, cases[n], out, base_dir, hello))
            if checked.cfg.flight == "emulated" and not checked.budget.is_host:  # too slow to emulate: now, too
                cal = cal if cal is not None else load_calibration()
                check_runnable(checked.cfg.budget, checked.budget, checked.budget.duty(cal))
        except InputError as exc:
            raise InputError(f"case {n!r}: {exc}") from None


def measure_case(name: str, case: dict, cfg: RunConfig) -> dict:
    """Run ``case`` as ``cfg`` (:func:`case_config`) says; its metrics, in reference seconds."""
    from hil_server.run import LATE_SIGNAL, run_descent

    summary = run_descent(cfg, log=lambda s: print(s, file=sys.stderr))
    stop = summary.get("interrupted_by") or summary.get(LATE_SIGNAL)
    if stop:  # Ctrl-C or a cancelled CI job: not a regression, and nothing more runs
        raise RegressInterrupted(int(stop), name)
    # a board's seconds are its own: no emulated speed to take out (its baseline holds for that board only)
    speed, ref = (1.0, 1.0) if is_board(case) else effective_speed(case["budget"], cfg.budget_file)
    scale = speed / ref
    cur = {
        # not a metric: the run's own reason when it did not finish (a board that never answered read as a latency
        # regression, its reason only in the captured stderr); taken out before the baseline is written
        "incomplete_reason": None if summary.get("complete", True) else str(summary.get("reason") or "unknown"),
        "deadline_hit_rate": summary["deadline_hit_rate"],
        "errors": summary["errors"],
        "pairs": summary["pairs"],
        # Results the flight software cut short (a coarser anytime level or stages skipped): faster, not better
        "degraded": int(summary.get("degraded") or 0),
        # not a metric either: the share of the flight time its process waited for its core (the host's load)
        "contention_pct": summary.get("flight_contention_pct"),
    }
    for m in LATENCY_METRICS:
        cur[m] = summary["flight_" + m.replace("_ref_s", "_s")] * scale
    cur["e2e_latency_max_s"] = summary["e2e_latency_max_s"]  # seconds on this host and link: judged for a board
    cur["e2e_latency_p50_s"] = summary["e2e_latency_p50_s"]
    cpu = [
        float(r["stages"]["total"]["cpu_s"])
        for r in summary["records"]
        if r.get("status") == "result" and "total" in (r.get("stages") or {})
    ]
    for m, q in zip(CPU_METRICS, (50, 95, 100)):
        cur[m] = _pct(cpu, q) * scale
    return cur


def compare(
    name: str, cur: dict, base: dict | None, tol: dict, metrics: tuple[str, ...] = LATENCY_METRICS
) -> CaseOutcome:
    o = CaseOutcome(name, cur, base, metrics=metrics)
    if base is None:
        o.problems.append("no baseline for this case (run with --update)")
        return o
    if cur["deadline_hit_rate"] < base["deadline_hit_rate"] - tol["hit_rate_drop"] - 1e-9:
        rate, base_rate = apart(cur["deadline_hit_rate"], base["deadline_hit_rate"])
        o.problems.append(f"deadline hit rate {rate} < baseline {base_rate}")
    if cur.get("errors", 0) > base.get("errors", 0):
        o.problems.append(f"errors {cur['errors']} > baseline {base.get('errors', 0)}")
    if "pairs" in base and cur.get("pairs") != base["pairs"]:  # half the workload passed as a whole (QA 66a)
        o.problems.append(
            f"pairs: {cur.get('pairs')} ran, the baseline recorded {base['pairs']} (the case's workload changed: "
            "record it again with --update)"
        )
    o.limits["deadline_hit_rate"] = base["deadline_hit_rate"] - tol["hit_rate_drop"]
    o.limits["errors"] = base.get("errors", 0)
    if "pairs" in base:
        o.limits["pairs"] = base["pairs"]
    if "degraded" in base:  # baselines recorded before the count was kept cannot judge it (diff_table says so)
        o.limits["degraded"] = base["degraded"]
        if cur.get("degraded", 0) > base["degraded"]:
            o.problems.append(
                f"degraded {cur['degraded']} > baseline {base['degraded']} (Results at a coarser level or with "
                "stages skipped; their latency is lower because they did less)"
            )
    for k in metrics:
        c, b = cur.get(k, math.nan), base.get(k, math.nan)
        if math.isnan(b):
            continue
        limit = max(b * (1 + tol["latency_rel"]), b + tol["latency_abs_s"])
        o.limits[k] = limit
        if limit >= 2.0 * b:  # a fast case: the absolute tolerance lets it double unseen (QA of stop 73)
            o.loose.append(k)
        if math.isnan(c) or c > limit:
            shown, limit_shown = apart(c, limit, 3)
            o.problems.append(f"{k} {shown} > limit {limit_shown} (baseline {b:.3f})")
    return o


COUNTS = ("degraded", "errors", "pairs")  # the table's whole-number rows


def _table_keys(o: CaseOutcome) -> list[str]:
    """The rows of case outcome ``o`` in the diff table and regress.json: the hit rate, the counts (errors and
    the pair count were judged but shown nowhere, QA of stop 80), then its judged metrics."""
    return ["deadline_hit_rate", *COUNTS, *o.metrics]


def _fmt(metric: str) -> str:
    return "d" if metric in COUNTS else ".3f"


def _about(problem: str, metric: str) -> bool:
    """Whether a problem text is about ``metric`` (the hit rate's says "deadline hit rate", with spaces)."""
    return problem.startswith((metric, metric.replace("_", " ")))


def _change(was: Any, now: Any, fmt: str) -> str:
    """``was`` and the relative change to ``now``, for an --update's table."""
    try:
        w, n = float(was), float(now)
    except (TypeError, ValueError):
        return str(was)
    if not (math.isfinite(w) and math.isfinite(n)):
        return f"{w:{fmt}}" if math.isfinite(w) else "–"
    head = f"{int(w):d}" if fmt == "d" else f"{w:{fmt}}"
    return head + (f", {100.0 * (n - w) / w:+.0f} %" if w else "")


def _metric_verdict(o: CaseOutcome, k: str) -> str:
    """The verdict of metric ``k`` of case outcome ``o``, as the diff table and regress.json say it."""
    c = o.current.get(k, math.nan)
    fmt = _fmt(k)
    bad = any(_about(p, k) for p in o.problems)
    verdict = "REGRESSION" if bad else "ok"
    if o.baseline is not None and k not in o.baseline:
        verdict = "not judged: not in the baseline (record it with --update)"
    # a hit rate under the one required read "ok" beside a FAIL, even as an --update recorded it (QA 71)
    missed = k == "deadline_hit_rate" and o.below_required
    if o.unwritten:
        verdict = f"measured; not recorded ({o.unwritten})"
    elif o.recorded:
        verdict = "recorded" + ("; deadlines missed (below the hit rate required)" if missed else "")
        if o.previous is not None and k in o.previous:  # what the update replaces, and by how much
            verdict += f" (was {_change(o.previous[k], c, fmt)})"
    elif missed and not bad:
        verdict = "deadlines missed (below the hit rate required)"
    elif k in o.loose and not bad:
        # the factor, not "double": a 0.003 s baseline held to 0.103 s may grow 34x (QA of stop 80)
        b, lim = (o.baseline or {}).get(k, math.nan), o.limits.get(k, math.nan)
        grow = f"grow {lim / b:.0f}x" if b > 0 and math.isfinite(lim) else "at least double"
        verdict = f"ok (loosely: the absolute tolerance lets it {grow})"
    return verdict


def diff_table(outcomes: list[CaseOutcome]) -> str:
    """One line per case and metric: baseline, the limit it was held to, the current value, the verdict.

    The hit rate's limit is a floor; every other limit is a ceiling.
    """
    lines = [f"{'case':<30} {'metric':<22} {'baseline':>10} {'limit':>10} {'current':>10}  verdict"]
    for o in outcomes:
        keys = _table_keys(o)
        for k in keys:
            b = (o.baseline or {}).get(k, math.nan)
            c = o.current.get(k, math.nan)
            lim = o.limits.get(k, math.nan)
            fmt = _fmt(k)
            bound = {"deadline_hit_rate": "≥", "pairs": "="}.get(k, "≤") + f"{lim:{fmt}}" if math.isfinite(lim) else "–"
            b_txt = f"{b:>10{fmt}}" if isinstance(b, int) or math.isfinite(b) else f"{'–':>10}"
            c_txt = f"{c:>10{fmt}}" if isinstance(c, int) or math.isfinite(c) else f"{'–':>10}"
            lines.append(f"{o.name:<30} {k:<22} {b_txt} {bound:>10} {c_txt}  {_metric_verdict(o, k)}")
        for p in o.problems:  # a changed pair count's says what to do about it: kept below its row
            if not any(_about(p, k) for k in keys if k != "pairs"):
                lines.append(f"{o.name:<30} {p}")
        if o.contention_pct is not None and o.contention_pct >= CONTENTION_SHOWN_PCT:
            # a loaded host read exactly as a slower program, its load warning taken before the run (QA of stop 73)
            lines.append(
                f"{o.name:<30} note: its flight process waited {o.contention_pct:.0f} % of its flight time for its "
                "core, which other processes held: a latency over its limit here may be the host's load"
            )
    return "\n".join(lines)


CASE_KEYS = frozenset(
    {
        "scenario",
        "budget",
        "budget_file",
        "link",
        "pairs",
        "seed",
        "image_size",
        "manifest",
        "metrics",
        "flight",
        "keys",
        "deadline_s",
        "budget_recorded",
        "workload_recorded",
        "min_hit_rate",
    }
)
DOC_KEYS = frozenset({"cases", "tolerances", "note", "recorded"})


def validate_baseline(doc: object, where: str, base_dir: Path | None = None) -> None:
    """Refuse, before anything runs, a baseline that is not what ``--update`` writes: one line naming the field.

    A hand-edited baseline that slipped through would otherwise fail with a traceback after minutes of runs,
    or (an empty ``cases``) silently run the default cases instead of the ones asked for.
    """
    from hil_server.budgets import deadline_problem, load_budgets
    from protocol.errors import InputError
    from protocol.pairdir import IMAGE_SIZE_MAX, IMAGE_SIZE_MIN

    def bad(what: str) -> InputError:
        return InputError(f"latency baseline {where}: {what}")

    def number(v: object) -> bool:
        return not isinstance(v, bool) and isinstance(v, (int, float)) and math.isfinite(v)

    if not isinstance(doc, dict):
        raise bad(f"expected a JSON object with 'cases', got {type(doc).__name__}")
    unknown = sorted(set(doc) - DOC_KEYS)
    if unknown:
        raise bad(f"unknown key(s) {', '.join(unknown)}; a baseline has {', '.join(sorted(DOC_KEYS))}")
    tol = doc.get("tolerances", {})
    if not isinstance(tol, dict):
        raise bad("'tolerances' must be an object")
    for k, v in tol.items():
        if k not in DEFAULT_TOLERANCES:
            raise bad(f"unknown tolerance {k!r}; known: {', '.join(sorted(DEFAULT_TOLERANCES))}")
        if not number(v) or v < 0 or (k == "hit_rate_drop" and v > 1):
            raise bad(f"tolerance {k!r} must be a number >= 0{' and <= 1' if k == 'hit_rate_drop' else ''}, got {v!r}")
    cases = doc.get("cases")
    if not isinstance(cases, dict) or not cases:
        raise bad("'cases' must be a non-empty object of named cases")
    budgets = load_budgets()
    for name, case in cases.items():
        w = f"case {name!r}"
        # a case's name names its output directory under --out and a row of the diff table
        if not (0 < len(name) <= 100 and name.isprintable() and name not in (".", "..") and not set(name) & set("/\\")):
            raise bad(f"{w}: a case name is 1-100 printable characters without '/' or '\\' (it names a directory)")
        if not isinstance(case, dict):
            raise bad(f"{w} must be an object")
        unknown = sorted(set(case) - CASE_KEYS)
        if unknown:
            raise bad(f"{w}: unknown key(s) {', '.join(unknown)}; a case has {', '.join(sorted(CASE_KEYS))}")
        for k in ("scenario", "budget", "link"):
            if not isinstance(case.get(k), str) or not case[k]:
                raise bad(f"{w}: {k!r} must be a non-empty string, got {case.get(k)!r}")
        own = case.get("budget_file")
        if own is not None and (not isinstance(own, str) or not own):
            raise bad(f"{w}: 'budget_file' must be a non-empty path, got {own!r}")
        # a budget of one's own comes from its file (relative to the baseline), as `run --budget-file` takes it
        choices = budgets if own is None else _own_budgets(_path(own, base_dir), w, bad)
        if case["budget"] not in choices:
            where_from = "" if own is None else f" in {own}"
            raise bad(f"{w}: unknown budget {case['budget']!r}{where_from}; choose one of: {', '.join(choices)}")
        if case.get("flight", "emulated") not in ("emulated", "external"):
            raise bad(f"{w}: 'flight' must be 'emulated' or 'external' (a board of one's own), got {case['flight']!r}")
        if is_board(case) and not case["link"].startswith(("serial:", "zmq:")):
            raise bad(f"{w}: a board's 'link' is serial:DEVICE[@BAUD] or zmq:ENDPOINT, got {case['link']!r}")
        if "keys" in case and (not isinstance(case["keys"], str) or not case["keys"]):
            raise bad(f"{w}: 'keys' must be a non-empty path, got {case['keys']!r}")
        if "deadline_s" in case and (why := deadline_problem(case["deadline_s"])):
            raise bad(f"{w}: 'deadline_s' (as `run --deadline`) {why}")
        rec = case.get("budget_recorded")
        if rec is not None and (not isinstance(rec, dict) or set(rec) - set(BUDGET_FIGURES)):
            raise bad(f"{w}: 'budget_recorded' is what --update writes: an object of {', '.join(BUDGET_FIGURES)}")
        work = case.get("workload_recorded")
        if work is not None and (not isinstance(work, dict) or set(work) - WORKLOAD_KEYS):
            raise bad(
                f"{w}: 'workload_recorded' is what --update writes: an object of {', '.join(sorted(WORKLOAD_KEYS))}"
            )
        mhr = case.get("min_hit_rate")
        if mhr is not None and (not number(mhr) or not 0.0 <= mhr <= 1.0):
            raise bad(f"{w}: 'min_hit_rate' (as --min-hit-rate) must be a number in [0, 1], got {mhr!r}")
        if "seed" in case and (isinstance(case["seed"], bool) or not isinstance(case["seed"], int) or case["seed"] < 0):
            raise bad(f"{w}: 'seed' must be an integer >= 0, got {case['seed']!r}")
        size = case.get("image_size")
        if size is not None and (
            isinstance(size, bool) or not isinstance(size, int) or not IMAGE_SIZE_MIN <= size <= IMAGE_SIZE_MAX
        ):
            raise bad(
                f"{w}: 'image_size' must be an integer number of pixels in {IMAGE_SIZE_MIN}..{IMAGE_SIZE_MAX}, "
                f"got {size!r}"
            )
        if "manifest" in case and (not isinstance(case["manifest"], str) or not case["manifest"]):
            raise bad(f"{w}: 'manifest' must be a non-empty path, got {case['manifest']!r}")
        pairs = case.get("pairs")
        if pairs is not None and (
            not isinstance(pairs, list) or not pairs or not all(isinstance(x, str) and x for x in pairs)
        ):
            raise bad(f"{w}: 'pairs' must be a non-empty list of pair labels, got {pairs!r}")
        metrics = case.get("metrics")
        if metrics is None:
            continue
        if not isinstance(metrics, dict):
            raise bad(f"{w}: 'metrics' must be an object")
        if "deadline_hit_rate" not in metrics:
            raise bad(f"{w}: 'metrics' has no 'deadline_hit_rate'")
        for k, v in metrics.items():
            if k in ("errors", "pairs", "degraded"):
                if isinstance(v, bool) or not isinstance(v, int) or v < 0:
                    raise bad(f"{w}: metric {k!r} must be a whole number >= 0, got {v!r}")
            elif k == "deadline_hit_rate" and not (number(v) and 0 <= v <= 1):
                raise bad(f"{w}: metric 'deadline_hit_rate' is a share of pairs in [0, 1], got {v!r}")
            elif not number(v) or v < 0:
                raise bad(f"{w}: metric {k!r} must be a finite number >= 0, got {v!r}")


def _own_budgets(path: Path | None, w: str, bad) -> dict:
    from hil_server.budgets import BudgetError, load_budgets

    try:
        return load_budgets(path)
    except BudgetError as exc:
        raise bad(f"{w}: {exc}") from None


def budget_record(case: dict, base_dir: Path | None) -> dict:
    """The figures of a case's budget (:data:`hil_server.budgets.BUDGET_FIGURES`), from its file or the shipped
    ones: what it stood for when its metrics were recorded (``budget_recorded``, written by ``--update``). A board
    file edited since (2760 -> 400 DMIPS) read exactly as before, latencies being in reference seconds."""
    from hil_server.budgets import get_budget

    b = get_budget(case["budget"], _path(case.get("budget_file"), base_dir))
    return {k: getattr(b, k) for k in BUDGET_FIGURES}


# what a case's latencies were measured on, with the value a case that leaves the key out runs with
WORKLOAD_DEFAULTS: dict[str, Any] = {
    "scenario": None,
    "pairs": None,
    "seed": 0,
    "image_size": None,
    "manifest": None,
    "deadline_s": None,
    "flight": "emulated",
}
WORKLOAD_KEYS = frozenset({*WORKLOAD_DEFAULTS, "manifest_sha256", "scenario_sha256"})


def workload_record(case: dict, base_dir: Path | None) -> dict:
    """What a case runs (``workload_recorded``, written by ``--update``): its scenario, pairs, seed, image size,
    manifest (with the first 16 hex digits of its manifest.json's SHA-256), deadline and flight side. Only the pair
    count was compared: a case moved to another scenario, seed or image size passed against latencies measured on
    the old one (QA of stop 78)."""
    rec = {k: case.get(k, d) for k, d in WORKLOAD_DEFAULTS.items()}
    m = _path(case.get("manifest"), base_dir)
    if m is not None:
        rec["manifest_sha256"] = _digest(m / "manifest.json" if m.is_dir() else m)
    scenario = str(case.get("scenario"))
    if scenario not in ("vertical", "approach"):  # a trajectory file (as `run` takes it): edited under one name
        rec["scenario_sha256"] = _digest(Path(scenario))
    return rec


def _digest(path: Path) -> str | None:
    """The first 16 hex digits of ``path``'s SHA-256 (None when it cannot be read)."""
    try:
        return hashlib.sha256(path.read_bytes()).hexdigest()[:16]
    except OSError:
        return None


def _moved(old: dict, new: dict, defaults: dict) -> list[str]:
    """'key old -> new' for each of ``new``'s keys whose value differs from ``old``'s (``defaults``' where ``old``
    leaves it out)."""
    return [f"{k} {old.get(k, defaults.get(k))!r} -> {v!r}" for k, v in new.items() if old.get(k, defaults.get(k)) != v]


def workload_change(case: dict, base_dir: Path | None) -> str:
    """'the case's workload changed since the baseline (scenario 'vertical' -> 'approach')', or '' (unchanged, or
    not recorded: baselines written before stop 78 are judged on their pair count alone)."""
    old = case.get("workload_recorded")
    if not isinstance(old, dict):
        return ""
    moved = _moved(old, workload_record(case, base_dir), WORKLOAD_DEFAULTS)
    if not moved:
        return ""
    return (
        f"the case's workload changed since the baseline ({', '.join(moved)}): its latencies were measured on "
        "another; re-record the case with --update"
    )


def budget_change(case: dict, base_dir: Path | None) -> str:
    """'budget X changed since the baseline (cpu_dmips 2760 -> 400)', or '' (unchanged, or not recorded)."""
    old = case.get("budget_recorded")
    if not old:
        return ""
    new = budget_record(case, base_dir)
    moved = _moved(old, new, {})
    if not moved:
        return ""
    # only the processor's speed changes the computer; a deadline, memory or line changes what it is asked to do
    # (a deadline of 1.0 -> 0.3 s was blamed on "the same computer", QA of stop 80)
    why = (
        "its reference seconds no longer measure the same computer"
        if any(m.startswith("cpu_dmips ") for m in moved)
        else "the case no longer asks the same of it"
    )
    return f"budget {case['budget']} changed since the baseline ({', '.join(moved)}): {why}; re-record it with --update"


def host_conditions() -> tuple[dict, list[str]]:
    """What this host's numbers rest on (its calibration, its load) and, for people, what is wrong with it."""
    import os

    from hil_server.budgets import calibration_notes, host_load_note, load_calibration

    cal = load_calibration()
    notes = calibration_notes(cal)
    cond: dict = {"calibration": None}
    if cal is not None:
        cond["calibration"] = {"key": cal.key, "measured_at": cal.measured_at, "units_per_s": cal.units_per_s}
    try:
        cond["load_1min"] = round(os.getloadavg()[0], 2)
        cond["cpus"] = os.cpu_count() or 1
    except OSError:
        pass
    if note := host_load_note():  # the one rule `run` warns by
        notes.append(note)
    return cond, notes


def _records(recorded: object) -> list[dict]:
    """The recording sessions of a baseline's ``recorded`` block, newest first: the block itself, then its
    ``earlier`` ones (a partial ``--update`` keeps the sessions of the cases it did not run)."""
    if not isinstance(recorded, dict):
        return []
    earlier = recorded.get("earlier")
    return [recorded] + [r for r in (earlier if isinstance(earlier, list) else []) if isinstance(r, dict)]


def _recorded_calibration(doc: dict, name: str) -> dict | None:
    """The calibration the host that recorded case ``name`` had (a session without a ``cases`` list recorded
    every case: baselines from before it was kept)."""
    for rec in _records(doc.get("recorded")):
        cases = rec.get("cases")
        if not isinstance(cases, list) or name in cases:
            cal = rec.get("calibration")
            return cal if isinstance(cal, dict) else None
    return None


CALIBRATION_MOVED = 0.10  # a same-host calibration this far from the baseline's is said


def _calibration_moved(doc: dict, names: list[str], now_cal: dict) -> str:
    """Said when this host was calibrated again since cases ``names`` were recorded on it and its speed moved by
    more than :data:`CALIBRATION_MOVED` ("" otherwise): the emulated budgets' duty cycles rest on it."""
    now = now_cal.get("units_per_s")
    if not isinstance(now, (int, float)) or not now > 0:
        return ""
    then = {
        float(c["units_per_s"])
        for n in names
        if isinstance(c := _recorded_calibration(doc, n), dict)
        and c.get("key") == now_cal.get("key")
        and isinstance(c.get("units_per_s"), (int, float))
        and c["units_per_s"] > 0
    }
    far = sorted(u for u in then if abs(now / u - 1.0) > CALIBRATION_MOVED)
    if not far:
        return ""
    was = ", ".join(f"{u:.1f}" for u in far)
    return (
        f"this host's calibration reads {now:.1f} units/s, and the baseline was recorded under {was}: the emulated "
        "budgets' duty cycles and the reference seconds are set from it, so latencies and degraded counts move "
        "with it, not with the flight software (record the baseline again with --update if the new one stands)"
    )


def _earlier_records(recorded: object, names: list[str], all_cases: dict) -> list[dict]:
    """The sessions behind the cases a partial ``--update`` did not re-record, each with only those cases."""
    out, done = [], set(names)
    for rec in _records(recorded):
        cases = rec.get("cases")
        left = [n for n in (cases if isinstance(cases, list) else list(all_cases)) if n in all_cases and n not in done]
        if left:
            out.append({k: v for k, v in rec.items() if k != "earlier"} | {"cases": left})
            done.update(left)
    return out


def check_regression(
    baseline: Path,
    *,
    out: Path = Path("out/regress"),
    cases: list[str] | None = None,
    update: bool = False,
    min_hit_rate: float | None = None,
    board_link: str | None = None,
    hello_timeout_s: float | None = None,
    uncalibrated: bool = False,
    figures: bool = True,
) -> tuple[bool, str, dict]:
    """Run the cases; returns (ok, readable diff, new baseline document).

    ok: no case regressed against the baseline (not judged with ``update``) and every case's deadline
    hit rate reached ``min_hit_rate`` (None: every pair met its deadline end to end). ``board_link``: run
    the board cases (``"flight": "external"``) on this link instead of their own (not written back).
    ``hello_timeout_s``: how long each case waits for its flight side's first Hello (None: ``run``'s default).
    ``uncalibrated``: judge emulated cases on a host that was never calibrated (refused otherwise: their reference
    seconds would assume the anchor's speed). ``figures``: each case's report.html draws its pictures.
    """
    from protocol.errors import InputError

    baseline = Path(baseline)
    if baseline.is_dir():
        raise InputError(f"latency baseline {baseline} is a directory: give the baseline's JSON file")
    if not baseline.is_file() and not update:
        raise InputError(f"no latency baseline at {baseline} (record one with `hazard-hil regress --update`)")
    if update:  # the runs must not be lost to a baseline that cannot be written
        _check_writable(baseline)
    if baseline.is_file():
        try:
            doc = json.loads(baseline.read_text(encoding="utf-8"))
        except (OSError, ValueError) as exc:
            raise InputError(f"latency baseline {baseline}: unreadable ({exc})") from None
    else:  # --update without a baseline: record the default cases (those --cases names), and say so
        # all of them were put in the new file and only --cases' run: the others then measured nothing, and the
        # baseline was refused after the run (QA of stop 71)
        chosen = [k for k in DEFAULT_CASES if cases is None or k in cases]
        missing = [c for c in cases or () if c not in DEFAULT_CASES]
        if missing:
            raise InputError(
                f"no baseline at {baseline} to hold case(s) {missing}: name shipped cases "
                f"({', '.join(DEFAULT_CASES)}), or write the file with your cases first "
                '({"cases": {NAME: {"scenario": ..., "budget": ..., "link": ...}}})'
            )
        # a misspelt --baseline read as a new file, silently beside the one meant (QA of stop 80)
        near = _near_baseline(baseline)
        print(f"regress: no baseline at {baseline}: recording the shipped cases ({', '.join(chosen)}) into it"
              + (f" (not {near}, which is there: did you mean it?)" if near else ""), file=sys.stderr)  # fmt: skip
        doc = {"cases": {k: {**DEFAULT_CASES[k]} for k in chosen}}
    validate_baseline(doc, str(baseline), baseline.resolve().parent)
    all_cases = doc["cases"]
    tol = {**DEFAULT_TOLERANCES, **doc.get("tolerances", {})}
    if cases is not None and not cases:
        raise InputError(f"--cases names no case; known: {', '.join(sorted(all_cases))}")
    names = list(all_cases) if cases is None else list(dict.fromkeys(cases))
    unknown = [n for n in names if n not in all_cases]
    if unknown:
        raise InputError(f"unknown regression case(s) {unknown}; known: {sorted(all_cases)}")
    if min_hit_rate is not None and not 0.0 <= min_hit_rate <= 1.0:
        raise InputError(f"--min-hit-rate must be in [0, 1], got {min_hit_rate}")
    if hello_timeout_s is not None and not (math.isfinite(hello_timeout_s) and 0 < hello_timeout_s <= 86400):
        raise InputError(f"--hello-timeout must be a number of seconds in (0, 86400], got {hello_timeout_s}")
    from reports.console import printable

    cond, notes = host_conditions()
    now_cal = cond.get("calibration")
    others = sorted({str(c.get("key")) for n in names if isinstance(c := _recorded_calibration(doc, n), dict)})
    if not update and now_cal is not None and [k for k in others if k != now_cal.get("key")]:
        # reference seconds compare across hosts only as far as each host's calibration holds (QA 66a): said
        keys = ", ".join(printable(k, 60) for k in others if k != now_cal.get("key"))
        notes.append(
            f"the baseline was recorded on another host ({keys}); this one is "
            f"{printable(str(now_cal.get('key')), 60)}: its reference seconds rest on both hosts' calibrations"
        )
    if not update and now_cal is not None and (moved := _calibration_moved(doc, names, now_cal)):
        # the budgets' duty cycles come from the calibration: a new one on the same host moved every emulated
        # case's latencies and degraded count, and the FAIL read as the flight software's (QA of stop 80)
        notes.append(moved)
    if all(is_board(all_cases[n]) for n in names):
        notes = []  # this host's calibration and load say nothing about a board's speed
    if update and cond["calibration"] is None and baseline.resolve() == default_baseline_path().resolve():
        # the shipped baseline is what every CI job compares against; another file only carries the warning below
        # (and its "recorded" block says the host was uncalibrated)
        raise InputError(
            "refusing to record the shipped baseline on an uncalibrated host: its reference seconds would assume "
            "the anchor's speed; run `hazard-hil calibrate` first"
        )
    if cond["calibration"] is None and not uncalibrated and not all(is_board(all_cases[n]) for n in names):
        # reference seconds then assume the anchor's speed: a host case read 30 % low, a gate that much looser that
        # still said PASS, with only a warning on stderr (QA of stop 73)
        raise InputError(
            "this host is not calibrated: its cases' reference seconds would assume it runs at the anchor's speed, "
            "so a regression could pass unseen; run `hazard-hil calibrate` first (about a minute, kept in "
            "$HAZARD_HIL_HOME), or give --uncalibrated to judge anyway (the verdict then says so)"
        )
    if board_link is not None and not any(is_board(all_cases[n]) for n in names):
        raise InputError('--link applies to board cases ("flight": "external"); none of these cases is one')
    base_dir = baseline.resolve().parent
    unrecorded = [n for n in names if not update and all_cases[n].get("metrics") is None]
    if unrecorded:
        # each ran in full, then failed "no baseline" (QA of stop 71): a missing baseline is exit 2
        shipped = baseline.resolve() == default_baseline_path().resolve()
        where = "" if shipped else f" --baseline {baseline}"  # the hint went to the shipped baseline (QA of stop 71)
        raise InputError(
            f"case{'s' if len(unrecorded) > 1 else ''} {', '.join(unrecorded)} in {baseline} "
            f"{'have' if len(unrecorded) > 1 else 'has'} no recorded metrics: record them with "
            f"`hazard-hil regress{where} --update --cases {','.join(unrecorded)}`"
        )
    check_cases(names, {n: _with_link(all_cases[n], board_link) for n in names}, out, base_dir, hello_timeout_s)
    changed = {} if update else {n: _changes(all_cases[n], base_dir) for n in names}
    for n, whats in changed.items():
        for what in whats:
            print(f"regress: case {n}: {what}", file=sys.stderr)
    for note in notes:
        print(f"regress: warning: {note}", file=sys.stderr)
    outcomes: list[CaseOutcome] = []
    missed = False
    for i, n in enumerate(names, 1):
        case = all_cases[n]
        run_case = _with_link(case, board_link)
        where = f"the board on {run_case['link']}" if is_board(case) else case["budget"]
        print(f"regress: case {i}/{len(names)} {n} ({case['scenario']} on {where})", file=sys.stderr)
        try:
            cur = measure_case(n, run_case, case_config(n, run_case, out, base_dir, hello_timeout_s, figures))
        except RegressInterrupted as exc:
            for o in outcomes:  # the table read "recorded" for cases the baseline then did not get (QA of stop 73)
                o.unwritten = "interrupted: the baseline is unchanged" if o.recorded else ""
            exc.finished = diff_table(outcomes) if outcomes else ""
            exc.rows = outcome_rows(outcomes)
            raise
        incomplete = cur.pop("incomplete_reason", None)
        contended = cur.pop("contention_pct", None)
        # a user's host-speed budget is unthrottled too: its wall latency measures the host's other load (QA 66a)
        metrics = _judged_for(case, baseline)
        o = compare(n, cur, None if update else case.get("metrics"), tol, metrics)
        if update:
            o.problems.clear()  # no baseline to regress against: it is being written
            if cur.get("degraded"):  # recorded as allowed: a deadline nothing could meet passed every later check
                note = (
                    f"case {n}: {cur['degraded']} of {cur.get('pairs')} pairs came back degraded (a coarser level "
                    "or stages skipped); the baseline allows that many from now on"
                )
                print(f"regress: warning: {note}", file=sys.stderr)
                notes.append(note)
            o.recorded = True
            o.previous = case.get("metrics")
            case["metrics"] = cur
            # the rate it was recorded at is the one later checks hold it to: without it, a case recorded with
            # --min-hit-rate failed every check that did not repeat the option (QA of stop 80)
            if min_hit_rate is None:
                case.pop("min_hit_rate", None)
            else:
                case["min_hit_rate"] = min_hit_rate
            case["budget_recorded"] = budget_record(case, base_dir)
            case["workload_recorded"] = workload_record(case, base_dir)
        else:
            o.problems.extend(changed.get(n, []))
        if incomplete:
            o.problems.append(f"the run did not finish: {incomplete}")
        o.contention_pct = contended
        need, whose = required_hit_rate(case, min_hit_rate)
        if not cur["deadline_hit_rate"] >= need - 1e-12:
            missed = o.below_required = True
            o.problems.append(
                f"deadlines: {cur['deadline_hit_rate']:.0%} of pairs met theirs end to end, {need:.0%} required{whose}"
            )
        outcomes.append(o)
    new_doc = {
        "tolerances": tol,
        "cases": all_cases,
        "note": "latencies in reference seconds; see hil_server/regress.py",
    }
    if update:  # what the new numbers rest on, for whoever reads the baseline later
        new_doc["recorded"] = {**cond, "warnings": notes, "cases": names}
        if earlier := _earlier_records(doc.get("recorded"), names, all_cases):
            new_doc["recorded"]["earlier"] = earlier  # the cases --cases left alone keep what they rest on
    elif "recorded" in doc:
        new_doc["recorded"] = doc["recorded"]
    ok = all(not o.problems for o in outcomes) and not missed
    refusal = _refusal(all_cases, baseline, ok) if update else ""
    if refusal:  # its rows read "recorded" above "baseline NOT written" (review of stop 73)
        ok = False
        for o in outcomes:
            o.unwritten = "the baseline is not written: see below"
    diff = diff_table(outcomes)
    if notes:
        diff += "\n" + "\n".join(f"warning: {n}" for n in notes)
    # whether the verdict rests on an uncalibrated host: the cases run, not every case of the baseline
    uncal = cond["calibration"] is None and not all(is_board(all_cases[n]) for n in names)
    _write_report(out, {"baseline": str(baseline), "update": update, "judged_ok": ok, "warnings": notes,
                        "refusal": refusal, "uncalibrated": uncal, "cases": outcome_rows(outcomes)})  # fmt: skip
    return ok, diff, new_doc


def required_hit_rate(case: dict, min_hit_rate: float | None) -> tuple[float, str]:
    """The deadline hit rate ``case`` must reach and where it comes from: ``--min-hit-rate`` when given, else the
    rate the baseline recorded the case at (its ``min_hit_rate``), else every pair (1.0)."""
    if min_hit_rate is not None:
        return min_hit_rate, ""
    if case.get("min_hit_rate") is not None:
        return float(case["min_hit_rate"]), " (the baseline's min_hit_rate, recorded with --min-hit-rate)"
    return 1.0, ""


def _changes(case: dict, base_dir: Path | None) -> list[str]:
    """What changed in a case since its metrics were recorded: its budget's figures, its workload."""
    return [w for w in (budget_change(case, base_dir), workload_change(case, base_dir)) if w]


def _refusal(cases: dict, baseline: Path, ok: bool) -> str:
    """Why an --update must not write ``cases`` (with the metrics just measured), or "" when it may; the metrics it
    would write are cleaned of non-finite values meanwhile."""
    # a case without a single result has no latency to record (NaN): such a baseline could never be read back,
    # and writing it would lose the one that was there. A metric a case cannot measure (a board whose Telemetry
    # leaves out its stages has no CPU seconds) is left out, and read back as "not judged" (QA 66a)
    empty = []
    for n, c in cases.items():
        m = c.get("metrics") or {}
        # the metrics the case is judged on must be there, or it could never fail again (review of stop 66);
        # a board's own latency alone may be missing (its Telemetry need not report one): its end-to-end is judged
        must = E2E_METRICS if is_board(c) else _judged_for(c, baseline)
        missing = [k for k in ("deadline_hit_rate", *must) if _not_finite(m.get(k, math.nan))]
        if missing:
            empty.append(f"{n} ({', '.join(missing)})")
        else:
            c["metrics"] = {k: v for k, v in m.items() if not _not_finite(v)}
    if empty:
        return (
            f"case(s) {', '.join(empty)} measured none of the metrics named, which they are judged on (no Result, or "
            "a flight program whose Telemetry leaves them out)"
        )
    if not ok:  # a baseline of missed deadlines passed every later run held to it (QA of stop 73)
        return (
            "a case missed its deadlines or did not finish (above); to record a case that misses some, give the hit "
            "rate it may have: --min-hit-rate"
        )
    return ""


REPORT_NAME = "regress.json"  # in --out: the diff table and verdict for a CI to read (QA of stop 73)


def outcome_rows(outcomes: list[CaseOutcome]) -> list[dict]:
    """The diff table as data: per case its problems and, per metric, baseline, limit, current and verdict."""
    rows = []
    for o in outcomes:
        metrics = {
            k: {
                "baseline": _finite((o.baseline or {}).get(k)),
                "limit": _finite(o.limits.get(k)),
                "current": _finite(o.current.get(k)),
                "verdict": _metric_verdict(o, k),
            }
            for k in _table_keys(o)
        }
        rows.append(
            {
                "case": o.name,
                "problems": list(o.problems),
                "recorded": o.recorded and not o.unwritten,
                "metrics": metrics,
                "contention_pct": o.contention_pct,
            }
        )
    return rows


def _finite(v: Any) -> Any:
    return None if isinstance(v, float) and not math.isfinite(v) else v


def _write_report(out: Path, doc: dict) -> None:
    """``OUT/regress.json``, whole or not at all; a refused write is said, not fatal (the console has the table)."""
    from reports.html import write_atomic

    try:
        Path(out).mkdir(parents=True, exist_ok=True)
        write_atomic(Path(out) / REPORT_NAME, json.dumps(doc, indent=1, sort_keys=True) + "\n")
    except OSError as exc:
        print(f"regress: warning: {Path(out) / REPORT_NAME} not written ({exc.strerror or exc})", file=sys.stderr)


def _read_report(out: Path) -> dict:
    """``OUT/regress.json`` as :func:`check_regression` wrote it ({} when it could not)."""
    try:
        doc = json.loads((Path(out) / REPORT_NAME).read_text())
    except (OSError, ValueError):
        return {}
    return doc if isinstance(doc, dict) else {}


def _final_report(out: Path, verdict: str, code: int) -> None:
    """Add the command's own verdict and exit code to ``OUT/regress.json``."""
    _write_report(out, {**_read_report(out), "verdict": verdict, "exit_code": code})


def _check_writable(baseline: Path) -> None:
    """Refuse a baseline file ``--update`` could not write, before its cases run (minutes of work)."""
    import tempfile

    from protocol.errors import InputError

    parent = baseline.parent if str(baseline.parent) else Path(".")
    if not parent.is_dir():
        raise InputError(f"latency baseline {baseline}: directory {parent} does not exist")
    try:
        with tempfile.TemporaryFile(dir=parent):
            pass
    except OSError as exc:
        raise InputError(f"latency baseline {baseline} cannot be written ({exc.strerror or exc})") from None


def _with_link(case: dict, board_link: str | None) -> dict:
    """A board case on ``--link`` instead of its own (not written back)."""
    return {**case, "link": board_link} if board_link is not None and is_board(case) else case


def run_regression(
    baseline: Path,
    *,
    update: bool = False,
    out: Path = Path("out/regress"),
    cases: list[str] | None = None,
    min_hit_rate: float | None = None,
    board_link: str | None = None,
    hello_timeout_s: float | None = None,
    uncalibrated: bool = False,
    figures: bool = True,
) -> int:
    from protocol.outdir import claim_out

    with claim_out(out, "regress"):  # each case's run holds its own OUT/<case> too
        # an earlier run's verdict must not pass for this one's when this one ends early (exit 2, a signal)
        (Path(out) / REPORT_NAME).unlink(missing_ok=True)
        try:
            ok, diff, new_doc = check_regression(
                baseline,
                out=out,
                cases=cases,
                update=update,
                min_hit_rate=min_hit_rate,
                board_link=board_link,
                hello_timeout_s=hello_timeout_s,
                uncalibrated=uncalibrated,
                figures=figures,
            )
        except RegressInterrupted as exc:
            if exc.finished:  # the verdicts of the cases that had run before the signal
                print(exc.finished)
            print(f"regress: {exc}; the cases after it were not run, {baseline} is unchanged", file=sys.stderr)
            print("INTERRUPTED")
            # a CI job reading OUT/regress.json found none: the earlier one is removed at the start (QA of stop 78);
            # the keys a finished run's report has, its warnings and refusal unknown at the signal
            doc = {"baseline": str(baseline), "update": update, "judged_ok": False, "warnings": [], "refusal": ""}
            doc.update(uncalibrated=None, interrupted=str(exc), cases=exc.rows)
            _write_report(out, {**doc, "verdict": "INTERRUPTED", "exit_code": 128 + exc.signum})
            return 128 + exc.signum
    print(diff)
    report = _read_report(out)
    if update:
        from reports.html import write_atomic

        if report.get("refusal"):
            print(f"baseline NOT written: {report['refusal']}; {baseline} is unchanged")
            print("FAIL")
            _final_report(out, "FAIL: baseline not written", 1)
            return 1
        write_atomic(Path(baseline), json.dumps(new_doc, indent=1, sort_keys=True) + "\n")
        print(f"baseline written: {baseline}")
    blind = " (uncalibrated host: reference seconds at the anchor's speed)" if report.get("uncalibrated") else ""
    verdict = ("PASS" if ok else "FAIL") + (" (baseline recorded)" if update else f" against {baseline}") + blind
    print(verdict)
    _final_report(out, verdict, 0 if ok else 1)
    return 0 if ok else 1


def _judged_for(case: dict, baseline: Path) -> tuple[str, ...]:
    """The metrics an emulated ``case`` of ``baseline`` is judged on."""
    from hil_server.budgets import get_budget

    own = _path(case.get("budget_file"), Path(baseline).resolve().parent)
    return judged_metrics(case["budget"], case.get("flight", "emulated"), get_budget(case["budget"], own).is_host)


def _not_finite(v: object) -> bool:
    return isinstance(v, float) and not math.isfinite(v)
