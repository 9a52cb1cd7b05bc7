"""Stream a rendered descent to the flight side and collect what comes back.

The ground half of an HIL run: reads the pair directories listed in a
``manifest.json`` (written by ``hazard-hil render``), sends ``Config`` then two
``Frame``s per pair (upper = frame_index 0, lower = 1, sharing a ``pair_id``)
over the link, and records every ``Result``, ``Telemetry`` and ``Error``.

Pacing: ``lockstep`` (default) sends a pair, waits for its outcome, then sends
the next - clean per-pair latency. ``asap`` sends everything at once and shows
queueing on a slow processor; each answer is recorded (and shown) as it arrives,
while the later pairs' frames are still on the line. Every pair ends in ``results.jsonl`` as
``result`` or ``error`` with a reason; a pair with no answer within the
ground's own timeout is recorded as ``error: no_response`` - nothing is lost.

Link sessions (docs/protocol.md): the ground says Hello (with its link session
id), waits for the server's Hello, then sends Config. The first Hello is awaited
at most ``hello_timeout_s`` (the link session included), with a progress line
every 10 s; when it never comes the descent ends at once: every pair is recorded
as ``not_run`` with the reason and the process exits 5. When the session is lost
(the far end stopped reading, went silent, closed, or was restarted), the pairs
in flight end at once as ``link_down`` errors with the link's reason; the ground
then waits for a new session, says Hello and Config again, and carries on with
the next pair. The wait is ``reconnect_timeout_s`` from the moment the loss was
seen, not per pair: a flight computer that stays away ends each later pair at
once as ``link_down`` (it came back if its session is up by then), so a lost
board ends a descent in seconds rather than in pairs x 10 s. The process exits 3
when a session was lost on the way (0 otherwise).

A message from the flight side that the link refuses although it arrived whole
(it fails to decode, the decoder's budget or the schema: a wrong-shaped grid, a
field out of range; :meth:`protocol.links.Link.take_refusals` names it) is acted
on at once, as the HIL server does for its flight process: a refused Result
ends the oldest pair waiting for one as ``bad_result`` with the reason (it used
to wait out the response timeout, 3 x deadline + 30 s, and end as
``no_response``, the reason lost), a refused Telemetry lets its pair complete
without it (``telemetry_missing`` in the record), and any other refused message
is said on stderr. Each is counted; ``ground.json`` beside ``results.jsonl``
holds ``refused_messages`` and the last one's type and reason. A refusal is
matched to a pair only once the messages received before it have been taken.

A record from the flight side whose header declares more than the size limit
(``Limits.max_message_bytes``) cannot be accepted, and nothing behind it in the
stream can arrive until all its declared bytes have gone by (a board that
declares 1 GiB and trickles it would hold every later pair). The ground does
not wait: a Result ends its pair at once as ``bad_result`` with the declared
size, and the ground gives up that link session (the far end is told) and
carries on in a new one, as after a lost session.

The deadline (docs/hil.md) is judged here, on ``e2e_latency_s``: from the
moment the ground finished sending the pair's last frame (its last byte on the
line) to the moment the ground holds the whole Result. Each record carries it
with ``deadline_met`` and ``deadline_margin_s``, and beside it the flight
latency the far end reported (``flight_latency_s``), the frames' and the
Result's line times (``frames_line_s``, ``result_line_s`` as the sender
measured it, ``result_rx_s`` first to last frame here) and ``result_bytes``.
``Config.options["link_baud"]`` tells the flight side this link's rate (0 =
none to plan for), so it can leave room for its Result's line time;
``Config.options["descent_id"]`` identifies this descent in every session it resends Config in;
``Config.options["result_rev"]`` that this ground decodes every Result field
(``protocol.messages.RESULT_REV``): a flight side told nothing sends only the
baseline fields an older ground decodes.

After every pair, its line is appended to ``results.jsonl`` and, with
``--telemetry``, to the timing lines (one ``write`` each), and ``ground.json``
is replaced atomically. SIGTERM and SIGINT end the descent between messages:
what finished is on disk, the process exits 128 + the signal number.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import signal
import sys
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from protocol.arq import ECHO_TEXT, Received, Refusal
from protocol.errors import InputError, os_error_text
from protocol.grids import decimated_geometry, elevation_from_wire, psafe_from_wire
from protocol.links import MECHANISM_MISMATCH_TEXT, WRITE_RECORD_WAIT_S, LinkClosed, ZmqLink
from protocol.messages import (
    MESSAGE_NAMES,
    PROTOCOL_VERSION,
    RESULT_REV,
    Config,
    Error,
    Frame,
    Heartbeat,
    Hello,
    Result,
    Telemetry,
    without_arrays,
)
from protocol.pairdir import read_manifest, read_pair
from protocol.plan import plan_note as _plan_note
from protocol.quiet import Quieter
from protocol.stall import StallClock
from reports.console import printable
from reports.html import save_npy_atomic, write_atomic

from .results_file import append_records

EXIT_LINK_LOST = 3
EXIT_NO_HELLO = 5  # the flight side never said Hello: nothing ran (every pair recorded as not_run)
LINK_CODES = ("link_down",)
# the ground's link counters kept in ground.json (protocol.arq.STAT_KEYS: a serial link's; a ZeroMQ link has none)
LINE_COUNTERS = ("crc_errors", "malformed", "bytes_discarded", "retransmits", "retransmit_bytes", "echoed_frames")
# a ZeroMQ link's frames dropped by the session rules (docs/protocol.md section 7): a seq that did not rise, a frame
# of a past or unknown session
SESSION_DROPS = ("duplicates_dropped", "misaddressed_frames", "foreign_frames")
REFUSALS_SAID = 5  # refusals of one message type said one by one; then one line per quiet period, with the count
REFUSAL_DRAIN_S = 0.2  # before acting on a refusal: what the link's reader still holds is taken first (in order)
UNANSWERED_TEXT = (
    "its ZeroMQ connection is up but the board never answered on it: a board serves one ground at a time and this "
    "one is busy with another (its console says 'second peer ... refused'), or its program is not reading"
)
UNATTRIBUTED_SAID = 5  # unattributed Errors from the flight side said one by one; then one line per ...
UNATTRIBUTED_QUIET_S = 10.0  # ... this many seconds, with the count
HELLO_NOTE_S = 10.0  # a progress line this often while the first Hello is awaited
LINE_OVERHEAD = 1.15  # framing, byte stuffing and acknowledgements over the images' bytes (9600 baud: 22 s for 19)
QUEUE_SHOWN_S = 0.05  # a Result's wait in the sender's queue is shown on the console from this long
# a Result's Telemetry follows it at once (the HIL server sends both together); a board that sends none had its
# Results dropped after the response timeout, as "no result or error"
TELEMETRY_GRACE_S = 10.0
# ... plus twice the line time of this many bytes on a paced line: the Telemetry goes once the Result is
# acknowledged, and at 1200 baud its ~1-2 kB took longer than the 10 s alone (the Result's line time then read
# 0.00 s and the flight latency was lost, stop 60's QA)
TELEMETRY_LINE_BYTES = 4096


def hello_record(h: Hello) -> dict:
    """Who a Hello says its sender is, as the run's files keep it (ground.json's ``flight_hello``, and the HIL
    server's record of a ``--flight-cmd`` program's): ``role``, ``software`` (None when the Hello left it out: a
    board that names nobody is not "hazard-hil") and ``protocol_version``, escaped; the fields it left out, read as
    their documented defaults, under ``omitted``."""
    out: dict = {
        "role": printable(h.role, 64),
        "software": None if "software" in h.omitted else printable(h.software, 128),
        "protocol_version": h.protocol_version,
    }
    if h.omitted:
        out["omitted"] = list(h.omitted)
    return out


def telemetry_grace_s(baud: float | None, base_s: float = TELEMETRY_GRACE_S) -> float:
    """How long a Result's Telemetry is awaited on a line of ``baud`` (None or 0: unpaced, ZeroMQ); ``base_s``
    is the grace before the line time (tests shorten it: a board that sends no Telemetry waits it out per pair)."""
    return base_s + (2.0 * TELEMETRY_LINE_BYTES * 10 / baud if baud else 0.0)


UPLINK_NOTE_S = 10.0  # a progress line this often while a pair's frames are on a slow line
AUTH_GIVE_UP_S = 5.0  # the far end refused our CURVE key for this long: the first Hello will not come
# timing fields of a record that also go to the telemetry lines
TELEMETRY_KEYS = (
    "pair_id",
    "label",
    "status",
    "code",
    "level",
    "degraded",
    "skipped",
    "e2e_latency_s",
    "deadline_s",
    "deadline_met",
    "deadline_margin_s",
    "flight_latency_s",
    "flight_deadline_met",
    "server_e2e_s",
    "frames_line_s",
    "frames_retx_s",
    "result_line_s",
    "result_queue_s",
    "result_rx_s",
    "outside_flight_s",
    "ground_stopped_s",
    "result_bytes",
    "queue_wait_s",
    "cpu_fraction",
    "peak_rss_mib",
    "stages",
    "stage_order",
    "plan",
    "pose_verdict",
    "pose",
    "flight_notes",
    "elapsed_s",
)


def plan_note(rec: dict) -> str:
    """Why a recorded Result stopped below the full level (:func:`protocol.plan.plan_note` on its ``plan`` and
    ``skipped``); "" when its Telemetry did not say."""
    return _plan_note(rec.get("plan"), rec.get("skipped"))


class Interrupted(Exception):
    """SIGTERM or SIGINT: end the descent, keeping what finished."""

    def __init__(self, signum: int) -> None:
        super().__init__(f"interrupted by {signal.Signals(signum).name}")
        self.signum = signum


@dataclass
class PairOutcome:
    pair_id: str
    label: str
    altitude_m: float
    pair_dir: str
    seqs: tuple[int, int]
    sent_at: float = 0.0
    turn_at: float = 0.0  # when the ground took the pair up (it may end before a byte of it is sent)
    result: Result | None = None
    telemetry: Telemetry | None = None
    error: Error | None = None
    link_s: float = 0.0
    frames_written_at: float | None = None  # the lower frame's last byte on the line
    frames_line_s: float | None = None
    # the lower frame's retransmissions after its first whole transmission (a noisy line): the deadline's clock
    # started at that first one, and the flight side may have had the pair only at the last
    frames_retx_s: float = 0.0
    result_t_first: float | None = None
    result_t_done: float | None = None
    result_order: int = 0  # its Result's place among the messages the link received (Received.order)
    drops_at_send: int = 0  # the link's session drops (SESSION_DROPS) when its frames went
    ignored_at_send: int = 0  # Results the ground had ignored (for no pair sent) when its frames went
    result_bytes: int = 0
    telemetry_missing: str | None = None  # why the pair completes without Telemetry (it was refused)
    ground_stopped_s: float = 0.0  # this process was not scheduled for so long while the pair was in flight
    telemetry_wait_stopped_s: float = 0.0  # ... and while its Result was in and its Telemetry awaited
    last_frame_started: float | None = None  # the lower frame's first byte handed to the line
    frame_ids: tuple[int, ...] = ()  # its Frames' message ids on the link
    frames_in_dir: int = 2  # its pair directory's frames: the HIL streams frames 0 and the last of them

    @property
    def finished(self) -> bool:
        return self.error is not None or (
            self.result is not None and (self.telemetry is not None or self.telemetry_missing is not None)
        )


def same_camera(a: dict, b: dict) -> bool:
    """The same intrinsics, but for the last bits of a float written by another tool (relative 1e-9)."""
    return set(a) == set(b) and all(math.isclose(float(a[k]), float(b[k]), rel_tol=1e-9) for k in a)


def camera_mismatch(camera: dict, descent: dict) -> str:
    """Why a pair whose camera is not the descent's cannot be streamed in it (the Config says it once)."""

    def said(c: dict) -> str:
        return f"{c['width']}x{c['height']} px, fx {c['fx']:.6g}, fy {c['fy']:.6g}, cx {c['cx']:.6g}, cy {c['cy']:.6g}"

    return (
        f"its camera ({said(camera)}) is not the descent's ({said(descent)}): the Config names the camera once per "
        "descent (docs/protocol.md); stream it in a run of its own"
    )


