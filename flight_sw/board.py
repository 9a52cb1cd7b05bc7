"""Our flight software on a board of your own: it serves a ground over a serial line or ZeroMQ directly.

Under ``hazard-hil run`` the flight process talks to the HIL server, which holds the ground's link,
answers the ground's Hello, and keeps each ground session's pairs apart. On a real board there is no
HIL server: ``hazard-hil flight --link serial:/dev/ttyUSB0@921600`` runs the same
:class:`flight_sw.flight_main.FlightProcess` on the link itself, and :class:`GroundSession` does
the HIL server's part of the protocol (docs/protocol.md section 6; the ground runs
``hazard-hil run --flight external``):

* it answers each ground's Hello, in that ground's link session, with ``Hello(role="flight")``;
* a new ground session (another run, or the same ground reconnected) drops the pairs half received. A
  reconnected ground has already recorded its pairs in flight as ``link_down`` and goes on with the
  next pair (:mod:`ground_sim.stream`), so nothing it waits for is dropped here. The fused map goes on
  when the session's Config carries the last one's ``descent_id`` (the same descent reconnected) and
  restarts otherwise (:meth:`~flight_sw.flight_main.FlightProcess.new_ground_session`);
* everything is sent within the session of the ground that said Hello last. The flight software reads
  the link only between pairs, so a pair's answer belongs to that session; if the link lost it meanwhile
  (the ground restarted, its new Hello not yet read), the link fails the answer (counted in its
  ``failures``) instead of handing it to the next ground as a stranger's;
* messages of a session whose Hello never came are dropped and counted, as the HIL server does, and a
  message the link refuses although it arrived whole (it fails to decode or the schema) is said on the
  console and counted.

The board runs at its own speed: no duty cycle, no ``time_scale`` (the deadline plan measures the
board's own stage costs). The link's sessions, retransmissions and timeouts are
:mod:`protocol.links`'s.
"""

from __future__ import annotations

import sys
import time
from collections import OrderedDict
from collections.abc import Callable
from typing import Any

from protocol.messages import MESSAGE_NAMES, Error, Frame, Hello, Result, Telemetry
from protocol.quiet import Quieter

KERNELS = ("flight_sw._sgmc", "flight_sw._treesc")  # setup.py builds them where the board has a C compiler
REFUSALS_SAID = 5  # refused messages said one by one on the console; then one line per REFUSALS_QUIET_S with a count
REFUSALS_QUIET_S = 10.0
PAIR_IDS_KEPT = 4096  # frame seq -> pair_id: far more than the frames in flight at any time
NOISE_NOTE_S = 10.0  # a byte-stream line that carries only bytes no frame checks out of is said at most this often


