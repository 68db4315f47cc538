"""The G1 executor's tick logic without DDS: frames, hand-over ramps, limits, watchdogs, faults,
locked waists, the low-level mode and the last check before sending. Time is simulated: every
call gets an explicit monotonic time."""

from __future__ import annotations

import numpy as np
import pytest

from services.executor.g1.control import TORQUE_FAULT_SAMPLES, G1Controller, Phase, check_frame
from services.executor.g1.errors import G1StartError
from services.executor.g1.state import G1State
from services.executor.g1.frames import lowcmd_crc
from services.executor.g1.layout import ARM_SDK_HOLD_GAINS, G1_JOINTS, LOWCMD_HOLD_GAINS, WEIGHT_SLOT
from services.safety.kinematics import RobotKinematics
from shared.config import G1Config, load_config
from shared.robot_spec import configured_robot_spec, default_robot_spec_path, load_robot_spec

SPEC = load_robot_spec(default_robot_spec_path())
PERIOD = 0.002
SLOTS = np.array([13, 14, 15, 16, 18, 22, 23, 25])  # the 8 imitation joints
ARMS = SLOTS[2:]
#: a standing pose (slot order): arms a little forward and out, elbows bent
POSE = np.zeros(29)
POSE[[15, 16, 18, 22, 23, 25]] = [0.3, 0.25, 0.9, 0.3, -0.25, 0.9]
HW_LOWER = np.array([j.lower for j in G1_JOINTS])
HW_UPPER = np.array([j.upper for j in G1_JOINTS])


def conf(**overrides) -> G1Config:
    return G1Config(**{"ramp_in_s": 0.5, "ramp_out_s": 0.4, **overrides})


def state(t: float, q: np.ndarray = POSE, dq: np.ndarray | None = None, tau: np.ndarray | None = None,
          mode_machine: int = 5) -> G1State:
    return G1State(q=np.array(q, float), dq=np.zeros(29) if dq is None else dq,
                   tau_est=np.zeros(29) if tau is None else tau, mode_machine=mode_machine, received=t)


class Robot:
    """A controller driven tick by tick; the robot tracks the sent targets of commanded slots
    exactly when ``follow`` (else it stays put)."""

    def __init__(self, c: G1Config | None = None, mode_machine: int = 5, follow: bool = True) -> None:
        self.ctl = G1Controller(SPEC, c or conf(), PERIOD)
        self.t = 0.0
        self.q = POSE.copy()
        self.follow = follow
        self.ctl.attach(state(self.t, self.q, mode_machine=mode_machine))
        self.frames: list[np.ndarray] = []

    def run(self, seconds: float, command: np.ndarray | None = None, states: bool = True) -> list[np.ndarray]:
        frames = []
        for _ in range(round(seconds / PERIOD)):
            self.t += PERIOD
            if states:
                self.ctl.update_state(state(self.t, self.q))
            if command is not None:
                self.ctl.command(self.t, command, np.zeros(8))
            frame = self.ctl.step(self.t)
            assert frame is not None
            frames.append(frame)
            if self.follow:
                on = frame["motor_cmd"]["mode"][:29] == 1
                self.q = np.where(on, frame["motor_cmd"]["q"][:29], self.q)
        self.frames += frames
        return frames


def weights(frames: list[np.ndarray]) -> np.ndarray:
    return np.array([float(f["motor_cmd"]["q"][WEIGHT_SLOT]) for f in frames])


def targets(frames: list[np.ndarray], slots: np.ndarray = SLOTS) -> np.ndarray:
    return np.array([f["motor_cmd"]["q"][slots].astype(float) for f in frames])


def test_idle_frames_carry_zero_weight_and_the_measured_pose() -> None:
    robot = Robot(conf(arm_sdk_joints="imitation"))
    frames = robot.run(0.05)  # no command yet
    assert robot.ctl.phase is Phase.IDLE
    f = frames[-1]
    m = f["motor_cmd"]
    assert float(m["q"][WEIGHT_SLOT]) == 0.0
    assert int(f["crc"]) == lowcmd_crc(f)
    assert int(f["mode_machine"]) == 5 and int(f["mode_pr"]) == 0
    imitation_only = np.zeros(29, int)
    imitation_only[SLOTS] = 1
    # only the 8 imitation joints: every other motor keeps the balance controller's values
    np.testing.assert_array_equal(m["mode"][:29], imitation_only)
    others = imitation_only == 0
    assert (m["mode"][29:] == 0).all() and (m["kp"][:29][others] == 0).all() and (m["kd"][:29][others] == 0).all()
    np.testing.assert_allclose(m["q"][SLOTS], POSE[SLOTS], atol=1e-6)
    np.testing.assert_allclose(m["kp"][SLOTS], 60.0)
    np.testing.assert_allclose(m["kd"][SLOTS], 1.5)


