"""Child process for the two-process link tests: the 'flight' side of a descent.

usage: python tests/protocol_peer.py serial <slave_path> | zmq <endpoint>

Receives Frames until a Heartbeat with counter == 0xFFFF ('done'); answers each
Frame with a Result naming its seq (hazard grid filled with the mean of the
image, so content is checked end to end), then sends a Telemetry carrying its
link statistics and exits after the sender has acknowledged it.
"""

from __future__ import annotations

import sys

import numpy as np

from protocol.links import SerialLink, ZmqLink
from protocol.messages import Frame, Heartbeat, Hello, Result, Telemetry


def main() -> int:
    kind, where = sys.argv[1], sys.argv[2]
    link = (
        SerialLink(where, ack_timeout=0.3, max_attempts=20, name="peer")
        if kind == "serial"
        else ZmqLink(where, bind=False, name="peer")
    )
    link.send(Hello(role="flight"))  # handshake: the ground waits for this before streaming
    prev = None
    while True:
        msg = link.recv(timeout=60.0)
        if msg is None:
            return 3
        if isinstance(msg, Heartbeat) and msg.counter == 0xFFFF:
            break
        if isinstance(msg, Frame):
            level = float(msg.image.mean())
            grid = np.full((16, 16), level, np.float32)
            link.send(
                Result(
                    frame_seqs=(prev if prev is not None else msg.seq, msg.seq),
                    hazard_grid=grid,
                    elevation_grid=grid,
                    grid_origin_xy=(0.0, 0.0),
                    grid_cell_m=1.0,
                    hazard_image=np.full(msg.image.shape, level, np.float32),
                )
            )
            prev = msg.seq
    stats = link.stats
    link.send(Telemetry(frame_seqs=(0, 0), link={k: v for k, v in stats.items()}))
    link.flush(30.0)
    link.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
