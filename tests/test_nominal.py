"""q_nom between camera frames: extrapolated by its rate, at most one frame period
ahead, never outside the joint limits, stopped on a joint without a rate; the service and the
evaluator use this one implementation."""

from __future__ import annotations

import numpy as np

from services.safety.nominal import NominalTrack

Q_MIN, Q_MAX = np.full(3, -1.0), np.full(3, 1.0)
FRAME = 1 / 30


def track_with(q, dq, frame: float = FRAME, max_horizon: float = 0.05) -> NominalTrack:
    track = NominalTrack(np.zeros(3))
    track.update(np.zeros(3), np.zeros(3), 10.0, 0.0, max_horizon, Q_MIN, Q_MAX)  # the previous frame
    track.update(np.asarray(q, float), np.asarray(dq, float), 10.0 + frame, 1.0, max_horizon, Q_MIN, Q_MAX)
    return track


def test_extrapolates_by_the_rate_for_one_frame_then_holds() -> None:
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


def test_never_leaves_the_joint_limits_and_stops_there() -> None:
    track = track_with([0.95, -0.99, 0.0], [5.0, -5.0, 1.0])
    rng = np.random.default_rng(1)
    for now in 1.0 + rng.uniform(-0.1, 1.0, 500):
        q, dq = track.at(now)
        assert (q >= Q_MIN).all() and (q <= Q_MAX).all()
        assert (np.abs(q - [0.95, -0.99, 0.0]) <= 5.0 * FRAME + 1e-12).all()
    q, dq = track.at(1.0 + 0.02)
    np.testing.assert_allclose(q, [1.0, -1.0, 0.02])
    np.testing.assert_allclose(dq, [0.0, 0.0, 1.0])  # a joint at its limit has no rate


def test_horizon_is_the_frame_interval_capped_and_the_first_state_is_held() -> None:
    track = NominalTrack(np.zeros(3))
    track.update(np.zeros(3), np.ones(3), 3.0, 0.0, 0.05, Q_MIN, Q_MAX)
    q, dq = track.at(0.02)  # the first state: no frame period known, no extrapolation
    assert (q == 0).all() and (dq == 0).all()
    assert track_with(np.zeros(3), np.ones(3), frame=0.2).current.horizon == 0.05  # a long gap: capped
    assert track_with(np.zeros(3), np.ones(3), max_horizon=0.0).at(1.02)[0].max() == 0.0  # 0: a staircase


def test_the_same_state_again_never_extrapolates_further() -> None:
    """Re-applied (config change, stale spell over): its first arrival time and horizon stay."""
    track = track_with([0.0, 0.0, 0.0], [1.0, 1.0, 1.0])
    track.update(np.zeros(3), np.ones(3), 10.0 + FRAME, 3.0, 0.05, Q_MIN, Q_MAX)
    q, dq = track.at(3.01)
    np.testing.assert_allclose(q, FRAME)
    assert (dq == 0).all()