class GroundSession:
    """A protocol link to a ground, seen by :class:`~flight_sw.flight_main.FlightProcess` as the HIL
    server's link: ``recv``/``send``/``flush``/``stats`` and the rest pass through, with the sessions
    handled here (module doc). ``on_new_session()`` is called when a new ground says Hello."""

    def __init__(
        self, link: Any, on_new_session: Callable[[], None] | None = None, log: Callable[[str], None] | None = None
    ):
        self.link = link
        self.on_new_session = on_new_session
        self.log = log or (lambda text: print(text, file=sys.stderr, flush=True))
        self.epoch: int | None = None  # the link session of the ground we serve
        self.ground_session: int | None = None  # its Hello.session
        self.pair_ids: OrderedDict[int, str] = OrderedDict()  # frame seq -> pair_id, for the pair's line
        self.levels: dict[int, str] = {}  # the last Results' levels by their upper frame's seq, for the pair's line
        self.counters = {"sessions": 0, "pairs": 0, "dropped_no_hello": 0, "refused": 0, "errors": 0}
        self._refusals = Quieter(first=REFUSALS_SAID, quiet_s=REFUSALS_QUIET_S)
        self._errors = Quieter(first=REFUSALS_SAID, quiet_s=REFUSALS_QUIET_S)  # Errors it answered, said alike
        # Results sent and not yet known delivered: message id -> pair id. The pair's line says "met" when its
        # Telemetry goes; a Result the link then failed to deliver (the session lost) was never corrected
        self.unconfirmed: OrderedDict[int, str] = OrderedDict()
        self.fused_results: Callable[[], int | None] = lambda: None  # results in the fused map (None: no fusion)
        self._line_seen: tuple[float, float, float, float] | None = None  # (time, bytes, frames, bad) last looked at

    def __getattr__(self, name: str) -> Any:  # flush, stats, failed, close, ...: the link's own
        return getattr(self.link, name)

    def recv(self, timeout: float | None = None) -> Any:
        """The next message for the flight software, or None (a Hello answered here counts as nothing)."""
        pkt = self.link.recv_packet(timeout)
        self._say_refusals()
        self._say_errors_due(time.monotonic())
        self._say_line_noise()
        self._confirm_results()
        if pkt is None:
            return None
        msg, epoch = pkt.message, pkt.epoch
        if isinstance(msg, Hello):
            if epoch != self.epoch or msg.session != self.ground_session:
                self._new_session(msg, epoch)
            self.link.send(Hello(role="flight", session=self.link.session_id), epoch=epoch)
            return None
        if epoch != self.epoch:
            self.counters["dropped_no_hello"] += 1
            return None
        if isinstance(msg, Frame):
            self.pair_ids[msg.seq] = str(msg.pair_id)
            while len(self.pair_ids) > PAIR_IDS_KEPT:
                self.pair_ids.popitem(last=False)
        return msg

    def _say_refusals(self) -> None:
        """Messages the link refused although they arrived whole (a stranger's, or a ground's over the limits):
        said here, as nothing else will: the first ``REFUSALS_SAID`` each, then one line per ``REFUSALS_QUIET_S``
        with how many came meanwhile (a stranger's garbage printed 100 identical lines in seconds); all counted."""
        now = time.monotonic()
        for refusal in self.link.take_refusals():
            type_code, reason = refusal.type_code, refusal.reason
            self.counters["refused"] += 1
            what = MESSAGE_NAMES.get(type_code, f"type {type_code}") if type_code is not None else "message"
            say, unsaid, _ = self._refusals.offer("refused", now, f"{what}: {reason}")
            if say:
                n = self._refusals.seen("refused")
                more = " (from now on at most one line per 10 s, with a count)" if n == REFUSALS_SAID else ""
                before = f" ({unsaid} more refused before it, not shown)" if unsaid else ""
                self.log(f"flight: refused a {what} from the link: {reason}{before}{more}")
        # the link keeps the latest REFUSALS_KEPT between two looks and counts them all: a flood of 20 000 read 64
        # (QA of stop 72, as the ground's "1000 read 129" of stop 58)
        counted = self.link.refused_count() if hasattr(self.link, "refused_count") else 0
        if counted > self.counters["refused"]:
            self._refusals.add_unsaid(
                "refused", counted - self.counters["refused"], "message whose reason was not kept"
            )
            self.counters["refused"] = counted
        for _, unsaid, since, latest in self._refusals.due(now):
            self.log(f"flight: refused {unsaid} more message(s) from the link in the last {since:.0f} s "
                     f"(the latest a {latest})")  # fmt: skip

    def _say_line_noise(self) -> None:
        """A byte-stream line that carried bytes and not one valid frame over the last ``NOISE_NOTE_S`` s or more:
        a ground at another baud, or another device on the port. The ground says so when its Hello goes
        unanswered; the board's console said nothing at all (QA of stop 71)."""
        now = time.monotonic()
        if self._line_seen is not None and now - self._line_seen[0] < NOISE_NOTE_S:
            return
        stats = getattr(self.link, "stats", None)
        stats = stats() if callable(stats) else stats
        if not isinstance(stats, dict) or "crc_errors" not in stats:  # ZeroMQ: TCP delivers whole messages or none
            return
        cur = (
            now,
            float(stats.get("bytes_received", 0)),
            float(stats.get("frames_received", 0)),
            float(stats.get("crc_errors", 0)) + float(stats.get("malformed", 0)),
        )
        last, self._line_seen = self._line_seen, cur
        if last is None:
            return
        got, frames, bad = (c - p for c, p in zip(cur[1:], last[1:]))
        if got > 0 and frames == 0:
            self.log(
                f"flight: the line carried {got:.0f} bytes in the last {now - last[0]:.0f} s but not one valid frame "
                f"of this protocol ({bad:.0f} failed their checks): a ground at another baud, or another device on "
                "this port?"
            )

    def _new_session(self, hello: Hello, epoch: int) -> None:
        self.counters["sessions"] += 1
        self.log(
            f"flight: ground session {hello.session:08x} (link session {epoch}, role {hello.role!r})"
            + (
                ": the earlier session's pairs half received are dropped; its fused map goes on if this is the same "
                "descent (its Config's descent_id)"
                if self.epoch is not None
                else ""
            )
        )
        self.epoch, self.ground_session = epoch, hello.session
        self.pair_ids.clear()
        self.levels.clear()
        if self.on_new_session is not None:
            self.on_new_session()

    def send(self, message: Any, timeout: float | None = None) -> int | None:
        """Send in the session the message belongs to; nothing before a ground said Hello."""
        msg = getattr(message, "message", message)  # an Encoded message: its Message decides
        if isinstance(msg, Hello):
            return None  # the flight software's Hello at boot: each ground's Hello is answered in recv()
        if self.epoch is None:
            return None  # no ground yet: nobody to tell (heartbeats, mostly)
        mid = int(self.link.send(message, timeout=timeout, epoch=self.epoch))
        if isinstance(msg, Result):
            self.levels[int(msg.frame_seqs[0])] = msg.level + (" (degraded)" if msg.degraded else "")
            self.unconfirmed[mid] = self.pair_ids.get(int(msg.frame_seqs[0]), "?")
            while len(self.unconfirmed) > PAIR_IDS_KEPT:
                self.unconfirmed.popitem(last=False)
        elif isinstance(msg, Telemetry):
            self._pair_line(msg)
        elif isinstance(msg, Error):
            self._error_line(msg)
        return mid

    def _error_line(self, err: Error) -> None:
        """A pair answered with an Error (a frame the camera or the poses refuse): the board's console showed only
        its session lines (QA of stop 72). Said as refusals are: the first few, then a count per 10 s."""
        self.counters["errors"] += 1
        pair = self.pair_ids.get(int(err.seq), "?") if err.seq is not None else "?"
        now = time.monotonic()
        say, unsaid, _ = self._errors.offer("error", now, f"{err.code}")
        if say:
            before = f" ({unsaid} more Error(s) before it, not shown)" if unsaid else ""
            self.log(f"flight: pair {pair}: answered with Error {err.code}: {err.text}{before}")
        self._say_errors_due(now)

    def _say_errors_due(self, now: float) -> None:
        for _, n, since, latest in self._errors.due(now):
            self.log(f"flight: answered {n} more Error(s) in the last {since:.0f} s (the latest {latest})")

    def _confirm_results(self) -> None:
        """Say a Result the link failed to deliver after its pair's line was printed (forget the delivered)."""
        ask = getattr(self.link, "outcome", None)
        if ask is None:  # a link that does not track its messages
            self.unconfirmed.clear()
            return
        for mid, pair in list(self.unconfirmed.items()):
            outcome = str(ask(mid) or "")
            if outcome == "pending":
                continue
            del self.unconfirmed[mid]
            if outcome.startswith("failed"):
                why = outcome.removeprefix("failed: ")
                self.log(f"flight: pair {pair}: its Result was not delivered after all ({why})")

    def _pair_line(self, tel: Telemetry) -> None:
        """One line per pair on the board's console: what the ground will judge, as this side saw it."""
        seq = int(tel.frame_seqs[0])
        self.counters["pairs"] += 1
        pair = self.pair_ids.get(seq, "?")
        level = self.levels.pop(seq, "no Result")
        verdict = "met" if tel.deadline_met else "MISSED"
        fused = self.fused_results()
        # computed for a ground whose session has since gone: it read as "met" while the ground recorded link_down
        gone = not (getattr(self.link, "established", True) and getattr(self.link, "epoch", self.epoch) == self.epoch)
        gone = gone or seq not in self.pair_ids  # its frames came in a session a newer ground's Hello replaced
        self.log(
            f"flight: pair {pair}: {level}, {tel.total_latency_s:.2f} s from its last frame "
            + (
                "(not delivered: the ground's session ended before the answer went out)"
                if gone
                else f"(deadline {tel.deadline_s:g} s with the Result's line time: {verdict}, as this side expects)"
            )
            + (f"; the fused map holds {fused} result(s)" if fused else "")
        )


