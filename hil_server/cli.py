"""The ``hazard-hil`` console script, and the HIL server's own subcommands.

Each package contributes its subcommands through a ``cli`` module with
``register(subparsers)``, declared as an entry point in the group
``hazard_hil.commands`` (pyproject.toml). This module only assembles them, so
packages stay independent: ground_sim never imports flight_sw, and nothing
imports studies. Heavy imports happen inside the command handlers, keeping
``hazard-hil --help`` fast.

A handler is stored as ``func`` on the parsed namespace and returns an exit
code. Errors meant for users are raised as :class:`protocol.errors.InputError`
(or a subclass) and printed as one line, not a traceback.

The HIL server's subcommands: ``budgets``, ``calibrate`` (emulation), ``run``,
``demo``, ``regress`` (runs).
"""

from __future__ import annotations

import argparse
import errno
import shutil
import sys
import warnings
from importlib import metadata
from pathlib import Path
from typing import NoReturn

from protocol.errors import InputError, comma_items, os_error_text
from protocol.outdir import refuse_if_held

ENTRY_POINT_GROUP = "hazard_hil.commands"
# help order of the project's own packages; commands of other installed packages follow by name
_ORDER = ("ground_sim", "flight_sw", "hil_server", "studies")
# `process` is registered by studies (it scores against the truth, which flight_sw never reads) but is listed with
# the flight software's commands, where a user looks for it
_LISTED_AFTER = {"process": "scenes"}


def register(subparsers: argparse._SubParsersAction) -> None:
    _register_emulation(subparsers)
    _register_runs(subparsers)


def version() -> str:
    try:
        return metadata.version("hazard-hil")
    except metadata.PackageNotFoundError:
        return "unknown (not installed)"


class HelpFormatter(argparse.RawDescriptionHelpFormatter):
    """Descriptions as written; every option's help ends with its default unless it already names one."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        if (
            "default" not in text
            and action.default not in (None, False, argparse.SUPPRESS)
            and (action.option_strings or action.nargs in ("?", "*"))
            # a flag that switches something off (store_false) would read "--no-warm-up ... (default: True)"
            and not isinstance(action, argparse._StoreConstAction)
        ):
            text += " (default: %(default)s)"
        return text


class OneLineErrors(argparse.ArgumentParser):
    """A usage error is one line on stderr, as every other bad input is (argparse prints the whole usage block
    first), pointing at ``--help``; exit 2."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


class CommandParser(OneLineErrors):
    """Every subcommand's parser: the shared help format."""

    def __init__(self, *args, **kwargs) -> None:
        kwargs.setdefault("formatter_class", HelpFormatter)
        super().__init__(*args, **kwargs)


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineErrors(
        prog="hazard-hil",
        description="Hardware-in-the-loop emulation of vision-based hazard detection for planetary landing.",
        formatter_class=HelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {version()}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=CommandParser)
    eps = sorted(
        metadata.entry_points(group=ENTRY_POINT_GROUP),
        key=lambda e: (_ORDER.index(e.name) if e.name in _ORDER else len(_ORDER), e.name),
    )
    if not eps:  # running from a source tree that was never installed
        raise SystemExit("hazard-hil: no commands registered; install the package (make install)")
    for ep in eps:
        ep.load()(sub)
    listed = sub._choices_actions  # argparse's list of the commands' help lines, in the order --help shows them
    for name, after in _LISTED_AFTER.items():
        move = [a for a in listed if a.dest == name]
        anchor = [i for i, a in enumerate(listed) if a.dest == after]
        if move and anchor:
            listed.remove(move[0])
            listed.insert(anchor[0] + 1, move[0])
    return parser


class Terminated(KeyboardInterrupt):
    """SIGTERM or SIGHUP, handled as a Ctrl-C is: worker pools ended, partial results saved, then exit 128 + N.

    Without it a plain ``kill PID`` ended the process at once, and its pool's workers (spawned, each its own
    process) went on rendering, then waited for work for good."""

    def __init__(self, signum: int) -> None:
        super().__init__(signum)
        self.signum = signum


def _terminate(signum: int, _frame: object) -> NoReturn:
    raise Terminated(signum)


def _stop_signals() -> dict[int, object]:
    """Install :func:`_terminate` for SIGTERM and SIGHUP (a hangup left ignored, as under nohup, stays so);
    returns the handlers replaced. Commands with their own handling (``run``, ``flight``) install theirs."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        return {}
    saved: dict[int, object] = {}
    for sig in (signal.SIGTERM, signal.SIGHUP):
        old = signal.getsignal(sig)
        if old is not signal.SIG_IGN:
            saved[sig] = signal.signal(sig, _terminate)
    return saved


def console(text: str = "") -> None:
    """``print`` to stdout for a long command's progress: once stdout is closed (piped into ``head``), what follows
    goes nowhere and the command goes on. A BrokenPipeError ended `run` part-way, its summary still "in
    progress" (QA of stop 71)."""
    try:
        print(text, flush=True)
    except BrokenPipeError:
        import os

        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())  # Python's own advice: the interpreter's last flush fails too else
        os.close(devnull)


