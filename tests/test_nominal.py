"""q_nom between camera frames: on a path that never runs more than one frame period ahead of the
newest state, never leaves the joint limits, stops after that frame and on a joint without a rate;
by default continuous (no jump at a new frame), or jumping to each state (``target_path: jump``). The
service and the evaluator use this one implementation."""

from __future__ import annotations

import numpy as np
import pytest

from services.safety.nominal import NominalTrack, frame_stamp
from shared.config import TargetPath
from tests.support.messages import human_state

Q_MIN, Q_MAX = np.full(3, -1.0), np.full(3, 1.0)
FRAME = 1 / 30
JUMP, CONTINUOUS = TargetPath.JUMP, TargetPath.CONTINUOUS


def track_with(q, dq, frame: float = FRAME, max_horizon: float = 0.05, path: TargetPath = JUMP) -> NominalTrack:
    """A track after two states: zeros (no rate) at time 0, then ``q``, ``dq`` one ``frame`` later, at time 1."""
    track = NominalTrack(np.zeros(3))
    track.update(np.zeros(3), np.zeros(3), 10.0, 0.0, max_horizon, Q_MIN, Q_MAX, path)  # the previous frame
    track.update(np.asarray(q, float), np.asarray(dq, float), 10.0 + frame, 1.0, max_horizon, Q_MIN, Q_MAX, path)
    return track


def test_jump_extrapolates_by_the_rate_for_one_frame_then_holds() -> None:
    track = track_with([0.1, 0.2, -0.3], [2.0, -1.0, 0.0])
    for tau in np.linspace(0, FRAME, 20, endpoint=False):
        q, dq = track.at(1.0 + tau)
        np.testing.assert_allclose(q, [0.1 + 2 * tau, 0.2 - tau, -0.3])
        np.testing.assert_allclose(dq, [2.0, -1.0, 0.0])
    end = np.array([0.1 + 2 * FRAME, 0.2 - FRAME, -0.3])
    for late in (FRAME, 0.1, 5.0):  # never more than one frame period ahead; then no rate
        q, dq = track.at(1.0 + late)
        np.testing.assert_allclose(q, end)
        assert (dq == 0).all()
    q, dq = track.at(0.9)  # before the state took effect: the state itself
    np.testing.assert_allclose(q, [0.1, 0.2, -0.3])


def test_continuous_goes_from_where_it_was_to_the_state_one_frame_ahead_then_holds() -> None:
    """The previous path held 0; the new state's one-frame extrapolation is reached exactly when the
    next frame is due, on a straight line whose velocity is q̇_nom (the surprise fed forward)."""
    track = track_with([0.1, 0.2, -0.3], [2.0, -1.0, 0.0], path=CONTINUOUS)
    end = np.array([0.1 + 2 * FRAME, 0.2 - FRAME, -0.3])
    for tau in np.linspace(0, FRAME, 20, endpoint=False):
        q, dq = track.at(1.0 + tau)
        np.testing.assert_allclose(q, end * tau / FRAME)
        np.testing.assert_allclose(dq, end / FRAME)
    for late in (FRAME, 0.1, 5.0):  # never more than one frame period ahead; then no rate
        q, dq = track.at(1.0 + late)
        np.testing.assert_allclose(q, end)
        assert (dq == 0).all()
    q, _ = track.at(0.9)  # before the state took effect: where the path was
    assert (q == 0).all()


def _random_states(rng: np.random.Generator, n: int = 200) -> list[tuple[np.ndarray, np.ndarray, float, float]]:
    """(q, dq, stamp, arrival) of a jittery 30 Hz camera, some frames late, with rates and targets
    that do not agree (noise, a person who changes direction), some targets beyond the limits."""
    states, stamp, arrival = [], 0.0, 0.0
    for _ in range(n):
        gap = FRAME * rng.choice([1.0, 1.0, 1.0, 0.5, 2.0, 3.0])
        stamp += gap
        arrival = max(arrival, stamp + 0.06 + rng.uniform(-0.01, 0.01))
        states.append((rng.uniform(-1.3, 1.3, 3), rng.uniform(-8.0, 8.0, 3), stamp, arrival))
    return states


@pytest.mark.parametrize("path", [CONTINUOUS, JUMP])
def test_never_leaves_the_limits_nor_runs_more_than_a_frame_ahead(path: TargetPath) -> None:
    """On random states, at random times: q_nom within the limits, between where the path started and
    the newest state extrapolated by one horizon (so never further ahead than that), at rest after it."""
    rng = np.random.default_rng(7)
    track = NominalTrack(np.zeros(3))
    for q, dq, stamp, arrival in _random_states(rng):
        before = track.at(arrival)[0]
        nominal = track.update(q, dq, stamp, arrival, 0.05, Q_MIN, Q_MAX, path)
        end = np.clip(q + dq * nominal.horizon, Q_MIN, Q_MAX)
        start = before if path is CONTINUOUS else np.clip(q, Q_MIN, Q_MAX)
        for now in arrival + rng.uniform(-0.01, 0.1, 20):
            q_nom, dq_nom = track.at(now)
            assert (q_nom >= Q_MIN).all() and (q_nom <= Q_MAX).all()
            low, high = np.minimum(start, end), np.maximum(start, end)
            assert (q_nom >= low - 1e-12).all() and (q_nom <= high + 1e-12).all()
            if now - arrival >= nominal.horizon:
                np.testing.assert_allclose(q_nom, end, atol=1e-12)
                assert (dq_nom == 0).all()