def _served(c: dict, stats: dict | None = None) -> str:
    """The board's last words: what it served, and what its line dropped (``stats``: the link's)."""
    from flight_sw.flight_main import line_damage

    damage = line_damage(stats or {})
    return (
        f"served {c['sessions']} ground session(s), {c['pairs']} pair(s)"
        + (f" ({c['errors']} answered with an Error)" if c.get("errors") else "")
        + f"; {c['refused']} message(s) refused, "
        f"{c['dropped_no_hello']} dropped (no Hello in their session)"
        + (
            f"; the line dropped {damage['flight_rx_damaged']:.0f} damaged frame(s) "
            f"({damage['flight_rx_noise_bytes']:.0f} bytes of noise)"
            if damage
            else ""
        )
    )


def serve(
    spec: str,
    *,
    keys: str | None = None,
    insecure: bool = False,
    heartbeat_s: float = 0.25,
    warm_up: bool = True,
    threads: int = 1,
    link_timeout: float = 4.0,
    log: Callable[[str], None] | None = None,
) -> int:
    """Serve grounds on the link ``spec`` (``serial:DEVICE[@BAUD]`` or ``zmq:ENDPOINT``, the board binding)
    until the link fails (exit 1) or a signal stops it (128 + the signal). Bad usage raises InputError."""
    import signal

    import cv2

    from protocol.errors import InputError
    from protocol.linkspec import (
        HEARTBEAT_LINE_SHARE,
        check_link_spec,
        check_link_timeout,
        heartbeat_period,
        open_link,
        parse_serial,
    )

    from .flight_main import FaultPlan, FlightProcess, link_stats
    from .kernels import load_kernel
    from .pipeline import PRESETS

    say = log or (lambda text: print(text, file=sys.stderr, flush=True))
    if not 1 <= threads <= 256:
        raise InputError(f"--threads must be in [1, 256], got {threads}")
    if not heartbeat_s > 0:
        raise InputError(f"the heartbeat period must be > 0 s, got {heartbeat_s}")
    check_link_timeout(link_timeout)
    if insecure and keys is not None:  # the ground settled it the other way, and the two disagreed
        raise InputError("--keys and --insecure exclude each other: CURVE with the key directory, or none")
    # a link that cannot be (a missing or held device, a bad endpoint) is said before the warm-up's seconds
    check_link_spec(spec, server=True, insecure=insecure, peer_timeout=link_timeout, keys=keys, check_keys=True)
    kind, _, rest = spec.partition(":")
    if kind == "serial":  # on a slow line the heartbeats would crowd out the Results
        beat = heartbeat_period(parse_serial(rest)[1], heartbeat_s)
        if beat > heartbeat_s:
            share = f"{HEARTBEAT_LINE_SHARE:.0%}"
            say(f"flight: a heartbeat every {beat:.1f} s, not {heartbeat_s:g} s: at most {share} of this line")
        heartbeat_s = beat
    cv2.setNumThreads(threads)  # 1: one core, as the emulated processor; a board may give the pipeline more
    prefault = False
    if warm_up:  # before the link opens: no ground waits on it
        from .warmup import boot_warm_up

        w = boot_warm_up(PRESETS["fast"])
        prefault = bool(w["allocator_settled"])
        say(f"flight: boot warm-up {w['cpu_s']:.3f} s CPU ({w['size_px']} px pair, level {w['level']})")
    stopped: list[int] = []

    def stop(signum: int, _frame: Any) -> None:
        stopped.append(signum)
        raise KeyboardInterrupt

    old = signal.signal(signal.SIGTERM, stop)
    # a hangup (the terminal or ssh session closed) ends the board like SIGTERM: its last line, a CLOSE to the
    # ground; under nohup SIGHUP is ignored and stays so
    old_hup = signal.getsignal(signal.SIGHUP)
    if old_hup is not signal.SIG_IGN:
        signal.signal(signal.SIGHUP, stop)
    link = None
    ground = GroundSession(None, log=say)  # its link is set below: a signal while the link opens finds it
    try:
        # the link's own events on the console: sessions up and lost, a ground with the wrong CURVE key, a second
        # ground refused while one is served (a repeating one is said once per 10 s with a count)
        link = ground.link = open_link(
            spec,
            server=True,
            keys=keys,
            insecure=insecure,
            peer_timeout=link_timeout,
            connect_timeout=None,
            name="ground",
            log=lambda text: say(f"flight: {text}"),
        )
        flight = FlightProcess(ground, FaultPlan(), heartbeat_s, prefault)
        ground.on_new_session = flight.new_ground_session
        ground.fused_results = lambda: flight.fused.results if flight.fused is not None else None
        missing = [m for m in KERNELS if load_kernel(m) is None]
        if missing:  # the install found no C compiler: the numpy references run instead, several times slower
            say(f"flight: compiled kernels missing ({', '.join(missing)}): their numpy references run instead")
        say(f"flight: serving on {spec}; waiting for a ground (hazard-hil run --flight external --link ...)")
        flight.run(watch_parent=False)  # detached (nohup, a daemon) it must outlive its parent
        why = f"the link failed: {link.failed}" if link.failed else "the link closed"
        say(f"flight: {why}; {_served(ground.counters, link_stats(ground.link))}")  # sums what it did, however it ends
        return 1
    except KeyboardInterrupt:  # stop() above, or a Ctrl-C (a signal in the warm-up is hazard-hil's own: 128 + N)
        sig = stopped[0] if stopped else signal.SIGINT
        say(f"flight: stopped by {signal.Signals(sig).name}; {_served(ground.counters, link_stats(ground.link))}")
        return 128 + sig
    finally:
        signal.signal(signal.SIGTERM, old)
        if old_hup is not signal.SIG_IGN:
            signal.signal(signal.SIGHUP, old_hup)
        if link is not None:
            link.close()
