"""pytest plugin: latency/deadline regression checks inside a user's own test suite.

Installed with the package (entry point ``pytest11``), it adds the option
``--hil-baseline FILE`` and the fixture ``hil_regression``::

    def test_flight_software_keeps_its_deadlines(hil_regression):
        hil_regression(cases=["vertical-snapdragon-serial"])   # fails with the diff table

The fixture runs the cases of the baseline (see :mod:`hil_server.regress`) and
fails the test with the readable diff when any case regresses.
"""

from __future__ import annotations

from pathlib import Path

import pytest


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption("--hil-baseline", default=None, help="hazard-hil latency baseline for the hil_regression fixture")


@pytest.fixture
def hil_regression(request: pytest.FixtureRequest, tmp_path: Path):
    def check(baseline: str | Path | None = None, cases: list[str] | None = None) -> str:
        from hil_server.regress import check_regression, default_baseline_path

        path = Path(baseline or request.config.getoption("--hil-baseline") or default_baseline_path())
        if not path.is_file():
            pytest.fail(f"no latency baseline at {path} (create it with `hazard-hil regress --update`)", pytrace=False)
        ok, diff, _ = check_regression(path, out=tmp_path / "regress", cases=cases)
        if not ok:
            pytest.fail("latency regression:\n" + diff, pytrace=False)
        return diff

    return check
