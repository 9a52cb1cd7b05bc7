"""The HIL supervisor: the box the ground simulator talks to.

It relays between the ground link (serial pty or ZeroMQ) and the flight
process, which it starts on an emulated processor (one pinned core, CPU duty
cycle, memory ceiling; :mod:`hil_server.procemu`) and talks to over a local
socket pair - or, for a user's own flight program (``--flight-cmd``), over a
pty whose path the program gets as ``{port}`` in its command line and as
``$HAZARD_HIL_PORT`` (docs/hil.md). Being in the middle lets it account for
every pair:

* it tells the flight software the emulated slowdown (``time_scale`` = 1 / CPU
  fraction in ``Config.options``), so reserves it plans in unthrottled seconds
  scale with the budget,
* it timestamps the last frame of each pair (the flight latency starts there),
* it enforces a hard limit (deadline + grace) and a heartbeat watchdog, killing
  and restarting a hung flight process,
* it turns crashes and memory-ceiling breaches into ``Error`` messages for the
  pair in progress, restarts the flight process, replays the frames of the
  pairs still outstanding, and carries on,
* it adds what only the outside can measure (achieved CPU fraction, peak RSS,
  the result's line time, its own estimate of the end-to-end latency: last frame
  in -> Result acknowledged) to the flight's ``Telemetry``, sent once the ground
  has acknowledged the whole Result. The deadline verdict that counts is the
  ground's, on ``e2e_latency_s`` (docs/hil.md).

Every pair the ground completes ends in exactly one of: ``Result`` (full or
degraded) or ``Error`` with a reason. Telemetry is also written as JSON lines.

Link sessions (docs/protocol.md): a ground that stops answering, closes or is
replaced by a restarted one ends its session; the pairs it had outstanding end
as ``link_down`` errors in the telemetry (the ground cannot be told), and a new
ground session starts from a clean slate. Frames go to the flight process under
the supervisor's own sequence numbers and pair ids, so a result the flight
process finishes for a dead session is recognised and dropped. The process
exits 0 after a clean session, 3 if a ground session was lost.
"""

from __future__ import annotations

import argparse
import json
import os
import queue
import shlex
import signal
import socket
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path

from protocol.arq import Refusal, Skipping
from protocol.errors import InputError
from protocol.links import WRITE_RECORD_WAIT_S
from protocol.messages import MESSAGE_NAMES, Config, Error, Frame, Heartbeat, Hello, Result, Telemetry, without_arrays
from protocol.stall import StallClock
from reports.console import printable

# After a kill the flight process needs a moment to come back; frames that
# arrive meanwhile are queued and replayed.
HEARTBEAT_TIMEOUT_S = 5.0  # at full speed; scaled by 1/duty when throttled
MIN_GRACE_S = 2.0
END_GRACE_S = 1.0  # a run's end: a flight program's time to exit after the CLOSE at full speed, before it is killed
END_GRACE_MAX_S = 5.0  # ... scaled by its budget's slowdown, to this at most
LAST_WORDS_S = 1.0  # a dead flight process's link is read to its end for at most this long ...
LAST_WORDS_QUIET_S = 0.2  # ... or until it has been quiet this long (a pty gives no end of stream)
EXIT_LINK_LOST = 3
EXIT_FLIGHT_FAILED = 4  # the flight program never came up: it died MAX_BOOT_FAILURES times before its Hello
MAX_BOOT_FAILURES = 3
NO_HELLO_LOG = "no Hello from the flight process"  # that line's opening, which hazard-hil run quotes
MAX_REFUSAL_LOGS = 100  # refusals logged one by one per run; past that only counted (the logs stay bounded)
# link counters of the flight line that mean "the flight process sent something the HIL server refused":
# a record over the size limit or of an unknown type (reassembly_errors), a body that fails to decode or the
# schema, e.g. a wrong-shaped grid (decode_errors); and frames dropped as line garbage
REFUSED_STATS = ("decode_errors", "reassembly_errors")
LINE_ERROR_STATS = ("crc_errors", "malformed", "oversize")


class FlightFailed(Exception):
    """The flight program cannot be brought up (it dies before it says Hello, again and again)."""


@dataclass
class PairState:
    pair_id: str
    frames: dict[int, Frame] = field(default_factory=dict)  # as the ground sent them
    fframes: dict[int, Frame] = field(default_factory=dict)  # as forwarded to the flight process
    arrivals: dict[int, float] = field(default_factory=dict)  # frame_index -> monotonic arrival time
    complete_at: float | None = None  # monotonic time the last frame arrived
    proc_at_complete: dict | None = None  # emulated-processor stats then, for the pair's CPU fraction
    garbage_at_complete: int = 0  # frames from the flight process that had failed the line's checks by then
    proc_at_result: dict | None = None
    sent_to: int = -1  # flight generation the frames went to
    frame_mids: dict[int, int] = field(default_factory=dict)  # frame_index -> message id on that generation's link
    unreached: int = 0  # incarnations that died before acknowledging its frames (one is forgiven, not a loop)
    # monotonic time the last frame reached the current generation: complete_at, or its restart's replay. The hang
    # watchdog counts from here: a pair that waited while earlier generations crashed is not this one's hang
    sent_at: float | None = None
    result: Result | None = None
    result_at: float | None = None  # monotonic time the Result came from the flight process
    result_mid: int | None = None  # its message id on the ground link
    flight_telemetry: Telemetry | None = None  # held until the Result is acknowledged
    result_link_s: float = 0.0
    # the Result's wait in the ground link's send queue (behind an earlier pair's Result on a slow line)
    result_queue_s: float | None = None
    result_acked_at: float | None = None  # monotonic time the ground acknowledged the whole Result
    # when it was first seen acknowledged before the writer had recorded its last write (its line time then ends
    # at the ACK): the Telemetry waits up to WRITE_RECORD_WAIT_S for the write's own end
    result_write_wait: float | None = None
    done: bool = False
    # seconds this process itself was not scheduled while the pair was open (SIGSTOP, a paused VM): not the
    # flight process's silence; the watchdogs leave it out (a stopped server killed a healthy flight process)
    stopped_s: float = 0.0

    def release(self) -> None:
        """A finished pair keeps its frames' and Result's scalars, not their arrays (images twice, grids): a long
        descent held them all until the run ended, +0.7-3.4 MiB a pair (stop 63's soak QA)."""
        self.frames = {k: without_arrays(f) for k, f in self.frames.items()}
        self.fframes = {k: without_arrays(f) for k, f in self.fframes.items()}
        if self.result is not None:
            self.result = without_arrays(self.result)

    @property
    def seqs(self) -> tuple[int, int]:
        return (self.frames[0].seq, self.frames[1].seq)

    @property
    def fseqs(self) -> tuple[int, int]:
        return (self.fframes[0].seq, self.fframes[1].seq)


def to_replay(pairs: list[PairState]) -> list[PairState]:
    """The pairs a restarted flight process is sent again: every one not finished, but those answered in full (their
    Result and Telemetry in, the ground's acknowledgement awaited). Under asap a restarted process was sent such a
    pair, computed it again, and its Result was ignored "for no open pair", the next pair behind it (stop 60's QA)."""
    return [st for st in pairs if not st.done and (st.result is None or st.flight_telemetry is None)]


def pair_contention_s(before: dict | None, after: dict) -> float:
    """Run-queue wait of the flight process while a pair was outstanding (s): the time it was ready to run and
    another process held its core, capped at the wall time it did not run (see :func:`pair_cpu_fraction`). A
    latency regression on a busy host showed no sign of it (QA of stop 73)."""
    if before is None:
        return float("nan")
    d_cpu = after["cpu_s"] - before["cpu_s"]
    d_wall = after["wall_s"] - before["wall_s"]
    return max(0.0, min(after["contention_s"] - before["contention_s"], max(0.0, d_wall - d_cpu)))


