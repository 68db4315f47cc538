"""The ``camera`` source on real photographs of people (scikit-image's ``astronaut.png`` and
``camera.png``): BlazePose on LiteRT, monocular 3D by PnP, the robot-frame transform, the model
installer, and the source end to end on a video file (also through ``safemimic perception``)."""

from __future__ import annotations

import hashlib
import math
import subprocess
import sys
import threading
import zipfile
from pathlib import Path

import cv2
import numpy as np
import pytest
import skimage.data

from services.perception.camera.blazepose import BlazePose, PoseLandmarks, Roi, ssd_anchors
from services.perception.camera.geometry import (
    BLAZEPOSE_KEYPOINTS,
    blazepose_skeleton,
    camera_matrix,
    optical_to_robot,
    rpy_matrix,
    solve_camera_points,
)
from services.perception.camera.model import (
    MODEL_FILES,
    ModelError,
    ModelPaths,
    default_model_dir,
    extract_models,
    install_models,
    locate_models,
)
from services.perception.pipeline import PerceptionPipeline
from services.perception.sources import SourceUnavailable, open_source
from services.safety.human_memory import HumanMemory
from services.safety.protective_stop import STILL_SPEED
from shared.config import CameraExtrinsics, CameraIntrinsics, HumanConfig, PerceptionConfig
from shared.names import KEYPOINT_INDEX as K
from tests.support.processes import free_port
from tests.support.team import REPO
from tests.test_perception_service import LIGHT_RUNNER

MIN_CONFIDENCE = PerceptionConfig().point_filter.min_confidence
#: BlazePose landmark indices used below.
NOSE, LEFT_EAR, RIGHT_EAR, LEFT_SHOULDER, RIGHT_SHOULDER, RIGHT_ELBOW, RIGHT_HIP = 0, 7, 8, 11, 12, 14, 24
#: Where the body parts are in the photographs (x0, y0, x1, y1 px), drawn generously around them.
#: astronaut.png: facing the camera, cut at the waist (hips and hands out of view or hidden).
#: camera.png: the cameraman in profile, facing right, his left arm hidden behind the camera.
REGIONS = {
    "astronaut": {
        NOSE: (180, 90, 270, 170), LEFT_EAR: (230, 80, 310, 170), RIGHT_EAR: (140, 80, 220, 170),
        LEFT_SHOULDER: (250, 200, 360, 300), RIGHT_SHOULDER: (60, 200, 170, 300),
    },
    "camera": {
        NOSE: (200, 120, 280, 210), RIGHT_EAR: (170, 100, 240, 180), RIGHT_SHOULDER: (60, 130, 170, 240),
        RIGHT_ELBOW: (90, 240, 220, 370), RIGHT_HIP: (40, 260, 170, 380),
    },
}
#: The person's own extent in each photograph (with the camera he holds): confident points lie inside.
PERSON = {"astronaut": (0, 0, 400, 512), "camera": (0, 60, 420, 512)}


def photograph(name: str) -> np.ndarray:
    """scikit-image's photograph as a BGR image (camera.png is grey)."""
    image = getattr(skimage.data, name)()
    return cv2.cvtColor(image, cv2.COLOR_GRAY2BGR if image.ndim == 2 else cv2.COLOR_RGB2BGR)


@pytest.fixture(scope="module")
def models() -> ModelPaths:
    """The installed weights (``make install`` runs ``safemimic pose-model install``; done here if not)."""
    try:
        return locate_models(default_model_dir())
    except ModelError:
        return install_models(default_model_dir())


@pytest.fixture(scope="module")
def poses(models: ModelPaths) -> dict[str, PoseLandmarks]:
    blazepose = BlazePose(models)
    found = {}
    for name in REGIONS:
        blazepose.reset()
        pose = blazepose(cv2.cvtColor(photograph(name), cv2.COLOR_BGR2RGB))
        assert pose is not None, f"nobody found in {name}.png"
        found[name] = pose
    return found


def inside(point: np.ndarray, box: tuple[float, float, float, float]) -> bool:
    return box[0] <= point[0] <= box[2] and box[1] <= point[1] <= box[3]


