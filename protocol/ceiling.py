"""A memory ceiling for a link endpoint process (the HIL supervisor, the ground streamer).

The codec bounds what one message may cost (:mod:`protocol.codec`); this is the
backstop for everything else: ``RLIMIT_AS`` is set to the process's address
space at the time of the call (interpreter, numpy, OpenCV, libzmq already
loaded) plus ``extra_mib``, so an allocation beyond it fails with
``MemoryError`` in this process instead of exhausting the host.
"""

from __future__ import annotations

import resource

from protocol.errors import InputError

MIB = 1 << 20


def address_space_bytes() -> int:
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith("VmSize:"):
                return int(line.split()[1]) * 1024
    raise OSError("VmSize not in /proc/self/status")


def apply_memory_ceiling(extra_mib: float) -> int:
    """Limit this process's address space to its current size + ``extra_mib``; returns the limit (bytes)."""
    if not extra_mib > 0:
        raise InputError(f"memory ceiling headroom must be > 0 MiB, got {extra_mib}")
    limit = address_space_bytes() + int(extra_mib * MIB)
    _, hard = resource.getrlimit(resource.RLIMIT_AS)
    if hard != resource.RLIM_INFINITY:
        limit = min(limit, hard)
    resource.setrlimit(resource.RLIMIT_AS, (limit, hard))
    return limit
