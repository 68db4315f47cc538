"""The human-update benchmark's input (bench/human_update.py): the timed path is the full one, a
person seen moving over a full window at both rates (no timing is asserted)."""

from __future__ import annotations

import math

import pytest

from bench.human_update import RATES_HZ, WARMUP_S, stream
from services.safety.human_memory import HumanMemory
from services.safety.protective_stop import STILL_SPEED


@pytest.mark.parametrize("rate", RATES_HZ)
def test_the_benchmarks_person_is_seen_moving_over_a_full_window(rate: float) -> None:
    memory = HumanMemory()
    for message in stream(rate, int(WARMUP_S * rate)):
        memory.update(message, message.stamp, hold_s=2.0)
    assert not memory.lost and math.isfinite(memory.seen_speed) and memory.seen_speed > STILL_SPEED
    assert round(rate) + 1 <= memory._seen.frames <= round(rate) + 2  # noqa: SLF001 (a second and the one before; k/rate rounds)
