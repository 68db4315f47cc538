"""Point filter (EMA + jump rejection + hold + reset) and the capsules built from its output."""

from __future__ import annotations

import math

import numpy as np
import pytest

from services.perception.capsules import HumanCapsules, capsule_radii
from services.perception.pipeline import PerceptionPipeline
from services.perception.point_filter import PointFilter
from services.perception.stream import SkeletonFrame
from services.perception.synthetic import skeleton
from shared.config import HumanConfig, PerceptionConfig, PointFilterConfig
from shared.geometry import segment_closest_points
from shared.names import CAPSULE_NAMES, KEYPOINT_INDEX as K, POSE_ANGLE_NAMES

DT = 1 / 30
ONES = np.ones(15)
WRIST = K["left_wrist"]
C = {name: i for i, name in enumerate(CAPSULE_NAMES)}
A = {name: i for i, name in enumerate(POSE_ANGLE_NAMES)}


def pose() -> np.ndarray:
    return skeleton(np.array([0, 0, 0.6, 0.3, 0.8, 0.2, 0.1, 0.4]))


def run(filt: PointFilter, frames: list[np.ndarray], confidences: list[np.ndarray] | None = None, t0: float = 0.0):
    out = []
    for i, xyz in enumerate(frames):
        out.append(filt(t0 + i * DT, xyz, ONES if confidences is None else confidences[i]))
    return out


def test_a_single_frame_outlier_is_rejected_counted_and_held() -> None:
    filt = PointFilter(PointFilterConfig(), 15)
    frames = [pose() for _ in range(20)]
    frames[10] = frames[10].copy()
    frames[10][WRIST] += (0.0, 0.6, 0.0)  # 18 m/s in one frame: a detection error
    out = run(filt, frames)
    assert filt.rejected == 1 and filt.reacquired == 0
    np.testing.assert_allclose(out[10].points[WRIST], pose()[WRIST], atol=1e-12)  # held where it was
    assert out[10].valid.all() and out[11].valid.all()
    np.testing.assert_allclose(out[-1].points, pose(), atol=1e-12)


def test_steady_motion_is_followed_with_the_configured_lag() -> None:
    conf = PointFilterConfig(ema_tau_s=0.05)
    filt = PointFilter(conf, 15)
    velocity = np.array([0.8, -0.3, 0.2])  # m/s, the whole body
    frames = [pose() + velocity * i * DT for i in range(60)]
    out = run(filt, frames)
    lag = filt.steady_state_lag(DT)
    alpha = 1 - math.exp(-DT / conf.ema_tau_s)
    assert lag == pytest.approx(DT * (1 - alpha) / alpha) and 0.02 < lag < conf.ema_tau_s
    np.testing.assert_allclose(out[-1].points, frames[-1] - velocity * lag, atol=1e-9)
    assert filt.rejected == 0

    # ... and the capsules' endpoint velocities are the motion's velocity (finite differences).
    capsules = HumanCapsules(HumanConfig())
    for skeleton_out in out:
        _, valid, velocities = capsules(skeleton_out)
    assert valid.all()
    np.testing.assert_allclose(velocities, np.broadcast_to(velocity, velocities.shape), atol=1e-9)


def test_no_smoothing_is_the_identity() -> None:
    filt = PointFilter(PointFilterConfig(ema_tau_s=0.0), 15)
    frames = [pose() + 0.01 * i for i in range(5)]
    np.testing.assert_array_equal(run(filt, frames)[-1].points, frames[-1])


def test_missing_wrist_is_held_then_marks_the_arm_invalid() -> None:
    conf = PerceptionConfig()
    pipeline = PerceptionPipeline(conf, HumanConfig())
    hold = conf.point_filter.hold_s
    results = []
    for i in range(40):
        xyz, confidence = pose(), ONES.copy()
        if i >= 10:
            confidence[WRIST] = 0.1 if i % 2 else 0.0  # below min_confidence: missing
            if i % 3 == 0:
                xyz[WRIST] = np.nan
        results.append(pipeline.step(SkeletonFrame(t=i * DT, xyz=xyz, conf=confidence, captured=0.0)))
    lost_at = 9 * DT
    for i, result in enumerate(results):
        held = i * DT - lost_at <= hold + 1e-9
        assert result.keypoint_valid[WRIST] == held, i
        assert result.theta_valid[A["left_elbow"]] == held
        assert result.capsule_valid[C["left_forearm"]] == held
        assert result.theta_valid[A["left_shoulder_pitch"]]  # the shoulder angles need no wrist
        assert np.isfinite(result.capsules).all() and np.isfinite(result.theta).all()
    assert not results[-1].keypoint_valid[WRIST] and results[-1].keypoint_valid.sum() == 14
    assert pipeline.counters.invalid_frames == sum(not r.theta_valid.all() for r in results)

    # The wrist comes back elsewhere after the hold: it starts afresh (no blending with stale data).
    back = pose()
    back[WRIST] += (0.3, 0.0, 0.3)
    result = pipeline.step(SkeletonFrame(t=40 * DT, xyz=back, conf=ONES, captured=0.0))
    assert result.keypoint_valid[WRIST]
    np.testing.assert_allclose(result.keypoints[WRIST], back[WRIST])
    assert (result.capsule_velocities[C["left_forearm"]] == 0).all()  # no velocity across the gap


