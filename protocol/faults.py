"""Link fault injection and pty plumbing.

* :class:`CorruptingChannel` - seeded per-byte drop / bit-flip / duplicate.
* :func:`open_pty_pair` - one raw pty: ``(master_fd, slave_path)``.
* :class:`ByteRelay` - copy bytes fd -> fd in a thread, optionally through a channel.
* :class:`PtyBridge` - two raw ptys joined by relays (what ``socat pty,raw pty,raw``
  does), so two processes can each open a :class:`protocol.links.SerialLink`
  on ``bridge.paths[0]`` / ``bridge.paths[1]``, with corruption in the middle.
"""

from __future__ import annotations

import errno
import os
import select
import threading
import tty

import numpy as np

from protocol.errors import InputError


class CorruptingChannel:
    """Per-byte faults with probabilities ``drop``, ``flip`` (one random bit) and ``dup``.

    The random stream depends only on ``seed`` and the byte count, not on how
    the bytes are chunked, so a run is reproducible for a given byte sequence.
    """

    def __init__(self, seed: int, drop: float = 0.0, flip: float = 0.0, dup: float = 0.0) -> None:
        for name, p in (("drop", drop), ("flip", flip), ("dup", dup)):
            if not 0.0 <= p <= 1.0:
                raise InputError(f"CorruptingChannel: {name} rate must be in [0, 1], got {p}")
        self.rates = (drop, flip, dup)
        self._rng = np.random.default_rng(seed)
        self._lock = threading.Lock()
        self.stats = {"bytes_in": 0, "dropped": 0, "flipped": 0, "duplicated": 0}

    def apply(self, data: bytes) -> bytes:
        if not data:
            return data
        drop, flip, dup = self.rates
        with self._lock:
            u = self._rng.random((len(data), 3))
            bits = self._rng.integers(0, 8, len(data))
        arr = np.frombuffer(data, np.uint8).copy()
        flipped = u[:, 1] < flip
        arr[flipped] ^= np.uint8(1) << bits[flipped].astype(np.uint8)
        dropped = u[:, 0] < drop
        duplicated = (u[:, 2] < dup) & ~dropped
        counts = 1 - dropped.astype(np.int64) + duplicated
        self.stats["bytes_in"] += len(data)
        self.stats["dropped"] += int(dropped.sum())
        self.stats["flipped"] += int(flipped.sum())
        self.stats["duplicated"] += int(duplicated.sum())
        return np.repeat(arr, counts).tobytes()


def open_pty_pair() -> tuple[int, str]:
    """Open a pty in raw mode; returns ``(master_fd, slave_path)``.

    The slave is set raw (no echo, no line editing, no CR/LF mapping) before
    its fd is closed; another process opens ``slave_path`` (pyserial also
    re-applies raw mode). Until the slave is open, reads on the master fail
    with EIO - :class:`protocol.links.StreamLink` tolerates that.
    """
    master, slave = os.openpty()
    tty.setraw(slave)
    path = os.ttyname(slave)
    os.close(slave)
    return master, path


class ByteRelay:
    """Copy bytes from ``src_fd`` to ``dst_fd`` in a daemon thread, through ``channel`` if given; with ``cores``
    the thread runs on those host cores (``cores_used``: the ones it runs on, read back once it has started)."""

    def __init__(
        self, src_fd: int, dst_fd: int, channel: CorruptingChannel | None = None, cores: frozenset[int] = frozenset()
    ) -> None:
        self.src, self.dst, self.channel = src_fd, dst_fd, channel
        self.bytes_relayed = 0
        self.cores_used: list[int] | None = None
        self._started = threading.Event()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, args=(cores,), name="byte-relay", daemon=True)
        self._thread.start()
        self._started.wait(5.0)

    def _run(self, cores: frozenset[int]) -> None:
        try:
            if cores and hasattr(os, "sched_setaffinity"):
                os.sched_setaffinity(0, cores)  # 0: this thread alone
            self.cores_used = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None
        finally:
            self._started.set()
        while not self._stop.is_set():
            try:
                r, _, _ = select.select([self.src], [], [], 0.05)
                if not r:
                    continue
                data = os.read(self.src, 1 << 16)
            except OSError as exc:
                if exc.errno in (errno.EIO, errno.EBADF) and not self._stop.is_set():
                    self._stop.wait(0.02)  # slave side not open yet, or just closed
                    continue
                return
            if not data:
                return
            if self.channel is not None:
                data = self.channel.apply(data)
            mv = memoryview(data)
            try:
                while mv:
                    mv = mv[os.write(self.dst, mv) :]
            except OSError:
                if self._stop.is_set():
                    return
            self.bytes_relayed += len(data)

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=1.0)


class PtyBridge:
    """Two raw ptys whose masters are relayed to each other (optionally corrupted per direction; the relay threads
    on ``cores`` if given, see :class:`ByteRelay`).

    ``paths = (slave_a, slave_b)``. The slaves are kept open here (never read)
    so the masters do not see EIO while the peers come and go.
    """

    def __init__(
        self,
        a_to_b: CorruptingChannel | None = None,
        b_to_a: CorruptingChannel | None = None,
        *,
        cores: frozenset[int] = frozenset(),
    ) -> None:
        self._fds: list[int] = []
        paths = []
        for _ in range(2):
            master, slave = os.openpty()
            tty.setraw(slave)
            paths.append(os.ttyname(slave))
            self._fds += [master, slave]
        self.paths: tuple[str, str] = (paths[0], paths[1])
        m_a, m_b = self._fds[0], self._fds[2]
        self.relays = (ByteRelay(m_a, m_b, a_to_b, cores), ByteRelay(m_b, m_a, b_to_a, cores))

    def close(self) -> None:
        """Stop the relays and close the ptys; again is a no-op. A second close closed the same descriptor numbers
        again, by then another file's (a font matplotlib was reading: "Illegal seek", and no report page)."""
        for r in self.relays:
            r.stop()
        fds, self._fds = self._fds, []
        for fd in fds:
            try:
                os.close(fd)
            except OSError:
                pass

    def __enter__(self) -> PtyBridge:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