def main(argv: list[str] | None = None) -> int:
    import signal

    parser = build_parser()
    args, extra = parser.parse_known_args(argv)
    if extra:  # named by the command they were given to, pointing at its --help (argparse names the top level)
        where = f"hazard-hil {args.command}" if getattr(args, "command", None) else "hazard-hil"
        print(f"{where}: error: unrecognized arguments: {' '.join(extra)} (see {where} --help)", file=sys.stderr)
        return 2
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    saved = _stop_signals()
    shown = warnings.showwarning
    try:  # from the moment the handlers are in: a stop while modules still import is a clean exit 128 + N too
        warnings.showwarning = _one_line_warning(shown)
        _no_empty_paths(sys.argv[1:] if argv is None else argv)
        for option in ("out", "cache", "figures"):  # the directories a command creates
            if getattr(args, option, None) is not None:
                check_out_dir(Path(getattr(args, option)), f"--{option}")
        csv_path, json_path = getattr(args, "csv", None), getattr(args, "json", None)
        if isinstance(csv_path, Path) and isinstance(json_path, Path) and csv_path.resolve() == json_path.resolve():
            raise InputError(f"--csv and --json name the same file ({csv_path}): the second would overwrite the first")
        for option in ("csv", "json"):  # files a command writes at its end (`score`), after all its work
            value = getattr(args, option, None)
            if isinstance(value, Path):
                if value.is_dir():
                    raise InputError(f"--{option} {value} is a directory, not a file")
                check_out_dir(value.parent, f"--{option}'s directory")
                refuse_if_held(value.parent, f"--{option}'s directory")
        return int(args.func(args) or 0)
    except Terminated as exc:
        print(f"stopped by {signal.Signals(exc.signum).name}", file=sys.stderr)
        return 128 + exc.signum
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except InputError as exc:
        print(f"hazard-hil {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # the system refused a read or write the command needed: a full disk, a file in the way
        print(f"hazard-hil {args.command}: error: {os_error_text(exc)}{_full_disk_where(exc, args)}", file=sys.stderr)
        return 1
    except MemoryError as exc:  # past the memory checks (another process took the room): one line, not a traceback
        why = str(exc) or "an allocation failed"
        print(f"hazard-hil {args.command}: error: out of memory ({why}): free some, or use a smaller camera",
              file=sys.stderr)  # fmt: skip
        return 1
    finally:
        warnings.showwarning = shown
        for sig, old in saved.items():
            signal.signal(sig, old)  # type: ignore[arg-type]


FULL_DISK_BYTES = 1 << 20  # a disk with less than this free is named as the full one


def _full_disk_where(exc: OSError, args: argparse.Namespace) -> str:
    """For a full disk whose error names no file (numpy's, a library's write): which of the command's output
    locations is on a disk with no room left, e.g. `` (the disk holding --out r1 is full)``; else ""."""
    if exc.filename is not None or exc.errno not in (errno.ENOSPC, errno.EDQUOT):
        return ""
    from hil_server.budgets import calibration_path

    places = [(f"--{o}", getattr(args, o, None)) for o in ("out", "cache", "figures", "csv", "json", "baseline")]
    places.append(("the calibration store", calibration_path()))
    full = []
    for label, value in places:
        if not isinstance(value, str | Path):
            continue
        probe = Path(value).absolute()
        while not probe.exists() and probe != probe.parent:
            probe = probe.parent
        try:
            free = shutil.disk_usage(probe).free
        except OSError:
            continue
        if free < FULL_DISK_BYTES:
            full.append(f"{label} {value}" if label.startswith("--") else f"{label} ({value})")
    return f" (the disk holding {' and '.join(full)} is full)" if full else ""


def _one_line_warning(fallback):
    """``warnings.showwarning`` that says our own warnings as one line, ``warning: ...``, not as Python's source
    file, line number and code line; any other warning is shown as Python shows it (``fallback``)."""
    from hil_server.budgets import UncalibratedWarning

    said: set[str] = set()

    def show(message, category, filename, lineno, file=None, line=None):
        if issubclass(category, UncalibratedWarning):
            if str(message) not in said:  # once per command: each place that asks the host's speed warned (3x a run)
                said.add(str(message))
                print(f"warning: {message}", file=file or sys.stderr)
        else:
            fallback(message, category, filename, lineno, file, line)

    return show


PATH_OPTIONS = ("--out", "--cache", "--figures", "--csv", "--json")


def _no_empty_paths(argv: list[str]) -> None:
    """``--out ''`` is an empty path, which pathlib reads as the current directory: ``process`` wrote its files
    among the user's. Refused, as any other path that names nothing."""
    for i, a in enumerate(argv):
        name, eq, value = a.partition("=")
        if name in PATH_OPTIONS and (
            (eq and not value.strip()) or (not eq and i + 1 < len(argv) and not argv[i + 1].strip())
        ):
            raise InputError(f"{name} must name a path, got an empty one")


def check_out_dir(out: Path, option: str = "--out") -> None:
    """Refuse, before any work, an output directory that cannot become one: an existing file, a path under one,
    or one whose nearest existing directory cannot be written (every command creates its ``--out``, some only
    after minutes of work). Nothing is created here: a command refused later leaves nothing half-made."""
    import tempfile

    for q in (out, *out.parents):
        if q.exists():
            if not q.is_dir():
                where = "is a file, not a directory" if q == out else f"is under {q}, which is not a directory"
                raise InputError(f"{option} {out} {where}")
            break
    else:
        q = Path(".")
    try:  # a nameless file made and dropped in the nearest existing directory: the only proof for root, whom
        # permission bits do not stop (/proc, a read-only file system)
        with tempfile.TemporaryFile(dir=q):
            pass
    except OSError as exc:
        why = exc.strerror or str(exc)
        raise InputError(f"{option} {out} cannot be written: no file can be made in {q} ({why})") from None


# --------------------------------------------------------------------------- emulation
def _register_emulation(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "budgets",
        help="list processor budgets and the duty cycle each means on this host",
        description="List the processor budgets (hil_server/budgets.toml) with the CPU duty "
        "cycle each one means on this host.",
    )
    p.add_argument("--file", default=None, help="budget file (default: the packaged budgets.toml)")
    p.add_argument("--sources", action="store_true", help="also print where each figure comes from")
    p.set_defaults(func=_budgets)

    c = subparsers.add_parser(
        "calibrate",
        help="measure this host's single-core speed and the throttle's efficiency, and store them",
        description="Run the reference workload (plane-sweep image operations) on one "
        "thread, then under the emulated processor's throttle at a grid of duty cycles, and store this host's "
        "speed and how much work a throttled CPU-second does, for the budgets.",
    )
    c.add_argument("--seconds", type=float, default=3.0, help="CPU seconds to measure (default 3)")
    c.add_argument(
        "--duty-cycles",
        type=_duty_list,
        default=None,
        metavar="F,F,...",
        help="duty cycles in [0.001, 1) to measure the throttle's efficiency at (default "
        "0.005,0.01,0.02,0.05,0.1,0.2,0.5: about 30 s)",
    )
    c.add_argument("--file", default=None, help="budget file whose anchor to report against")
    c.set_defaults(func=_calibrate)


def _budgets(args: argparse.Namespace) -> int:
    import warnings

    from hil_server.budgets import (
        FLIGHT_BASE_MIB,
        FLIGHT_BYTES_PER_PIXEL,
        FLIGHT_FLOOR_MIB,
        FLIGHT_RSS_MARGIN,
        UncalibratedWarning,
        calibration_notes,
        calibration_path,
        load_budgets,
        load_calibration,
        max_image_side,
    )
    from protocol.pairdir import IMAGE_SIZE_MAX

    budgets = load_budgets(args.file)
    cal = load_calibration()
    anchor = next(iter(budgets.values())).anchor
    for note in calibration_notes(cal):
        print(f"warning: {note}", file=sys.stderr)
    if cal is None:
        host_dmips = anchor.dmips
    else:
        host_dmips = cal.host_dmips(anchor)
        print(
            f"host: {cal.cpu_model} on {cal.hostname}, {host_dmips:.0f} DMIPS per core "
            f"(calibrated {cal.measured_at}, {calibration_path()})"
        )
    width = max(15, *(len(n) + 2 for n in budgets))
    print(
        f"{'budget':<{width}}{'DMIPS':>8}{'share':>9}{'slower':>10}{'duty':>9}{'memory':>11}{'max image':>11}"
        f"{'deadline':>10}  {'link':<16}description"
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UncalibratedWarning)  # said once above
        for b in budgets.values():
            dmips = "host" if b.is_host else f"{b.cpu_dmips:.0f}"
            link = b.link if b.baud is None else f"{b.link} {b.baud}"
            duty = b.duty(cal)
            side = max_image_side(b.memory_mib)
            # `render` and `run --image-size` make at most IMAGE_SIZE_MAX px: a larger "max image" is none they make
            camera = "none" if side <= 0 else f">={IMAGE_SIZE_MAX}" if side > IMAGE_SIZE_MAX else f"{side}x{side}"
            share, applied = f"{100 * duty.effective:.3g}%", f"{100 * duty.applied:.3g}%"
            memory = f"{b.memory_mib:g} MiB" if b.memory_mib < 10**5 else f"{b.memory_mib / 1024:.0f} GiB"
            print(
                f"{b.name:<{width}}{dmips:>8}{share:>9}{f'{1 / duty.effective:.1f}x':>10}{applied:>9}"
                f"{memory:>11}{camera:>11}{b.deadline_s:>9g}s  {link:<16}{b.description}"
            )
            if args.sources:
                print(f"{'':<{width}}source: {b.source}")
            for why in _unrunnable(b, duty, host_dmips):
                print(f"{'':<{width}}note: {why}")
    print(
        "share: the fraction of one host core's full-speed work the budget stands for; duty: the CPU duty cycle "
        "that delivers it (higher: a throttled CPU-second does less work, `hazard-hil calibrate` measures how much)"
    )
    print(
        f"max image: the largest square camera whose flight process fits the memory ceiling (peak private RSS ~"
        f"{FLIGHT_BASE_MIB:.0f} MiB + {FLIGHT_BYTES_PER_PIXEL:.0f} B/pixel, at least {FLIGHT_FLOOR_MIB:g} MiB, "
        f"+{FLIGHT_RSS_MARGIN:.0%}); "
        "`run` refuses larger ones"
    )
    return 0


def _physical_mib() -> float | None:
    """This host's RAM in MiB, or None where the system does not say."""
    import os

    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**20
    except (ValueError, OSError, AttributeError):
        return None


def _unrunnable(budget, duty, host_dmips: float) -> list[str]:
    """What `run` would say of ``budget`` on this host, said in `budgets`' listing before anyone waits for it."""
    from hil_server.budgets import BudgetError, check_runnable, flight_peak_rss_mib, max_image_side

    out = []
    try:
        check_runnable(budget.name, budget, duty)
    except BudgetError as exc:
        out.append(f"`run` refuses it here: {str(exc).split(': ', 1)[-1]}")
    if budget.link == "serial" and budget.baud:
        from hil_server.run import RunConfig
        from protocol.errors import InputError
        from protocol.linkspec import check_baud

        try:  # a 300-baud budget listed without a word, then `run` refused it (QA of stop 78)
            check_baud(budget.baud, RunConfig.link_timeout_s)
        except InputError as exc:
            out.append(f"`run` refuses its line at the default --link-timeout: {exc}")
    if budget.outruns(host_dmips):
        out.append(
            f"faster than this host's core ({host_dmips:.0f} DMIPS): it runs at this core's full speed, so its "
            "verdict is pessimistic"
        )
    ram = _physical_mib()
    if ram is not None and budget.memory_mib > ram:  # the ceiling then never binds: this host runs out first
        out.append(
            f"its memory ceiling, {budget.memory_mib:.0f} MiB, is over this host's {ram:.0f} MiB of RAM: the host "
            "runs out before the ceiling is reached"
        )
    if max_image_side(budget.memory_mib) <= 0:
        out.append(
            f"no camera fits: our flight process alone needs ~{flight_peak_rss_mib(0):.0f} MiB "
            f"of its {budget.memory_mib} MiB (a flight program of your own may need less: `run --flight-cmd`)"
        )
    return out


def _duty_list(text: str) -> tuple[float, ...]:
    try:
        out = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected duty cycles like 0.01,0.1, got {text!r}") from None
    from hil_server.calibrate import MIN_EFFICIENCY_DUTY

    if not out or not all(MIN_EFFICIENCY_DUTY <= f < 1.0 for f in out):  # 1e-9 ran for ever, deaf to Ctrl-C
        raise argparse.ArgumentTypeError(
            f"each duty cycle must be in [{MIN_EFFICIENCY_DUTY:g}, 1) (a probe at 0.1 % takes about a minute), "
            f"got {text!r}"
        )
    return out


def _calibrate(args: argparse.Namespace) -> int:
    from hil_server.budgets import (
        BudgetError,
        calibrate_host,
        calibration_drift,
        calibration_path,
        check_store_writable,
        load_budgets,
        load_calibration,
    )

    if not 0 < args.seconds <= 600:
        raise BudgetError(f"--seconds must be in (0, 600], got {args.seconds:g}")
    check_store_writable()
    anchor = next(iter(load_budgets(args.file).values())).anchor
    print(f"measuring the reference workload for ~{args.seconds:g} CPU seconds on one thread, then the throttle's")
    print("efficiency at each duty cycle (about 30 s for the default ones)...")
    try:
        before = load_calibration()
    except BudgetError:  # an unreadable store: calibrate_host keeps it aside and starts afresh
        before = None
    cal = calibrate_host(
        seconds=args.seconds,
        efficiency_fractions=args.duty_cycles,
        progress=lambda line: print(f"  {line}", flush=True),
    )
    print(
        f"{cal.units_per_s:.2f} units/s (spread p10-p90 {cal.spread:.0%}); anchor {anchor.units_per_s:g} units/s "
        f"= {anchor.dmips:.0f} DMIPS -> this host {cal.host_dmips(anchor):.0f} DMIPS per core; each budget's duty "
        "cycle is raised by 1/efficiency (`hazard-hil budgets`)"
    )
    print(f"stored for {cal.key} ({cal.libraries}) in {calibration_path()}")
    drift = calibration_drift(before, cal)
    if drift:
        print(drift[0].upper() + drift[1:])
    return 0


# --------------------------------------------------------------------------- runs
# The demo: a short vertical descent over loopback serial on a flight-computer
# budget, sized to finish well inside two minutes on a 2-core machine.
DEMO_DEFAULTS = {
    "scenario": "vertical",
    "link": "serial",
    "budget": "snapdragon801",
    "pairs": ["600/300", "300/150", "200/100"],
}


def _pairs(text: str | None) -> list[str] | None:
    return comma_items(text, "--pairs") if text else None


BUDGET_LINK = "the budget's link, see `hazard-hil budgets`"  # --link's default where a run names none


def _add_run_options(p: argparse.ArgumentParser, defaults: dict) -> None:
    p.set_defaults(run_defaults=defaults)
    p.add_argument(
        "--scenario",
        default=None,
        help=f"vertical | approach | trajectory FILE (default: {defaults.get('scenario', 'vertical')})",
    )
    p.add_argument(
        "--link",
        default=None,
        help="serial | zmq (a loopback link to the emulated flight processor); with --flight external the far "
        "end: serial:DEVICE[@BAUD] (e.g. serial:/dev/ttyUSB0@115200) or zmq:tcp://HOST:PORT "
        f"(default: {defaults.get('link', BUDGET_LINK)})",
    )
    p.add_argument(
        "--flight",
        choices=("emulated", "external"),
        default="emulated",
        help="emulated: flight software under the supervisor on the budget's emulated processor (default); "
        "external: a flight computer outside, on --link (no supervisor, no budget; timing measured at the ground)",
    )
    p.add_argument(
        "--flight-cmd",
        default=None,
        metavar="CMD",
        help="run your own flight program under the budget instead of ours, e.g. "
        '".venv/bin/python examples/minimal_flight.py --port {port}" ({port}: its serial line, also $HAZARD_HIL_PORT; '
        "docs/hil.md)",
    )
    p.add_argument("--keys", type=Path, default=None, help="--flight external over zmq: the ground's CURVE key dir")
    p.add_argument(
        "--min-hit-rate",
        type=float,
        default=None,
        help="exit 0 when at least this share of pairs met the deadline (default: every pair must)",
    )
    p.add_argument(
        "--budget", default=defaults.get("budget", "host"), help="emulated processor, see `hazard-hil budgets`"
    )
    p.add_argument(
        "--budget-file",
        type=Path,
        default=None,
        help="a budget file of your own (the packaged budgets.toml's format; `hazard-hil budgets --file FILE` "
        "lists it) that --budget names a budget of (default: the packaged one)",
    )
    p.add_argument(
        "--pairs",
        default=None,
        help="comma-separated pair labels, e.g. 600/300,300/150 "
        f"(default: {','.join(defaults['pairs']) if defaults.get('pairs') else 'all of the scenario'})",
    )
    p.add_argument("--seed", type=int, default=None, help="terrain and noise seed of the rendered descent (default: 0)")
    p.add_argument("--scene", default=None, help="scene preset or TOML file (default: the scenario's)")
    p.add_argument("--preset", choices=("fast", "thesis"), default="fast", help="flight software parameter preset")
    p.add_argument(
        "--pace",
        choices=("lockstep", "asap"),
        default="lockstep",
        help="lockstep: the next pair goes once the last is answered; asap: stream the descent without waiting",
    )
    p.add_argument("--deadline", type=float, default=None, help="override the budget's deadline (s, end to end)")
    p.add_argument(
        "--baud",
        type=int,
        default=None,
        help="serial baud rate (default: the budget's, else 921600; 115200 works; 0: unpaced)",
    )
    p.add_argument(
        "--image-size",
        type=int,
        default=None,
        help="render a square camera of this many px (32-4096) with the thesis camera's 30 deg FOV, in place of the "
        "scenario's (a trajectory file's own too; default: the scenario's, 512 px for vertical and approach)",
    )
    p.add_argument(
        "--manifest",
        type=Path,
        default=None,
        help="stream pairs already rendered by `hazard-hil render` (their manifest.json, or the directory that "
        "holds it); of a directory of more "
        "than two frames, frames 0 and the last; every pair must share the first pair's camera",
    )
    p.add_argument(
        "--corrupt",
        type=float,
        default=0.0,
        help="serial only, the emulated flight processor only: per-byte drop/flip/duplicate rate injected on the line "
        "(e.g. 1e-6; a board of your own: docs/hil.md section 6, a noisy line)",
    )
    p.add_argument(
        "--full-maps",
        action="store_true",
        help="Results also carry full-resolution image maps (hazard, elevation, state: MBs per pair on the line)",
    )
    fusion = p.add_mutually_exclusive_group()  # both given: the last won, and nothing said which
    fusion.add_argument(
        "--fusion",
        action="store_true",
        default=True,
        help="Results report the map fused over the descent (flight_sw.fusion, the default; held-out figures in "
        "docs/benchmarks/multiframe.md)",
    )
    fusion.add_argument("--no-fusion", dest="fusion", action="store_false", help="each Result reports its pair alone")
    p.add_argument(
        "--insecure",
        action="store_true",
        help="zmq only: no CURVE authentication (loopback debugging only; by default every run makes its own keys)",
    )
    p.add_argument(
        "--link-timeout",
        type=float,
        default=4.0,
        help="a far end silent or not acknowledging this long ends the link session (s, default 4)",
    )
    p.add_argument(
        "--hello-timeout",
        type=float,
        default=None,
        metavar="S",
        help="how long the ground waits for the flight side's first Hello, link session included, with a line every "
        "10 s; then every pair is recorded as not run (default: 120 s with --flight external, 900 s emulated: a slow "
        "budget boots slowly)",
    )
    p.add_argument(
        "--reconnect-timeout",
        type=float,
        default=10.0,
        metavar="S",
        help="after a lost link session, how long the ground waits for the flight side to come back, from the loss "
        "(not per pair); pairs due meanwhile wait, later ones are recorded as link_down (default 10 s)",
    )
    p.add_argument("--link-fault", default=None, help=argparse.SUPPRESS)  # tests: stall@N | exit@N
    # tests: the ground's wait for a Result's Telemetry (s), which a board that sends none waits out per pair
    p.add_argument("--telemetry-grace", type=float, default=None, help=argparse.SUPPRESS)
    # tests: how often the ground says the first Hello is still awaited (s)
    p.add_argument("--hello-note", type=float, default=None, help=argparse.SUPPRESS)
    p.add_argument("--fault", default=None, help=argparse.SUPPRESS)  # tests: crash@N | hang@N | oom@N (our flight sw)
    p.add_argument("--out", type=Path, default=Path("out/run"), help="output directory (created)")
    p.add_argument("--no-progress", action="store_true", help="no render progress bar (per-pair lines still print)")
    p.add_argument(
        "--no-figures",
        action="store_true",
        help="report.html without its pictures, tables and notes only (about 1 s less per pair: a three-pair 128 px "
        "descent took 4.8 s instead of 7.7 s; for gates that read summary.json)",
    )
    p.add_argument(
        "--no-throttle-check",
        action="store_true",
        help="run a throttled budget on the stored calibration as it is; by default the throttle's efficiency is "
        "measured again at a slow budget's duty cycle first (5-10 s), and the host's full-speed rate on a faster one "
        "(0.5 s), each said when it drifted (docs/hil.md section 4)",
    )


# what a rendered descent takes, and a manifest already fixes
_RENDER_OPTIONS = ("scenario", "pairs", "seed", "scene", "image_size")


def _config(args: argparse.Namespace):
    import math

    from hil_server.budgets import OWN_BUDGET_HINT, get_budget
    from hil_server.run import RunConfig

    defaults = getattr(args, "run_defaults", {})
    if args.manifest is not None:
        given = [f"--{k.replace('_', '-')}" for k in _RENDER_OPTIONS if getattr(args, k) is not None]
        if given:
            raise InputError(f"--manifest streams pairs already rendered; {', '.join(given)} would be ignored")
    from hil_server.budgets import deadline_problem
    from protocol.linkspec import check_link_timeout, check_positive_seconds

    if args.deadline is not None and (why := deadline_problem(args.deadline)):
        raise InputError(f"--deadline {why}")
    if args.hello_timeout is not None and not (math.isfinite(args.hello_timeout) and 0 < args.hello_timeout <= 86400):
        raise InputError(f"--hello-timeout must be a number of seconds in (0, 86400], got {args.hello_timeout}")
    for option, seconds in (("--telemetry-grace", args.telemetry_grace), ("--hello-note", args.hello_note)):
        if seconds is not None:
            check_positive_seconds(option, seconds)
    if args.link_timeout is not None:
        check_link_timeout(args.link_timeout)
    if args.baud is not None:
        from protocol.linkspec import BAUD_MAX, BAUD_MIN

        if args.baud and not BAUD_MIN <= args.baud <= BAUD_MAX:  # 0: unpaced, as serial:DEV@0
            raise InputError(f"--baud must be 0 (unpaced) or in [{BAUD_MIN}, {BAUD_MAX:.0e}] baud, got {args.baud}")
    if args.image_size is not None:
        from protocol.pairdir import square_camera

        square_camera(args.image_size)  # checked before anything is calibrated or rendered
    if args.seed is not None:
        from ground_sim.cli import check_seed

        check_seed(args.seed)  # the render's terrain hash, as `render --seed`
    link = args.link or defaults.get("link")
    if link is None:  # the budget's own link: a host run over ZeroMQ, a flight board over serial
        budget = get_budget(args.budget, args.budget_file, hint=OWN_BUDGET_HINT)
        link = budget.link if args.flight == "emulated" else "serial"
        if args.corrupt and link != "serial":  # "not to --link zmq" named an option never given (QA of stop 71)
            raise InputError(
                f"--corrupt applies to the serial link only, and the {budget.name} budget's own link is {link}: "
                "add --link serial"
            )
    pairs = _pairs(args.pairs) if args.pairs is not None else defaults.get("pairs")
    scenario = args.scenario or defaults.get("scenario", "vertical")
    if args.manifest is None:
        from ground_sim.trajectory import load_trajectory

        load_trajectory(scenario)  # an unknown name is refused before anything starts
    return RunConfig(
        scenario=scenario,
        link=link,
        budget=args.budget,
        budget_file=args.budget_file,
        out=args.out,
        pairs=pairs,
        seed=args.seed or 0,
        scene=args.scene,
        preset=args.preset,
        pace=args.pace,
        deadline_s=args.deadline,
        baud=args.baud,
        image_size=args.image_size,
        manifest=args.manifest,
        corrupt=args.corrupt,
        full_maps=args.full_maps,
        fusion=args.fusion,
        insecure=args.insecure,
        link_timeout_s=args.link_timeout,
        hello_timeout_s=args.hello_timeout,
        reconnect_timeout_s=args.reconnect_timeout,
        link_fault=args.link_fault,
        telemetry_grace_s=args.telemetry_grace,
        hello_note_s=args.hello_note,
        fault=args.fault,
        flight=args.flight,
        flight_cmd=args.flight_cmd,
        keys=args.keys,
        min_hit_rate=args.min_hit_rate,
        progress=not args.no_progress,
        figures=not args.no_figures,
        throttle_check=not args.no_throttle_check,
    )


def _finish(summary: dict, args: argparse.Namespace, name: str) -> int:
    """Print the verdict and return the exit code (docs/hil.md): 0 only when every pair met its deadline end to
    end (or --min-hit-rate was reached), 1 otherwise, 128 + N when signal N cut the run short."""
    from hil_server.run import exit_code, verdict_line

    if summary.get("link_errors"):
        n = summary["link_errors"]
        print(f"{name}: LINK ERROR: {n} pair{'' if n == 1 else 's'} lost to link failures", file=sys.stderr)
    code = exit_code(summary, args.min_hit_rate)
    print(f"{name}: {verdict_line(summary, args.min_hit_rate)} -> exit {code}")
    return code


def _cmd_run(args: argparse.Namespace) -> int:
    from hil_server.run import run_descent

    summary = run_descent(_config(args), log=console)
    report = Path(args.out) / ("summary.md" if summary.get("report_error") else "report.html")
    print(f"report: {report}")
    return _finish(summary, args, "run")


def _cmd_demo(args: argparse.Namespace) -> int:
    from hil_server.budgets import calibrate_host, load_calibration
    from hil_server.run import check_run_config, run_descent

    cfg = _config(args)
    checked = check_run_config(cfg)  # bad options are refused before the half-minute calibration below
    if load_calibration() is None:  # a budget means an absolute speed only on a calibrated host
        from hil_server.budgets import check_store_writable

        check_store_writable()
        _refuse_hopeless_budget(checked.cfg.budget, checked.budget)
        print("demo: this host is not calibrated yet; measuring it once (hazard-hil calibrate, about 30 s)")
        cal = calibrate_host(seconds=2.0, progress=lambda line: print(f"demo:   {line}", flush=True))
        print(f"demo: {cal.units_per_s:.1f} reference units/s on {cal.cpu_model}")
    summary = run_descent(cfg, log=console)
    if not summary.get("report_error"):
        print(f"\nDemo finished. Report: {(Path(args.out) / 'report.html').resolve()}")
    print(f"Summary table: {(Path(args.out) / 'summary.md').resolve()}")
    return _finish(summary, args, "demo")


# How much slower than the anchor this host may measure: a budget too slow to emulate even then is hopeless
HOST_SPEED_SLACK = 2.0


def _refuse_hopeless_budget(name: str, budget) -> None:
    """Refuse, before the demo spends half a minute calibrating this host, a budget that `run` would refuse even
    if the host measured :data:`HOST_SPEED_SLACK` times slower than the anchor (stop 56's QA: a budget of 0.04 %
    of the core was refused only after the calibration)."""
    from hil_server.budgets import MIN_RUN_SHARE, BudgetError

    if budget.cpu_dmips is None:
        return
    import warnings

    from hil_server.budgets import UncalibratedWarning

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UncalibratedWarning)  # the demo says so itself
        share = budget.duty(None).effective  # at the anchor's speed: no calibration yet
    if share * HOST_SPEED_SLACK < MIN_RUN_SHARE:
        raise BudgetError(
            f"budget {name} ({budget.cpu_dmips:g} DMIPS) is about {100 * share:.2g} % of a core at the anchor's "
            f"speed, under the {100 * MIN_RUN_SHARE:g} % that `run` emulates even on a host {HOST_SPEED_SLACK:g}x "
            "slower (refused before calibrating this host)"
        )


