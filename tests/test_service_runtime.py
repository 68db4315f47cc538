"""The loop runtime every service shares (shared.service): a step that raises is counted, logged
once per streak (and the first ten), skipped; a streak as long as the limit is a bug and raises."""

from __future__ import annotations

import logging

import pytest

from shared.service import StepErrors


def test_failing_steps_are_counted_logged_once_per_streak_and_raised_at_the_limit(caplog: pytest.LogCaptureFixture) -> None:
    errors = StepErrors(logging.getLogger("test.loop"), "tick", limit=3)
    calls = {"n": 0}

    def flaky() -> int:
        calls["n"] += 1
        if calls["n"] % 2 == 0:
            raise RuntimeError("boom")
        return calls["n"]

    with caplog.at_level(logging.ERROR, logger="test.loop"):
        results = [errors.run(flaky) for _ in range(6)]
    assert results == [1, None, 3, None, 5, None] and errors.total == 3
    assert sum("tick failed" in r.message for r in caplog.records) == 3  # ≤ 10 so far: each one

    def broken() -> None:
        raise ValueError("always")

    assert errors.run(broken) is None  # the last flaky call failed: a streak of 2
    with pytest.raises(ValueError):
        errors.run(broken)  # 3 in a row: the limit
    assert errors.total == 5


def test_beyond_the_first_ten_only_the_first_failure_of_a_streak_is_logged(caplog: pytest.LogCaptureFixture) -> None:
    errors = StepErrors(logging.getLogger("test.loop"), "frame", limit=1000)

    def broken() -> None:
        raise RuntimeError("x")

    with caplog.at_level(logging.ERROR, logger="test.loop"):
        for _ in range(50):
            errors.run(broken)
        errors.run(lambda: None)
        errors.run(broken)
    assert errors.total == 51
    assert sum("frame failed" in r.message for r in caplog.records) == 10 + 1
