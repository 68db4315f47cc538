"""Timing helpers shared by the benchmarks: percentiles and JSON output with the machine attached
(:func:`tests.support.machine.machine`: the benchmarks run from the checkout, like the tests)."""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from tests.support.machine import machine

RESULTS_DIR = Path(__file__).resolve().parent / "results"


def time_calls(fn: Callable[[], object], repeats: int, warmup: int = 100) -> np.ndarray:
    """Wall-clock seconds of ``repeats`` calls of ``fn`` (after ``warmup`` untimed calls)."""
    for _ in range(warmup):
        fn()
    samples = np.empty(repeats)
    clock = time.perf_counter
    for i in range(repeats):
        start = clock()
        fn()
        samples[i] = clock() - start
    return samples


def percentiles_us(samples_s: np.ndarray) -> dict[str, float]:
    """p50/p90/p99/max/mean of samples given in seconds, in microseconds."""
    us = samples_s * 1e6
    return {
        "p50": float(np.percentile(us, 50)),
        "p90": float(np.percentile(us, 90)),
        "p99": float(np.percentile(us, 99)),
        "max": float(us.max()),
        "mean": float(us.mean()),
        "n": int(us.size),
    }


def write_result(result: dict[str, Any], out_dir: Path = RESULTS_DIR) -> Path:
    """Write ``result`` (must hold ``name``) to ``out_dir/{name}.json`` with the machine attached."""
    out_dir.mkdir(parents=True, exist_ok=True)
    result = {**result, "machine": machine(), "time": time.strftime("%Y-%m-%dT%H:%M:%S%z")}
    path = out_dir / f"{result['name']}.json"
    path.write_text(json.dumps(result, indent=2) + "\n")
    return path
