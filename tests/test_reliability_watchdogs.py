"""The quick variant of ``make reliability``'s watchdogs group: a running stack
(real Zenoh, MuJoCo, the CBF-QP) through config changes, a calibration and restarts of
perception, the executor and the safety service; every command rate-limited, every watchdog
shown in SafetyStatus and counted."""

from __future__ import annotations

import pytest

from bench.reliability import watchdogs


@pytest.mark.integration
def test_watchdogs_and_rate_limits_hold_through_changes_and_restarts() -> None:
    results = watchdogs.run(quick=True)
    for result in results:
        print(f"\n  {result}")
    assert [r.name for r in results] == ["rate_limit", "watchdog_human", "watchdog_joint_state",
                                         "watchdog_executor_command"]
    assert all(r.passed for r in results), [str(r) for r in results if not r.passed]
