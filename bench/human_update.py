"""Benchmark: the safety service's memory of the person, per human state, at a camera's rate and at ten times it.

Each fresh HumanState the safety service reads goes through ``HumanMemory.update`` (held capsules,
lateness, how fast the person was seen to move over the last second:
:class:`~services.safety.seen_motion.SeenMotion`) and ``HumanMemory.capsules`` (swept ahead by
``safety.human_predict_s``). The timed call is both, on a person whose every capsule moves, at
30 Hz (a camera) and at 300 Hz (the load check's flood, ``tests/reliability/test_load.py``: ten
times as many frames in the stillness window). ``rate_ratio`` = p50 at 300 Hz / p50 at 30 Hz: the
work per state must not grow with the rate (recomputed over the whole window, it did: 0.4–0.8 ms
more per state at 300 Hz, the flood's deadlines missed). Each rate warms up over 2 s of states (the window
full), then the two rates are timed in alternating blocks, so load from other processes falls on
both alike.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from bench.common import percentiles_us
from services.safety.human_memory import HumanMemory
from shared.config import SafetyConfig
from shared.messages import HumanState
from shared.names import CAPSULE_NAMES
from tests.support.messages import human_state

RATES_HZ = (30.0, 300.0)
WARMUP_S = 2.0
BLOCKS = 20
STATES_PER_BLOCK = 150


def stream(rate_hz: float, n: int) -> list[HumanState]:
    """``n`` states ``1/rate_hz`` apart, every capsule endpoint circling at 0.5 m/s (capture stamp = stamp)."""
    base = human_state()
    states = []
    for k in range(n):
        t = k / rate_hz
        offset = 0.16 * np.array([np.cos(3.0 * t), np.sin(3.0 * t), 0.0])
        states.append(base.model_copy(update={"stamp": t, "capture_stamp": t, "seq": k, "capsules": base.capsules + offset}))
    return states


def run() -> dict[str, Any]:
    safety = SafetyConfig()
    n_external = len(CAPSULE_NAMES)  # one person's slots
    timed: dict[float, list[float]] = {rate: [] for rate in RATES_HZ}
    memories, streams, cursors = {}, {}, {}
    for rate in RATES_HZ:
        warmup = int(WARMUP_S * rate)
        streams[rate] = stream(rate, warmup + BLOCKS * STATES_PER_BLOCK)
        memories[rate] = HumanMemory()
        for message in streams[rate][:warmup]:
            memories[rate].update(message, message.stamp, safety.lost_human_hold_s)
        cursors[rate] = warmup
    clock = time.perf_counter
    for _ in range(BLOCKS):
        for rate in RATES_HZ:
            memory, states = memories[rate], streams[rate]
            for message in states[cursors[rate]:cursors[rate] + STATES_PER_BLOCK]:
                start = clock()
                memory.update(message, message.stamp, safety.lost_human_hold_s)
                memory.capsules(n_external, safety.human_velocity_term, safety.human_predict_s)
                timed[rate].append(clock() - start)
            cursors[rate] += STATES_PER_BLOCK
    slow, fast = (percentiles_us(np.asarray(timed[rate])) for rate in RATES_HZ)
    return {
        "name": "human_update",
        "what": "HumanMemory.update + capsules (swept) per human state, at 300 Hz (p50/p99) and 30 Hz",
        "unit": "us",
        "p50": fast["p50"],
        "p99": fast["p99"],
        "stats": fast,
        "stats_30hz": slow,
        "rate_ratio": fast["p50"] / slow["p50"],
    }
