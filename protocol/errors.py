"""Error types shared by every package.

:class:`InputError` marks a problem with what the user or a peer supplied (a bad
file, a wrong image size, a NaN pose). The CLI prints it as one clear line
instead of a traceback; library callers can catch it like any ``ValueError``.
"""

from __future__ import annotations

import errno


class InputError(ValueError):
    """Bad input, with a message that names the problem and where it is."""


# Exit status of a flight process that ran out of memory (MemoryError or a failed
# allocation under RLIMIT_AS): the supervisor reports it as a memory-ceiling breach.
EXIT_MEMORY = 75


def comma_items(text: str, option: str) -> list[str]:
    """The stripped items of a comma-separated option value (``""`` or ``","``: none).

    An empty item (two commas in a row, or a comma at either end) is refused rather than skipped: ``1,,2`` is
    more likely a value lost in typing than a list of two.
    """
    items = [s.strip() for s in text.split(",")]
    if not any(items):  # "" or ",": no items, which the caller names
        return []
    if not all(items):
        raise InputError(f"{option}: an empty item in {text!r} (two commas in a row, or a comma at an end)")
    return items


# errors only a write meets: said as "cannot write X", whatever verb the caller chose
_WRITE_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EFBIG})


def os_error_text(exc: OSError, verb: str = "use") -> str:
    """One line for an OSError the system raised: the file and its reason (``cannot write X: No space left on
    device``), not Python's ``[Errno 28]`` form."""
    if exc.errno in _WRITE_ERRNOS:
        verb = "write"
    where = " and ".join(str(f) for f in (exc.filename, exc.filename2) if f is not None)
    why = exc.strerror or str(exc) or type(exc).__name__
    return f"cannot {verb} {where}: {why}" if where else why
