"""``hazard-hil process PAIR_DIR --out OUT_DIR``: run the pipeline offline on a pair directory.

Every frame of the directory is used (2-16, frame 0 the reference: a multi-baseline sweep,
:func:`flight_sw.pipeline.run_pipeline_multi`); ``--widest-pair`` uses frames 0 and -1 only.

Writes ``elevation.npy``, ``hazard.npy``, ``state.npy``, ``psafe.npy``, with ``fast`` also
``sigma.npy`` (the elevation's 1-sigma) and ``filled.npy`` (True where the elevation is a gap fill
carried into dark shadow, not a match), ``result.json``, pictures (``dem.png``, ``hazard.png``; none with
``--no-figures``) and ``report.html``. The pair is read without its ground truth: flight software never
sees it (DESIGN.md).
The command is registered by :mod:`studies`, which hands :func:`process` a :class:`Scorer` that scores the
written outputs against the truth as ``hazard-hil score`` does and adds its figures and page section.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

if TYPE_CHECKING:
    from .pictures import Appendix


class Scorer(Protocol):
    """What the command's caller scores a run's outputs with (studies: against the pair's ground truth, as
    ``hazard-hil score`` does). The flight software hands it only the output directory it wrote."""

    def prepare(self) -> None:
        """Read and check what the scoring needs, before the pipeline runs: bad input is refused (InputError)
        before any work, and an earlier run's outputs are still there."""

    def score(self, out: Path, title: str, m_per_px: float | None) -> Appendix | None:
        """Score the outputs in ``out`` (``result.json`` and the maps are written) and write its own files there;
        what the console line and the report page add, or None when there is nothing to score against."""


def register(subparsers: argparse._SubParsersAction) -> None:
    """The ``flight`` command; ``process`` is registered by :mod:`studies` (:func:`register_process`)."""
    _register_flight(subparsers)


def register_process(
    subparsers: argparse._SubParsersAction, scorer: Callable[[argparse.Namespace], Scorer] | None = None
) -> None:
    """The ``process`` command; ``scorer(args)`` gives the :class:`Scorer` of a run (none: the outputs alone)."""
    p = subparsers.add_parser(
        "process",
        help="DEM, hazard map and safe sites from a pair directory",
        description="Run the flight pipeline offline on a pair directory (every frame: 2-16, frame 0 the "
        "reference) and write elevation.npy, hazard.npy, state.npy, psafe.npy, sigma.npy and filled.npy (fast), "
        "result.json, pictures and "
        "report.html in OUT_DIR (docs/design.md). The pipeline never reads the directory's ground truth; with one, the "
        "outputs are then scored against it as `hazard-hil score` scores them (score.json, confusion.png, "
        "dem_error.png and a section of the page). "
        "Exit 0 when the outputs are written, 1 when the system refused a write (a full disk), 2 on bad input (the "
        "pair, its poses or truth files, also one the system will not let it read; the options; an --out that "
        "cannot be written), 128 + N when signal N stopped it "
        "(130: Ctrl-C): an earlier run's outputs are removed first, so what is left is this run's alone.",
    )
    p.add_argument("pair_dir", metavar="PAIR_DIR", help="pair directory (pair.json, i1.png, i2.png, ...)")
    p.add_argument("--out", required=True, metavar="OUT_DIR", help="output directory (created)")
    p.add_argument(
        "--preset",
        default="fast",
        choices=("fast", "thesis", "fast_v1"),
        help="parameter preset: fast (flight v2, default), thesis (the reproduction), fast_v1 (issue-6 fast)",
    )
    p.add_argument(
        "--no-refine-pose",
        dest="refine_pose",
        action="store_false",
        help="take the frames' navigation poses as they are (fast refines them from the images first: "
        "docs/benchmarks/pose.md); to see what the refinement does",
    )
    p.add_argument(
        "--deadline",
        type=float,
        default=None,
        metavar="S",
        help="time budget in seconds; past it the best level reached is returned (degraded)",
    )
    p.add_argument("--sites", type=int, default=None, metavar="K", help="number of safe sites (default 5)")
    p.add_argument(
        "--aim",
        default=None,
        metavar="X,Y",
        help="the aim point (world metres): sites of equal P(safe), in steps of 0.01, are ranked by their distance "
        "to it (default 0,0: the world origin)",
    )
    p.add_argument(
        "--widest-pair",
        action="store_true",
        help="use frames 0 and -1 only (default: every frame of the directory, multi-baseline)",
    )
    p.add_argument(
        "--no-figures",
        action="store_true",
        help="write the maps, result.json and report.html without the pictures (dem.png, hazard.png and, against "
        "the truth, confusion.png and dem_error.png): a 128 px pair with its truth took 1.3 s instead of 3.7 s",
    )
    p.set_defaults(func=lambda args: _process_held(args, None if scorer is None else scorer(args)))


