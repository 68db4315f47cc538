"""The evaluator against the true person: the true person is the unfiltered source, the
perceived one lags it by exactly the latency and is corrupted reproducibly, every robot surface
counts, a pair touching at home counts once pressed deeper, a contact is blamed on whoever moved,
the lag estimate recovers a known delay. Real perception, MuJoCo, Pinocchio and DAQP."""

from __future__ import annotations

import json
from pathlib import Path

import mujoco
import numpy as np
import pytest

from safemimic.evaluate.episode import run_episode
from safemimic.evaluate.evaluation import evaluation_config, true_person_of
from safemimic.evaluate.fidelity import (
    ACQUIRE_S, best_delay, delayed, direction_errors, fidelity, judged_from, lag_ms, limited_follower,
)
from safemimic.evaluate.person import CameraModel, corrupt, interpolate_skeleton, latency_text, perceive
from safemimic.evaluate.source import EvaluationInput, open_input
from safemimic.evaluate.truth import CLOSING_SPEED, TruthProbe, fixed_bodies
from services.executor.mujoco.model import PDGains
from services.executor.mujoco.sim import SimRobot
from services.perception.placement import Placement
from services.perception.scenarios import get_scenario, scenario_recording
from services.safety.kinematics import RobotKinematics
from shared.config import ExecutorConfig
from shared.names import CAPSULE_NAMES, KEYPOINT_INDEX, KEYPOINT_NAMES
from shared.robot_spec import configured_robot_spec, default_robot_spec_path, load_robot_spec
from tests.support.team import G1_MJCF
from tests.test_evaluate_compare import safemimic
from tests.test_executor_sim import person_capsules

GAINS = PDGains.from_config(ExecutorConfig())
OURS = load_robot_spec(default_robot_spec_path())
WRIST = KEYPOINT_INDEX["right_wrist"]
LEFT_FOREARM = CAPSULE_NAMES.index("left_forearm")


def write_recording(path: Path, xyz: np.ndarray, fps: float = 30.0) -> Path:
    np.savez(path, names=np.array(KEYPOINT_NAMES), t=np.arange(len(xyz)) / fps, xyz=xyz, fps=np.float64(fps),
             conf=np.ones(xyz.shape[:2]))
    return path


def raise_recording(seconds: float = 2.0) -> np.ndarray:
    return scenario_recording(get_scenario("side-by-side-arm-raise"), seconds, 30.0, Placement(y=0.7)).xyz.copy()


# ------------------------------------------------------------------------------- the two people
def test_true_person_is_the_recording_unfiltered_and_interpolated(tmp_path: Path) -> None:
    """A wrist that jumps 0.4 m in one frame: the point filter rejects the jump for the perceived
    person, the true person (MuJoCo's) has it at once, and between frames it is interpolated."""
    xyz = raise_recording()
    xyz[30:, WRIST] += [0.0, -0.4, 0.0]
    path = write_recording(tmp_path / "jump.npz", xyz)
    conf = evaluation_config(str(path), None, "recorded", None)
    source = open_input(conf)
    points, valid = interpolate_skeleton(source, np.array([1.0, 1.0 + 0.5 / 30]))
    assert valid.all()
    np.testing.assert_allclose(points[0], xyz[30], atol=1e-12)  # exact frame time: the raw frame
    np.testing.assert_allclose(points[1], 0.5 * (xyz[30] + xyz[31]), atol=1e-12)
    person = true_person_of(conf, source, RobotKinematics(configured_robot_spec(conf)))
    k = int(round(1.0 * conf.safety.rate_hz))
    forearm = CAPSULE_NAMES.index("right_forearm")
    elbow_to_wrist = xyz[30, WRIST] - xyz[30, KEYPOINT_INDEX["right_elbow"]]
    expected_end = xyz[30, WRIST] + conf.human.hand_extension * elbow_to_wrist / np.linalg.norm(elbow_to_wrist)
    np.testing.assert_allclose(person.capsules[k, forearm, 1], expected_end, atol=1e-9)
    perceived = perceive(conf, source)
    state = perceived.states[30]
    assert np.linalg.norm(state.keypoints[WRIST] - xyz[30, WRIST]) > 0.3, "the filter rejects the jump"
    assert perceived.counters.rejected_jumps > 0


def test_a_keypoint_missing_in_the_next_frame_leaves_an_exact_frame_time_valid_and_finite(tmp_path: Path) -> None:
    """At a frame's own time the next frame has weight 0: a wrist missing there (NaN) must not turn
    the present wrist into NaN while it counts as valid (the true person's angles would read it as
    a point at the origin)."""
    xyz = raise_recording()
    xyz[31, WRIST] = np.nan
    conf = evaluation_config(str(write_recording(tmp_path / "gap.npz", xyz)), None, "recorded", None)
    points, valid = interpolate_skeleton(open_input(conf), np.array([1.0, 1.0 + 0.5 / 30, 31 / 30]))
    assert valid[0, WRIST] and not valid[1, WRIST] and not valid[2, WRIST]
    np.testing.assert_allclose(points[0], xyz[30], atol=1e-12)
    assert np.isnan(points[1:, WRIST]).all() and np.isfinite(points[valid]).all()