def test_by_default_every_upper_body_motor_is_commanded_the_others_held() -> None:
    """As Unitree's arm example: an rt/arm_sdk frame sets all 17 upper-body slots, none left at mode 0,
    kp 0, kd 0 for the firmware to blend in at full weight (``arm_sdk_joints: imitation`` does)."""
    assert G1Config().arm_sdk_joints.value == "upper_body"
    robot = Robot()
    m = robot.run(0.05)[-1]["motor_cmd"]
    np.testing.assert_array_equal(m["mode"][:29], [0] * 12 + [1] * 17)  # upper body only, legs untouched
    assert (m["mode"][29:] == 0).all() and (m["kp"][:12] == 0).all()
    np.testing.assert_allclose(m["q"][12:29], POSE[12:29], atol=1e-6)
    held = [s for s in range(12, 29) if s not in SLOTS]
    np.testing.assert_allclose(m["kp"][held], ARM_SDK_HOLD_GAINS[0])
    np.testing.assert_allclose(m["kd"][held], ARM_SDK_HOLD_GAINS[1])


def test_ramp_in_starts_at_the_measured_pose_and_reaches_full_weight() -> None:
    robot = Robot()
    robot.run(0.02)
    goal = robot.ctl.q_home + np.array([0.1, -0.1, -0.5, 0.3, -0.4, -0.5, -0.3, -0.4])
    frames = robot.run(1.5, goal)
    w = weights(frames)
    assert w[0] == 0.0 and 0 < w[1] <= PERIOD / 0.5 + 1e-6, "the weight starts at 0"
    assert (np.diff(w) >= -1e-7).all() and (np.diff(w) <= PERIOD / 0.5 + 1e-6).all(), "monotone, ≤ one ramp step per tick"
    full = int(np.argmax(w >= 1.0))
    assert w[full] == 1.0 and abs(full * PERIOD - 0.5) < 0.01, f"full weight after {full * PERIOD:.3f} s"
    q = targets(frames)
    speeds = np.array(robot.ctl.conf.max_speed)
    assert (np.abs(q[0] - POSE[SLOTS]) <= speeds * PERIOD + 1e-6).all(), "the first target is the measured pose"
    assert (np.abs(np.diff(q, axis=0)) <= speeds * PERIOD + 1e-5).all(), "targets move at most max_speed"
    np.testing.assert_allclose(q[-1], goal, atol=1e-5)
    assert robot.ctl.phase is Phase.ACTIVE and robot.ctl.counters["ramp_ins"] == 1
    held = [s for s in range(12, 29) if s not in SLOTS]
    np.testing.assert_allclose(targets(frames, np.array(held)), np.tile(POSE[held], (len(frames), 1)), atol=1e-6)


@pytest.mark.parametrize("phase", ["ramp-in", "ramp-out"])
def test_a_stalled_loop_resumes_the_ramp_where_it_was(phase: str) -> None:
    """A tick 0.4 s late (a loaded computer) moves the weight by two control periods' worth, as the
    targets: never the 80 % of the ramp that the clock alone would make of it."""
    robot = Robot()
    goal = robot.ctl.q_home
    robot.run(0.1 if phase == "ramp-in" else 0.8, goal)  # 0.5 s ramp-in: part way / done
    if phase == "ramp-out":
        robot.ctl.begin_stop()
        robot.run(0.1, goal)
    before = robot.ctl.weight
    robot.t += 0.4  # the stall
    robot.ctl.update_state(state(robot.t, robot.q))
    robot.ctl.command(robot.t, goal, np.zeros(8))
    robot.ctl.step(robot.t)
    ramp = robot.ctl.conf.ramp_in_s if phase == "ramp-in" else robot.ctl.conf.ramp_out_s
    assert 0.0 < abs(robot.ctl.weight - before) <= 2 * PERIOD / ramp + 1e-9, (before, robot.ctl.weight)


