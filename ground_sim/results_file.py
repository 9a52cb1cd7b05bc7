"""The ground's ``results.jsonl``: one JSON object per line, one line per pair, appended by
:func:`ground_sim.stream.run_ground` (one ``write`` per pair, :func:`append_records`) and read by the HIL run's summary
and by `hazard-hil score`. The run reads its other JSON-lines files (the HIL server's ``supervisor.jsonl``,
the ground's one-line ``ground.json``) the same lenient way.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterable
from pathlib import Path


def append_records(path: str | Path, records: Iterable[dict]) -> int:
    """Append ``records`` to ``path`` as JSON lines in one ``write`` (``O_APPEND``) and return the bytes written.

    A descent's records only ever grow, so the file is appended rather than rewritten after each pair: rewriting
    it whole wrote O(n^2) bytes over a long descent (200 pairs: ~110 MB for a 1.1 MB file, stop 63's soak QA).
    One ``write`` to a regular file is not split by a signal, so a reader sees whole lines; should the disk fill
    mid-line, the lenient reader skips the torn line and the strict one names it.
    """
    data = "".join(json.dumps(r, sort_keys=True) + "\n" for r in records).encode()
    if not data:
        return 0
    fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o666)
    try:
        view = memoryview(data)
        while view:  # a short write (a full disk) raises from the next call rather than losing the tail silently
            view = view[os.write(fd, view) :]
    finally:
        os.close(fd)
    return len(data)


def read_results(path: str | Path, *, strict: bool = True) -> list[dict]:
    """The records of ``path``, in order.

    ``strict``: a line that is not a JSON object raises ``ValueError`` naming the file and the line (a file given
    by a user that is no HIL run's). Otherwise such a line is skipped (the run's own file: a torn last line, left
    only by a disk that filled mid-write, does not cost the summary the pairs before it), and a missing file is
    none.
    """
    p = Path(path)
    if not strict and not p.is_file():
        return []
    out = []
    text = p.read_text(errors="strict" if strict else "replace")
    for n, line in enumerate(text.splitlines(), 1):
        if not line.strip():
            continue
        try:
            r = json.loads(line)
            if not isinstance(r, dict):
                raise ValueError(f"a record is a {type(r).__name__}, not an object")
        except RecursionError:  # json's parser recurses once per nested list or object
            if strict:
                raise ValueError(f"{p}: line {n}: JSON nested too deeply") from None
            continue
        except ValueError as exc:
            if strict:
                raise ValueError(f"{p}: line {n}: {exc}") from None
            continue
        out.append(r)
    return out
