"""Skeleton sources: replay (any key order, extra keys, placement, pacing, loop), scenarios,
``record-scenario``, default placements against the robot's reach, and the camera's clear error."""

from __future__ import annotations

import math
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from services.perception.capsules import HumanCapsules
from services.perception.placement import Placement, initial_pose, parse_placement, place_recording
from services.perception.point_filter import PointFilter
from services.perception.scenarios import SCENARIOS, get_scenario, scenario_frames, scenario_recording
from services.perception.sources import SourceUnavailable, open_source
from services.perception.synthetic import skeleton
from shared.body import Body
from shared.config import HumanConfig, PerceptionConfig
from shared.geometry import segment_closest_points
from shared.names import CAPSULE_NAMES, KEYPOINT_INDEX as K, KEYPOINT_NAMES
from shared.skeleton import read_recording
from tests.support.team import MOCAP_DIR, REPO

FPS = 30.0
# The robot in its own frame at home (config/robots/g1.yaml + safemimic_g1.xml, pelvis at 0.793 m):
# torso capsule and the shoulder joints; an arm reaches ≈ 0.55 m from its shoulder.
ROBOT_TORSO = (np.array([0.0, 0.0, 0.741]), np.array([0.0, 0.0, 1.069]), 0.114)
ROBOT_SHOULDERS = (np.array([0.0, 0.138, 1.085]), np.array([0.0, -0.138, 1.085]))
ROBOT_ARM_REACH = 0.55


def walking_clip(frames: int = 20) -> np.ndarray:
    """(T, 15, 3) a synthetic person facing +x, walking forward slowly, arms swinging."""
    return np.array([
        skeleton(np.array([0, 0, 0.3 * math.sin(i / 5), 0.1, 0.3, -0.3 * math.sin(i / 5), 0.1, 0.3]))
        + (0.02 * i, 0.0, 0.0)
        for i in range(frames)
    ])


def save_shuffled(path, xyz: np.ndarray) -> None:
    """A recording with the keypoints in reversed order and keys the format does not define."""
    order = list(reversed(KEYPOINT_NAMES))
    np.savez(
        path, names=np.array(order), t=np.arange(len(xyz)) / FPS, xyz=xyz[:, [K[n] for n in order]], fps=FPS,
        motion=np.array("walking"), comment=np.array("extra key"), conf=np.full((len(xyz), 15), 0.9),
    )


def frames_of(conf: PerceptionConfig, limit: int = 10_000) -> list:
    source = open_source(conf)
    stop = threading.Event()
    out = []
    for frame in source.frames(stop):
        out.append(frame)
        if len(out) >= limit:
            stop.set()
    return out


def test_replay_reads_keys_in_another_order_with_extra_keys(tmp_path) -> None:
    clip = walking_clip()
    save_shuffled(tmp_path / "walk.npz", clip)
    conf = PerceptionConfig(source="replay", recording=str(tmp_path / "walk.npz"), placement="recorded", realtime=False)
    frames = frames_of(conf)
    assert len(frames) == len(clip)
    np.testing.assert_array_equal(np.array([f.xyz for f in frames]), clip)  # canonical order again
    assert all(f.conf.tolist() == [0.9] * 15 for f in frames)
    assert [f.t for f in frames] == pytest.approx(np.arange(len(clip)) / FPS)
    assert not any(f.discontinuity for f in frames)


def test_a_recording_without_a_pelvis_replays_with_the_hip_centre_and_a_whole_torso(tmp_path) -> None:
    """A file from a skeleton with no pelvis keypoint (COCO-style estimators): the replay source
    puts it at the hip centre, as the camera sources do, so the person keeps their torso capsule
    (the robot's rows still see it) and is placed by it."""
    clip = walking_clip()
    names = [n for n in KEYPOINT_NAMES if n != "pelvis"]
    np.savez(tmp_path / "coco.npz", names=np.array(names), t=np.arange(len(clip)) / FPS, fps=FPS,
             xyz=clip[:, [K[n] for n in names]])
    frames = frames_of(PerceptionConfig(source="replay", recording=str(tmp_path / "coco.npz"), placement="recorded",
                                        realtime=False))
    xyz = np.array([f.xyz for f in frames])
    np.testing.assert_allclose(xyz[:, K["pelvis"]], 0.5 * (clip[:, K["left_hip"]] + clip[:, K["right_hip"]]))
    capsules, points = HumanCapsules(HumanConfig()), PointFilter(PerceptionConfig().point_filter, 15)
    valid = [capsules(points(f.t, f.xyz, f.conf))[1] for f in frames]
    assert all(v[CAPSULE_NAMES.index("torso")] for v in valid)