@pytest.mark.parametrize("upper_body", [False, True])
def test_a_protective_stop_damps_the_imitated_joints_by_stop_damping_until_a_command_that_is_not(upper_body: bool) -> None:
    """kd of the imitated slots × ``stop_damping`` while the newest command is a protective stop; the
    other commanded slots (held at the ramp-in pose) keep their gains; the next command restores kd.
    The frames pass the last check before sending (a latched fault would ramp out)."""
    robot = Robot(conf(stop_damping=2.5, arm_sdk_joints="upper_body" if upper_body else "imitation"))
    goal = robot.ctl.q_home
    robot.run(0.6, goal)
    plain = robot.run(0.01, goal)[-1]["motor_cmd"]
    np.testing.assert_allclose(plain["kd"][SLOTS], 1.5)
    robot.t += PERIOD
    robot.ctl.command(robot.t, goal, np.zeros(8), stop=True)
    stopping = robot.run(0.01)[-1]["motor_cmd"]
    np.testing.assert_allclose(stopping["kd"][SLOTS], 2.5 * 1.5)
    others = np.flatnonzero(plain["mode"][:29] == 1)
    others = others[~np.isin(others, SLOTS)]
    assert len(others) == (9 if upper_body else 0)
    np.testing.assert_array_equal(stopping["kd"][others], plain["kd"][others])
    np.testing.assert_array_equal(stopping["kp"][:29], plain["kp"][:29])
    assert robot.ctl.counters["stop_commands"] == 1
    again = robot.run(0.01, goal)[-1]["motor_cmd"]
    np.testing.assert_allclose(again["kd"][SLOTS], 1.5)
    assert robot.ctl.phase is Phase.ACTIVE and not robot.ctl.faulted


def test_targets_stay_in_range_and_within_torque_reach() -> None:
    robot = Robot(follow=False)  # the arm is blocked: it never moves
    robot.run(0.01)
    far = robot.ctl.q_home.copy()
    far[2] = -5.0  # left shoulder pitch far beyond its range (−3.0892)
    applied = robot.ctl.command(robot.t, far, np.zeros(8))
    assert applied[2] == pytest.approx(-3.0892 + 0.05)
    assert robot.ctl.counters["clipped_commands"] == 1
    frames = robot.run(1.0, far)
    reach = 0.8 * 25.0 / 60.0  # torque_fraction · τ_max / kp
    q = targets(frames)[:, 2]
    assert q.min() == pytest.approx(POSE[15] - reach, abs=1e-5), "held within torque reach of the blocked arm"
    assert robot.ctl.counters["torque_clamped_ticks"] > 0
    limits = SPEC.model_copy(update={"limits": {"left_elbow_joint": (0.5, 1.0)}})
    ctl = G1Controller(limits, conf(), PERIOD)
    assert ctl.command(0.0, np.full(8, 2.0), np.zeros(8))[4] == 1.0  # the description's tighter limit


def test_command_timeout_ramps_out_then_fresh_commands_ramp_in_again() -> None:
    robot = Robot()
    goal = robot.ctl.q_home
    robot.run(0.7, goal)
    assert robot.ctl.phase is Phase.ACTIVE
    frozen = targets(robot.frames[-1:])[0]
    frames = robot.run(0.9)  # commands stop
    w = weights(frames)
    timeout = robot.ctl.conf.command_timeout_s
    assert (w[: round(timeout / PERIOD) - 1] == 1.0).all(), "full weight until the timeout"
    out = w[round(timeout / PERIOD) + 1:]
    assert (np.diff(out) <= 1e-7).all() and out[-1] == 0.0
    assert abs(int(np.argmax(w == 0.0)) * PERIOD - (timeout + 0.4)) < 0.01, "linear ramp-out over ramp_out_s"
    np.testing.assert_allclose(targets(frames), np.tile(frozen, (len(frames), 1)), atol=1e-6)
    assert robot.ctl.phase is Phase.IDLE and robot.ctl.counters["ramp_outs"] == {"command timeout": 1}
    frames = robot.run(0.1, goal)
    assert robot.ctl.phase is Phase.RAMP_IN and robot.ctl.counters["ramp_ins"] == 2
    assert weights(frames)[0] == 0.0 and 0 < weights(frames)[1] < 0.01