def skeleton_of(pose: PoseLandmarks, extrinsics: CameraExtrinsics | None = None,
                min_confidence: float = MIN_CONFIDENCE) -> tuple[np.ndarray, np.ndarray]:
    k = camera_matrix(CameraIntrinsics(), 512, 512)
    return blazepose_skeleton(pose.image, pose.world, pose.confidence, k, np.zeros(0),
                              optical_to_robot(extrinsics or CameraExtrinsics()), min_confidence)


def test_anchor_grid_matches_the_detector_output() -> None:
    anchors = ssd_anchors()
    assert anchors.shape == (28 * 28 * 2 + 14 * 14 * 2 + 7 * 7 * 6, 2) == (2254, 2)
    np.testing.assert_allclose(anchors[0], [0.5 / 28, 0.5 / 28])
    np.testing.assert_allclose(anchors[-1], [6.5 / 7, 6.5 / 7])


def test_roi_is_centred_scaled_and_turned_upright() -> None:
    upright = Roi.from_points(np.array([100.0, 200.0]), np.array([100.0, 100.0]))  # body axis straight up
    assert (upright.cx, upright.cy, upright.size, upright.rotation) == pytest.approx((100, 200, 250, 0))
    lying = Roi.from_points(np.array([100.0, 200.0]), np.array([200.0, 200.0]))  # head to the image right
    assert lying.rotation == pytest.approx(math.pi / 2)
    # The crop's top centre (where the head goes) is on the image's side of the scale point.
    affine = lying.crop_to_image(256)
    np.testing.assert_allclose(affine[:, :2] @ [128.0, 0.0] + affine[:, 2], [225.0, 200.0])


@pytest.mark.parametrize("name", REGIONS)
def test_landmarks_land_on_the_person(poses: dict[str, PoseLandmarks], name: str) -> None:
    pose = poses[name]
    assert pose.score > 0.9
    for index, box in REGIONS[name].items():
        assert pose.confidence[index] >= MIN_CONFIDENCE, (name, index)
        assert inside(pose.image[index], box), (name, index, pose.image[index])
    confident = [i for i in sorted({j for js in BLAZEPOSE_KEYPOINTS.values() for j in js})
                 if pose.confidence[i] >= MIN_CONFIDENCE]
    assert all(inside(pose.image[i], PERSON[name]) for i in confident)
    if name == "astronaut":  # facing the camera: her left shoulder is on the image's right
        assert pose.image[LEFT_SHOULDER, 0] > pose.image[RIGHT_SHOULDER, 0]


@pytest.mark.parametrize(("name", "shortest"), [("astronaut", 0.2), ("camera", 0.15)])
def test_limbs_are_human_sized_in_metres(poses: dict[str, PoseLandmarks], name: str, shortest: float) -> None:
    """Upper arm 0.2–0.4 m, shoulder joints 0.2–0.4 m apart (camera.png is in profile, its near arm
    points at the lens and the model's depth shortens it: 0.21 m, so its bound is 0.15 m)."""
    xyz, _ = skeleton_of(poses[name])
    arms = [np.linalg.norm(xyz[K[f"{side}_shoulder"]] - xyz[K[f"{side}_elbow"]]) for side in ("left", "right")]
    seen = [length for length in arms if np.isfinite(length)]
    assert seen and all(shortest <= length <= 0.4 for length in seen), arms
    shoulders = np.linalg.norm(xyz[K["left_shoulder"]] - xyz[K["right_shoulder"]])
    assert 0.2 <= shoulders <= 0.4


def test_low_confidence_points_are_missing_never_invented(poses: dict[str, PoseLandmarks]) -> None:
    pose = poses["astronaut"]  # cut at the waist: hips, knees and ankles are not in the picture
    for min_confidence in (MIN_CONFIDENCE, 0.9):
        xyz, conf = skeleton_of(pose, min_confidence=min_confidence)
        for name, sources in BLAZEPOSE_KEYPOINTS.items():
            seen = pose.confidence[list(sources)].min() >= min_confidence
            assert np.isfinite(xyz[K[name]]).all() == seen, name
            assert (conf[K[name]] >= min_confidence) if seen else conf[K[name]] == 0.0
    xyz, _ = skeleton_of(pose)
    assert np.isnan(xyz[[K["pelvis"], K["left_knee"], K["right_ankle"]]]).all()
    assert np.isfinite(xyz[[K["head"], K["left_shoulder"], K["right_shoulder"]]]).all()


