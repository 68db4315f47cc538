"""Retargeting by arm directions, through the shipped G1 model's kinematics and self pairs."""

from __future__ import annotations

import numpy as np
import pytest

from services.safety.assembly import build_pipeline, make_retargeter
from services.safety.direction_retarget import DirectionRetargeter
from services.safety.kinematics import RobotKinematics
from services.safety.retarget import Pose, Retargeter
from shared.config import load_config
from shared.names import KEYPOINT_INDEX as K
from shared.torso_frame import person_arm_directions, robot_arm_directions

FPS = 30.0
#: The person's torso frame in the robot frame: rows e_x (right), e_y (forward), e_z (up) of a
#: person standing upright, facing +x.
PERSON_AXES = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
DOWN, FORWARD, OUT_LEFT = np.array([0, 0, -1.0]), np.array([0, 1.0, 0]), np.array([-1.0, 0, 0])  # in F_T


def conf_with(**retargeting):
    return load_config(environ={}, overrides={"retargeting": {"method": "directions", **retargeting}})


def retargeter(**retargeting) -> DirectionRetargeter:
    conf = conf_with(**retargeting)
    pipeline = build_pipeline(conf)
    assert isinstance(pipeline.retargeter, DirectionRetargeter)
    return pipeline.retargeter


def skeleton(left: tuple[np.ndarray, np.ndarray], right: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Keypoints (15, 3) and validity of an upright person whose (upper arm, forearm) directions in
    its torso frame F_T are ``left`` and ``right``."""
    points, valid = np.zeros((15, 3)), np.zeros(15, bool)
    points[K["pelvis"]] = (0.0, 0.0, 1.0)
    for side, (upper, fore), y in (("left", left, 0.18), ("right", right, -0.18)):
        shoulder = np.array([0.0, y, 1.45])
        elbow = shoulder + 0.3 * (PERSON_AXES.T @ (upper / np.linalg.norm(upper)))
        wrist = elbow + 0.25 * (PERSON_AXES.T @ (fore / np.linalg.norm(fore)))
        points[K[f"{side}_shoulder"]], points[K[f"{side}_elbow"]], points[K[f"{side}_wrist"]] = shoulder, elbow, wrist
    for name in ("pelvis", "left_shoulder", "right_shoulder", "left_elbow", "right_elbow", "left_wrist", "right_wrist"):
        valid[K[name]] = True
    return points, valid


def pose(points: np.ndarray, valid: np.ndarray, t: float, rate: float = 1.0) -> Pose:
    """A state with the person's angles zero (waist at home) and arm rates ``rate`` (non-zero: computable)."""
    return Pose(np.zeros(8), np.ones(8, bool), np.full(8, rate), points, valid, t)


def errors_deg(r: DirectionRetargeter, q: np.ndarray, points: np.ndarray, valid: np.ndarray, mirror: bool) -> np.ndarray:
    person = person_arm_directions(points, valid, mirror, 0.05)
    robot = robot_arm_directions(r.kinematics.compute(q)[0], 0.05)
    return np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", person, robot), -1, 1)))


def self_h(r: DirectionRetargeter, q: np.ndarray, body=None) -> np.ndarray:
    """h of every self pair of ``body`` (default: ``r``'s) at ``q`` (m, with the filter's φ)."""
    endpoints, jacobians = r.kinematics.compute(q)
    return np.concatenate([b.constraint_rows(q, endpoints, jacobians, 1.0, r.phi, 0.0, None).h
                           for b in (r.body if body is None else body)])


def test_the_method_is_configured() -> None:
    assert isinstance(build_pipeline(conf_with(method="linear")).retargeter, Retargeter)
    assert isinstance(build_pipeline(load_config(environ={})).retargeter, Retargeter)  # the default: paper eq. 2


def test_a_pose_the_robot_can_take_is_reproduced_exactly() -> None:
    """Person directions taken from the robot's own arms at random poses, approached over a second:
    the target's arms point the same way (< 0.5°) and the waist is eq. 2's."""
    r = retargeter()
    kin = RobotKinematics(r.kinematics.spec)
    rng = np.random.default_rng(3)
    home = kin.q_home
    reached = 0
    for _ in range(30):
        goal = home.copy()
        goal[2:] = rng.uniform(kin.q_min[2:] * 0.6, kin.q_max[2:] * 0.6)
        directions = robot_arm_directions(kin.compute(goal)[0], 0.05)
        if np.isnan(directions).any() or (self_h(r, goal) < 0.02).any():
            continue  # only poses well clear of the robot's own body
        reached += 1
        r.hold(home)
        start = robot_arm_directions(kin.compute(home)[0], 0.05)
        for k in range(1, 31):  # the person moves there over a second
            w = k / 30
            d = (1 - w) * start + w * directions
            points, valid = skeleton((d[0], d[1]), (d[2], d[3]))
            q = r.track(pose(points, valid, k / FPS))[0]
        assert errors_deg(r, q, points, valid, False).max() < 0.5
        np.testing.assert_allclose(q[:2], home[:2])
    assert reached >= 6


def test_the_target_keeps_clear_of_the_robots_own_body() -> None:
    """Arms hanging straight down, a little inwards: the robot's arm cannot point there without
    entering its torso or pelvis. Without the body the target does (some self h < 0); with it every
    self pair keeps h ≥ the clearance (φ), and the arms still point down within 40°."""
    inward = np.array([[0.15, 0.0, -1.0], [0.1, 0.1, -1.0]])  # left arm: +x is the person's right
    points, valid = skeleton((inward[0], inward[1]), (inward[0] * [-1, 1, 1], inward[1] * [-1, 1, 1]))
    free = retargeter()
    free.body = ()
    clear = retargeter()
    for k in range(10):
        q_free = free.track(pose(points, valid, k / FPS))[0]
        q_clear = clear.track(pose(points, valid, k / FPS))[0]
    assert self_h(free, q_free, clear.body).min() < 0.0
    assert self_h(clear, q_clear).min() >= clear.clearance - 1e-3
    assert errors_deg(clear, q_clear, points, valid, False).max() < 40


@pytest.mark.parametrize("mirror", [False, True])
def test_facing_the_person_the_robot_takes_the_other_arm(mirror: bool) -> None:
    """The person's right arm forward, the left hanging: side by side the robot's right arm goes
    forward; facing (mirror) its left."""
    r = retargeter(mirror=mirror)
    points, valid = skeleton((DOWN, DOWN), (FORWARD, FORWARD))
    for k in range(10):
        q = r.track(pose(points, valid, k / FPS))[0]
    robot = robot_arm_directions(r.kinematics.compute(q)[0], 0.05)
    forward_arm = slice(0, 2) if mirror else slice(2, 4)
    hanging_arm = slice(2, 4) if mirror else slice(0, 2)
    assert (robot[forward_arm] @ FORWARD > np.cos(np.radians(20))).all()
    assert (robot[hanging_arm] @ DOWN > np.cos(np.radians(30))).all()


def test_an_arm_whose_keypoints_are_missing_keeps_its_target() -> None:
    r = retargeter()
    points, valid = skeleton((FORWARD, FORWARD), (OUT_LEFT * [-1, 1, 1], OUT_LEFT * [-1, 1, 1]))
    for k in range(10):
        q_before = r.track(pose(points, valid, k / FPS))[0]
    moved, _ = skeleton((DOWN, DOWN), (DOWN, DOWN))
    valid_now = valid.copy()
    valid_now[K["left_elbow"]] = False
    q_after = r.track(pose(moved, valid_now, 10 / FPS))[0]
    np.testing.assert_array_equal(q_after[2:5], q_before[2:5])  # the left arm holds
    assert np.abs(q_after[5:] - q_before[5:]).max() > 0.05  # the right follows


def test_the_target_moves_no_faster_than_the_velocity_bound() -> None:
    """The person's arm from hanging to overhead in one frame: the target goes at u_max."""
    r = retargeter()
    down, valid = skeleton((DOWN, DOWN), (DOWN, DOWN))
    up, _ = skeleton((-DOWN, -DOWN), (-DOWN, -DOWN))
    q0 = r.track(pose(down, valid, 0.0))[0]
    q1 = r.track(pose(up, valid, 1 / FPS))[0]
    assert (np.abs(q1 - q0) <= r.max_speed / FPS + 1e-12).all()
    assert np.abs(q1 - q0)[2:].max() == pytest.approx(r.max_speed[2:].max() / FPS)


def test_rates_are_the_low_passed_difference_and_restart_with_the_persons() -> None:
    """An arm raised forward at a steady 1 rad/s: after the low-pass settles the rate of its shoulder
    pitch is the targets' own difference quotient; a state whose person rates restarted (all of the
    arm's θ̇ 0) restarts the arm's rate at 0; the waist's rate is eq. 2's (S θ̇)."""
    r = retargeter()
    targets, rates = [], []
    for k in range(40):
        angle = 0.2 + k / FPS  # rad from hanging, 1 rad/s
        d = np.array([0.0, np.sin(angle), -np.cos(angle)])
        points, valid = skeleton((d, d), (DOWN, DOWN))
        q, dq = r.track(pose(points, valid, k / FPS, rate=0.5))
        targets.append(q)
        rates.append(dq)
    targets, rates = np.array(targets), np.array(rates)
    quotient = np.diff(targets, axis=0) * FPS
    np.testing.assert_allclose(rates[-1, 2:5], quotient[-1, 2:5], atol=0.05)
    assert abs(rates[-1, 2]) > 0.5  # the shoulder pitch does move
    np.testing.assert_allclose(rates[:, :2], 0.5 * np.array(r.linear.scale[:2]) * np.ones((40, 2)))
    angle = 0.2 + 40 / FPS
    d = np.array([0.0, np.sin(angle), -np.cos(angle)])
    points, valid = skeleton((d, d), (DOWN, DOWN))
    _, dq = r.track(pose(points, valid, 40 / FPS, rate=0.0))
    np.testing.assert_array_equal(dq, 0.0)


def test_the_compiled_normal_equations_match_finite_differences() -> None:
    """JᵀJ + λI and Jᵀ(p − d) of the kernel against J by central differences of d(q) = R û(q) (the
    robot's torso frame R held at q, as the kernel holds it), at random poses and targets."""
    from services.safety.direction_kernel import direction_normal_equations
    from shared.torso_frame import ARM_CAPSULES as capsules, FRAME_CAPSULES as frame, robot_arm_rotation

    kin = RobotKinematics(retargeter().kinematics.spec)
    rng = np.random.default_rng(7)
    moving = np.arange(2, 8)
    for _ in range(20):
        q = rng.uniform(kin.q_min, kin.q_max)
        ends = kin.compute(q)[0].copy()
        rotation = robot_arm_rotation(ends, 0.05)

        def directions(x: np.ndarray) -> np.ndarray:
            e = kin.compute(x)[0]
            axis = e[capsules, 1] - e[capsules, 0]
            return (axis / np.linalg.norm(axis, axis=1, keepdims=True)) @ rotation.T

        jac = np.zeros((12, 6))
        for j, joint in enumerate(moving):
            step = np.zeros(8)
            step[joint] = 1e-6
            jac[:, j] = ((directions(q + step) - directions(q - step)) / 2e-6).reshape(-1)
        targets = rng.normal(size=(4, 3))
        targets /= np.linalg.norm(targets, axis=1, keepdims=True)
        hessian, gradient = np.empty((6, 6)), np.empty(6)
        ends, jacobians = kin.compute(q)
        assert direction_normal_equations(ends, jacobians, frame, capsules, targets, moving, 0.5, 0.05, hessian, gradient)
        np.testing.assert_allclose(hessian, jac.T @ jac + 0.5 * np.eye(6), atol=1e-6)
        np.testing.assert_allclose(gradient, jac.T @ (targets - directions(q)).reshape(-1), atol=1e-6)
