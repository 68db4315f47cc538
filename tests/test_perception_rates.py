"""θ̇ (HumanState.theta_rate) from the filtered skeleton: the rate of a known motion, zeros where it is
not computable (invalid angle, re-initialised keypoint, filter reset), wrapping, and the message."""

from __future__ import annotations

import math

import numpy as np
import pytest

from services.perception.angles import AngleRates
from services.perception.pipeline import PerceptionPipeline
from services.perception.base import SkeletonFrame
from services.perception.synthetic import skeleton
from shared.codec import decode, encode
from shared.config import HumanConfig, PerceptionConfig, PoseAnglesConfig
from shared.lowpass import RateFilter, angle_rate_filter
from shared.names import KEYPOINT_INDEX as K
from shared.names import POSE_ANGLE_NAMES

FPS = 30.0
A = {name: i for i, name in enumerate(POSE_ANGLE_NAMES)}
OMEGA = 1.5  # rad/s


def pose_at(t: float) -> np.ndarray:
    """Left shoulder pitch ramping at OMEGA (inside the paper zone), right elbow bending at −OMEGA/2."""
    theta = np.array([0.0, 0.0, -0.4 + OMEGA * t, 0.2, 0.3, 0.1, 0.15, 1.2 - 0.5 * OMEGA * t])
    return skeleton(theta)


def frames(n: int, t0: float = 0.0, start: int = 0) -> list[SkeletonFrame]:
    return [SkeletonFrame(t=t0 + i / FPS, xyz=pose_at(i / FPS), conf=np.ones(15), captured=0.0) for i in range(start, start + n)]


def test_rates_of_a_known_motion_through_the_pipeline() -> None:
    pipeline = PerceptionPipeline(PerceptionConfig(), HumanConfig())
    results = [pipeline.step(frame) for frame in frames(24)]
    assert (results[0].theta_rate == 0).all()  # nothing to difference yet
    settled = results[-1].theta_rate
    assert settled[A["left_shoulder_pitch"]] == pytest.approx(OMEGA, rel=0.02)
    assert settled[A["right_elbow"]] == pytest.approx(-0.5 * OMEGA, rel=0.02)
    others = [i for i in range(8) if i not in (A["left_shoulder_pitch"], A["right_elbow"])]
    assert np.abs(settled[others]).max() < 0.02
    message = decode(encode(results[-1].to_message(stamp=1.0)))
    np.testing.assert_array_equal(message.theta_rate, settled)


def test_rates_are_zero_where_not_computable() -> None:
    pipeline = PerceptionPipeline(PerceptionConfig(), HumanConfig())
    out = [pipeline.step(frame) for frame in frames(15)]
    assert out[-1].theta_rate[A["left_shoulder_pitch"]] > 1.0
    # The left elbow keypoint vanishes for the hold and beyond: the left shoulder angles go invalid.
    hold_frames = int(PerceptionConfig().point_filter.hold_s * FPS) + 2
    for i in range(15, 15 + hold_frames):
        frame = frames(1, start=i)[0]
        confidence = np.ones(15)
        confidence[K["left_elbow"]] = 0.0
        out.append(pipeline.step(SkeletonFrame(t=frame.t, xyz=frame.xyz, conf=confidence, captured=0.0)))
    lost = out[-1]
    assert not lost.theta_valid[A["left_shoulder_pitch"]]
    assert lost.theta_rate[A["left_shoulder_pitch"]] == 0.0 and lost.theta_rate[A["left_elbow"]] == 0.0
    assert lost.theta_rate[A["right_elbow"]] == pytest.approx(-0.5 * OMEGA, rel=0.05)  # the other arm is unaffected
    back = pipeline.step(frames(1, start=15 + hold_frames)[0])  # the elbow returns: fresh, no difference across the gap
    assert back.theta_valid[A["left_shoulder_pitch"]] and back.theta_rate[A["left_shoulder_pitch"]] == 0.0
    again = pipeline.step(frames(1, start=16 + hold_frames)[0])
    assert again.theta_rate[A["left_shoulder_pitch"]] > 0.0  # and it restarts from 0 after
    # A discontinuity (replay starting over) resets the filter: every rate 0 on that frame.
    restart = frames(1, t0=0.0)[0]
    reset = pipeline.step(SkeletonFrame(t=restart.t, xyz=restart.xyz, conf=restart.conf, captured=0.0, discontinuity=True))
    assert pipeline.counters.filter_resets == 1 and (reset.theta_rate == 0).all()