def test_person_is_placed_in_front_of_the_camera_in_the_robot_frame(poses: dict[str, PoseLandmarks]) -> None:
    """Default mount: camera 2.5 m in front of the robot, 1.2 m high, looking back at it. The astronaut,
    photographed at chest height from about a metre, stands between the camera and the robot, upright."""
    xyz, _ = skeleton_of(poses["astronaut"])
    head, left, right = xyz[K["head"]], xyz[K["left_shoulder"]], xyz[K["right_shoulder"]]
    assert 0.5 < head[0] < 2.2 and abs(head[1]) < 0.4 and 0.9 < head[2] < 1.8
    assert head[2] > max(left[2], right[2])  # head above the shoulders
    assert left[1] > right[1]  # she faces the camera, the robot's heading (+x): her left is the robot's left (+y)


def test_known_extrinsics_give_known_robot_coordinates() -> None:
    default = optical_to_robot(CameraExtrinsics())  # at (2.5, 0, 1.2), yaw π: looks along −x
    optical = np.array([[0.0, 0.0, 2.0], [1.0, 0.0, 2.0], [0.0, 1.0, 2.0]])  # ahead, image right, image down
    np.testing.assert_allclose(default.apply(optical), [[0.5, 0.0, 1.2], [0.5, 1.0, 1.2], [0.5, 0.0, 0.2]], atol=1e-12)
    tilted = optical_to_robot(CameraExtrinsics(position=[0.0, 0.0, 1.5], rpy=[0.0, math.radians(30), 0.0]))
    np.testing.assert_allclose(tilted.apply(np.array([0.0, 0.0, 2.0])), [2 * math.cos(math.pi / 6), 0.0, 1.5 - 1.0], atol=1e-12)
    turned = optical_to_robot(CameraExtrinsics(position=[0.0, 0.0, 1.0], rpy=[0.0, 0.0, math.pi / 2]))  # looks along +y
    np.testing.assert_allclose(turned.apply(np.array([0.0, 0.0, 3.0])), [0.0, 3.0, 1.0], atol=1e-12)
    rotation = rpy_matrix(0.3, -0.2, 2.0)
    np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(rotation) == pytest.approx(1.0)


def test_intrinsics_from_field_of_view_or_config() -> None:
    k = camera_matrix(CameraIntrinsics(hfov_deg=90.0), 640, 480)
    np.testing.assert_allclose(k, [[320.0, 0, 320.0], [0, 320.0, 240.0], [0, 0, 1]])
    k = camera_matrix(CameraIntrinsics(fx=600.0, fy=610.0, cx=300.0, cy=250.0), 640, 480)
    np.testing.assert_allclose(k, [[600.0, 0, 300.0], [0, 610.0, 250.0], [0, 0, 1]])


def test_pnp_recovers_where_a_known_body_stands(poses: dict[str, PoseLandmarks]) -> None:
    """Project the astronaut's metric landmarks from a known pose (turned 0.3 rad, 3 m away) with a
    distorted lens; solving from the image points gives back that pose's camera-frame points."""
    world = poses["astronaut"].world
    rotation = rpy_matrix(0.1, 0.3, -0.05)
    translation = np.array([0.4, -0.2, 3.0])
    truth = world @ rotation.T + translation
    k = camera_matrix(CameraIntrinsics(), 640, 480)
    distortion = np.array([-0.1, 0.02, 0.0, 0.0])
    image, _ = cv2.projectPoints(world, cv2.Rodrigues(rotation)[0], translation, k, distortion)
    usable = np.ones(len(world), dtype=bool)
    usable[::3] = False  # a third not used (low confidence): still transformed
    solved = solve_camera_points(image.reshape(-1, 2), world, usable, k, distortion)
    np.testing.assert_allclose(solved, truth, atol=1e-4)
    assert solve_camera_points(image.reshape(-1, 2), world, np.arange(len(world)) < 5, k, distortion) is None


