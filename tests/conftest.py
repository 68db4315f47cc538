"""Fixtures the tests share; the helpers behind them are in ``tests/support/``."""

from __future__ import annotations

import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.support.processes import Proc


def pytest_addoption(parser: pytest.Parser) -> None:
    """The reliability checks' options (``tests/reliability/``; ``make reliability`` passes both)."""
    group = parser.getgroup("reliability", "reliability checks (tests/reliability)")
    group.addoption("--reliability-long", action="store_true",
                    help="run each reliability check's long variant and hold every timing budget "
                         "(also SAFEMIMIC_RELIABILITY=long)")
    group.addoption("--reliability-report", metavar="PATH", type=Path,
                    help="write the checks' results as JSON to PATH at the end (make reliability: "
                         "bench/results/reliability.json)")


@pytest.fixture
def spawn(tmp_path_factory: pytest.TempPathFactory) -> Iterator:
    """Start processes that are terminated at the end of the test. Their temporary files (``$TMPDIR``:
    e.g. the run folders ``safemimic demo`` keeps for its logs) go to the test's own temporary
    folder, which pytest removes, not to the machine's ``/tmp``."""
    procs: list[Proc] = []
    scratch = str(tmp_path_factory.mktemp("spawned"))

    def start(*args: str, env: dict[str, str] | None = None) -> Proc:
        proc = Proc([sys.executable, *args], {"TMPDIR": scratch, **(env or {})})
        procs.append(proc)
        return proc

    yield start
    for proc in procs:
        proc.stop()