def test_a_recording_without_a_body_part_says_how_much_of_the_person_it_shows(tmp_path: Path) -> None:
    """No left wrist in half the frames: the left forearm of the true person is missing there, so
    contacts with it cannot be counted; metrics.json says the share of steps with the whole person
    and the command warns below 90 %."""
    xyz = raise_recording(2.0)
    xyz[30:, KEYPOINT_INDEX["left_wrist"]] = np.nan
    path = write_recording(tmp_path / "no_wrist.npz", xyz)
    out = tmp_path / "out"
    done = safemimic("evaluate", "--skeleton", str(path), "--placement", "side-by-side", "--quiet", "--out", str(out))
    assert done.returncode == 0, done.stderr
    complete = json.loads((out / "metrics.json").read_text())["input"]["true_person_complete"]
    assert 0.4 < complete < 0.6, complete
    assert "the recording has the whole person in only" in done.stderr


def test_perceived_person_lags_the_true_one_by_exactly_the_latency(tmp_path: Path) -> None:
    path = write_recording(tmp_path / "raise.npz", raise_recording(1.0))
    conf = evaluation_config(str(path), None, "recorded", None)
    source = open_input(conf)
    prompt, late = perceive(conf, source, CameraModel(latency_s=0.0)), perceive(conf, source, CameraModel(latency_s=0.1))
    np.testing.assert_allclose(late.t - prompt.t, 0.1, atol=1e-12)
    np.testing.assert_array_equal(late.states[10].capsules, prompt.states[10].capsules)
    kinematics = RobotKinematics(configured_robot_spec(conf))
    person = true_person_of(conf, source, kinematics)
    episode = run_episode(conf, late, person, enforce=True, kinematics=kinematics)
    frame_times = np.array([f.t for f in source.frames]) - source.frames[0].t
    expected = np.searchsorted(frame_times + 0.1, episode.t + 1e-9, side="right") - 1
    np.testing.assert_array_equal(episode.human, expected)  # the state in force: 100 ms old at least
    assert (episode.human[episode.t < 0.1 - 1e-9] == -1).all()


def test_noise_and_dropout_reproduce_with_a_seed_and_noise_runs_along_the_viewing_rays(tmp_path: Path) -> None:
    path = write_recording(tmp_path / "raise.npz", raise_recording(2.0))
    conf = evaluation_config(str(path), None, "recorded", None)
    source = open_input(conf)
    model = CameraModel(latency_s=0.06, depth_noise_m=0.05, dropout=0.2, seed=7)
    first, again = perceive(conf, source, model), perceive(conf, source, model)
    other = perceive(conf, source, CameraModel(latency_s=0.06, depth_noise_m=0.05, dropout=0.2, seed=8))
    keypoints = [np.stack([s.keypoints for s in track.states]) for track in (first, again, other)]
    np.testing.assert_array_equal(keypoints[0], keypoints[1])
    assert not np.array_equal(keypoints[0], keypoints[2])
    camera = np.asarray(conf.perception.camera.extrinsics.position)
    rng = np.random.default_rng(7)
    dropped = np.mean([np.isnan(corrupt(f, camera, model, rng)[0].xyz).any(axis=1).mean() for f in source.frames])
    assert 0.15 < dropped < 0.25, dropped  # each keypoint missing with probability 0.2
    assert first.counters.missing_points < dropped * len(source.frames) * len(KEYPOINT_NAMES)  # the hold bridges

    frame = source.frames[5]
    noisy, _ = corrupt(frame, camera, CameraModel(depth_noise_m=0.05, seed=1), np.random.default_rng(1))
    shift = noisy.xyz - frame.xyz
    rays = frame.xyz - camera
    centre = frame.xyz.mean(axis=0) - camera
    normals = np.cross(rays, centre)  # the shift lies in the plane of the own ray and the centre's ray
    assert np.abs(np.einsum("ij,ij->i", shift, normals / np.linalg.norm(normals, axis=1, keepdims=True))).max() < 1e-9
    assert np.linalg.norm(shift, axis=1).min() > 0


def _runs(hidden: np.ndarray) -> np.ndarray:
    """The lengths of the runs of True in each column of ``hidden`` (F, K) bool."""
    padded = np.zeros((hidden.shape[0] + 2, hidden.shape[1]), np.int8)
    padded[1:-1] = hidden
    edges = np.diff(padded, axis=0)
    return np.concatenate([np.flatnonzero(edges[:, k] == -1) - np.flatnonzero(edges[:, k] == 1)
                           for k in range(hidden.shape[1])])


