"""Our flight software on a board of one's own (``hazard-hil flight``, flight_sw/board.py): it serves
``hazard-hil run --flight external`` over a serial line or ZeroMQ, one ground session after another."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from hilkit import run_hil, small_descent

from flight_sw.board import GroundSession
from hil_server.cli import main as cli
from hil_server.run import exit_code
from protocol.arq import Refusal
from protocol.messages import Config, Error, Frame, Heartbeat, Hello, Result, Telemetry

ROOT = Path(__file__).resolve().parents[1]
PAIRS = ["600/300", "300/150"]
BOARD = [sys.executable, "-m", "hil_server.cli", "flight", "--no-warm-up"]


@pytest.fixture(scope="module")
def manifest(tmp_path_factory):
    return small_descent(tmp_path_factory.mktemp("pairs"), PAIRS)


def _stop(board: subprocess.Popen, sig: int = signal.SIGTERM) -> tuple[int, str]:
    board.send_signal(sig)
    try:
        _, err = board.communicate(timeout=20)
    except subprocess.TimeoutExpired:
        board.kill()
        _, err = board.communicate()
    return board.returncode, err


def _scores(s: dict) -> list[tuple]:
    keys = ("fp_pct", "cdi_pct", "dem_mean_abs", "dem_coverage_pct")
    return [(r["label"], r["level"], *(r["scores"][k] for k in keys)) for r in s["records"]]


def test_our_flight_software_on_a_serial_board_serves_one_ground_after_another(manifest, tmp_path):
    from protocol.faults import PtyBridge

    with PtyBridge() as bridge:
        board = subprocess.Popen(
            [*BOARD, "--link", f"serial:{bridge.paths[0]}@0"], cwd=ROOT, stderr=subprocess.PIPE, text=True
        )
        try:
            runs = [
                run_hil(manifest, tmp_path / f"run{k}", flight="external", link=f"serial:{bridge.paths[1]}@0")
                for k in range(2)
            ]
        finally:
            rc, err = _stop(board)
    for s in runs:
        assert exit_code(s) == 0 and s["complete"] and s["budget"] is None
        recs = s["records"]
        assert [r["status"] for r in recs] == ["result", "result"]
        # the real pipeline answered, not an empty Result: full level, an elevation, FP within the limit
        assert all(r["level"] == "full" for r in recs)
        assert all(r["scores"]["dem_coverage_pct"] > 50 and r["scores"]["fp_pct"] <= 1.0 for r in recs)
    # the second ground started afresh: nothing of the first descent's fused map carried over
    assert _scores(runs[0]) == _scores(runs[1])
    assert rc == 128 + signal.SIGTERM
    assert err.count("flight: ground session ") == 2 and "pairs half received are dropped" in err
    assert (
        err.count("flight: pair ") == 4
        and "served 2 ground session(s), 4 pair(s); 0 message(s) refused, 0 dropped" in err
    )


def test_a_board_on_a_noisy_line_answers_what_the_emulated_processor_answers(manifest, tmp_path):
    from protocol.faults import CorruptingChannel, PtyBridge

    down = CorruptingChannel(seed=21, drop=1e-4, flip=1e-4, dup=1e-4)
    up = CorruptingChannel(seed=22, drop=1e-4, flip=1e-4, dup=1e-4)
    with PtyBridge(up, down) as bridge:
        board = subprocess.Popen(
            [*BOARD, "--link", f"serial:{bridge.paths[0]}@921600"], cwd=ROOT, stderr=subprocess.PIPE, text=True
        )
        try:
            link = f"serial:{bridge.paths[1]}@921600"
            s = run_hil(manifest, tmp_path / "board", flight="external", link=link, figures=True)  # the captions
        finally:
            rc, err = _stop(board)
    assert sum(ch.stats[k] for ch in (up, down) for k in ("dropped", "flipped", "duplicated")) > 10, "must corrupt"
    assert exit_code(s) == 0 and s["complete"], err
    # the noise the ground's link dropped is counted and said (it was in no output file); which bytes the noise
    # hits depends on the timing, so the note is held to the counters, whatever they are this time
    from ground_sim.stream import LINE_COUNTERS
    from hil_server.run import flight_note

    line = s["ground_counters"]["line"]
    assert set(line) == set(LINE_COUNTERS), line
    bad = line["crc_errors"] + line["malformed"]
    assert (f"the ground's line dropped {bad} damaged frame" in flight_note(s)) == (bad > 0), (line, flight_note(s))
    # and the board's side of the line, which its Telemetry says (QA of stop 72: it reached no summary)
    fb = max(float(r["link"].get("flight_rx_damaged", 0)) for r in s["records"])
    assert (f"the flight side's line dropped {fb:.0f} damaged frame" in flight_note(s)) == (fb > 0), flight_note(s)
    assert fb == 0 or "; the line dropped " in err.strip().splitlines()[-1], err[-400:]  # the board's last line
    # the same frames through the HIL server to the emulated processor at the same rate (so the ground asks for the
    # same grid steps and elevation unit): the same Results, byte for byte in effect
    emulated = run_hil(manifest, tmp_path / "emulated", "serial", baud=921600, figures=True)
    assert _scores(s) == _scores(emulated)
    assert rc == 128 + signal.SIGTERM
    # the board reports its Result's own line time (first byte out -> acknowledged), as the HIL server does: the
    # ground's own span from the first to the last frame misses the first frame (a one-frame Result read 0.00 s)
    for runs in (s, emulated):
        for r in runs["records"]:
            assert r["result_line_s"] > r["result_rx_s"] and r["result_line_s"] >= 0.8 * r["result_bytes"] * 10 / 921600
    # the board says the rate its port is set to, and the ground compares it with its own (the same here)
    from hil_server.run import baud_note

    assert all(r["link"]["port_baud"] == 921600 for r in s["records"]) and baud_note(s) == ""
    # both pace their Results at the line's rate: no downlink missing from the latencies
    from hil_server.run import unpaced_note

    assert unpaced_note(s) == "" and unpaced_note(emulated) == ""
    # the report's resources: no throttle and no ceiling on a board (QA of stop 71: a caption about "the duty cycle
    # the throttle applied" and "the budget's memory ceiling"), and the board's own memory, which it reports since
    # stop 72 (the chart was empty): our flight process holds numpy, OpenCV and the maps, tens of MiB at least
    import html

    page = html.unescape((tmp_path / "board" / "report.html").read_text())
    assert "The CPU fraction the flight side reported (no throttle: it runs at its own speed), and its peak " \
           "private RSS as it reported it." in page, page[page.find("resources.png") - 400 :][:900]  # fmt: skip
    assert all(20 < r["peak_rss_mib"] < 2000 for r in s["records"]), [r["peak_rss_mib"] for r in s["records"]]
    assert "the throttle applied" in html.unescape((tmp_path / "emulated" / "report.html").read_text())


class Blackout:
    """Both directions of a line (one instance each, sharing the clock) go silent for ``seconds`` once the
    ground -> board direction carries ``trigger`` (e.g. the second pair's id, in its first Frame): a session lost
    at a known point of the descent."""

    def __init__(self, until: list[float], trigger: bytes | None = None, seconds: float = 6.0) -> None:
        self.until, self.trigger, self.seconds, self.tail = until, trigger, seconds, b""  # until: both directions'

    def apply(self, data: bytes) -> bytes:
        now = time.monotonic()
        if self.trigger is not None and self.trigger in self.tail + data:
            self.until[0], self.trigger = now + self.seconds, None
        self.tail = data[-64:]
        return b"" if now < self.until[0] else data


def test_a_descent_reconnected_mid_way_keeps_its_fused_map_on_the_board(tmp_path):
    """The line goes silent for 6 s from the second pair's first Frame: both ends lose the session (4 s),
    that pair ends as link_down, and the ground reconnects and goes on. Its Config in the new session carries the
    same descent_id, so the board's fused map goes on (it restarted at every new session: a noisy line cost the
    descent its history). The next run, with its own descent_id, starts afresh."""
    from protocol.faults import PtyBridge

    manifest = small_descent(tmp_path / "pairs", ["600/300", "300/150", "200/100"])
    until = [0.0]
    with PtyBridge(Blackout(until), Blackout(until, trigger=b"p001-")) as bridge:  # type: ignore[arg-type]
        board = subprocess.Popen(
            [*BOARD, "--link", f"serial:{bridge.paths[0]}@0"], cwd=ROOT, stderr=subprocess.PIPE, text=True
        )
        try:
            s = run_hil(manifest, tmp_path / "run", flight="external", link=f"serial:{bridge.paths[1]}@0")
            again = run_hil(manifest, tmp_path / "again", flight="external", link=f"serial:{bridge.paths[1]}@0")
        finally:
            rc, err = _stop(board)
    assert [r["status"] for r in s["records"]] == ["result", "error", "result"], s["records"]
    assert s["records"][1]["code"] == "link_down"
    assert err.count("flight: ground session ") == 3, err  # the first run's two sessions, the second run's one
    held = [int(x.split("the fused map holds ")[1].split()[0]) for x in err.splitlines() if "fused map holds" in x]
    # the first run's last pair was fused onto the first (the second pair never reached the board whole); the
    # next run started afresh
    assert held == [1, 2, 1, 2, 3], err
    # and the board says which it did at each new session's Config
    kept = [x for x in err.splitlines() if x.startswith(("flight: the same descent", "flight: another descent"))]
    assert ["goes on" in x for x in kept] == [True, False], err
    assert [r["status"] for r in again["records"]] == ["result"] * 3
    assert rc == 128 + signal.SIGTERM
    # said in the outputs, not only on the console as it happened (stop 60's QA: a restarted board read "PASS")
    from hil_server.run import session_note

    assert s["ground_counters"]["link_sessions"]["sessions"] == 2 and "2 link sessions" in session_note(s)
    assert "2 link sessions" in (tmp_path / "run" / "summary.md").read_text()
    assert again["ground_counters"]["link_sessions"]["sessions"] == 1 and session_note(again) == ""


def test_our_flight_software_on_a_zeromq_board_with_curve_keys(manifest, tmp_path):
    keys = tmp_path / "keys"
    made = subprocess.run([sys.executable, "-m", "hil_server.cli", "keys", str(keys)], cwd=ROOT, check=True,
                          capture_output=True, text=True)  # fmt: skip
    assert "server.key_secret and clients/" in made.stdout
    assert {f.stat().st_mode & 0o777 for f in keys.rglob("*") if f.is_file()} == {0o600}
    with socket_port() as port:
        pass
    board = subprocess.Popen(
        [*BOARD, "--link", f"zmq:tcp://127.0.0.1:{port}", "--keys", str(keys)],
        cwd=ROOT,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        s = run_hil(manifest, tmp_path / "run", flight="external", link=f"zmq:tcp://127.0.0.1:{port}", keys=str(keys))
    finally:
        rc, err = _stop(board)
    assert exit_code(s) == 0 and [r["level"] for r in s["records"]] == ["full", "full"], err
    assert rc == 128 + signal.SIGTERM


SAYS = {
    "regular file": "a regular file, not a character device",
    "directory": "a directory, not a character device",
    "held": "is held by process",
    "not a tty": "/dev/null is not a serial device (a character device of the kernel's 'mem' class",
    "pty multiplexer": "/dev/ptmx is not a serial device (a terminal, console or the pty multiplexer",
    "--baud too slow": "at 2400 baud one link frame takes up to 6.4 s, past the 4 s link timeout",
    "two rates": "--baud 2400 and --link",
}


@pytest.mark.parametrize("what", list(SAYS))
def test_a_ground_refuses_a_serial_device_it_cannot_use_before_rendering(tmp_path, capsys, what):
    """A "device" that is a file, a directory or a character device that is not a serial port (/dev/null, the
    pty multiplexer), a device another process holds (a board or a ground still running on it), or a rate given
    with --baud that the link timeout cannot carry, is one line and exit 2 at once; each used to fail the
    ground's open after the descent was rendered (exit 1); /dev/ptmx even waited out the hello timeout."""
    from protocol.faults import PtyBridge
    from protocol.links import SerialLink

    (tmp_path / "file").write_text("")
    with PtyBridge() as bridge:
        device = {
            "regular file": str(tmp_path / "file"),
            "directory": str(tmp_path),
            "not a tty": "/dev/null",
            "pty multiplexer": "/dev/ptmx",
        }.get(what, bridge.paths[1])
        holder = SerialLink(device, 921600) if what == "held" else None
        link = {"--baud too slow": f"serial:{device}", "two rates": f"serial:{device}@9600"}.get(
            what, f"serial:{device}@921600"
        )
        baud = ["--baud", "2400"] if what in ("--baud too slow", "two rates") else []
        try:
            assert cli(["run", "--flight", "external", "--link", link, *baud, "--out", str(tmp_path / "o")]) == 2
        finally:
            if holder is not None:
                holder.close()
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and SAYS[what] in err[0], err
    assert not (tmp_path / "o" / "pairs").exists()  # nothing rendered