def test_placements_put_the_person_where_they_say(tmp_path) -> None:
    clip = walking_clip()
    # The same person recorded in some other world frame: turned 130° and 3 m away.
    save_shuffled(tmp_path / "elsewhere.npz", Placement(x=3.0, y=-1.0, yaw=math.radians(130)).apply(clip))
    conf = PerceptionConfig(source="replay", recording=str(tmp_path / "elsewhere.npz"), realtime=False)

    side = frames_of(conf.model_copy(update={"placement": "side-by-side"}))
    np.testing.assert_allclose(side[0].xyz[K["pelvis"], :2], (0.0, conf.side_by_side_y), atol=1e-9)
    np.testing.assert_allclose(side[-1].xyz, Placement(y=conf.side_by_side_y).apply(clip[-1]), atol=1e-9)

    facing = frames_of(conf.model_copy(update={"placement": "facing"}))[0].xyz
    assert facing[K["pelvis"], 0] == pytest.approx(conf.facing_distance)
    assert facing[K["left_shoulder"], 1] < facing[K["right_shoulder"], 1]  # turned around: left is −y
    assert facing[K["left_ankle"], 2] == pytest.approx(clip[0, K["left_ankle"], 2])  # floor untouched

    explicit = frames_of(conf.model_copy(update={"placement": "0.5,-0.8,1.5708"}))[0].xyz
    np.testing.assert_allclose(explicit[K["pelvis"], :2], (0.5, -0.8), atol=1e-9)
    assert initial_pose(place_recording(read_recording(tmp_path / "elsewhere.npz"), Placement(yaw=0.3)))[2] == pytest.approx(0.3)

    assert parse_placement("recorded", conf) == Placement(normalize=False)
    with pytest.raises(ValueError, match="x,y,yaw"):
        parse_placement("left-of-robot", conf)


def test_default_placements_bring_arms_into_reach_but_keep_torsos_apart() -> None:
    """Scenarios (narrow and wide shoulders) and the real clips side by side."""
    conf, human = PerceptionConfig(), HumanConfig()
    clips: list[tuple[str, np.ndarray, bool]] = []
    for name, scenario in SCENARIOS.items():
        for width in (0.20, 0.37):
            placement = parse_placement("auto", conf, auto=scenario.placement)
            _, xyz = scenario_frames(scenario, np.arange(0, scenario.period, 1 / FPS), placement, Body(shoulder_width=width))
            clips.append((f"{name} w={width}", xyz, name in ("side-by-side-arm-raise", "reach-forward")))
    for path in sorted(MOCAP_DIR.glob("*.npz")) if MOCAP_DIR.is_dir() else []:
        placed = place_recording(read_recording(path), parse_placement("side-by-side", conf))
        clips.append((path.name, placed.xyz, True))
    for label, xyz, reaches in clips:
        torso_gap, arm_to_shoulder = capsule_clearances(xyz, conf, human)
        assert torso_gap >= 0.25, f"{label}: the person's torso comes within {torso_gap:.2f} m of the robot's"
        if reaches:
            assert arm_to_shoulder < ROBOT_ARM_REACH, f"{label}: arms stay {arm_to_shoulder:.2f} m from the robot's shoulders"


def capsule_clearances(xyz: np.ndarray, conf: PerceptionConfig, human: HumanConfig) -> tuple[float, float]:
    """Min surface gap human torso ↔ robot torso, min gap human arm capsules ↔ robot shoulder joints."""
    point_filter, builder = PointFilter(conf.point_filter, 15), HumanCapsules(human)
    arms = [CAPSULE_NAMES.index(n) for n in ("left_upper_arm", "left_forearm", "right_upper_arm", "right_forearm")]
    torso_gap = arm_gap = math.inf
    for i, points in enumerate(xyz):
        capsules, _, _ = builder(point_filter(i / FPS, points, np.ones(15)))
        a, b = capsules[0]
        d = segment_closest_points(a, b, ROBOT_TORSO[0], ROBOT_TORSO[1]).distance[0]
        torso_gap = min(torso_gap, d - builder.radii[0] - ROBOT_TORSO[2])
        for k in arms:
            for shoulder in ROBOT_SHOULDERS:
                d = segment_closest_points(capsules[k, 0], capsules[k, 1], shoulder, shoulder).distance[0]
                arm_gap = min(arm_gap, d - builder.radii[k])
    return torso_gap, arm_gap


