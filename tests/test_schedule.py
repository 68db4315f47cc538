"""shared.schedule: absolute-time ticks, stalls counted as missed slots with the phase kept."""

from __future__ import annotations

import threading
import time

from shared.schedule import FixedRateSchedule

PERIOD = 0.01


def test_stall_counts_whole_missed_periods_and_keeps_the_phase() -> None:
    schedule = FixedRateSchedule(PERIOD)
    schedule.start(threading.Event())
    assert schedule.wait() is not None and schedule.missed == 0  # tick 0: due at start
    time.sleep(3.5 * PERIOD)  # a stall: ticks 1 and 2 are lost, tick 3 starts late
    now = schedule.wait()
    assert now is not None and schedule.missed >= 2 and schedule.max_late_s >= 2.5 * PERIOD
    assert schedule.due <= now < schedule.due + 2 * PERIOD
    phase = (schedule.due - schedule.begin) / PERIOD
    assert abs(phase - round(phase)) < 1e-9  # still on the original grid: no drift, no burst


def test_overrun_is_a_miss_and_stop_or_duration_end_the_loop() -> None:
    schedule = FixedRateSchedule(PERIOD)
    stop = threading.Event()
    schedule.start(stop, duration=5 * PERIOD)
    schedule.wait()
    schedule.finished(schedule.due + 0.5 * PERIOD)
    assert schedule.missed == 0
    schedule.finished(schedule.due + 1.5 * PERIOD)
    assert schedule.missed == 1
    ticks = 1
    while schedule.wait() is not None:
        ticks += 1
    assert 2 <= ticks <= 6  # the duration ended it
    schedule.start(stop)
    stop.set()
    assert schedule.wait() is None


def test_set_period_restarts_the_grid_one_new_period_ahead() -> None:
    schedule = FixedRateSchedule(PERIOD)
    schedule.start(threading.Event())
    schedule.wait()
    before = time.monotonic()
    schedule.set_period(2 * PERIOD)
    now = schedule.wait()
    assert now is not None and now - before >= 2 * PERIOD - 1e-3 and schedule.period == 2 * PERIOD
