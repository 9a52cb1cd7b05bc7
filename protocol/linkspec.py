"""Open a link from a one-line spec, the form every command line and config uses.

``serial:URL[@BAUD]``  any pyserial port URL: a device (``/dev/ttyUSB0``), a pty slave path,
                       ``socket://HOST:PORT``, ``rfc2217://HOST:PORT``, ``loop://``. BAUD (default
                       921600) sets the port and paces writes in software at 10 bits per byte,
                       since a pty or a socket has no line rate of its own; ``@0`` leaves writes
                       unpaced. A trailing ``@digits`` is always read as the baud rate.
``zmq:ENDPOINT``       a ZeroMQ endpoint, e.g. ``zmq:tcp://127.0.0.1:5555``; the server side
                       binds, the client connects. CURVE-authenticated with the keys in
                       ``keys`` (see :mod:`protocol.zmqauth`); ``insecure=True`` only on loopback.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

from protocol.arq import ArqConfig
from protocol.errors import InputError
from protocol.framing import DEFAULT_MAX_FRAME

DEFAULT_BAUD = 921600
BAUD_MIN, BAUD_MAX = 50, 100_000_000  # a paced line's rates


def parse_serial(rest: str) -> tuple[str, int | None]:
    """``URL[@BAUD]`` -> (url, baud or None for unpaced)."""
    url, sep, baud = rest.rpartition("@")
    if sep and url and not baud:
        raise InputError(f"serial link spec {rest!r}: nothing after '@' (the baud, e.g. @921600, or @0 for unpaced)")
    if sep and url and baud and "/" not in baud and not baud.isdigit():  # serial:/dev/ttyS0@fast: a baud meant
        raise InputError(
            f"serial link spec {rest!r}: the baud after '@' must be a whole number of bits per second (0: unpaced), "
            f"got {baud!r}"
        )
    if not sep or not baud.isdigit():
        return rest, DEFAULT_BAUD
    if not url:
        raise InputError(f"serial link spec {rest!r} has no device")
    b = int(baud)
    if b and not BAUD_MIN <= b <= BAUD_MAX:
        raise InputError(f"serial baud must be 0 (unpaced) or in [{BAUD_MIN}, {BAUD_MAX:.0e}], got {b}")
    return url, (b or None)


# a board's heartbeats may take at most this share of a paced serial line (the link's own keepalive keeps the
# session alive; the heartbeat says the flight software is): at 2400 baud one every 0.25 s took 80 % of it
HEARTBEAT_LINE_SHARE = 0.02


def heartbeat_period(baud: int | None, period_s: float) -> float:
    """The heartbeat period on a line of ``baud`` (None: unpaced): ``period_s``, or longer where one heartbeat's
    frame would otherwise take more than :data:`HEARTBEAT_LINE_SHARE` of the line (10 bits per byte)."""
    if baud is None:
        return period_s
    from protocol.codec import encode_message
    from protocol.framing import dgram_frame
    from protocol.messages import Heartbeat

    frame = dgram_frame(0xFFFFFFFF, 0xFFFFFFFF, Heartbeat.TYPE, encode_message(Heartbeat(time_s=0.0, counter=2**31)))
    return max(period_s, len(frame) * 10 / baud / HEARTBEAT_LINE_SHARE)


MAX_RECONNECT_TIMEOUT_S = 3600.0  # the ground's wait for a lost flight side to come back


def check_reconnect_timeout(seconds: float) -> None:
    """Refuse a reconnect wait outside (0, :data:`MAX_RECONNECT_TIMEOUT_S`] s (NaN too)."""
    if not 0 < seconds <= MAX_RECONNECT_TIMEOUT_S:
        raise InputError(
            f"--reconnect-timeout must be a number of seconds in (0, {MAX_RECONNECT_TIMEOUT_S:g}], got {seconds}"
        )


def check_positive_seconds(option: str, seconds: float) -> None:
    """Refuse a timer option that is not a finite number of seconds above 0."""
    if not (math.isfinite(seconds) and seconds > 0):
        raise InputError(f"{option} must be a positive number of seconds, got {seconds}")


MAX_LINK_TIMEOUT_S = 3600.0  # a peer silent longer than an hour is gone; beyond this the timers overflow
# an idle but healthy peer speaks once per keepalive (1 s): a shorter silence is no sign of a lost peer
MIN_LINK_TIMEOUT_S = 2.0


def check_link_timeout(seconds: float, option: str = "--link-timeout") -> None:
    """Refuse a link timeout a healthy link cannot keep (under two keepalives) or the timers cannot hold."""
    if not MIN_LINK_TIMEOUT_S <= seconds <= MAX_LINK_TIMEOUT_S:  # NaN fails too
        raise InputError(
            f"{option} must be a number of seconds in [{MIN_LINK_TIMEOUT_S:g}, {MAX_LINK_TIMEOUT_S:g}] (a healthy "
            f"peer speaks once a second), got {seconds}"
        )


# one link frame (DEFAULT_MAX_FRAME bytes, byte stuffing and a margin: x1.5) must take well under the link timeout,
# or a healthy but slow line reads as a peer that stopped acknowledging (measured: 2400 baud with the 4 s timeout
# lost every session; 4800 worked)
FRAME_TIME_MARGIN = 1.5


def check_baud(baud: int | None, peer_timeout: float | None) -> None:
    """Refuse a paced rate at which one link frame takes longer than the link timeout allows (``None``: unpaced
    or no timeout, nothing to check): the session would be lost on every frame, after the descent was rendered."""
    if baud is None or peer_timeout is None:
        return
    frame_s = FRAME_TIME_MARGIN * DEFAULT_MAX_FRAME * 10 / baud
    if frame_s >= peer_timeout:
        need = math.ceil(FRAME_TIME_MARGIN * DEFAULT_MAX_FRAME * 10 / peer_timeout)
        raise InputError(
            f"at {baud} baud one link frame takes up to {frame_s:.1f} s, past the {peer_timeout:g} s link timeout: "
            f"use at least {need} baud, or a much longer --link-timeout on both ends"
        )


def check_zmq_endpoint(endpoint: str, *, bind: bool) -> None:
    """Refuse an endpoint libzmq would refuse only at connect time, or take wrongly: ``tcp://HOST:PORT`` with a
    port in 1..65535 (``*`` for any host or port where binding), ``ipc://PATH`` or ``inproc://NAME`` (which
    :func:`check_link_spec` then refuses for a link between processes). A port out of range was taken modulo
    65536 (``tcp://*:99999`` listened on 34463)."""
    scheme, sep, rest = endpoint.partition("://")
    if not sep or scheme not in ("tcp", "ipc", "inproc"):
        raise InputError(f"ZeroMQ endpoint must be tcp://HOST:PORT, ipc://PATH or inproc://NAME, got {endpoint!r}")
    if scheme != "tcp":
        if not rest:
            raise InputError(f"ZeroMQ endpoint {endpoint!r} names no {'path' if scheme == 'ipc' else 'name'}")
        return
    host, colon, port = rest.rpartition(":")
    if not colon or not host:
        raise InputError(f"ZeroMQ endpoint {endpoint!r} needs a host and a port: tcp://HOST:PORT")
    if host == "*" and not bind:
        raise InputError(f"ZeroMQ endpoint {endpoint!r}: '*' is for the binding side; connect to the board's address")
    if port == "*" and bind:
        return
    if not port.isdigit() or not 1 <= int(port) <= 65535:
        raise InputError(f"ZeroMQ endpoint {endpoint!r}: the port must be a number in 1..65535, got {port!r}")


def _check_resolves(endpoint: str) -> None:
    """A host name that does not resolve is said now: libzmq retried it silently until the hello timeout
    (120 s), which then read as a board that never answered."""
    import socket

    # libzmq's "tcp://SOURCE;HOST:PORT" binds the source address: the host to resolve is after the ';'
    host, _, port = endpoint[len("tcp://") :].rpartition(";")[2].rpartition(":")
    host = host.strip("[]")
    try:
        socket.getaddrinfo(host, int(port), type=socket.SOCK_STREAM)
    except (OSError, UnicodeError, ValueError) as exc:
        raise InputError(f"ZeroMQ endpoint {endpoint!r}: host {host!r} does not resolve ({exc})") from None


def _check_bindable(endpoint: str) -> None:
    """The binding side's host and port, tried now with a socket of our own: a name that does not resolve, an
    address not this machine's or a port in use was said by libzmq only after a board's warm-up (``cannot bind
    ...: Resource temporarily unavailable``). A port taken between this check and the bind is still said then."""
    import errno
    import socket

    host, _, port = endpoint[len("tcp://") :].rpartition(";")[2].rpartition(":")
    host = host.strip("[]")
    if port == "*" or host in {name for _, name in socket.if_nameindex()}:
        return  # any port; or an interface name (tcp://eth0:PORT), which libzmq binds and getaddrinfo does not know
    try:
        if host == "*":  # libzmq's wildcard: IPv4's, unless its IPv6 option is on (ours is not)
            infos = socket.getaddrinfo(None, int(port), socket.AF_INET, socket.SOCK_STREAM, 0, socket.AI_PASSIVE)
        else:
            infos = socket.getaddrinfo(host, int(port), type=socket.SOCK_STREAM)
    except (OSError, UnicodeError, ValueError) as exc:
        raise InputError(f"ZeroMQ endpoint {endpoint!r}: host {host!r} does not resolve ({exc})") from None
    family, kind, proto, _, addr = infos[0]
    with socket.socket(family, kind, proto) as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as libzmq's listener: TIME_WAIT is no bar
        try:
            probe.bind(addr)
        except OSError as exc:
            why = {
                errno.EADDRINUSE: f"port {port} is in use (another board or run?)",
                errno.EADDRNOTAVAIL: f"{host!r} is not an address of this machine",
                errno.EACCES: f"port {port} needs privileges",
            }.get(exc.errno or 0, exc.strerror or str(exc))
            raise InputError(f"ZeroMQ endpoint {endpoint!r}: cannot bind: {why}") from None


def check_link_spec(
    spec: str,
    *,
    server: bool,
    insecure: bool = False,
    peer_timeout: float | None = None,
    keys: str | Path | None = None,
    check_keys: bool = False,
) -> None:
    """What can be known of a link spec without opening it, said before any work (a board's warm-up, a ground's
    rendering): its form, a serial device's state (:func:`check_serial_device`), a ZeroMQ endpoint
    (:func:`check_zmq_endpoint`), ``--insecure`` off loopback and, with ``check_keys``, a ZeroMQ link's key
    files for its side (:func:`protocol.links.check_zmq_security`)."""
    from protocol.links import check_zmq_security, is_loopback_endpoint

    kind, _, rest = spec.partition(":")
    if kind == "serial" and rest:
        device, baud = parse_serial(rest)
        check_baud(baud, peer_timeout)
        check_serial_device(device)
    elif kind == "zmq" and rest:
        check_zmq_endpoint(rest, bind=server)
        if rest.startswith("inproc://"):  # the ground, the HIL server and a board are separate processes
            raise InputError(
                f"ZeroMQ endpoint {rest!r}: inproc:// joins threads of one process; another process needs "
                "tcp://HOST:PORT or ipc://PATH"
            )
        if rest.startswith("tcp://"):
            (_check_bindable if server else _check_resolves)(rest)
        if check_keys:
            check_zmq_security(rest, keys, insecure)
            if keys is not None and not insecure:
                from protocol.zmqauth import client_keys, server_keys

                (server_keys if server else client_keys)(keys)  # a missing or unreadable key file
        elif insecure and not is_loopback_endpoint(rest):
            raise InputError(f"--insecure is for loopback debugging only; {rest!r} is not a loopback endpoint")
    else:
        raise InputError(f"link spec must be serial:URL[@BAUD] or zmq:ENDPOINT, got {spec!r}")


def _lock_holder(st) -> int | None:
    """The pid holding a flock on the file ``st`` describes (Linux ``/proc/locks``), or None: seen without opening
    the device, which on a USB serial adapter would pulse DTR and can reset the board behind it."""
    key = f"{os.major(st.st_dev):02x}:{os.minor(st.st_dev):02x}:{st.st_ino}"
    try:
        text = Path("/proc/locks").read_text()
    except OSError:
        return None
    for line in text.splitlines():
        f = line.split()
        if len(f) >= 6 and f[1] == "FLOCK" and f[5] == key and f[4].isdigit():
            return int(f[4])
    return None


def _char_device_class(st: os.stat_result) -> str | None:
    """The kernel's class of a character device (``tty`` for serial ports and terminals, ``mem`` for
    /dev/null...), read from sysfs without opening it; None where sysfs does not list it (pty slaves)."""
    link = Path(f"/sys/dev/char/{os.major(st.st_rdev)}:{os.minor(st.st_rdev)}/subsystem")
    try:
        return Path(os.readlink(link)).name or None
    except OSError:
        return None


def check_serial_device(device: str) -> None:
    """Refuse, before minutes of rendering, a serial device that cannot be this link: missing, not a character
    device (a regular file, a directory), a character device of another class than tty (``/dev/null``), or held
    by another process (our links lock their device). A
    pyserial URL (``socket://``, ``rfc2217://``, ``loop://``) passes: only opening it can tell."""
    import stat

    if "://" in device:
        return
    try:
        st = os.stat(device)
    except FileNotFoundError:
        raise InputError(f"no serial device {device} (is it plugged in, and is the name right?)") from None
    except OSError as exc:
        raise InputError(f"serial device {device}: {exc.strerror or exc}") from None
    if not stat.S_ISCHR(st.st_mode):
        what = "a directory, " if stat.S_ISDIR(st.st_mode) else "a regular file, " if stat.S_ISREG(st.st_mode) else ""
        raise InputError(f"{device} is not a serial device ({what}not a character device)")
    kind = _char_device_class(st)
    if kind is not None and kind != "tty":
        raise InputError(
            f"{device} is not a serial device (a character device of the kernel's {kind!r} class, not 'tty')"
        )
    major, minor = os.major(st.st_rdev), os.minor(st.st_rdev)
    if major == 5 or (major == 4 and minor < 64):  # Linux devices.txt: 5 = tty, console, ptmx; 4/0-63 = consoles
        raise InputError(
            f"{device} is not a serial device (a terminal, console or the pty multiplexer: use a port such as "
            "/dev/ttyUSB0, /dev/ttyACM0 or /dev/ttyS0, or a pty's slave)"
        )
    holder = _lock_holder(st)
    if holder is not None:
        raise InputError(f"serial device {device} is held by process {holder} (a ground or board still running on it?)")
    # with this process's effective ids and capabilities, and without opening it (an open toggles DTR, which resets
    # some boards): a port one may not open was found only after the render, as an exit 1 (QA of stop 73)
    effective = os.access in os.supports_effective_ids
    if not os.access(device, os.R_OK | os.W_OK, effective_ids=effective):
        raise InputError(f"serial device {device}: permission denied (it needs read and write access; {_who_may(st)})")


def _who_may(st: os.stat_result) -> str:
    """How to be let at a device of ``st``: its group, which a user joins (``dialout`` on Debian)."""
    import grp

    try:
        group = grp.getgrgid(st.st_gid).gr_name
    except (KeyError, OverflowError):
        group = str(st.st_gid)
    if st.st_mode & 0o060 == 0o060:
        return f"its group {group!r} has it: `sudo usermod -aG {group} $USER`, then log in again"
    return f"its owner and mode {st.st_mode & 0o777:03o} keep others out: ask whoever set them up"


def open_link(
    spec: str,
    *,
    server: bool,
    keys: str | Path | None = None,
    insecure: bool = False,
    peer_timeout: float | None = 4.0,
    connect_timeout: float | None = 30.0,
    name: str = "",
    log=None,
):
    from protocol.links import SerialLink, ZmqLink

    if peer_timeout is not None:
        check_link_timeout(peer_timeout, "link timeout")
    kind, _, rest = spec.partition(":")
    if kind == "serial" and rest:
        url, baud = parse_serial(rest)
        check_baud(baud, peer_timeout)
        cfg = ArqConfig(peer_timeout=peer_timeout, connect_timeout=connect_timeout)
        return SerialLink(url, baud=baud, device_baud=baud or DEFAULT_BAUD, config=cfg, name=name, log=log)
    if kind == "zmq" and rest:
        check_zmq_endpoint(rest, bind=server)
        return ZmqLink(
            rest,
            bind=server,
            keys=keys,
            insecure=insecure,
            peer_timeout=peer_timeout,
            connect_timeout=connect_timeout,
            name=name,
            log=log,
        )
    raise InputError(f"link spec must be serial:URL[@BAUD] or zmq:ENDPOINT, got {spec!r}")