def _frame_from_pair(pair, index: int, seq: int, pair_id: str) -> Frame:
    """The Frame of ``frame_index`` 0 (the pair's frame 0) or 1 (its last frame: DESIGN.md's pair of a directory
    of more frames; frame 1 of a four-frame descent was streamed, a baseline a third as long)."""
    pose = pair.poses[-1 if index else 0]
    return Frame(
        seq=seq,
        capture_time_s=float(pose.time_s),
        position_m=tuple(float(v) for v in pose.position),
        R_world_to_cam=np.asarray(pose.R, dtype="<f8"),
        altimeter_m=float(pair.altimeter_m[-1 if index else 0]),
        image=np.ascontiguousarray(pair.images[-1 if index else 0]),
        pair_id=pair_id,
        frame_index=index,
        sun_azimuth_deg=None if pair.sun is None else float(pair.sun.azimuth_deg),
        sun_elevation_deg=None if pair.sun is None else float(pair.sun.elevation_deg),
    )


def _places(latency_s: float, deadline_s: float) -> int:
    """Decimals that tell ``latency_s`` from ``deadline_s`` (2 to 6): 0.0208 s against a 0.02 s deadline read
    "0.02 s  deadline 0.02 s MISSED" (stop 62's QA L3)."""
    places = 2
    while places < 6 and latency_s != deadline_s and round(latency_s, places) == round(deadline_s, places):
        places += 1
    return places


def write_outcome(out_dir: Path, o: PairOutcome, deadline_s: float = float("nan")) -> dict:
    """Save arrays of a finished pair under ``out_dir/<pair_id>/`` and return its JSON record.

    ``deadline_s``: the deadline the ground set; the record's ``deadline_met`` is
    ``e2e_latency_s <= deadline_s`` (docs/hil.md).

    Grids: ``state_grid.npy`` (uint8 codes), ``psafe_grid.npy`` (float32, NaN outside),
    ``elevation_grid.npy`` (float32 m, NaN = none; on its own, possibly decimated grid),
    ``elevation_filled_grid.npy`` (bool, that grid's shape: the elevation leans on a gap fill) when sent;
    full-resolution maps when sent: ``hazard.npy``, ``elevation.npy``, ``state.npy`` and
    ``elevation_filled_image.npy`` (bool, ``elevation.npy``'s shape: that pixel's elevation is a gap fill).

    A Result whose Telemetry was refused is recorded without the far end's figures (``flight_latency_s``,
    ``stages``, ...), with ``telemetry_missing`` saying why.
    """
    rec: dict = {
        "pair_id": o.pair_id,
        "label": o.label,
        "altitude_m": o.altitude_m,
        "pair_dir": o.pair_dir,
        "frame_seqs": list(o.seqs),
        "link_s": o.link_s,
        "frames_line_s": o.frames_line_s,
        "frames_retx_s": o.frames_retx_s,  # cut to e2e below: a retransmission after the Result came is none of it
        # from the first byte of the pair queued (or, for a pair that never went out, from its turn) to its outcome
        # recorded: how long an error took, too
        "elapsed_s": time.monotonic() - (o.sent_at or o.turn_at) if (o.sent_at or o.turn_at) else None,
        "deadline_s": deadline_s,
        "deadline_met": False,
    }
    if o.ground_stopped_s:  # its latency includes it: an answer that came in time may read as late
        rec["ground_stopped_s"] = o.ground_stopped_s
    if o.frames_in_dir > 2:  # said once on stderr alone, and the row's "300/250/200/150" read as all four (QA 74)
        rec["frames_in_dir"] = o.frames_in_dir
    if o.error is not None:
        # the flight side's words, escaped: they reach the console, the logs and the summary
        rec.update(status="error", code=printable(o.error.code, 100), text=printable(o.error.text))
        return rec
    assert o.result is not None and (o.telemetry is not None or o.telemetry_missing is not None)
    d = out_dir / o.pair_id
    d.mkdir(parents=True, exist_ok=True)
    r, t = o.result, o.telemetry
    arrays = {
        "state_grid": np.asarray(r.state_grid, dtype=np.uint8),
        "psafe_grid": psafe_from_wire(r.psafe_grid),  # on its own (decimated) geometry
        "elevation_grid": elevation_from_wire(r.elevation_grid, r.elevation_offset_m, r.elevation_unit_cm),
    }
    if r.elevation_filled is not None:
        arrays["elevation_filled_grid"] = np.asarray(r.elevation_filled, bool)
    for name, arr in (("hazard", r.hazard_image), ("elevation", r.elevation_image), ("state", r.state_image)):
        if arr is not None:
            arrays[name] = np.asarray(arr)
    if r.elevation_filled_image is not None:
        arrays["elevation_filled_image"] = np.asarray(r.elevation_filled_image, bool)
    for name, arr in arrays.items():  # each file whole or absent; a full disk names it
        save_npy_atomic(d / f"{name}.npy", arr)
    e_origin, e_cell = decimated_geometry(tuple(r.grid_origin_xy), r.grid_cell_m, r.elevation_step)
    p_origin, p_cell = decimated_geometry(tuple(r.grid_origin_xy), r.grid_cell_m, r.psafe_step)
    e2e = None
    rx_span = None if o.result_t_first is None or o.result_t_done is None else o.result_t_done - o.result_t_first
    if o.result_t_done is not None and o.frames_written_at is not None:
        # the writer stamps "written" once it runs again after its write returned; under load a fast answer
        # arrived before that stamp (e2e -0.00 s), and no answer can start before the frames are out (ZeroMQ: a
        # message arrives whole, its first byte unseen)
        answer_began = o.result_t_first if o.result_t_first is not None else o.result_t_done
        written = min(o.frames_written_at, answer_began)
        e2e = o.result_t_done - written
        if o.frames_written_at > answer_began:  # kept: the latency is then a lower bound, by at most this
            rec["written_stamp_late_s"] = o.frames_written_at - answer_began
    met = e2e is not None and e2e <= deadline_s
    if e2e is not None:
        rec["frames_retx_s"] = min(float(rec["frames_retx_s"]), max(0.0, e2e))
    rec.update(
        status="result",
        degraded=bool(r.degraded),
        level=r.level,
        skipped=list(r.skipped),
        grid_origin_xy=list(r.grid_origin_xy),
        grid_cell_m=r.grid_cell_m,
        elevation_origin_xy=list(e_origin),
        elevation_cell_m=e_cell,
        elevation_step=r.elevation_step,
        elevation_unit_cm=r.elevation_unit_cm,
        psafe_origin_xy=list(p_origin),
        psafe_cell_m=p_cell,
        psafe_step=r.psafe_step,
        full_maps=r.hazard_image is not None,
        sites=[asdict(s) for s in r.sites],
        no_site_reason=None if r.no_site_reason is None else printable(r.no_site_reason),
        # the deadline, judged here: the last frame's last byte sent -> the whole Result held
        e2e_latency_s=e2e,
        deadline_met=bool(met),
        deadline_margin_s=None if e2e is None else deadline_s - e2e,
        # the sender's line time comes with its Telemetry: without one it is unknown, not the span between the
        # Result's first and last frame here (0.00 s for a one-frame Result that took 4.7 s at 1200 baud)
        result_line_s=None,
        result_rx_s=rx_span,
        result_bytes=o.result_bytes,
        out_dir=str(d),
    )
    if t is None:
        rec["telemetry_missing"] = o.telemetry_missing
        return rec
    rec.update(
        # what the far end reported: its compute latency (last frame in -> Result out) and its own verdict
        # None when its Telemetry leaves it out: a board that does not say is not one that took 0 s
        flight_latency_s=None if "total_latency_s" in t.omitted else t.total_latency_s,
        flight_deadline_met=bool(t.deadline_met),
        server_e2e_s=t.link.get("server_e2e_s"),
        # the Result's line time as its sender measured it (first byte on the line -> last, MessageTimes.line_s)
        # ... and only as it measured it: a Telemetry without it (a user's program) read 0.00 s, the span between a
        # one-frame Result's first and last frame here (QA 64a); that span stays result_rx_s
        result_line_s=_line_within(t.link.get("result_link_s"), e2e, t, rec),
        # its wait in the sender's queue before that (behind an earlier pair's Result on a slow line); None: not sent
        result_queue_s=t.link.get("result_queue_s"),
        queue_wait_s=t.queue_wait_s,
        cpu_fraction=t.cpu_fraction,
        peak_rss_mib=t.peak_rss_bytes / 2**20 if t.peak_rss_bytes else None,  # 0: the flight side did not say
        stages=t.stages,
        # the order the flight side listed them in (the reference: the order they ran); the JSON lines sort keys
        stage_order=list(t.stages),
        link=t.link,
    )
    if rec["result_line_s"] is None and e2e is not None and rec["flight_latency_s"] is not None:  # ZeroMQ, say
        # what the end-to-end latency holds besides the flight's own compute: the link both ways and any queue
        rec["outside_flight_s"] = max(0.0, e2e - float(t.total_latency_s))
    if t.plan:  # revision 4: the deadline plan's figures
        rec["plan"] = t.plan
    # revision 5: the pose refinement's outcome and the flight side's warnings (a pose kept at navigation, sensors
    # that disagree), which no ground saw before; left out when the flight side does not say
    if t.pose_verdict:
        rec["pose_verdict"] = printable(t.pose_verdict)
    if t.pose:
        rec["pose"] = t.pose
    if t.notes:
        rec["flight_notes"] = [printable(n) for n in t.notes]
    return rec


