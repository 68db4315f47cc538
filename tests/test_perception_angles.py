"""Pose angles θ (paper §II-A): convention on known poses, the paper's formulas, rotation invariance,
the overhead flaw and its continuous fix, degenerate inputs, real motion capture."""

from __future__ import annotations

import math

import numpy as np
import pytest

from services.perception.angles import PoseEstimator
from shared.torso_frame import torso_axes
from services.perception.placement import Placement
from services.perception.scenarios import SCENARIOS, scenario_frames
from services.perception.synthetic import skeleton
from shared.body import Body
from shared.config import PoseAnglesConfig
from shared.names import KEYPOINT_INDEX as K
from shared.names import POSE_ANGLE_NAMES
from shared.skeleton import read_recording
from tests.support.team import MOCAP_DIR

ALL_VALID = np.ones(15, dtype=bool)
FPS = 30.0
A = {name: i for i, name in enumerate(POSE_ANGLE_NAMES)}


def estimate(points: np.ndarray, estimator: str = "continuous", valid: np.ndarray = ALL_VALID) -> tuple[np.ndarray, np.ndarray]:
    return PoseEstimator(PoseAnglesConfig(estimator=estimator))(points, valid)


def standing() -> np.ndarray:
    """An upright person facing +x (x forward, y left, z up), arms straight down."""
    return skeleton(np.zeros(8))


def with_arm(points: np.ndarray, side: str, direction: tuple[float, float, float], fore: tuple[float, float, float] | None = None) -> np.ndarray:
    """Set ``side``'s upper arm (and forearm, default: straight on) along robot-frame directions."""
    out = points.copy()
    u = np.array(direction, float) / np.linalg.norm(direction)
    f = u if fore is None else np.array(fore, float) / np.linalg.norm(fore)
    out[K[f"{side}_elbow"]] = out[K[f"{side}_shoulder"]] + 0.3 * u
    out[K[f"{side}_wrist"]] = out[K[f"{side}_elbow"]] + 0.25 * f
    return out


def paper_literal(points: np.ndarray) -> np.ndarray:
    """The paper's eight formulas, transcribed symbol by symbol (F_T: x right, y forward, z up)."""
    p = {name: points[i] for name, i in K.items()}
    k = np.array([0.0, 0.0, 1.0])
    e_z = 0.5 * (p["left_shoulder"] + p["right_shoulder"]) - p["pelvis"]
    e_z /= np.linalg.norm(e_z)
    lateral = p["right_shoulder"] - p["left_shoulder"]
    e_x = lateral - (lateral @ e_z) * e_z
    e_x /= np.linalg.norm(e_x)
    e_y = np.cross(e_z, e_x)
    R = np.stack([e_x, e_y, e_z])
    theta = [
        math.atan2(-e_y @ np.cross(k, e_z), k @ e_z),
        math.atan2(-e_x @ np.cross(k, e_z), k @ e_z),
    ]
    for side, sign in (("left", -1.0), ("right", 1.0)):
        u = p[f"{side}_elbow"] - p[f"{side}_shoulder"]
        f = p[f"{side}_wrist"] - p[f"{side}_elbow"]
        uT = R @ u
        theta += [
            math.atan2(uT[1], -uT[2]),
            math.atan2(sign * uT[0], -uT[2]),
            math.acos(np.clip(u @ f / (np.linalg.norm(u) * np.linalg.norm(f)), -1, 1)),
        ]
    return np.array(theta)


# --- the convention on poses with known answers -------------------------------------------------

