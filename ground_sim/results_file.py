"""The ground's ``results.jsonl``: one JSON object per line, one line per pair, written by
:func:`ground_sim.stream.run_ground` (atomically, the whole file at a time) and read by the HIL run's summary
and by `hazard-hil score`. The run reads its other JSON-lines files (the HIL server's ``supervisor.jsonl``,
the ground's one-line ``ground.json``) the same lenient way.
"""

from __future__ import annotations

import json
from pathlib import Path


def read_results(path: str | Path, *, strict: bool = True) -> list[dict]:
    """The records of ``path``, in order.

    ``strict``: a line that is not a JSON object raises ``ValueError`` naming the file and the line (a file given
    by a user that is no HIL run's). Otherwise such a line is skipped (the run's own file: a torn last line,
    impossible with atomic writes, would not cost the summary the pairs before it), and a missing file is none.
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
