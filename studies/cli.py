"""``hazard-hil evaluate`` and ``hazard-hil sensitivity``: the thesis's ch. 6 tables and sec 6.3 Monte Carlo."""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from ground_sim.render import DEFAULT_RASTER, RASTERS
from ground_sim.seeds import describe_seeds, seed_runs
from protocol.errors import InputError, comma_items
from protocol.pairdir import IMAGE_SIZE_MAX, IMAGE_SIZE_MIN, THESIS_CAMERA_PX


def _positive(kind: str, most: int | None = None, least: int = 1):
    def conv(text: str) -> int:
        try:
            v = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{kind} must be an integer, got {text!r}") from None
        if v < least or (most is not None and v > most):
            raise argparse.ArgumentTypeError(f"{kind} must be >= {least}{f' and <= {most}' if most else ''}, got {v}")
        return v

    return conv


MIN_CAMERA_PX = (
    IMAGE_SIZE_MIN  # studies.evaluate.camera_for refuses smaller cameras (in a worker, after the work started)
)


def add_seed_options(
    p: argparse.ArgumentParser,
    default_n: int,
    what: str = "scene seeds",
    how: str = "results are medians over seeds",
) -> None:
    """``--seed-set tuning|held-out`` (default held-out), ``--seeds N`` (the first N of it, default ``default_n``
    or the whole set when it is smaller), ``--seed-list``."""
    p.add_argument(
        "--seed-set",
        choices=["held-out", "tuning"],
        default=None,
        help="which documented seed set to draw from (ground_sim.seeds): held-out 1000-1099 (default; "
        "quote these) or tuning 0-9 (tune on these)",
    )
    p.add_argument(
        "--seeds",
        type=_positive("--seeds"),
        default=None,
        help=f"number of {what}: the first N of the seed set (default {default_n}, or all of a smaller set); {how}",
    )
    p.set_defaults(seeds_default=default_n)
    p.add_argument("--seed-list", default=None, help="explicit comma-separated seeds instead (e.g. 1000,1003)")


def check_backend(args: argparse.Namespace) -> None:
    """``--workers`` sizes the local pool; with ``--scheduler`` the cluster's workers run it, so both is a
    contradiction (the count was ignored)."""
    if getattr(args, "scheduler", None) is not None and getattr(args, "workers", None) is not None:
        raise InputError("--workers sets local processes; with --scheduler the Dask cluster's workers run: give one")


# the exit codes of evaluate, sensitivity and landings, said in their help
STUDY_EXIT_CODES = (
    "Exit 0 when every task is done, 1 when some failed (the rest are saved: rerun the same command to retry them), "
    "2 on bad input, 128 + N when signal N stopped it (130: Ctrl-C; resumable)."
)


def camera_note(camera_px: int | None) -> str:
    """Said beside the seeds wherever a study's tables sit next to the thesis's: another camera than its 512 px
    one changes the ground sample distance, and so every figure."""
    if camera_px is None or camera_px == THESIS_CAMERA_PX:
        return ""
    from flight_sw.psafe import model_for_image
    from studies.evaluate import other_camera

    note = f"; {other_camera(camera_px)}: not its setup"
    # what `process` warns of per pair, said once for the study: a smaller camera tests another detector
    if model_for_image(None, (camera_px, camera_px)) is None:
        note += "; `fast`'s calibrated P(safe) is not fitted for it: the Gaussian rule stands in, with a higher FP"
    if camera_px < SMALL_FOR_REFINEMENT_PX:
        note += "; pose refinement is skipped on most pairs (too little shared image to track)"
    return note


def warn_not_held_out(seeds: list[int], seed_set: str) -> str:
    """:func:`ground_sim.seeds.not_held_out`, said once on stderr as a warning; returns it for the page."""
    from ground_sim.seeds import not_held_out

    why = not_held_out(seeds, seed_set)
    if why:
        _note(f"warning: {why}")
    return why


# under this a 2:1 pair's shared area is under four of pose refinement's 15 px tracking windows a side: at 128 px
# `sensitivity --preset refine` printed identical rows for fast and fast_unrefined (stop 57's studies QA)
SMALL_FOR_REFINEMENT_PX = 200


def holding_out(command: str, fn: Callable[[argparse.Namespace], int]) -> Callable[[argparse.Namespace], int]:
    """``fn`` with its ``--out`` held for it (:func:`protocol.outdir.claim_out`): two studies writing one directory
    at once computed everything twice, and merged ``metrics.csv`` over each other's rows."""

    def run(args: argparse.Namespace) -> int:
        from protocol.outdir import claim_out

        with claim_out(args.out, command):
            return fn(args)

    return run


def _campaign_failed(what: str, exc: Exception) -> int:
    """Some tasks failed (each said above with its reason); the rest are saved: exit 1."""
    print(f"hazard-hil {what}: {exc}; rerun the same command to retry them", file=sys.stderr)
    return 1


@contextlib.contextmanager
def writing_report(out: Path) -> Iterator[None]:
    """A Ctrl-C while the page and tables are written ended in a bare "interrupted", the page missing: every
    result is already saved, so say that a rerun only writes the report. The page goes: an earlier run's page
    beside this run's tables read as theirs (2 seeds on the page, 1 in metrics.csv; stop 63's QA). This run's own
    page, written whole before the stop (a broken pipe as the tables print), stays (review of stop 63)."""
    page = out / "report" / "index.html"

    def identity() -> tuple[int, int] | None:  # the page is written beside and renamed: a new page, a new inode
        try:
            st = page.stat()
        except OSError:
            return None
        return st.st_dev, st.st_ino

    earlier = identity()
    try:
        yield
    except BaseException as exc:
        now = identity()
        ours = now is not None and now != earlier
        if not ours:
            with contextlib.suppress(OSError):
                page.unlink(missing_ok=True)
        what = "its page is this run's" if ours else "whose page is removed"
        if isinstance(exc, KeyboardInterrupt):  # Terminated too
            _note(f"interrupted while writing the report, {what}; every result is saved in {out / 'runs'}: rerun "
                  "the same command to write it (nothing is computed again)")  # fmt: skip
        else:
            _note(f"stopped while writing the report, {what}; every result is saved in {out / 'runs'}")
        raise


def note_page_owner(out: Path, command: str) -> None:
    """Each study writes ``OUT/report/index.html``: say so when this one replaces another study's page (its
    results stay in OUT; only the page that showed them goes), rather than replacing it without a word."""
    from reports.html import page_title

    old = page_title(out / "report" / "index.html") or ""
    if old.startswith("hazard-hil ") and not old.startswith(f"hazard-hil {command}"):
        other = old.split()[1].rstrip(":")
        _note(
            f"note: {out / 'report' / 'index.html'} was the {other} page and is now {command}'s; give each study "
            f"its own --out (rerun {other} into its own directory to see its page again)"
        )