def _line_within(line_s: float | None, e2e: float | None, t: Telemetry, rec: dict) -> float | None:
    """The sender's line time of a Result, at most what the end-to-end latency leaves beside the flight's compute
    and the Result's queue: on a noisy line the sender retransmits what the ground already holds (its ACKs lost),
    and read "result line 3.27 s" in a pair "end to end 1.92 s" (stop 60's QA). The sender's own figure is kept
    as ``result_line_sender_s`` when it is cut."""
    if line_s is None or e2e is None or t.total_latency_s is None:
        return line_s
    queued = t.link.get("result_queue_s")
    bound = max(0.0, e2e - float(t.total_latency_s) - float(queued or 0.0))
    if float(line_s) <= bound + 0.005:
        return line_s
    rec["result_line_sender_s"] = float(line_s)
    return bound


def descent_pair_id(i: int, entry: dict) -> str:
    """The id of the ``i``-th pair of a descent (its manifest ``entry``): ``p001-300_150``, its place first, so
    that records sort in descent order (:func:`descent_index`)."""
    return f"p{i:03d}-{entry.get('label', i)}".replace("/", "_")


def descent_index(pair_id: str) -> int | None:
    """The place in its descent of a pair id :func:`descent_pair_id` made, or None."""
    head, sep, _ = pair_id.partition("-")
    return int(head[1:]) if sep and head[:1] == "p" and head[1:].isdigit() else None


class LinkDown(Exception):
    """The link session is gone and did not come back in time."""


class NoHello(LinkDown):
    """The flight side never said Hello in the first session: nothing can run."""


@dataclass
class _SessionState:
    epoch: int | None = None  # link session the app handshake (Hello both ways) was done in
    config_epoch: int | None = None  # link session Config was sent in
    sessions: int = 0
    lost_since: float | None = None  # monotonic time the ground first went without a session since its last one
    refused_messages: int = 0  # messages from the flight side the ground refused (ground.json)
    last_refused: dict | None = None  # {"type", "reason"} of the latest
    flight_hello: dict | None = None  # what the flight side said it is: role, software, protocol_version
    said_middle_frames: bool = False  # a pair directory of more than two frames was said to be streamed as a pair
    saved: int = 0  # records already appended to results.jsonl
    telemetry_saved: int = 0  # ... and to the timing lines


def _silent_link_reason(link, where: str) -> str:
    """Why a link never came up, from what its line carried: nothing at all, or bytes that are not this protocol
    (another device on the port, or the right one at another baud: both look like line noise to the decoder)."""
    stats = getattr(link, "stats", None) or {}
    got = int(stats.get("bytes_received", 0) or 0)
    frames = int(stats.get("frames_received", 0) or 0)
    echoed = int(stats.get("echoed_frames", 0) or 0)
    if echoed and echoed == frames:
        return f"{ECHO_TEXT}, and nothing else came: no peer answers on it ({echoed} of them came back)"
    if where.startswith("serial") and got > 0:
        bad = int(stats.get("crc_errors", 0) or 0) + int(stats.get("malformed", 0) or 0)
        if frames == 0:
            return (
                f"its line carried {got} bytes but not one valid frame of this protocol ({bad} failed their checks): "
                "another device on this port, or another baud?"
            )
        return (
            f"its line carried {frames} frames ({got} bytes) but never a link session: a peer of another protocol "
            "version, or one that is not answering?"
        )
    if getattr(link, "answered", None) is False:
        return UNANSWERED_TEXT
    if getattr(link, "refused_only", False) and where.startswith("zmq:tcp://"):
        hostport = where[len("zmq:tcp://") :]
        return (
            f"nothing listens on {hostport} (connection refused): is the board's flight program (`hazard-hil "
            "flight`, or your own) running?"
        )
    check = (
        "on this port, at this baud"
        if where.startswith("serial")
        else "serving this endpoint, with these keys, and not busy with another ground (a board serves one at a time)"
    )
    return f"its link never answered (is it powered, {check}?)"