def test_ramp_out_keeps_targets_still() -> None:
    robot = Robot()
    robot.run(0.7, robot.ctl.q_home + 0.05)
    robot.ctl.begin_stop()
    frames = robot.run(0.5)
    q = targets(frames)
    np.testing.assert_allclose(q, np.tile(q[0], (len(q), 1)), atol=1e-7)
    assert weights(frames)[-1] == 0.0 and robot.ctl.finished
    assert robot.ctl.counters["ramp_outs"] == {"stop": 1}
    robot.run(0.2, robot.ctl.q_home)  # stopping: commands never ramp in again
    assert robot.ctl.phase is Phase.IDLE and robot.ctl.counters["ramp_ins"] == 1


def test_state_timeout_ramps_out() -> None:
    robot = Robot()
    robot.run(0.7, robot.ctl.q_home)
    frames = robot.run(0.7, robot.ctl.q_home, states=False)
    w = weights(frames)
    lost = round(robot.ctl.conf.state_timeout_s / PERIOD)
    assert (w[: lost - 1] == 1.0).all() and w[-1] == 0.0
    assert robot.ctl.counters["ramp_outs"] == {"state timeout": 1}
    assert robot.ctl.phase is Phase.IDLE


def test_overspeed_latches_a_fault() -> None:
    robot = Robot()
    robot.run(0.7, robot.ctl.q_home)
    dq = np.zeros(29)
    dq[16] = 12.0  # faster than fault_speed (10 rad/s)
    robot.ctl.update_state(state(robot.t, robot.q, dq=dq))
    assert robot.ctl.phase is Phase.RAMP_OUT and "joint speed" in robot.ctl.counters["faults"][0]
    robot.ctl.update_state(state(robot.t, robot.q, dq=dq))
    assert len(robot.ctl.counters["faults"]) == 1, "one fault, reported once"
    robot.run(1.0, robot.ctl.q_home)
    assert robot.ctl.phase is Phase.FAULT and robot.ctl.weight == 0.0
    assert robot.ctl.counters["ramp_ins"] == 1, "a fault never ramps in again"


def test_torque_above_the_limit_for_consecutive_states_latches_a_fault() -> None:
    robot = Robot()
    robot.run(0.7, robot.ctl.q_home)
    tau = np.zeros(29)
    tau[18] = 26.0  # elbow limit 25 N·m
    for _ in range(TORQUE_FAULT_SAMPLES - 1):
        robot.ctl.update_state(state(robot.t, robot.q, tau=tau))
    robot.ctl.update_state(state(robot.t, robot.q))  # a sample below the limit resets the count
    for _ in range(TORQUE_FAULT_SAMPLES - 1):
        robot.ctl.update_state(state(robot.t, robot.q, tau=tau))
    assert not robot.ctl.faulted
    robot.ctl.update_state(state(robot.t, robot.q, tau=tau))
    assert robot.ctl.faulted and "torque" in robot.ctl.counters["faults"][0]


def test_non_finite_states_are_dropped() -> None:
    robot = Robot()
    bad = POSE.copy()
    bad[16] = np.nan
    assert not robot.ctl.update_state(state(1.0, bad))
    assert robot.ctl.counters["invalid_states"] == 1 and robot.ctl.state.received == 0.0


def test_locked_waist_refuses_by_default() -> None:
    with pytest.raises(G1StartError, match="arms_only"):
        Robot(mode_machine=6)
    with pytest.raises(G1StartError, match="arms_only"):
        Robot(conf(waist="locked"), mode_machine=5)
    with pytest.raises(G1StartError, match="executor.g1.waist"):
        Robot(mode_machine=99)  # unknown variant: the waist must be configured
    Robot(conf(waist="unlocked"), mode_machine=99)


