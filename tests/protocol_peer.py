"""Child process for the two-process link tests: the 'flight' side of a descent.

usage: python tests/protocol_peer.py serial <port url> | zmq <endpoint> <key dir>

Receives Frames until an Error with code 'done' (reliable; a Heartbeat is not); answers each
Frame with a compact Result naming its seq (``grid_origin_xy[0]`` = the image's
mean, so content is checked end to end), then sends a Telemetry carrying its
link statistics and exits once the Telemetry is delivered.
"""

from __future__ import annotations

import sys

import numpy as np

from protocol.links import SerialLink, ZmqLink
from protocol.messages import Error, Frame, Hello, Result, Telemetry


def main() -> int:
    kind, where = sys.argv[1], sys.argv[2]
    link = (
        SerialLink(where, baud=None, name="peer")
        if kind == "serial"
        else ZmqLink(where, bind=False, keys=sys.argv[3], name="peer")
    )
    if not link.wait_established(60.0):
        return 4
    link.send(Hello(role="flight", session=link.session_id))  # the ground waits for this before streaming
    while True:
        msg = link.recv(timeout=60.0)
        if msg is None:
            return 3
        if isinstance(msg, Error) and msg.code == "done":
            break
        if isinstance(msg, Frame):
            grid = np.zeros((16, 16), np.uint8)
            link.send(
                Result(
                    frame_seqs=(msg.seq, msg.seq),
                    state_grid=grid,
                    psafe_grid=grid,
                    elevation_grid=np.zeros((16, 16), np.int16),
                    grid_origin_xy=(float(msg.image.mean()), 0.0),
                    grid_cell_m=1.0,
                    hazard_image=np.full(msg.image.shape, 0.5, np.float32),
                )
            )
    stats = link.stats
    mid = link.send(Telemetry(frame_seqs=(0, 0), link={k: float(v) for k, v in stats.items()}))
    link.flush(30.0)
    ok = link.outcome(mid) in ("delivered", "sent")
    link.close()
    return 0 if ok else 5


if __name__ == "__main__":
    sys.exit(main())
