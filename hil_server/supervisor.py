"""The HIL supervisor: the box the ground simulator talks to.

It relays between the ground link (serial pty or ZeroMQ) and the flight
process, which it starts on an emulated processor (one pinned core, CPU duty
cycle, memory ceiling; :mod:`hil_server.procemu`) and talks to over a local
socket pair. Being in the middle lets it account for every pair:

* it timestamps the last frame of each pair (latency starts there),
* it enforces a hard limit (deadline + grace) and a heartbeat watchdog, killing
  and restarting a hung flight process,
* it turns crashes and memory-ceiling breaches into ``Error`` messages for the
  pair in progress, restarts the flight process, replays the frames of the
  pairs still outstanding, and carries on,
* it adds what only the outside can measure (achieved CPU fraction, peak RSS,
  deadline outcome seen from the link) to the flight's ``Telemetry``.

Every pair the ground completes ends in exactly one of: ``Result`` (full or
degraded) or ``Error`` with a reason. Telemetry is also written as JSON lines.
"""

from __future__ import annotations

import argparse
import json
import queue
import socket
import sys
import threading
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

from protocol.messages import Config, Error, Frame, Heartbeat, Hello, Result, Telemetry

# After a kill the flight process needs a moment to come back; frames that
# arrive meanwhile are queued and replayed.
HEARTBEAT_TIMEOUT_S = 5.0  # at full speed; scaled by 1/duty when throttled
MIN_GRACE_S = 2.0


@dataclass
class PairState:
    pair_id: str
    frames: dict[int, Frame] = field(default_factory=dict)
    arrivals: dict[int, float] = field(default_factory=dict)  # frame_index -> monotonic arrival time
    complete_at: float | None = None  # monotonic time the last frame arrived
    proc_at_complete: dict | None = None  # emulated-processor stats then, for the pair's CPU fraction
    proc_at_result: dict | None = None
    sent_to: int = -1  # flight generation the frames went to
    result: Result | None = None
    result_link_s: float = 0.0
    done: bool = False

    @property
    def seqs(self) -> tuple[int, int]:
        return (self.frames[0].seq, self.frames[1].seq)


def pair_cpu_fraction(before: dict | None, after: dict) -> float:
    """CPU the flight process got while a pair was outstanding, over the wall time it could run.

    ``(cpu_after - cpu_before) / (avail_after - avail_before)`` with ``avail = wall -
    contention`` (time it waited for a host core that another process held is not
    the emulator's doing). The lifetime figure would be diluted by idle waits.
    """
    if before is None:
        return float("nan")
    d_cpu = after["cpu_s"] - before["cpu_s"]
    d_avail = (after["wall_s"] - after["contention_s"]) - (before["wall_s"] - before["contention_s"])
    return d_cpu / d_avail if d_avail > 0 else float("nan")


class Reader(threading.Thread):
    """Moves messages from a link into the supervisor's single event queue."""

    def __init__(self, link, tag: str, events: queue.Queue, generation: int = 0) -> None:
        super().__init__(name=f"reader-{tag}", daemon=True)
        self.link, self.tag, self.events, self.generation = link, tag, events, generation
        self.stopped = threading.Event()
        # stamped here, not in the main loop: the loop may be busy (a result's line time on a slow
        # or noisy link) while the peer is perfectly alive
        self.last_message = time.monotonic()

    def run(self) -> None:
        while not self.stopped.is_set():
            try:
                msg = self.link.recv(timeout=0.2)
            except (EOFError, OSError):
                self.events.put((self.tag, self.generation, EOFError()))
                return
            if msg is not None:
                self.last_message = time.monotonic()
                self.events.put((self.tag, self.generation, msg))