def test_rate_differences_are_wrapped_and_low_passed() -> None:
    """θ going from 3.1 to −3.1 rad moved +0.083 rad, not −6.2; a fixed cut-off (β = 0) is the
    low-pass α = 1/(1 + τ/Δt)."""
    rates = AngleRates(PoseAnglesConfig(rate_cutoff_hz=5.0, rate_beta=0.0, rate_second_order=False))
    valid, fresh = np.ones(8, bool), np.zeros(15, bool)
    dt = 1 / FPS
    rates(0.0, np.full(8, 3.1), valid, fresh)
    out = rates(dt, np.full(8, -3.1), valid, fresh)
    alpha = 1 / (1 + 1 / (2 * math.pi * 5.0 * dt))
    np.testing.assert_allclose(out, alpha * (2 * math.pi - 6.2) / dt)
    assert np.isfinite(rates(dt, np.zeros(8), valid, fresh)).all()  # no time elapsed: no division, rates kept finite


def test_rate_filter_cut_off_grows_with_speed_as_one_euro_defines_it() -> None:
    """f_c = cutoff + β |ω̂| (Casiez et al. 2012, on the rate): one step from a known ω̂ against the
    definition; a fast channel follows a step in its rate sooner than a still one."""
    dt, cutoff, beta = 1 / FPS, 1.0, 10.0
    rates = RateFilter(2, cutoff, beta)
    usable = np.ones(2, bool)
    rates.update(dt, np.array([0.0, 3.0]) * dt, usable)  # ω̂ = α(1 Hz) · (0, 3)
    before = rates.rate.copy()
    after = rates.update(dt, np.array([1.0, 4.0]) * dt, usable)
    gain = 1 / (1 + 1 / (2 * math.pi * (cutoff + beta * np.abs(before)) * dt))
    np.testing.assert_allclose(after, before + gain * (np.array([1.0, 4.0]) - before))
    assert gain[1] > gain[0]


def test_second_order_rate_is_exact_for_a_constant_acceleration_and_restarts_first_order() -> None:
    """The slope at t of the parabola through the last three samples, on uneven intervals: x = t²
    has rate 2t there exactly (the first difference is the rate half an interval back)."""
    rates = RateFilter(1, cutoff_hz=1e9, beta=0.0, second_order=True)  # no low-pass to speak of
    times = np.array([0.0, 0.03, 0.07, 0.1, 0.135])
    usable = np.ones(1, bool)
    for i in range(1, len(times)):
        dt = times[i] - times[i - 1]
        out = rates.update(dt, np.array([times[i] ** 2 - times[i - 1] ** 2]), usable)
        expected = 2 * times[i] if i >= 2 else times[i] + times[i - 1]  # the first one is first order
        assert out[0] == pytest.approx(expected, rel=1e-6)
    rates.update(0.03, np.array([np.nan]), ~usable)  # not usable: 0, and the next is first order again
    assert rates.rate[0] == 0.0
    out = rates.update(0.03, np.array([0.06]), usable)
    assert out[0] == pytest.approx(2.0, rel=1e-6)


def test_direction_rates_use_the_same_filter_as_the_person() -> None:
    """Both retargetings' rates come from one definition (perception.angles' parameters)."""
    conf = PoseAnglesConfig(rate_cutoff_hz=2.0, rate_beta=3.0, rate_second_order=True)
    rates = angle_rate_filter(8, conf)
    assert (rates.cutoff_hz, rates.beta, rates.second_order) == (2.0, 3.0, True)


def test_theta_rate_is_validated_like_every_array() -> None:
    result = PerceptionPipeline(PerceptionConfig(), HumanConfig()).step(frames(1)[0])
    message = result.to_message(stamp=0.0)
    assert message.schema_.version == 2
    fields = {name: getattr(message, name) for name in type(message).model_fields if name != "schema_"}
    for bad in (np.full(8, np.nan), np.array([0.0] * 7 + [np.inf]), np.zeros(7), np.zeros((8, 1))):
        with pytest.raises(ValueError):
            type(message)(**{**fields, "theta_rate": bad})



@pytest.mark.parametrize("bad", [np.inf, -np.inf, np.nan])
def test_a_non_finite_angle_difference_restarts_its_rate_instead_of_spreading(bad: float) -> None:
    """θ̇ is always finite: an angle whose difference is not finite (an overflowing skeleton) gives
    0 and restarts; the other angles go on as if it had been finite, and the next finite
    differences move the restarted angle again."""
    dt, valid, fresh = 1 / FPS, np.ones(8, bool), np.zeros(15, bool)
    hit, clean = AngleRates(PoseAnglesConfig()), AngleRates(PoseAnglesConfig())
    for k in range(3):
        for rates in (hit, clean):
            rates(k * dt, np.full(8, 0.1 * k), valid, fresh)
    theta = np.full(8, 0.3)
    out, expected = hit(3 * dt, np.where(np.arange(8) == 3, bad, theta), valid, fresh), clean(3 * dt, theta, valid, fresh)
    assert np.isfinite(out).all() and out[3] == 0.0
    np.testing.assert_array_equal(np.delete(out, 3), np.delete(expected, 3))
    hit(4 * dt, np.full(8, 0.4), valid, fresh)
    out = hit(5 * dt, np.full(8, 0.5), valid, fresh)
    assert np.isfinite(out).all() and out[3] > 0.0