@pytest.mark.parametrize("mode, says", [(0o600, "its owner and mode 600 keep others out"), (0o660, "usermod -aG")])
def test_a_serial_device_one_may_not_open_is_refused_before_any_work(tmp_path, mode, says):
    """A port the user may not read and write (not in the dialout group) was found only after the render, as
    "the ground simulator exited with 2" and exit 1; `flight` found it after its warm-up (QA of stop 73). As
    another user than the device's owner (nobody, when the tests run as root), both refuse it at once."""
    import grp
    import shutil

    from protocol.faults import PtyBridge

    root = os.geteuid() == 0
    if root and shutil.which("setpriv") is None:
        pytest.skip("root without setpriv: no way to be refused a device")
    with PtyBridge() as bridge:
        device = bridge.paths[1]
        if root:  # root without its override of file permissions, the device another user's
            try:
                gid = grp.getgrnam("dialout").gr_gid
            except KeyError:
                gid = 65534
            os.chown(device, 65534, gid)
            prefix = ["setpriv", "--bounding-set=-dac_override,-dac_read_search"]
        else:
            mode, prefix = 0, []  # not even its owner, then
        os.chmod(device, mode)
        for argv in (
            ["run", "--flight", "external", "--link", f"serial:{device}@921600", "--out", str(tmp_path / "o")],
            ["flight", "--link", f"serial:{device}@921600"],
        ):
            p = subprocess.run(
                [*prefix, sys.executable, "-m", "hil_server.cli", *argv], capture_output=True, text=True,
                timeout=120, cwd=tmp_path,
            )  # fmt: skip
            assert p.returncode == 2, (argv[0], p.stderr)
            assert f"serial device {device}: permission denied" in p.stderr, p.stderr
            if root:
                assert says in p.stderr, p.stderr
    assert not (tmp_path / "o" / "pairs").exists()  # nothing rendered


