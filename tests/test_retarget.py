"""Retargeting (paper eq. 2) checked through forward kinematics of the shipped G1 model."""

from __future__ import annotations

import numpy as np
import pytest

from services.safety.assembly import build_pipeline
from services.safety.retarget import mirror_pose
from shared.config import load_config

HALF_PI = np.pi / 2


@pytest.fixture(scope="module", params=[False, True], ids=["side-by-side", "mirror"])
def pipeline(request):
    conf = load_config(environ={}, overrides={"retargeting": {"mirror": request.param, "method": "linear"}})
    return build_pipeline(conf)


def arm_directions(pipeline, q: np.ndarray, side: str) -> tuple[np.ndarray, np.ndarray]:
    """Unit upper-arm and forearm directions of the robot's ``side`` arm in the world frame."""
    kin = pipeline.kinematics
    shoulder = kin.frame_position(f"{side}_shoulder_roll_link", q)
    elbow = kin.frame_position(f"{side}_elbow_link", q)
    wrist = kin.frame_position(f"{side}_wrist_roll_link", q)
    unit = lambda v: v / np.linalg.norm(v)  # noqa: E731
    return unit(elbow - shoulder), unit(wrist - elbow)


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip(a @ b, -1, 1))))


def theta(**angles: float) -> np.ndarray:
    names = ["torso_roll", "torso_pitch", "l_pitch", "l_roll", "l_elbow", "r_pitch", "r_roll", "r_elbow"]
    return np.array([angles.get(n, 0.0) for n in names])


def robot_side(pipeline, person_side: str) -> str:
    """Which robot arm imitates the person's ``person_side`` arm."""
    if not pipeline.retargeter.mirror:
        return person_side
    return "right" if person_side == "left" else "left"


FORWARD, DOWN = np.array([1.0, 0, 0]), np.array([0, 0, -1.0])


def test_neutral_person_gives_home_with_arms_down(pipeline) -> None:
    q = pipeline.retargeter(theta())
    np.testing.assert_allclose(q, pipeline.kinematics.q_home)
    for side in ("left", "right"):
        upper, fore = arm_directions(pipeline, q, side)
        assert angle_deg(upper, DOWN) < 25 and angle_deg(fore, DOWN) < 30


@pytest.mark.parametrize("person_side", ["left", "right"])
def test_arm_forward_points_forward(pipeline, person_side: str) -> None:
    key = "l_pitch" if person_side == "left" else "r_pitch"
    q = pipeline.retargeter(theta(**{key: HALF_PI}))
    upper, fore = arm_directions(pipeline, q, robot_side(pipeline, person_side))
    # The G1 shoulder-roll axis is tilted 16° about x (its link quaternion), so the affine map of
    # eq. 2 leaves a raised arm up to ~16° inward of straight ahead; it still points forward.
    assert angle_deg(upper, FORWARD) < 20 and angle_deg(fore, FORWARD) < 20
    other = "right" if robot_side(pipeline, person_side) == "left" else "left"
    assert angle_deg(arm_directions(pipeline, q, other)[0], DOWN) < 25


@pytest.mark.parametrize("person_side", ["left", "right"])
def test_arm_out_sideways_and_elbow_flexion(pipeline, person_side: str) -> None:
    side = robot_side(pipeline, person_side)
    key = person_side[0]
    q = pipeline.retargeter(theta(**{f"{key}_roll": 1.2, f"{key}_elbow": HALF_PI}))
    upper, fore = arm_directions(pipeline, q, side)
    outward = np.array([0, 1.0 if side == "left" else -1.0, 0])
    assert upper @ outward > 0.8  # arm raised out to the robot's own side
    assert abs(upper @ fore) < 0.2  # elbow bent about 90°


def test_torso_lean(pipeline) -> None:
    kin = pipeline.kinematics
    top = lambda q: kin.compute(q)[0][0, 1].copy()  # noqa: E731  torso capsule top (compute reuses its buffers)
    upright = top(pipeline.retargeter(theta()))
    forward = top(pipeline.retargeter(theta(torso_pitch=0.3)))
    left = top(pipeline.retargeter(theta(torso_roll=0.3)))  # person leans to their left
    assert forward[0] - upright[0] > 0.05
    lean_y = left[1] - upright[1]
    assert (lean_y > 0.05) if not pipeline.retargeter.mirror else (lean_y < -0.05)


