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

import os
from pathlib import Path

from protocol.arq import ArqConfig
from protocol.errors import InputError

DEFAULT_BAUD = 921600
BAUD_MIN, BAUD_MAX = 50, 100_000_000  # a paced line's rates


def parse_serial(rest: str) -> tuple[str, int | None]:
    """``URL[@BAUD]`` -> (url, baud or None for unpaced)."""
    url, sep, baud = rest.rpartition("@")
    if not sep or not baud.isdigit():
        return rest, DEFAULT_BAUD
    if not url:
        raise InputError(f"serial link spec {rest!r} has no device")
    b = int(baud)
    if b and not BAUD_MIN <= b <= BAUD_MAX:
        raise InputError(f"serial baud must be 0 (unpaced) or in [{BAUD_MIN}, {BAUD_MAX:.0e}], got {b}")
    return url, (b or None)


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


def check_serial_device(device: str) -> None:
    """Refuse, before minutes of rendering, a serial device that cannot be this link: missing, not a character
    device (a regular file, a directory), or held by another process (our links lock their device). A
    pyserial URL (``socket://``, ``rfc2217://``, ``loop://``) passes: only opening it can tell."""
    import stat

    if "://" in device:
        return
    try:
        st = os.stat(device)
    except FileNotFoundError:
        raise InputError(f"no serial device {device} (is the board connected on this port?)") from None
    except OSError as exc:
        raise InputError(f"serial device {device}: {exc.strerror or exc}") from None
    if not stat.S_ISCHR(st.st_mode):
        what = "a directory, " if stat.S_ISDIR(st.st_mode) else "a regular file, " if stat.S_ISREG(st.st_mode) else ""
        raise InputError(f"{device} is not a serial device ({what}not a character device)")
    holder = _lock_holder(st)
    if holder is not None:
        raise InputError(f"serial device {device} is held by process {holder} (a ground or board still running on it?)")


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

    if peer_timeout is not None and not peer_timeout > 0:
        raise InputError(f"link timeout must be > 0 s, got {peer_timeout}")
    kind, _, rest = spec.partition(":")
    if kind == "serial" and rest:
        url, baud = parse_serial(rest)
        cfg = ArqConfig(peer_timeout=peer_timeout, connect_timeout=connect_timeout)
        return SerialLink(url, baud=baud, device_baud=baud or DEFAULT_BAUD, config=cfg, name=name, log=log)
    if kind == "zmq" and rest:
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
