"""Open a link from a one-line spec, the form every command line and config uses.

``serial:PATH[@BAUD]``  a pyserial port (a pty slave path, a device, or ``loop://``);
                        BAUD paces writes to that line rate (a pty has none of its own).
``zmq:ENDPOINT``        a ZeroMQ endpoint, e.g. ``zmq:tcp://127.0.0.1:5555``; the
                        server side binds, the client connects.
"""

from __future__ import annotations

from protocol.errors import InputError

SERIAL_MAX_ATTEMPTS = 12


def open_link(spec: str, *, server: bool):
    from protocol.links import SerialLink, ZmqLink

    kind, _, rest = spec.partition(":")
    if kind == "serial" and rest:
        path, _, baud = rest.rpartition("@") if "@" in rest else (rest, "", "")
        if baud and not baud.isdigit():
            raise InputError(f"link spec {spec!r}: baud must be an integer")
        # HIL serial lines carry 0.3-3 MB results in one CRC-checked frame: on a noisy line a
        # few more attempts than the library default keep a run from losing whole pairs.
        return SerialLink(path, baud=int(baud) if baud else None, max_attempts=SERIAL_MAX_ATTEMPTS)
    if kind == "zmq" and rest:
        return ZmqLink(rest, bind=server)
    raise InputError(f"link spec must be serial:PATH[@BAUD] or zmq:ENDPOINT, got {spec!r}")
