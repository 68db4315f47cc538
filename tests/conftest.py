"""Fixtures the tests share; the helpers behind them are in ``tests/support/``."""

from __future__ import annotations

import sys
from collections.abc import Iterator

import pytest

from tests.support.processes import Proc


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