def pair_cpu_fraction(before: dict | None, after: dict) -> float:
    """CPU the flight process got while a pair was outstanding, over the wall time it could run.

    ``d_cpu / (d_wall - min(d_contention, d_wall - d_cpu))``: time it waited for a host core that another
    process held is not the emulator's doing. The contention is the run-queue wait summed over its threads, which
    add up while they queue together: it is capped at the wall time the process did not run, so the figure cannot
    pass 1 (a contended host read 5.59 of one core where 0.166 s CPU in 1.165 s was had; stop 63's soak QA).
    The lifetime figure would be diluted by idle waits.
    """
    if before is None:
        return float("nan")
    d_cpu = after["cpu_s"] - before["cpu_s"]
    d_avail = after["wall_s"] - before["wall_s"] - pair_contention_s(before, after)
    return d_cpu / d_avail if d_avail > 0 else float("nan")


@dataclass(frozen=True)
class NewLinkSession:
    """A :class:`Reader`'s event: its link's session ``epoch`` is up; ``why`` is the link's reason the one before it
    ended (the peer gave it up, docs/protocol.md section 2 rule 7), "" for the link's first."""

    epoch: int
    why: str


class Reader(threading.Thread):
    """Moves messages from a link into the supervisor's single event queue; with ``sessions``, a
    :class:`NewLinkSession` ahead of the first message of each link session."""

    def __init__(self, link, tag: str, events: queue.Queue, generation: int = 0, sessions: bool = False) -> None:
        super().__init__(name=f"reader-{tag}", daemon=True)
        self.link, self.tag, self.events, self.generation = link, tag, events, generation
        self.sessions = sessions
        self.stopped = threading.Event()
        # stamped here, not in the main loop: the loop may be busy (a result's line time on a slow
        # or noisy link) while the peer is perfectly alive
        self.last_message = time.monotonic()

    def run(self) -> None:
        from protocol.links import LinkClosed

        seen: int | None = None  # the link session its messages came in so far
        while not self.stopped.is_set():
            try:
                pkt = self.link.recv_packet(timeout=0.2)
                up = self.link.established
            except (EOFError, OSError, LinkClosed):
                self.events.put((self.tag, self.generation, EOFError(), 0))
                return
            epoch = pkt.epoch if pkt is not None else (self.link.epoch if up else None)
            # a later session only: the old session's last message can be read after the new one is up
            if self.sessions and epoch is not None and (seen is None or epoch > seen):
                why = "" if seen is None else str(getattr(self.link, "last_error", None) or "the peer started anew")
                self.events.put((self.tag, self.generation, NewLinkSession(epoch, why), epoch))
                seen = epoch
            if pkt is not None:
                self.last_message = time.monotonic()
                self.events.put((self.tag, self.generation, pkt.message, pkt.epoch))


def flight_argv(flight_cmd: str, port: str) -> list[str]:
    """A user's flight command split like a shell would (no shell runs it), ``{port}`` replaced by the pty path."""
    try:
        argv = shlex.split(flight_cmd)
    except ValueError as exc:
        raise InputError(f"--flight-cmd: cannot split {flight_cmd!r}: {exc}") from None
    if not argv:
        raise InputError("--flight-cmd is empty")
    return [a.replace("{port}", port) for a in argv]


class FlightHandle:
    """One incarnation of the flight process on the emulated processor.

    Our own flight software talks over an inherited socket; a user's program
    (``flight_cmd``) over a fresh raw pty, the same byte stream a serial board gets.
    """

    def __init__(
        self,
        processor_factory,
        generation: int,
        fault: str | None,
        heartbeat_s: float,
        flight_cmd: str | None = None,
    ) -> None:
        from protocol.links import LOCAL_CONFIG, PTY_CONFIG, StreamLink

        self.generation = generation
        self.flight_cmd = flight_cmd
        self.proc = processor_factory()
        if flight_cmd:
            from protocol.faults import open_pty_pair

            master, port = open_pty_pair()
            env = {**os.environ, "HAZARD_HIL_PORT": port, "HAZARD_HIL_LINK": f"serial:{port}@0"}
            try:
                self.proc.start(flight_argv(flight_cmd, port), env=env, merge_stdout=True)
            except BaseException:
                os.close(master)
                raise
            self.link = StreamLink(master, config=PTY_CONFIG, name=f"flight{generation}")
            self.says_eof = False  # a pty's master reads EIO, which the link takes for "not open yet"
        else:
            parent, child = socket.socketpair()
            argv = [
                sys.executable,
                "-m",
                "flight_sw.flight_main",
                "--fd",
                str(child.fileno()),
                "--heartbeat",
                str(heartbeat_s),
            ]
            if fault:
                argv += ["--fault", fault]
            self.proc.start(argv, pass_fds=(child.fileno(),))
            child.close()
            self.link = StreamLink(parent, config=LOCAL_CONFIG, name=f"flight{generation}")
            self.says_eof = True  # a socket's end of stream comes after everything the process sent
        self.last_refusal: str | None = None  # the latest message refused from this incarnation, for a hang's reason
        self.last_ignored: str | None = None  # ... and the latest Result it sent for no open pair
        # (type code, reason) of a record accounted for as refused from its header, before its REJECT: its REJECT,
        # should all its bytes still come before the restart, is not counted twice
        self.refused_early: tuple[int, str] | None = None
        self.seen = dict.fromkeys(REFUSED_STATS + LINE_ERROR_STATS, 0.0)  # link counters already accounted for
        # the flight side answers the ground's Hello (docs/protocol.md section 6); ours says Hello unasked
        self.link.send(Hello(role="hil-server"))
        self.hello = False
        self.started = time.monotonic()
        self.replayed = 0  # pairs whose frames were sent at its start, right behind the Hello
        # its link session the server last sent Config in (None: its first, not yet up): what is sent to it goes
        # in that session or fails, never ahead of the Config a new session is sent (supervisor._resync_flight)
        self.epoch: int | None = None

    def link_stats(self) -> dict | None:
        """This incarnation's link counters, or None once its link cannot say (closed)."""
        try:
            stats = self.link.stats
            return stats() if callable(stats) else stats
        except Exception:
            return None

    def line_garbage(self) -> int:
        """Frames from this incarnation that failed the line's checks (CRC, framing, size) since it started."""
        stats = self.link_stats()
        if stats is None:
            return 0
        return int(sum(float(stats.get(k, 0)) for k in LINE_ERROR_STATS))

    def no_hello_note(self) -> tuple[int, str]:
        """Why no Hello has come from this incarnation, as far as its link can tell, and how far it got (0 nothing
        came, 1 bytes but no frame, 2 frames failing their checks, 3 a link but no Hello message): a user's own
        program read "no Hello" the same whether it never wrote, wrote frames that failed their CRC, or never sent
        the message (QA of stop 73)."""
        stats = self.link_stats()
        if stats is None:
            return 0, ""
        got, bad = int(stats.get("bytes_received", 0)), int(stats.get("crc_errors", 0) + stats.get("malformed", 0))
        if not got:
            return 0, (
                "nothing came from it on its link: it never answered the link's HELLO frame (is it reading and "
                "writing the port it was given? docs/protocol.md section 2)"
            )
        if not stats.get("established"):
            if bad:
                return 2, (
                    f"its link never came up: {bad} frame{'' if bad == 1 else 's'} it sent failed the CRC or framing "
                    f"check ({got} bytes came): check its CRC-32 (big-endian on the wire) and the framing's flags "
                    "and escapes (docs/protocol.md section 1)"
                )
            return 1, f"its link never came up: {got} bytes came from it, none a valid HELLO frame (docs/protocol.md)"
        return 3, (
            "its link came up (the HELLO frames were exchanged) but no Hello message came over it "
            "(docs/protocol.md section 6)"
        )

    def take_refusals(self) -> list[Refusal]:
        """The messages the link refused from this incarnation since the last call."""
        return self.link.take_refusals()

    def skipping(self) -> Skipping | None:
        """The record from the flight process that the link is skipping now (its header says it will be refused:
        over the size limit or of an unknown type), or None."""
        arq = getattr(self.link, "arq", None)
        return arq.skipping if arq is not None else None

    def new_counts(self) -> dict[str, int]:
        """The refusal and line-error counters of this incarnation's link since the last call."""
        stats = self.link_stats()
        if stats is None:  # a closed link: nothing new
            return {}
        out = {}
        for k, before in self.seen.items():
            now = float(stats.get(k, before))
            out[k] = int(now - before)
            self.seen[k] = now
        return out

    def close(self, reason: str | None = None, grace_s: float = 0.0) -> None:
        """End the program: with ``grace_s`` and a user's program, a CLOSE first (code 0, the ground is done:
        docs/protocol.md section 2 rule 8) and that long to exit, as a board is told; then, or at once, killed with
        ``reason``. Until stop 79 a run's end killed a `--flight-cmd` program outright: its exit handlers never ran.
        Our own flight process ends on its socket's end and is spared the wait."""
        if grace_s > 0 and self.flight_cmd and self.proc.alive:
            self.link.say_done("the ground is done")
            self.proc.wait(grace_s)
        if reason and self.proc.alive:
            self.proc.kill(reason)
        self.link.close()
        self.proc.close()


