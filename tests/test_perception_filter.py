"""Point filter (EMA or One Euro + jump rejection + hold + reset) and the capsules built from its output."""

from __future__ import annotations

import math

import numpy as np
import pytest

from services.perception.angles import AngleRates, PoseEstimator
from services.perception.capsules import HumanCapsules
from shared.body import capsule_radii
from services.perception.pipeline import PerceptionPipeline
from services.perception.point_filter import FilteredSkeleton, PointFilter
from services.perception.base import SkeletonFrame
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


KINDS = ["ema", "one_euro"]


@pytest.mark.parametrize("kind", KINDS)
def test_a_single_frame_outlier_is_rejected_counted_and_held(kind: str) -> None:
    filt = PointFilter(PointFilterConfig(kind=kind), 15)
    frames = [pose() for _ in range(20)]
    frames[10] = frames[10].copy()
    frames[10][WRIST] += (0.0, 0.6, 0.0)  # 18 m/s in one frame: a detection error
    out = run(filt, frames)
    assert filt.rejected == 1 and filt.reacquired == 0
    np.testing.assert_allclose(out[10].points[WRIST], pose()[WRIST], atol=1e-12)  # held where it was
    assert out[10].valid.all() and out[11].valid.all()
    np.testing.assert_allclose(out[-1].points, pose(), atol=1e-12)


def test_steady_motion_is_followed_with_the_configured_lag() -> None:
    conf = PointFilterConfig(kind="ema", ema_tau_s=0.05)
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
    filt = PointFilter(PointFilterConfig(kind="ema", ema_tau_s=0.0), 15)
    frames = [pose() + 0.01 * i for i in range(5)]
    np.testing.assert_array_equal(run(filt, frames)[-1].points, frames[-1])


@pytest.mark.parametrize("kind", KINDS)
def test_missing_wrist_is_held_then_marks_the_arm_invalid(kind: str) -> None:
    conf = PerceptionConfig(point_filter={"kind": kind})
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


@pytest.mark.parametrize("kind", KINDS)
def test_a_long_gap_resets_everything(kind: str) -> None:
    conf = PointFilterConfig(kind=kind)
    filt = PointFilter(conf, 15)
    run(filt, [pose()] * 5)
    moved = pose() + (2.0, 0.0, 0.0)  # the person walked 2 m while the camera was off
    out = filt(5 * DT + conf.reset_gap_s + 0.1, moved, ONES)
    assert filt.resets == 1 and filt.rejected == 0 and out.fresh.all()
    np.testing.assert_array_equal(out.points, moved)
    filt(0.0, pose(), ONES)  # time going backwards (a replay restarting) resets too
    assert filt.resets == 2


@pytest.mark.parametrize("kind", KINDS)
def test_a_bad_first_measurement_is_reanchored(kind: str) -> None:
    conf = PointFilterConfig(kind=kind, reacquire_frames=3)
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
        elif kind == 3:  # beyond any person (MAX_COORD_M): missing, as no HumanState could carry it
            xyz[rng.integers(15)] *= 1e6
        elif kind == 4:
            confidence[:] = np.nan
        elif kind == 5:  # a detector's jump within reach: rejected by the filter
            xyz[rng.integers(15)] += 5.0
        result = pipeline.step(SkeletonFrame(t=i * DT, xyz=xyz, conf=confidence, captured=0.0))
        message = result.to_message(stamp=float(i))  # validates: finite arrays, radii in range
        assert np.isfinite(message.capsule_velocities).all()
    assert pipeline.counters.frames == 300 and pipeline.counters.rejected_jumps > 0  # (to_message validated
    # every frame: no point beyond MAX_COORD_M reached a HumanState)


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


def test_an_invalid_capsule_keeps_its_last_endpoints_without_velocity() -> None:
    """Zeros before its first valid frame; then the last valid endpoints, velocity 0, while the
    other capsules follow the skeleton with finite-difference velocities."""
    builder = HumanCapsules(HumanConfig())
    thigh, knee, every, none = C["left_thigh"], K["left_knee"], np.ones(15, bool), np.zeros(15, bool)
    without_knee = every.copy()
    without_knee[knee] = False
    unseen = pose()
    unseen[knee] = np.nan  # a point never seen is NaN in the filter's output
    capsules, valid, velocities = builder(FilteredSkeleton(0.0, unseen, without_knee, without_knee))
    assert not valid[thigh] and valid.sum() == 6 and (capsules[thigh] == 0).all() and (velocities == 0).all()

    seen = builder(FilteredSkeleton(DT, pose(), every, none))[0]
    moved = pose() + (0.03, 0.0, 0.0)
    capsules, valid, velocities = builder(FilteredSkeleton(2 * DT, moved, without_knee, none))
    assert not valid[thigh] and valid.sum() == 6
    np.testing.assert_array_equal(capsules[thigh], seen[thigh])
    assert (velocities[thigh] == 0).all()
    others = np.arange(7) != thigh
    np.testing.assert_allclose(capsules[others], seen[others] + (0.03, 0.0, 0.0), atol=1e-12)
    np.testing.assert_allclose(velocities[others], np.broadcast_to((0.03 / DT, 0.0, 0.0), velocities[others].shape),
                               atol=1e-9)