def _register_flight(subparsers: argparse._SubParsersAction) -> None:
    f = subparsers.add_parser(
        "flight",
        help="run our flight software on a board of your own, serving `run --flight external` over a link",
        description="Run the flight software (the `fast` pipeline, fusion, the deadline plan) on this machine - a "
        "board of your own - and serve a ground over a serial line or ZeroMQ: on the ground PC, "
        "`hazard-hil run --flight external --link serial:DEVICE@BAUD` (docs/hil.md section 6). Serves one ground "
        "session after another until stopped (exit 128 + the signal) or the link fails (exit 1); exit 2 on bad "
        "usage, before the warm-up (a device that is missing, not a serial port, held by another process or not "
        "yours to open, a bad link spec or key directory).",
    )
    f.add_argument(
        "--link",
        required=True,
        metavar="SPEC",
        help="serial:DEVICE[@BAUD] (e.g. serial:/dev/ttyUSB0@921600; BAUD 0: unpaced) or zmq:tcp://*:PORT (binds)",
    )
    f.add_argument(
        "--keys", default=None, metavar="DIR", help="zmq: this board's CURVE key dir (server.key_secret, clients/)"
    )
    f.add_argument("--insecure", action="store_true", help="zmq on loopback only: no CURVE authentication")
    f.add_argument("--threads", type=int, default=1, help="OpenCV threads (default 1: one core, as the emulation)")
    f.add_argument(
        "--link-timeout", type=float, default=4.0, metavar="S", help="a ground silent this long ends its session"
    )
    f.add_argument("--no-warm-up", dest="warm_up", action="store_false", help="skip the boot warm-up")
    f.set_defaults(func=_flight)


def _flight(args: argparse.Namespace) -> int:
    from .board import serve

    return serve(
        args.link,
        keys=args.keys,
        insecure=args.insecure,
        warm_up=args.warm_up,
        threads=args.threads,
        link_timeout=args.link_timeout,
    )


def _check_memory(pair_dir: Path, widest_pair: bool, pictures: bool = True) -> None:
    """The memory check of :func:`flight_sw.validate.check_memory`, from pair.json alone: a camera too large
    for this machine is refused before its frames are read. A pair.json that cannot be read this way is left
    to ``read_pair``, which says what is wrong with it. A pair that fits without its pictures is told so."""
    from protocol.pairdir import declared_size

    from .validate import FlightInputError, check_memory, memory_room

    size = declared_size(pair_dir)
    if size is None:
        return
    w, h, n = size
    n = 2 if widest_pair else n
    try:
        check_memory(w, h, n, pictures=pictures)  # process draws its pictures after the maps
    except FlightInputError as exc:
        if not pictures:
            raise
        try:  # with a tenth to spare: the estimate is the pipeline's measured peak, and the truth's arrays come on top
            check_memory(w, h, n, int(0.9 * memory_room()[0]))
        except FlightInputError:
            raise exc from None
        raise FlightInputError(f"{exc}; without its pictures (--no-figures) it would fit") from None


# what `process` writes in --out, or removes there when this run has none of it (an earlier run's must not stay)
PROCESS_OUTPUTS = (
    "elevation.npy",
    "hazard.npy",
    "state.npy",
    "psafe.npy",
    "sigma.npy",
    "filled.npy",
    "result.json",
    "dem.png",
    "hazard.png",
    "score.json",  # the scorer's (studies.quicklook): against the truth
    "confusion.png",
    "dem_error.png",
    "report.html",
)