@pytest.mark.parametrize("estimator", ["continuous", "paper"])
def test_known_poses_give_the_documented_angles(estimator: str) -> None:
    base = standing()
    theta, valid = estimate(base, estimator)
    assert valid.all()
    np.testing.assert_allclose(theta, 0.0, atol=1e-12)  # arms down, straight, upright torso

    # Exactly horizontal is the paper's singular set (its roll is atan2(0, 0)): 1 mrad below it.
    forward = with_arm(with_arm(base, "left", (1, 0, -1e-3)), "right", (1, 0, -1e-3))
    theta, _ = estimate(forward, estimator)
    assert theta[A["left_shoulder_pitch"]] == pytest.approx(math.pi / 2, abs=2e-3)
    assert theta[A["right_shoulder_pitch"]] == pytest.approx(math.pi / 2, abs=2e-3)
    assert theta[A["left_shoulder_roll"]] == pytest.approx(0.0, abs=1e-12)
    assert theta[A["left_elbow"]] == pytest.approx(0.0, abs=1e-6)

    # Out sideways: left arm along +y (the person's left), right along −y: +π/2 roll on both sides.
    sideways = with_arm(with_arm(base, "left", (0, 1, -1e-3)), "right", (0, -1, -1e-3))
    theta, _ = estimate(sideways, estimator)
    assert theta[A["left_shoulder_roll"]] == pytest.approx(math.pi / 2, abs=2e-3)
    assert theta[A["right_shoulder_roll"]] == pytest.approx(math.pi / 2, abs=2e-3)
    assert theta[A["left_shoulder_pitch"]] == pytest.approx(0.0, abs=1e-9)

    # Inward (across the body) is negative roll; backward is negative pitch.
    across = with_arm(base, "left", (0, -1, -1.5))
    assert estimate(across, estimator)[0][A["left_shoulder_roll"]] < -0.5
    back = with_arm(base, "right", (-1, 0, -1))
    assert estimate(back, estimator)[0][A["right_shoulder_pitch"]] == pytest.approx(-math.pi / 4)

    # Elbow: straight = 0, forearm at 90° to the upper arm = π/2.
    bent = with_arm(base, "left", (0, 0, -1), fore=(1, 0, 0))
    assert estimate(bent, estimator)[0][A["left_elbow"]] == pytest.approx(math.pi / 2)


@pytest.mark.parametrize("estimator", ["continuous", "paper"])
def test_torso_lean_signs(estimator: str) -> None:
    forward = skeleton(np.array([0.0, 0.3, 0, 0, 0, 0, 0, 0]))
    assert forward[K["spine_chest"], 0] > 0.1  # really leaning towards +x, the person's front
    theta, _ = estimate(forward, estimator)
    assert theta[A["torso_pitch"]] == pytest.approx(0.3) and theta[A["torso_roll"]] == pytest.approx(0.0, abs=1e-12)
    left = skeleton(np.array([0.25, 0.0, 0, 0, 0, 0, 0, 0]))
    assert left[K["spine_chest"], 1] > 0.1  # really leaning towards +y, the person's left
    theta, _ = estimate(left, estimator)
    assert theta[A["torso_roll"]] == pytest.approx(0.25) and theta[A["torso_pitch"]] == pytest.approx(0.0, abs=1e-12)


def test_estimators_are_the_papers_formulas_where_the_arm_is_below_the_shoulder() -> None:
    """Random bodies and poses with both upper arms in the paper zone (−u_z ≥ paper_zone)."""
    rng = np.random.default_rng(3)
    zone = PoseAnglesConfig().paper_zone
    checked = 0
    while checked < 300:
        body = Body(shoulder_width=rng.uniform(0.20, 0.37), upper_arm=rng.uniform(0.22, 0.34))
        theta = np.concatenate([rng.uniform(-0.4, 0.4, 2), rng.uniform([-1.2, -1.2, 0], [1.2, 1.2, 2.6], (2, 3)).ravel()])
        points = skeleton(theta, body)
        axes = np.array(torso_axes(points[K["pelvis"]], points[K["left_shoulder"]], points[K["right_shoulder"]], 0.05))
        down = [-(axes @ (points[K[f"{s}_elbow"]] - points[K[f"{s}_shoulder"]]))[2] / body.upper_arm for s in ("left", "right")]
        if min(down) < zone:
            continue
        checked += 1
        literal = paper_literal(points)
        paper, continuous = estimate(points, "paper")[0], estimate(points, "continuous")[0]
        np.testing.assert_allclose(paper, literal, atol=1e-9)
        np.testing.assert_allclose(continuous, literal, atol=1e-9)
        np.testing.assert_allclose(continuous, theta, atol=1e-9)  # the generator's known angles