def test_locked_waist_arms_only_drops_and_counts_waist_targets(caplog: pytest.LogCaptureFixture) -> None:
    robot = Robot(conf(on_locked_waist="arms_only"), mode_machine=6)
    assert "limit them to ±0.01 rad" in caplog.text  # the shipped description lets the waist move
    locked = SPEC.model_copy(update={"limits": {"waist_roll_joint": (-0.01, 0.01), "waist_pitch_joint": (-0.01, 0.01)}})
    caplog.clear()
    G1Controller(locked, conf(on_locked_waist="arms_only"), PERIOD).attach(state(0.0, mode_machine=6))
    assert "imitating the arms only" in caplog.text and "limit them" not in caplog.text
    assert robot.ctl.dropped_joints == ["waist_roll_joint", "waist_pitch_joint"]
    goal = robot.ctl.q_home.copy()
    goal[0], goal[1], goal[4] = 0.2, -0.1, 1.0
    applied = robot.ctl.command(robot.t, goal, np.zeros(8))
    assert applied[0] == applied[1] == 0.0 and applied[4] == 1.0
    frames = robot.run(0.8, goal)
    assert all((f["motor_cmd"]["mode"][[13, 14]] == 0).all() and (f["motor_cmd"]["kp"][[13, 14]] == 0).all() for f in frames)
    assert robot.ctl.counters["waist_commands_dropped"] == len(frames) + 1
    assert robot.ctl.counters["max_waist_drop_rad"] == pytest.approx(0.2)
    assert targets(frames[-1:], np.array([18]))[0, 0] == pytest.approx(1.0, abs=1e-5)


def test_lowcmd_mode_commands_every_motor_and_ramps_stiffness() -> None:
    robot = Robot(conf(mode="lowcmd"))
    idle = robot.run(0.02)[-1]["motor_cmd"]
    assert (idle["mode"][:29] == 1).all() and (idle["kp"][:29] == 0).all(), "weight 0: damping only"
    np.testing.assert_allclose(idle["kd"][:29], [g[1] if s not in SLOTS else 1.5 for s, g in enumerate(LOWCMD_HOLD_GAINS)])
    frames = robot.run(0.7, robot.ctl.q_home)
    half = frames[round(0.25 / PERIOD)]["motor_cmd"]
    w = 0.5  # a quarter second into a half-second ramp
    np.testing.assert_allclose(half["kp"][3], LOWCMD_HOLD_GAINS[3][0] * w, rtol=0.02)  # knee, held
    np.testing.assert_allclose(half["kp"][SLOTS], 60.0 * w, rtol=0.02)
    full = frames[-1]["motor_cmd"]
    np.testing.assert_allclose(full["kp"][SLOTS], 60.0)
    np.testing.assert_allclose(full["q"][:12], POSE[:12], atol=1e-6)  # legs hold the measured pose
    assert all(float(f["motor_cmd"]["q"][WEIGHT_SLOT]) == 0.0 for f in frames), "no blend weight in lowcmd"


def test_check_frame_finds_what_must_not_be_sent() -> None:
    robot = Robot()
    frames = robot.run(0.7, robot.ctl.q_home)
    prev, good = frames[-2], frames[-1]
    commanded = robot.ctl.commanded
    step = np.zeros(29)
    step[SLOTS] = np.array(robot.ctl.conf.max_speed) * 2 * PERIOD

    def problems(frame: np.ndarray) -> list[str]:
        return check_frame(frame, commanded, prev, HW_LOWER, HW_UPPER, step)

    assert problems(good) == []
    bad = good.copy()
    bad["crc"] ^= 1
    assert problems(bad) == ["CRC mismatch"]
    for mutate, expected in (
        (lambda m: m["mode"].__setitem__(3, 1), "not to be commanded"),
        (lambda m: m["q"].__setitem__(18, 3.0), "outside the joint range"),
        (lambda m: m["q"].__setitem__(16, m["q"][16] + 0.1), "jump"),
        (lambda m: m["q"].__setitem__(WEIGHT_SLOT, 1.5), "blend weight"),
        (lambda m: m["kd"].__setitem__(20, -1.0), "negative gains"),
        (lambda m: m["dq"].__setitem__(15, np.inf), "non-finite"),
    ):
        bad = good.copy()
        mutate(bad["motor_cmd"])
        bad["crc"] = lowcmd_crc(bad)
        assert any(expected in p for p in problems(bad)), (expected, problems(bad))