def _left_after_stop(out: Path, removing: bool = False) -> str:
    """What a `process` stopped while writing left in ``out``: its own outputs only (the earlier run's went first);
    ``removing``: stopped while the earlier run's were removed, so what is left is that run's (review of stop 63:
    they were called this run's)."""
    have = [n for n in PROCESS_OUTPUTS if (out / n).is_file()]
    if removing:
        left = f"; it still holds the earlier run's {', '.join(have)}" if have else ""
        return f"process: stopped while removing an earlier run's outputs from {out}{left}; run it again"
    if not have:
        return f"process: stopped while writing {out}: nothing of this run is in it yet; run it again"
    return (
        f"process: stopped while writing {out}: it holds this run's {', '.join(have)} only"
        + ("" if "result.json" in have else " (no result.json: incomplete)")
        + "; run it again for the rest"
    )


def _save_npy(path: Path, arr: Any) -> None:
    from reports.html import save_npy_atomic

    save_npy_atomic(path, arr)


def _check_out(pair_dir: Path, out: Path) -> None:
    """Refuse an --out where an output would replace one of the pair's own files (its pair.json, a frame image
    it names, its truth): `process PAIR --out PAIR` with frames named hazard.png lost them."""
    from protocol.pairdir import TRUTH_FILES, named_images

    from .validate import FlightInputError

    inputs = [*named_images(pair_dir), *(pair_dir / n for n in ("pair.json", *TRUTH_FILES.values()))]
    existing = []
    for p in inputs:
        try:
            if p.is_file():
                existing.append(p)
        except OSError:  # a name the file system cannot hold: no file of the pair's to overwrite
            continue

    def same(a: Path, b: Path) -> bool:  # one file under two names: a case-folding file system, a hard link
        try:
            return os.path.samefile(a, b)
        except OSError:
            return False

    hit = [n for n in PROCESS_OUTPUTS if (out / n).exists() and any(same(out / n, p) for p in existing)]
    if hit:
        raise FlightInputError(
            f"--out {out}: process would replace the pair's own {', '.join(hit)}; give an output directory of its own"
        )


def _process_held(args: argparse.Namespace, scorer: Scorer | None = None) -> int:
    """:func:`_process` with its ``--out`` held (:func:`protocol.outdir.claim_out`): it wrote into a live run's
    directory, and replaced what another command was writing there (QA 64b)."""
    from protocol.outdir import claim_out

    with claim_out(args.out, "process"):
        return _process(args, scorer)