def test_keypoints_hidden_in_runs_keep_the_dropout_share_and_make_capsules_lost(tmp_path: Path) -> None:
    """--dropout-frames L: each keypoint hidden a share P of the frames in runs of L frames on average
    (a Markov chain; independently per frame without it, runs of 1/(1 − P)); runs longer than the
    point filter's hold make capsules lost, and the robot stands (``person_lost_steps``), where the
    same share hidden independently is bridged by the hold."""
    rng = np.random.default_rng(11)
    for model, mean_run in ((CameraModel(dropout=0.1, dropout_frames=12.0), 12.0),
                            (CameraModel(dropout=0.1), 1.0 / 0.9), (CameraModel(dropout=0.3, dropout_frames=2.0), 2.0)):
        hidden = np.zeros((40000, len(KEYPOINT_NAMES)), bool)
        for f in range(1, len(hidden)):
            hidden[f] = model.hidden(rng.random(len(KEYPOINT_NAMES)), hidden[f - 1])
        assert abs(hidden.mean() - model.dropout) < 0.1 * model.dropout, (model, hidden.mean())
        assert abs(_runs(hidden).mean() - mean_run) < 0.1 * mean_run, (model, _runs(hidden).mean())
    assert CameraModel(dropout=0.1, dropout_frames=12.0).settings()["dropout_frames"] == 12.0

    path = write_recording(tmp_path / "raise.npz", raise_recording(6.0))
    conf = evaluation_config(str(path), None, "recorded", None)
    source = open_input(conf)
    kinematics = RobotKinematics(configured_robot_spec(conf))
    person = true_person_of(conf, source, kinematics)
    lost = {}
    for frames in (0.0, 20.0):
        model = CameraModel(latency_s=0.06, dropout=0.1, dropout_frames=frames, seed=2)
        track = perceive(conf, source, model)
        hidden_frames = np.mean([not s.capsule_valid.all() for s in track.states])
        episode = run_episode(conf, track, person, enforce=True, kinematics=kinematics)
        lost[frames] = (hidden_frames, int(episode.person_lost.sum()))
    assert lost[0.0] == (0.0, 0), lost  # hidden a frame or two at a time: held by the point filter
    assert lost[20.0][0] > 0.1 and lost[20.0][1] > 0, lost  # hidden for ⅔ s on average: capsules lost, robot stands


def test_a_late_camera_delays_frames_now_and_then_in_order_and_changes_nothing_else(tmp_path: Path) -> None:
    """--latency-jitter-ms: every state later than frame time + latency by an exponential extra delay
    of the given mean, still in order; the same seed gives the same arrivals, and the noise and
    dropout (their own random stream) are the same as without jitter; the safety loop uses the
    newest state *arrived*, so a late frame holds the one before it longer."""
    path = write_recording(tmp_path / "raise.npz", raise_recording(4.0))
    conf = evaluation_config(str(path), None, "recorded", None)
    source = open_input(conf)
    steady = CameraModel(latency_s=0.06, depth_noise_m=0.03, dropout=0.1, seed=4)
    late = CameraModel(latency_s=0.06, depth_noise_m=0.03, dropout=0.1, seed=4, jitter_s=0.03)
    on_time, jittered = perceive(conf, source, steady), perceive(conf, source, late)
    extra = jittered.t - on_time.t
    assert (extra >= -1e-12).all() and (np.diff(jittered.t) >= 0.0).all()
    assert 0.015 < extra.mean() < 0.06 and extra.max() > 0.06  # a mean of 30 ms, some frames much later
    np.testing.assert_array_equal(jittered.t, perceive(conf, source, late).t)
    for a, b in zip(on_time.states, jittered.states, strict=True):
        np.testing.assert_array_equal(a.keypoints, b.keypoints)  # the same noise and dropout
    assert late.settings()["latency_jitter_ms"] == 30.0 and steady.settings()["latency_jitter_ms"] == 0.0
    assert latency_text(late.settings()) == "60 ms + jitter (mean) 30 ms" and latency_text(steady.settings()) == "60 ms"
    np.testing.assert_array_equal(steady.arrivals(np.arange(5) / 30), np.arange(5) / 30 + 0.06)
    kinematics = RobotKinematics(configured_robot_spec(conf))
    episode = run_episode(conf, jittered, true_person_of(conf, source, kinematics), enforce=True, kinematics=kinematics)
    expected = np.searchsorted(jittered.t, episode.t + 1e-9, side="right") - 1
    np.testing.assert_array_equal(episode.human, expected)


def test_camera_model_refuses_out_of_range_values() -> None:
    for bad in ({"latency_s": -0.01}, {"depth_noise_m": -1.0}, {"dropout": 1.0}, {"jitter_s": -0.001},
                {"jitter_s": 1.5}, {"dropout": 0.1, "dropout_frames": 0.5}, {"dropout": 0.9, "dropout_frames": 5.0},
                {"dropout_frames": 15.0}):
        with pytest.raises(ValueError):
            CameraModel(**bad)


# ------------------------------------------------------------------------------- every surface
def test_a_visual_only_link_touching_the_person_is_counted(tmp_path: Path) -> None:
    """A hand with no collision geometry (like Menagerie's rubber hands): MuJoCo's contact list
    cannot see it, the surface distance does."""
    text = OURS.model_path.read_text()
    body = '<body name="left_elbow_link"'
    start = text.index(body)
    close = text.index(">", start) + 1
    hand = ('<body name="left_test_hand" pos="0.6 0 0"><geom name="left_test_hand" type="sphere" size="0.04" '
            'contype="0" conaffinity="0" group="2"/></body>')
    model = tmp_path / OURS.model_path.name
    model.write_text(text[:close] + hand + text[close:])
    for mesh_dir in ("meshes", "assets"):
        if (OURS.model_path.parent / mesh_dir).is_dir():
            (tmp_path / mesh_dir).symlink_to(OURS.model_path.parent / mesh_dir)
    sim = SimRobot(OURS.with_model(model), GAINS)
    hand_geom = sim.model.geom("left_test_hand").id
    assert hand_geom in set(sim.surface_geoms.tolist())
    centre = sim.data.geom_xpos[hand_geom].copy()
    sim.set_human(*person_capsules(LEFT_FOREARM, centre + [0.0, 0.0, -0.05], centre + [0.0, 0.0, 0.05], 0.02))
    sim.step()
    touching = sim.surface_contacts()
    assert [c.robot_body for c in touching] == ["left_test_hand"], touching
    assert [(c.body_a, c.body_b) for c in sim.contacts().robot_human] == [("left_test_hand", "left_forearm")]