def test_limits_invalid_angles_and_calibration(pipeline) -> None:
    r = pipeline.retargeter
    q = r(theta(l_pitch=100.0, r_roll=-100.0))
    assert (q >= r.q_min).all() and (q <= r.q_max).all()
    before = r(theta(l_pitch=0.5))
    valid = np.ones(8, bool)
    valid[2] = valid[5] = False  # shoulder pitches missing: keep the previous values
    after = r(theta(l_pitch=1.5, r_pitch=1.5), valid)
    np.testing.assert_array_equal(after[[2, 5]], before[[2, 5]])
    neutral_bias = theta(l_elbow=0.2, r_elbow=0.15, torso_pitch=0.05)
    r.calibrate(neutral_bias)
    np.testing.assert_allclose(r(neutral_bias), np.clip(r.q_home + r.offset, r.q_min, r.q_max))
    r.calibrate(theta())
    with pytest.raises(ValueError):
        r.calibrate(np.full(8, np.nan))


def test_mirror_pose_is_an_involution() -> None:
    th = np.arange(8.0)
    np.testing.assert_array_equal(mirror_pose(mirror_pose(th)), th)
    np.testing.assert_array_equal(mirror_pose(th)[[2, 3, 4]], th[[5, 6, 7]])


def test_rate_is_s_times_theta_rate_mirrored_and_zero_where_clipped_or_invalid(pipeline) -> None:
    """q̇_nom = S ⊙ θ̇' (θ̇ mirrored like θ), 0 where q_nom is clipped or θ is invalid, and
    it is the derivative of the retargeting wherever q_nom is not clipped."""
    r = pipeline.retargeter
    rng = np.random.default_rng(4)
    th = theta(torso_roll=0.1, l_pitch=0.6, l_roll=0.3, l_elbow=0.5, r_pitch=0.4, r_roll=0.2, r_elbow=0.7)
    rate = rng.uniform(-3, 3, 8)
    r(th)
    dq = r.rate(rate)
    expected = r.scale * (mirror_pose(rate) if r.mirror else rate)
    np.testing.assert_allclose(dq, expected)
    eps = 1e-6  # the retargeting's own derivative
    np.testing.assert_allclose((r(th + eps * rate) - r(th - eps * rate)) / (2 * eps), dq, atol=1e-6)
    r(th)
    # a joint clipped at its limit: the person goes on, q_nom stays, so does its rate (0)
    far = th.copy()
    far[2] = 6.0  # left pitch far past the robot's range
    clipped_joint = 5 if r.mirror else 2
    q = r(far)
    assert q[clipped_joint] in (r.q_min[clipped_joint], r.q_max[clipped_joint])
    dq = r.rate(rate)
    assert dq[clipped_joint] == 0.0 and np.count_nonzero(dq) == 7
    # an invalid angle keeps its last q_nom and has no rate; a non-finite rate gives 0
    valid = np.ones(8, bool)
    valid[4] = False
    r(th, valid)
    dq = r.rate(np.where(np.arange(8) == 0, np.nan, rate))
    assert dq[7 if r.mirror else 4] == 0.0 and dq[0] == 0.0


def test_hold_makes_unseen_joints_continue_from_the_given_target(pipeline) -> None:
    r = pipeline.retargeter
    current = np.clip(r.q_home + 0.3, r.q_min, r.q_max)
    r.hold(current + 100.0)  # clipped to the limits
    np.testing.assert_array_equal(r(np.zeros(8), np.zeros(8, bool)), r.q_max)
    r.hold(current)
    valid = np.zeros(8, bool)
    valid[2] = True  # only one shoulder pitch is seen (the person's left: the robot's right if mirrored)
    q = r(theta(left_shoulder_pitch=0.5), valid)
    assert np.count_nonzero(q != current) == 1  # that joint follows; every other keeps the held target