def test_yawing_the_whole_recording_changes_no_angle() -> None:
    """Rotation about the vertical (and a translation) leaves θ unchanged to 1e-9 rad."""
    scenario = SCENARIOS["side-by-side-arm-raise"]
    _, xyz = scenario_frames(scenario, np.arange(0, 8, 1 / FPS), Placement(y=0.7))
    clips = [xyz]
    if MOCAP_DIR.is_dir():
        clips += [read_recording(path).xyz[::3] for path in sorted(MOCAP_DIR.glob("*.npz"))]
    for clip in clips:
        reference = angles_of(clip)
        for yaw in (0.7, -2.4, math.pi):
            moved = angles_of(Placement(x=1.3, y=-0.4, yaw=yaw).apply(clip))
            assert np.abs(moved - reference).max() <= 1e-9


def angles_of(frames: np.ndarray, estimator: str = "continuous") -> np.ndarray:
    """θ of every frame of a sequence (T, 15, 3), one estimator with history."""
    pose = PoseEstimator(PoseAnglesConfig(estimator=estimator))
    return np.array([pose(points, ALL_VALID)[0] for points in frames])


# --- the known flaw: arms overhead ---------------------------------------------------------------

def sweep(plane: str, frames: int = 90) -> tuple[np.ndarray, float]:
    """Both arms swept from hanging down to straight overhead at 30 fps (per-frame step in rad)."""
    step = math.pi / frames
    out = []
    for i in range(frames + 1):
        b = i * step
        if plane == "sideways":  # left arm along +y, right along −y, up to overhead
            points = with_arm(with_arm(standing(), "left", (0, math.sin(b), -math.cos(b))), "right", (0, -math.sin(b), -math.cos(b)))
        else:
            points = with_arm(with_arm(standing(), "left", (math.sin(b), 0, -math.cos(b))), "right", (math.sin(b), 0, -math.cos(b)))
        out.append(points)
    return np.array(out), step


@pytest.mark.parametrize("plane", ["sideways", "forward"])
def test_continuous_angles_stay_smooth_overhead_and_match_the_paper_below_the_shoulder(plane: str) -> None:
    frames, step = sweep(plane)
    c, p = angles_of(frames), angles_of(frames, "paper")
    assert np.isfinite(c).all()
    assert np.abs(np.diff(c, axis=0)).max() <= 3 * step, "continuous estimator jumped"
    assert np.abs(np.diff(p, axis=0)).max() > 10 * step, "the paper's estimator should wrap overhead (the flaw)"
    # The arm ends straight up: pitch π (forward sweep) or roll π (sideways sweep).
    joint = "shoulder_roll" if plane == "sideways" else "shoulder_pitch"
    assert c[-1, A[f"left_{joint}"]] == pytest.approx(math.pi) and c[-1, A[f"right_{joint}"]] == pytest.approx(math.pi)
    # Below the shoulder (the arm ≥ 30° under horizontal, the paper zone) the two agree exactly.
    below = np.arange(len(frames)) * step <= math.acos(PoseAnglesConfig().paper_zone)
    assert below.sum() > 20
    np.testing.assert_allclose(c[below], p[below], atol=1e-9)


@pytest.mark.parametrize("name", sorted(SCENARIOS))
def test_continuous_estimator_reads_back_every_scenarios_known_angles(name: str) -> None:
    scenario = SCENARIOS[name]
    times = np.arange(0, scenario.period, 1 / FPS)
    theta, xyz = scenario_frames(scenario, times, Placement(y=0.7), Body(shoulder_width=0.22))
    np.testing.assert_allclose(angles_of(xyz), theta, atol=1e-6)


# --- degenerate inputs ---------------------------------------------------------------------------

