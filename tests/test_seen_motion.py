"""SeenMotion: the running window's speed equals the window's computed in full, on random streams."""

from __future__ import annotations

import math

import numpy as np
import pytest

from services.safety.seen_motion import STILL_SEEN_FOR_S, STILL_WINDOW_S, SeenMotion

SLOTS = 7


def speed_in_full(frames: list[tuple[float, np.ndarray, np.ndarray]]) -> float:
    """SeenMotion's class-doc definition over every frame of a window, each computed from scratch."""
    stamps = np.array([f[0] for f in frames])
    endpoints = np.array([f[1] for f in frames])
    valid = np.array([f[2] for f in frames])
    if stamps[0] > stamps[-1] - STILL_SEEN_FOR_S:
        return math.inf
    now = valid[-1]
    if not now.any():
        return 0.0
    worst = 0.0
    for slot in np.flatnonzero(now):
        seen = valid[:, slot]
        if 2 * seen.sum() < len(frames):
            return math.inf
        span = stamps[-1] - stamps[seen][0]
        if span <= 0.0:
            return math.inf
        ends = endpoints[seen, slot]  # (n, 2, 3)
        rms = np.sqrt(((ends - ends.mean(axis=0)) ** 2).sum(axis=2).mean(axis=0))  # (2,)
        worst = max(worst, rms.max() / span)
    return math.sqrt(12.0) * worst


def window_after(frames: list[tuple[float, np.ndarray, np.ndarray]]) -> list[tuple[float, np.ndarray, np.ndarray]]:
    """The frames SeenMotion's window holds after ``frames`` (the class doc's rule, applied in full)."""
    window: list[tuple[float, np.ndarray, np.ndarray]] = []
    for frame in frames:
        if window and frame[0] == window[-1][0]:
            continue
        if window and frame[0] < window[-1][0]:
            window = []
        window.append(frame)
        while len(window) > 1 and window[1][0] <= frame[0] - STILL_WINDOW_S:
            window.pop(0)
    return window


@pytest.mark.parametrize("seed", range(6))
def test_the_running_sums_give_the_speed_of_the_window_computed_in_full_on_random_streams(seed: int) -> None:
    """Random rates (10–500 Hz, jittered), people standing metres from the origin and moving or
    still under noise, capsules flickering in and out, repeated and backwards stamps, minutes long:
    the running window's speed is the full one's to rounding (1e-9 relative, or 1e-9 m/s where it is
    about 0), inf and 0 exactly where it is."""
    rng = np.random.default_rng(seed)
    seen = SeenMotion(SLOTS)
    stream: list[tuple[float, np.ndarray, np.ndarray]] = []
    t, rate = 0.0, rng.uniform(10.0, 500.0)
    centre = rng.uniform(-3.0, 3.0, (SLOTS, 2, 3))
    velocity = rng.normal(0.0, 0.5, (SLOTS, 2, 3))
    flicker = rng.uniform(0.0, 0.4, SLOTS)
    kinds = {"inf": 0, "zero": 0, "finite": 0}
    for k in range(4000):
        if rng.random() < 0.002:  # the stream starts over
            t -= rng.uniform(0.1, 3.0)
        elif rng.random() < 0.01:  # the same frame again
            pass
        else:
            t += rng.uniform(0.5, 1.5) / rate
        if rng.random() < 0.003:
            rate = rng.uniform(10.0, 500.0)
        still = (k // 500) % 2 == 0
        endpoints = centre + (0.0 if still else t) * velocity + rng.normal(0.0, 0.01, (SLOTS, 2, 3))
        valid = rng.random(SLOTS) >= flicker
        if stream and t == stream[-1][0]:
            endpoints, valid = stream[-1][1], stream[-1][2]
        stream.append((t, endpoints, valid))
        got = seen.see(t, endpoints, valid)
        window = window_after(stream[-1200:]) if k % 7 == 0 else None
        if window is None:
            continue
        assert seen.frames == len(window)
        want = speed_in_full(window)
        if math.isinf(want) or want == 0.0:
            kinds["inf" if math.isinf(want) else "zero"] += 1
            assert got == want, k
        else:
            kinds["finite"] += 1
            assert got == pytest.approx(want, rel=1e-9, abs=1e-9), k
    assert kinds["finite"] > 100 and kinds["inf"] > 10  # both cases were checked


def test_a_still_capsule_is_exactly_still_however_far_it_stands_and_however_long() -> None:
    """Sums of the endpoints less a reference: a capsule standing 50 m away for an hour at 500 Hz is
    still to the last digit (sums of the endpoints themselves lose ‖e‖²·n·ε to cancellation)."""
    seen = SeenMotion(SLOTS)
    endpoints = np.full((SLOTS, 2, 3), 50.0)
    valid = np.ones(SLOTS, bool)
    for k in range(500 * 60):  # a minute of frames, then an hour's worth of stamps in steps
        seen.see(k / 500.0, endpoints, valid)
    assert seen.speed == 0.0
    assert seen.see(3600.0, endpoints + [0.0, 0.0, 0.01], valid) > 0.0  # one frame 1 cm away: moving


def test_a_capsule_back_after_leaving_the_window_is_judged_afresh() -> None:
    """A capsule that moved, left the window (invalid for longer than it) and came back still
    elsewhere is exactly still: its sums start again from 0, not from what rounding left of them."""
    rng = np.random.default_rng(1)
    seen = SeenMotion(SLOTS)
    only, nobody = np.arange(SLOTS) == 0, np.zeros(SLOTS, bool)
    for k in range(300):
        seen.see(k / 100.0, rng.normal(0.0, 1.0, (SLOTS, 2, 3)), only)
    for k in range(300, 500):
        seen.see(k / 100.0, np.zeros((SLOTS, 2, 3)), nobody)
    for k in range(500, 700):
        speed = seen.see(k / 100.0, np.full((SLOTS, 2, 3), 2.0), only)
    assert speed == 0.0
