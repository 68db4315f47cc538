"""How a reliability check reports: behaviour and timing budgets, the report ``make reliability``
writes, and the machine's wake-up probe."""

from __future__ import annotations

import json
from pathlib import Path

from tests.reliability.check import CheckResult, write_report
from tests.support.machine import (
    STEAL_MAX_PCT, WAKE_MAX_MS, WAKE_P99_MAX_MS, cpu_times, host_kept_cpu, steal_pct, wake_latency,
)


def test_a_check_passes_only_when_it_behaved_and_met_every_budget() -> None:
    fine = CheckResult("kill9_safety", True, {"max_resume_s": 1.2}, {"resume_within_2s": True})
    slow = CheckResult("kill9_safety", True, {"max_resume_s": 2.4}, {"resume_within_2s": False})
    broken = CheckResult("kill9_safety", False, {"max_resume_s": None}, {"resume_within_2s": False})
    no_budget = CheckResult("fuzz_codec", True, {"messages": 10})
    assert fine.passed and no_budget.passed
    assert not slow.passed and slow.behaved
    assert not broken.passed and not broken.behaved
    assert str(fine).startswith("PASS kill9_safety")
    assert str(slow).startswith("BUDGET MISSED (resume_within_2s) kill9_safety")
    assert str(broken).startswith("FAIL kill9_safety")
    row = json.loads(json.dumps(slow.to_json()))
    assert row == {"name": "kill9_safety", "passed": False, "behaved": True,
                   "budgets": {"resume_within_2s": False}, "max_resume_s": 2.4}


def test_the_report_lists_every_check_and_passes_only_when_all_did(tmp_path: Path) -> None:
    fine = CheckResult("fuzz_codec", True, {"messages": 10})
    slow = CheckResult("kill9_safety", True, {"max_resume_s": 2.4}, {"resume_within_2s": False})
    path = tmp_path / "results" / "reliability.json"
    write_report([fine], path, long=True, duration_s=12.34, all_tests_passed=True)
    report = json.loads(path.read_text())
    assert set(report) == {"checks", "passed", "quick", "duration_s", "machine", "time"}
    assert report["checks"] == [fine.to_json()] and report["passed"] and not report["quick"]
    assert report["duration_s"] == 12.3 and report["machine"]["cores"]
    write_report([fine, slow], path, long=True, duration_s=1.0, all_tests_passed=True)
    assert not json.loads(path.read_text())["passed"]  # a missed budget
    write_report([fine], path, long=False, duration_s=1.0, all_tests_passed=False)
    assert not json.loads(path.read_text())["passed"]  # a check that raised has no result
    write_report([], path, long=False, duration_s=1.0, all_tests_passed=True)
    assert not json.loads(path.read_text())["passed"]  # nothing ran


def test_wake_latency_measures_lateness_and_says_whether_the_machine_keeps_time() -> None:
    wake = wake_latency(0.3)
    assert set(wake) == {"p50_ms", "p99_ms", "max_ms", "steal_pct", "scheduling", "keeps_time"}
    assert 0.0 <= wake["p50_ms"] <= wake["p99_ms"] <= wake["max_ms"]
    assert wake["keeps_time"] == (wake["p99_ms"] <= WAKE_P99_MAX_MS and wake["max_ms"] <= WAKE_MAX_MS)
    assert wake["steal_pct"] is None or 0.0 <= wake["steal_pct"] <= 100.0
    assert wake["scheduling"]


def test_the_hosts_steal_over_a_window_and_whether_it_took_too_much() -> None:
    """steal_pct over a window from cpu_times (None where /proc/stat is missing or no time passed);
    a budget is held only where the host took at most STEAL_MAX_PCT of the CPU (or nobody knows)."""
    before = cpu_times()
    sum(range(2_000_000))  # some CPU time passes
    steal = steal_pct(before)
    assert before is not None or steal is None  # unknown where /proc/stat is not
    assert steal is None or 0.0 <= steal <= 100.0
    assert steal_pct(None) is None
    assert host_kept_cpu(None) and host_kept_cpu(0.0) and host_kept_cpu(STEAL_MAX_PCT)
    assert not host_kept_cpu(STEAL_MAX_PCT + 0.01) and not host_kept_cpu(22.27)
