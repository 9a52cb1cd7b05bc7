"""The ground's results.jsonl, read strictly (a user's file for `score`) or leniently (the run's own)."""

from __future__ import annotations

import pytest

from ground_sim.results_file import read_results


def test_strict_reading_names_the_bad_line_and_lenient_reading_keeps_the_rest(tmp_path):
    p = tmp_path / "results.jsonl"
    p.write_text('{"pair_id": "600_300"}\n\n[1, 2]\n{"pair_id": "300_150"}\n{"torn": \n')
    with pytest.raises(ValueError, match=r"line 3: a record is a list, not an object"):
        read_results(p)
    assert [r["pair_id"] for r in read_results(p, strict=False)] == ["600_300", "300_150"]
    assert read_results(tmp_path / "missing.jsonl", strict=False) == []
    with pytest.raises(OSError):
        read_results(tmp_path / "missing.jsonl")
    deep = tmp_path / "deep.jsonl"
    deep.write_text("[" * 100000 + "]" * 100000 + "\n")
    with pytest.raises(ValueError, match=r"nested too deeply|not an object"):
        read_results(deep)