def test_the_real_g1_rubber_hands_are_robot_surfaces() -> None:
    if not G1_MJCF.is_file():
        pytest.skip(f"real G1 model not found at {G1_MJCF} (set SAFEMIMIC_TEAM_SHARED to the team folder)")
    sim = SimRobot(OURS.with_model(G1_MJCF), GAINS)
    names = {sim.model.geom(g).name or f"#{g}" for g in sim.surface_geoms}
    hands = [g for g in sim.surface_geoms if sim.model.geom_dataid[g] >= 0
             and "rubber_hand" in sim.model.mesh(sim.model.geom_dataid[g]).name]
    assert len(hands) == 2, names
    centre = sim.data.geom_xpos[hands[0]].copy()
    sim.set_human(*person_capsules(LEFT_FOREARM, centre + [0.0, 0.0, -0.03], centre + [0.0, 0.0, 0.03], 0.01))
    sim.step()
    assert any(c.robot_body.endswith("wrist_yaw_link") for c in sim.surface_contacts())


def test_a_pair_touching_at_home_counts_once_pressed_deeper() -> None:
    home = {**OURS.home, "left_shoulder_roll_joint": -0.1, "left_elbow_joint": 1.9}  # upper arm on the chest
    sim = SimRobot(OURS.model_copy(update={"home": home}), GAINS)
    pair = ("left_shoulder_yaw_link", "torso_link")
    assert pair in sim.home_contacts
    sim.step(100)
    assert pair not in {(c.body_a, c.body_b) for c in sim.contacts().robot_robot}
    q = sim.q_home.copy()
    q[sim.joint_names.index("left_shoulder_roll_joint")] = -0.5  # further into the chest
    sim.set_command(q)
    sim.step(250)
    pressed = {(c.body_a, c.body_b): c.depth for c in sim.contacts().robot_robot}
    assert pressed.get(pair, 0.0) > 1e-3, pressed


# ------------------------------------------------------------------------------- who moved
def test_an_arm_driven_into_a_still_person_is_robot_caused() -> None:
    sim = SimRobot(OURS, GAINS)
    kinematics = RobotKinematics(OURS)
    probe = TruthProbe(evaluation_config(None, "neutral", "auto", None), kinematics)
    hand = sim.data.body("left_elbow_link").xpos.copy() + [0.25, 0.0, 0.0]
    capsules, radii, valid = person_capsules(CAPSULE_NAMES.index("torso"), hand + [0.12, -0.3, 0.0],
                                         hand + [0.12, 0.3, 0.0], 0.05)
    sim.set_human(capsules, radii, valid)
    elbow = sim.joint_names.index("left_elbow_joint")
    pitch = sim.joint_names.index("left_shoulder_pitch_joint")
    caused, rates = [], []
    for k in range(400):  # the forearm swings forward/up into the torso capsule in front of it
        q = sim.q_home.copy()
        q[pitch] -= min(1.2, 0.006 * k)
        q[elbow] -= min(0.6, 0.003 * k)
        sim.set_command(q)
        sim.step()
        touching = sim.surface_contacts()
        if touching:
            caused.append(any(c.closing_speed > CLOSING_SPEED for c in touching))
            step = probe.measure(sim.q, sim.dq, capsules, radii, valid)
            rates.append(np.nanmin(step.rate[~probe.is_self]))
    assert caused and np.mean(caused) > 0.5, caused
    assert min(rates) < -CLOSING_SPEED  # the capsule view agrees: the robot closes the pair


def test_the_commanded_closing_speed_is_the_contact_point_velocity_along_the_normal() -> None:
    """−nᵀ J_p[:, I] dq against a finite difference of the contact point carried by its body when
    only the imitation joints move by ε·dq; zero for a still command."""
    sim = SimRobot(OURS, GAINS)
    endpoints, _ = RobotKinematics(OURS).compute(sim.q_home)
    forearm = endpoints[CAPSULE_NAMES.index("left_forearm")].mean(axis=0)
    sim.set_human(*person_capsules(LEFT_FOREARM, forearm + [0.03, -0.2, 0.0], forearm + [0.03, 0.2, 0.0], 0.05))
    sim.set_command(sim.q_home)
    sim.step()
    contact = sim.surface_contacts()[0]
    body = sim.data.body(contact.robot_body)
    local = body.xmat.reshape(3, 3).T @ (contact.point - body.xpos)
    qadr = [sim.model.joint(name).qposadr[0] for name in sim.joint_names]
    rng = np.random.default_rng(7)
    for _ in range(5):
        dq, eps = rng.normal(size=len(sim.joint_names)), 1e-7
        data = mujoco.MjData(sim.model)
        data.qpos[:] = sim.data.qpos
        data.qpos[qadr] += eps * dq
        mujoco.mj_kinematics(sim.model, data)
        moved = data.body(contact.robot_body).xpos + data.body(contact.robot_body).xmat.reshape(3, 3) @ local
        expected = -float(contact.normal @ (moved - contact.point)) / eps
        assert sim.commanded_closing_speed(contact, dq) == pytest.approx(expected, rel=1e-4, abs=1e-7)
    assert sim.commanded_closing_speed(contact, np.zeros(len(sim.joint_names))) == 0.0