def test_degenerate_inputs_give_finite_angles_and_flags() -> None:
    base = standing()
    up = with_arm(base, "left", (0, 0, 1))  # the arm along the torso axis, overhead
    theta, valid = estimate(up)
    assert valid.all() and np.isfinite(theta).all()
    assert theta[A["left_shoulder_pitch"]] == pytest.approx(math.pi) and theta[A["left_shoulder_roll"]] == pytest.approx(0.0)

    collapsed = base.copy()
    collapsed[K["right_shoulder"]] = collapsed[K["left_shoulder"]]  # shoulders on top of each other
    theta, valid = estimate(collapsed)
    assert np.isfinite(theta).all()
    assert not valid[[A["torso_roll"], A["torso_pitch"], A["left_shoulder_pitch"], A["right_shoulder_roll"]]].any()
    assert valid[A["left_elbow"]]  # the elbow needs no torso

    short = base.copy()
    short[K["left_elbow"]] = short[K["left_shoulder"]]  # zero-length upper arm
    theta, valid = estimate(short)
    assert np.isfinite(theta).all() and not valid[2:5].any() and valid[5:].all()

    missing = ALL_VALID.copy()
    missing[K["right_wrist"]] = False
    nan_points = base.copy()
    nan_points[K["right_wrist"]] = np.nan
    theta, valid = estimate(nan_points, valid=missing)
    assert np.isfinite(theta).all() and not valid[A["right_elbow"]] and valid[A["right_shoulder_pitch"]]

    garbage = np.full((15, 3), np.nan)
    for estimator in ("continuous", "paper"):
        theta, valid = estimate(garbage, estimator)  # NaN even where "valid" claims otherwise
        assert np.isfinite(theta).all() and not valid.any()


def test_invalid_angles_hold_their_last_value() -> None:
    estimator = PoseEstimator(PoseAnglesConfig())
    raised = skeleton(np.array([0, 0, 1.0, 0.2, 0.5, 0, 0, 0]))
    first, _ = estimator(raised, ALL_VALID)
    lost = ALL_VALID.copy()
    lost[K["left_elbow"]] = False
    theta, valid = estimator(standing(), lost)
    assert not valid[2:5].any()
    np.testing.assert_array_equal(theta[2:5], first[2:5])


# --- real motion capture -------------------------------------------------------------------------

def mocap_clips() -> list:
    if not MOCAP_DIR.is_dir() or not any(MOCAP_DIR.glob("*.npz")):
        pytest.skip(f"real motion-capture clips not found in {MOCAP_DIR} (team data folder absent)")
    return sorted(MOCAP_DIR.glob("*.npz"))


def test_real_motion_capture_gives_finite_smooth_angles() -> None:
    """Per frame, a shoulder angle moves at most 3× the upper arm's own direction change (≥ 1°)."""
    worst_paper = 0.0
    for path in mocap_clips():
        xyz = read_recording(path).xyz
        for name in ("continuous", "paper"):
            theta = angles_of(xyz, name)
            assert np.isfinite(theta).all()
            step = np.abs(np.diff(theta, axis=0))
            for side, first in (("left", 2), ("right", 5)):
                u = xyz[:, K[f"{side}_elbow"]] - xyz[:, K[f"{side}_shoulder"]]
                u /= np.linalg.norm(u, axis=1, keepdims=True)
                moved = np.arccos(np.clip((u[1:] * u[:-1]).sum(axis=1), -1, 1))  # ≈ the torso-frame change here
                ratio = step[:, first:first + 2].max(axis=1) / np.maximum(moved + torso_turn(xyz), 0.02)
                if name == "continuous":
                    assert ratio.max() <= 3.0, f"{path.name}: {side} shoulder jumped ({ratio.max():.1f}× the arm's motion)"
                else:
                    worst_paper = max(worst_paper, ratio.max())
            if name == "continuous":
                assert step.max() < 1.2, f"{path.name}: some angle changed by {step.max():.2f} rad in one frame"
    print(f"paper estimator: worst shoulder step {worst_paper:.0f}× the arm's motion on these clips")


def torso_turn(xyz: np.ndarray) -> np.ndarray:
    """Per-frame rotation angle of the torso frame (the arm's direction is measured in it)."""
    axes = np.array([torso_axes(p[K["pelvis"]], p[K["left_shoulder"]], p[K["right_shoulder"]], 0.05) for p in xyz])
    relative = np.einsum("tij,tkj->tik", axes[1:], axes[:-1])
    return np.arccos(np.clip((np.trace(relative, axis1=1, axis2=2) - 1) / 2, -1, 1))


# --- the windmill: an arm circling forward, overhead, down behind, and around again --------------

def windmill(turns: float = 2.0, step_deg: float = 2.0) -> tuple[np.ndarray, float]:
    """Both arms straight, circling in the sagittal plane from hanging down (forward first)."""
    step = math.radians(step_deg)
    frames = []
    for i in range(int(round(turns * 2 * math.pi / step)) + 1):
        b = i * step  # the arm's angle from hanging down, forward positive
        direction = (math.sin(b), 0.0, -math.cos(b))
        frames.append(with_arm(with_arm(standing(), "left", direction), "right", direction))
    return np.array(frames), step


