"""The loop runtime every service shares (shared.service): a step that raises is counted, logged
once per streak (and the first ten), skipped; a streak as long as the limit is a bug and raises.
Step times keep the last and a window; refusals add the service's own to the bus's; a config update
is validated on arrival or counted refused with its reason; a pending item is the newest put, taken once; the achieved rate is the ticks over the elapsed time."""

from __future__ import annotations

import logging
import threading
import time

import numpy as np
import pytest

from shared.bus import Bus
from shared.config import BusConfig, StackConfig
from shared.messages import ConfigUpdate
from shared.service import Pending, Refusals, ScheduledService, StepErrors, StepTimes, validated_update
from tests.support.bus import await_route
from tests.support.processes import free_port


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


def test_step_times_keep_the_last_and_a_window_of_the_most_recent() -> None:
    times = StepTimes(window=3)
    assert times.last_s == 0.0 and np.array_equal(times.recent(), [0.0])
    for seconds in (0.1, 0.2, 0.3, 0.4):
        times.record(seconds)
    assert times.last_s == 0.4
    assert sorted(times.recent()) == [0.2, 0.3, 0.4]  # the oldest overwritten


def test_rate_counters_are_the_ticks_over_the_elapsed_time() -> None:
    service = ScheduledService()
    service.ticks = 250
    assert service.rate_counters(None) == {}
    assert service.rate_counters(0.5) == {"elapsed_s": 0.5, "achieved_hz": 500.0}
    assert service.rate_counters(0.0)["achieved_hz"] == 0.0


def test_pending_holds_the_newest_item_until_taken_once() -> None:
    pending: Pending[int] = Pending()
    assert pending.take() is None
    pending.put(1)
    pending.put(2)
    assert pending.peek() == 2 and pending.take() == 2 and pending.take() is None
    threads = [threading.Thread(target=pending.put, args=(i,)) for i in range(20)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert pending.take() in range(20) and pending.peek() is None


def test_a_config_update_is_validated_or_counted_refused_with_its_reason(caplog: pytest.LogCaptureFixture) -> None:
    refusals, log = Refusals(), logging.getLogger("test.config")
    good = StackConfig().model_dump(mode="json")
    good["safety"]["gamma"] = 12.0
    accepted = validated_update(ConfigUpdate(stamp=0.0, version=2, config=good), refusals, log)
    assert isinstance(accepted, StackConfig) and accepted.safety.gamma == 12.0
    assert refusals.own("config") == 0
    bad = {**good, "safety": {**good["safety"], "gamma": -1.0}}
    with caplog.at_level(logging.WARNING, logger="test.config"):
        assert validated_update(ConfigUpdate(stamp=0.0, version=3, config=bad), refusals, log) is None
    assert refusals.own("config") == 1
    assert "rejected config update v3" in caplog.text and "gamma" in caplog.text


@pytest.mark.integration
def test_refusals_add_the_services_own_to_the_buss_drops() -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with Bus(BusConfig(mode="peer", listen=[endpoint], multicast_scouting=False), "refusals", "safety") as bus, \
            Bus(BusConfig(mode="peer", connect=[endpoint], multicast_scouting=False), "refusals", "test") as sender:
        bus.subscribe("config", lambda message: None)
        await_route(sender, "config")
        refusals = Refusals()
        assert refusals.by_topic(bus) == {}
        sender.put_raw("config", b"not msgpack")
        deadline = time.monotonic() + 5
        while not bus.dropped["config"] and time.monotonic() < deadline:
            time.sleep(0.01)
        refusals.refuse("config")
        refusals.refuse("robot/command")
        assert refusals.own("config") == 1
        assert refusals.by_topic(bus) == {"config": 2, "robot/command": 1}