def write_video(path: Path, frames: list[np.ndarray], fps: float) -> Path:
    height, width = frames[0].shape[:2]
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, (width, height))
    assert writer.isOpened()
    for frame in frames:
        writer.write(frame)
    writer.release()
    return path


@pytest.fixture(scope="module")
def video(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """4 frames of the astronaut, 2 empty (black) frames, 3 of the astronaut again, at 10 fps."""
    astronaut, empty = photograph("astronaut"), np.zeros((512, 512, 3), np.uint8)
    return write_video(tmp_path_factory.mktemp("video") / "astronaut.avi", [astronaut] * 4 + [empty] * 2 + [astronaut] * 3, 10.0)


def test_source_streams_a_video_file_as_skeleton_frames(models: ModelPaths, video: Path) -> None:
    conf = PerceptionConfig(source="camera", realtime=False, camera={"device": str(video), "model_dir": str(models.detector.parent)})
    source = open_source(conf)
    assert source.fps == pytest.approx(10.0) and str(video) in source.name
    frames = list(source.frames(threading.Event()))
    assert [f.t for f in frames] == pytest.approx(np.arange(9) / 10.0)
    assert all(f.xyz.shape == (15, 3) and f.conf.shape == (15,) for f in frames)
    seen = [i for i, f in enumerate(frames) if np.isfinite(f.xyz[K["head"]]).all()]
    assert seen == [0, 1, 2, 3, 6, 7, 8]  # nobody in the black frames, found again after them
    for i in (4, 5):
        assert np.isnan(frames[i].xyz).all() and (frames[i].conf == 0).all()
    heads = np.array([frames[i].xyz[K["head"]] for i in seen])
    # The same still photograph: the same place, up to the monocular depth's jitter along the optical axis.
    spread = np.ptp(heads, axis=0)
    assert spread[0] < 0.3 and spread[1:].max() < 0.1, spread
    assert source.counters() == {"frames": 9, "no_person": 2, "failed": 0, "ended": "end of the video file"}


def test_a_still_photograph_is_judged_still_through_its_depth_jitter(tmp_path: Path, models: ModelPaths) -> None:
    """The cameraman photographed, 10 s of the same frame at 30 fps, through the camera source, the
    point filter and the capsules into the safety layer's memory: the monocular depth jitters every
    capsule by centimetres from frame to frame, so his measured capsule velocities never fall to the
    back-out's still speed, but their spread over the last second does on most frames after the
    first 3 s where no capsule is held (his half-hidden legs flicker in and out)."""
    video = write_video(tmp_path / "camera.avi", [photograph("camera")] * 300, 30.0)
    source = open_source(PerceptionConfig(source="camera", realtime=False,
                                          camera={"device": str(video), "model_dir": str(models.detector.parent)}))
    pipeline, memory = PerceptionPipeline(PerceptionConfig(), HumanConfig()), HumanMemory()
    measured, seen, held = [], [], []
    for frame in source.frames(threading.Event()):
        result = pipeline.step(frame)
        memory.update(result.to_message(frame.t, frame.t), frame.t, 2.0)
        measured.append(np.linalg.norm(result.capsule_velocities[result.capsule_valid], axis=2).max(initial=0.0))
        seen.append(memory.seen_speed)
        held.append(memory.lost)
    assert len(seen) == 300
    after = slice(90, None)
    measured_still = np.array(measured[after]) <= STILL_SPEED
    seen_still = (np.array(seen[after]) <= STILL_SPEED)[~np.array(held[after])]
    assert measured_still.mean() < 0.05 and len(seen_still) > 100
    assert seen_still.mean() > 0.4, seen_still.mean()


def test_source_stops_when_asked(models: ModelPaths, video: Path) -> None:
    source = open_source(PerceptionConfig(source="camera", camera={"device": str(video), "model_dir": str(models.detector.parent)}))
    stop = threading.Event()
    for count, _ in enumerate(source.frames(stop), start=1):
        stop.set()
    assert count == 1 and not source.capture.isOpened()  # released


def test_unavailable_camera_sources_say_what_to_do(tmp_path: Path, models: ModelPaths) -> None:
    with pytest.raises(SourceUnavailable, match="safemimic pose-model install"):
        open_source(PerceptionConfig(source="camera", camera={"model_dir": str(tmp_path)}))
    model_dir = str(models.detector.parent)
    with pytest.raises(SourceUnavailable, match="no such video file"):
        open_source(PerceptionConfig(source="camera", camera={"device": str(tmp_path / "none.mp4"), "model_dir": model_dir}))
    (tmp_path / "junk.mp4").write_bytes(b"not a video")
    with pytest.raises(SourceUnavailable, match="cannot open"):
        open_source(PerceptionConfig(source="camera", camera={"device": str(tmp_path / "junk.mp4"), "model_dir": model_dir}))
    with pytest.raises(SourceUnavailable, match="cannot open camera 63"):
        open_source(PerceptionConfig(source="camera", camera={"device": 63, "model_dir": model_dir}))


def test_models_install_from_a_wheel_and_are_verified(tmp_path: Path, models: ModelPaths) -> None:
    wheel = tmp_path / "mediapipe-0.10.21-py3-none-any.whl"
    with zipfile.ZipFile(wheel, "w") as archive:
        for spec in MODEL_FILES:
            archive.write(models.detector.parent / spec.name, spec.member)
    installed = extract_models(wheel, tmp_path / "models")
    for spec, path in zip(MODEL_FILES, (installed.detector, installed.landmarker), strict=True):
        assert hashlib.sha256(path.read_bytes()).hexdigest() == spec.sha256
    assert install_models(tmp_path / "models") == installed  # already there: nothing downloaded
    installed.landmarker.write_bytes(b"truncated")
    with pytest.raises(ModelError, match="corrupt"):
        locate_models(tmp_path / "models")
    forged = tmp_path / "forged.whl"
    with zipfile.ZipFile(forged, "w") as archive:
        for spec in MODEL_FILES:
            archive.writestr(spec.member, b"other weights")
    with pytest.raises(ModelError, match="pinned SHA-256"):
        extract_models(forged, tmp_path / "other")


def pose_model(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "safemimic.cli", "pose-model", *args],
                          cwd=REPO, capture_output=True, text=True, timeout=60)