@pytest.mark.parametrize("estimator", ["continuous", "paper"])
@pytest.mark.parametrize("kind", KINDS)
def test_the_pipeline_is_its_stages_one_after_the_other(kind: str, estimator: str) -> None:
    """``step`` hands the stages Python lists: it gives what their array calls give, on noisy
    frames with dropouts, NaN, outliers and replay restarts (every stage resets with the filter)."""
    conf = PerceptionConfig(point_filter={"kind": kind}, angles={"estimator": estimator})
    pipeline = PerceptionPipeline(conf, HumanConfig())
    filt, angles = PointFilter(conf.point_filter, 15), PoseEstimator(conf.angles)
    rates, builder = AngleRates(conf.angles), HumanCapsules(HumanConfig())
    rng = np.random.default_rng(7)
    missing = invalid_frames = 0
    for i in range(240):
        phase = i % 90 + 40 * (i // 90)  # a replay restarting elsewhere every 90 frames
        true_theta = [0.1, 0.0, 0.4 + 2.5 * math.sin(phase / 20), 1.2 + math.cos(phase / 15), 0.5, 0.3, 0.2, 0.9]
        xyz = skeleton(np.array(true_theta)) + rng.normal(scale=0.003, size=(15, 3))
        confidence = np.ones(15)
        if i % 7 == 3:
            confidence[rng.integers(15, size=2)] = 0.0
        if i % 11 == 5:
            xyz[rng.integers(15)] = np.nan
        if i % 13 == 6:
            xyz[rng.integers(15)] += 0.5  # an outlier
        if 30 <= i < 40:
            xyz[K["right_elbow"]] += 1.5  # moved for good: re-anchored (fresh) after a few frames
        if 100 <= i < 120:
            xyz[WRIST] = np.nan  # lost beyond the hold
        frame = SkeletonFrame(t=i * DT, xyz=xyz, conf=confidence, captured=0.0, discontinuity=i in (90, 180))
        got = pipeline.step(frame)

        resets = filt.resets
        filtered = filt(frame.t, frame.xyz, frame.conf, frame.discontinuity)
        if filt.resets != resets:
            angles.reset()
            rates.reset()
            builder.reset()
        theta, theta_valid = angles(filtered.points, filtered.valid, frame.t)
        capsules, capsule_valid, velocities = builder(filtered)
        expected = {
            "keypoints": np.where(filtered.valid[:, None], filtered.points, 0.0), "keypoint_valid": filtered.valid,
            "theta": theta, "theta_valid": theta_valid, "theta_rate": rates(frame.t, theta, theta_valid, filtered.fresh),
            "capsules": capsules, "capsule_valid": capsule_valid, "capsule_velocities": velocities,
        }
        for name, value in expected.items():
            np.testing.assert_array_equal(getattr(got, name), value, err_msg=f"{name}, frame {i}")
        missing += int((~filtered.valid).sum())
        invalid_frames += not (theta_valid.all() and capsule_valid.all())
    counters = pipeline.counters
    assert counters.frames == 240 and counters.filter_resets == filt.resets == 2
    assert counters.rejected_jumps == filt.rejected > 0 and counters.reacquired == filt.reacquired > 0
    assert counters.missing_points == missing > 0 and counters.invalid_frames == invalid_frames > 0


# --- the One Euro filter (Casiez, Roussel, Vogel, CHI 2012) --------------------------------------

def one_euro_reference(t: np.ndarray, x: np.ndarray, min_cutoff: float, beta: float, d_cutoff: float) -> np.ndarray:
    """The published scalar filter, transcribed: α(f_c) = 1/(1 + τ/T_e), τ = 1/(2π f_c);
    dx = (x_i − x_{i−1})/T_e low-passed at d_cutoff; f_c = min_cutoff + β|dx̂|; x̂ low-passed at f_c."""
    def alpha(cutoff: float, te: float) -> float:
        return 1.0 / (1.0 + (1.0 / (2 * math.pi * cutoff)) / te)

    out, x_hat, dx_hat = [x[0]], x[0], 0.0
    for i in range(1, len(x)):
        te = t[i] - t[i - 1]
        dx_hat += alpha(d_cutoff, te) * ((x[i] - x[i - 1]) / te - dx_hat)
        x_hat += alpha(min_cutoff + beta * abs(dx_hat), te) * (x[i] - x_hat)
        out.append(x_hat)
    return np.array(out)


def test_one_euro_is_the_published_filter_and_its_cutoff_grows_with_speed() -> None:
    """Motion along one axis (‖ẋ̂‖ = |ẋ̂|): every keypoint equals the paper's scalar filter to 1e-12;
    at constant speed v the lag is 1/(2π (min_cutoff + β v)) — shorter the faster the point moves."""
    conf = PointFilterConfig(kind="one_euro", min_cutoff_hz=1.3, beta=7.0, d_cutoff_hz=2.0)
    rng = np.random.default_rng(3)
    t = np.cumsum(rng.uniform(0.025, 0.04, 200))  # uneven frame times
    x = np.cumsum(rng.normal(scale=0.01, size=200)) + 0.3 * np.sin(3 * t)  # stays under max_speed
    filt = PointFilter(conf, 15)
    got = np.array([filt(ti, pose() + (xi, 0.0, 0.0), ONES).points[WRIST, 0] - pose()[WRIST, 0] for ti, xi in zip(t, x)])
    np.testing.assert_allclose(got, one_euro_reference(t, x, 1.3, 7.0, 2.0), atol=1e-12)
    assert filt.rejected == 0

    lags = []
    for speed in (0.2, 1.0, 3.0):
        filt = PointFilter(conf, 15)
        out = run(filt, [pose() + (speed * i * DT, 0.0, 0.0) for i in range(150)])
        lag = (speed * 149 * DT - (out[-1].points[WRIST, 0] - pose()[WRIST, 0])) / speed
        assert lag == pytest.approx(1 / (2 * math.pi * (1.3 + 7.0 * speed)), rel=1e-6)
        assert lag == pytest.approx(filt.steady_state_lag(DT, speed), rel=1e-6)
        lags.append(lag)
    assert lags[0] > lags[1] > lags[2]


def test_shipped_one_euro_has_less_lag_than_the_ema_and_no_more_jitter() -> None:
    """A still point with 1 cm Gaussian noise (jitter = std of the output) and a point moving at
    1 m/s (lag): the shipped One Euro against the paper's EMA (τ = 0.03 s)."""
    ema = PointFilterConfig(kind="ema")
    one_euro = PointFilterConfig()
    assert one_euro.kind == "one_euro"
    noise = np.random.default_rng(11).normal(scale=0.01, size=(600, 3))
    jitter, lag = {}, {}
    for name, conf in (("ema", ema), ("one_euro", one_euro)):
        out = run(PointFilter(conf, 15), [pose() + n for n in noise])
        jitter[name] = float(np.std([o.points[WRIST] for o in out[30:]], axis=0).mean())
        moving = run(PointFilter(conf, 15), [pose() + (i * DT, 0.0, 0.0) for i in range(120)])
        lag[name] = 119 * DT - (moving[-1].points[WRIST, 0] - pose()[WRIST, 0])
    assert jitter["one_euro"] <= jitter["ema"], jitter
    assert lag["one_euro"] < 0.6 * lag["ema"], lag
    assert jitter["one_euro"] < 0.01  # it does smooth: below the raw noise


@pytest.mark.parametrize("field, value", [("kind", "kalman"), ("min_cutoff_hz", 0.0), ("min_cutoff_hz", -1.0),
                                          ("beta", -0.1), ("d_cutoff_hz", 0.0), ("d_cutoff_hz", 1e3), ("beta", math.nan)])
def test_one_euro_settings_are_validated(field: str, value: object) -> None:
    with pytest.raises(ValueError, match=field):
        PointFilterConfig(**{field: value})
    PointFilterConfig(kind="one_euro", min_cutoff_hz=0.5, beta=0.0, d_cutoff_hz=5.0)  # in range: fine


def test_switching_kind_at_run_time_keeps_the_points() -> None:
    """The service applies a new point_filter live: the estimate carries over, only smoothing changes."""
    filt = PointFilter(PointFilterConfig(kind="ema"), 15)
    run(filt, [pose()] * 5)
    filt.conf = PointFilterConfig(kind="one_euro")
    out = filt(5 * DT, pose(), ONES)
    assert not out.fresh.any() and filt.resets == 0
    np.testing.assert_allclose(out.points, pose(), atol=1e-12)