def _process(args: argparse.Namespace, scorer: Scorer | None = None) -> int:
    import dataclasses
    import time

    import numpy as np

    from protocol.pairdir import pair_fingerprint, read_pair
    from reports.html import write_atomic
    from reports.jsondoc import json_text
    from reports.plots import ground_step_m
    from reports.progress import Ticker

    from .pictures import write_process_report
    from .pipeline import PRESETS, run_pipeline_multi
    from .validate import FlightInputError, check_frames

    if args.deadline is not None and not (math.isfinite(args.deadline) and args.deadline >= 0):
        raise FlightInputError(f"--deadline must be a finite, non-negative number of seconds, got {args.deadline}")
    _check_memory(Path(args.pair_dir), args.widest_pair, not args.no_figures)
    pair = read_pair(args.pair_dir, load_truth=False)  # a pair it cannot read is said as such first
    if scorer is not None:  # its input (the truth) refused now, not after the pipeline's work
        scorer.prepare()
    _check_out(Path(args.pair_dir), Path(args.out))
    params = PRESETS[args.preset]
    if not args.refine_pose:
        params = dataclasses.replace(params, refine_pose=False)
    if args.sites is not None:
        if args.sites < 0:
            raise FlightInputError(f"--sites must be >= 0, got {args.sites}")
        params = dataclasses.replace(params, n_sites=args.sites)
    aim = _aim_point(args.aim)
    frames = [0, pair.n_frames - 1] if args.widest_pair else list(range(pair.n_frames))
    try:  # the pipeline's own input checks first: a pair it refuses is that one error, not notes then it (a 2 px
        # camera's "160 m per pixel" note came before "too small to map"; QA of stop 75)
        check_frames([pair.images[k] for k in frames], [pair.poses[k] for k in frames], pair.camera)
    except FlightInputError as exc:
        raise FlightInputError(f"{Path(args.pair_dir) / 'pair.json'}: {exc}") from None
    for note in pair.notes:  # conversions and repairs the reader made: into result.json and onto the page too
        print(f"note: {note}", file=sys.stderr)
    # a crushed frame the run leaves out (--widest-pair) is no warning on its maps
    unused = {text for k, text in pair.shallow_warnings.items() if k not in frames}
    reader_warnings = [text for text in pair.warnings if text not in unused]
    for text in reader_warnings:  # implausible scales, a frame the 16-bit shift crushed: as the pipeline's warnings
        print(f"warning: {text}", file=sys.stderr)
    # minutes at 4096 px went without a word
    shape = f"{pair.camera.width}x{pair.camera.height} px"
    ticker = Ticker(f"process: {len(frames)} frames of {shape}, working", since=time.monotonic())
    try:
        with ticker:
            res = run_pipeline_multi(
                [pair.images[k] for k in frames],
                [pair.poses[k] for k in frames],
                pair.camera,
                preset=params,
                deadline_s=args.deadline,
                altimeter_m=[pair.altimeter_m[k] for k in frames],  # per frame used (NaN: none)
                sun_elevation_deg=pair.sun.elevation_deg if pair.sun else None,  # the shading cues' sun (optional)
                sun_azimuth_deg=pair.sun.azimuth_deg if pair.sun else None,
                frame_numbers=frames,  # --widest-pair: its messages name the directory's frames
                nominal_site_xy=aim,
            )
    except FlightInputError as exc:  # the pipeline's checks of the camera and poses: name the file they came from
        raise FlightInputError(f"{Path(args.pair_dir) / 'pair.json'}: {exc}") from None
    out = Path(args.out)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise FlightInputError(f"--out {out}: cannot create ({exc.strerror})") from None
    earlier = [n for n in PROCESS_OUTPUTS if (out / n).is_file()]
    if earlier:  # a user's hazard.png of their own went without a word; other files there are kept
        print(f"note: {out}: replacing {', '.join(earlier[:4])}{' ...' if len(earlier) > 4 else ''}", file=sys.stderr)
    doc: dict[str, Any] = {
        "pair_dir": str(Path(args.pair_dir).resolve()),
        "pair_fingerprint": pair_fingerprint(pair.images),  # `score` refuses this output against another pair
        "preset": args.preset,
        "frames": len(frames),
        "frames_used": frames,  # the directory's frames the run read (--widest-pair: the first and the last)
        "frames_in_dir": pair.n_frames,
        "figures": not args.no_figures,  # False: --no-figures, no picture was drawn by request
        "params": res.params,
        "level": res.level,
        "degraded": res.degraded,
        "valid_fraction": res.valid_fraction,
        "timings": res.timings,
        "info": res.info,
        "grid": {
            "origin_xy": list(res.grid.origin_xy),
            "cell_m": res.grid.cell_m,
            "shape": list(res.grid.hazard.shape),
            "rows_toward": "-Y",
        },
        "aim_xy": list(aim),
        "sites": [s.to_dict() for s in res.sites],
        "no_site_reason": res.info.get("no_site_reason", ""),
        "covered_fraction": float(res.covered.mean()),
        "unsafe_fraction": float(np.mean(res.hazard[res.covered] >= 1)) if res.covered.any() else None,
    }
    messages = _process_messages(res, pair, out, frames)
    off = _aim_off_map(aim, res.grid)
    if off:  # sites bunched in the map's corner nearest an aim 190 m away, without a word (sites QA of stop 75)
        messages.append((False, f"{out}: {off}"))
    # the reader's warnings (said before the pipeline ran) and the run's; the reader's notes too: said on stderr
    # alone, a pair in km left a DEM in km with an empty warnings list (QA of stop 75)
    doc["warnings"] = [*reader_warnings, *(text.removeprefix("warning: ") for warn, text in messages if warn)]
    doc["notes"] = list(pair.notes)
    # the run's own notes (an aim point off the map, poses refined or left unchecked, stages skipped) had been said
    # on stdout alone (QA of stop 79)
    doc["run_notes"] = [text.removeprefix(f"{out}: ") for warn, text in messages if not warn]
    # the earlier run's outputs go first, each of this run's is written whole beside its target and renamed over
    # it, result.json after the arrays and the pictures after it: an interrupted run leaves only its own files,
    # never a mix of two runs that `score` took for one (a kill mid-write left the old result.json and pictures
    # beside new maps; stop 63's QA)
    with Ticker(f"process: writing the maps and the report of {out}", since=ticker.since):
        removing = True
        try:
            for name in sorted(earlier, key=lambda n: n != "result.json"):  # the record of the earlier run first
                (out / name).unlink(missing_ok=True)
            for name in PROCESS_OUTPUTS:  # what a run killed outright mid-write left beside its target (write_atomic's)
                for tmp in out.glob(f".{name}.*"):
                    tmp.unlink(missing_ok=True)
            removing = False
            _save_npy(out / "elevation.npy", res.elevation)
            _save_npy(out / "hazard.npy", res.hazard)
            _save_npy(out / "state.npy", res.state)
            _save_npy(out / "psafe.npy", res.psafe)
            if res.sigma is not None:  # v2: the elevation's 1-sigma (m); a gap fill's is large
                _save_npy(out / "sigma.npy", res.sigma)
            if res.filled is not None:  # v2: True where elevation.npy holds a gap fill (dark shadow), not a match
                _save_npy(out / "filled.npy", res.filled)
            write_atomic(out / "result.json", json_text(doc))
            gsd = ground_step_m(res.world_xy)
            name = Path(args.pair_dir).resolve().name  # a saved PNG names its pair: only its folder did
            head = f"{name}: " if name else ""
            appendix, unscored = None, None
            if scorer is not None:
                try:
                    appendix = scorer.score(out, head, gsd)
                except OSError as exc:  # its own files refused: the flight side's pictures and page still come
                    unscored = exc
            write_process_report(out, pair.images[0], res, doc, appendix, gsd, figures=not args.no_figures)
        except BaseException:  # a Ctrl-C, a SIGTERM, a full disk: what is there is this run's alone, and said
            print(_left_after_stop(out, removing), file=sys.stderr)
            raise
    fills = res.info.get("dem_filled_fraction")
    line = (
        f"{res.level}{' (degraded)' if res.degraded else ''}: "
        f"DEM on {res.valid_fraction:.1%} of the overlap its poses give"
        f"{'' if fills is None else f' ({fills:.1%} gap fill)'}, "
        f"{len(res.sites)} sites"
        + (f" ({res.info['no_site_reason']})" if not res.sites and res.info.get("no_site_reason") else "")
        + f", {res.timings['total']['wall_s']:.3f} s wall ({res.timings['total']['cpu_s']:.3f} s CPU)"
    )
    if pair.n_frames > 2:  # the page said "2 frames" of a 4-frame directory, naming none (QA of stop 78)
        heights = ", ".join(f"{k} ({float(pair.poses[k].position[2]):.0f} m)" for k in frames)
        line += f"; frames {heights} of {pair.n_frames}"
    if appendix is not None:
        line += appendix.line
    print(f"{out}: {line}")
    for warn, text in messages:
        print(text, file=sys.stderr if warn else sys.stdout)
    for text in [] if appendix is None else appendix.notes:
        print(text, file=sys.stderr)
    print(f"report: {out / 'report.html'}")
    if unscored is not None:  # the maps, result.json and the page stand; the scores against the truth do not
        raise unscored
    return 0