def test_real_time_pacing_and_seamless_scenario_loop() -> None:
    conf = PerceptionConfig(scenario="wave", scenario_fps=FPS, loop=True)
    source = open_source(conf)
    stop = threading.Event()
    started = time.monotonic()
    frames = []
    for frame in source.frames(stop):
        frames.append(frame)
        if len(frames) == 10:
            stop.set()
    assert time.monotonic() - started >= 9 / FPS * 0.9  # paced, not as fast as possible
    assert len(frames) == 10 and frames[-1].captured - frames[0].captured >= 9 / FPS * 0.9

    fast = open_source(conf.model_copy(update={"realtime": False}))
    stop = threading.Event()
    period_frames = round(get_scenario("wave").period * FPS)
    laps = []
    for frame in fast.frames(stop):
        laps.append(frame)
        if len(laps) == 2 * period_frames + 1:
            stop.set()
    times = np.array([f.t for f in laps])
    assert (np.diff(times) > 0).all() and not any(f.discontinuity for f in laps)  # periodic: no reset
    np.testing.assert_allclose(laps[period_frames].xyz, laps[0].xyz)


def test_replay_loop_marks_each_restart(tmp_path) -> None:
    save_shuffled(tmp_path / "walk.npz", walking_clip(6))
    conf = PerceptionConfig(source="replay", recording=str(tmp_path / "walk.npz"), realtime=False, loop=True)
    frames = frames_of(conf, limit=15)
    assert [f.discontinuity for f in frames] == [i in (6, 12) for i in range(15)]
    assert (np.diff([f.t for f in frames]) > 0).all()


def test_unavailable_sources_say_why(tmp_path) -> None:
    with pytest.raises(SourceUnavailable, match="cannot open camera 63|pose-model install"):
        open_source(PerceptionConfig(source="camera", camera={"device": 63}))  # no /dev/video63 here
    with pytest.raises(SourceUnavailable, match="needs a recording"):
        open_source(PerceptionConfig(source="replay"))
    with pytest.raises(SourceUnavailable, match="cannot read"):
        open_source(PerceptionConfig(source="replay", recording=str(tmp_path / "missing.npz")))
    with pytest.raises(SourceUnavailable, match="unknown scenario"):
        open_source(PerceptionConfig(scenario="juggling"))


def test_record_scenario_writes_a_replayable_recording(tmp_path) -> None:
    out = tmp_path / "raise.npz"
    done = subprocess.run(
        [sys.executable, "-m", "safemimic.cli", "record-scenario", "side-by-side-arm-raise", str(out),
         "--seconds", "2", "--fps", "20", "--placement", "facing", "--shoulder-width", "0.25"],
        cwd=REPO, capture_output=True, text=True, timeout=60,
    )
    assert done.returncode == 0, done.stderr
    recording = read_recording(out)
    assert len(recording) == 40 and recording.fps == 20 and "side-by-side-arm-raise" in recording.source
    expected = scenario_recording(get_scenario("side-by-side-arm-raise"), 2, 20, Placement(x=0.95, yaw=math.pi), Body(shoulder_width=0.25))
    np.testing.assert_allclose(recording.xyz, expected.xyz, atol=1e-12)
    width = np.linalg.norm(recording.xyz[0, K["left_shoulder"]] - recording.xyz[0, K["right_shoulder"]])
    assert width == pytest.approx(0.25)

    replayed = frames_of(PerceptionConfig(source="replay", recording=str(out), placement="recorded", realtime=False))
    np.testing.assert_allclose(np.array([f.xyz for f in replayed]), recording.xyz)

    bad = subprocess.run([sys.executable, "-m", "safemimic.cli", "record-scenario", "juggling", str(out)],
                         cwd=REPO, capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and "invalid choice" in bad.stderr
