"""Error types shared by every package.

:class:`InputError` marks a problem with what the user or a peer supplied (a bad
file, a wrong image size, a NaN pose). The CLI prints it as one clear line
instead of a traceback; library callers can catch it like any ``ValueError``.
"""

from __future__ import annotations


class InputError(ValueError):
    """Bad input, with a message that names the problem and where it is."""


# Exit status of a flight process that ran out of memory (MemoryError or a failed
# allocation under RLIMIT_AS): the supervisor reports it as a memory-ceiling breach.
EXIT_MEMORY = 75