# A study's worker also imports and runs the renderer, the scoring and the studies: measured 130 MiB resident per
# worker at a 128 px camera (stop 57's studies QA), where the pipeline's model alone says 37: `--workers 1000`
# would have started 637 of them, ~80 GiB, on a 23 GiB host
STUDY_WORKER_EXTRA_BYTES = 96 * 2**20


def check_local_room(args: argparse.Namespace, n_frames: int = 2) -> None:
    """Before any rendering: each local worker runs the pipeline on a ``--camera-px`` pair
    (:func:`flight_sw.validate.peak_memory_bytes`); refuse a camera one run cannot fit in the memory this process
    can spend, as ``process`` refuses one pair (an 8192 px camera started and would have needed ~12 GiB per
    worker), and run only as many workers at once as fit (said). ``n_frames`` > 2: the multi-frame descents,
    which run one at a time in this process. More workers than cores is allowed, and said. With ``--scheduler``,
    the scheduler is probed instead (:func:`studies.executor.probe_scheduler`)."""
    import os

    from flight_sw.validate import memory_room, peak_memory_bytes

    if getattr(args, "scheduler", None) is not None:  # the cluster's workers: their memory is theirs to judge
        from studies.executor import probe_scheduler

        # but one that is not there is said now: a render's progress bar and an OUT came first (QA of stop 78)
        probe_scheduler(args.scheduler)
        return
    cores = os.cpu_count() or 1
    workers = args.workers or cores
    if workers > cores:
        _note(f"note: --workers {workers} on {cores} core(s): the workers share them, none runs faster")
    px = args.camera_px or THESIS_CAMERA_PX
    room, what = memory_room()
    for frames in sorted({2, n_frames}):
        need = peak_memory_bytes(px, px, frames)
        if need > room:
            raise InputError(
                f"a {px} px camera needs ~{need / 2**20:.0f} MiB per pipeline run ({frames} frames), but only "
                f"{room / 2**20:.0f} MiB {what}: use a smaller --camera-px"
            )
    each = peak_memory_bytes(px, px, 2) + STUDY_WORKER_EXTRA_BYTES
    fit = max(1, room // each)
    if workers > fit:  # the executor starts a worker per pending task up to this count: as many as fit at once
        _note(
            f"note: {workers} workers on a {px} px camera would need ~{workers * each / 2**20:.0f} MiB at once, but "
            f"{room / 2**20:.0f} MiB {what}: running {fit}"
        )
        args.workers = fit


def resolve_seeds(args: argparse.Namespace, default_n: int) -> tuple[list[int], str]:
    """(seeds, name of the set they come from: 'held-out', 'tuning' or 'explicit ...')."""
    from ground_sim.seeds import SEED_SETS, seed_set_of

    if args.seed_list is not None and getattr(args, "seeds", None) is not None:
        raise InputError("--seeds N and --seed-list: give one (--seeds takes the first N of --seed-set)")
    if args.seed_list is not None and not args.seed_list.strip():
        raise InputError("--seed-list is empty: give comma-separated seeds, e.g. 1000,1003")
    if args.seed_list:
        items = comma_items(args.seed_list, "--seed-list")
        try:
            seeds = [int(x) for x in items]
        except ValueError:
            raise InputError(f"--seed-list: expected comma-separated integers, got {args.seed_list!r}") from None
        if not seeds or len(set(seeds)) != len(seeds):
            raise InputError(f"--seed-list: need distinct seeds, got {args.seed_list!r}")
        from ground_sim.cli import check_seed

        for x in seeds:  # as `run` and `render` refuse them (a negative seed read as "other seeds")
            check_seed(x, "--seed-list seeds")
        sets = sorted({seed_set_of(x) for x in seeds})
        if args.seed_set is not None and sets != [args.seed_set]:
            other = [x for x in seeds if seed_set_of(x) != args.seed_set]
            raise InputError(
                f"--seed-list {args.seed_list}: seed(s) {other[:5]} are not in the {args.seed_set} set given by "
                "--seed-set; drop --seed-set or list only its seeds"
            )
        return seeds, sets[0] if len(sets) == 1 else "mixed"
    name = args.seed_set or "held-out"
    pool = SEED_SETS[name]
    n = args.seeds or min(default_n, len(pool))  # a default the set cannot fill means all of it, not an error
    if n > len(pool):
        raise InputError(f"--seeds {n}: the {name} set has only {len(pool)} seeds")
    return list(pool[:n]), name


def _scheduler(text: str) -> str:
    from studies.executor import check_scheduler_address

    try:
        return check_scheduler_address(text)
    except InputError as exc:
        raise argparse.ArgumentTypeError(str(exc).removeprefix("--scheduler ")) from None


def _executor_options(p: argparse.ArgumentParser) -> None:
    """--scheduler and --workers: where the tasks of a study run."""
    p.add_argument(
        "--scheduler",
        type=_scheduler,
        default=None,
        help="Dask scheduler address, e.g. tcp://host:8786 (default: local processes)",
    )
    p.add_argument(
        "--workers",
        type=_positive("--workers"),
        default=None,
        help="local worker processes (default: CPU count; 1 = in-process)",
    )


def _common(p: argparse.ArgumentParser, seeds_default: int, figures_note: str = "") -> None:
    add_seed_options(p, seeds_default)
    p.add_argument("--out", required=True, type=Path, help="output directory (resumes if it exists)")
    p.add_argument("--cache", type=Path, default=None, help="rendered-pair cache (default OUT/cache)")
    _executor_options(p)
    p.add_argument(
        "--camera-px",
        "--image-size",  # render's and run's name for it
        dest="camera_px",
        type=_positive("--camera-px", IMAGE_SIZE_MAX, MIN_CAMERA_PX),
        default=None,
        help=f"square camera size with the thesis's 30 deg FOV, {MIN_CAMERA_PX}-{IMAGE_SIZE_MAX} (default 512, the "
        "thesis camera; the tables then say they are not the thesis's)",
    )
    p.add_argument("--altitudes", default=None, help="comma-separated subset of table altitudes [m]")
    p.add_argument(
        "--max-raster-cells",
        type=int,
        default=None,
        help="render with this terrain raster cap (default 1000000; docs/scenes.md); its renders and runs "
        "are kept apart from the default's",
    )
    p.add_argument(
        "--raster",
        choices=list(RASTERS),
        default=DEFAULT_RASTER,
        help="tiles (default): render every view from rasters per image tile at the tile's own GSD/2; view: "
        "one capped raster per view, 1.2-4.2x coarser at 512 px (the renders before 2026-11-25; "
        "docs/scenes.md); each raster's renders and runs are kept apart",
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    _no_figures_option(p, figures_note)


def _no_figures_option(p: argparse.ArgumentParser, note: str = "") -> None:
    """``note``: what the command's pictures cost or keep, after the option's common help."""
    p.add_argument(
        "--no-figures",
        action="store_true",
        help="report/index.html without its pictures, the tables alone, as `run --no-figures`; the pictures an "
        f"earlier run drew for the page are removed{note}",
    )


def register(subparsers: Any) -> None:
    from flight_sw.cli import register_process

    p = subparsers.add_parser(
        "evaluate",
        help="score the pipeline against ground truth; thesis tables side by side",
        description="Render (or reuse) a scenario, run the pipeline, score it against "
        "ground truth and print/write the thesis's ch. 6 tables next to ours. " + STUDY_EXIT_CODES,
    )
    p.add_argument(
        "--scenario", required=True, choices=["vertical", "approach"], help="the thesis scenario whose tables to fill"
    )
    p.add_argument(
        "--preset", choices=["fast", "thesis", "both"], default="both", help="flight software preset(s) to evaluate"
    )
    p.add_argument(
        "--multi-frame",
        action="store_true",
        help="also render one multi-frame descent per seed and compare the fast preset's multi-baseline run and "
        "fused maps against the best single pair (chosen with the truth; issue 10); locally the descents run in "
        "this process, one after another (--workers sizes the pair stage only); --scheduler runs them on the cluster",
    )
    p.add_argument(
        "--frames",
        default=None,
        help="with --multi-frame: comma-separated frame altitudes [m], decreasing, 2-16 (default 300,250,200,150)",
    )
    _common(
        p,
        seeds_default=3,
        figures_note=" (a pair's map figures take about 1 CPU-s each; the maps are kept, so a later run draws them)",
    )
    p.set_defaults(func=holding_out("evaluate", _evaluate))

    s = subparsers.add_parser(
        "sensitivity",
        help="pose-error Monte Carlo (thesis sec 6.3)",
        description="DEM error increase under pose-knowledge errors on the approach "
        "scenario (Tables 6.12-6.19), relative to perfect knowledge. " + STUDY_EXIT_CODES,
    )
    s.add_argument(
        "--kind",
        required=True,
        choices=["altitude", "attitude", "lateral", "rollyaw"],
        help="which navigation error to inject (thesis sec 6.3)",
    )
    s.add_argument(
        "--samples",
        type=_positive("--samples"),
        default=20,
        help="samples per seed and altitude (default 20, at most 10000); attitude's first six are the thesis's "
        "levels -0.15 ... +0.15 deg in order, the rest drawn",
    )
    s.add_argument(
        "--preset",
        choices=["fast", "thesis", "fast_unrefined", "both", "refine"],
        default="both",
        help="flight software preset(s) to study; both: fast and thesis; refine: fast with and without pose "
        "refinement (fast_unrefined)",
    )
    _common(s, seeds_default=2)
    s.set_defaults(func=holding_out("sensitivity", _sensitivity))
    register_landings(subparsers)
    register_score(subparsers)
    register_process(subparsers, scorer=_truth_look)  # flight_sw's command; scoring lives on this side (DESIGN.md)


def _truth_look(args: argparse.Namespace) -> Any:
    from studies.quicklook import TruthLook

    return TruthLook(args.pair_dir, figures=not args.no_figures)


def _parse_alts(text: str | None) -> list[int] | None:
    if text is None:
        return None
    items = comma_items(text, "--altitudes")
    try:
        values = [float(a) for a in items]
        alts = [int(v) for v in values]
    except (ValueError, OverflowError):
        raise InputError(f"--altitudes: expected comma-separated numbers, got {text!r}") from None
    cut = [f"{v:g}" for v, a in zip(values, alts, strict=True) if v != a]
    if cut:  # 300.9 was read as 300 without a word: the tables' altitudes are whole metres
        raise InputError(f"--altitudes: the table altitudes are whole metres, got {', '.join(cut)}")
    if not alts:
        raise InputError("--altitudes is empty: give comma-separated table altitudes, e.g. 300,150")
    return alts


def _parse_frames(scenario: str, text: str | None) -> list[float]:
    """``--frames``: 2-16 decreasing positive altitudes, checked by the trajectory before any work starts."""
    from ground_sim.trajectory import frames_at
    from studies.multiframe import DEFAULT_FRAMES

    if text is None:
        return list(DEFAULT_FRAMES)
    items = comma_items(text, "--frames")
    try:
        alts = [float(a) for a in items]
    except ValueError:
        raise InputError(f"--frames: expected comma-separated altitudes, got {text!r}") from None
    frames_at(scenario, alts)  # TrajectoryError (an InputError) with the reason
    return alts


def _note(message: str) -> None:
    """A progress line: on stderr like every progress bar, so stdout keeps the tables alone."""
    print(message, file=sys.stderr, flush=True)


def _presets(choice: str) -> list[str]:
    return {"both": ["fast", "thesis"], "refine": ["fast", "fast_unrefined"]}.get(choice, [choice])


def _evaluate(args: argparse.Namespace) -> int:
    from studies import evaluate as ev
    from studies.executor import CampaignError

    check_backend(args)
    seeds, seed_set = resolve_seeds(args, args.seeds_default)
    if args.frames is not None and not args.multi_frame:
        raise InputError("--frames sets the multi-frame descents' altitudes: it needs --multi-frame")
    frames = _parse_frames(args.scenario, args.frames)
    check_local_room(args, len(frames) if args.multi_frame else 2)
    warning = warn_not_held_out(seeds, seed_set)
    try:
        rows = ev.evaluate_scenario(
            args.scenario,
            args.out,
            presets=_presets(args.preset),
            seeds=seeds,
            cache_dir=args.cache,
            camera_px=args.camera_px,
            altitudes=_parse_alts(args.altitudes),
            scheduler=args.scheduler,
            workers=args.workers,
            progress=not args.no_progress,
            max_cells=args.max_raster_cells,
            raster=args.raster,
            figures=not args.no_figures,
        )
    except CampaignError as exc:
        return _campaign_failed("evaluate", exc)
    multi = None
    if args.multi_frame:
        from studies import multiframe as mf

        try:
            multi = mf.evaluate_multiframe(
                args.scenario,
                args.out,
                seeds,
                frames=frames,
                cache_dir=args.cache,
                camera_px=args.camera_px,
                progress=None if args.no_progress else _note,
                max_cells=args.max_raster_cells,
                raster=args.raster,
                scheduler=args.scheduler,
            )
        except CampaignError as exc:
            return _campaign_failed("evaluate: multi-frame", exc)
    with writing_report(args.out):
        return _evaluation_page(args, rows, multi, frames, describe_seeds(seeds, seed_set), warning)


def tables_setting(scenario: str, scene: str, seeds_text: str, camera_px: int | None, warning: str = "") -> str:
    """The first line of ``tables_<scenario>.md``, the file pasted into RESULTS.md: its seeds, scene, scenario and
    camera, which it did not carry (a tuning-seed or 128 px table read as the thesis setup's held-out one)."""
    from studies.evaluate import other_camera

    camera = other_camera(camera_px) or f"the thesis's {THESIS_CAMERA_PX} px camera"
    return f"*{scenario} scenario, scene {scene}; {seeds_text}; {camera}*" + (
        f" **WARNING: {warning}**" if warning else ""
    )


def _evaluation_page(
    args: argparse.Namespace, rows: list, multi: Any, frames: list[float], seeds_text: str, warning: str = ""
) -> int:
    from studies import evaluate as ev
    from studies import report

    scene = rows[0]["scene"] if rows else "?"
    setting = tables_setting(args.scenario, scene, seeds_text, args.camera_px, warning)
    seeds_text += camera_note(args.camera_px)
    note_page_owner(args.out, "evaluate")
    page = report.evaluation_report(
        args.out,
        rows,
        title=f"hazard-hil evaluate: {args.scenario} scenario, {seeds_text}",
        figure_preset=_presets(args.preset)[0],
        multiframe=multi,
        map_tag=ev.render_tag(args.max_raster_cells, args.raster),
        setting=setting,
        subtitle=f"WARNING: {warning}" if warning else "",
        figures=not args.no_figures,
    )
    print(f"scene {rows[0]['scene'] if rows else '?'}, {seeds_text}")
    print((args.out / "report" / f"tables_{args.scenario}.md").read_text())
    if multi:
        print(f"multi-frame descents ({'/'.join(f'{a:g}' for a in frames)} m) against the best pair, preset fast:")
        print((args.out / "report" / f"multiframe_{args.scenario}.md").read_text())
    print(f"metrics: {args.out / 'metrics.csv'}\nreport:  {page}")
    print(renders_line(Path(args.cache) if args.cache is not None else args.out / "cache"))
    others = sorted({str(r["scenario"]) for r in ev.read_metrics_csv(args.out / "metrics.csv")} - {args.scenario})
    if others:
        print(
            f"note: metrics.csv also keeps the {', '.join(others)} rows evaluated into this --out before; "
            f"the page shows {args.scenario}",
            file=sys.stderr,
        )
    return 0


def _sensitivity(args: argparse.Namespace) -> int:
    from studies import evaluate as ev
    from studies.executor import CampaignError

    check_backend(args)
    seeds, seed_set = resolve_seeds(args, args.seeds_default)
    alts = _parse_alts(args.altitudes) or list(ev.SENSITIVITY_ALTITUDES)
    check_local_room(args)
    warning = warn_not_held_out(seeds, seed_set)
    try:
        rows = ev.sensitivity_campaign(
            args.kind,
            args.out,
            samples=args.samples,
            seeds=seeds,
            presets=_presets(args.preset),
            cache_dir=args.cache,
            camera_px=args.camera_px,
            altitudes=alts,
            scheduler=args.scheduler,
            workers=args.workers,
            progress=not args.no_progress,
            max_cells=args.max_raster_cells,
            raster=args.raster,
        )
    except CampaignError as exc:
        return _campaign_failed("sensitivity", exc)
    with writing_report(args.out):
        return _sensitivity_page(args, rows, describe_seeds(seeds, seed_set), warning)


def sensitivity_setting(rows: list[dict[str, Any]]) -> str:
    """The seeds and camera of one kind's sensitivity rows (``held-out seeds 1000-1001 (2), a 128 px camera``), as
    its section of the shared page states them; rows written before the CSVs named the camera say so."""
    seeds = sorted({int(r["seed"]) for r in rows})
    sets = sorted({str(r["seed_set"]) for r in rows if r.get("seed_set")})
    if not seeds:
        said = "no seeds"
    elif sets:
        said = describe_seeds(seeds, sets[0] if len(sets) == 1 else "mixed")
    else:  # rows written before they carried their seed set
        said = describe_seeds(seeds, "").strip() + ", seed set not recorded"
    cams = sorted({int(r["camera_px"]) for r in rows if r.get("camera_px") is not None})
    if not cams:
        return f"{said}, camera not recorded"
    return f"{said}, {'a ' if len(cams) == 1 else ''}{'/'.join(map(str, cams))} px camera{'s' if len(cams) > 1 else ''}"


def _sensitivity_page(args: argparse.Namespace, rows: list, seeds_text: str, warning: str = "") -> int:
    from reports.html import drop_pictures, dropped_note
    from studies import evaluate as ev
    from studies import report

    summ = ev.sensitivity_summary(rows)
    # the seeds and camera first, as evaluate says them; the columns by the glossary's labels, as the page names
    # them (the console's raw field names were explained nowhere on it; QA of stop 73)
    print(f"{args.kind}: {seeds_text}{camera_note(args.camera_px)}")
    print(report.rows_markdown(summ, list(summ[0]) if summ else [], labels=True))
    # one page for every study run into this directory, so kinds do not overwrite each other; each section
    # states its own seeds and camera: the headline's are this run's, and earlier kinds' may differ
    sections, other = [], []
    mine = sensitivity_setting(rows)
    if args.no_figures and (
        gone := drop_pictures(args.out / "report" / f"sensitivity_{kind}.png" for kind in ev.SENSITIVITY_KINDS)
    ):
        _note(dropped_note("sensitivity", len(gone), args.out / "report"))
    for kind in ev.SENSITIVITY_KINDS:
        csv_path = args.out / f"sensitivity_{kind}.csv"
        if not csv_path.is_file():
            continue
        krows = rows if kind == args.kind else ev.read_metrics_csv(csv_path)
        ks = ev.sensitivity_summary(krows)
        plots = (
            []
            if args.no_figures
            else [report.plot_sensitivity(krows, kind, args.out / "report" / f"sensitivity_{kind}.png").name]
        )
        table = report.Table([report.Column(k) for k in (ks[0] if ks else {})], ks)
        setting = sensitivity_setting(krows)
        sections.append((f"sensitivity: {kind} ({setting})", [table], plots))
        if kind != args.kind and setting != mine:
            other.append(f"{kind} ({setting})")
    note = camera_note(args.camera_px)
    note_page_owner(args.out, "sensitivity")
    # which seeds, on the page itself: a tuning-seed study's page could not be told from a held-out one's
    title = f"hazard-hil sensitivity (thesis sec 6.3); {seeds_text}{note}"
    if other:
        title = (
            f"hazard-hil sensitivity (thesis sec 6.3); {args.kind}: {seeds_text}{note}; the other sections are "
            "earlier runs into this --out with other settings, each stated in its heading"
        )
    page = report.write_html(
        args.out / "report",
        title,
        sections,
        subtitle=f"WARNING ({args.kind}): {warning}" if warning else "",
        figures=not args.no_figures,
        # the samples the console names were linked nowhere on the page (QA of stop 85)
        files=[(f"../sensitivity_{k}.csv", f"the {k} study's samples: a row per draw") for k in ev.SENSITIVITY_KINDS]
        + [("../runs/", "the logs a rerun resumes from")],
    )
    print(f"samples: {args.out / f'sensitivity_{args.kind}.csv'}\nreport:  {page}")
    if other:
        _note(
            f"note: the page also shows {'; '.join(other)}: run into this --out before, with other settings than "
            f"this {args.kind} run's ({mine}); each section's heading states its own"
        )
    return 0


def _summary_state(path: Path) -> str:
    """What an interrupted campaign left in ``path``: the signal can land before, during or after the final
    summary, so the file (written whole or not at all) is read rather than assumed partial."""
    try:
        complete = json.loads(path.read_text()).get("complete")
    except (OSError, ValueError, AttributeError):
        return f"no summary written: {path}"
    return f"{'summary' if complete else 'partial summary'} (complete: {str(bool(complete)).lower()}): {path}"


def register_landings(subparsers: Any) -> None:
    from studies.landings import DEFAULT_POSE_ERROR, PER_RENDER

    p = subparsers.add_parser(
        "landings",
        help="landing Monte Carlo: P(safe landing) with its 95 %% interval, per scene and preset",
        description="Fly N landings over library scenes (hazard-hil scenes): each draws a scene seed, an aim "
        "point, the sun (where the scene allows), an image pair and navigation errors, runs the pipeline, and "
        "judges its top-ranked site against ground truth (every truth pixel within 1.5 m safe). Writes "
        "landings.csv (one row per landing and preset), landings.json (P(safe) with a Wilson interval, "
        "P(no site), divert percentiles; overall, per scene, per preset) and report/index.html. Resumable. "
        + STUDY_EXIT_CODES,
    )
    p.add_argument("--scenes", required=True, help="comma-separated library scenes, or 'all'")
    p.add_argument(
        "--n", type=_positive("--n"), required=True, help="landings (rounded up to whole renders, as many per scene)"
    )
    p.add_argument("--out", required=True, type=Path, help="output directory (resumes if it holds this campaign)")
    p.add_argument(
        "--preset", choices=["fast", "thesis", "both"], default="both", help="flight software preset(s) that land"
    )
    p.add_argument(
        "--per-render",
        type=_positive("--per-render"),
        default=PER_RENDER,
        help=f"aim points (landings) sharing one rendered pair (default {PER_RENDER}; at most max(--n, {PER_RENDER}))",
    )
    p.add_argument(
        "--pose-error",
        default=DEFAULT_POSE_ERROR,
        help=f"navigation errors per frame, PoseError syntax, or 'none' (default {DEFAULT_POSE_ERROR})",
    )
    _executor_options(p)
    camera = _positive("--camera-px", IMAGE_SIZE_MAX, MIN_CAMERA_PX)
    p.add_argument("--camera-px", "--image-size", dest="camera_px", type=camera, default=None, help=argparse.SUPPRESS)
    p.add_argument(
        "--cache",
        type=Path,
        default=None,
        help="keep rendered pairs here and reuse them (campaigns that differ only in aim points, navigation "
        "errors or presets render once); default: no cache",
    )
    add_seed_options(p, 100, "scene seeds to cycle through", "the landings of every seed are pooled")
    p.add_argument(
        "--raster",
        choices=list(RASTERS),
        default=DEFAULT_RASTER,
        help="tiles (default): render every view at its GSD/2 from rasters per image tile; view: one capped "
        "raster per view (docs/scenes.md); each raster's renders are cached apart",
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    _no_figures_option(p)
    p.set_defaults(func=holding_out("landings", _landings))


def _landings(args: argparse.Namespace) -> int:
    import time

    from ground_sim import library
    from studies import landings as ld
    from studies.executor import CampaignError

    names = comma_items(args.scenes, "--scenes")
    if "all" in names and len(names) > 1:
        raise InputError(f"--scenes: 'all' already names every library scene; give it alone, got {args.scenes!r}")
    scenes = [e.name for e in library.entries()] if names == ["all"] else names
    check_backend(args)
    seeds, seed_set = resolve_seeds(args, args.seeds_default)
    check_local_room(args)
    warn_not_held_out(seeds, seed_set)  # the page says it from the campaign's seeds
    if not args.pose_error.strip():  # an unset shell variable would have meant perfect navigation, without a word
        raise InputError("--pose-error is empty: give PoseError syntax (e.g. alt=0.5,pitch=0.05) or 'none'")
    pe = None if args.pose_error.strip().lower() == "none" else args.pose_error
    c = ld.Campaign(
        tuple(scenes),
        args.n,
        tuple(seeds),
        seed_set,
        tuple(_presets(args.preset)),
        args.per_render,
        pe,
        args.camera_px,
        args.raster,
    )
    ld.claim_out_dir(c, args.out)
    drawn = seeds[: min(len(seeds), -(-c.n_groups // len(scenes)))]  # render g takes seed g // len(scenes)
    print(
        f"landings: {ld.counted(c.n_landings, 'landing')}"
        + (
            f" (--n {c.n} rounded up to whole renders of {c.per_render}, the same number for each of the "
            f"{len(scenes)} scenes)"
            if c.n_landings != c.n
            else ""
        )
        + f" in {ld.counted(c.n_groups, 'render')} over {', '.join(scenes)}; "
        f"{describe_seeds(drawn, seed_set)}; presets {', '.join(c.presets)}{camera_note(args.camera_px)}",
        file=sys.stderr,
    )
    t0 = time.time()
    note_page_owner(args.out, "landings")
    try:
        _, summary = ld.run_campaign(
            c,
            args.out,
            scheduler=args.scheduler,
            workers=args.workers,
            progress=not args.no_progress,
            cache_dir=args.cache,
            figures=not args.no_figures,
        )
    except CampaignError as exc:
        code = _campaign_failed("landings", exc)
        print(f"partial summary (complete: false): {args.out / 'landings.json'}", file=sys.stderr)
        return code
    except KeyboardInterrupt:
        print(_summary_state(args.out / "landings.json"), file=sys.stderr)
        raise
    per_scene = summary.get("per_scene") or {}
    for p, st in summary["per_preset"].items():
        lo, hi = st["p_safe_ci95"]
        print(
            f"{p:7s} P(safe) {st['p_safe']:.3f} [{lo:.3f}, {hi:.3f}]  P(no site) {st['p_no_site']:.3f}  "
            f"P(unsafe site) {st['p_unsafe']:.3f}  aim point safe {st['p_aim_safe']:.3f}  "
            f"divert p50 / p90 {_metres(st['divert_m']['p50'])} / {_metres(st['divert_m']['p90'])}  (n = {st['n']})"
        )
        if len(per_scene) > 1:  # a campaign over several scenes: each one's figure too, as the report has
            for scene, by_preset in per_scene.items():
                sc = by_preset.get(p)
                if sc:
                    slo, shi = sc["p_safe_ci95"]
                    print(
                        f"{'':7s}   {scene:<14s} P(safe) {sc['p_safe']:.3f} [{slo:.3f}, {shi:.3f}]  "
                        f"P(no site) {sc['p_no_site']:.3f}  (n = {sc['n']})"
                    )
        for why, k in summary.get("no_site_reasons", {}).get(p, {}).items():
            print(f"{'':7s}   no site x {k}: {why}")
    # the interval's caveat with the numbers, not only on the page (QA 65b L3)
    print(f"{'':7s}   [lo, hi]: {summary.get('ci95_note') or ''}")
    used = [int(x) for x in summary.get("seeds_used") or seeds]  # the landings drew these, not the whole set
    print(f"{describe_seeds(used, seed_set)}{camera_note(args.camera_px)}; wall {time.time() - t0:.0f} s")
    unused = [s for s in seeds if s not in used]
    if unused and used:  # asked for, never drawn: the campaign rests on fewer seeds than asked (QA of stop 73)
        print(
            f"note: seed{'s' if len(unused) > 1 else ''} {seed_runs(unused)} asked for but not drawn: "
            f"{summary.get('n_landings_flown', '?')} landings drew {len(used)} of the {len(seeds)} seeds; more "
            "landings (--n) reach more of them",
            file=sys.stderr,
        )
    print(f"rows:    {args.out / 'landings.csv'}\nsummary: {args.out / 'landings.json'}")
    print(f"report:  {args.out / 'report' / 'index.html'}")
    return 0


def _metres(v: float | None) -> str:
    return "-" if v is None else f"{v:.1f} m"


def register_score(subparsers: Any) -> None:
    from studies.score import FP_LIMIT_PCT

    p = subparsers.add_parser(
        "score",
        help="score any detector's output directories against ground truth (FP, CDI, DEM error, sites)",
        description="Score the output files of any detector (docs/design.md: hazard.npy, and optionally elevation.npy, "
        "state.npy and result.json's sites) against a pair's ground truth, by the design's convention: per pixel "
        "FP (undetected hazards), TP/TN/FN, CDI; DEM error; whether each site, and the top-ranked one, is truly "
        "safe over its whole 3 m footprint (DESIGN.md). PAIRS is a pair directory and OUTPUTS its output "
        "directory, or PAIRS a rendered descent (manifest.json) and OUTPUTS a directory with one output directory"
        " per pair, named as the pair directory. Exit 0 when every pair was scored with FP at or under the limit,"
        " 1 when one was over it, 3 when a pair had no usable output (each named on stderr; the others are still"
        " scored), 2 on bad usage or a pair of a descent without ground truth (named; the others are still scored);"
        " when several apply, 2 wins over 3, and 3 over 1; 4 when --csv, --json or a --figures picture could not be"
        " written once scored (named on stderr; the scores are printed), which wins over the others; a target"
        " refused before any scoring (a directory, or one that cannot be written) is bad usage, 2."
        " Without gt_hazard_i1.npy the true hazard is derived from gt_elevation, gt_depth and, when there,"
        " gt_shadow (docs/design.md). An"
        " output that maps nothing (all NaN) is usable: it calls nothing safe.",
    )
    p.add_argument("pairs", type=Path, help="a pair directory with ground truth, or a descent with manifest.json")
    p.add_argument("outputs", type=Path, help="the detector's output directory (or one per pair, by pair name)")
    p.add_argument(
        "--max-fp",
        type=float,
        default=FP_LIMIT_PCT,
        help=f"FP limit per pair in %% of the scored pixels (default {FP_LIMIT_PCT:g}, thesis Table 2.1)",
    )
    p.add_argument(
        "--csv",
        type=Path,
        default=None,
        help="also write one row per pair here (fixed columns, empty where a pair has no value)",
    )
    p.add_argument("--json", type=Path, default=None, help="also write the rows and the summary here")
    p.add_argument(
        "--figures",
        type=Path,
        default=None,
        help="draw one picture per pair here (PAIR_score.png): the sites on frame 0, the pixel scores, the truth",
    )
    p.set_defaults(func=_score)


def renders_line(cache: Path) -> str:
    """Where a study's renders are kept, and how much they hold: only the tables and the page were named, and a
    4096 px campaign's cache grows by 227 MB a pair (QA of stop 74)."""
    size = sum(f.stat().st_size for f in cache.rglob("*") if f.is_file()) if cache.is_dir() else 0
    return f"renders: {cache} ({size / 2**20:.0f} MiB; a rerun reuses them, and deleting the directory frees them)"


def _score(args: argparse.Namespace) -> int:
    import math

    from protocol.outdir import claim_out
    from reports.console import printable
    from studies.score import check_not_an_input, pair_jobs, stray_outputs, summarise

    if not (math.isfinite(args.max_fp) and 0 <= args.max_fp <= 100):
        raise InputError(f"--max-fp must be a percentage in [0, 100], got {args.max_fp:g}")
    jobs = pair_jobs(args.pairs, args.outputs)
    for option in ("csv", "json"):
        if getattr(args, option) is not None:
            check_not_an_input(getattr(args, option), jobs, args.pairs, args.outputs, f"--{option}")
    stray = stray_outputs(args.pairs, args.outputs, jobs, ours=[args.figures])
    if args.figures is not None:  # a --csv named as a pair's figure held CSV text under a .png name
        drawn_names = {f"{j.pair_dir.name}_score.png" for j in jobs}
        for option in ("csv", "json"):
            value = getattr(args, option)
            if value is not None and value.name in drawn_names and value.parent.resolve() == args.figures.resolve():
                raise InputError(f"--{option} {value} is the picture --figures draws for its pair: name another file")
    with contextlib.ExitStack() as held:
        if args.figures is not None:  # another command writing there (an evaluate) and this one undid each other
            held.enter_context(claim_out(args.figures, "score"))
        rows = _score_rows(jobs, args.figures)
    summary = summarise(rows, args.max_fp)
    _print_scores(rows, summary)
    for r in rows:  # in the table on stdout, and here: a CI log that keeps stderr says which and why
        if r.get("pair_error"):
            print(f"hazard-hil score: {r['pair']}: cannot be scored: {r['error']}", file=sys.stderr)
        elif r.get("error"):
            print(f"hazard-hil score: {r['pair']}: no usable output: {r['error']}", file=sys.stderr)
    if stray:  # skipped without a word: a typo'd name left its pair "no such output directory" and no hint why
        more = f" and {len(stray) - 8} more" if len(stray) > 8 else ""
        names = ", ".join(printable(n, 80) for n in stray[:8]) + more
        expected = ", ".join(printable(j.out_dir.name, 80) for j in jobs[:4]) + (", ..." if len(jobs) > 4 else "")
        print(
            f"note: {args.outputs} also holds {names}, which {'is' if len(stray) == 1 else 'are'} no pair of the "
            f"manifest (an output directory is named as its pair directory: {expected})",
            file=sys.stderr,
        )
    derived = [r for r in rows if r.get("truth_note") and not r.get("error")]
    if derived:  # one note for the descent, not one per pair
        more = f" (and {len(derived) - 1} more pairs likewise)" if len(derived) > 1 else ""
        print(f"note: {derived[0]['pair']}: {derived[0]['truth_note']}{more}", file=sys.stderr)
    posed = [r for r in rows if r.get("truth_poses") == "reported" and not r.get("error")]
    if posed:
        more = f" (and {len(posed) - 1} more pairs likewise)" if len(posed) > 1 else ""
        print(
            f"note: {posed[0]['pair']}: pair.json has no true_frames, so its frames' reported poses are taken as "
            f"true: the sites are placed on the ground through them, and an error in them is not seen{more}",
            file=sys.stderr,
        )
    drawn = sum("figure" in r for r in rows)
    if args.figures is not None:  # none is drawn for a pair without a usable output: say so, not a bare path
        print(f"figures: {args.figures} ({drawn} of {len(rows)} pairs)" if drawn else "figures: none, no usable output")
    unwritten = [r for r in rows if r.get("figure_error")]
    for r in unwritten:  # the scores above stand; the picture does not
        print(f"hazard-hil score: error: {r['pair']}: its figure: {r['figure_error']}", file=sys.stderr)
    if not _write_score_files(args, rows, summary) or unwritten:
        return EXIT_WRITE_FAILED
    if any(r.get("pair_error") for r in rows):  # the descent's own input, not the detector: as bad usage
        return 2
    if summary["failed"]:  # a broken submission is not a detector over its FP budget: a code of its own
        return EXIT_NO_OUTPUT
    return 0 if summary["pairs_over_fp_limit"] == 0 else 1


def _write_score_files(args: argparse.Namespace, rows: list[dict[str, Any]], summary: dict[str, Any]) -> bool:
    """Write ``--csv`` and ``--json``; False, said in one line naming the file, when the system refuses one (a full
    disk): exit 1 said "FP over the limit" for a detector that passed, and the message named no file (QA 65b L4)."""
    from reports.html import write_atomic
    from reports.jsondoc import json_text
    from studies.score import json_row, write_csv

    ok = True  # each file is tried: a refused --csv left a good --json unwritten (review of stop 65)
    for option, path, label in (("--csv", args.csv, "rows:   "), ("--json", args.json, "summary:")):
        if path is None:
            continue
        try:
            if option == "--csv":
                write_csv(rows, path)
            else:  # whole or not at all, as the csv
                write_atomic(path, json_text({"summary": summary, "rows": [json_row(r) for r in rows]}))
        except OSError as exc:  # after the scores above, which stand: only the file is missing
            why = exc.strerror or str(exc) or type(exc).__name__
            print(f"hazard-hil score: error: cannot write {option} {path}: {why}", file=sys.stderr)
            ok = False
            continue
        print(f"{label} {path}")
    return ok


SCORE_PROGRESS_PAIRS = 50  # a descent this long shows a progress bar (scoring takes ~7 ms a 128 px pair, 0.1 s at 512)


def _score_rows(jobs: list[Any], figures: Path | None) -> list[dict[str, Any]]:
    """One row per pair job of ``score``: its scores, or why it has none (``error``; ``pair_error`` when the
    pair itself, not the detector's output, is at fault)."""
    from reports.progress import Progress

    # a long descent shows its progress (3000 pairs scored for 21 s without a word; QA of stop 74), and an
    # interrupt says how far it got: the files are written whole, after every pair, so none is
    bar = Progress(len(jobs), desc="score", enabled=len(jobs) >= SCORE_PROGRESS_PAIRS)
    rows: list[dict[str, Any]] = []
    try:
        for job in jobs:
            rows.append(_score_job(job, len(jobs), figures))
            bar.update(label=job.label)
    except KeyboardInterrupt:
        drawn = f"; the figures of those pairs are in {figures}" if figures is not None and rows else ""
        print(
            ("\n" if bar.enabled and sys.stderr.isatty() else "")  # the bar's line is not ended on a terminal
            + f"hazard-hil score: interrupted after {len(rows)} of {len(jobs)} pairs: no table, --csv or --json "
            f"(written whole, once every pair is scored){drawn}; run it again",
            file=sys.stderr,
        )
        raise
    return rows


def _score_job(job: Any, n_jobs: int, figures: Path | None) -> dict[str, Any]:
    """One pair's row of ``score`` (:func:`_score_rows`)."""
    from protocol.pairdir import pair_fingerprint, read_pair
    from studies.score import ScoreError, check_read_memory, read_output, score_output

    row: dict[str, Any] = {
        "pair": job.label,
        "pair_dir": str(job.pair_dir),
        "output_dir": str(job.out_dir),
        "error": job.missing,
    }
    if job.missing is not None:  # an HIL run's pair with no Result: its truth is judged now too
        with contextlib.suppress(InputError):  # an unreadable pair is said once it has an output to score
            check_read_memory(job.pair_dir)
            _no_truth_either(row, read_pair(job.pair_dir), str(job.pair_dir))
    else:
        try:  # a pair that cannot be read, or has no truth (below), is bad input: alone, said as usage is
            check_read_memory(job.pair_dir)
            pair = read_pair(job.pair_dir)
        except InputError as exc:
            if n_jobs == 1:
                raise
            row["error"], row["pair_error"] = str(exc), True  # in a descent: named, and the others scored
            return row
        try:
            out = read_output(job.out_dir, pair.images[0].shape, job.sites, pair_fingerprint(pair.images))
        except ScoreError as exc:  # the detector's missing or broken output: that pair's failure, the rest go on
            row["error"] = str(exc) + job.hint
            _no_truth_either(row, pair, str(job.pair_dir))
        else:
            fig = None if figures is None else figures / f"{job.pair_dir.name}_score.png"
            try:
                row.update(score_output(pair, out, str(job.pair_dir), fig))
            except ScoreError as exc:  # the pair's truth, not the output
                if n_jobs == 1:
                    raise
                row["error"], row["pair_error"] = str(exc), True
            if fig is not None and not row.get("pair_error") and not row.get("figure_error"):
                row["figure"] = str(fig)
    return row


def _no_truth_either(row: dict[str, Any], pair: Any, where: str) -> None:
    """A row without a usable output (``row["error"]``) whose pair has no truth either says both, as bad input
    (``pair_error``): the truth problem was hidden until an output was given (QA 61a L6)."""
    from studies.score import truth_problem

    problem = truth_problem(pair, where)[1]
    if problem:
        row["error"], row["pair_error"] = f"{problem}; and no usable output: {row['error']}", True


EXIT_NO_OUTPUT = 3  # `score`: a pair had no usable output (missing or broken files)
# `score`: --csv or --json could not be written. The other commands exit 1 on a refused write (hil_server.cli.main),
# but score's 1 is its verdict, "FP over the limit", which a CI job must be able to tell from a full disk
EXIT_WRITE_FAILED = 4
UNMAPPED_WARN_PCT = 50.0  # a detector that leaves over half the overlap NaN is said to, whatever its FP


def _print_scores(rows: list[dict[str, Any]], s: dict[str, Any]) -> None:
    import math

    def f(v: Any, fmt: str = ".2f") -> str:
        return "-" if v is None or (isinstance(v, float) and math.isnan(v)) else format(v, fmt)

    def md(text: Any) -> str:  # a '|' in a path split the table's row; a newline ended it
        return str(text).replace("|", "\\|").replace("\n", " ")

    cols = ("pair", "FP %", "CDI %", "hazards detected %", "safe recognised %", "unmapped %", "DEM mean abs m")
    print("| " + " | ".join(cols) + " | sites safe | top site |")
    print("|---|" + "---:|" * (len(cols) - 1) + "---:|---|")
    for r in rows:
        if r["error"] is not None:
            what = "cannot be scored" if r.get("pair_error") else "no usable output"
            print(f"| {md(r['pair'])} | {what}: {md(r['error'])} |" + " |" * len(cols))
            continue
        top = {True: "truly safe", False: "**NOT safe**", None: "no site"}[r["top_site_truly_safe"]]
        if r.get("sites_unknown"):  # not "no site": the output cannot say (an interrupted `process`)
            top = r["sites_unknown"]
        if r.get("top_site_confirmed") is False:  # scored as not safe: the truth cannot vouch for all of it
            top = "**not confirmed** (footprint off frame 0, or its truth unknown)"
        over = " **over**" if r["fp_pct"] > s["fp_limit_pct"] else ""
        cells = [
            f"{f(r['fp_pct'])}{over}",
            f(r["cdi_pct"], ".1f"),
            f(r["hazards_detected_pct"], ".1f"),
            f(r["safe_recognised_pct"], ".1f"),
            f(r["unmapped_pct"], ".1f"),
            f(r.get("dem_mean_abs_m"), ".3f"),
            f"{r['sites_truly_safe']}/{r['sites']}"
            + (f" ({u} not confirmed)" if (u := r.get("sites_unconfirmed")) else ""),
            top,
        ]
        print(f"| {md(r['pair'])} | " + " | ".join(cells) + " |")
    for r in rows:  # an all-NaN map "passes" with FP 0: it called nothing, which the exit code does not say
        if r["error"] is None and (r.get("unmapped_pct") or 0.0) >= UNMAPPED_WARN_PCT:
            print(f"warning: {r['pair']}: {r['unmapped_pct']:.0f} % of the scored pixels have no hazard value "
                  "(NaN in hazard.npy, counted as not called safe)", file=sys.stderr)  # fmt: skip
        # an elevation.npy of NaN alone read "-" in the DEM column without a word, as hazard.npy's did (QA of stop 78)
        cover = r.get("dem_coverage_pct")
        if r["error"] is None and cover is not None and cover <= 100.0 - UNMAPPED_WARN_PCT:
            print(f"warning: {r['pair']}: elevation.npy has a value on {cover:.0f} % of the scored pixels "
                  "(NaN where no elevation was recovered)", file=sys.stderr)  # fmt: skip
    no_truth = sum(bool(r.get("pair_error")) for r in rows)
    failed = "".join(
        f"; {n} {what}"
        for n, what in ((s["failed"] - no_truth, "without a usable output"), (no_truth, "that cannot be scored"))
        if n
    )
    if s.get("truth_derived"):
        failed += f"; {s['truth_derived']} against a truth hazard derived from the other truth files (see the notes)"
    n_unconf = s.get("top_sites_unconfirmed", 0)
    unconfirmed = f"{n_unconf} not confirmed: footprint off frame 0; " if n_unconf else ""
    if s["scored"]:
        print(
            f"{s['scored']} of {s['pairs']} pairs scored: FP worst {f(s['fp_worst_pct'])} % "
            f"({s['pairs_over_fp_limit']} over {s['fp_limit_pct']:g} %), CDI median {f(s['cdi_median_pct'], '.1f')} % "
            f"(lowest {f(s['cdi_lowest_pct'], '.1f')} %), top site truly safe {s['top_sites_truly_safe']}/"
            f"{s['top_sites']} ({unconfirmed}{s['no_site']} without a site"
            + (f", {s['sites_unknown']} whose sites are unknown" if s.get("sites_unknown") else "")
            + f"){failed}"
        )
    else:
        print(f"no pair scored{failed}")