def test_a_servo_settling_on_a_still_command_is_robot_caused_but_not_commanded() -> None:
    """The command jumps into the person and then stays (u* = 0): the servo moves the forearm
    into it, which the contact count blames on the robot, and the commanded speed says the
    command did not; driven with the matching velocity, both agree: every step with a contact the
    robot closes has one the command closes too (the evaluator's ``robot_caused_commanded``). A
    single contact need not: a second geom of the wrist grazing the person at a constant depth
    closes at 1.9 mm/s while the command's share there is 0.9 mm/s (the shoulder's servo still
    swinging past the command, 1.19 rad/s against 1.0, and the joints held at home yielding)."""
    sim = SimRobot(OURS, GAINS)
    endpoints, _ = RobotKinematics(OURS).compute(sim.q_home)
    forearm = endpoints[CAPSULE_NAMES.index("left_forearm")].mean(axis=0)
    person = person_capsules(LEFT_FOREARM, forearm + [0.07, -0.3, 0.0], forearm + [0.07, 0.3, 0.0], 0.04)
    sim.set_human(*person)
    pitch = sim.joint_names.index("left_shoulder_pitch_joint")
    target = sim.q_home.copy()
    target[pitch] -= 0.3  # the arm forward, through the capsule in front of the forearm
    still, settling = np.zeros(len(sim.joint_names)), []
    for _ in range(100):
        sim.set_command(target)
        sim.step()
        closing = [c for c in sim.surface_contacts() if c.closing_speed > CLOSING_SPEED]
        settling += [sim.commanded_closing_speed(c, still) for c in closing]
    assert settling and max(settling) == 0.0
    moving = sim.q_home.copy()
    forward = still.copy()
    forward[pitch] = -1.0
    sim.reset()
    sim.set_human(*person)
    commanded = []
    for _ in range(300):
        moving = moving + forward * sim.timestep
        sim.set_command(moving, forward)
        sim.step()
        closing = [c for c in sim.surface_contacts() if c.closing_speed > CLOSING_SPEED]
        if closing:
            commanded.append(max(sim.commanded_closing_speed(c, forward) for c in closing))
    assert commanded and min(commanded) > CLOSING_SPEED


def test_a_person_moving_into_a_still_robot_is_person_caused() -> None:
    sim = SimRobot(OURS, GAINS)
    endpoints, _ = RobotKinematics(OURS).compute(sim.q_home)
    forearm = endpoints[CAPSULE_NAMES.index("left_forearm")].mean(axis=0)
    steps = 0
    for k in range(400):  # a capsule sliding sideways into the still forearm at 0.5 m/s
        x = forearm + [0.0, 0.3 - 0.5 * k * sim.timestep, 0.0]
        sim.set_human(*person_capsules(LEFT_FOREARM, x + [0.0, 0.0, -0.2], x + [0.0, 0.0, 0.2], 0.04))
        sim.set_command(sim.q_home)
        sim.step()
        touching = sim.surface_contacts()
        if touching:
            steps += 1
            assert all(c.closing_speed <= CLOSING_SPEED for c in touching), [c.closing_speed for c in touching]
    assert steps > 20


@pytest.mark.parametrize("model", ["ours", "g1"])
def test_fixed_bodies_are_those_no_imitation_joint_moves(model: str) -> None:
    """The pelvis and the legs are fixed, the torso and every arm link are not; a person standing
    in the pelvis counts among the fixed-body contacts, one touching the forearm does not."""
    if model == "g1" and not G1_MJCF.is_file():
        pytest.skip(f"real G1 model not found at {G1_MJCF} (set SAFEMIMIC_TEAM_SHARED to the team folder)")
    spec = OURS if model == "ours" else OURS.with_model(G1_MJCF)
    sim = SimRobot(spec, GAINS)
    fixed = fixed_bodies(sim.model, tuple(sim.joint_names))
    assert {"pelvis", "left_hip_pitch_link", "right_knee_link"} <= fixed, sorted(fixed)
    moved = {"torso_link", "left_shoulder_pitch_link", "left_elbow_link", "right_shoulder_roll_link"}
    assert not moved & fixed, sorted(moved & fixed)
    pelvis = sim.data.body("pelvis").xpos.copy()
    sim.set_human(*person_capsules(CAPSULE_NAMES.index("torso"), pelvis + [0.0, -0.2, 0.0], pelvis + [0.0, 0.2, 0.0], 0.05))
    sim.step()
    assert "pelvis" in {c.robot_body for c in sim.surface_contacts()}


