"""The angle-rate benchmark's tracking loop (bench/angle_rates.py): the stack's NominalTrack and
u = θ̇ + K (θ_nom − q) on a known ramp (no timing is asserted)."""

from __future__ import annotations

import numpy as np
import pytest

from bench.angle_rates import tracked
from shared.config import PoseAnglesConfig, SafetyConfig

FPS = 30.0
RATE = 0.5  # rad/s


def ramp() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    t = np.arange(90) / FPS
    return t, np.outer(t, np.full(8, RATE)), np.ones((len(t), 8), bool), np.zeros((len(t), 15), bool)


def test_the_loop_follows_a_ramp_with_feed_forward_and_trails_it_by_the_rate_over_k_without() -> None:
    angles = ramp()
    safety = SafetyConfig()
    steps, q, u = tracked(angles, PoseAnglesConfig(), safety)
    late = steps > 2.0  # the rate filter and the loop have settled
    truth = RATE * steps[late, None]
    np.testing.assert_allclose(q[late], np.broadcast_to(truth, q[late].shape), atol=2e-3)
    np.testing.assert_allclose(u[late], RATE, atol=1e-2)
    _, q_paper, _ = tracked(angles, PoseAnglesConfig(), safety.model_copy(update={"feedforward": False}))
    error = truth - q_paper[late]  # the paper's eq. 7: the error K-only tracking leaves on a ramp
    assert error.mean() == pytest.approx(RATE / safety.gain, rel=0.1)
