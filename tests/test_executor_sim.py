"""The executor's MuJoCo simulation core (services.executor.mujoco: model, contacts, sim), in-process, with our shipped
G1-class model and with Menagerie's real G1 (meshes): welded base, joint servos, the person's
capsules, and contact counting including the architecture §10 trap (a mocap capsule inside the welded
pelvis, which MuJoCo's own contact list never reports)."""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterator

import mujoco
import numpy as np
import pytest

from services.executor.mujoco.executor import MujocoExecutor, open_viewer
from services.executor.mujoco.model import STICTION_IMPEDANCE, PDGains, SimModelError, servo_name
from services.executor.mujoco.sim import SimRobot
from shared.config import ExecutorConfig
from shared.names import CAPSULE_NAMES
from shared.robot_spec import RobotSpec, default_robot_spec_path, load_robot_spec
from tests.support.team import G1_MJCF

GAINS = PDGains.from_config(ExecutorConfig())
OURS = load_robot_spec(default_robot_spec_path())
TORSO = CAPSULE_NAMES.index("torso")
LEFT_FOREARM = CAPSULE_NAMES.index("left_forearm")


def model_spec(which: str) -> RobotSpec:
    if which == "ours":
        return OURS
    if not G1_MJCF.is_file():
        pytest.skip(f"real G1 model not found at {G1_MJCF} (set SAFEMIMIC_TEAM_SHARED to the team folder)")
    return OURS.with_model(G1_MJCF)


@pytest.fixture(scope="module", params=["ours", "real_g1"])
def sim(request) -> SimRobot:
    robot = SimRobot(model_spec(request.param), GAINS)
    yield robot


@pytest.fixture(autouse=True)
def _fresh(request) -> None:
    if "sim" in request.fixturenames:
        request.getfixturevalue("sim").reset()


def with_joints(sim: SimRobot, **angles: float) -> np.ndarray:
    """Home with some imitation joints (``name_joint=value``, rad) changed."""
    q = sim.q_home.copy()
    for name, value in angles.items():
        q[sim.joint_names.index(name)] = value
    return q