def test_continuous_never_jumps_where_jump_does() -> None:
    """At each new frame the continuous q_nom is where it was the instant before; the jumping one
    moves by the frame's surprise."""
    steps = {}
    for path in (CONTINUOUS, JUMP):
        track, largest = NominalTrack(np.zeros(3)), 0.0
        first, *later = _random_states(np.random.default_rng(3))
        track.update(*first[:3], first[3], 0.05, Q_MIN, Q_MAX, path)  # the first state: nothing to come from
        for q, dq, stamp, arrival in later:
            before = track.at(arrival)[0]
            track.update(q, dq, stamp, arrival, 0.05, Q_MIN, Q_MAX, path)
            largest = max(largest, float(np.abs(track.at(arrival)[0] - before).max()))
        steps[path] = largest
    assert steps[CONTINUOUS] < 1e-12
    assert steps[JUMP] > 0.5


def test_jump_stops_at_a_joint_limit() -> None:
    track = track_with([0.95, -0.99, 0.0], [5.0, -5.0, 1.0])
    q, dq = track.at(1.0 + 0.02)
    np.testing.assert_allclose(q, [1.0, -1.0, 0.02])
    np.testing.assert_allclose(dq, [0.0, 0.0, 1.0])  # a joint at its limit has no rate


@pytest.mark.parametrize("path", [CONTINUOUS, JUMP])
def test_horizon_is_the_frame_interval_capped_and_the_first_state_is_held(path: TargetPath) -> None:
    track = NominalTrack(np.zeros(3))
    track.update(np.full(3, 0.5), np.ones(3), 3.0, 0.0, 0.05, Q_MIN, Q_MAX, path)
    q, dq = track.at(0.02)  # the first state: no frame period known, no extrapolation, no path to it
    assert (q == 0.5).all() and (dq == 0).all()
    assert track_with(np.zeros(3), np.ones(3), frame=0.2, path=path).current.horizon == 0.05  # a long gap: capped
    staircase = track_with(np.full(3, 0.5), np.ones(3), max_horizon=0.0, path=path)  # 0: a staircase
    assert (staircase.at(1.0)[0] == 0.5).all() and (staircase.at(1.02)[0] == 0.5).all()


@pytest.mark.parametrize("path", [CONTINUOUS, JUMP])
def test_the_same_state_again_never_extrapolates_further(path: TargetPath) -> None:
    """Re-applied (config change, stale spell over): its first arrival time, horizon and start stay."""
    track = track_with([0.0, 0.0, 0.0], [1.0, 1.0, 1.0], path=path)
    first = track.at(1.01)[0]
    track.update(np.zeros(3), np.ones(3), 10.0 + FRAME, 3.0, 0.05, Q_MIN, Q_MAX, path)
    np.testing.assert_allclose(track.at(1.01)[0], first)  # the same path
    q, dq = track.at(3.01)
    np.testing.assert_allclose(q, FRAME)
    assert (dq == 0).all()


def test_a_frame_that_arrives_late_with_the_next_one_still_gets_one_frame_period() -> None:
    """A camera late now and then: two states published a millisecond apart after a stall. Their
    frame stamps (capture times) are a frame period apart, so the newest is extrapolated for a full
    period, where their publication stamps would have allowed 1 ms (a staircase until the next)."""
    late = human_state().model_copy(update={"stamp": 5.200, "capture_stamp": 3.000})
    next_one = late.model_copy(update={"stamp": 5.201, "capture_stamp": 3.000 + FRAME})
    assert frame_stamp(next_one) - frame_stamp(late) == pytest.approx(FRAME)
    assert frame_stamp(late.model_copy(update={"capture_stamp": None})) == 5.200  # a source without one
    track = NominalTrack(np.zeros(3))
    for state, since in ((late, 2.0), (next_one, 2.001)):
        track.update(np.zeros(3), np.ones(3), frame_stamp(state), since, 0.05, Q_MIN, Q_MAX, JUMP)
    q, dq = track.at(2.001 + FRAME / 2)
    np.testing.assert_allclose(q, np.full(3, FRAME / 2))
    np.testing.assert_allclose(dq, 1.0)
    np.testing.assert_allclose(track.at(2.001 + 1.0)[0], np.full(3, FRAME))  # then holds, one period ahead