def stream_descent(
    link,
    manifest_path: Path,
    out_dir: Path,
    *,
    budget: str,
    deadline_s: float,
    preset: str = "fast",
    pace: str = "lockstep",
    response_timeout_s: float | None = None,
    hello_timeout_s: float = 900.0,
    reconnect_timeout_s: float = 10.0,
    full_maps: bool = False,
    fusion: bool = True,
    elevation_step: int = 1,
    psafe_step: int = 1,
    elevation_unit_cm: int = 1,
    progress: Callable[[dict], None] | None = None,
    telemetry_path: Path | None = None,
    where: str = "the link",
    telemetry_grace_base_s: float = TELEMETRY_GRACE_S,
    hello_note_s: float = HELLO_NOTE_S,
) -> list[dict]:
    """Run the ground side of a descent; returns one record per pair (also in ``results.jsonl``).

    ``hello_timeout_s`` bounds the wait for the first session's Hello (the link session included); ``where``
    names the far end in messages (e.g. ``serial:/dev/ttyUSB0``). ``telemetry_grace_base_s`` is the base of the
    wait for a Result's Telemetry (:func:`telemetry_grace_s`; tests shorten it, a board without Telemetry waits it
    out at every pair). ``hello_note_s``: how often a line says the first Hello is still awaited (tests shorten
    it, to see the line without waiting 10 s for it).

    On :class:`Interrupted` (raised by a signal handler) the records so far are on disk and the
    exception propagates. On :class:`NoHello` every pair without a record is recorded as ``not_run`` first.
    """
    manifest = read_manifest(manifest_path)
    base = Path(manifest_path).parent
    entries = manifest["pairs"]
    out_dir.mkdir(parents=True, exist_ok=True)
    timeout = response_timeout_s if response_timeout_s is not None else 3.0 * deadline_s + 30.0
    options = {
        "full_maps": int(bool(full_maps)),
        "elevation_step": int(elevation_step),
        "psafe_step": int(psafe_step),
        "elevation_unit_cm": int(elevation_unit_cm),
        # the line the Result comes back on, so the flight side can plan for its line time (0: no rate)
        "link_baud": int(getattr(link, "baud", None) or 0),
        "fusion": int(bool(fusion)),
        # the newest Result schema revision this ground decodes (an older flight side ignores the option)
        "result_rev": RESULT_REV,
        # this descent's identity, resent unchanged with Config in every link session: a flight side that outlives
        # grounds (a board) keeps its fused map for the same descent reconnected and starts afresh for the next
        # (a nonce, as the link's session ids are; 31 bits, exact in any number type)
        "descent_id": int.from_bytes(os.urandom(4), "big") >> 1,
    }

    outcomes: dict[tuple[int, int], PairOutcome] = {}
    by_lower_seq: dict[int, PairOutcome] = {}
    unattributed = Quieter(first=UNATTRIBUTED_SAID, quiet_s=UNATTRIBUTED_QUIET_S)  # Errors about no pair
    ignored = Quieter(first=UNATTRIBUTED_SAID, quiet_s=UNATTRIBUTED_QUIET_S)  # answers that are no pair's answer
    refusals_said = Quieter(first=REFUSALS_SAID, quiet_s=UNATTRIBUTED_QUIET_S)  # messages refused, per type
    records: list[dict] = []
    config: Config | None = None
    state = _SessionState()
    results_path = out_dir / "results.jsonl"
    counters_path = out_dir / "ground.json"
    write_atomic(results_path, "")
    write_atomic(counters_path, json.dumps({"refused_messages": 0, "last_refused": None}) + "\n")
    if telemetry_path is not None:
        write_atomic(telemetry_path, "")

    def note(text: str) -> None:
        _say(f"ground: {text}")

    def session_drops() -> int:
        """The flight side's ZeroMQ messages the link dropped by the session rules so far (0 on a serial line)."""
        stats = link.stats if isinstance(link, ZmqLink) else {}
        return sum(int(stats.get(k, 0) or 0) for k in SESSION_DROPS)

    def session_ok() -> bool:
        return state.epoch is not None and not link.failed and link.established and link.epoch == state.epoch

    def recv(timeout: float) -> Received | None:
        """The link's next packet, or None; None too once its transport has failed (the device gone, EOF): the
        callers then find the session lost and say why. A LinkClosed let out of collect or drain was a traceback
        that lost the Result already in and every later pair's record."""
        try:
            return link.recv_packet(timeout=timeout)
        except LinkClosed:
            return None

    def lost_why() -> str:
        """Why the session is gone: the link's last loss, else what its state shows (a new session can be up
        before the loss of the old one is told: the reason read "None")."""
        if link.failed:
            return f"the link failed: {link.failed}"
        if link.last_error:
            return link.last_error
        if link.established:
            return "the link started a new session (the flight side, or this side's link, restarted it)"
        return "the link is down"

    def first_hello() -> None:
        """The first session: link session and Hello within ``hello_timeout_s`` in all, a line every 10 s meanwhile
        (a board that is off, on another port or at another baud, or an emulated processor booting slowly); raises
        NoHello. A session lost during the handshake is a LinkDown, as in any session: its pair ends as
        ``link_down`` and the next pair tries again (a very noisy line loses sessions, it is not a silent peer)."""
        t0 = time.monotonic()
        end, next_note = t0 + hello_timeout_s, t0 + hello_note_s
        refused_since: float | None = None  # when the far end first refused our CURVE key
        said_unanswered = False
        while not link.wait_established(min(1.0, max(0.0, end - time.monotonic()))):
            now = time.monotonic()
            for r in link.take_refusals():  # before any session: a stranger's, counted and said
                count_refusal(r.type_code, f"before any session: {r.reason}")
            if getattr(link, "answered", None) is False and not said_unanswered:
                # said at once, not after the whole wait: the other ground's descent may end, and this one go on
                said_unanswered = True
                note(f"{UNANSWERED_TEXT}; waiting up to {hello_timeout_s:g} s in all")
            if link.failed:
                raise NoHello(f"the link to the flight computer on {where} failed: {link.failed}")
            failures = int((getattr(link, "stats", None) or {}).get("auth_failures", 0) or 0)
            if failures and refused_since is None:
                refused_since = now
            # a key is not refused by chance and libzmq redials ~10 times a second: waiting out the hello timeout
            # (120 s for a board) would only repeat the refusal
            if (
                refused_since is not None
                and now - refused_since >= AUTH_GIVE_UP_S
                and not getattr(link, "secure", True)
            ):
                raise NoHello(
                    f"the flight computer on {where} requires CURVE authentication and this ground has none "
                    "(--insecure): give it --keys DIR with a key the board accepts"
                )
            if (
                refused_since is not None
                and now - refused_since >= AUTH_GIVE_UP_S
                and MECHANISM_MISMATCH_TEXT in (link.last_error or "")
            ):
                raise NoHello(
                    f"the flight computer on {where} runs without CURVE (--insecure) and this ground has keys: "
                    "start the board with --keys DIR, or give both --insecure on loopback"
                )
            if refused_since is not None and now - refused_since >= AUTH_GIVE_UP_S:
                raise NoHello(
                    f"the CURVE handshake with the flight computer on {where} failed ({failures} "
                    f"handshake{'' if failures == 1 else 's'} in {now - t0:.0f} s): either the board's key directory "
                    "does not hold this ground's public key in clients/, or this ground's server.key is not the "
                    "board's (`hazard-hil keys DIR` makes a matching set)"
                )
            if now >= end:
                stranger = (
                    f"something there answers, but not in this protocol ({state.refused_messages} messages "
                    f"refused, the latest: {state.last_refused['reason']})"
                    if state.refused_messages and state.last_refused
                    else _silent_link_reason(link, where)
                )
                raise NoHello(f"no Hello from the flight computer on {where} within {hello_timeout_s:g} s: {stranger}")
            if now >= next_note:
                next_note = note_mark(t0, now)
        handshake(max(0.0, end - time.monotonic()), t0, first=True)

    def note_mark(t0: float, now: float) -> float:
        """Say the latest ``hello_note_s`` mark passed (10 s, 20 s, ...), not the measured time, which a late loop
        rounded up past it ("11 s of 11 s"); after a stall, that mark alone. Returns when the next one is due."""
        mark = hello_note_s * ((now - t0) // hello_note_s)
        note(f"waiting for the flight computer's Hello on {where} ({mark:.0f} s of {hello_timeout_s:.0f} s)")
        return t0 + mark + hello_note_s

    def handshake(hello_s: float, t0: float, first: bool = False) -> None:
        """Hello both ways in the link session up now, within ``hello_s`` (raises LinkDown, or NoHello when no Hello
        came in the ``first`` session); a line every 10 s."""
        state.epoch = None
        for r in link.take_refusals():  # from before this session: its pairs have ended
            refused(r, set())
        epoch = link.epoch

        def closed(exc: Exception) -> Exception:  # the device failed between the link session and the Hello
            why = f"the link to the flight computer on {where} failed: {link.failed or exc}"
            return NoHello(why) if first else LinkDown(why)

        try:
            link.send(Hello(role="ground", session=link.session_id), epoch=epoch)
        except LinkClosed as exc:
            raise closed(exc) from None
        end = time.monotonic() + hello_s
        next_note = t0 + hello_note_s * (1 + (time.monotonic() - t0) // hello_note_s)  # the next mark from now
        while True:  # the HIL server answers Hello once its flight process has booted
            pkt = recv(0.5)  # a failed transport reads as nothing: said below (it was a traceback)
            if pkt is not None and isinstance(pkt.message, Hello) and pkt.epoch == epoch:
                said_hello(pkt.message)
                break
            if link.failed:
                raise closed(LinkClosed(link.failed))
            if not link.established or link.epoch != epoch:
                raise LinkDown(f"link session lost during the handshake: {lost_why()}")
            now = time.monotonic()
            if now > end:
                raise (NoHello if first else LinkDown)(
                    f"no Hello from the flight computer on {where} within {hello_timeout_s:g} s (its link answers: "
                    "is its flight software running?)"
                )
            if now > next_note:
                next_note = note_mark(t0, now)
        state.epoch = epoch
        state.sessions += 1
        if state.sessions > 1:
            note(f"resynchronised: new link session {link.session_id:08x} <-> {link.peer_session:08x}")

    def said_hello(h: Hello) -> None:
        """Keep who the flight side says it is (ground.json, the summary); say what this ground cannot vouch for."""
        new = hello_record(h)
        if new == state.flight_hello:
            return
        state.flight_hello = new
        if h.omitted:
            note(
                f"the flight side's Hello leaves out {', '.join(h.omitted)}: read as the defaults of docs/protocol.md "
                f"section 5 (protocol_version {h.protocol_version})"
            )
        if h.protocol_version != PROTOCOL_VERSION:
            note(
                f"the flight side says it speaks protocol version {h.protocol_version}; this ground speaks "
                f"{PROTOCOL_VERSION} (docs/protocol.md): what it sends may be refused or read wrongly"
            )
        if h.role not in ("flight", "hil-server"):
            note(f"the flight side's Hello says role {new['role']!r}, not 'flight'")

    def ensure_session() -> None:
        if session_ok():
            return
        if state.sessions == 0:
            first_hello()
            return
        state.epoch = None
        now = time.monotonic()
        if state.lost_since is None:
            state.lost_since = now
        # one wait per loss, shared by the pairs whose turn comes meanwhile: a board that stays away must not
        # cost every remaining pair the whole timeout
        if not link.wait_established(max(0.0, state.lost_since + reconnect_timeout_s - now)):
            why = link.last_error or "silent"
            gone = time.monotonic() - state.lost_since
            raise LinkDown(
                f"no link session with the flight computer for {gone:.0f} s (the ground waits {reconnect_timeout_s:g} "
                f"s for one after a loss; {why})"
            )
        handshake(hello_timeout_s, time.monotonic())
        state.lost_since = None

    def send_config() -> None:
        if config is not None and state.config_epoch != state.epoch:
            link.send(config, epoch=state.epoch)
            state.config_epoch = state.epoch

    def fail_in_flight(want: set[tuple[int, int]], why: str) -> None:
        for s in list(want):
            o = outcomes[s]
            if o.result is not None and not o.finished:  # its Result came: it stands, without Telemetry
                o.telemetry_missing = f"{why} before its Telemetry came"
                record(o)
            elif not o.finished:
                give_up(o, "link_down", why)
            want.discard(s)

    def overdue_telemetry(want: set[tuple[int, int]]) -> None:
        """A pair whose Result came :func:`telemetry_grace_s` ago without its Telemetry completes without it: a
        board that sends none lost every Result it sent, each after the whole response timeout (36 s)."""
        now = time.monotonic()
        grace = telemetry_grace_s(getattr(link, "baud", None), telemetry_grace_base_s)
        for s in sorted(want):
            o = outcomes[s]
            if telemetry_overdue(o, now, grace):
                o.telemetry_missing = f"no Telemetry came within {grace:.0f} s of its Result"
                want.discard(s)
                record(o)

    def held_stream(want: set[tuple[int, int]]) -> bool:
        """True when the flight side's stream is held by a record declared over the size limit (see the module
        doc): a Result ends the oldest pair waiting for one as ``bad_result``, and the session is given up."""
        held = getattr(link, "skipping", None)  # byte-stream links only: ZeroMQ carries whole messages
        if held is None or not held.oversize:
            return False
        what = MESSAGE_NAMES.get(held.type_code, f"message of type {held.type_code}")
        why = f"the flight computer's {what} was refused from its header: {held.reason}"
        count_refusal(held.type_code, held.reason, show=False)  # said below, or in its pair's record
        waiting = [outcomes[k] for k in sorted(want) if outcomes[k].result is None and not outcomes[k].finished]
        if held.type_code == Result.TYPE and waiting:
            o = waiting[0]
            give_up(o, "bad_result", f"{why}; the link session was given up (its stream cannot resynchronise)")
            want.discard(o.seqs)
        else:  # no pair to blame: the pairs in flight end with the session, this says why
            note(f"FLIGHT ERROR: {why}; giving up this link session and starting a new one")
        link.abandon_session(f"the flight computer's stream is held by a record over the size limit ({why})")
        return True

    def count_refusal(type_code: int | None, reason: str, show: bool = True) -> str:
        """Count one message refused from the flight side; a line on stderr as :data:`REFUSALS_SAID` allows."""
        what = MESSAGE_NAMES.get(type_code, "message") if type_code is not None else "message"
        state.refused_messages += 1
        state.last_refused = {"type": what, "reason": reason}
        if show:  # the first few one by one, then one line per quiet period with the count since (a ZeroMQ peer
            # speaking garbage printed 100 near-identical lines; QA 64a)
            say, unsaid, since = refusals_said.offer(what, time.monotonic(), reason)
            if say:
                more = f" ({unsaid} more refused in the last {since:.0f} s)" if unsaid else ""
                note(f"the flight computer sent a {what} the ground refused: {reason}{more}")
        return what

    def refused(r: Refusal, want: set[tuple[int, int]]) -> None:
        """One message from the flight side that the link refused (a wrong-shaped grid, a field out of range, a
        body over the decoder's budget): counted and noted. A refused Result ends its pair as ``bad_result`` at
        once (the flight side will not send it again): the pair its body names when it got that far (a schema
        failure), else, in ``want``, the oldest pair that had no Result when it was refused, unless an older
        pair's Result came after it (``Refusal.order``: that pair was answered after all; answers are taken to
        come in pair order). A refusal reaches the ground apart from the messages: taken in arrival order, one
        acted on after its pair's good Result had ended the next pair instead. A Telemetry lets the oldest pair
        holding its Result complete without it (``telemetry_missing``)."""
        type_code, reason = r.type_code, r.reason
        count_refusal(type_code, reason)
        pending = [outcomes[k] for k in sorted(want) if not outcomes[k].finished]
        if type_code == Result.TYPE and r.frame_seqs is not None:  # it said which pair it answered
            o = outcomes.get(r.frame_seqs)
            if o is not None and o.seqs in want and o.result is None:
                want.discard(o.seqs)
                give_up(o, "bad_result", f"the flight computer's Result was refused: {reason}")
            elif o is not None and o.sent_at:
                had = "it has its Result already" if o.result is not None else "its record stands"
                note(f"pair {o.pair_id}: a Result of it was refused; {had}")
        elif type_code == Result.TYPE and want:
            sent = [x for x in outcomes.values() if x.sent_at and x.sent_at <= r.t]
            answered_after = [x for x in sent if x.result is not None and x.result_order > r.order]
            o = next((x for x in pending if x.result is None and x.sent_at and x.sent_at <= r.t), None)
            if answered_after and (o is None or answered_after[0].sent_at <= o.sent_at):
                note(f"pair {answered_after[0].pair_id}: a Result of it was refused, and a good one came after it")
            elif o is not None:
                want.discard(o.seqs)
                give_up(o, "bad_result", f"the flight computer's Result was refused: {reason}")
        elif type_code == Telemetry.TYPE:
            o = next((x for x in pending if x.result is not None and x.telemetry is None), None)
            if o is not None:
                o.telemetry_missing = f"its Telemetry was refused: {reason}"
                want.discard(o.seqs)
                record(o)

    def take_refusals(want: set[tuple[int, int]]) -> None:
        """Act on what the link refused from the flight side since the last look. Called when nothing received
        is waiting; what the link's reader may still be handing over is taken first, so that a refusal is matched
        to a pair after the messages that came before it on the link."""
        for text in link.take_drop_notes():  # frames the session layer drops are no refusal: said once each
            note(f"the link dropped the flight side's {text}; more such are only counted (ground.json)")
        got = link.take_refusals()
        if not got:
            return
        end = time.monotonic() + REFUSAL_DRAIN_S
        while time.monotonic() < end:
            pkt = recv(0.05)
            if pkt is None:
                break
            handle(pkt, want)
        for r in got:
            refused(r, want)

    def ignore(name: str, why: str) -> None:
        """A message from the flight side that answers nothing: counted, and said for the first few of its kind."""
        if ignored.offer(name, time.monotonic())[0]:
            n = ignored.seen(name)
            more = f" ({n} so far)" if n > UNATTRIBUTED_SAID else ""
            note(f"ignored a {name} from the flight side{more}{why}")

    def handle(pkt, want: set[tuple[int, int]]) -> None:
        if pkt.epoch != state.epoch:
            return
        msg = pkt.message
        if isinstance(msg, (Heartbeat, Hello)):
            return
        key = tuple(getattr(msg, "frame_seqs", ()) or ())
        o = outcomes.get(key) if key else None
        if isinstance(msg, Error):
            o = by_lower_seq.get(msg.seq) if msg.seq is not None else None
            if o is None:
                o = next((x for x in outcomes.values() if msg.seq in x.seqs), None)
            if o is not None and (not o.sent_at or pkt.t_done < o.sent_at):
                o = None  # about a pair whose frames had not gone: no answer to them
            if o is None:
                # said for the first few, then once per UNATTRIBUTED_QUIET_S with the count: a flood of them printed
                # 1660 lines in 2.8 s
                if unattributed.offer("error", time.monotonic())[0]:
                    n = unattributed.seen("error")
                    more = f" ({n} so far)" if n > UNATTRIBUTED_SAID else ""
                    note(
                        f"unattributed error from flight side{more}: {printable(msg.code, 100)}: {printable(msg.text)}"
                    )
                return
            o.error = msg
        elif isinstance(msg, (Result, Telemetry)):
            if o is not None and o.last_frame_started is None and o.frame_ids:  # its frames still being confirmed
                t = link.times(o.frame_ids[-1])
                o.last_frame_started = t.first_tx if t is not None else None
            why = _not_an_answer(msg, o, pkt.t_done)
            if why is not None:  # counted in ground.json and said, as the HIL server does for its flight process
                ignore(type(msg).__name__, f" for frames {list(key)}: {why}")
                return
            assert o is not None
            if isinstance(msg, Result):
                o.result = msg
                o.result_t_first, o.result_t_done, o.result_bytes = pkt.t_first, pkt.t_done, pkt.nbytes
                o.result_order = pkt.order
                if isinstance(link, ZmqLink):  # a ZeroMQ message arrives whole: its line time is not seen here
                    o.result_t_first = None
            else:
                o.telemetry = msg
        else:  # a Config or a Frame: the ground's own messages, which the flight side has no cause to send
            ignore(type(msg).__name__, ": the ground sends those, it takes none")
            return
        if o is not None and o.finished and o.seqs in want:
            want.discard(o.seqs)
            record(o)

    def collect(until: float, want: set[tuple[int, int]], awaited: tuple[int, int] | None = None) -> None:
        """Record what comes for the pairs of ``want`` until ``until``, or until ``awaited``'s outcome is in."""
        while want and (awaited is None or awaited in want) and time.monotonic() < until:
            # what has arrived is read before the session is judged: an answer that came in before the session
            # was lost stands (after this side was stopped for 8 s, one was thrown away as link_down)
            pkt = recv(0.0)
            if pkt is not None:
                handle(pkt, want)
                continue
            if not session_ok():
                fail_in_flight(want, f"link session lost: {lost_why()}")
                return
            if held_stream(want):
                fail_in_flight(want, f"link session given up: {lost_why()}")
                return
            take_refusals(want)  # nothing received is waiting: refusals are matched to pairs now
            overdue_telemetry(want)
            if not want:
                return
            pkt = recv(0.2)
            stopped()  # before the answer is taken: its latency includes a stop
            if pkt is not None:
                handle(pkt, want)

    def stopped() -> None:
        """What :class:`protocol.stall.StallClock` saw since the last look: this process was not scheduled
        (SIGSTOP, a paused VM), while it waited, sent or drained. The pairs awaiting their Result meanwhile are
        marked, as their latency, measured here, includes the stop (an answer that came in time read as MISSED
        at 8 s without a word); a pair whose Result is in has its latency already."""
        gap = stall.take()
        if not gap:
            return
        hit = [o for o in outcomes.values() if o.sent_at and o.result is None and not o.finished]
        for o in hit:
            o.ground_stopped_s += gap
        for o in outcomes.values():  # the Telemetry grace is this process's running time, as the server's watchdog
            if o.result is not None and not o.finished:
                o.telemetry_wait_stopped_s += gap
        if hit:
            note(f"this process was not scheduled for {gap:.1f} s: the latency of {len(hit)} pair(s) in flight "
                 "includes it")  # fmt: skip

    def drain(want: set[tuple[int, int]]) -> None:
        """Take what has arrived, without waiting: with ``asap`` pacing the answers to the first pairs come in
        while the next pairs' frames are still on the line, and are recorded (and shown) then, not after the
        last pair is sent; so are the refusals among them."""
        stopped()
        while want:  # what has arrived counts even when the session has since been lost
            pkt = recv(0.0)
            if pkt is None:
                if session_ok():
                    take_refusals(want)
                break
            handle(pkt, want)
        overdue_telemetry(want)  # after what has arrived: a Telemetry in the queue is no missing one

    def save() -> None:
        # whole, a signal held meanwhile: one that came between an append and its count was followed by a second
        # save that appended the same records again (review of stop 64); the interrupted path holds them already
        held = signal.pthread_sigmask(signal.SIG_BLOCK, HELD_SIGNALS)
        try:
            write_records()
        finally:
            signal.pthread_sigmask(signal.SIG_SETMASK, held)

    def write_records() -> None:
        new = records[state.saved :]  # appended, not rewritten: a long descent wrote O(n^2) bytes (soak QA)
        append_records(results_path, new)
        state.saved = len(records)
        if telemetry_path is not None:
            lines = records[state.telemetry_saved :]
            append_records(telemetry_path, ({k: r[k] for k in TELEMETRY_KEYS if k in r} for r in lines))
            state.telemetry_saved = len(records)
        stats = getattr(link, "stats", None) or {}
        # the link counts every refusal; the ground is handed the latest REFUSALS_KEPT between two looks
        refused = max(state.refused_messages, link.refused_count())
        counters = {"refused_messages": refused, "last_refused": state.last_refused, "flight_hello": state.flight_hello}
        counters |= {
            "ignored_results": ignored.seen("Result"),
            "ignored_telemetry": ignored.seen("Telemetry"),
            "ignored_other": ignored.seen("Config") + ignored.seen("Frame"),
            "unattributed_errors": unattributed.seen("error"),
        }
        # what the line did meanwhile: noise the framing dropped and the retransmissions that mended it
        counters["line"] = {k: int(stats.get(k, 0) or 0) for k in LINE_COUNTERS if k in stats}
        if isinstance(link, ZmqLink):  # TCP repeats nothing: a frame dropped here is one the flight side meant
            counters["session_drops"] = {k: int(stats.get(k, 0) or 0) for k in SESSION_DROPS}
        if hasattr(link, "baud"):  # a serial line's pace, as the Config told the flight side (0: unpaced)
            counters["line_baud"] = int(link.baud or 0)
        # sessions the link had with the flight side: a lost or restarted one was said on the console and in no
        # output (a board killed and restarted mid-descent, its fused map started afresh: "PASS", stop 60's QA)
        counters["link_sessions"] = {
            k: int(stats.get(k, 0) or 0) for k in ("sessions", "peer_restarts", "peer_losses", "foreign_hellos")
        }
        write_atomic(counters_path, json.dumps(counters, sort_keys=True) + "\n")

    def record(o: PairOutcome, show: bool = True) -> None:
        rec = write_outcome(out_dir, o, deadline_s)
        records.append(rec)
        save()
        if o.result is not None:  # recorded and saved: a long descent held every pair's grids (stop 63's soak QA)
            o.result = without_arrays(o.result)
        if progress and show:
            progress(rec)

    def give_up(o: PairOutcome, code: str, text: str, show: bool = True) -> None:
        o.error = Error(code=code, seq=o.seqs[1], text=text[:4000])
        record(o, show)

    def send_frames(o: PairOutcome, frames: list[Frame]) -> bool:
        o.sent_at = time.monotonic()
        o.drops_at_send = session_drops()
        o.ignored_at_send = ignored.seen("Result")
        try:
            ids = [link.send(f, timeout=timeout, epoch=state.epoch) for f in frames]
        except LinkClosed as exc:  # the transport failed as the pair went: its pair is lost to the link
            give_up(o, "link_down", lost_why() if link.failed else str(exc))
            return False
        o.frame_ids = tuple(ids)
        # the frames' own line time (a 512x512 pair is ~46 s at 115200 baud) on top of the response timeout;
        # a stalled link ends sooner anyway (its peer timeout fails them)
        baud = getattr(link, "baud", None)
        line_s = 2.0 * sum(f.image.nbytes for f in frames) * 10 / baud if baud else 0.0
        deadline = time.monotonic() + timeout + line_s
        next_note = o.sent_at + UPLINK_NOTE_S
        while time.monotonic() < deadline:  # both frames on the far side: their line time is the link time
            outs = [link.outcome(i) or "" for i in ids]
            if all(x != "pending" for x in outs):
                break
            if baud and progress is not None and time.monotonic() >= next_note:  # a slow line, not a hung ground
                note(f"pair {o.pair_id}: its frames on the line for {time.monotonic() - o.sent_at:.0f} s of about "
                     f"{line_s / 2 * LINE_OVERHEAD:.0f} s at {baud} baud")  # fmt: skip
                next_note += UPLINK_NOTE_S
            link.flush(timeout=0.2)
            # the earlier pairs' answers, as they come (lockstep: those the ground stopped waiting for)
            drain(late if pace == "lockstep" else in_flight)
        failed = [f for f in link.failures() if f.seq in ids]
        outs = [link.outcome(i) or "" for i in ids]
        if failed or any(x == "pending" for x in outs):
            # both frames usually fail for one reason: said once
            whys = dict.fromkeys(f"{f.message_type} not delivered: {f.reason}" for f in failed)
            why = "; ".join(whys) or "frames still queued"
            give_up(o, "link_down", why)
            return False
        # the peer's ACK can be read before the writer recorded the frame's last write: "written" would be the
        # moment it was handed over, a frame's line time early (1 s at 9600 baud; stop 60's review)
        t_up, t_low = link.times(ids[0]), link.times(ids[1], settle_s=WRITE_RECORD_WAIT_S)
        o.frames_written_at = t_low.written if t_low is not None else None
        # not its "written" time: a paced writer records it after the line time, and a fast answer can beat that
        o.last_frame_started = (t_low.first_tx if t_low is not None else None) or o.sent_at
        # ZeroMQ: "written" is libzmq taking the frame, "delivered" its release of the bytes to the kernel (the
        # earliest it can have been, protocol.links). Through a 500 kB/s path the release came seconds later and
        # the uplink counted against the deadline
        released = t_low.delivered if isinstance(link, ZmqLink) and t_low is not None else None
        if released is not None and t_low is not None and t_low.written and released > t_low.written:
            o.frames_written_at = released
        if t_up is not None and t_low is not None and t_up.first_tx is not None and t_low.delivered is not None:
            o.frames_line_s = t_low.delivered - t_up.first_tx
        if not isinstance(link, ZmqLink) and t_low is not None and t_low.last_tx and t_low.written:
            o.frames_retx_s = max(0.0, t_low.last_tx - t_low.written)
        o.link_s = time.monotonic() - o.sent_at
        return True

    def new_outcome(i: int, entry: dict) -> PairOutcome:
        """The outcome of the manifest's i-th pair (frame seqs 2i, 2i + 1), registered."""
        pair_id = descent_pair_id(i, entry)
        seq = 2 * i
        o = PairOutcome(
            pair_id,
            str(entry.get("label", i)),
            float(entry.get("altitude_m", float("nan"))),
            str(base / entry["path"]),
            (seq, seq + 1),
            turn_at=time.monotonic(),
        )
        outcomes[o.seqs] = o
        by_lower_seq[seq + 1] = o
        return o

    in_flight: set[tuple[int, int]] = set()  # asap pacing: pairs sent and not yet answered
    late: set[tuple[int, int]] = set()  # lockstep pacing: pairs the ground stopped waiting for, not yet answered
    stall = StallClock()
    try:
        for i, entry in enumerate(entries):
            o = new_outcome(i, entry)
            pair_dir, pair_id = Path(o.pair_dir), o.pair_id
            try:  # a bad pair (NaN pose, wrong size, unreadable file) is reported, the descent goes on
                pair = read_pair(pair_dir, load_truth=False)
                frames = [_frame_from_pair(pair, k, o.seqs[k], pair_id) for k in (0, 1)]
                for f in frames:
                    f.validated()
                if config is not None and not same_camera(pair.camera.to_dict(), config.camera):
                    raise InputError(camera_mismatch(pair.camera.to_dict(), config.camera))
            except InputError as exc:
                give_up(o, "bad_input", str(exc))
                continue
            o.frames_in_dir = len(pair.images)
            if not math.isfinite(o.altitude_m):  # a hand-made manifest without altitude_m: the lower frame's height
                o.altitude_m = float(pair.poses[-1].position[2])  # (the table said "—"; QA 74)
            if len(pair.images) > 2 and not state.said_middle_frames:
                state.said_middle_frames = True
                note(
                    f"{o.label}: {len(pair.images)} frames; the HIL streams a pair: frames 0 and "
                    f"{len(pair.images) - 1} (DESIGN.md), not the {len(pair.images) - 2} between (`process` uses "
                    "every frame)"
                )
            if config is None:
                config = Config(
                    camera=pair.camera.to_dict(),
                    budget=budget,
                    deadline_s=float(deadline_s),
                    preset=preset,
                    options=options,
                )
            if link.failed:  # the transport is gone for good (EOF, device unplugged): nothing more can go
                give_up(o, "link_down", f"link failed: {link.failed}")
                continue
            try:
                ensure_session()
            except NoHello as exc:  # nothing can run: every pair left is recorded as not run, the descent ends
                give_up(o, "not_run", f"not run: {exc}", show=False)  # one error line for all (the caller's)
                for k in range(i + 1, len(entries)):
                    give_up(new_outcome(k, entries[k]), "not_run", f"not run: {exc}", show=False)
                raise
            except LinkDown as exc:
                if progress is None:  # else the pair's own line says it: two lines per pair with one reason
                    note(f"LINK ERROR: {exc}")
                give_up(o, "link_down", str(exc))
                continue
            try:
                send_config()
            except LinkClosed as exc:
                give_up(o, "link_down", lost_why() if link.failed else str(exc))
                continue
            if not send_frames(o, frames):
                if progress is None:
                    note(f"LINK ERROR: pair {pair_id}: {o.error.text if o.error else ''}")
                continue
            if pace == "lockstep" and o.finished:  # answered while its frames were on the line (an Error about
                record(o)  # the first, taken with the late pairs' answers): recorded now, not after the timeout
            elif pace == "lockstep":
                want = {o.seqs} | late  # a late answer to an earlier pair is recorded when it comes
                collect(time.monotonic() + timeout + o.link_s, want, awaited=o.seqs)
                late.intersection_update(want)
                if o.seqs in want and i + 1 < len(entries):
                    late.add(o.seqs)
                    what = "its Result came, its Telemetry not" if o.result is not None else "no answer"
                    note(
                        f"pair {pair_id}: {what} within {timeout:.0f} s; the next pair goes now, and this one's "
                        "answer is still recorded if it comes before the descent ends"  # no later (QA 64a, M4)
                    )
            else:
                in_flight.add(o.seqs)
                if o.finished:  # answered while its own frames were on the line (an Error about the first)
                    in_flight.discard(o.seqs)
                    record(o)
                drain(in_flight)
        pending = {
            s for s, o in outcomes.items() if not o.finished and not any(r["frame_seqs"] == list(s) for r in records)
        }
        if pending:
            if pace == "lockstep":  # each waited its own response timeout already: no second one for each
                until = max(outcomes[k].sent_at + outcomes[k].link_s + timeout for k in pending)
            else:  # asap: answered one after another, the last behind all the others
                until = time.monotonic() + timeout * max(1, len(pending))
            if progress is not None and until - time.monotonic() >= UPLINK_NOTE_S:
                note(f"waiting up to {until - time.monotonic():.0f} s for the answers to {len(pending)} pair(s)")
            drain(pending)  # what has arrived already: in lockstep `until` is often past, and collect reads nothing
            collect(until, pending)
            # a Result in and its Telemetry on its way: awaited for its own line time, as mid-descent (the last pair
            # at 300 baud lost its Telemetry to the response timeout's end; stop 60's review)
            grace = telemetry_grace_s(getattr(link, "baud", None), telemetry_grace_base_s)
            owed = [outcomes[k].result_t_done for k in pending if outcomes[k].result is not None]
            later = max((t + grace for t in owed if t is not None), default=0.0)
            if pending and later > time.monotonic():
                collect(later, pending)
        for r in link.take_refusals():  # after every pair's end: counted, no pair to blame
            refused(r, set())
        for s, o in outcomes.items():
            if not any(r["frame_seqs"] == list(s) for r in records):
                if o.finished:  # answered, but not while a collect wanted it: the answer stands
                    pass
                elif o.result is not None:  # its Result came, its Telemetry never did: the Result stands
                    o.telemetry_missing = "no Telemetry came" + (
                        f" (link session lost: {lost_why()})" if not session_ok() and state.sessions else ""
                    )
                elif not session_ok() and state.sessions:
                    o.error = Error(code="link_down", text=f"link session lost: {lost_why()}", seq=s[1])
                elif not state.sessions:
                    o.error = Error(code="link_down", text="no session with the HIL server", seq=s[1])
                else:
                    waited = time.monotonic() - o.sent_at
                    text = f"no result or error {waited:.0f} s after its frames went (response timeout {timeout:.0f} s)"
                    dropped = session_drops() - o.drops_at_send
                    if dropped:  # answers the session rules threw away read as none at all
                        text += (
                            f"; meanwhile the link dropped {dropped} of the flight side's messages by the session "
                            "rules (said above)"
                        )
                    if o.telemetry is not None:  # kept with nothing to say it came (QA 64a)
                        text += "; its Telemetry came, its Result did not"
                    stray = ignored.seen("Result") - o.ignored_at_send
                    if stray:  # an answer under other frame numbers read as none at all (QA 64a)
                        text += (
                            f"; meanwhile {stray} Result(s) came for frames no open pair has, and were ignored "
                            "(said above: wrong frame_seqs?)"
                        )
                    o.error = Error(code="no_response", text=text, seq=s[1])
                rec = write_outcome(out_dir, o, deadline_s)
                records.append(rec)
                if progress is not None:  # each said, as the pairs before them were
                    progress(rec)
        save()
    except Interrupted as exc:
        # a pair whose frames went is not "not run": recorded with what came, or as interrupted while in flight;
        # written whole, a second signal waiting meanwhile (it would leave half the records, temporary files)
        signal.pthread_sigmask(signal.SIG_BLOCK, HELD_SIGNALS)
        for s, o in outcomes.items():
            if o.sent_at and not any(r["frame_seqs"] == list(s) for r in records):
                if not o.finished and o.result is not None:  # the answer came, its Telemetry not yet
                    o.telemetry_missing = f"{exc} before its Telemetry came"
                elif not o.finished:
                    # link_s is set once both frames are on the far side (send_frames' end): before that, mid-uplink
                    when = "after its frames went" if o.link_s > 0 else "while its frames went"
                    o.error = Error(code="interrupted", text=f"{exc} {when}; its answer was not awaited", seq=s[1])
                records.append(write_outcome(out_dir, o, deadline_s))
        save()
        signal.pthread_sigmask(signal.SIG_UNBLOCK, HELD_SIGNALS)
        raise
    finally:
        stall.close()
    return records


def telemetry_overdue(o: PairOutcome, now: float, grace_s: float = TELEMETRY_GRACE_S) -> bool:
    """Whether ``o``'s Result came over ``grace_s`` of this process's running time ago and its Telemetry has not:
    the ground's own stops meanwhile (``telemetry_wait_stopped_s``) are left out, as the HIL server's watchdog
    leaves out its own (a Telemetry that came during an 11 s stop of the ground was taken for missing)."""
    if o.result is None or o.finished or o.result_t_done is None:
        return False
    return now - o.result_t_done - o.telemetry_wait_stopped_s > grace_s


def _say(*parts: object) -> None:
    """A console line in one write: print's two (the text, then its newline) let the link's event thread put its
    own line between them, and two lines ran together on the console and in ground.log (stop 57's board QA)."""
    sys.stderr.write(" ".join(str(x) for x in parts) + "\n")
    sys.stderr.flush()


def _not_an_answer(msg: Result | Telemetry, o: PairOutcome | None, t_done: float) -> str | None:
    """Why a Result or Telemetry is no answer to a pair sent (None: it is ``o``'s): for frames no pair has, or
    a pair whose frames had not gone when it came (a board that guessed the next seqs read as answering with a
    negative latency, "met"), or a second one for its pair (the first stands, as under the HIL server)."""
    if o is None:
        return "no pair was sent with them"
    # an answer needs both frames: whole before the last one started on the line (a slow line), it answers no sending
    if not o.sent_at or o.last_frame_started is None or t_done < o.last_frame_started:
        return f"it came before pair {o.pair_id}'s frames were sent"
    if (o.result if isinstance(msg, Result) else o.telemetry) is not None:
        return f"pair {o.pair_id} has one already; the first stands"
    if o.error is not None:  # a refused Result or an Error ended it: recorded
        return f"pair {o.pair_id} was recorded already ({o.error.code}); this came after"
    if isinstance(msg, Telemetry) and o.telemetry_missing is not None:  # too late: its pair is recorded
        return f"pair {o.pair_id} was recorded without it ({o.telemetry_missing})"
    return None


def auto_grid_steps(link_spec: str) -> tuple[int, int]:
    """(P(safe) step, elevation step) that keep the Result small for the line (docs/benchmarks/protocol.md).

    Encoded Result on the demo pairs (256 x 256 grid, flight v2 with the P(safe) model refitted on
    the thesis scene): 106-110 kB at (1, 1), 65-70 kB at (1, 2) - of which 44-46 kB is the continuous
    P(safe) grid at full resolution - 34-37 kB at (2, 2), 22-24 kB at (2, 4), 8-10 kB at (4, 8).
    ZeroMQ or unpaced (1, 1); from 460800 baud (2, 2), ~0.4 s at 921600; from 230400 (2, 4); below
    (4, 8), ~0.9 s at 115200 baud. (P(safe) decimation is a block minimum: conservative.)
    """
    from protocol.linkspec import parse_serial

    kind, _, rest = link_spec.partition(":")
    if kind != "serial":
        return 1, 1
    _, baud = parse_serial(rest)
    if baud is None:
        return 1, 1
    if baud >= 460800:
        return 2, 2
    return (2, 4) if baud >= 230400 else (4, 8)


def auto_elevation_unit_cm(link_spec: str) -> int:
    """The elevation grid's unit for the line: 10 cm on a serial link, 1 cm otherwise.

    A 10 cm unit rounds by at most 5 cm (RMS 2.9 cm), against a DEM whose own mean error is 0.17-0.85 m
    (docs/RESULTS.md, Table 6.2), and it shrinks the compressed elevation grid by 31-55 % on the held-out
    descents' fused maps (docs/benchmarks/protocol.md, "Elevation unit and the planar predictor").
    """
    return 10 if link_spec.partition(":")[0] == "serial" else 1


def _refused_count(path: Path) -> int:
    try:
        return int(json.loads(path.read_text()).get("refused_messages") or 0)
    except (OSError, ValueError, AttributeError):
        return 0


HELD_SIGNALS = (signal.SIGINT, signal.SIGTERM)


def _interrupt(signum: int, frame: object) -> None:
    raise Interrupted(signum)


def _interruption(exc: BaseException) -> Interrupted | None:
    """The :class:`Interrupted` that ``exc`` was raised while handling (its ``__context__`` chain), or None."""
    seen: BaseException | None = exc
    while seen is not None:
        if isinstance(seen, Interrupted):
            return seen
        seen = seen.__context__
    return None


def main(argv: list[str] | None = None, *, restore_handlers: bool = True) -> int:
    """The ground streamer's process entry. SIGINT and SIGTERM end it with what finished recorded.

    ``hazard-hil run`` starts it with both signals blocked: one sent while the interpreter imports (before any
    handler exists; a Ctrl-C there was a KeyboardInterrupt traceback in ground.log) waits, pending, until the
    handler below is in place, and then stops the ground as cleanly as one sent later. ``restore_handlers``:
    put the caller's handlers back at the end (in-process callers); the process entry leaves the ones its end
    set (ignored: a late Ctrl-C must not be a traceback while the interpreter exits)."""
    before = {sig: signal.signal(sig, _interrupt) for sig in HELD_SIGNALS}
    try:
        signal.pthread_sigmask(signal.SIG_UNBLOCK, HELD_SIGNALS)  # a held one is raised here, as Interrupted
        return _main(argv)
    except Interrupted as exc:  # before the descent began: the descent's own stop says what finished
        _say(f"ground: {exc} before the descent began")
        return 128 + exc.signum
    except OSError as exc:  # a full disk under --out: one line naming the file, not a traceback (QA of stop 72)
        _say(f"ground: error: {os_error_text(exc)}")
        return 1
    except Exception as exc:
        # the handler raised inside threading's Thread.start (a signal while the stall clock started), which then
        # failed on its own registry with a KeyError: a traceback, the signal only its context (CI of stop 82)
        if (signalled := _interruption(exc)) is None:
            raise
        _say(f"ground: {signalled} before the descent began")
        return 128 + signalled.signum
    finally:
        for sig, handler in before.items() if restore_handlers else ():
            signal.signal(sig, handler)


def _main(argv: list[str] | None) -> int:
    ap = argparse.ArgumentParser(prog="python -m ground_sim.stream", description=__doc__.splitlines()[0])
    ap.add_argument("--link", required=True, help="serial:URL[@BAUD] or zmq:ENDPOINT (connect)")
    ap.add_argument("--manifest", type=Path, required=True)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--budget", required=True)
    ap.add_argument("--deadline", type=float, required=True)
    ap.add_argument("--preset", default="fast")
    ap.add_argument("--pace", choices=("lockstep", "asap"), default="lockstep")
    ap.add_argument("--keys", type=Path, default=None, help="CURVE key directory (zmq links)")
    ap.add_argument("--insecure", action="store_true", help="zmq without CURVE (loopback debugging only)")
    ap.add_argument("--link-timeout", type=float, default=4.0, help="peer silent/stalled this long = link lost (s)")
    ap.add_argument(
        "--reconnect-timeout",
        type=float,
        default=10.0,
        help="after a lost session, wait this long for a new one (s; from the loss, not per pair)",
    )
    ap.add_argument(
        "--hello-timeout",
        type=float,
        default=900.0,
        help="wait this long for the flight side's first Hello, link session included (s; default 900: a slow "
        "emulated processor boots slowly); then every pair is recorded as not run and the exit code is 5",
    )
    ap.add_argument("--full-maps", action="store_true", help="ask for full-resolution image maps in each Result")
    ap.add_argument(
        "--fusion",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="ask for the map fused over the descent (default) or, with --no-fusion, each pair's alone",
    )
    ap.add_argument("--elevation-step", default="auto", help="elevation grid decimation k >= 1, or auto")
    ap.add_argument("--psafe-step", default="auto", help="P(safe) grid decimation k >= 1, or auto")
    ap.add_argument(
        "--elevation-unit-cm", default="auto", help="elevation grid unit in cm, 1-1000, or auto (10 on serial, else 1)"
    )
    ap.add_argument("--memory-mib", type=float, default=1024.0, help="this process's memory headroom (MiB)")
    ap.add_argument("--telemetry", type=Path, default=None, help="per-pair timing lines (JSON) written here")
    # tests: the base of the wait for a Result's Telemetry (s), which a board that sends none waits out per pair
    ap.add_argument("--telemetry-grace", type=float, default=TELEMETRY_GRACE_S, help=argparse.SUPPRESS)
    # tests: how often a line says the first Hello is still awaited (s)
    ap.add_argument("--hello-note", type=float, default=HELLO_NOTE_S, help=argparse.SUPPRESS)
    # started by `hazard-hil run`: a SIGTERM is then the run's, which says its reason on the line before
    ap.add_argument("--under-run", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    from protocol.ceiling import apply_memory_ceiling
    from protocol.linkspec import check_positive_seconds, check_reconnect_timeout, open_link

    try:
        auto_p, auto_e = auto_grid_steps(args.link)
        step = auto_e if args.elevation_step == "auto" else int(args.elevation_step)
        pstep = auto_p if args.psafe_step == "auto" else int(args.psafe_step)
        if not (1 <= step <= 1024 and 1 <= pstep <= 1024):
            raise InputError("--elevation-step and --psafe-step must be in [1, 1024] or auto")
        unit = auto_elevation_unit_cm(args.link) if args.elevation_unit_cm == "auto" else int(args.elevation_unit_cm)
        if not 1 <= unit <= 1000:
            raise InputError(f"--elevation-unit-cm must be in [1, 1000] or auto, got {unit}")
        check_positive_seconds("--hello-timeout", args.hello_timeout)
        check_positive_seconds("--telemetry-grace", args.telemetry_grace)
        check_positive_seconds("--hello-note", args.hello_note)
        check_reconnect_timeout(args.reconnect_timeout)
        read_manifest(args.manifest)  # before the link: a malformed manifest is one line, exit 2
        link = open_link(
            args.link,
            server=False,
            keys=args.keys,
            insecure=args.insecure,
            peer_timeout=args.link_timeout,
            connect_timeout=args.reconnect_timeout,
            # the far end: the HIL server in front of the emulated processor, or a flight computer of one's own
            name="flight-computer" if args.budget == "external" else "hil-server",
            log=lambda s: _say(f"ground: {s}"),
        )
    except (InputError, ValueError) as exc:
        _say(f"ground: error: {exc}")
        return 2
    apply_memory_ceiling(args.memory_mib)

    def show(rec: dict) -> None:
        if rec["status"] == "result":
            flag = "met" if rec["deadline_met"] else "MISSED"
            e2e = rec.get("e2e_latency_s")
            line = rec.get("result_line_s")
            queued = rec.get("result_queue_s")
            flight = rec.get("flight_latency_s")
            why = plan_note(rec)
            stopped = rec.get("ground_stopped_s")
            missing = rec.get("telemetry_missing") or (
                "not reported: its Telemetry has no total_latency_s" if "flight_deadline_met" in rec else "no Telemetry"
            )
            if stopped:
                why = f"this process was stopped {stopped:.1f} s meanwhile, which the latency includes" + (
                    f"; {why}" if why else ""
                )
            _say(
                f"ground: {rec['label']:>10}  {rec['level']:<10} end to end "
                + (f"{e2e:6.{_places(e2e, rec['deadline_s'])}f} s" if e2e is not None else "     ? s")
                + f"  deadline {rec['deadline_s']:g} s {flag}  (flight "
                + (f"{flight:.2f} s" if flight is not None else f"? s: {missing}")
                + (f", result queued {queued:.2f} s" if queued is not None and queued >= QUEUE_SHOWN_S else "")
                + (
                    f", the last frame's retransmissions {retx:.2f} s"
                    if (retx := rec.get("frames_retx_s") or 0.0) >= QUEUE_SHOWN_S
                    else ""
                )
                + (
                    f", result line {line:.2f} s)"
                    if line is not None
                    else f", link and queues {outside:.2f} s: no line time measured)"
                    if (outside := rec.get("outside_flight_s")) is not None
                    else ")"
                )
                + (f"; {why}" if why else "")
            )
            for note in rec.get("flight_notes", ()):  # the flight side's own warnings on the pair
                _say(f"ground: {'':>10}  flight says: {note}")
        else:
            _say(f"ground: {rec['label']:>10}  ERROR {rec['code']}: {rec['text']}")

    try:
        records = stream_descent(
            link,
            args.manifest,
            args.out,
            budget=args.budget,
            deadline_s=args.deadline,
            preset=args.preset,
            pace=args.pace,
            reconnect_timeout_s=args.reconnect_timeout,
            hello_timeout_s=args.hello_timeout,
            where=args.link,
            full_maps=args.full_maps,
            fusion=args.fusion,
            elevation_step=step,
            psafe_step=pstep,
            elevation_unit_cm=unit,
            progress=show,
            telemetry_path=args.telemetry,
            telemetry_grace_base_s=args.telemetry_grace,
            hello_note_s=args.hello_note,
        )
    except Interrupted as exc:
        # under `run` a SIGTERM is the run stopping its ground (a failed HIL server, a user's SIGTERM): "interrupted
        # by SIGTERM" read as a signal from outside, which nobody sent (QA of stop 85)
        why = (
            "stopped by `hazard-hil run` (SIGTERM; its reason is on the line above)"
            if args.under_run and exc.signum == signal.SIGTERM
            else str(exc)
        )
        _say(f"ground: {why}; the pairs that finished are in {args.out / 'results.jsonl'}")
        return 128 + exc.signum
    except NoHello as exc:  # every pair is recorded as not run (results.jsonl)
        _say(f"ground: error: {exc}")
        return EXIT_NO_HELLO
    finally:
        for sig in HELD_SIGNALS:
            signal.signal(sig, signal.SIG_IGN)  # already ending: let the link close
        link.close()
    failed = sum(r["status"] != "result" for r in records)
    lost = sum(r.get("code") in LINK_CODES for r in records)
    refused = _refused_count(args.out / "ground.json")
    _say(
        f"ground: {_count(len(records), 'pair')}, {_count(len(records) - failed, 'result')}, "
        f"{_count(failed, 'error')}"
        + (f", {_count(refused, 'message')} from the flight side refused" if refused else "")
    )
    if lost:
        # the reason that cost the first lost pair, not the link's latest event (a new session's "X -> Y")
        first = next(str(r.get("text") or "") for r in records if r.get("code") in LINK_CODES)
        _say(f"ground: LINK ERROR: {_count(lost, 'pair')} lost to link failures (first: {first})")
        return EXIT_LINK_LOST
    return 0


def _count(n: int, noun: str) -> str:
    """'1 pair', '3 pairs'."""
    return f"{n} {noun}{'' if n == 1 else 's'}"


if __name__ == "__main__":
    sys.exit(main(restore_handlers=False))
