"""pytest plugin: latency/deadline regression checks inside a user's own test suite.

Installed with the package (entry point ``pytest11``), it adds the option
``--hil-baseline FILE`` and the fixture ``hil_regression``::

    def test_flight_software_keeps_its_deadlines(hil_regression):
        hil_regression(cases=["vertical-snapdragon-serial"])   # fails with the diff table

``hil_regression(baseline=None, cases=None, min_hit_rate=None, link=None, hello_timeout_s=None,
uncalibrated=False, figures=False)`` runs the cases of the baseline (``baseline``, else ``--hil-baseline``, else the
shipped one; see :mod:`hil_server.regress`), as ``hazard-hil regress --no-figures`` does with the same options, and
returns the diff table.
It fails the test with that table when any case regresses, and with one line on bad usage (an unknown case, a
malformed baseline, a host never calibrated: run ``hazard-hil calibrate`` in the job first), as the command's
exit 2 does.
"""

from __future__ import annotations

from pathlib import Path

import pytest


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption("--hil-baseline", default=None, help="hazard-hil latency baseline for the hil_regression fixture")


@pytest.fixture
def hil_regression(request: pytest.FixtureRequest, tmp_path: Path):
    """``check(baseline=None, cases=None, min_hit_rate=None, link=None, hello_timeout_s=None, uncalibrated=False,
    figures=False) -> diff``: run the baseline's cases (all, or ``cases``, a list of names); fail the test with the
    diff when one regresses. The cases' report pages are drawn without pictures unless ``figures``: a test reads
    the verdict, and the pictures cost about 1 s per pair."""

    def check(
        baseline: str | Path | None = None,
        cases: list[str] | None = None,
        min_hit_rate: float | None = None,
        link: str | None = None,
        hello_timeout_s: float | None = None,
        uncalibrated: bool = False,
        figures: bool = False,
    ) -> str:
        from hil_server.regress import RegressInterrupted, check_regression, default_baseline_path
        from protocol.errors import InputError

        if isinstance(cases, str):  # a lone name was split into its letters
            pytest.fail(f"hil_regression(cases=...) takes a list of case names, got the string {cases!r}", False)
        path = Path(baseline or request.config.getoption("--hil-baseline") or default_baseline_path())
        if not path.is_file():
            pytest.fail(f"no latency baseline at {path} (create it with `hazard-hil regress --update`)", pytrace=False)
        bad: str | None = None
        try:
            ok, diff, _ = check_regression(
                path,
                out=tmp_path / "regress",
                cases=cases,
                min_hit_rate=min_hit_rate,
                board_link=link,
                hello_timeout_s=hello_timeout_s,
                uncalibrated=uncalibrated,
                figures=figures,
            )
        except InputError as exc:  # bad usage: one line, not a traceback from inside the library
            bad = f"hil_regression: {exc}"
        except RegressInterrupted as exc:  # Ctrl-C or a cancelled job stops the session, not this test alone
            pytest.exit(f"hil_regression: {exc}", returncode=128 + exc.signum)
        if bad is not None:  # failed outside the except: its message once, not twice with "During handling ..."
            pytest.fail(bad, pytrace=False)
        if not ok:  # a slower case, a missed deadline, or a run that did not finish (the table says which)
            pytest.fail("HIL regression:\n" + diff, pytrace=False)
        return diff

    return check
