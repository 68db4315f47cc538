"""Benchmark: encode + validate + decode of a HumanState (budget p50 ≤ 50 µs, architecture §8)."""

from __future__ import annotations

from typing import Any

import numpy as np

from bench.common import percentiles_us, time_calls
from shared.codec import decode, encode
from shared.messages import HumanState

BUDGET_P50_US = 50.0


def human_state() -> HumanState:
    rng = np.random.default_rng(0)
    return HumanState(
        stamp=1.0,
        keypoints=rng.normal(size=(15, 3)),
        keypoint_valid=np.ones(15, bool),
        theta=rng.normal(size=8),
        theta_valid=np.ones(8, bool),
        capsules=rng.normal(size=(7, 2, 3)),
        capsule_radii=np.full(7, 0.06),
        capsule_valid=np.ones(7, bool),
        capsule_velocities=rng.normal(size=(7, 2, 3)),
    )


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