def _aim_point(text: str | None) -> tuple[float, float]:
    """``--aim X,Y`` as world metres; the world origin when not given."""
    from .validate import FlightInputError

    if text is None:
        return (0.0, 0.0)
    try:
        x, y = (float(v) for v in text.split(","))
    except ValueError:
        raise FlightInputError(f"--aim must be X,Y in metres, got {text!r}") from None
    if not (math.isfinite(x) and math.isfinite(y)):
        raise FlightInputError(f"--aim must be finite, got {text!r}")
    return (x, y)


def _aim_off_map(aim: tuple[float, float], grid: Any) -> str:
    """A note when the aim point lies outside the mapped ground (the grid's cells with a state), else ""."""
    import numpy as np

    from protocol.pairdir import STATE_OUTSIDE

    mapped = np.asarray(grid.state) != STATE_OUTSIDE
    if not mapped.any():
        return ""
    X, Y = grid.cell_xy()
    x, y = X[mapped], Y[mapped]
    half = 0.5 * float(grid.cell_m)
    if x.min() - half <= aim[0] <= x.max() + half and y.min() - half <= aim[1] <= y.max() + half:
        return ""
    return (
        f"the aim point ({aim[0]:g}, {aim[1]:g}) lies outside the mapped ground (x {x.min():.0f} to {x.max():.0f} m, "
        f"y {y.min():.0f} to {y.max():.0f} m): the sites are the safe ones nearest it, not near it (--aim)"
    )