def test_pose_model_command_checks_and_explains(tmp_path: Path, models: ModelPaths) -> None:
    ok = pose_model("check", "--dir", str(models.detector.parent))
    assert ok.returncode == 0 and "pose models OK" in ok.stdout
    missing = pose_model("check", "--dir", str(tmp_path))
    assert missing.returncode == 1 and "safemimic pose-model install" in missing.stderr and "Traceback" not in missing.stderr
    where = pose_model("path", "--dir", str(tmp_path))
    assert where.returncode == 0 and where.stdout.strip() == str(tmp_path)


@pytest.mark.integration
def test_perception_service_runs_the_camera_on_a_video_without_heavy_imports(spawn, models: ModelPaths, video: Path) -> None:
    port = free_port()
    service = spawn(
        "-c", LIGHT_RUNNER, "perception", "--device", str(video), "--fast", "--robot-id", f"camera_{port}",
        "--mode", "peer", "--listen", f"tcp/127.0.0.1:{port}", "--no-multicast",
        env={"SAFEMIMIC__PERCEPTION__CAMERA__MODEL_DIR": str(models.detector.parent)},
    )
    ready = service.wait_json("ready", timeout=30)
    assert ready["source"] == f"camera {video}" and ready["fps"] == pytest.approx(10.0)
    done = service.wait_json("done", timeout=60)
    imports = service.wait_json("imports", timeout=10)
    assert service.popen.wait(10) == 0
    assert imports["attempted"] == [] and imports["loaded"] == []
    assert done["frames"] == done["published"] == 9 and done["errors"] == 0
    assert done["source"] == {"frames": 9, "no_person": 2, "failed": 0, "ended": "end of the video file"}
