"""How a reliability check reports: :class:`CheckResult` (behaviour, timing budgets, figures) and
the report ``make reliability`` writes (:func:`write_report`, ``bench/results/reliability.json``).

Each check is one test in ``tests/reliability/``: quick by default (``make test``, seconds), long
with ``--reliability-long`` or ``SAFEMIMIC_RELIABILITY=long`` (``make reliability``, the whole report
under 10 minutes). A test always holds its check to its behaviour; its timing budgets in the long
run always, in the quick run only where the test says (a deadline budget where
:func:`tests.support.machine.wake_latency` shows the machine keeps time; a restart budget never:
it is printed). A result is one line of the report: ``{"name", "passed", "behaved", "budgets",
figures...}``.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

from tests.support.machine import machine


@dataclass(frozen=True)
class CheckResult:
    """One named check: how the system behaved, its timing budgets, and the figures behind both.

    ``behaved`` is the behaviour the check is about (nothing crashed, nothing unsafe reached the
    robot, the service came back, the newest state was used, ...). ``budgets`` are the timing
    figures held to a bound (name → met), e.g. "resumed within 2 s" or "≥ 99 % of the deadlines
    kept": performance, which architecture §8 measures in reports, not in timed unit tests, because on a
    shared 2-core VM they move with the host (see :mod:`tests.support.machine`). ``passed``,
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


class Check(Protocol):
    """The ``check`` fixture: report ``result`` and hold it (behaviour always; budgets in the long
    run, and in the quick one where ``budgets`` is True)."""

    def __call__(self, result: CheckResult, *, budgets: bool = True) -> None: ...


def write_report(results: list[CheckResult], path: Path, *, long: bool, duration_s: float, all_tests_passed: bool) -> None:
    """Write ``{"checks": [...], "passed", "quick", "duration_s", "machine", "time"}`` to ``path``:
    passed when there are results, each passed, and no test failed (a check whose run raised has no result)."""
    report = {
        "checks": [result.to_json() for result in results],
        "passed": bool(results) and all(result.passed for result in results) and all_tests_passed,
        "quick": not long,
        "duration_s": round(duration_s, 1),
        "machine": machine(),
        "time": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(report, indent=2) + "\n")
