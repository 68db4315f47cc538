"""Reliability checks (``make reliability``): watchdogs, rate limits, faults, fuzzed input, load.

Each check module provides ``run(quick: bool = False) -> list[CheckResult]``. ``quick`` is the
bounded variant ``make test`` runs (seconds); the full variant is what ``make reliability`` runs
(the whole report stays under 10 minutes). A result is one line of ``bench/results/reliability.json``:
``{"name", "passed", figures...}``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any


@dataclass(frozen=True)
class CheckResult:
    """One named check: whether it passed, the figures that decided it, and why when it failed."""

    name: str
    passed: bool
    figures: dict[str, Any] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        """``{"name", "passed", **figures}`` (figures must be JSON-ready)."""
        return {"name": self.name, "passed": bool(self.passed), **self.figures}

    def __str__(self) -> str:
        shown = ", ".join(f"{k}={v}" for k, v in self.figures.items())
        return f"{'PASS' if self.passed else 'FAIL'} {self.name}: {shown}"