def test_arm_sdk_limits_the_imitated_waist_by_default() -> None:
    """Leaning over the balance controller tips the G1 (unitree_sdk2_python #146, #173):
    in arm_sdk mode the waist targets stay within executor.g1.arm_sdk_waist_range by default."""
    lean = np.array([0.4, 0.4, 0.3, 0.25, 0.9, 0.3, -0.25, 0.9])  # waist rolled and pitched forward
    default = G1Config().arm_sdk_waist_range
    assert default["waist_pitch_joint"][1] <= 0.05 and max(map(abs, default["waist_roll_joint"])) <= 0.1
    robot = Robot()
    frames = robot.run(2.0, lean)
    np.testing.assert_allclose(targets(frames[-1:], SLOTS[:2])[0], [default["waist_roll_joint"][1],
                                                                      default["waist_pitch_joint"][1]], atol=1e-6)
    np.testing.assert_allclose(targets(frames[-1:], ARMS)[0], lean[2:], atol=1e-6)  # the arms are not limited
    assert robot.ctl.command(robot.t, -lean, np.zeros(8))[1] == default["waist_pitch_joint"][0]
    for c in (conf(arm_sdk_waist_range={}), conf(mode="lowcmd")):  # switched off / not arm_sdk: hardware range
        frames = Robot(c).run(2.0, lean)
        np.testing.assert_allclose(targets(frames[-1:], SLOTS[:2])[0], lean[:2], atol=1e-6)


@pytest.mark.parametrize(("backend", "mode", "limited"), [("g1", "arm_sdk", True), ("g1", "lowcmd", False),
                                                         ("mujoco", "arm_sdk", False)])
def test_every_service_reads_the_arm_sdk_waist_range_from_the_robot_description(backend: str, mode: str,
                                                                                limited: bool) -> None:
    """Driving the real G1 in arm_sdk mode, the configured robot description holds the executor's
    waist range, so the safety layer's joint limits (and its retargeting's clip) are the range the
    executor drives, not up to the hardware's ±0.52 rad beyond it."""
    conf = load_config(environ={}, overrides={"executor": {"backend": backend, "g1": {"mode": mode}}})
    kinematics = RobotKinematics(configured_robot_spec(conf))
    waist = [kinematics.joint_names.index(j) for j in ("waist_roll_joint", "waist_pitch_joint")]
    ranges = [conf.executor.g1.arm_sdk_waist_range[j] for j in ("waist_roll_joint", "waist_pitch_joint")]
    within = [(kinematics.q_min[i], kinematics.q_max[i]) for i in waist]
    if limited:
        assert within == [tuple(r) for r in ranges]
        controller = G1Controller(configured_robot_spec(conf), conf.executor.g1, PERIOD)
        np.testing.assert_allclose([controller.lower[:2], controller.upper[:2]], np.array(within).T)
    else:
        assert all(lo < -0.5 and hi > 0.5 for lo, hi in within), within
    arms = [i for i in range(8) if i not in waist]
    plain = RobotKinematics(load_robot_spec(default_robot_spec_path()))
    np.testing.assert_array_equal(kinematics.q_min[arms], plain.q_min[arms])


@pytest.mark.parametrize("bad", [{"waist_yaw_joint": (-0.1, 0.1)}, {"waist_pitch_joint": (0.1, 0.2)},
                                 {"waist_roll_joint": (0.1, -0.1)}])
def test_arm_sdk_waist_range_is_validated(bad) -> None:
    with pytest.raises(ValueError):
        G1Config(arm_sdk_waist_range=bad)


def test_the_executor_warns_when_only_its_flag_says_g1(caplog: pytest.LogCaptureFixture) -> None:
    """``--backend g1`` on the executor alone: the safety service, reading the file, would plan with
    the description's waist range; the executor says what to set."""
    from services.executor.service import _warn_if_only_here

    g1 = load_config(environ={}, overrides={"executor": {"backend": "g1"}})
    with caplog.at_level("WARNING", logger="safemimic.executor"):
        _warn_if_only_here(g1, g1)
        assert not caplog.records
        _warn_if_only_here(g1, load_config(environ={}))
    assert len(caplog.records) == 1 and "put executor.backend: g1 in the configuration" in caplog.text


@pytest.mark.parametrize("bad", [{"kp": [60.0] * 7 + [1e6]}, {"kd": [1.5] * 7 + [1e4]}, {"max_speed": [6.0] * 7 + [1e6]},
                                 {"ramp_in_s": 0.01}, {"ramp_out_s": 0.01}])
def test_no_configuration_drives_the_motors_beyond_what_they_are_meant_for(bad) -> None:
    """Gains, the target's speed (which also bounds the last check's jump) and the hand-over ramps
    have hard limits: a typo or another robot's value is refused, not sent."""
    with pytest.raises(ValueError):
        G1Config(**bad)
    assert G1Config(kp=[500.0] * 8, kd=[20.0] * 8, max_speed=[37.0] * 8, ramp_in_s=0.25, ramp_out_s=0.25)