def _cmd_regress(args: argparse.Namespace) -> int:
    from hil_server.regress import default_baseline_path, run_regression

    return run_regression(
        args.baseline or default_baseline_path(),
        update=args.update,
        out=args.out,
        cases=None if args.cases is None else comma_items(args.cases, "--cases"),  # "": none
        min_hit_rate=args.min_hit_rate,
        board_link=args.link,
        hello_timeout_s=args.hello_timeout,
        uncalibrated=args.uncalibrated,
        figures=not args.no_figures,
    )


def _cmd_keys(args: argparse.Namespace) -> int:
    from protocol.zmqauth import generate_keys, where_keys_go

    print(where_keys_go(generate_keys(args.dir)))
    return 0


def _register_runs(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "run",
        help="end-to-end HIL descent: ground sim -> link -> emulated flight processor",
        description="Render a descent (or stream --manifest pairs), send each pair's frames over a serial line or "
        "ZeroMQ to flight software on an emulated flight processor, and score what comes back against the "
        "deadline (end to end, docs/hil.md) and the truth. Writes summary.json, summary.md, telemetry.jsonl, "
        "supervisor.jsonl, supervisor.log (the flight process's own log), ground.log, received/ (each pair's "
        "Result), pairs/ (the rendered pairs; not with --manifest), figures/ (not with --no-figures) and "
        "report.html in --out. Exit 0 only "
        "when every pair met its deadline (or --min-hit-rate of them), 1 otherwise, 2 on bad usage, 128 + N when "
        "signal N stopped it "
        "(SIGINT, SIGTERM, SIGHUP: every process stopped, summary.json marked incomplete).",
    )
    _add_run_options(p, {})
    p.set_defaults(func=_cmd_run)

    p = sub.add_parser(
        "demo",
        help="a short HIL descent over loopback serial with sensible defaults",
        description="`run` with defaults: the vertical descent's 600/300, 300/150 and 200/100 pairs over loopback "
        "serial to the Snapdragon 801 budget; calibrates this host first if it never was. Same exit codes as run.",
    )
    _add_run_options(p, DEMO_DEFAULTS)
    p.set_defaults(func=_cmd_demo, out=Path("out/demo"))

    p = sub.add_parser(
        "regress",
        help="re-run fixed scenario x budget cases and compare to a baseline",
        description="Re-run the baseline's scenario x budget cases and compare deadline hit rate and latency "
        "percentiles (host-independent reference seconds; the unthrottled host case on CPU seconds) with "
        "tolerances. Exit 0 when nothing regressed and every pair met its deadline (or --min-hit-rate of them), 1 "
        "with a diff table that shows "
        "each crossed limit (or the deadlines a case missed), 2 on bad usage (a host never calibrated, unless "
        "--uncalibrated), 128 + N when signal N stopped it. OUT/regress.json holds the table and the verdict.",
    )
    p.add_argument(
        "--baseline",
        type=Path,
        default=None,
        help="latency baseline JSON (default: the one shipped with the package, hil_server/latency_baseline.json)",
    )
    p.add_argument(
        "--update",
        action="store_true",
        help="rewrite the baseline with this run's numbers, each shown beside the one it replaces; a case that "
        "missed deadlines (below --min-hit-rate) or measured none of its metrics is not recorded (exit 1)",
    )
    p.add_argument("--cases", default=None, help="comma-separated case names (default: all in the baseline)")
    p.add_argument(
        "--min-hit-rate",
        type=float,
        default=None,
        help="also pass when a case's pairs met the deadline at least this often (default: the rate the case was "
        "recorded with, else every pair); the baseline's own hit rate still holds (hit_rate_drop). With --update "
        "the cases recorded keep it",
    )
    p.add_argument("--out", type=Path, default=Path("out/regress"), help="where the cases' runs are written")
    p.add_argument(
        "--link",
        default=None,
        metavar="SPEC",
        help='run the baseline\'s board cases ("flight": "external", a board serving `hazard-hil flight`) on '
        "this link instead of their own, e.g. serial:/dev/ttyUSB1@921600 (not written back)",
    )
    p.add_argument(
        "--hello-timeout",
        type=float,
        default=None,
        metavar="S",
        help="give up a case whose flight side has not said Hello after S seconds (default as `run`: 120 s for a "
        "board, 900 s for the emulated processor); a board that is off then fails its cases sooner",
    )
    p.add_argument(
        "--uncalibrated",
        action="store_true",
        help="judge on a host never calibrated (refused otherwise: its reference seconds would assume the anchor's "
        "speed, a looser gate by the host's speed ratio); the verdict line says so",
    )
    p.add_argument(
        "--no-figures",
        action="store_true",
        help="each case's report.html without its pictures (as `run --no-figures`; about 1 s less per pair)",
    )
    p.set_defaults(func=_cmd_regress)

    p = sub.add_parser(
        "keys",
        help="create a CURVE key directory for a ZeroMQ link to your own board",
        description="Create DIR (new or empty) with a server and a client CURVE key pair, every file mode 0600: "
        "`hazard-hil flight --keys DIR` on the board and `hazard-hil run --flight external --keys DIR` on the ground "
        "PC (copy the board its half: server.key_secret and clients/). `run` makes its own per run otherwise.",
    )
    p.add_argument("dir", metavar="DIR", help="a new or empty directory")  # a str: Path('') would read as '.'
    p.set_defaults(func=_cmd_keys)


if __name__ == "__main__":
    sys.exit(main())