def test_a_ground_whose_curve_key_the_board_refuses_gives_up_at_once_and_both_say_why(manifest, tmp_path):
    """Wrong keys used to cost the ground its whole hello timeout (120 s), printing the handshake failure ten times
    a second, while the board said nothing."""
    for side in ("board", "ground"):
        assert cli(["keys", str(tmp_path / side)]) == 0
    with socket_port() as port:
        pass
    board = subprocess.Popen(
        [*BOARD, "--link", f"zmq:tcp://127.0.0.1:{port}", "--keys", str(tmp_path / "board")],
        cwd=ROOT, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        t0 = time.monotonic()
        s = run_hil(manifest, tmp_path / "run", flight="external", link=f"zmq:tcp://127.0.0.1:{port}",
                    keys=str(tmp_path / "ground"), hello_timeout_s=60.0)  # fmt: skip
        took = time.monotonic() - t0
    finally:
        rc, err = _stop(board)
    why = s["reason"]
    assert exit_code(s) == 1 and not s["complete"] and "the CURVE handshake with the flight computer" in why, why
    assert all(r["code"] == "not_run" for r in s["records"])
    assert took < 20, took  # about 5 s of refusals, not the 60 s hello timeout
    said = [line for line in err.splitlines() if "auth_failed" in line]
    assert 1 <= len(said) <= 2 and "CURVE handshake failed" in said[0], err  # said, not repeated ~10 times a second
    assert rc == 128 + signal.SIGTERM


def test_keys_refuses_a_directory_it_cannot_make_or_would_overwrite(tmp_path, capsys):
    (tmp_path / "file").write_text("x")
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "server.key_secret").write_text("mine")
    for d, says in (("file", "is a file"), ("file/sub", "cannot create"), ("full", "not empty")):
        assert cli(["keys", str(tmp_path / d)]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and says in err[0], err
    assert (tmp_path / "full" / "server.key_secret").read_text() == "mine"
    # --help is help, not a directory named --help
    ran = subprocess.run([sys.executable, "-m", "protocol.zmqauth", "--help"], cwd=tmp_path, capture_output=True)
    assert ran.returncode == 0 and not (tmp_path / "--help").exists()


def test_keys_that_cannot_be_written_whole_leave_nothing_behind(tmp_path, capsys, monkeypatch):
    """A full disk left a 0-byte server.key_secret and clients/, and the next try, with room again, was refused
    "not empty; refusing to overwrite keys" (QA of stop 72)."""
    import errno

    import protocol.zmqauth as za

    real, calls = za._write, []

    def full(path, pub, sec):
        calls.append(path.name)
        if len(calls) == 3:  # the disk fills at the third file
            path.write_bytes(b"")
            raise OSError(errno.ENOSPC, "No space left on device")
        real(path, pub, sec)

    monkeypatch.setattr(za, "_write", full)
    for d in (tmp_path / "new", tmp_path / "empty"):
        if d.name == "empty":
            d.mkdir()
        calls.clear()
        assert cli(["keys", str(d)]) == 2
        err = capsys.readouterr().err.strip()
        assert f"cannot write the keys in {d}: No space left on device; nothing was left there" in err, err
        assert d.exists() == (d.name == "empty") and (not d.exists() or not any(d.iterdir()))
    monkeypatch.setattr(za, "_write", real)  # room again: the same command works
    assert cli(["keys", str(tmp_path / "new")]) == 0 and (tmp_path / "new" / "server.key_secret").stat().st_size > 0


class socket_port:
    """A free TCP port on loopback (bound and released)."""

    def __enter__(self) -> int:
        import socket

        self.sock = socket.socket()
        self.sock.bind(("127.0.0.1", 0))
        return int(self.sock.getsockname()[1])

    def __exit__(self, *exc: object) -> None:
        self.sock.close()


@pytest.mark.parametrize(
    ("link", "says"),
    [
        ("bogus", "link spec must be serial:URL[@BAUD] or zmq:ENDPOINT"),
        ("serial:/dev/no-such-tty@921600", "no serial device /dev/no-such-tty"),
        ("zmq:tcp://0.0.0.0:5599", "CURVE-authenticated"),
    ],
)
def test_a_link_that_cannot_serve_is_one_line_and_exit_2(link, says, capsys):
    assert cli(["flight", "--no-warm-up", "--link", link]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("hazard-hil flight: error: ") and says in err[0]


# -- the session rules, on a link that only records ----------------------------------------------------------


@dataclass
class Packet:
    message: object
    epoch: int


class RecordingLink:
    session_id = 0xABCD

    def __init__(self, packets: list[Packet], refusals: list[Refusal] | None = None) -> None:
        self.packets = list(packets)
        self.refusals = list(refusals or [])
        self.sent: list[tuple[object, int | None]] = []

    def take_refusals(self):
        out, self.refusals = self.refusals, []
        return out

    def recv_packet(self, timeout=None):
        return self.packets.pop(0) if self.packets else None

    def send(self, message, timeout=None, epoch=None) -> int:
        self.sent.append((message, epoch))
        return len(self.sent)


def _frame(seq: int, pair: str, k: int) -> Frame:
    eye = np.eye(3)
    img = np.zeros((4, 4), np.uint8)
    return Frame(
        seq=seq,
        capture_time_s=0.0,
        position_m=[0.0, 0.0, 100.0],
        R_world_to_cam=eye,
        altimeter_m=float("nan"),
        image=img,
        pair_id=pair,
        frame_index=k,
    )


def _result(seqs: tuple[int, int]) -> Result:
    return Result(
        frame_seqs=list(seqs),
        state_grid=np.full((2, 2), 2, np.uint8),
        psafe_grid=np.zeros((2, 2), np.uint8),
        elevation_grid=np.full((2, 2), -32768, np.int16),
        grid_origin_xy=[0.0, 0.0],
        grid_cell_m=1.0,
    )


def test_everything_goes_to_the_session_of_the_last_hello_and_strangers_are_dropped():
    cfg = Config(
        camera={"width": 4, "height": 4, "fx": 4.0, "fy": 4.0, "cx": 2.0, "cy": 2.0}, budget="", deadline_s=2.0
    )
    packets = [
        Packet(cfg, 1),  # before any Hello: a stranger's
        Packet(Hello(role="ground", session=11), 1),
        Packet(cfg, 1),
        Packet(_frame(1, "a", 0), 1),
        Packet(_frame(2, "a", 1), 1),
        Packet(_frame(3, "b", 0), 2),  # the link's next session, its ground's Hello not yet read
    ]
    link = RecordingLink(packets)
    resets = []
    ground = GroundSession(link, on_new_session=lambda: resets.append(1), log=lambda s: None)
    got = [ground.recv() for _ in packets]
    assert got[0] is None and got[1] is None and got[2] == cfg and isinstance(got[3], Frame) and got[5] is None
    assert ground.counters["dropped_no_hello"] == 2 and ground.counters["sessions"] == 1 and len(resets) == 1
    # pair "a", answered now: sent within session 1, which the link fails since session 2 is up
    link.sent.clear()
    ground.send(_result((1, 2)))
    ground.send(Telemetry(frame_seqs=[1, 2], total_latency_s=0.5, deadline_s=2.0))
    ground.send(Error(code="bad_input", text="x", seq=2))
    ground.send(Heartbeat(time_s=0.0))
    ground.send(Hello(role="flight"))  # the flight software's own, at boot: each ground's Hello is answered in recv
    assert [(type(m).__name__, e) for m, e in link.sent] == [
        ("Result", 1),
        ("Telemetry", 1),
        ("Error", 1),
        ("Heartbeat", 1),
    ]
    assert ground.counters["pairs"] == 1
    # the next ground's Hello: answered in its session, the flight software reset, and from then on session 2
    link.packets = [Packet(Hello(role="ground", session=22), 2), Packet(Hello(role="ground", session=22), 2)]
    link.sent.clear()
    assert ground.recv() is None and ground.recv() is None  # the same ground twice: one new session
    ground.send(Heartbeat(time_s=1.0))
    assert [(type(m).__name__, getattr(m, "role", None), e) for m, e in link.sent] == [
        ("Hello", "flight", 2),
        ("Hello", "flight", 2),
        ("Heartbeat", None, 2),
    ]
    assert ground.counters["sessions"] == 2 and len(resets) == 2 and ground.pair_ids == {}


def test_nothing_is_sent_before_a_ground_said_hello_and_a_refused_message_is_said():
    link = RecordingLink(
        [], refusals=[Refusal(3, "Frame.image: shape (0, 5) is empty", 0.0), Refusal(None, "malformed header", 0.0)]
    )
    said: list[str] = []
    ground = GroundSession(link, log=said.append)
    ground.send(Heartbeat(time_s=0.0))
    ground.send(Hello(role="flight"))
    assert link.sent == []
    assert ground.recv(0.01) is None
    assert ground.counters["refused"] == 2
    assert said == [
        "flight: refused a Frame from the link: Frame.image: shape (0, 5) is empty",
        "flight: refused a message from the link: malformed header",
    ]


def test_a_line_that_carries_only_noise_is_said_on_the_boards_console(monkeypatch):
    """A ground at another baud, or another device on the port: the ground said "another baud?" when its Hello went
    unanswered, and the board's console said nothing at all (QA of stop 71). Said per NOISE_NOTE_S while it lasts."""
    from flight_sw import board

    monkeypatch.setattr(board, "NOISE_NOTE_S", 0.0)
    link = RecordingLink([])
    said: list[str] = []
    ground = GroundSession(link, log=said.append)
    ground.recv(0.01)  # no stats (a ZeroMQ link has no CRC counters): nothing to say
    zero = {"bytes_received": 0, "frames_received": 0, "crc_errors": 0, "malformed": 0}
    link.stats = dict(zero)  # type: ignore[attr-defined]
    ground.recv(0.01)  # the first look
    link.stats = {**zero, "bytes_received": 1534, "crc_errors": 50, "malformed": 6}  # type: ignore[attr-defined]
    ground.recv(0.01)
    assert len(said) == 1, said
    assert "the line carried 1534 bytes in the last 0 s but not one valid frame of this protocol (56 failed their " \
           "checks): a ground at another baud, or another device on this port?" in said[0]  # fmt: skip
    link.stats = {**zero, "bytes_received": 3000, "frames_received": 3, "crc_errors": 52}  # type: ignore[attr-defined]
    ground.recv(0.01)  # frames came through: a noisy line, not a wrong one
    assert len(said) == 1


def _board_waiting_for_a_ground(port: str) -> tuple[subprocess.Popen, str]:
    """`hazard-hil flight` on ``port``, once it says it waits for a ground: (the process, what it said so far).
    Waiting, not a fixed sleep: a loaded machine took up to 2.3 s to get there; raw reads under select never
    block for good, nor leave the line in a buffer select cannot see."""
    import os
    import select

    board = subprocess.Popen([*BOARD, "--link", f"serial:{port}@921600"], cwd=ROOT, stderr=subprocess.PIPE, text=True)
    assert board.stderr is not None
    first = b""
    t0 = time.monotonic()
    while time.monotonic() - t0 < 60 and b"waiting for a ground" not in first:
        if select.select([board.stderr], [], [], 1.0)[0]:
            first += os.read(board.stderr.fileno(), 65536)
    return board, first.decode(errors="replace")


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGHUP])
def test_a_signal_stops_a_board_waiting_for_its_first_ground(tmp_path, sig):
    """A hangup (its terminal or ssh session closed) ends the board as SIGTERM does: its last line, the link closed."""
    from protocol.faults import PtyBridge

    with PtyBridge() as bridge:
        board, first = _board_waiting_for_a_ground(bridge.paths[0])
        rc, rest = _stop(board, sig)
    err = first + rest
    assert rc == 128 + sig, err
    assert f"stopped by {signal.Signals(sig).name}" in err
    assert "waiting for a ground" in err and "served 0 ground session(s), 0 pair(s); 0 message(s) refused" in err