class FlightHandle:
    """One incarnation of the flight process on the emulated processor."""

    def __init__(self, processor_factory, generation: int, fault: str | None, heartbeat_s: float) -> None:
        from protocol.links import StreamLink

        self.generation = generation
        parent, child = socket.socketpair()
        self.proc = processor_factory()
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
        self.link = StreamLink(parent)
        self.hello = False

    def close(self, reason: str | None = None) -> None:
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
        heartbeat_s: float = 0.25,
        grace_s: float | None = None,
        cpu_fraction: float = 1.0,
        log=print,
    ) -> None:
        self.ground = ground_link
        self.budget = budget
        self.processor_factory = processor_factory
        self.fault = fault
        self.heartbeat_s = heartbeat_s
        self.cpu_fraction = cpu_fraction
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
        self.restarts = 0
        self.counters = {
            "results": 0,
            "degraded": 0,
            "errors": 0,
            "deadline_missed": 0,
            "restarts": 0,
            "crashes": 0,
            "memory_ceiling": 0,
            "hangs": 0,
        }
        # open for the supervisor's lifetime, closed in serve()'s finally
        self.telemetry_file = open(telemetry_path, "a") if telemetry_path else None  # noqa: SIM115
        self.t_start = time.monotonic()  # telemetry times are seconds since the supervisor started

    # -- flight process lifecycle ---------------------------------------------------------
    def _start_flight(self) -> None:
        self.generation += 1
        self.flight = FlightHandle(
            self.processor_factory, self.generation, self.fault if self.generation == 1 else None, self.heartbeat_s
        )
        self.flight_reader = Reader(self.flight.link, "flight", self.events, self.generation)
        self.flight_reader.start()
        if self.config is not None:
            self.flight.link.send(self.config)
        for pid in self.order:  # replay what the dead incarnation never answered
            st = self.pairs[pid]
            if not st.done:
                for idx in sorted(st.frames):
                    self.flight.link.send(st.frames[idx])
                st.sent_to = self.generation

    def _restart_flight(self, reason: str) -> None:
        assert self.flight is not None
        report = None
        if self.flight.proc.alive:
            self.flight.proc.kill(reason)
        report = self.flight.proc.wait(5.0)
        if self.flight_reader:
            self.flight_reader.stopped.set()
        self.flight.close()
        self.counters["restarts"] += 1
        self.log(f"supervisor: flight process restarted ({reason}; exit {report})")
        self._start_flight()

    def _hard_limit(self) -> float:
        deadline = float(self.config.deadline_s if self.config else self.budget.deadline_s)
        grace = self.grace_s if self.grace_s is not None else max(MIN_GRACE_S, deadline)
        return deadline + grace

    def _oldest_outstanding(self) -> PairState | None:
        for pid in self.order:
            st = self.pairs[pid]
            if not st.done and st.complete_at is not None and st.result is None:
                return st
        return None

    # -- accounting -------------------------------------------------------------------------
    def _fail_pair(self, st: PairState, code: str, text: str) -> None:
        st.done = True
        self.counters["errors"] += 1
        err = Error(code=code, text=f"pair {st.pair_id}: {text}", seq=st.frames[1].seq if 1 in st.frames else None)
        self.ground.send(err)
        self._write_telemetry({"pair_id": st.pair_id, "event": "error", "code": code, "text": text})

    def _write_telemetry(self, record: dict) -> None:
        if self.telemetry_file:
            self.telemetry_file.write(json.dumps(record, sort_keys=True) + "\n")
            self.telemetry_file.flush()

    def _pair_for_seqs(self, seqs) -> PairState | None:
        for pid in self.order:
            st = self.pairs[pid]
            if 0 in st.frames and 1 in st.frames and st.seqs == tuple(seqs):
                return st
        return None

    # -- event handlers ---------------------------------------------------------------------
    def _on_ground(self, msg) -> bool:
        """Returns False when the ground is finished."""
        if isinstance(msg, EOFError):
            return False
        if isinstance(msg, Hello):
            # answer once the flight process has booted (at a low duty cycle its imports alone take a while)
            self.ground_waiting_hello = True
            self._answer_ground_hello()
        elif isinstance(msg, Config):
            self.config = msg
            assert self.flight is not None
            self.flight.link.send(msg)
        elif isinstance(msg, Frame):
            if msg.pair_id is None or msg.frame_index not in (0, 1):
                self.ground.send(Error(code="bad_frame", seq=msg.seq, text="frame needs pair_id and frame_index 0/1"))
                self.counters["errors"] += 1
                return True
            st = self.pairs.get(msg.pair_id)
            if st is None:
                st = self.pairs[msg.pair_id] = PairState(msg.pair_id)
                self.order.append(msg.pair_id)
            st.frames[msg.frame_index] = msg
            st.arrivals[msg.frame_index] = time.monotonic()
            assert self.flight is not None
            if len(st.frames) == 2:
                st.complete_at = time.monotonic()
                st.proc_at_complete = self.flight.proc.stats()
            self.flight.link.send(msg)
            st.sent_to = self.generation
        return True

    def _on_flight(self, generation: int, msg) -> None:
        if self.flight is None or generation != self.flight.generation:
            return  # a message from a dead incarnation
        if isinstance(msg, EOFError):
            self._on_flight_exit()
        elif isinstance(msg, Hello):
            self.flight.hello = True
            self._answer_ground_hello()
        elif isinstance(msg, Heartbeat):
            pass
        elif isinstance(msg, Result):
            st = self._pair_for_seqs(msg.frame_seqs)
            if st is None or st.done:
                return
            st.result = msg
            st.proc_at_result = self.flight.proc.stats()
            t0 = time.monotonic()
            self.ground.send(msg)
            self.ground.flush(timeout=self._hard_limit() + 120.0)  # the result's line time is telemetry too
            st.result_link_s = time.monotonic() - t0
        elif isinstance(msg, Telemetry):
            st = self._pair_for_seqs(msg.frame_seqs)
            if st is None or st.done:
                return
            st.done = True
            now = time.monotonic()
            # "last frame in -> result out": out = handed to the link, before its line time
            latency = now - (st.complete_at or now) - st.result_link_s
            deadline = float(self.config.deadline_s if self.config else self.budget.deadline_s)
            met = latency <= deadline
            stats = self.flight.proc.stats()
            tel = replace(
                msg,
                total_latency_s=latency,
                deadline_s=deadline,
                deadline_met=met,
                cpu_fraction=pair_cpu_fraction(st.proc_at_complete, st.proc_at_result or stats),
                peak_rss_bytes=int(stats.get("peak_rss_mib", 0.0) * 1024 * 1024),
                link={
                    **msg.link,
                    **self._link_stats(),
                    "flight_latency_s": msg.total_latency_s,
                    "result_link_s": st.result_link_s,
                    "restarts": float(self.counters["restarts"]),
                },
            )
            self.counters["results"] += 1
            if st.result is not None and st.result.degraded:
                self.counters["degraded"] += 1
            if not met:
                self.counters["deadline_missed"] += 1
            self.ground.send(tel)
            self._write_telemetry(
                {
                    "pair_id": st.pair_id,
                    "event": "result",
                    "frame_seqs": list(msg.frame_seqs),
                    "level": st.result.level if st.result else None,
                    "degraded": bool(st.result.degraded) if st.result else None,
                    "latency_s": latency,
                    "deadline_s": deadline,
                    "deadline_met": met,
                    "deadline_margin_s": deadline - latency,
                    "arrival_s": [round(st.arrivals[k] - self.t_start, 6) for k in sorted(st.arrivals)],
                    "queue_wait_s": msg.queue_wait_s,
                    "result_link_s": st.result_link_s,
                    "stages": msg.stages,
                    "cpu_fraction": tel.cpu_fraction,
                    "peak_rss_mib": stats.get("peak_rss_mib"),
                }
            )
        elif isinstance(msg, Error):
            # an error from the flight software about a specific frame or pair
            st = None
            for pid in self.order:
                s = self.pairs[pid]
                if not s.done and msg.seq is not None and any(f.seq == msg.seq for f in s.frames.values()):
                    st = s
            if st is not None:
                self._fail_pair(st, msg.code, msg.text)
            else:
                self.counters["errors"] += 1
                self.ground.send(msg)

    def _answer_ground_hello(self) -> None:
        if self.ground_waiting_hello and self.flight is not None and self.flight.hello:
            self.ground_waiting_hello = False
            self.ground.send(Hello(role="hil-server"))

    def _on_flight_exit(self) -> None:
        assert self.flight is not None
        report = self.flight.proc.wait(2.0)
        reason = getattr(report, "reason", None) or "flight process exited"
        code = "memory_ceiling" if "memory" in reason else "flight_crash"
        self.counters["memory_ceiling" if code == "memory_ceiling" else "crashes"] += 1
        st = self._oldest_outstanding()
        if st is not None:
            self._fail_pair(st, code, f"flight process died while processing ({reason})")
        self._restart_flight(reason)

    def _link_stats(self) -> dict[str, float]:
        stats = getattr(self.ground, "stats", {})
        stats = stats() if callable(stats) else stats
        return {f"ground_{k}": float(v) for k, v in dict(stats).items() if isinstance(v, (int, float))}

    def _check_watchdogs(self) -> None:
        assert self.flight is not None
        now = time.monotonic()
        st = self._oldest_outstanding()
        if st is not None and st.complete_at is not None and now - st.complete_at > self._hard_limit():
            self.counters["hangs"] += 1
            self._fail_pair(
                st,
                "deadline_hang",
                f"no result {now - st.complete_at:.1f} s after the last frame "
                f"(hard limit {self._hard_limit():.1f} s): flight process killed and restarted",
            )
            self._restart_flight("hung past the hard deadline")
            return
        hb_limit = HEARTBEAT_TIMEOUT_S / max(self.cpu_fraction, 0.01)
        assert self.flight_reader is not None
        if now - self.flight_reader.last_message > hb_limit:
            self.counters["hangs"] += 1
            if st is not None:
                self._fail_pair(st, "heartbeat_lost", f"no heartbeat for {hb_limit:.1f} s")
            self._restart_flight("heartbeat lost")
            return
        report = self.flight.proc.poll()
        if report is not None:
            self._on_flight_exit()

    def serve(self, idle_timeout_s: float = 600.0) -> int:
        self._start_flight()
        ground_reader = Reader(self.ground, "ground", self.events)
        ground_reader.start()
        last_activity = time.monotonic()
        try:
            while True:
                try:
                    tag, gen, msg = self.events.get(timeout=0.05)
                except queue.Empty:
                    self._check_watchdogs()
                    if time.monotonic() - last_activity > idle_timeout_s:
                        self.log("supervisor: idle timeout, shutting down")
                        return 0
                    continue
                if tag == "ground":
                    last_activity = time.monotonic()
                    if not self._on_ground(msg):
                        return 0
                else:
                    self._on_flight(gen, msg)
                self._check_watchdogs()
        finally:
            ground_reader.stopped.set()
            if self.flight_reader:
                self.flight_reader.stopped.set()
            if self.flight:
                self.flight.close("supervisor shutdown")
            self._write_telemetry({"event": "summary", **self.counters})
            if self.telemetry_file:
                self.telemetry_file.close()


