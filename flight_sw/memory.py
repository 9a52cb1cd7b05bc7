"""The flight process's own memory, as the HIL watchdog reads it from outside (:mod:`hil_server.procemu`).

A board running ``hazard-hil flight`` reports its private RSS peak in each Telemetry (``peak_rss_bytes``) with the same
reader, so a board run's report shows its memory; under the HIL server the watchdog's own reading replaces it.
"""

from __future__ import annotations

_MEM_FIELDS = (b"VmHWM", b"RssAnon", b"RssFile", b"RssShmem")  # /proc/PID/status keys the watchdog reads


def private_rss_bytes(pid: int | str = "self") -> tuple[int, int] | None:
    """(private RSS, private RSS peak estimate) in bytes from /proc/PID/status (``"self"``: this process); None once
    the process is gone, or where there is no /proc (a board that is not Linux).

    Private RSS = ``RssAnon + RssShmem``: the memory the flight software itself holds. File-backed
    pages (``RssFile``: the mapped code of Python, numpy, OpenCV) are left out because how many of
    them count as resident depends on the host's page cache, not on the flight software: the same
    ``import cv2`` is 25 MiB of RssFile from a long-cached install and 53 MiB from one just written
    (large page-cache folios are mapped whole). A flight computer's code lives in its own memory.

    The kernel keeps no private high-water mark, so the peak is estimated as
    ``max(private, VmHWM - RssFile)``: with RssFile non-decreasing this never exceeds the true
    private peak, and it catches a peak between two polls. (wait4's ru_maxrss is not used: after
    fork+exec it still holds the parent's RSS at fork.)
    """
    fields = _proc_kib(f"/proc/{pid}/status", _MEM_FIELDS)
    if fields is None or b"RssAnon" not in fields:
        return None  # zombie: no memory map left
    private = fields[b"RssAnon"] + fields.get(b"RssShmem", 0)
    return private, max(private, fields.get(b"VmHWM", 0) - fields.get(b"RssFile", 0))


_PSS_FIELDS = (b"Pss_Anon", b"Pss_Shmem")


def proportional_private_bytes(pid: int) -> int | None:
    """Private memory of ``pid`` with every page it shares with another process counted in proportion
    (``Pss_Anon + Pss_Shmem`` of ``/proc/PID/smaps_rollup``); None once the process is gone, or where the kernel
    gives no such split (before Linux 5.x; not Linux).

    Summed over a process tree it counts each page once. A forked child's ``RssAnon`` holds every page it still
    shares with its parent (copy-on-write), so a sum of ``RssAnon`` counted those pages twice.
    """
    fields = _proc_kib(f"/proc/{pid}/smaps_rollup", _PSS_FIELDS)
    if fields is None or b"Pss_Anon" not in fields:
        return None
    return fields[b"Pss_Anon"] + fields.get(b"Pss_Shmem", 0)


def _proc_kib(path: str, keys: tuple[bytes, ...]) -> dict[bytes, int] | None:
    """``keys`` of a ``/proc`` file of ``Key:  N kB`` lines, in bytes (read up to the last of them); None when the
    file cannot be read (the process is gone)."""
    fields: dict[bytes, int] = {}
    try:
        with open(path, "rb") as fh:
            for line in fh:
                key = line.split(b":", 1)[0]
                if key in keys:
                    fields[key] = int(line.split()[1]) * 1024
                    if len(fields) == len(keys):
                        break
    except (OSError, ValueError):
        return None
    return fields