class Supervisor:
    def __init__(
        self,
        ground_link,
        budget,
        processor_factory,
        *,
        telemetry_path: Path | None = None,
        fault: str | None = None,
        link_fault: str | None = None,
        flight_cmd: str | None = None,
        heartbeat_s: float = 0.25,
        grace_s: float | None = None,
        cpu_fraction: float = 1.0,
        effective_fraction: float | None = None,
        log=print,
    ) -> None:
        self.ground = ground_link
        self.budget = budget
        self.processor_factory = processor_factory
        self.fault = fault
        self.flight_cmd = flight_cmd
        self.link_fault = parse_link_fault(link_fault)
        self.heartbeat_s = heartbeat_s
        self.cpu_fraction = cpu_fraction  # the throttle's duty cycle
        # the work it delivers (hil_server.budgets.Duty): what the flight's clock runs at
        self.effective_fraction = cpu_fraction if effective_fraction is None else effective_fraction
        self.grace_s = grace_s
        self.log = log
        self.events: queue.Queue = queue.Queue()
        self.pairs: dict[str, PairState] = {}
        self.order: list[str] = []
        self.config: Config | None = None
        self.flight: FlightHandle | None = None
        self.flight_reader: Reader | None = None
        self.generation = 0
        self.ground_waiting_hello = False
        self.ground_epoch: int | None = None  # link session of the current ground
        self.ground_session: int | None = None  # its Hello.session
        self.ground_gen = 0  # ground sessions seen: prefixes pair ids sent to the flight process
        self.fseq = 0  # sequence numbers of frames forwarded to the flight process
        self.pairs_seen = 0
        self.restarts = 0
        self.counters = {
            "results": 0,
            "degraded": 0,
            "errors": 0,
            "deadline_missed": 0,
            "restarts": 0,
            "crashes": 0,
            "exits": 0,  # the flight process ended itself with status 0 mid-run (restarted, as after a crash)
            "memory_ceiling": 0,
            "hangs": 0,
            "link_errors": 0,
            "stale_results": 0,
            "stale_errors": 0,
            "stale_telemetry": 0,  # Telemetry after the pair's first, after its Error, or for no open pair
            "unexpected_messages": 0,
            "refused_messages": 0,  # messages from the flight process the HIL server refused (with reasons)
            "missing_telemetry": 0,  # Results the flight process sent no Telemetry for
            "flight_line_errors": 0,  # corrupted or malformed frames from the flight process, dropped
            "flight_sessions": 0,  # link sessions the flight program started anew (protocol.md section 2 rule 7)
        }
        self.boot_failures = 0  # flight incarnations in a row that died before their Hello
        self.no_hello_seen: tuple[int, str] = (-1, "")  # the furthest an incarnation without a Hello got, and why
        self.hello_seen = False  # some incarnation said Hello
        self.unlogged_bytes = 0  # the flight incarnations' output past the log's cap (procemu), closed ones
        self.closing = False  # serve() is shutting down: a second SIGTERM must not cut the summary short
        self._stall: StallClock | None = None  # this process's own stops (serve() runs it)
        self.stopped_s = 0.0  # how long this process went unscheduled in all (summary: the run says it)
        self._forgave_at: float | None = None  # the flight's last message as the last forgiven stop left it
        # open for the supervisor's lifetime, closed in serve()'s finally
        self.telemetry_file = open(telemetry_path, "a") if telemetry_path else None  # noqa: SIM115
        self.t_start = time.monotonic()  # telemetry times are seconds since the supervisor started

    # -- flight process lifecycle ---------------------------------------------------------
    def _start_flight(self) -> None:
        self.generation += 1
        self.flight = FlightHandle(
            self.processor_factory,
            self.generation,
            self.fault if self.generation == 1 else None,
            self.heartbeat_s,
            self.flight_cmd,
        )
        self.flight_reader = Reader(self.flight.link, "flight", self.events, self.generation, sessions=True)
        self.flight_reader.start()
        if self.config is not None:
            self._to_flight(self.config)
        for st in to_replay([self.pairs[pid] for pid in self.order]):  # what the dead incarnation never answered
            self._send_frames(st)
            st.sent_to = self.generation
            if st.complete_at is not None:
                st.sent_at = time.monotonic()
                st.stopped_s = 0.0  # its clock starts at the replay: earlier stops are not its slack
            self.flight.replayed += 1

    def _resync_flight(self, new: NewLinkSession) -> None:
        """The flight program gave up its link session and started a new one (docs/protocol.md section 2 rule 7:
        a spec-kept program does so after 4 s without a frame): say Hello and send Config again, as a ground does
        after a new session, and the frames of every pair it has not answered, which the old session's loss took
        with it. Until stop 79 the server went on with Frames alone, and a program that waits for a Config after
        a new session answered every later pair ``no_config``."""
        from protocol.links import LinkClosed

        assert self.flight is not None
        if not self.flight.proc.alive:  # a dead incarnation's last words: its exit is judged, nothing is resent
            return
        known = self.flight.epoch
        if known is not None and new.epoch <= known:
            return
        self.flight.epoch = new.epoch
        if known is None and new.epoch == 1:  # its link's first session: what was sent at its start went in it
            return
        self.counters["flight_sessions"] += 1
        pairs = [st for st in to_replay([self.pairs[pid] for pid in self.order]) if st.sent_to == self.generation]
        for st in [st for st in pairs if st.result is not None]:  # its Result came: computed again it is a second
            self._complete_without_telemetry(st, "its Telemetry was lost with the link session")
        again = [st for st in pairs if st.result is None]
        self.log(
            f"supervisor: the flight program started a new link session ({printable(new.why, 200)}): Hello, Config "
            f"and the frames of {len(again)} unanswered pair(s) sent again"
        )
        self._write_telemetry({"event": "flight_session", "reason": new.why, "pairs_resent": len(again)})
        try:
            self._to_flight(Hello(role="hil-server", session=self.ground_session or 0))
            if self.config is not None:
                self._to_flight(self.config)
            for st in again:  # their deadline clocks run on: the ground judges them end to end
                self._send_frames(st)
        except LinkClosed:  # it died meanwhile: its exit comes as the reader's EOF
            pass

    def _send_frames(self, st: PairState) -> None:
        """(Re)send the frames of ``st`` the server holds, in order, keeping their message ids."""
        st.frame_mids = {idx: self._to_flight(st.fframes[idx]) for idx in sorted(st.fframes)}

    def _to_flight(self, msg) -> int:
        """Send ``msg`` to the flight program in its link session the server knows: after that session ended it
        fails, where it would have gone ahead of the next session's Config (:meth:`_resync_flight` sends it
        again)."""
        assert self.flight is not None
        return self.flight.link.send(msg, epoch=self.flight.epoch)

    def _keep_no_hello_note(self) -> None:
        """Keep the furthest any incarnation without a Hello got (:meth:`FlightHandle.no_hello_note`): a restart
        by the heartbeat watchdog left a fresh link that had seen nothing yet."""
        if self.flight is not None and not self.flight.hello:
            self.no_hello_seen = max(self.no_hello_seen, self.flight.no_hello_note(), key=lambda n: (n[0], bool(n[1])))

    def _restart_flight(self, reason: str) -> None:
        assert self.flight is not None
        self._keep_no_hello_note()
        self._check_refusals()  # what this incarnation sent that was refused is accounted for before it goes
        report = None
        if self.flight.proc.alive:
            self.flight.proc.kill(reason)
        report = self.flight.proc.wait(5.0)
        if self.flight_reader:
            self.flight_reader.stopped.set()
        self.flight.close()
        self.unlogged_bytes += getattr(self.flight.proc, "unlogged_bytes", 0)
        self.counters["restarts"] += 1
        self.boot_failures = 0 if self.flight.hello else self.boot_failures + 1
        self.log(f"supervisor: flight process restarted ({reason}; exit {report})")
        self._write_telemetry({"event": "restart", "reason": reason, "exit": str(report)})
        if self.boot_failures >= MAX_BOOT_FAILURES:  # a crash loop would go on until the ground's 15 min wait
            last = getattr(report, "reason", None) or reason
            # a program that reads its input before it sends the Hello it queued can die on a replayed frame with
            # the Hello never out: "before it said Hello" is then true on the wire, but the frames are the suspect
            frames = (
                f" (its last start was sent the frames of {self.flight.replayed} pair(s) at once: it may die on a "
                "frame before its Hello goes out)"
                if self.flight.replayed
                else ""
            )
            # a program that never opened its line was killed for its silence: "died" sent its author looking
            # for a crash
            how = (
                "was killed for its silence (nothing on its line, not even a heartbeat)"
                if reason.startswith("heartbeat")
                else "died"
            )
            raise FlightFailed(
                f"the flight process {how} {self.boot_failures} times in a row before its Hello reached the HIL "
                f"server{frames}; last: {last}"
            )
        self._start_flight()

    def _hard_limit(self) -> float:
        deadline = float(self.config.deadline_s if self.config else self.budget.deadline_s)
        grace = self.grace_s if self.grace_s is not None else max(MIN_GRACE_S, deadline)
        return deadline + grace

    def _oldest(self, want: Callable[[PairState], bool]) -> PairState | None:
        """The oldest pair not done yet for which ``want`` holds."""
        return next((self.pairs[p] for p in self.order if not self.pairs[p].done and want(self.pairs[p])), None)

    def _oldest_outstanding(self) -> PairState | None:
        """The oldest pair with all its frames in and no Result yet."""
        return self._oldest(lambda st: st.complete_at is not None and st.result is None)

    # -- accounting -------------------------------------------------------------------------
    def _to_ground(self, msg) -> int | None:
        """Send within the current ground session only (a message for a dead session never reaches the next)."""
        if self.ground_epoch is None:
            return None
        return self.ground.send(msg, epoch=self.ground_epoch)

    def _fail_pair(self, st: PairState, code: str, text: str, tell_ground: bool = True) -> None:
        st.done = True
        self.counters["errors"] += 1
        if tell_ground:
            err = Error(code=code, text=f"pair {st.pair_id}: {text}", seq=st.frames[1].seq if 1 in st.frames else None)
            self._to_ground(err)
        self._write_telemetry({"pair_id": st.pair_id, "event": "error", "code": code, "text": text})
        st.release()

    def _write_telemetry(self, record: dict) -> None:
        if self.telemetry_file:
            self.telemetry_file.write(json.dumps(record, sort_keys=True) + "\n")
            self.telemetry_file.flush()

    def _pair_for_fseqs(self, fseqs) -> PairState | None:
        for pid in self.order:
            st = self.pairs[pid]
            if 0 in st.fframes and 1 in st.fframes and st.fseqs == tuple(fseqs):
                return st
        return None

    # -- event handlers ---------------------------------------------------------------------
    def _on_ground(self, msg, epoch: int) -> bool:
        """Returns False when the ground link is gone for good."""
        if isinstance(msg, EOFError):
            return False
        if isinstance(msg, Hello):
            self._new_ground_session(msg, epoch)
            # answer once the flight process has booted (at a low duty cycle its imports alone take a while)
            self.ground_waiting_hello = True
            self._answer_ground_hello()
        elif epoch != self.ground_epoch:
            return True  # from a session whose Hello we never saw: nothing to attribute it to
        elif isinstance(msg, Config):
            # the emulated slowdown, so the flight software can scale reserves it plans in unthrottled seconds: per
            # full-speed second, not per throttled CPU-second (those do less work, hil_server.budgets)
            self.config = replace(msg, options={**msg.options, "time_scale": 1.0 / self.effective_fraction})
            assert self.flight is not None
            self._to_flight(self.config)
        elif isinstance(msg, Frame):
            if msg.pair_id is None or msg.frame_index not in (0, 1):
                self._to_ground(Error(code="bad_frame", seq=msg.seq, text="frame needs pair_id and frame_index 0/1"))
                self.counters["errors"] += 1
                return True
            st = self.pairs.get(msg.pair_id)
            if st is None:
                st = self.pairs[msg.pair_id] = PairState(msg.pair_id)
                self.order.append(msg.pair_id)
                self._inject_link_fault()
            self.fseq += 1
            fmsg = replace(msg, seq=self.fseq, pair_id=f"g{self.ground_gen}:{msg.pair_id}")
            st.frames[msg.frame_index] = msg
            st.fframes[msg.frame_index] = fmsg
            st.arrivals[msg.frame_index] = time.monotonic()
            # the run's record of a pair the ground never recorded (the ground killed): its frames had come
            self._write_telemetry({"pair_id": msg.pair_id, "event": "frame", "frame_index": msg.frame_index})
            assert self.flight is not None
            if len(st.frames) == 2:
                st.complete_at = st.sent_at = time.monotonic()
                st.proc_at_complete = self.flight.proc.stats()
                st.garbage_at_complete = self.flight.line_garbage()
            if st.sent_to != self.generation:
                st.frame_mids.clear()
            st.frame_mids[msg.frame_index] = self._to_flight(fmsg)
            st.sent_to = self.generation
        return True

    def _inject_link_fault(self) -> None:
        """Test fault: at the N-th pair the ground link's far end freezes (stall) or vanishes (exit)."""
        kind, n = self.link_fault
        self.pairs_seen += 1
        if kind is None or self.pairs_seen - 1 != n:
            return
        self.log(f"supervisor: injected link fault {kind}@{n}")
        if kind == "stall":
            os.kill(os.getpid(), signal.SIGSTOP)  # stops reading and writing; run.py continues and ends us
        elif kind == "exit":
            if self.flight is not None:
                self.flight.proc.kill("link fault exit")
            os._exit(EXIT_LINK_LOST)

    def _new_ground_session(self, hello: Hello, epoch: int) -> None:
        if epoch == self.ground_epoch and hello.session == self.ground_session:
            return  # the same ground saying Hello again
        if self.ground_epoch is not None:
            self.log(f"supervisor: new ground session {hello.session:08x} (link session {epoch})")
        self._end_ground_session("ground_restarted", "a new ground session replaced this one")
        self.ground_epoch, self.ground_session = epoch, hello.session
        self.ground_gen += 1
        if self.flight is not None:
            # the flight process drops the old session's half pairs (recorded here already): held, they came back
            # after 8 more pairs as a stale frame_dropped (QA 65f L1). A board is told the same way (flight_sw.board)
            self._to_flight(Hello(role="hil-server", session=hello.session))

    def _end_ground_session(self, code: str, text: str) -> None:
        """The pairs of the ending ground session can no longer be answered: record them, clear the tables."""
        for pid in self.order:
            st = self.pairs[pid]
            if not st.done:
                self._fail_pair(st, code, text, tell_ground=False)
        self.pairs.clear()
        self.order.clear()
        self.ground_epoch = None

    def _on_flight(self, generation: int, msg) -> None:
        if self.flight is None or generation != self.flight.generation:
            return  # a message from a dead incarnation
        if isinstance(msg, EOFError):
            self._on_flight_exit()
        elif isinstance(msg, NewLinkSession):
            self._resync_flight(msg)
        elif isinstance(msg, Hello):
            if self.flight_cmd and not self.flight.hello:  # who a user's program says it is: kept nowhere before
                said = ", ".join(
                    f"{k} {printable(str(getattr(msg, k)), 128)!r}"
                    for k in ("role", "software", "protocol_version")
                    if k not in msg.omitted
                )
                left = f" (it leaves out {', '.join(msg.omitted)})" if msg.omitted else ""
                self.log(f"supervisor: the flight program's Hello: {said or 'no fields'}{left}")
                # for the run's summary: its ground's flight_hello is this server's
                from ground_sim.stream import hello_record  # the record the ground keeps of a board's Hello

                self._write_telemetry({"event": "flight_program_hello", **hello_record(msg)})
            self.hello_seen = self.flight.hello = True
            self._answer_ground_hello()
        elif isinstance(msg, Heartbeat):
            pass
        elif isinstance(msg, Result):
            st = self._pair_for_fseqs(msg.frame_seqs)
            if st is None or st.done or st.result is not None:
                # a pair gets one Result (docs/protocol.md): the first stands. A second one sent at once used to
                # replace it on its way to the ground; one for a pair not (or no longer) asked for vanished unsaid
                second = st is not None and not st.done
                what = "a second Result: the first stands" if second else "a Result for no open pair"
                self._ignore("stale_results", "stale_result", f"ignored {what} (frames {list(msg.frame_seqs)})")
                if not second and any(q > self.fseq or q < 1 for q in msg.frame_seqs):
                    # frames never forwarded: a pair that then hangs says so (its answer named the wrong frames).
                    # A late Result of a pair closed already (an old ground session's) is no such hint
                    self.flight.last_ignored = f"a Result for frames {list(msg.frame_seqs)}, never sent to it"
                return
            self.flight.last_ignored = None  # answers match again
            st.result = msg
            st.result_at = time.monotonic()
            st.proc_at_result = self.flight.proc.stats()
            st.result_mid = self._to_ground(replace(msg, frame_seqs=st.seqs))
            self._finish_if_delivered(st)
        elif isinstance(msg, Telemetry):
            st = self._pair_for_fseqs(msg.frame_seqs)
            if st is None or st.done or st.flight_telemetry is not None:
                # one Telemetry per Result (docs/protocol.md); a second one, or one after an Error or for a pair
                # closed already, vanished without a word (the ground counts its own as ignored_telemetry)
                second = st is not None and not st.done
                what = "a second Telemetry: the first stands" if second else "a Telemetry for no open pair"
                self._ignore("stale_telemetry", "stale_telemetry", f"ignored {what} (frames {list(msg.frame_seqs)})")
                return
            st.flight_telemetry = msg
            self._finish_if_delivered(st)
        elif isinstance(msg, Error):
            # an error from the flight software about a specific frame or pair
            st = None
            for pid in self.order:
                s = self.pairs[pid]
                if not s.done and msg.seq is not None and any(f.seq == msg.seq for f in s.fframes.values()):
                    st = s
            if st is not None:  # the program's words, escaped: they reach the log, the console and the summary
                self._fail_pair(st, printable(msg.code, 100), printable(msg.text))
            elif msg.seq is None:
                self.counters["errors"] += 1
                self._to_ground(msg)
            else:  # about a frame no open pair holds (one already answered, or never sent): it used to vanish
                why = f"ignored an Error about frame {msg.seq}, which no open pair holds: {printable(msg.text, 200)}"
                self._ignore("stale_errors", "stale_error", why)
        else:  # a Config or Frame is the ground's to send: from the flight side it means nothing (it was uncounted)
            why = f"ignored a {type(msg).__name__} from the flight process (the ground's to send)"
            self._ignore("unexpected_messages", "unexpected_message", why)

    def _ignore(self, counter: str, event: str, text: str) -> None:
        """A message from the flight process that nothing answers: counted, logged and kept as a flight event
        (the run's summary sums the counter and shows the last event)."""
        self.counters[counter] += 1
        self.log(f"supervisor: {text}")
        self._write_telemetry({"event": event, "text": text})

    def _finish_if_delivered(self, st: PairState) -> None:
        """Send the pair's Telemetry once the ground holds the whole Result (its line time is then known)."""
        if st.done or st.result is None or st.flight_telemetry is None:
            return
        if st.result_mid is None:
            self._fail_pair(st, "link_down", "no ground session to send the result to", tell_ground=False)
            return
        outcome = self.ground.outcome(st.result_mid) or "pending"
        if outcome == "pending":
            return
        if outcome.startswith("failed"):
            self._fail_pair(st, "link_down", f"result not delivered: {outcome[8:]}", tell_ground=False)
            return
        times = self.ground.times(st.result_mid)
        if times is not None and times.last_tx_pending:
            now = time.monotonic()
            st.result_write_wait = now if st.result_write_wait is None else st.result_write_wait
            if now - st.result_write_wait < WRITE_RECORD_WAIT_S:  # protocol.links: polled, not waited in this loop
                return  # the next poll reads it
        st.result_link_s = float(times.line_s) if times is not None and times.line_s is not None else 0.0
        st.result_queue_s = times.queue_s if times is not None else None
        st.result_acked_at = times.delivered if times is not None and times.delivered is not None else time.monotonic()
        self._complete(st, st.flight_telemetry)

    def _complete(self, st: PairState, msg: Telemetry) -> None:
        assert self.flight is not None and st.result_at is not None
        st.done = True
        # flight latency: last frame in here -> Result out of the flight process (before its line time)
        latency = st.result_at - (st.complete_at or st.result_at)
        # the server's view of the deadline: last frame in -> Result acknowledged by the ground, on this clock. The
        # ground's e2e_latency_s (the deadline's definition, judged at the ground) starts and ends at other events:
        # the two differ by a few ms either way (docs/hil.md)
        server_e2e = (st.result_acked_at or time.monotonic()) - (st.complete_at or st.result_at)
        deadline = float(self.config.deadline_s if self.config else self.budget.deadline_s)
        met = server_e2e <= deadline
        stats = self.flight.proc.stats()
        tel = replace(
            msg,
            frame_seqs=st.seqs,
            total_latency_s=latency,
            deadline_s=deadline,
            deadline_met=met,
            cpu_fraction=pair_cpu_fraction(st.proc_at_complete, st.proc_at_result or stats),
            peak_rss_bytes=int(stats.get("peak_rss_mib", 0.0) * 1024 * 1024),
            link={
                # the flight process's own result_queue_s is its local link's: the ground link's, or none, is ours
                **{k: v for k, v in msg.link.items() if k != "result_queue_s"},
                **self._link_stats(),
                "flight_latency_s": msg.total_latency_s,
                "result_link_s": st.result_link_s,
                **({} if st.result_queue_s is None else {"result_queue_s": st.result_queue_s}),
                "server_e2e_s": server_e2e,
                "restarts": float(self.counters["restarts"]),
                # its wait for its core while another process held it (none known before its last frame came)
                **(
                    {}
                    if st.proc_at_complete is None
                    else {"flight_contention_s": pair_contention_s(st.proc_at_complete, st.proc_at_result or stats)}
                ),
            },
        )
        self.counters["results"] += 1
        if st.result is not None and st.result.degraded:
            self.counters["degraded"] += 1
        if not met:
            self.counters["deadline_missed"] += 1
        self._to_ground(tel)
        self._write_telemetry(
            {
                "pair_id": st.pair_id,
                "event": "result",
                "frame_seqs": list(st.seqs),
                "level": st.result.level if st.result else None,
                "degraded": bool(st.result.degraded) if st.result else None,
                "flight_latency_s": latency,
                "server_e2e_s": server_e2e,
                "deadline_s": deadline,
                "server_deadline_met": met,
                "arrival_s": [round(st.arrivals[k] - self.t_start, 6) for k in sorted(st.arrivals)],
                "queue_wait_s": msg.queue_wait_s,
                "result_link_s": st.result_link_s,
                "result_queue_s": st.result_queue_s,
                "stages": msg.stages,
                "cpu_fraction": tel.cpu_fraction,
                "peak_rss_mib": stats.get("peak_rss_mib"),
            }
        )
        st.release()

    def _answer_ground_hello(self) -> None:
        if self.ground_waiting_hello and self.flight is not None and self.flight.hello:
            self.ground_waiting_hello = False
            self._to_ground(Hello(role="hil-server", session=self.ground.session_id))

    def _take_last_words(self) -> None:
        """Handle what the flight incarnation that just ended sent and this loop has not read yet: its Reader's
        queued events and what is still in its link. Taken after the restart, they were a dead incarnation's and
        dropped: a pair answered in full whose Telemetry was still queued was sent to the next incarnation again,
        answered twice and the pair after it missed its deadline (QA 64a, M1)."""
        from protocol.links import LinkClosed

        assert self.flight is not None
        gen = self.flight.generation
        if self.flight_reader is not None:
            self.flight_reader.stopped.set()
            self.flight_reader.join(timeout=1.0)  # one recv cycle (0.2 s) at most: it stops reading for good
        with self.events.mutex:  # the ground's events stay queued, in their order
            mine = [e for e in self.events.queue if e[0] == "flight" and e[1] == gen]
            rest = [e for e in self.events.queue if not (e[0] == "flight" and e[1] == gen)]
            self.events.queue.clear()
            self.events.queue.extend(rest)
        msgs = [e[2] for e in mine]
        # to the link's end (a socket's EOF), or a quiet spell (a pty says none): what its reader thread had not yet
        # parsed came after a drain that stopped at the first empty read, and was dropped (review of stop 64)
        end, quiet = time.monotonic() + LAST_WORDS_S, time.monotonic() + LAST_WORDS_QUIET_S
        while time.monotonic() < end:
            try:
                pkt = self.flight.link.recv_packet(timeout=0.05)
            except (EOFError, OSError, LinkClosed):  # a closed or failed link has nothing more to say
                break
            if pkt is not None:
                msgs.append(pkt.message)
                quiet = time.monotonic() + LAST_WORDS_QUIET_S
            elif time.monotonic() >= quiet and not getattr(self.flight, "says_eof", False):
                break
        for msg in msgs:
            if not isinstance(msg, EOFError):
                self._on_flight(gen, msg)

    def _on_flight_exit(self) -> None:
        assert self.flight is not None
        self._take_last_words()
        report = self.flight.proc.wait(2.0)
        reason = getattr(report, "reason", None) or "flight process exited"
        if "memory" in reason:
            code, counter, how = "memory_ceiling", "memory_ceiling", "died"
        elif getattr(report, "kind", None) == "ok":  # it ended itself, with success: not a crash, still a lost pair
            code, counter, how = "flight_exit", "exits", "exited"
            reason = "it exited with status 0 while the run was on"
        else:
            code, counter, how = "flight_crash", "crashes", "died"
        self.counters[counter] += 1
        st = self._oldest_outstanding()
        if st is not None and (st.unreached or self._reached_flight(st)):  # a second time: its crash, not a loop
            self._fail_pair(st, code, f"flight process {how} while processing ({reason})")
        elif st is not None:  # a crash between two pairs costs no pair: the next incarnation is sent it
            st.unreached += 1
            self.log(f"supervisor: pair {st.pair_id}: its frames never reached the flight process that {how}; "
                     "sent to the next one")  # fmt: skip
        self._restart_flight(reason)

    def _reached_flight(self, st: PairState) -> bool:
        """Whether the flight incarnation ``st`` was sent to acknowledged any of its frames: it had (part of) the
        pair when it died, and the pair is its crash (one that dies on a frame dies on it again). Frames forwarded as
        it died, none acknowledged (the pair after its last answer, come before its exit was seen), never reached
        it, and the pair is not its crash (QA 64a)."""
        assert self.flight is not None
        if st.sent_to != self.flight.generation or not st.frame_mids:
            return True  # not known otherwise: as before, the incarnation's
        return any(self.flight.link.outcome(mid) == "delivered" for mid in st.frame_mids.values())

    def _link_stats(self) -> dict[str, float]:
        stats = getattr(self.ground, "stats", {})
        stats = stats() if callable(stats) else stats
        return {f"ground_{k}": float(v) for k, v in dict(stats).items() if isinstance(v, (int, float))}

    def _check_ground_link(self) -> bool:
        """Session events of the ground link; False when the ground ended the session or the link is gone."""
        keep = True
        for ev in self.ground.events():
            earlier = self.ground_epoch is not None and ev.epoch != self.ground_epoch
            if ev.kind in ("lost", "restarted", "closed") and earlier:
                # about a session a newer Hello already replaced (the Reader's queue can run ahead of these events)
                if ev.kind != "closed":
                    self.counters["link_errors"] += 1  # counted whichever of the two the supervisor saw first
                self.log(f"supervisor: LINK ERROR: ground {ev.kind} (earlier session {ev.epoch}): {ev.text}")
                continue
            if ev.kind in ("lost", "restarted", "transport") or (ev.kind == "closed" and self._outstanding()):
                self.counters["link_errors"] += 1
                self.log(f"supervisor: LINK ERROR: ground {ev.kind}: {ev.text}")
                self._end_ground_session("link_down", f"ground link {ev.kind}: {ev.text}")
            elif ev.kind == "closed":
                self._end_ground_session("link_down", "ground closed the link")
            if ev.kind in ("closed", "transport"):
                keep = False
        for pid in list(self.order):
            self._finish_if_delivered(self.pairs[pid])
        return keep

    def _outstanding(self) -> bool:
        return any(not self.pairs[pid].done for pid in self.order)

    def _check_refusals(self) -> None:
        """Account for what the HIL server refused from the flight process since the last look.

        Every refused message is counted and logged with its reason. A refused Result (a wrong-shaped grid, a
        field out of range, an array over the decoder's budget) ends the oldest pair waiting for one at once as
        ``bad_result`` with that reason: the flight process will not send it again, and waiting for the hard
        limit would report a hang. A refused Telemetry completes its pair without one (the Result stands).
        """
        assert self.flight is not None
        counts = self.flight.new_counts()
        reasons = [(r.type_code, r.reason) for r in self.flight.take_refusals()]
        # a datagram that failed to decode is counted but not REJECTed (and a flood may outrun the kept reasons)
        unexplained = sum(counts.get(k, 0) for k in REFUSED_STATS) - len(reasons)
        early = self.flight.refused_early
        if early is not None and early in reasons:  # its REJECT came after all: it was accounted for from its header
            reasons.remove(early)
            self.flight.refused_early = None
        if unexplained > 0:
            reasons.append((None, "a datagram or message that failed to decode (reason not kept)"))
            self.counters["refused_messages"] += unexplained - 1  # the one appended is counted below
        for type_code, reason in reasons:
            self._refused(type_code, reason)
        garbage = sum(counts.get(k, 0) for k in LINE_ERROR_STATS)
        if garbage > 0:
            if self.counters["flight_line_errors"] == 0:
                self.log(f"supervisor: corrupted or malformed frames from the flight process dropped ({garbage})")
            self.counters["flight_line_errors"] += garbage

    def _refused(self, type_code: int | None, reason: str) -> None:
        """One message refused from the flight process: counted, logged, and its pair ended (see _check_refusals)."""
        assert self.flight is not None
        self.counters["refused_messages"] += 1
        what = MESSAGE_NAMES.get(type_code, "message") if type_code is not None else "message"
        self.flight.last_refusal = f"{what} refused: {reason}"
        n = self.counters["refused_messages"]
        if n <= MAX_REFUSAL_LOGS:
            more = "; further refusals are only counted" if n == MAX_REFUSAL_LOGS else ""
            self.log(f"supervisor: the flight process sent a {what} the HIL server refused: {reason}{more}")
            self._write_telemetry({"event": "refused", "type": what, "reason": reason})
        if type_code == Result.TYPE:
            st = self._oldest_outstanding()
            if st is not None:
                self._fail_pair(st, "bad_result", f"the flight process's Result was refused: {reason}")
        elif type_code == Telemetry.TYPE:
            st = self._oldest_without_telemetry()
            if st is not None:
                self._complete_without_telemetry(st, f"its Telemetry was refused: {reason}")

    def _refuse_skipped(self, held: Skipping) -> None:
        """Account now for the record the link is skipping: its REJECT would come only once its last byte is in."""
        assert self.flight is not None
        self.flight.refused_early = (held.type_code, held.reason)
        self._refused(held.type_code, held.reason)

    def _oldest_without_telemetry(self) -> PairState | None:
        """The oldest pair whose Result came and whose Telemetry has not."""
        return self._oldest(lambda st: st.result is not None and st.flight_telemetry is None)

    def _complete_without_telemetry(self, st: PairState, why: str) -> None:
        """A pair whose Result came but whose Telemetry did not: the Result is kept, the timing is the server's."""
        assert st.result_at is not None
        self.counters["missing_telemetry"] += 1
        self.log(f"supervisor: pair {st.pair_id}: no Telemetry from the flight process ({why}); Result kept")
        self._write_telemetry({"pair_id": st.pair_id, "event": "missing_telemetry", "text": why})
        deadline = float(self.config.deadline_s if self.config else self.budget.deadline_s)
        st.flight_telemetry = Telemetry(
            frame_seqs=st.fseqs,
            total_latency_s=max(0.0, st.result_at - (st.complete_at or st.result_at)),
            deadline_s=deadline,
            link={"flight_telemetry_missing": 1.0},
        )
        self._finish_if_delivered(st)

    def _flight_note(self, st: PairState | None = None) -> str:
        """What the HIL server refused from the current flight incarnation, for a hang's reason (or ""); the line
        garbage since pair ``st``'s frames were all in (all of this incarnation's without one)."""
        assert self.flight is not None
        skipping = self.flight.skipping()
        if skipping is not None:
            return f"; the flight process is sending a message the HIL server refuses ({skipping.reason})"
        last, ignored = self.flight.last_refusal, self.flight.last_ignored
        bad = max(0, self.flight.line_garbage() - (st.garbage_at_complete if st is not None else 0))
        return (
            (f"; last refused from the flight process: {last}" if last else "")
            + (f"; it sent {ignored}, which was ignored (its frame_seqs wrong?)" if ignored else "")
            # junk on its line instead of a Result read as a plain hang (QA of stop 73)
            + (
                f"; {bad} frame{'' if bad == 1 else 's'} it sent failed the line's checks (garbage on its line)"
                if bad
                else ""
            )
        )

    def _check_held_stream(self) -> bool:
        """Refuse at once a record the flight process declared over the size limit, and restart it; True if so.

        The link skips such a record's bytes as they come and REJECTs it once they have all gone by; nothing behind
        it in the stream can be read meanwhile. A process that declares 1 GiB and trickles it, heartbeats going on,
        used to hold its pair until the hard limit (reported as a hang) and every pair after it. Its header is
        enough: the record is refused now (a Result ends its pair as ``bad_result`` with the declared size, a
        Telemetry completes its pair without one), and since the stream cannot resynchronise short of all those
        bytes, the process is restarted and the pairs still outstanding are replayed to the next incarnation.
        """
        assert self.flight is not None
        held = self.flight.skipping()
        if held is None or not held.oversize:
            return False  # an unknown type within the size limit: its bytes are bounded, the stream goes on after
        self._refuse_skipped(held)
        what = MESSAGE_NAMES.get(held.type_code, "message")
        self._restart_flight(f"its stream is held by a {what} refused from its header: {held.reason}")
        return True

    def _check_watchdogs(self) -> None:
        assert self.flight is not None
        now = time.monotonic()
        gap = self._stall.take() if self._stall is not None else 0.0
        if gap:  # first: the stop is not the flight process's silence
            self._forgive_own_stop(gap)
        self._check_refusals()
        if self._check_held_stream():
            return
        st = self._oldest_outstanding()
        since = None if st is None or st.complete_at is None else max(st.complete_at, st.sent_at or st.complete_at)
        if (
            st is not None
            and st.complete_at is not None
            and since is not None
            and (now - since - st.stopped_s > self._hard_limit())
        ):
            self.counters["hangs"] += 1
            note = self._flight_note(st)
            skipping = self.flight.skipping()
            if skipping is not None:  # a record of an unknown type still trickling in: never refused otherwise
                self._refuse_skipped(skipping)
            self._fail_pair(
                st,
                "deadline_hang",
                f"no result {now - st.complete_at:.1f} s after the last frame"
                + (f" ({now - since:.1f} s after its restart's replay)" if since > st.complete_at else "")
                + f" (hard limit {self._hard_limit():.1f} s): flight process killed and restarted{note}",
            )
            self._restart_flight("hung past the hard deadline")
            return
        waiting = self._oldest_without_telemetry()
        if (
            waiting is not None
            and waiting.result_at is not None
            and (now - waiting.result_at - waiting.stopped_s > self._hard_limit())
        ):
            late = now - waiting.result_at
            self._complete_without_telemetry(
                waiting, f"none {late:.1f} s after its Result (hard limit {self._hard_limit():.1f} s)"
            )
        hb_limit = HEARTBEAT_TIMEOUT_S / max(self.effective_fraction, 0.01)
        assert self.flight_reader is not None
        if now - self.flight_reader.last_message > hb_limit:
            self.counters["hangs"] += 1
            if st is not None:
                self._fail_pair(st, "heartbeat_lost", f"no heartbeat for {hb_limit:.1f} s{self._flight_note(st)}")
            self._restart_flight("heartbeat lost")
            return
        report = self.flight.proc.poll()
        if report is not None:
            self._on_flight_exit()

    def serve(self, idle_timeout_s: float = 600.0) -> int:
        """Run until the ground closes its session, the link fails, or nothing happens for ``idle_timeout_s``.

        Returns 0, or :data:`EXIT_LINK_LOST` if a ground session was lost on the way.
        """
        self._start_flight()
        ground_reader = Reader(self.ground, "ground", self.events)
        ground_reader.start()
        last_activity = time.monotonic()
        self._stall = StallClock()
        try:
            while True:
                try:
                    tag, gen, msg, epoch = self.events.get(timeout=0.05)
                except queue.Empty:
                    self._check_watchdogs()
                    if not self._check_ground_link():
                        return self._exit_code()
                    if time.monotonic() - last_activity > idle_timeout_s:
                        self.log("supervisor: idle timeout, shutting down")
                        return self._exit_code()
                    continue
                if tag == "ground":
                    last_activity = time.monotonic()
                    if not self._on_ground(msg, epoch):
                        return self._exit_code()
                else:
                    self._on_flight(gen, msg)
                self._check_watchdogs()
                if not self._check_ground_link():
                    return self._exit_code()
        finally:
            self.closing = True  # main()'s SIGTERM handler no longer interrupts: the summary must be written
            if self.flight is not None and not self.flight.hello:  # what its links saw, for the run's reason
                self._keep_no_hello_note()
                why = self.no_hello_seen[1]
                # after a restart it is the last start's silence: "in 17 s" read as if none had ever said Hello, of
                # a program whose first two starts had (QA of stop 79)
                since = (
                    f"since its restart {time.monotonic() - self.flight.started:.0f} s before the end (an earlier "
                    "start did say Hello)"
                    if self.hello_seen
                    else f"in {time.monotonic() - self.t_start:.0f} s"
                )
                if why:
                    self.log(f"supervisor: {NO_HELLO_LOG} {since}: {why}")
            # a stop the loop never looked at since: `run` continues and ends a server stopped to the end at once,
            # and its summary said 0 s while the ground's pairs read as lost to the flight computer (QA of stop 85)
            self.stopped_s += self._stall.take()
            self._stall.close()
            ground_reader.stopped.set()
            if self.flight_reader:
                self.flight_reader.stopped.set()
            try:
                if self.flight:
                    self._check_refusals()
            finally:  # the counters first: closing the flight process may take a while
                # strangers on the HIL server's port (a wrong key, a second peer): in its log only, the run read PASS
                stats = getattr(self.ground, "stats", None) or {}  # a property of every Link
                port = int(stats.get("auth_failures", 0) or 0) + int(stats.get("peers_refused", 0) or 0)
                self._write_telemetry(
                    {"event": "summary", **self.counters, "port_refused": port, "server_stopped_s": self.stopped_s}
                )
                try:
                    if self.flight:
                        # a throttled program's exit takes its share's time: 1 s at 2 % is 20 ms of a core
                        grace = min(END_GRACE_MAX_S, END_GRACE_S / max(self.effective_fraction, 1e-3))
                        self.flight.close("supervisor shutdown", grace_s=grace)
                        self.unlogged_bytes += getattr(self.flight.proc, "unlogged_bytes", 0)
                    # after the close: the last incarnation's count is known once its output pipe ended
                    self._write_telemetry({"event": "flight_output", "unlogged_bytes": self.unlogged_bytes})
                finally:
                    if self.telemetry_file:
                        self.telemetry_file.close()
                        self.telemetry_file = None

    def _forgive_own_stop(self, gap: float) -> None:
        """This process was not scheduled for ``gap`` s (:class:`protocol.stall.StallClock`: its own busy work does
        not count): the flight process's answers and heartbeats meanwhile wait in the queue, unread. The open
        pairs' watchdogs and the heartbeat clock leave the gap out, so what came is read before anyone is judged
        silent (an 8 s stop of the server killed a healthy flight process as hung).

        As the ZeroMQ link does, the flight is forgiven one stop between two hearings of it: what a live flight
        process sent is read within a poll after a stop, so a second stop with nothing heard in between counts
        against it. Forgiven every time, a server starved again and again would never find a hung flight."""
        self.stopped_s += gap
        reader = self.flight_reader
        heard = None if reader is None else reader.last_message
        if heard is not None and heard == self._forgave_at:
            self.log(
                f"supervisor: this process was not scheduled for {gap:.1f} s; the flight process, not heard since "
                "the last such stop, is judged by its silence meanwhile"
            )
            return
        for st in self.pairs.values():
            if not st.done and st.complete_at is not None:
                st.stopped_s += gap
        if reader is not None and heard is not None:
            # the reader thread may store a newer message's time meanwhile: the later of the two stands (a plain
            # += could put back an older time and make the silence look longer)
            forgiven = max(reader.last_message, heard + gap)
            reader.last_message = self._forgave_at = forgiven  # not read again: a message meanwhile is a hearing
        self.log(f"supervisor: this process was not scheduled for {gap:.1f} s; the flight process is not blamed for it")

    def _exit_code(self) -> int:
        return EXIT_LINK_LOST if self.counters["link_errors"] else 0