# ------------------------------------------------------------------------------- fidelity
def test_lag_recovers_a_known_delay() -> None:
    dt = 0.002
    t = np.arange(0, 8.0, dt)
    truth = np.stack([0.6 * np.sin(2 * np.pi * 0.4 * t + j) + 0.2 * np.sin(2 * np.pi * 1.3 * t) for j in range(8)], axis=1)
    truth[:, 7] = 0.01 * np.sin(t)  # one joint that barely moves: left out
    delayed = np.vstack([np.repeat(truth[:1], 50, axis=0), truth[:-50]])  # 100 ms late
    assert lag_ms(truth, delayed, dt) == pytest.approx(100.0, abs=5.0)
    assert best_delay(truth[:, 0], truth[:, 0], dt) == pytest.approx(0.0)
    assert best_delay(truth[:100, 0], truth[:100, 0], dt) is None  # too short to search
    assert lag_ms(np.zeros((4000, 8)), np.zeros((4000, 8)), dt) is None  # nothing moves


def test_the_limited_follower_keeps_its_bounds_and_lags_only_where_they_bind() -> None:
    """limited_follower: never faster than u_max nor accelerating beyond accel_max (a noisy reference
    included); a motion within both bounds is followed with no lag; a sine whose acceleration exceeds
    the bound is followed late, and with no acceleration bound again without lag."""
    dt = 0.002
    t = np.arange(0, 6.0, dt)
    u_max, accel = np.full(8, 10.0), np.full(8, 60.0)
    rng = np.random.default_rng(0)
    noisy = np.cumsum(rng.normal(0.0, 0.05, (len(t), 8)), axis=0)
    q = limited_follower(noisy, dt, u_max, accel)
    v = np.diff(q, axis=0, prepend=noisy[:1]) / dt
    assert np.abs(v).max() <= 10.0 + 1e-9 and np.abs(np.diff(v, axis=0)).max() <= 60.0 * dt + 1e-9
    assert np.isfinite(q).all()

    def sine(frequency: float) -> np.ndarray:  # amplitude 0.5 rad: peak speed π f, peak acceleration 2 π² f²
        return np.tile(0.5 * (1.0 - np.cos(2 * np.pi * frequency * t))[:, None], (1, 8))

    slow, fast = sine(0.5), sine(3.0)  # 4.9 and 178 rad/s² at the peak (speed 1.6 and 9.4 rad/s)
    assert np.abs(limited_follower(slow, dt, u_max, accel) - slow).max() < 1e-3
    assert lag_ms(slow, limited_follower(slow, dt, u_max, accel), dt, 500) == 0.0
    assert lag_ms(fast, limited_follower(fast, dt, u_max, accel), dt, 500) >= 20.0
    assert lag_ms(fast, limited_follower(fast, dt, u_max, None), dt, 500) == 0.0


def test_fidelity_is_judged_from_one_second_after_the_person_is_first_perceived() -> None:
    """The robot's move from its home pose to the person's first pose is not imitation: an error
    that only exists before ACQUIRE_S after the first perceived state does not count, one after does."""
    dt, n = 0.002, 3000
    t = np.arange(n) * dt
    q_true = np.tile(0.5 * np.sin(2 * np.pi * 0.5 * t)[:, None], (1, 8))
    perceived = t >= 0.06  # the first state arrives after the camera latency
    start = judged_from(perceived, dt)
    assert start == 30 + round(ACQUIRE_S / dt)
    q_sim = q_true.copy()
    q_sim[:start] += 1.0  # still on its way from home
    free, directions = np.ones(n, bool), np.full((n, 4), 10.0)
    directions[:start] = 170.0
    result = fidelity(q_true, q_sim, free, directions, np.full((n, 4), 4.0), perceived, dt, 0.06, q_nom=q_true,
                      q_cbf=q_sim, directions_seen_late=np.full((n, 4), 7.0), q_limits_floor=q_true)
    assert result["rms_true"] == 0.0 and result["rms_true_free"] == 0.0 and result["lag_ms"] == 0.0
    assert result["direction_error_deg_p95"] == 10.0 and result["direction_error_deg_p95_at_target"] == 4.0
    assert result["direction_error_deg_p95_latency_floor"] == 7.0
    assert result["judged_from_s"] == pytest.approx(start * dt)
    q_sim[start + 10] += 1.0  # one step off inside the window counts
    assert fidelity(q_true, q_sim, free, directions, directions, perceived, dt, 0.06, q_nom=q_true, q_cbf=q_sim,
                    directions_seen_late=directions, q_limits_floor=q_true)["rms_true"] > 0.0
    never = fidelity(q_true, q_sim, free, directions, directions, np.zeros(n, bool), dt, 0.06, q_nom=q_true, q_cbf=q_sim,
                     directions_seen_late=directions, q_limits_floor=q_true)
    assert never["rms_true"] is None and never["judged_from_s"] is None and never["lag_ms"] is None
    assert never["lag_ms_target"] is never["lag_ms_command"] is never["lag_ms_servo"] is None
    assert never["lag_ms_limits_floor"] is None


def test_fidelity_waits_for_a_person_who_walks_into_view_late(tmp_path: Path) -> None:
    """A recording whose first second has no skeleton (the person not yet in view): perception
    publishes states that show nobody, and the judged steps begin ACQUIRE_S after the first state
    that shows the person (1 s + the latency), not after the first state."""
    from safemimic.evaluate.evaluation import evaluate

    xyz = raise_recording(2.5)
    xyz[:30] = np.nan
    path = write_recording(tmp_path / "late.npz", xyz)
    evaluation = evaluate(evaluation_config(str(path), None, "recorded", None))
    shows = evaluation.human.in_view(np.arange(len(evaluation.human.states)))
    assert not shows[:30].any() and shows[30:].all()
    assert not evaluation.human.in_view(np.array([-1]))[0]  # no state in force yet
    metrics = evaluation.metrics()
    for run in ("cbf", "nominal"):
        assert metrics[run]["fidelity"]["judged_from_s"] == pytest.approx(1.0 + 0.06 + ACQUIRE_S, abs=0.004)