def _process_messages(res: Any, pair: Any, out: Path, frames: list[int] | None = None) -> list[tuple[bool, str]]:
    """What `process` says of a run beyond its summary line, in order: (is a warning, text). Warnings go to stderr,
    and also into result.json (``warnings``) and the report page: the page showed a run on swapped frames as a green
    "full" (QA of stop 66). ``frames``: the directory's frames the run used (default: all)."""
    msgs: list[tuple[bool, str]] = []
    # frames the reader's common 16-bit shift crushed (its warning names them): the noise readings compare them
    crushed = [k for k in pair.shallow_frames if frames is None or k in frames]

    from protocol.plan import plan_note

    from .kernels import kernels_note, missing_kernels
    from .pose_refine import DISAGREES, NO_OVERLAP, REPEATED, UNMATCHED

    def say(text: str, file: Any = None) -> None:
        msgs.append((file is sys.stderr, text))

    slow = kernels_note(missing_kernels())
    if slow:  # an optional build that failed: every timing of this install is the numpy fallback's
        say(f"warning: {slow}", file=sys.stderr)
    if res.degraded:  # what the deadline left out, and why (the plan's figures, as the HIL ground shows them)
        skipped = list(res.info.get("skipped", ()))
        why = plan_note(res.info.get("plan"), skipped)
        say(f"{out}: skipped {', '.join(skipped) or 'nothing'}" + (f"; {why}" if why else ""))
    if "psafe_fallback" in res.info:  # the trees' calibration does not hold here: FP 1.6-5 % at 128 px
        say(f"warning: {res.info['psafe_fallback']}: P(safe) falls back to the Gaussian rule, whose FP is "
              "higher (docs/benchmarks/pipeline.md)", file=sys.stderr)  # fmt: skip
    for f in res.info.get("noisy_frames", ()):  # nothing else tells a noisy image: the DEM 3-5x worse, unsaid
        others, k, dn = [f"{v:.1f}" for v in f["others_dn"]], f["frame"], f["noise_dn"]
        # beside a frame the common shift crushed, a clean frame reads noisy (QA of stop 75)
        low = [j for j in crushed if j != k]
        why = (
            f"likely because frame {', '.join(map(str, low))} reads too little: its 16-bit values crushed by the "
            "pair's common 8-bit shift, as warned above"
            if low
            else "a sensor fault or a damaged image"
        )
        say(f"warning: frame {k}'s image is noisy: its pixel noise reads ~{dn:.0f} grey levels against "
              f"{', '.join(others)} in the other frame{'s' if len(others) > 1 else ''} ({why}); the maps rest on "
              "it, and their elevations are the worse for it (result.json info.noisy_frames)",
              file=sys.stderr)  # fmt: skip
    for f in res.info.get("blank_frames", ()):  # frame 0 blank: every other frame "could not check", unexplained
        others, k = [f"{v:.1f}" for v in f["others_dn"]], f["frame"]
        # a 16-bit frame the common shift crushed is no black or lost image: the reader's warning names its cause
        why = (
            "its 16-bit values crushed to a few grey levels by the pair's common 8-bit shift, as warned above"
            if k in crushed
            else "a black, saturated or lost image, or mostly so"
        )
        say(f"warning: frame {k}'s image is blank: its pixel-scale detail reads {f['noise_dn']:.1f} grey levels "
              f"against {', '.join(others)} in the other frame{'s' if len(others) > 1 else ''} ({why}); little or "
              "nothing in it can be matched (result.json info.blank_frames)", file=sys.stderr)  # fmt: skip
    if "altimeter_disagreement" in res.info:
        say(f"warning: {res.info['altimeter_disagreement']}; no site is offered on this map (result.json info)",
              file=sys.stderr)  # fmt: skip
    if res.info.get("altimeter_dem_unchecked"):  # not a fault: too little DEM where the beam lands
        say(f"{out}: {res.info['altimeter_dem_unchecked']}")
    side = min(pair.camera.width, pair.camera.height)
    cam = pair.camera
    if not (0.0 <= cam.cx <= cam.width and 0.0 <= cam.cy <= cam.height):  # allowed (a cropped sensor), rarely meant
        say(f"warning: the camera's principal point ({cam.cx:g}, {cam.cy:g}) lies off its {cam.width}x{cam.height} "
              "image: check pair.json's camera (a wrong one gave a DEM 23 m off)", file=sys.stderr)  # fmt: skip
    refined = _refined_poses(res.info.get("pose_refinement"))
    if refined:  # a correction was said only in result.json (stop 59's QA)
        say(f"{out}: navigation poses refined from the images: {'; '.join(refined)}")
    entries = _pose_entries(res.info.get("pose_refinement"))
    on_scale = [k for k, f, _ in entries if f.get("scale_disagrees")]  # the ground against frame 0's altimeter
    checked = [k for k, f, _ in entries if f.get("ground_gap_m") is not None]  # the ones it could be checked on
    for k, verdict, why in _unverified_poses(res.info.get("pose_refinement"), side):
        # the maps then rest on poses the images did not confirm (swapped or mislabelled frames, a gross pose error,
        # or terrain too bland to match): a 46 m DEM error on swapped frames looked like any other "full" run
        if verdict == NO_OVERLAP:  # never left out: geometry, not evidence against the frame
            # the navigation poses say the frames share too little ground to compare: nothing in the images is
            # against the pose, and a warning on every clean deep descent (29 in one QA pass) taught users to
            # skip warnings
            # "the maps rest on it" read wrong of a frame 2 km off that added nothing to them (QA 74)
            say(f"{out}: frame {k}: its pose is not checked by the images ({why}); what it adds to the maps rests on "
                  "it as navigation reports it, and a fault in it would go unseen")  # fmt: skip
        elif verdict == DISAGREES and k in on_scale:  # the ground against frame 0's altimeter: either may be wrong
            rest = "it is left out of the maps" if k in res.info.get("frames_dropped", ()) else "the maps rest on it"
            # a wrong frame-0 reading put every frame's pose at fault (pose QA of stop 75): the two are not told apart
            also = (
                f"; every frame checked ({', '.join(map(str, on_scale))}) disagrees alike, which points to frame 0's "
                "altimeter reading"
                if len(on_scale) > 1 and len(on_scale) == len(checked)
                else ""
            )
            say(f"warning: frame {k}: its images and navigation pose put the ground away from frame 0's altimeter "
                  f"({why}): the pose or frame 0's altimeter reading is wrong{also}; {rest} (result.json "
                  "info.pose_refinement)", file=sys.stderr)  # fmt: skip
        elif verdict == DISAGREES:  # matched, and the images ask for more than a navigation error
            rest = "it is left out of the maps" if k in res.info.get("frames_dropped", ()) else "the maps rest on it"
            say(f"warning: frame {k}: the images disagree with its navigation pose ({why}: more than a navigation "
                  f"error should be, so the refinement kept the pose); {rest} (result.json "
                  "info.pose_refinement)", file=sys.stderr)  # fmt: skip
        elif verdict in (UNMATCHED, REPEATED):  # texture, nothing consistent where the pose says; or one image twice
            rest = "it is left out of the maps" if k in res.info.get("frames_dropped", ()) else "the maps rest on it"
            # a reason that names its cause (the same image twice) is not followed by the list of causes
            causes = "" if verdict == REPEATED else ": another or a damaged image, or a pose far from the one declared"
            say(f"warning: frame {k}: its image does not match where its navigation pose says ({why}{causes}); "
                  f"{rest} (result.json info.pose_refinement)", file=sys.stderr)  # fmt: skip
        else:
            say(f"warning: frame {k}: the images could not check its navigation pose ({why}); the maps rest on it "
                  "unchecked (result.json info.pose_refinement)", file=sys.stderr)  # fmt: skip
    for k, why in _degenerate_poses(res.info.get("pose_refinement"), side):  # a fallback is said (issue 10)
        # not a warning: matched, nothing against the pose, but the geometry cannot fix it (a 1 deg pitch of a
        # highland approach 250/125 pair went by in silence with its DEM 10.6 m off; stop 60's QA F7)
        used = len(frames) if frames is not None else pair.n_frames
        if used == 2:  # a pair's fit is of both frames' attitudes: not the lower frame's fault alone
            say(f"{out}: frames {(frames or [0])[0]} and {k}: the images matched but cannot fix the pair's poses "
                  f"({why}); the maps rest on them as navigation reports them")  # fmt: skip
        else:
            say(f"{out}: frame {k}: the images matched but cannot fix its pose ({why}); the maps rest on it as "
                  "navigation reports it")  # fmt: skip
    if res.info.get("sites_withheld") and "altimeter_disagreement" not in res.info:  # the pose warnings above
        say(f"warning: {res.info['sites_withheld']}", file=sys.stderr)  # do not say what it costs the sites
    return msgs