def parse_link_fault(spec: str | None) -> tuple[str | None, int]:
    """``stall@N`` or ``exit@N`` (test fault injection on the ground link), or None."""
    if not spec:
        return None, -1
    kind, _, n = spec.partition("@")
    if kind not in ("stall", "exit") or not n.isdigit():
        raise InputError(f"--link-fault must be stall@N or exit@N, got {spec!r}")
    return kind, int(n)


def parse_efficiency(text: str) -> tuple[float, float]:
    """``F:ETA`` -> (duty cycle, efficiency), both in (0, 1]; anything else is an :class:`InputError`."""
    try:
        f, eta = (float(v) for v in text.split(":"))
    except ValueError:
        raise InputError(f"--throttle-efficiency must be F:ETA (e.g. 0.0163:0.65), got {text!r}") from None
    if not (0.0 < f <= 1.0 and 0.0 < eta <= 1.0):
        raise InputError(f"--throttle-efficiency: F and ETA must be in (0, 1], got {text!r}")
    return f, eta


def main(argv: list[str] | None = None) -> int:
    from hil_server.budgets import get_budget, load_calibration
    from hil_server.procemu import EmulatedProcessor, ProcessorSpec, flight_core, keep_off_core
    from protocol.ceiling import apply_memory_ceiling
    from protocol.linkspec import open_link

    ap = argparse.ArgumentParser(prog="python -m hil_server.supervisor", description=__doc__.splitlines()[0])
    ap.add_argument("--link", required=True, help="serial:URL[@BAUD] or zmq:ENDPOINT (bound here)")
    ap.add_argument("--budget", required=True)
    ap.add_argument("--budget-file", default=None, help="the budget file --budget names a budget of")
    ap.add_argument("--telemetry", type=Path, default=None, help="JSON-lines telemetry file")
    ap.add_argument("--fault", default=None, help="fault injection for the first flight incarnation")
    ap.add_argument(
        "--flight-cmd",
        default=None,
        help="run this flight program instead of ours (split like a shell; {port} = its pty, also $HAZARD_HIL_PORT)",
    )
    ap.add_argument("--link-fault", default=None, help="test fault on the ground link: stall@N or exit@N")
    ap.add_argument("--keys", type=Path, default=None, help="CURVE key directory (zmq links)")
    ap.add_argument("--insecure", action="store_true", help="zmq without CURVE (loopback debugging only)")
    ap.add_argument("--link-timeout", type=float, default=4.0, help="peer silent/stalled this long = link lost (s)")
    ap.add_argument("--memory-mib", type=float, default=1024.0, help="this process's memory headroom (MiB)")
    ap.add_argument("--idle-timeout", type=float, default=600.0)
    ap.add_argument(
        "--throttle-efficiency",
        default=None,
        metavar="F:ETA",
        help="the throttle's efficiency ETA measured at duty cycle F just before (hazard-hil run's check): the "
        "budget runs on the host's calibration rescaled to it",
    )
    args = ap.parse_args(argv)

    def log(s: str) -> None:  # one write per line: print's two let another thread's line in before the newline
        sys.stderr.write(s + "\n")
        sys.stderr.flush()

    try:
        budget = get_budget(args.budget, args.budget_file)
        parse_link_fault(args.link_fault)
        if args.flight_cmd is not None and not args.flight_cmd.strip():
            raise InputError("--flight-cmd is empty (an unset variable?): give the program to run, or leave it out")
        if args.flight_cmd:
            flight_argv(args.flight_cmd, "PORT")  # a command that cannot be split is bad usage, said now
        cal = None if budget.is_host else load_calibration()  # full speed needs no host speed
        if args.throttle_efficiency is not None and cal is not None:
            cal = cal.rescaled(*parse_efficiency(args.throttle_efficiency))
        duty = budget.duty(cal)
        fraction = duty.applied
        # the flight's core fixed before this server leaves it: a restarted flight process keeps the same one
        core = flight_core()
        spec = ProcessorSpec(cpu_fraction=fraction, memory_mib=budget.memory_mib, core=core)
        own_cores = keep_off_core(core)  # the flight's core is the flight's (procemu's docstring, stop 81)
        link = open_link(
            args.link,
            server=True,
            keys=args.keys,
            insecure=args.insecure,
            peer_timeout=args.link_timeout,
            connect_timeout=None,
            name="ground",
            log=log,
        )
    except InputError as exc:
        log(f"supervisor: error: {exc}")
        return 2

    sup: Supervisor | None = None

    def _term(signum, frame):  # orderly shutdown: the finally blocks kill the flight process
        if sup is not None and sup.closing:
            return  # already shutting down: let the summary and the flight process's kill finish
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, _term)
    sup = Supervisor(
        link,
        budget,
        lambda: EmulatedProcessor(spec),
        telemetry_path=args.telemetry,
        fault=args.fault,
        link_fault=args.link_fault,
        flight_cmd=args.flight_cmd,
        cpu_fraction=fraction,
        effective_fraction=duty.effective,
        log=log,
    )
    # where each ran, as it is, for the run's summary (a host of one allowed core shares it)
    sup._write_telemetry({"event": "cores", "flight": core, "server": sorted(own_cores)})
    limit = apply_memory_ceiling(args.memory_mib)
    log(
        f"supervisor: budget {budget.name} -> cpu fraction {fraction:.4f} (x{duty.efficiency:.2f} = "
        f"{duty.effective:.4f} of full speed), memory {budget.memory_mib} MiB, "
        # the ground's Config may set another deadline (`run --deadline 30` read "deadline 2.0 s" here; QA of stop 79)
        f"budget deadline {budget.deadline_s} s (the ground's Config may set another); own memory ceiling "
        f"{limit / 2**20:.0f} MiB address space; the flight on core {core}, this server on "
        + (f"core(s) {_cores(own_cores)}" if core not in own_cores else "the same (the only one allowed)")
    )
    failed: str | None = None
    try:
        return sup.serve(idle_timeout_s=args.idle_timeout)
    except KeyboardInterrupt:
        return sup._exit_code()
    except FlightFailed as exc:
        failed = str(exc)
        return EXIT_FLIGHT_FAILED
    finally:
        signal.signal(signal.SIGTERM, signal.SIG_IGN)  # already shutting down: finish closing the link
        link.close()
        if failed:  # the last line of supervisor.log: `run` reports it as the reason
            log(f"supervisor: error: {failed}")


def _cores(cores: frozenset[int]) -> str:
    return ",".join(str(c) for c in sorted(cores))


if __name__ == "__main__":
    sys.exit(main())