def test_a_long_gap_resets_everything() -> None:
    conf = PointFilterConfig()
    filt = PointFilter(conf, 15)
    run(filt, [pose()] * 5)
    moved = pose() + (2.0, 0.0, 0.0)  # the person walked 2 m while the camera was off
    out = filt(5 * DT + conf.reset_gap_s + 0.1, moved, ONES)
    assert filt.resets == 1 and filt.rejected == 0 and out.fresh.all()
    np.testing.assert_array_equal(out.points, moved)
    filt(0.0, pose(), ONES)  # time going backwards (a replay restarting) resets too
    assert filt.resets == 2


def test_a_bad_first_measurement_is_reanchored() -> None:
    conf = PointFilterConfig(reacquire_frames=3)
    filt = PointFilter(conf, 15)
    first = pose()
    first[WRIST] += (0.0, 0.0, 2.0)  # the very first wrist detection is wrong (2 m off)
    out = run(filt, [first] + [pose()] * 6)
    assert filt.rejected == 2 and filt.reacquired == 1  # two rejections, then the truth wins
    np.testing.assert_allclose(out[-1].points[WRIST], pose()[WRIST], atol=1e-12)
    assert out[3].fresh[WRIST] and not out[4].fresh[WRIST]


def test_garbage_never_crashes_and_never_yields_nan() -> None:
    rng = np.random.default_rng(5)
    pipeline = PerceptionPipeline(PerceptionConfig(), HumanConfig())
    for i in range(300):
        xyz = pose() + rng.normal(scale=0.02, size=(15, 3))
        confidence = rng.uniform(0, 1, 15)
        kind = i % 6
        if kind == 1:
            xyz[rng.integers(15)] = (np.inf, 0, 0)
        elif kind == 2:
            xyz[:] = np.nan
        elif kind == 3:
            xyz[rng.integers(15)] *= 1e6
        elif kind == 4:
            confidence[:] = np.nan
        result = pipeline.step(SkeletonFrame(t=i * DT, xyz=xyz, conf=confidence, captured=0.0))
        message = result.to_message(stamp=float(i))  # validates: finite arrays, radii in range
        assert np.isfinite(message.capsule_velocities).all()
    assert pipeline.counters.frames == 300 and pipeline.counters.rejected_jumps > 0


def test_capsules_follow_the_skeleton_with_configured_radii() -> None:
    human = HumanConfig(torso_radius=0.17, hand_extension=0.08)
    filt = PointFilter(PointFilterConfig(), 15)
    points = pose()
    out = filt(0.0, points, ONES)
    capsules, valid, velocities = HumanCapsules(human)(out)
    assert valid.all() and (velocities == 0).all()
    np.testing.assert_array_equal(capsule_radii(human)[C["torso"]], 0.17)
    np.testing.assert_array_equal(capsules[C["torso"]], points[[K["pelvis"], K["spine_chest"]]])
    np.testing.assert_array_equal(capsules[C["right_thigh"]], points[[K["right_hip"], K["right_knee"]]])
    fore = capsules[C["left_forearm"]]
    np.testing.assert_array_equal(fore[0], points[K["left_elbow"]])
    forearm = points[WRIST] - points[K["left_elbow"]]
    np.testing.assert_allclose(fore[1], points[WRIST] + 0.08 * forearm / np.linalg.norm(forearm))
    # The wrist lies on the forearm capsule's axis: distance 0.
    assert segment_closest_points(fore[0], fore[1], points[WRIST], points[WRIST]).distance[0] < 1e-12

    # Without spine_chest the torso reaches the shoulder centre; without a knee the thigh is invalid.
    confidence = ONES.copy()
    confidence[[K["spine_chest"], K["left_knee"]]] = 0.0
    builder = HumanCapsules(human)
    capsules, valid, _ = builder(PointFilter(PointFilterConfig(), 15)(0.0, points, confidence))
    np.testing.assert_allclose(capsules[C["torso"], 1], points[[K["left_shoulder"], K["right_shoulder"]]].mean(axis=0))
    assert valid[C["torso"]] and not valid[C["left_thigh"]] and valid[C["right_thigh"]]