@pytest.mark.parametrize("method", ["linear", "directions"])
def test_a_windmill_never_jumps_an_angle_or_the_robot_target(method: str) -> None:
    """Through the real pipeline (filter → angles) and the real retargeting of the shipped robot
    (either method): no angle changes by π or more between frames, θ stays in [seam − 2π, seam],
    and q_nom moves at most 0.2 rad per frame while the arm moves 2° (before: pitch jumped 2π,
    q_nom ≈ 4.3 rad); by directions, where the arm passes the shoulder's pitch stop, no faster than
    the velocity bound u_max."""
    from services.perception.pipeline import PerceptionPipeline
    from services.perception.base import SkeletonFrame
    from services.safety.assembly import make_retargeter
    from services.safety.kinematics import RobotKinematics
    from shared.config import load_config
    from shared.robot_spec import configured_robot_spec

    conf = load_config(environ={}, overrides={"retargeting": {"method": method}})
    spec = configured_robot_spec(conf)
    retarget = make_retargeter(conf, spec, RobotKinematics(spec))
    perception = PerceptionPipeline(conf.perception, conf.human)
    frames, _ = windmill()
    theta, q_nom, keypoints = [], [], []
    for i, points in enumerate(frames):
        t = i / FPS
        result = perception.step(SkeletonFrame(t=t, xyz=points, conf=np.ones(15), captured=t))
        assert result.theta_valid.all()
        theta.append(result.theta)
        keypoints.append(result.keypoints)
        q_nom.append(retarget.track(result.to_message(stamp=t))[0])
    theta, q_nom = np.array(theta), np.array(q_nom)
    seam = conf.perception.angles.seam
    assert np.isfinite(theta).all() and theta.min() >= seam - 2 * math.pi and theta.max() <= seam
    assert np.abs(np.diff(theta, axis=0)).max() < math.pi
    step = np.abs(np.diff(q_nom, axis=0))
    if method == "linear":
        assert step.max() <= 0.2
    else:
        assert (step <= np.array(conf.safety.u_max) / FPS + 1e-9).all()
        assert np.median(step[:, 2:].max(axis=1)) <= 0.2
    pitch = theta[:, [A["left_shoulder_pitch"], A["right_shoulder_pitch"]]]
    assert pitch.max() > 0.9 * math.pi  # it did follow the arm overhead (continuous through overhead)
    # Each time the arm hangs down again the angles are the paper's on the same filtered skeleton:
    # the switch at the seam (2π at branch_switch_rate) was spread well within the half turn since.
    for down in range(180, len(frames), 180):
        paper, _ = estimate(keypoints[down], "paper")
        np.testing.assert_allclose(theta[down], paper, atol=1e-9)
        assert abs(theta[down, A["left_shoulder_pitch"]]) < 0.05  # and that is about 0 (filter lag)


def test_the_windmill_switch_is_spread_at_the_configured_rate() -> None:
    """Past the seam, pitch returns to the tracked branch at branch_switch_rate (rad/s) minus the
    arm's own motion; a slower rate takes proportionally longer; angles move < π a frame at any rate."""
    frames, step = windmill(turns=1.5)
    for rate in (4.0, 2.0):
        conf = PoseAnglesConfig(branch_switch_rate=rate)
        pose = PoseEstimator(conf)
        theta = np.array([pose(points, ALL_VALID, t=i / FPS)[0] for i, points in enumerate(frames)])
        pitch = theta[:, A["left_shoulder_pitch"]]
        steps = np.diff(pitch)
        assert np.abs(np.diff(theta, axis=0)).max() < math.pi
        falling = steps < 0  # only while the switch is spread does pitch move against the arm
        assert falling.any()
        np.testing.assert_allclose(steps[falling][1:-1], step - rate / FPS, atol=1e-9)
        assert conf.seam - step <= pitch.max() <= conf.seam  # followed the arm up to the seam, then unwound
        assert np.count_nonzero(falling) == pytest.approx(2 * math.pi / (rate / FPS), abs=1)  # e: 2π → 0