def main(argv: list[str] | None = None) -> int:
    import signal

    from hil_server.budgets import get_budget, load_calibration
    from hil_server.procemu import EmulatedProcessor, ProcessorSpec
    from protocol.linkspec import open_link

    ap = argparse.ArgumentParser(prog="python -m hil_server.supervisor", description=__doc__.splitlines()[0])
    ap.add_argument("--link", required=True, help="serial:PATH[@BAUD] or zmq:ENDPOINT (bound here)")
    ap.add_argument("--budget", required=True)
    ap.add_argument("--telemetry", type=Path, default=None, help="JSON-lines telemetry file")
    ap.add_argument("--fault", default=None, help="fault injection for the first flight incarnation")
    ap.add_argument("--idle-timeout", type=float, default=600.0)
    args = ap.parse_args(argv)

    budget = get_budget(args.budget)
    fraction = budget.duty_fraction(load_calibration())
    spec = ProcessorSpec(cpu_fraction=fraction, memory_mib=budget.memory_mib)
    link = open_link(args.link, server=True)

    def _term(signum, frame):  # orderly shutdown: the finally blocks kill the flight process
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, _term)
    sup = Supervisor(
        link,
        budget,
        lambda: EmulatedProcessor(spec),
        telemetry_path=args.telemetry,
        fault=args.fault,
        cpu_fraction=fraction,
        log=lambda s: print(s, file=sys.stderr, flush=True),
    )
    print(
        f"supervisor: budget {budget.name} -> cpu fraction {fraction:.4f}, memory {budget.memory_mib} MiB, "
        f"deadline {budget.deadline_s} s",
        file=sys.stderr,
        flush=True,
    )
    try:
        return sup.serve(idle_timeout_s=args.idle_timeout)
    except KeyboardInterrupt:
        return 0
    finally:
        link.close()


if __name__ == "__main__":
    sys.exit(main())
