"""Benchmark: encode + validate + decode of a HumanState (budget p50 ≤ 50 µs, architecture §8)."""

from __future__ import annotations

from typing import Any

from bench.common import percentiles_us, time_calls
from shared.codec import decode, encode
from shared.messages import HumanState
from tests.support.messages import human_state

BUDGET_P50_US = 50.0


def run(repeats: int = 20000) -> dict[str, Any]:
    message = human_state()
    payload = encode(message)
    stats = percentiles_us(time_calls(lambda: decode(encode(message), HumanState), repeats))
    encode_stats = percentiles_us(time_calls(lambda: encode(message), repeats))
    decode_stats = percentiles_us(time_calls(lambda: decode(payload, HumanState), repeats))
    return {
        "name": "codec",
        "what": "HumanState encode + validate + decode (with capsule velocities)",
        "unit": "us",
        "p50": stats["p50"],
        "p99": stats["p99"],
        "stats": stats,
        "encode": encode_stats,
        "decode_validate": decode_stats,
        "bytes": len(payload),
        "budget_p50": BUDGET_P50_US,
        "within_budget": stats["p50"] <= BUDGET_P50_US,
    }