def _refined_poses(info: Any) -> list[str]:
    """Say "frame k (relative rotation corrected by r deg)" for each frame the images refined."""
    if not isinstance(info, dict):
        return []
    out = []
    for i, f in enumerate(info.get("frames") or [{"frame": 1, **info}]):
        if isinstance(f, dict) and f.get("refined"):
            rot = float(f.get("relative_rotation_correction_deg") or 0.0)
            # against: a frame too far below frame 0 to share its ground, checked with one above it (pose_refine._chain)
            rel = f"against frame {f['against']}, " if f.get("against") else ""
            what = f"relative rotation corrected by {rot:.2f} deg"
            turn = f.get("translation_dir_change_deg")
            if f.get("relative_rotation_held") and turn is not None:  # the rest of an attitude error went here
                what = (
                    f"near-nadir: relative rotation held across the view, corrected by {rot:.2f} deg (its roll about "
                    f"the optical axis fitted), the baseline turned {float(turn):.2f} deg, which the images cannot "
                    "tell from a rotation across the view"
                )
            out.append(f"frame {int(f.get('frame', i + 1))} ({rel}{what})")
    return out


def _pose_entries(info: Any) -> list[tuple[int, dict[str, Any], str]]:
    """(frame, entry, reason) for each frame of ``info["pose_refinement"]`` (a pair's own fit as frame 1), the
    reason prefixed with the frame a chained fit was checked against."""
    if not isinstance(info, dict):
        return []
    frames = info.get("frames") or [{"frame": 1, **info}]
    return [
        (
            int(f.get("frame", i + 1)),
            f,
            (f"against frame {f['against']}: " if f.get("against") else "") + str(f.get("reason", "")),
        )
        for i, f in enumerate(frames)
        if isinstance(f, dict)
    ]


