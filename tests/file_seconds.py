"""Refresh ``tests/file_seconds.json``, the seconds each test file took, which tests/conftest.py uses to hand the
longest files to the workers first.

    .venv/bin/python -m pytest -q -n 4 --dist loadfile --durations=0 | .venv/bin/python tests/file_seconds.py

It reads pytest's ``--durations=0`` lines (``12.34s call     tests/test_x.py::test_y``) from standard input and
sums setup, call and teardown per file. A file missing from the table is weighed by its count of tests.
"""

from __future__ import annotations

import json
import re
import sys
from collections import Counter, defaultdict
from pathlib import Path

LINE = re.compile(r"^\s*([0-9.]+)s (?:setup|call|teardown)\s+(tests/[^:\s]+\.py)::")
TABLE = Path(__file__).with_name("file_seconds.json")


def file_seconds(lines: list[str]) -> dict[str, float]:
    """Seconds per test file, summed over the ``--durations`` lines that name one."""
    out: dict[str, float] = defaultdict(float)
    for line in lines:
        if m := LINE.match(line):
            out[m.group(2)] += float(m.group(1))
    return dict(out)


def longest_first(nodeids: list[str], seconds: dict[str, float], per_test: float = 0.9) -> list[int]:
    """Indices of ``nodeids`` with their files in order of ``seconds`` (longest first; a file not in it weighs
    ``per_test`` seconds per test), each file's tests in their own order: the longest-processing-time-first
    rule for the workers' queue."""
    files = [n.split("::", 1)[0] for n in nodeids]
    counts = Counter(files)
    weight = {f: float(seconds.get(f, per_test * n)) for f, n in counts.items()}
    return sorted(range(len(nodeids)), key=lambda i: (-weight[files[i]], files[i], i))


def main() -> int:
    seconds = file_seconds(sys.stdin.read().splitlines())
    if not seconds:
        print("file_seconds.py: no '--durations=0' lines on standard input", file=sys.stderr)
        return 2
    TABLE.write_text(json.dumps({k: round(v, 1) for k, v in sorted(seconds.items())}, indent=0) + "\n")
    print(f"file_seconds.py: {len(seconds)} files, {sum(seconds.values()):.0f} s, written to {TABLE}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