def test_a_recording_of_one_frame_is_held_and_evaluated(tmp_path: Path) -> None:
    """One frame is a person standing still: the true person holds it at every control step and
    the evaluation runs (nothing to judge the lag on) instead of failing on its interpolation."""
    from safemimic.evaluate.evaluation import evaluate

    xyz = raise_recording(1.0)[:1]
    path = write_recording(tmp_path / "one.npz", xyz)
    conf = evaluation_config(str(path), None, "recorded", None)
    points, valid = interpolate_skeleton(open_input(conf), np.array([0.0, 0.5]))
    assert valid.all()
    np.testing.assert_array_equal(points[1], xyz[0])
    metrics = evaluate(conf).metrics()
    assert metrics["cbf"]["nan_count"] == 0 and metrics["cbf"]["fidelity"]["lag_ms"] is None


def test_a_robot_exactly_one_latency_late_scores_the_latency_floor() -> None:
    """rms_true_free_latency_floor is what a robot exactly at the target seen L late scores: for a
    sine of amplitude a and angular frequency ω, a·√2·|sin(ωL/2)|; a robot that trails further
    scores more, and one without latency scores 0 over a floor of 0."""
    dt, n, latency, omega, amplitude = 0.002, 4000, 0.06, 2 * np.pi * 1.5, 0.5
    t = np.arange(n) * dt
    q_true = np.tile(amplitude * np.sin(omega * t)[:, None], (1, 8))
    perceived, free, directions = np.ones(n, bool), np.ones(n, bool), np.full((n, 4), 5.0)
    late = fidelity(q_true, delayed(q_true, 30), free, directions, directions, perceived, dt, latency,
                    q_nom=delayed(q_true, 20), q_cbf=delayed(q_true, 27), directions_seen_late=directions,
                    q_limits_floor=delayed(q_true, 35))
    expected = amplitude * np.sqrt(2) * abs(np.sin(omega * latency / 2))
    assert late["rms_true_free_latency_floor"] == pytest.approx(expected, rel=0.01)
    assert late["rms_true_free"] == pytest.approx(late["rms_true_free_latency_floor"], abs=1e-6)
    assert late["lag_ms"] == pytest.approx(1e3 * latency)
    # the stages: target 20 steps behind the truth, command 7 behind it, servos 3 behind that
    assert (late["lag_ms_target"], late["lag_ms_command"], late["lag_ms_servo"]) == pytest.approx((40.0, 14.0, 6.0))
    assert late["lag_ms_limits_floor"] == pytest.approx(70.0)
    later = fidelity(q_true, delayed(q_true, 50), free, directions, directions, perceived, dt, latency,
                     q_nom=q_true, q_cbf=q_true, directions_seen_late=directions, q_limits_floor=q_true)
    assert later["rms_true_free"] > later["rms_true_free_latency_floor"]
    free_of_motion = fidelity(q_true, q_true, free, directions, directions, perceived, dt, 0.0, q_nom=q_true, q_cbf=q_true,
                              directions_seen_late=directions, q_limits_floor=q_true)
    assert free_of_motion["rms_true_free"] == free_of_motion["rms_true_free_latency_floor"] == 0.0


def test_the_direction_latency_floor_is_the_robot_at_the_target_seen_one_latency_late(tmp_path: Path) -> None:
    """target_directions' second array is direction_errors of the robot placed at q_true one latency
    late against the person now: 0 latency gives the at-target errors; on the raise (arms moving) the
    target seen late points elsewhere (by the paper's map not always further off: its own error and the
    latency's can cancel), and a still person has no latency to pay."""
    from safemimic.evaluate.metrics import target_directions

    path = write_recording(tmp_path / "raise.npz", raise_recording(2.0))
    conf = evaluation_config(str(path), None, "recorded", None)
    person = true_person_of(conf, open_input(conf), RobotKinematics(configured_robot_spec(conf)))
    mirror = conf.retargeting.mirror
    at_target, same = target_directions(person, mirror, 0.0)
    np.testing.assert_array_equal(same, at_target)
    _, late = target_directions(person, mirror, 0.06)
    steps = round(0.06 * conf.safety.rate_hz)
    by_hand = direction_errors(person.keypoints, person.valid, delayed(person.robot_at_target, steps), mirror)
    np.testing.assert_array_equal(late, by_hand)
    moving = np.ptp(person.q_true, axis=0).max() > 0.5
    assert moving and np.nanmax(np.abs(late - at_target)) > 2.0
    still = write_recording(tmp_path / "still.npz", np.repeat(raise_recording(1.0)[:1], 60, axis=0))
    conf = evaluation_config(str(still), None, "recorded", None)
    person = true_person_of(conf, open_input(conf), RobotKinematics(configured_robot_spec(conf)))
    at_target, late = target_directions(person, mirror, 0.06)
    np.testing.assert_allclose(late, at_target, atol=1e-9)


