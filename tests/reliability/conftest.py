"""The reliability checks' variant (quick or long), the ``check`` fixture every test reports its
result through, and the report written at the end when ``--reliability-report PATH`` is given."""

from __future__ import annotations

import os
import time

import pytest

from tests.reliability.check import Check, CheckResult, write_report

#: The results reported so far in this session, in the order the checks ran.
RESULTS = pytest.StashKey[list[CheckResult]]()
STARTED = pytest.StashKey[float]()
#: ``SAFEMIMIC_RELIABILITY=long`` selects the long variant like ``--reliability-long``.
LONG_ENV = "SAFEMIMIC_RELIABILITY"


def is_long(config: pytest.Config) -> bool:
    """Whether this session runs the long variant (``make reliability``)."""
    return bool(config.getoption("reliability_long")) or os.environ.get(LONG_ENV) == "long"


def pytest_configure(config: pytest.Config) -> None:
    """A fresh result list and the start time (pytest calls this hook for a conftest loaded only at
    collection too, e.g. under ``make test``'s ``pytest`` from the top)."""
    config.stash[RESULTS] = []
    config.stash[STARTED] = time.monotonic()


@pytest.fixture(scope="session")
def long_run(pytestconfig: pytest.Config) -> bool:
    """True in the long variant (``--reliability-long``), False in the quick one (``make test``)."""
    return is_long(pytestconfig)


@pytest.fixture
def check(pytestconfig: pytest.Config) -> Check:
    """``check(result, budgets=True)``: add ``result`` to the report, print it, and fail the test
    unless it behaved and, where budgets are held, met every budget. The long variant holds every
    budget whatever ``budgets`` says; the quick one only where the test passes ``budgets=True``
    (a deadline budget where the machine keeps time, never a restart budget)."""
    results = pytestconfig.stash[RESULTS]
    long = is_long(pytestconfig)

    def hold(result: CheckResult, *, budgets: bool = True) -> None:
        results.append(result)
        print(f"\n  {result}")
        assert result.behaved, str(result)
        if long or budgets:
            assert result.passed, str(result)

    return hold


def pytest_sessionfinish(session: pytest.Session, exitstatus: int) -> None:
    """Write the report (``--reliability-report PATH``) of the checks that ran."""
    path = session.config.getoption("reliability_report")
    if path is None:
        return
    write_report(session.config.stash[RESULTS], path, long=is_long(session.config),
                 duration_s=time.monotonic() - session.config.stash[STARTED],
                 all_tests_passed=session.testsfailed == 0 and exitstatus == 0)
    print(f"\nwrote {path}")