def person_capsules(capsule: int, a, b, radius: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Only capsule ``capsule`` valid, from a to b (m) with ``radius``; the others invalid."""
    capsules = np.zeros((7, 2, 3))
    capsules[capsule] = a, b
    valid = np.zeros(7, bool)
    valid[capsule] = True
    return capsules, np.full(7, radius), valid


# ------------------------------------------------------------------------------- the robot
def test_base_is_welded_and_home_holds_without_contacts(sim: SimRobot) -> None:
    assert sim.model.nq == sim.model.nv == 29, "the free joint must be gone: 29 hinge joints"
    assert sim.home_contacts == (), "our home keeps every link apart; so does Menagerie's G1 at our home"
    sim.step(500)  # 1 s
    pelvis = sim.data.body(sim.spec.base_body).xpos
    np.testing.assert_allclose(pelvis, [0.0, 0.0, sim.spec.base_height], atol=1e-12)
    np.testing.assert_allclose(sim.q, sim.q_home, atol=1e-3)
    held = [j for j in range(sim.model.njnt) if sim.model.joint(j).name not in sim.joint_names]
    np.testing.assert_allclose(sim.data.qpos[held], 0.0, atol=1e-3)  # every other joint: home = 0
    assert sim.contacts().empty


def test_step_command_is_followed_within_half_a_second(sim: SimRobot) -> None:
    target = sim.q_home + np.array([0.2, 0.2, -0.4, 0.3, -0.4, -0.4, -0.3, -0.4])  # arms out/forward
    applied = sim.set_command(target)
    np.testing.assert_array_equal(applied, target)
    sim.step(round(0.5 / sim.timestep))
    assert np.abs(sim.q - target).max() < 0.02, sim.q - target
    assert np.abs(sim.dq).max() < 0.2
    assert sim.contacts().empty


def test_a_motor_asked_for_more_than_its_torque_is_saturated(sim: SimRobot) -> None:
    """At rest at home no motor is at its limit; a 0.5 rad step on the left shoulder pitch asks its
    servo for kp · 0.5 rad, beyond the G1's 25 N·m, so that motor (and no other) gives its whole
    torque until the joint has come most of the way."""
    np.testing.assert_allclose(sim.torque_limit, [50, 50, 25, 25, 25, 25, 25, 25])
    sim.set_command(sim.q_home)
    sim.step(50)
    assert not sim.saturated.any()
    target = sim.q_home.copy()
    target[2] -= 0.5
    sim.set_command(target)
    sim.step(1)
    assert sim.saturated[2] and sim.saturated.sum() == 1, sim.saturated
    sim.step(round(0.5 / sim.timestep))
    assert not sim.saturated.any()


def test_velocity_feed_forward_reduces_tracking_lag(sim: SimRobot) -> None:
    """A ramp at 1 rad/s on the left elbow: with its velocity fed forward the lag nearly vanishes."""
    lags = []
    for feed_forward in (False, True):
        sim.reset()
        elbow = sim.joint_names.index("left_elbow_joint")
        for k in range(1, 151):  # 0.3 s
            q = sim.q_home.copy()
            q[elbow] -= 1.0 * k * sim.timestep
            dq = np.zeros(8)
            dq[elbow] = -1.0 if feed_forward else 0.0
            sim.set_command(q, dq)
            sim.step()
        lags.append(abs(sim.q[elbow] - q[elbow]))
    assert lags[1] < 0.3 * lags[0], lags


def _track_swing(sim: SimRobot, feed_forward: bool) -> tuple[np.ndarray, float]:
    """Max |q − q_ref| (8,) over 1.2 s of an acceleration-bounded swing: both shoulders pitch
    ±0.6 rad at 3 Hz-ish (peak 40 rad/s²) and the waist pitch ±0.15 rad: what an imitated punch
    looks like after the safety layer's acceleration bound; and the largest deviation of a held
    joint (waist yaw, shoulder yaws, wrists) from home (rad)."""
    sim.reset()
    model = sim.model
    held = np.setdiff1d(np.arange(model.nu), [model.actuator(servo_name(j)).id for j in sim.joint_names])
    held_qpos = model.jnt_qposadr[model.actuator_trnid[held, 0]]
    held_home = sim.data.qpos[held_qpos].copy()
    held_worst = 0.0
    pitch = [sim.joint_names.index(j) for j in ("left_shoulder_pitch_joint", "right_shoulder_pitch_joint")]
    waist = sim.joint_names.index("waist_pitch_joint")
    w = 2 * np.pi * 1.3
    worst = np.zeros(8)
    for k in range(round(1.2 / sim.timestep)):
        t = k * sim.timestep
        q, dq, ddq = sim.q_home.copy(), np.zeros(8), np.zeros(8)
        for j, amp in ((pitch[0], -0.6), (pitch[1], 0.6), (waist, 0.15)):
            q[j] += amp * np.sin(w * t)
            dq[j], ddq[j] = amp * w * np.cos(w * t), -amp * w * w * np.sin(w * t)
        sim.set_command(q, dq, ddq)
        sim.step()
        if t > 0.2:  # past the start-up transient
            worst = np.maximum(worst, np.abs(sim.q - q))
            held_worst = max(held_worst, float(np.abs(sim.data.qpos[held_qpos] - held_home).max()))
    return worst, held_worst


def test_torque_feed_forward_follows_an_acceleration_bounded_swing(sim: SimRobot) -> None:
    """M(q) q̈_ref + Coriolis fed forward: the shoulders and the waist (which the swinging arms
    push) follow a fast swing several times closer than with position + velocity feed-forward, and
    the joints held at home, fed the swing's reaction, stay there several times closer too."""
    with_ff, held_with = _track_swing(sim, True)
    sim.gains = PDGains(**{**GAINS.__dict__, "torque_feedforward": False})
    try:
        without, held_without = _track_swing(sim, False)
    finally:
        sim.gains = GAINS
    assert held_with < 0.5 * held_without, (held_with, held_without)  # measured: 0.019 against 0.047 rad (waist yaw)
    assert with_ff.max() < 0.4 * without.max(), (with_ff, without)  # measured: 0.03 against 0.09 rad
    waist = sim.joint_names.index("waist_pitch_joint")
    assert with_ff[waist] < 0.3 * without[waist], (with_ff, without)  # measured: 0.003 against 0.019 rad


def _brake_at_once(sim: SimRobot, joint: str, speed: float, stop: bool) -> tuple[float, float]:
    """``joint`` swung from home up to ``speed`` (rad/s, at 60 rad/s², then 0.1 s at that speed), then
    commanded to rest where its command is (q̇_ref 0 from one step to the next, ``stop`` says whether
    that command is a protective stop): faster than its motor can brake. Returns how far the joint
    overshoots the command in its direction of motion (rad) and its speed 0.1 s later (rad/s)."""
    sim.reset()
    j, dt = sim.joint_names.index(joint), sim.timestep
    q, dq, ddq = sim.q_home.copy(), np.zeros(8), np.zeros(8)
    for k in range(round((abs(speed) / 60.0 + 0.1) / dt)):
        v = np.sign(speed) * min(60.0 * (k + 1) * dt, abs(speed))
        ddq[j], dq[j] = (v - dq[j]) / dt, v
        q[j] += v * dt
        sim.set_command(q, dq, ddq)
        sim.step()
    overshoot, later = 0.0, round(0.1 / dt)
    for k in range(later):
        sim.set_command(q, stop=stop)
        sim.step()
        overshoot = max(overshoot, float(np.sign(speed) * (sim.q[j] - q[j])))
    return overshoot, abs(float(sim.dq[j]))


@pytest.mark.parametrize("joint", ["left_shoulder_pitch_joint", "right_shoulder_roll_joint"])  # forward, outward
def test_a_protective_stop_damps_the_servos_so_an_arm_braked_at_once_overshoots_less(sim: SimRobot, joint: str) -> None:
    """In a stop the imitation joints damp with kd × ``stop_damping`` (2: the shoulders' damping ratio
    0.45–0.48 → 0.90–0.95 at home), the velocity feed-forward through that kd. Commanded to rest at
    once from 4 rad/s (a stop's command settled onto the robot does that), a shoulder runs on less far
    past the command and is slower 0.1 s later (measured, both models: pitch 80 → 61 mrad and 1.07 →
    0.56 rad/s; roll 77 → 58 mrad and 0.99 → 0.50 rad/s). The next command that is not a stop
    restores kd, as does a reset."""
    assert sim.gains.stop_damping == 2.0
    act = sim.model.actuator(servo_name(joint)).id
    kd = sim.gains.of(joint, True)[1]
    plain, plain_speed = _brake_at_once(sim, joint, -4.0, stop=False)
    assert sim.model.actuator_biasprm[act, 2] == pytest.approx(-kd)
    damped, damped_speed = _brake_at_once(sim, joint, -4.0, stop=True)
    assert sim.model.actuator_biasprm[act, 2] == pytest.approx(-2.0 * kd)
    q = sim.q
    sim.set_command(q)
    assert sim.model.actuator_biasprm[act, 2] == pytest.approx(-kd)
    assert damped < 0.9 * plain, (damped, plain)
    assert damped_speed < 0.7 * plain_speed, (damped_speed, plain_speed)
    sim.set_command(q, stop=True)
    sim.reset()
    assert sim.model.actuator_biasprm[act, 2] == pytest.approx(-kd), "a reset restores kd"


WAIST_JOINTS = ("waist_yaw_joint", "waist_roll_joint", "waist_pitch_joint")


def test_every_waist_servo_is_about_critically_damped(sim: SimRobot) -> None:
    """The waist carries the whole upper body: its servos' damping ratio ζ = kd / (2 √(kp I)), with I
    the joint's own inertia at home (the joint-space mass matrix's diagonal: the links above it,
    armature included), is at least 0.9 for the imitated roll and pitch and for the yaw held at
    home (measured: roll 0.91, pitch 1.16, yaw 1.09). At ``hold_kd`` = 10 the held yaw had ζ 0.36:
    the arms' reaction rang it, and a robot at rest kept turning its forearm into a person at
    1–3 mm/s (docs/safety-measurements.md "The held waist yaw")."""
    model, data = sim.model, mujoco.MjData(sim.model)
    data.qpos[:] = sim.data.qpos  # home
    mujoco.mj_forward(model, data)
    inertia = np.zeros((model.nv, model.nv))
    mujoco.mj_fullM(model, data, inertia)
    for joint in WAIST_JOINTS:
        dof = model.jnt_dofadr[model.joint(joint).id]
        kp, kd = GAINS.of(joint, joint in sim.joint_names)
        zeta = kd / (2.0 * np.sqrt(kp * inertia[dof, dof]))
        assert zeta >= 0.9, (joint, round(zeta, 2))


def test_the_held_waist_yaw_comes_back_from_the_arms_reaction_without_swinging_past_home(sim: SimRobot) -> None:
    """Both shoulders pitch opposite ways (a torque about the vertical, as in a punch with the other
    arm pulled back) and brake to rest at the arms' acceleration bound (60 rad/s²). The waist yaw,
    held at home, takes the reaction; once the arms are at rest it returns without swinging past
    home by more than 15 % of its deflection (measured: 11 %; 38 % at the old hold_kd 10)."""
    yaw = sim.model.jnt_qposadr[sim.model.joint("waist_yaw_joint").id]
    home = sim.data.qpos[yaw]
    pitch = [sim.joint_names.index(j) for j in ("left_shoulder_pitch_joint", "right_shoulder_pitch_joint")]

    def swing(t: float) -> np.ndarray:
        accel = np.zeros(8)
        accel[pitch] = np.array([1.0, -1.0]) * (60.0 if t < 0.1 else -60.0 if t < 0.2 else 0.0)
        return accel

    deflection = np.array([sim.data.qpos[yaw] - home for _ in _drive(sim, swing, 0.8)])
    at_rest = deflection[round(0.2 / sim.timestep):]
    sign = np.sign(deflection[np.argmax(np.abs(deflection))])
    assert np.abs(deflection).max() > 3e-4, "the swing was expected to deflect the held yaw"
    assert (sign * at_rest).min() > -0.15 * np.abs(deflection).max(), (np.abs(deflection).max(), (sign * at_rest).min())


def _track_bang_bang(sim: SimRobot, lead: bool) -> float:
    """Max |q − q_ref| of the right shoulder pitch at the end of each period, over 0.8 s of a
    command accelerating at ±60 rad/s² (the default accel_max of the arms), q_ref = q_cbf⁺."""
    j = sim.joint_names.index("right_shoulder_pitch_joint")

    def bang_bang(t: float) -> np.ndarray:
        accel = np.zeros(8)
        accel[j] = 60.0 if t % 0.4 < 0.1 or t % 0.4 >= 0.3 else -60.0
        return accel

    return max(abs(sim.q[j] - q[j]) for q in _drive(sim, bang_bang, 0.8, lead))


def _drive(sim: SimRobot, accel: Callable[[float], np.ndarray], seconds: float, lead: bool = False) -> Iterator[np.ndarray]:
    """From rest at home, command the joints along u̇ = ``accel(t)`` (8,) rad/s² for ``seconds``: each
    step sends q_cbf⁺ (the end of its period, with u* and u̇; ``lead``: the servos follow the command
    over the period) and steps the simulation; yields the commanded q (8,) after each step."""
    sim.reset()
    dt, q, u = sim.timestep, sim.q_home.copy(), np.zeros(8)
    for k in range(round(seconds / dt)):
        u_next = u + accel(k * dt) * dt
        q = q + u_next * dt
        sim.set_command(q, u_next, (u_next - u) / dt, lead_s=dt if lead else 0.0)
        u = u_next
        sim.step()
        yield q


def test_servos_follow_the_command_over_its_period_not_ahead_of_it(sim: SimRobot) -> None:
    """A command's q is the end of its period (q_cbf⁺ = q_cbf + Δt u*): servos aimed there from
    the period's start run ahead of the command (extra torque kp Δt |u|); following the command's
    trajectory over the period they stay several times closer (measured 0.0010 against
    0.0130 rad)."""
    with_lead, without = _track_bang_bang(sim, True), _track_bang_bang(sim, False)
    assert with_lead < 0.4 * without, (with_lead, without)
    with pytest.raises(ValueError, match="lead_s"):
        sim.set_command(sim.q_home, lead_s=-0.001)


def _slow_ramp_error(sim: SimRobot) -> float:
    """Max |q − q_ref| of the right shoulder pitch over the last 0.5 s of a 0.3 rad/s ramp."""
    sim.reset()
    j = sim.joint_names.index("right_shoulder_pitch_joint")
    q, dq, worst = sim.q_home.copy(), np.zeros(8), 0.0
    dq[j] = -0.3
    for k in range(round(1.0 / sim.timestep)):
        q = q + dq * sim.timestep
        sim.set_command(q, dq, np.zeros(8), lead_s=sim.timestep)
        sim.step()
        if k * sim.timestep > 0.5:
            worst = max(worst, abs(sim.q[j] - q[j]))
    return worst


def test_the_joints_friction_is_fed_forward_with_the_commanded_velocity(sim: SimRobot) -> None:
    """A slow ramp lags by the joint's Coulomb friction over kp (0.3 N·m / 150 N·m/rad = 0.002 rad:
    millimetres at the hand, all of a self pair's sliding contact) unless the servo adds the friction
    in the direction of the commanded velocity."""
    with_ff = _slow_ramp_error(sim)
    sim.gains = PDGains(**{**GAINS.__dict__, "torque_feedforward": False})
    try:
        without = _slow_ramp_error(sim)
    finally:
        sim.gains = GAINS
    assert without > 0.0015 and with_ff < 0.25 * without, (with_ff, without)


def imitation_dofs(sim: SimRobot) -> np.ndarray:
    """The imitation joints' dof indices in ``sim.model``."""
    return sim.model.jnt_dofadr[[sim.model.joint(name).id for name in sim.joint_names]]


def _creep_within_friction(sim: SimRobot) -> np.ndarray:
    """(8,) rad/s: each imitation joint's speed 0.5–0.6 s after being commanded 0.9 f/kp away
    from where it rests (its servo's torque stays below the joint's dry friction f)."""
    sim.reset()
    kp = np.array([sim.gains.of(joint, True)[0] for joint in sim.joint_names])
    sim.set_command(sim.q_home + 0.9 * sim.model.dof_frictionloss[imitation_dofs(sim)] / kp)
    sim.step(round(0.5 / sim.timestep))
    before = sim.q
    sim.step(round(0.1 / sim.timestep))
    return np.abs(sim.q - before) / 0.1


def test_a_servo_held_within_its_friction_does_not_creep(sim: SimRobot) -> None:
    """Stiction: a joint loaded below its dry friction stays where it is (a geared joint does). With
    MuJoCo's default soft friction (impedance 0.9–0.95) the same servos drift ≈ 1 mrad/s: a robot
    commanded to stand still near a person would keep closing in on them."""
    assert (sim.model.dof_solimp[imitation_dofs(sim), :2] == STICTION_IMPEDANCE).all()
    held = _creep_within_friction(sim)
    default = sim.model.dof_solimp[:, :2].copy()
    sim.model.dof_solimp[:, :2] = 0.9, 0.95  # MuJoCo's default
    try:
        soft = _creep_within_friction(sim)
    finally:
        sim.model.dof_solimp[:, :2] = default
    assert held.max() < 2e-5 and soft.max() > 5e-4, (held, soft)


def test_arm_commanded_into_the_torso_is_a_robot_robot_contact(sim: SimRobot) -> None:
    sim.set_command(with_joints(sim, left_shoulder_pitch_joint=-0.6, left_shoulder_roll_joint=-0.8))
    sim.step(250)
    pairs = {(c.body_a, c.body_b) for c in sim.contacts().robot_robot}
    assert ("left_shoulder_yaw_link", "torso_link") in pairs, pairs
    assert all(c.depth > 0 for c in sim.contacts().robot_robot)


# ------------------------------------------------------------------------------- the person
def test_human_capsule_inside_the_welded_pelvis_is_counted(sim: SimRobot) -> None:
    """architecture §10: MuJoCo skips contacts between two DOF-less bodies (mocap capsule, welded pelvis)."""
    sim.set_human(*person_capsules(TORSO, [0.0, -0.02, 0.72], [0.0, 0.02, 0.72], 0.03))
    sim.step()
    assert sim.data.ncon == 0, "the person collides with nothing: it is measured, never simulated"
    report = sim.contacts()
    assert [(c.body_a, c.body_b) for c in report.robot_human] == [("pelvis", "torso")]
    assert report.robot_human[0].depth > 0.02
    assert report.robot_robot == ()


def test_human_capsule_is_resized_at_runtime_and_parked_when_invalid(sim: SimRobot) -> None:
    """A forearm capsule pointing forward from the left elbow: short it stays clear, long it reaches
    the arm (its centre is then 0.45 m away: MuJoCo's bounding volumes must follow the new size),
    invalid it is gone."""
    elbow = sim.data.body("left_elbow_link").xpos.copy()
    far_end = elbow + [0.9, 0.0, 0.0]
    for near_x, valid, touches in [(0.2, True, False), (0.0, True, True), (0.0, False, False)]:
        capsules, radii, flags = person_capsules(LEFT_FOREARM, elbow + [near_x, 0.0, 0.0], far_end, 0.03)
        flags[LEFT_FOREARM] = valid
        sim.set_human(capsules, radii, flags)
        sim.step()
        hits = {(c.body_a, c.body_b) for c in sim.contacts().robot_human}
        assert any(b == "left_forearm" and a.startswith("left_") for a, b in hits) == touches, (near_x, valid, hits)
        assert all(b == "left_forearm" for _, b in hits)


def test_human_capsules_touch_nothing_and_never_push_the_robot(sim: SimRobot) -> None:
    """The person's capsules collide with nothing (not each other, not the robot): a person pressed
    into the arm is measured as a contact, yet the arm stays where its servo holds it."""
    capsules = np.tile([[2.0, 0.0, 0.5], [2.0, 0.0, 1.5]], (7, 1, 1))  # all overlapping, away from the robot
    sim.set_human(capsules, np.full(7, 0.1), np.ones(7, bool))
    sim.step()
    assert sim.data.ncon == 0 and sim.contacts().empty
    human = [sim.model.geom(f"human_{c}").id for c in CAPSULE_NAMES]
    assert (sim.model.geom_contype[human] == 0).all() and (sim.model.geom_conaffinity[human] == 0).all()
    elbow = sim.data.body("left_elbow_link").xpos.copy()
    sim.set_human(*person_capsules(LEFT_FOREARM, elbow + [-0.3, 0.0, 0.0], elbow + [0.3, 0.0, 0.0], 0.08))
    sim.step(250)
    assert any(c.capsule == "left_forearm" for c in sim.surface_contacts())
    np.testing.assert_allclose(sim.q, sim.q_home, atol=2e-3)


def test_bad_inputs_are_refused_or_neutralised(sim: SimRobot) -> None:
    with pytest.raises(ValueError, match="shape"):
        sim.set_command(np.zeros(7))
    with pytest.raises(ValueError, match="finite"):
        sim.set_command(np.full(8, np.nan))
    applied = sim.set_command(np.full(8, 100.0))
    np.testing.assert_array_equal(applied, sim.q_max)
    with pytest.raises(ValueError, match="expected capsules"):
        sim.set_human(np.zeros((6, 2, 3)), np.zeros(6), np.ones(6, bool))
    far = np.tile([[1e9, 0.0, 0.0], [1e9, 0.0, 1.0]], (7, 1, 1))  # finite but absurd: parked
    far[0] = np.nan
    sim.set_human(far, np.full(7, 0.1), np.ones(7, bool))
    sim.step(10)
    assert np.isfinite(sim.data.qpos).all() and sim.contacts().robot_human == ()


# ------------------------------------------------------------------------------- construction
@pytest.mark.parametrize("which", ["ours", "real_g1"])
def test_pairs_touching_at_home_are_excluded_and_listed(which: str) -> None:
    spec = model_spec(which)
    home = {**spec.home, "left_shoulder_roll_joint": -0.1, "left_elbow_joint": 1.9}  # upper arm on the chest
    robot = SimRobot(spec.model_copy(update={"home": home}), GAINS)
    assert ("left_shoulder_yaw_link", "torso_link") in robot.home_contacts
    robot.step(100)
    assert robot.contacts().robot_robot == ()
    # the other arm is not excluded: pushed into the torso it is still counted
    robot.set_command(with_joints(robot, right_shoulder_pitch_joint=-0.6, right_shoulder_roll_joint=0.8))
    robot.step(250)
    assert ("right_shoulder_yaw_link", "torso_link") in {(c.body_a, c.body_b) for c in robot.contacts().robot_robot}


def test_model_errors_are_clear(tmp_path) -> None:
    with pytest.raises(SimModelError, match="does not exist"):
        SimRobot(OURS.with_model(tmp_path / "missing.xml"), GAINS)
    broken = tmp_path / "broken.xml"
    broken.write_text("<mujoco><worldbody><body name='pelvis'>")
    with pytest.raises(SimModelError, match="cannot load"):
        SimRobot(OURS.with_model(broken), GAINS)
    with pytest.raises(SimModelError, match="no_such_joint"):
        SimRobot(OURS, PDGains(1.0, 0.1, 1.0, 0.1, per_joint={"no_such_joint": (1.0, 0.1)}))
    with pytest.raises(SimModelError, match="base body"):
        SimRobot(OURS.model_copy(update={"base_body": "nowhere"}), GAINS)


def test_executor_splits_the_control_period_into_physics_steps() -> None:
    executor = MujocoExecutor(OURS, GAINS, period=1 / 200)
    assert executor.substeps == 3 and executor.sim.timestep == pytest.approx(1 / 600)
    start = executor.sim.time
    executor.tick()
    assert executor.sim.time - start == pytest.approx(1 / 200)
    reading = executor.read_state()
    np.testing.assert_allclose(reading.q, executor.q_home, atol=1e-4)
    assert mujoco.mj_name2id(executor.sim.model, mujoco.mjtObj.mjOBJ_JOINT, "floating_base_joint") == -1


def test_viewer_without_a_usable_display_warns_instead_of_exiting(monkeypatch, caplog) -> None:
    """MuJoCo's viewer exits the process when GLFW fails: a display that cannot open must be
    detected first (here an X display nobody serves)."""
    monkeypatch.setenv("DISPLAY", ":4711")
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    robot = SimRobot(OURS, GAINS)
    with caplog.at_level(logging.WARNING, logger="safemimic.executor"):
        assert open_viewer(robot.model, robot.data) is None
    assert "running headless" in caplog.text