def test_a_board_whose_line_fails_ends_with_what_it_served(tmp_path):
    """A line that failed under the board (a second reader, the other end closed) ended it without the last line
    hil.md promises, the sum of what it served."""
    from protocol.faults import PtyBridge

    bridge = PtyBridge()
    board, first = _board_waiting_for_a_ground(bridge.paths[0])
    bridge.close()  # the line goes away under it
    try:
        assert board.stderr is not None
        rest = board.stderr.read()
        rc = board.wait(timeout=60)
    finally:
        board.kill()
    err = first + rest
    assert rc == 1, err
    last = err.strip().splitlines()[-1]
    assert last.startswith("flight: the link failed") and "served 0 ground session(s), 0 pair(s)" in last, err


@pytest.mark.exclusive_core
def test_regress_gates_a_board_against_its_own_baseline(tmp_path, capsys):
    from protocol.faults import PtyBridge

    base = tmp_path / "board_baseline.json"
    case = {"scenario": "vertical", "budget": "snapdragon801", "flight": "external", "pairs": ["600/300"]}
    case |= {"image_size": 128, "link": "serial:/dev/the-lab-board@0"}  # this machine's device comes with --link
    base.write_text(json.dumps({"cases": {"board": case}}))
    with PtyBridge() as bridge:
        board = subprocess.Popen(
            [*BOARD, "--link", f"serial:{bridge.paths[0]}@0"], cwd=ROOT, stderr=subprocess.PIPE, text=True
        )
        try:
            args = ["regress", "--uncalibrated", "--baseline", str(base), "--out", str(tmp_path / "out"), "--link"]
            args.append(f"serial:{bridge.paths[1]}@0")
            assert cli([*args, "--update"]) == 0
            doc = json.loads(base.read_text())
            metrics = doc["cases"]["board"]["metrics"]
            assert doc["cases"]["board"]["link"] == case["link"]  # the override is not written back
            assert metrics["deadline_hit_rate"] == 1.0 and metrics["pairs"] == 1 and metrics["latency_p50_ref_s"] > 0
            # timing belongs in the benchmarks: this host under a loaded CI took 0.15 then 0.27 s, past the default
            # 0.1 s, so the gate is shown passing with room, then failing with none
            doc["tolerances"] = {"latency_rel": 20.0, "latency_abs_s": 5.0}
            base.write_text(json.dumps(doc))
            assert cli(args) == 0
            # a baseline the board cannot meet: latencies a thousandth of what it takes, no tolerance
            metrics.update(
                {k: metrics[k] / 1000 for k in ("latency_p50_ref_s", "latency_p95_ref_s", "latency_max_ref_s")}
            )
            doc["tolerances"] = {"latency_rel": 0.0, "latency_abs_s": 0.0}
            base.write_text(json.dumps(doc))
            capsys.readouterr()
            assert cli(args) == 1
        finally:
            _stop(board)
    got = capsys.readouterr()
    assert "REGRESSION" in got.out and "latency_p50_ref_s" in got.out and "FAIL" in got.out
    assert "regress: warning" not in got.err  # this host's calibration and load say nothing about the board