def test_direction_error_is_zero_for_the_same_pose_and_mirrors_facing() -> None:
    """A robot whose capsules lie exactly along the person's segments has 0° error; facing, the
    robot's left arm is compared with the person's right one, reflected."""
    p = np.zeros((1, 15, 3))
    K = KEYPOINT_INDEX
    p[0, K["pelvis"]] = [0, 0, 1.0]
    p[0, K["left_shoulder"]], p[0, K["right_shoulder"]] = [0, 0.2, 1.5], [0, -0.2, 1.5]
    p[0, K["left_elbow"]], p[0, K["left_wrist"]] = [0.3, 0.2, 1.5], [0.3, 0.2, 1.8]  # forward, forearm up
    p[0, K["right_elbow"]], p[0, K["right_wrist"]] = [0, -0.2, 1.2], [0, -0.2, 0.9]  # hanging
    valid = np.ones((1, 15), bool)
    robot = np.zeros((1, 7, 2, 3))
    C = {n: i for i, n in enumerate(CAPSULE_NAMES)}
    robot[0, C["torso"]] = p[0, K["pelvis"]], [0, 0, 1.5]
    for side in ("left", "right"):
        robot[0, C[f"{side}_upper_arm"]] = p[0, K[f"{side}_shoulder"]], p[0, K[f"{side}_elbow"]]
        robot[0, C[f"{side}_forearm"]] = p[0, K[f"{side}_elbow"]], p[0, K[f"{side}_wrist"]]
    np.testing.assert_allclose(direction_errors(p, valid, robot, mirror=False), 0.0, atol=1e-6)
    mirrored = direction_errors(p, valid, robot, mirror=True)
    assert mirrored[0, 0] > 80  # the robot's left arm points forward, the person's right hangs


def test_evaluation_reports_the_truth_keys(tmp_path: Path) -> None:
    from safemimic.evaluate.evaluation import evaluate

    path = write_recording(tmp_path / "raise.npz", raise_recording(3.0))
    metrics = evaluate(evaluation_config(str(path), None, "recorded", None), camera=CameraModel(seed=3)).metrics()
    for run in ("cbf", "nominal"):
        m = metrics[run]
        assert m["person_caused_contact_steps"] + m["robot_caused_contact_steps"] == m["true_contacts_robot_human"]
        assert 0 <= m["robot_caused_contact_steps_commanded"] <= m["robot_caused_contact_steps"]
        assert 0 <= m["robot_approach_steps_commanded"] <= m["robot_approach_steps"]
        for steps, mm in (("robot_caused_contact_steps", "robot_caused_contact_mm"),
                          ("robot_approach_steps", "robot_approach_mm")):
            assert (m[mm] > 0) == (m[steps] > 0), m  # every counted step closes > 1 mm/s for 2 ms
        assert 0 <= m["torque_saturated_steps"] <= metrics["input"]["control_steps"]
        assert set(m["fidelity"]) == {"lag_ms", "rms_true", "rms_true_free", "direction_error_deg_p50",
                                      "direction_error_deg_p95", "direction_error_deg_p50_at_target",
                                      "direction_error_deg_p95_at_target", "judged_from_s",
                                      "rms_true_free_latency_floor", "lag_ms_target", "lag_ms_command",
                                      "lag_ms_servo", "direction_error_deg_p50_latency_floor",
                                      "direction_error_deg_p95_latency_floor", "lag_ms_limits_floor"}
        assert m["fidelity"]["lag_ms"] is not None and m["fidelity"]["lag_ms"] > 0
        # the target alone trails the true person by the camera latency (60 ms) and the point filter
        assert m["fidelity"]["lag_ms_target"] >= 60.0 and m["fidelity"]["lag_ms_servo"] is not None
        # no robot follows the target seen 60 ms late with less lag than the latency (±1 step)
        assert m["fidelity"]["lag_ms_limits_floor"] >= 58.0
        assert m["true_contacts_fixed_bodies"] == 0  # beside the robot: only the arms meet
    assert metrics["nominal"]["true_contacts_robot_human"] > metrics["cbf"]["true_contacts_robot_human"]
    assert metrics["nominal"]["robot_caused_contact_steps_commanded"] > 0  # without the CBF the command drives in
    assert metrics["input"]["latency_ms"] == 60.0 and metrics["input"]["seed"] == 3


def test_a_person_standing_inside_the_robot_is_a_fixed_body_contact_at_every_step(tmp_path: Path) -> None:
    """The person's pelvis placed on the robot's: every step touches the pelvis and legs, with the
    CBF or without, and those steps are the floor true_contacts_fixed_bodies reports."""
    from safemimic.evaluate.evaluation import evaluate

    path = write_recording(tmp_path / "raise.npz", raise_recording(1.0))
    metrics = evaluate(evaluation_config(str(path), None, "0.0,0.0,0.0", None)).metrics()
    for run in ("cbf", "nominal"):
        m = metrics[run]
        steps = metrics["input"]["control_steps"]
        assert m["true_contacts_fixed_bodies"] == m["true_contacts_robot_human"] == steps, m


def test_evaluation_input_is_read_once_in_order() -> None:
    conf = evaluation_config(None, "cross-arm-reach", "auto", None)
    source = open_input(conf, 1.0)
    assert isinstance(source, EvaluationInput) and len(source.frames) == 30
    assert all(b.t > a.t for a, b in zip(source.frames, source.frames[1:]))
