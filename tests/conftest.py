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
def spawn() -> Iterator:
    """Start processes that are terminated at the end of the test."""
    procs: list[Proc] = []

    def start(*args: str, env: dict[str, str] | None = None) -> Proc:
        proc = Proc([sys.executable, *args], env)
        procs.append(proc)
        return proc

    yield start
    for proc in procs:
        proc.stop()
