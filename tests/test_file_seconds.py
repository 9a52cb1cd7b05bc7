"""The workers' queue: test files longest first (tests/file_seconds.py, tests/conftest.py)."""

from __future__ import annotations

import json
from pathlib import Path

from file_seconds import TABLE, file_seconds, longest_first

TESTS = Path(__file__).parent


def test_durations_lines_are_summed_per_file():
    lines = [
        "============ slowest durations ============",
        "12.50s call     tests/test_a.py::test_one[x-1]",
        "0.50s setup    tests/test_a.py::test_one[x-1]",
        "3.00s teardown tests/test_b.py::TestK::test_two",
        "(7 durations < 0.005s hidden.)",
    ]
    assert file_seconds(lines) == {"tests/test_a.py": 13.0, "tests/test_b.py": 3.0}


def test_the_longest_file_goes_first_and_a_files_tests_keep_their_order():
    ids = ["tests/test_a.py::t1", "tests/test_a.py::t2", "tests/test_b.py::t1", "tests/test_new.py::t1"]
    ids += [f"tests/test_new.py::t{k}" for k in range(2, 7)]
    # test_new.py is not in the table: 6 tests at 0.9 s weigh 5.4 s, between a (2 s) and b (60 s)
    order = longest_first(ids, {"tests/test_a.py": 2.0, "tests/test_b.py": 60.0})
    assert [ids[i] for i in order][:2] == ["tests/test_b.py::t1", "tests/test_new.py::t1"]
    assert [ids[i] for i in order][-2:] == ["tests/test_a.py::t1", "tests/test_a.py::t2"]
    assert sorted(order) == list(range(len(ids)))


def test_the_table_names_only_test_files_that_exist():
    table = json.loads(TABLE.read_text())
    stale = [f for f in table if not (TESTS.parent / f).is_file()]
    assert not stale, f"tests/file_seconds.json names files that are gone: {stale}; refresh it (tests/file_seconds.py)"
    assert all(v >= 0 for v in table.values())
