"""The safety service's watchdog states: a trip is a change to tripped, counted and logged once."""

from __future__ import annotations

import logging

import pytest

from services.safety.watchdogs import Watchdogs


def test_a_watchdog_counts_each_trip_once_and_logs_trips_and_clearings(caplog: pytest.LogCaptureFixture) -> None:
    dogs = Watchdogs(logging.getLogger("test.watchdogs"))
    with caplog.at_level(logging.INFO, logger="test.watchdogs"):
        states = [dogs.watch("human_state", up, "old") for up in (False, True, True, True, False, True)]
    assert states == [False, True, True, True, False, True]
    assert dogs.trips == {"human_state": 2} and dogs.tripped("human_state") and not dogs.tripped("resync")
    messages = [r.getMessage() for r in caplog.records]
    assert messages == ["watchdog human_state tripped: old (1 so far)", "watchdog human_state cleared",
                        "watchdog human_state tripped: old (2 so far)"]
