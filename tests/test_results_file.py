"""The ground's results.jsonl, read strictly (a user's file for `score`) or leniently (the run's own)."""

from __future__ import annotations

import pytest

from ground_sim.results_file import append_records, read_results


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


def test_records_are_appended_as_whole_lines_and_nothing_is_written_for_none(tmp_path):
    p = tmp_path / "results.jsonl"
    assert append_records(p, []) == 0 and not p.exists()
    n = append_records(p, [{"pair_id": "600_300"}])
    n += append_records(p, ({"pair_id": x} for x in ("300_150", "200_100")))
    assert n == p.stat().st_size
    assert [r["pair_id"] for r in read_results(p)] == ["600_300", "300_150", "200_100"]