@pytest.mark.parametrize(
    ("change", "says"),
    [
        ({"flight": "board"}, "'flight' must be 'emulated' or 'external'"),
        ({"flight": "external", "link": "serial"}, "a board's 'link' is serial:DEVICE[@BAUD] or zmq:ENDPOINT"),
        ({"deadline_s": -1}, "'deadline_s' (as `run --deadline`) must be a number of seconds in [0.001, 3600]"),
        ({"deadline_s": 1e-5}, "'deadline_s' (as `run --deadline`) must be a number of seconds in [0.001, 3600]"),
        ({"image_size": "128"}, "'image_size' must be an integer number of pixels in 32..4096, got '128'"),
        ({"image_size": 8}, "'image_size' must be an integer number of pixels"),
        ({"seed": -1}, "'seed' must be an integer >= 0"),
        ({"seed": 1.5}, "'seed' must be an integer >= 0"),
        ({"manifest": ""}, "'manifest' must be a non-empty path"),
    ],
)
def test_a_malformed_board_case_is_one_line_and_exit_2(tmp_path, capsys, change, says):
    base = tmp_path / "b.json"
    case = {"scenario": "vertical", "budget": "host", "link": "zmq", **change}
    base.write_text(json.dumps({"cases": {"c": case}}))
    assert cli(["regress", "--uncalibrated", "--baseline", str(base), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and says in err[0]


def test_regress_gives_up_on_a_board_that_is_off_after_its_hello_timeout(tmp_path, capsys):
    """A board that is off (nobody on the device) costs a case the hello timeout, which regress now takes."""
    from protocol.faults import PtyBridge

    base = tmp_path / "b.json"
    case = {"scenario": "vertical", "budget": "host", "flight": "external", "pairs": ["600/300"], "image_size": 64}
    base.write_text(json.dumps({"cases": {"c": {**case, "link": "serial:/dev/the-lab-board@0"}}}))
    args = ["regress", "--uncalibrated", "--baseline", str(base), "--out", str(tmp_path / "o"), "--hello-timeout"]
    assert (
        cli([*args, "0"]) == 2
        and "--hello-timeout must be a number of seconds in (0, 86400]" in capsys.readouterr().err
    )
    with PtyBridge() as bridge:
        t0 = time.monotonic()
        assert cli([*args, "2", "--link", f"serial:{bridge.paths[1]}@0", "--update"]) == 1
        took = time.monotonic() - t0
    assert "no Hello from the flight computer" in capsys.readouterr().err
    assert took < 60, took  # rendering the 64 px pair, then 2 s of waiting (the default is 120 s)


def test_regress_link_needs_a_board_case(tmp_path, capsys):
    base = tmp_path / "b.json"
    base.write_text(json.dumps({"cases": {"c": {"scenario": "vertical", "budget": "host", "link": "zmq"}}}))
    assert (
        cli(
            [
                "regress",
                "--uncalibrated",
                "--baseline",
                str(base),
                "--link",
                "serial:/dev/x@0",
                "--out",
                str(tmp_path / "o"),
            ]
        )
        == 2
    )
    assert "none of these cases is one" in capsys.readouterr().err


def test_a_board_started_detached_outlives_the_shell_that_started_it(tmp_path):
    from protocol.faults import PtyBridge

    pidfile, err = tmp_path / "board.pid", tmp_path / "board.err"
    with PtyBridge() as bridge:
        cmd = " ".join([*BOARD, "--link", f"serial:{bridge.paths[0]}@0"])
        # as after `nohup ... &` and a logout
        # the shell outlives the board's start-up, then exits: the running board is reparented
        subprocess.run(["bash", "-c", f"{cmd} 2>{err} & echo $! > {pidfile}; sleep 3"], cwd=ROOT, check=True)
        pid = int(pidfile.read_text())
        try:
            time.sleep(1.5)
            assert Path(f"/proc/{pid}").exists(), err.read_text()
            s = run_hil(small_descent(tmp_path / "pairs", ["600/300"]), tmp_path / "run", flight="external",
                        link=f"serial:{bridge.paths[1]}@0")  # fmt: skip
            assert exit_code(s) == 0
        finally:
            subprocess.run(["kill", "-TERM", str(pid)], check=False)
            for _ in range(100):
                if not Path(f"/proc/{pid}").exists() or " Z " in Path(f"/proc/{pid}/stat").read_text():
                    break
                time.sleep(0.1)
    assert "stopped by SIGTERM" in err.read_text()


def test_regress_update_that_records_nothing_keeps_the_old_baseline(tmp_path, capsys):
    base = tmp_path / "b.json"
    case = {"scenario": "vertical", "budget": "host", "flight": "external", "link": "serial:/dev/x@0"}
    case |= {"pairs": ["600/300"], "image_size": 96, "metrics": {"deadline_hit_rate": 1.0, "latency_p50_ref_s": 0.1}}
    base.write_text(json.dumps({"cases": {"b": case}}))
    before = base.read_text()
    from protocol.faults import PtyBridge

    with PtyBridge() as bridge:  # a board that is off
        args = [
            "regress",
            "--uncalibrated",
            "--baseline",
            str(base),
            "--update",
            "--link",
            f"serial:{bridge.paths[1]}@0",
        ]
        assert cli([*args, "--hello-timeout", "1", "--out", str(tmp_path / "o")]) == 1
    assert base.read_text() == before
    assert "baseline NOT written" in capsys.readouterr().out


def test_the_diff_table_marks_a_hit_rate_regression_on_its_row():
    from hil_server.regress import DEFAULT_TOLERANCES, LATENCY_METRICS, compare, diff_table

    base = {"deadline_hit_rate": 1.0, **dict.fromkeys(LATENCY_METRICS, 1.0)}
    cur = {**base, "deadline_hit_rate": 0.0}
    row = [
        ln for ln in diff_table([compare("b", cur, base, DEFAULT_TOLERANCES)]).splitlines() if "deadline_hit_rate" in ln
    ]
    assert len(row) == 1 and row[0].endswith("REGRESSION")


def test_a_run_killed_outright_leaves_no_ground_streamer_holding_the_device(manifest, tmp_path):
    """``kill -9`` on ``hazard-hil run``: its ground streamer (a child in its own process group, so the terminal's
    Ctrl-C does not reach it) used to keep running, holding the serial device; the next ground on it then failed."""
    import psutil

    from protocol.faults import PtyBridge

    with PtyBridge() as bridge:  # no board on the far end: the ground waits for its Hello
        run = subprocess.Popen(
            [sys.executable, "-m", "hil_server.cli", "run", "--manifest", str(manifest), "--flight", "external",
             "--link", f"serial:{bridge.paths[1]}@0", "--out", str(tmp_path / "run")],
            cwd=ROOT, stderr=subprocess.PIPE, text=True,
        )  # fmt: skip
        try:
            children: list = []
            for _ in range(200):
                children = psutil.Process(run.pid).children()
                if children:
                    break
                time.sleep(0.1)
            assert children, "the run never started its ground streamer"
            time.sleep(1.0)  # the streamer is up and waiting
            run.kill()
            run.communicate(timeout=10)
            _, alive = psutil.wait_procs(children, timeout=10)
            assert not alive, [p.cmdline() for p in alive]
        finally:
            if run.poll() is None:
                run.kill()


def test_a_flood_of_refused_messages_is_summed_not_printed_line_by_line(monkeypatch):
    """Raw garbage on an insecure board's port printed 100 identical lines within seconds."""
    from flight_sw import board

    clock = [1000.0]
    monkeypatch.setattr(board.time, "monotonic", lambda: clock[0])
    link = RecordingLink([], refusals=[Refusal(None, "malformed message header: 238 bytes, not 16", 0.0)] * 40)
    said: list[str] = []
    ground = GroundSession(link, log=said.append)
    assert ground.recv(0.01) is None
    assert ground.counters["refused"] == 40 and len(said) == board.REFUSALS_SAID
    assert said[-1].endswith("(from now on at most one line per 10 s, with a count)")
    clock[0] += board.REFUSALS_QUIET_S  # the quiet time is over: the sum is said, on a timer ...
    assert ground.recv(0.01) is None
    assert said[-1].startswith("flight: refused 35 more message(s) from the link in the last 10 s"), said[-1]
    link.refusals = [Refusal(None, "malformed message header: 238 bytes, not 16", 0.0)] * 3
    clock[0] += 1.0
    assert ground.recv(0.01) is None and len(said) == board.REFUSALS_SAID + 1  # ... and quiet again
    clock[0] += board.REFUSALS_QUIET_S
    link.refusals = [Refusal(None, "malformed message header: 238 bytes, not 16", 0.0)]
    assert ground.recv(0.01) is None  # or with the next one, once the quiet time is over
    assert said[-1].endswith("16 (3 more refused before it, not shown)"), said[-1]
    assert ground.counters["refused"] == 44 and len(said) == board.REFUSALS_SAID + 2


def test_a_zeromq_port_where_nothing_listens_is_named_as_such(tmp_path):
    """libzmq retries a refused port in silence: the run read "its link never answered (is it powered ...?)"."""
    import socket

    with socket.socket() as s:  # a port that was free a moment ago: nothing listens on it
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    manifest = small_descent(tmp_path / "pairs", ["600/300"], px=64)
    s = run_hil(manifest, tmp_path / "run", f"zmq:tcp://127.0.0.1:{port}", flight="external", insecure=True,
                hello_timeout_s=2.0)  # fmt: skip
    assert not s["complete"] and f"nothing listens on 127.0.0.1:{port} (connection refused)" in s["reason"], s


def test_a_pair_whose_ground_left_is_not_called_met_on_the_board():
    """The board printed "met, as this side expects" for a pair computed after its ground's session had ended;
    the ground had recorded it as link_down."""
    link = RecordingLink([Packet(Hello(role="ground", session=7), 1)])
    said: list[str] = []
    ground = GroundSession(link, log=said.append)
    assert ground.recv() is None
    tel = Telemetry(frame_seqs=[0, 1], stages={}, total_latency_s=0.27, deadline_s=2.0, deadline_met=True)
    link.established, link.epoch = True, 1
    ground.pair_ids[0] = "p000-600_300"  # its frames came in this session
    ground.send(tel)
    assert "met, as this side expects" in said[-1]
    link.established = False  # the session is gone: the answer cannot reach that ground
    ground.send(tel)
    assert "not delivered: the ground's session ended" in said[-1] and "met" not in said[-1], said[-1]
    # a newer ground's Hello replaced the session while the pair was computed: not that ground's pair either
    link.established = True
    link.packets = [Packet(Hello(role="ground", session=8), 1)]
    assert ground.recv() is None and ground.pair_ids == {}
    ground.send(tel)
    assert "not delivered" in said[-1], said[-1]


def test_a_stranger_speaking_zeromq_on_the_boards_port_is_counted_and_named(tmp_path):
    """Before a session the ground neither said nor counted what it refused: 160 malformed messages from a rogue
    on the port ended as "the board never answered", with refused_messages 0."""
    import threading

    import zmq

    ctx = zmq.Context()
    rogue = ctx.socket(zmq.PAIR)
    rogue.linger = 0
    port = rogue.bind_to_random_port("tcp://127.0.0.1")
    stop = threading.Event()

    def babble() -> None:
        while not stop.is_set():
            rogue.send(b"\x02\x01", zmq.NOBLOCK) if rogue.poll(0, zmq.POLLOUT) else None
            time.sleep(0.05)

    t = threading.Thread(target=babble, daemon=True)
    t.start()
    try:
        manifest = small_descent(tmp_path / "pairs", ["600/300"], px=64)
        s = run_hil(manifest, tmp_path / "run", f"zmq:tcp://127.0.0.1:{port}", flight="external", insecure=True,
                    hello_timeout_s=3.0)  # fmt: skip
    finally:
        stop.set()
        t.join(2)
        rogue.close()
        ctx.term()
    assert not s["complete"] and "answers, but not in this protocol" in s["reason"], s["reason"]
    counters = json.loads((tmp_path / "run" / "received" / "ground.json").read_text())
    assert counters["refused_messages"] > 0 and "before any session" in counters["last_refused"]["reason"]


def test_a_ground_that_fails_after_its_checks_gives_the_run_its_reason_and_a_log(tmp_path):
    """A device that refuses at open time (a socket:// port where nothing listens) ended the ground with exit 2: its
    reason went to the console once, while summary.md and every pair said only "the ground simulator exited with 2"."""
    import socket

    with socket.socket() as s:  # a port that was free a moment ago
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    manifest = small_descent(tmp_path / "pairs", ["600/300"], px=64)
    s = run_hil(manifest, tmp_path / "run", f"serial:socket://127.0.0.1:{port}", flight="external")
    assert not s["complete"] and s["reason"].startswith("the ground simulator exited with 2: ground: error: ")
    assert "Connection refused" in s["reason"] and str(tmp_path / "run" / "ground.log") in s["reason"], s["reason"]
    assert "Connection refused" in (tmp_path / "run" / "ground.log").read_text()
    assert all("Connection refused" in r["text"] for r in s["records"])


def test_a_result_the_link_failed_to_deliver_after_its_line_said_met_is_corrected():
    """The board printed "met" when the Telemetry went, while the Result still waited in its link; the session was
    lost before it left (a board frozen 25 s), and nothing ever said so."""
    link = RecordingLink([Packet(Hello(role="ground", session=7), 1)])
    outcomes: dict[int, str] = {}
    link.outcome = outcomes.get  # type: ignore[attr-defined]
    said: list[str] = []
    ground = GroundSession(link, log=said.append)
    assert ground.recv() is None
    link.established, link.epoch = True, 1
    ground.pair_ids[0] = "p000-600_300"
    mid = ground.send(_result((0, 1)))
    ground.send(Telemetry(frame_seqs=[0, 1], stages={}, total_latency_s=0.2, deadline_s=2.0, deadline_met=True))
    assert "met, as this side expects" in said[-1]
    outcomes[mid] = "pending"
    assert ground.recv() is None and len(said) == 2  # nothing known yet
    outcomes[mid] = "failed: session lost: no frame from the peer for 4.0 s"
    assert ground.recv() is None
    want = "flight: pair p000-600_300: its Result was not delivered after all (session lost: no frame from the peer"
    assert said[-1] == want + " for 4.0 s)", said[-1]
    assert ground.recv() is None and len(said) == 3  # said once


def test_strangers_knocking_on_the_hil_servers_port_reach_the_runs_summary(tmp_path):
    """Clients without the run's CURVE keys knocked on the emulated run's ZeroMQ port: supervisor.log said so,
    while the summary read PASS as if nobody had."""
    import threading

    import zmq

    manifest = small_descent(tmp_path / "pairs", ["600/300", "300/150"], px=64)
    stop = threading.Event()
    knocked: list[int] = []

    def knock() -> None:  # find the server's port on its command line, then knock without keys
        ctx = zmq.Context()
        try:
            while not stop.is_set():
                for d in Path("/proc").iterdir():
                    try:
                        cmd = (d / "cmdline").read_bytes().split(b"\0") if d.name.isdigit() else []
                    except OSError:
                        continue
                    if b"hil_server.supervisor" in b" ".join(cmd) and str(tmp_path).encode() in b" ".join(cmd):
                        link = next((c for c in cmd if c.startswith(b"zmq:tcp://")), None)
                        if link is not None and not knocked:
                            # until the run ends (at most 30): a server that bound late missed the first knocks
                            for _ in range(30):
                                if stop.is_set():
                                    break
                                s = ctx.socket(zmq.PAIR)
                                s.linger = 0
                                s.connect(link.decode()[4:])
                                s.send(b"hello?", zmq.NOBLOCK) if s.poll(200, zmq.POLLOUT) else None
                                time.sleep(0.3)
                                s.close()
                            knocked.append(1)
                time.sleep(0.1)
        finally:
            ctx.term()

    t = threading.Thread(target=knock, daemon=True)
    t.start()
    try:
        s = run_hil(manifest, tmp_path / "run", "zmq")
    finally:
        stop.set()
        t.join(5)
    assert knocked, "the HIL server's port was never found"
    counters = s["supervisor_counters"]
    assert counters.get("port_refused", 0) >= 1, counters
    from hil_server.run import flight_note

    assert "refused on the HIL server's port" in flight_note(s), flight_note(s)


def test_a_board_says_when_its_port_rate_is_not_the_grounds():
    """A board at 9600 baud under a ground pacing 921600 planned for the ground's rate and called its own miss
    "met"; a pty carries the bytes whatever the rates, so nothing else noticed."""
    from flight_sw.flight_main import baud_mismatch_note

    said = baud_mismatch_note(921600, 9600)
    assert "921600 baud" in said and "set to 9600" in said and "must match" in said
    assert baud_mismatch_note(921600, 921600) == "" and baud_mismatch_note(0, 9600) == ""
    assert baud_mismatch_note(921600, None) == ""  # an unpaced side: nothing to compare
    # the ground's record of the run says it too (only the board's console did; QA of stop 71)
    from hil_server.run import baud_note

    summary = {"ground_counters": {"line_baud": 921600}, "records": [{"link": {"port_baud": 115200.0}}, {}]}
    said = baud_note(summary)
    assert "serial port is set to 115200 baud, and this ground paced the line at 921600 baud" in said
    assert baud_note({**summary, "ground_counters": {"line_baud": 0}}) == ""  # an unpaced ground: nothing to compare
    summary["records"][0]["link"]["port_baud"] = 921600.0
    assert baud_note(summary) == ""


def test_a_result_faster_than_the_line_rate_is_said_with_the_downlink_it_leaves_out():
    """QA of stop 74: a board writing unpaced into a pty read "end to end 0.0011 s, met" for 342 bytes that take
    3.7 ms at 921600 baud. The note names the time left out and whether a deadline would flip with it."""
    from hil_server.run import unpaced_note

    def rec(e2e: float, n: int, flight: float | None = 0.0005, met: bool = True) -> dict:
        return {"label": "600/300", "e2e_latency_s": e2e, "result_bytes": n, "flight_latency_s": flight,
                "deadline_met": met}  # fmt: skip

    recs = [rec(0.0011, 342), rec(0.5, 342), {"status": "error"}]  # an error record is no Result
    s = {"ground_counters": {"line_baud": 921600}, "deadline_s": 2.0, "records": recs}
    said = unpaced_note(s)
    assert said.startswith("1 of 2 Results reached this ground faster than 921600 baud"), said
    assert "342 bytes need 0.0037 s" in said and "every deadline met here would still be met" in said, said
    # a deadline it would flip: 200 kB at 115200 baud is 17 s of line, arrived in 1.5 s
    s = {"ground_counters": {"line_baud": 115200}, "deadline_s": 2.0, "records": [rec(1.5, 200_000, flight=None)]}
    assert "with it, 1 of the deadlines met here would have been missed" in unpaced_note(s), unpaced_note(s)
    # paced: the line time is in the latency; and an unpaced ground, a tiny Result, or no figures say nothing
    assert unpaced_note({**s, "records": [rec(18.0, 200_000)]}) == ""
    assert unpaced_note({**s, "ground_counters": {"line_baud": 0}}) == ""
    fast = {**s, "ground_counters": {"line_baud": 921600}}
    assert unpaced_note({**fast, "records": [rec(0.0001, 100)]}) == ""  # 1.1 ms of line: within the clocks' jitter
    assert unpaced_note({**s, "records": [{"e2e_latency_s": None, "result_bytes": 342}]}) == ""


def test_the_zeromq_example_flight_program_serves_a_ground_with_curve(manifest, tmp_path):
    """examples/minimal_flight_zmq.py, written from docs/protocol.md alone: the session layer of section 7 (the
    header, the HELLO handshake, rising message numbers), ext 2 arrays, and CURVE with `hazard-hil keys`. A user
    writing a ZeroMQ flight side had only the serial example to start from (stop 58's QA)."""
    from hil_server.run import _free_tcp_port
    from protocol.zmqauth import generate_keys

    keys = generate_keys(tmp_path / "keys")
    endpoint = f"tcp://127.0.0.1:{_free_tcp_port()}"
    board = subprocess.Popen(
        [sys.executable, str(ROOT / "examples" / "minimal_flight_zmq.py"), "--endpoint", endpoint, "--keys", str(keys)],
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        s = run_hil(manifest, tmp_path / "run", flight="external", link=f"zmq:{endpoint}", keys=keys)
    finally:
        board.terminate()
        _, err = board.communicate(timeout=10)
    assert exit_code(s) == 0 and s["complete"], s.get("reason")
    assert [r["status"] for r in s["records"]] == ["result", "result"] and f"listening on {endpoint}" in err
    # its answer: every cell unknown, no site; and the ground saw nothing to drop or refuse
    assert all(r["level"] == "none" and not r["sites"] for r in s["records"])
    g = s["ground_counters"]
    assert g["refused_messages"] == 0 and not any(g["session_drops"].values()), g
    # who it said it is, kept for the reader of the summary
    assert g["flight_hello"] == {"role": "flight", "software": "minimal_flight_zmq", "protocol_version": 2}
    assert "The flight side says it is 'minimal_flight_zmq'" in (tmp_path / "run" / "summary.md").read_text()


SLOW_ZMQ_FLIGHT = """
import sys, time
sys.path.insert(0, {examples!r})
import minimal_flight as mf
import minimal_flight_zmq as z

plain = mf.answer
calls = []


def slow(*a):  # a detector that takes its time (past the ground's 4 s link timeout) on the first two pairs it gets
    calls.append(1)
    if len(calls) == 1:
        open({inside!r}, "w").close()  # inside answer() for the first ground: the test stops that ground now
    if len(calls) <= 2:  # the second: the next ground's first pair, its session kept up meanwhile
        time.sleep(5.0)
    return plain(*a)


mf.answer = slow
sys.exit(z.main(sys.argv[1:]))
"""


def test_the_zeromq_example_serves_the_next_ground_after_one_left_while_it_computed(manifest, tmp_path):
    """A ground stopped (Ctrl-C) while the example was inside answer(): its next send blocked for good on the PAIR
    socket, and every later ground got no Hello (stop 58's QA). It sends without waiting now."""
    from hil_server.run import _free_tcp_port

    script = tmp_path / "slow_flight.py"
    inside = tmp_path / "inside_answer"
    script.write_text(SLOW_ZMQ_FLIGHT.format(examples=str(ROOT / "examples"), inside=str(inside)))
    endpoint = f"tcp://127.0.0.1:{_free_tcp_port()}"
    board = subprocess.Popen(
        [sys.executable, str(script), "--endpoint", endpoint, "--insecure"], stderr=subprocess.PIPE
    )
    try:
        first = subprocess.Popen(
            [sys.executable, "-m", "hil_server.cli", "run", "--flight", "external", "--link", f"zmq:{endpoint}",
             "--insecure", "--manifest", str(manifest), "--out", str(tmp_path / "first"), "--no-progress"],
            cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        )  # fmt: skip
        t0 = time.monotonic()  # its Hello, Config and the first pair's frames went: the board is inside answer()
        while not inside.exists() and first.poll() is None and time.monotonic() - t0 < 60:
            time.sleep(0.05)
        assert inside.exists(), "the board never got the first ground's pair"
        first.send_signal(signal.SIGINT)
        assert first.wait(30) == 130
        s = run_hil(manifest, tmp_path / "second", flight="external", link=f"zmq:{endpoint}", insecure=True)
    finally:
        board.terminate()
        board.communicate(timeout=10)
    # served: both answered (the first late, a 5 s detector against a 2 s deadline, which is the board's business)
    assert s["complete"] and [r["status"] for r in s["records"]] == ["result", "result"], s.get("reason")


def test_a_flood_past_what_the_link_keeps_is_counted_whole(monkeypatch):
    """The link hands over the latest REFUSALS_KEPT refusals between two looks and counts them all: a flood of
    20 000 read "64 message(s) refused" on the board's last line (QA of stop 72)."""
    from flight_sw import board
    from protocol.arq import REFUSALS_KEPT

    class Flooded(RecordingLink):
        def refused_count(self) -> int:
            return 20_000

    clock = [1000.0]
    monkeypatch.setattr(board.time, "monotonic", lambda: clock[0])
    kept = [Refusal(None, "malformed message header: 2 bytes, not 16", 0.0)] * REFUSALS_KEPT
    said: list[str] = []
    ground = GroundSession(Flooded([], refusals=kept), log=said.append)
    assert ground.recv(0.01) is None and ground.counters["refused"] == 20_000
    clock[0] += board.REFUSALS_QUIET_S
    assert ground.recv(0.01) is None
    assert said[-1].startswith(f"flight: refused {20_000 - board.REFUSALS_SAID} more message(s) from the link"), said


def test_a_pair_answered_with_an_error_is_a_line_on_the_boards_console(monkeypatch):
    """A frame the camera refuses was answered `Error bad_frame` to the ground, and the board's console, which
    prints a line per pair, showed nothing (QA of stop 72). A flood of them is summed as refusals are."""
    from flight_sw import board
    from protocol.messages import Error, Hello

    clock = [1000.0]
    monkeypatch.setattr(board.time, "monotonic", lambda: clock[0])
    hello = Packet(Hello(role="ground", session=7), epoch=1)
    frames = [Packet(_frame(10 + k, f"p{k}", 0), epoch=1) for k in range(8)]
    said: list[str] = []
    ground = GroundSession(RecordingLink([hello, *frames]), log=said.append)
    for _ in range(9):
        ground.recv(0.01)
    for k in range(8):
        ground.send(Error(code="bad_frame", text=f"frame {10 + k}: image 64x200, the camera is 128x128", seq=10 + k))
    lines = [s for s in said if "Error" in s]
    assert lines[0] == "flight: pair p0: answered with Error bad_frame: frame 10: image 64x200, the camera is 128x128"
    assert len(lines) == board.REFUSALS_SAID and ground.counters["errors"] == 8
    clock[0] += board.REFUSALS_QUIET_S
    ground.recv(0.01)
    assert said[-1] == "flight: answered 3 more Error(s) in the last 10 s (the latest bad_frame)", said[-1]
    assert "served 1 ground session(s), 0 pair(s) (8 answered with an Error);" in board._served(ground.counters)


def test_the_boards_last_line_and_its_telemetry_say_what_its_line_dropped():
    from flight_sw.board import _served
    from flight_sw.flight_main import line_damage

    c = {"sessions": 1, "pairs": 2, "refused": 0, "dropped_no_hello": 0}
    assert line_damage({"crc_errors": 0, "malformed": 0}) == {} and "the line dropped" not in _served(c, {})
    stats = {"crc_errors": 3, "malformed": 2, "bytes_discarded": 814}
    assert line_damage(stats) == {"flight_rx_damaged": 5.0, "flight_rx_noise_bytes": 814.0}
    assert _served(c, stats).endswith("; the line dropped 5 damaged frame(s) (814 bytes of noise)")
