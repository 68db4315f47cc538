"""Reliability checks (``make reliability``): watchdogs, rate limits, faults, fuzzed input, load.

Each check module provides ``run(quick: bool = False) -> list[CheckResult]``. ``quick`` is the
bounded variant ``make test`` runs (seconds); the full variant is what ``make reliability`` runs
(the whole report stays under 10 minutes). A result is one line of ``bench/results/reliability.json``:
``{"name", "passed", "behaved", "budgets", figures...}``. ``make test`` holds every check to its
behaviour; the timing budgets it holds only where the machine can keep time (a deadline budget
when :func:`bench.reliability.machine.wake_latency` shows timely wake-ups), and prints them always.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any


@dataclass(frozen=True)
class CheckResult:
    """One named check: how the system behaved, its timing budgets, and the figures behind both.

    ``behaved`` is the behaviour the check is about (nothing crashed, nothing unsafe reached the
    robot, the service came back, the newest state was used, ...). ``budgets`` are the timing
    figures held to a bound (name → met), e.g. "resumed within 2 s" or "≥ 99 % of the deadlines
    kept": performance, which architecture §8 measures in reports, not in timed unit tests, because on a
    shared 2-core VM they move with the host (see :mod:`bench.reliability.machine`). ``passed``,
    the verdict ``make reliability`` reports and exits on, needs both.
    """

    name: str
    behaved: bool
    figures: dict[str, Any] = field(default_factory=dict)
    budgets: dict[str, bool] = field(default_factory=dict)

    @property
    def passed(self) -> bool:
        """The behaviour and every budget."""
        return self.behaved and all(self.budgets.values())

    def to_json(self) -> dict[str, Any]:
        """``{"name", "passed", "behaved", "budgets", **figures}`` (figures must be JSON-ready)."""
        return {"name": self.name, "passed": bool(self.passed), "behaved": bool(self.behaved),
                "budgets": {k: bool(v) for k, v in self.budgets.items()}, **self.figures}

    def __str__(self) -> str:
        shown = ", ".join(f"{k}={v}" for k, v in self.figures.items())
        missed = [name for name, met in self.budgets.items() if not met]
        verdict = "PASS" if self.passed else "FAIL" if not self.behaved else f"BUDGET MISSED ({', '.join(missed)})"
        return f"{verdict} {self.name}: {shown}"