def _degenerate_poses(info: Any, side: int) -> list[tuple[int, str]]:
    """(frame, reason) where pose refinement fell back to the navigation pose on geometry that cannot fix it
    (:data:`flight_sw.pose_refine.DEGENERATE`), on images of at least ``pose_refine.CHECK_MIN_SIDE`` px."""
    from .pose_refine import CHECK_MIN_SIDE, DEGENERATE

    if side < CHECK_MIN_SIDE:
        return []
    return [(k, why) for k, f, why in _pose_entries(info) if f.get("verdict") == DEGENERATE]


def _unverified_poses(info: Any, side: int) -> list[tuple[int, str, str]]:
    """(frame, verdict, reason) where pose refinement kept the navigation pose because it could not match the images, or
    because they ask for a correction no navigation error explains (:func:`flight_sw.pose_refine.refine_pair`'s
    fallbacks that mean "no evidence" or "evidence against", not "navigation agreed"), from
    ``info["pose_refinement"]``. None for images narrower than ``pose_refine.CHECK_MIN_SIDE``: there the
    refinement cannot check clean pairs either (too few matches, an overlap under its four track windows), so a
    warning would say nothing about these frames."""
    from .pose_refine import unchecked

    return [
        (k, str(f["verdict"]), why)
        for k, f, why in _pose_entries(info)
        if not f.get("refined") and unchecked(str(f.get("verdict", "")), side)
    ]
