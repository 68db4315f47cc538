"""Benchmark: one perception step, filter + angles + capsules per frame (budget p50 ≤ 100 µs; architecture §8: ≤ 1 ms).

Input: the scripted ``wave`` and ``side-by-side-arm-raise`` scenarios (arms overhead, in the
robot's workspace) at 30 fps with 3 mm Gaussian noise, a single-frame outlier every 50 frames
(rejected) and a missing wrist every 40 frames, so every branch of the filter and the continuous
estimator runs. Frames are precomputed; the timed call is ``PerceptionPipeline.step`` (continuous
estimator; the paper's is timed too). Building and encoding the HumanState are reported apart.

Also the camera source on this CPU (``camera``, ``camera_fps``): a 640 × 480 MJPG video of
scikit-image's astronaut photograph read by the real source (decode → BlazePose tracking →
PnP → robot frame), frames per second, plus each stage's milliseconds (the detector apart: it
runs only when the track is lost). Skipped, with the reason, where the camera extra, the
weights or scikit-image are missing.
"""

from __future__ import annotations

import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from bench.common import percentiles_us, time_calls
from services.perception.pipeline import PerceptionPipeline
from services.perception.placement import parse_placement
from services.perception.scenarios import get_scenario, scenario_frames
from services.perception.base import SkeletonFrame
from shared.codec import encode
from shared.config import HumanConfig, PerceptionConfig
from shared.names import KEYPOINT_INDEX

BUDGET_P50_US = 100.0
FPS = 30.0
NOISE_M = 0.003
CAMERA_FRAMES = 90


def bench_frames(n_frames: int = 2000) -> list[SkeletonFrame]:
    """Noisy scenario frames with outliers and dropouts (deterministic)."""
    conf = PerceptionConfig()
    rng = np.random.default_rng(0)
    frames: list[SkeletonFrame] = []
    t = 0.0
    for name in ("wave", "side-by-side-arm-raise"):
        scenario = get_scenario(name)
        times = np.arange(n_frames // 2) / FPS
        _, xyz = scenario_frames(scenario, times, parse_placement("auto", conf, auto=scenario.placement))
        xyz = xyz + rng.normal(scale=NOISE_M, size=xyz.shape)
        for i in range(len(times)):
            points, confidence = xyz[i].copy(), np.ones(len(xyz[i]))
            if i % 50 == 25:
                points[KEYPOINT_INDEX["left_wrist"]] += 0.5  # outlier
            if i % 40 == 10:
                confidence[KEYPOINT_INDEX["right_wrist"]] = 0.0  # dropout
            frames.append(SkeletonFrame(t=t, xyz=points, conf=confidence, captured=0.0))
            t += 1.0 / FPS
    return frames


def _time_pipeline(frames: list[SkeletonFrame], estimator: str) -> tuple[np.ndarray, PerceptionPipeline]:
    pipeline = PerceptionPipeline(PerceptionConfig(angles={"estimator": estimator}), HumanConfig())
    for frame in frames[:100]:  # warm-up
        pipeline.step(frame)
    pipeline = PerceptionPipeline(PerceptionConfig(angles={"estimator": estimator}), HumanConfig())
    samples = np.empty(len(frames))
    clock = time.perf_counter
    for i, frame in enumerate(frames):
        start = clock()
        pipeline.step(frame)
        samples[i] = clock() - start
    return samples, pipeline


def run(repeats: int = 4) -> dict[str, Any]:
    frames = bench_frames()
    samples: dict[str, list[np.ndarray]] = {"continuous": [], "paper": []}
    pipelines: dict[str, PerceptionPipeline] = {}
    for _ in range(repeats):  # round robin: load from other processes falls on both alike
        for estimator, runs in samples.items():
            timed, pipelines[estimator] = _time_pipeline(frames, estimator)
            runs.append(timed)
    stats = percentiles_us(np.concatenate(samples["continuous"]))
    paper = np.concatenate(samples["paper"])
    pipeline = pipelines["continuous"]
    result = pipeline.step(SkeletonFrame(t=frames[-1].t + 1 / FPS, xyz=frames[-1].xyz, conf=frames[-1].conf, captured=0.0))
    message_stats = percentiles_us(time_calls(lambda: result.to_message(stamp=1.0), 5000))
    encode_stats = percentiles_us(time_calls(lambda: encode(result.to_message(stamp=1.0)), 5000))
    counters = pipeline.counters
    return {
        "name": "perception",
        "what": "PerceptionPipeline.step: point filter + 8 pose angles (continuous) + 7 capsules with velocities, per frame",
        "unit": "us",
        "p50": stats["p50"],
        "p99": stats["p99"],
        "stats": stats,
        "paper_estimator": percentiles_us(paper),
        "to_message": message_stats,
        "to_message_and_encode": encode_stats,
        "frames": len(frames),
        "rejected_jumps": counters.rejected_jumps,
        "invalid_frames": counters.invalid_frames,
        "budget_p50": BUDGET_P50_US,
        "within_budget": stats["p50"] <= BUDGET_P50_US,
        **bench_camera(),
    }


def _camera_frame() -> np.ndarray:
    """scikit-image's astronaut photograph (BGR) centred on a 640 × 480 grey canvas."""
    import cv2
    import skimage.data

    canvas = np.full((480, 640, 3), 128, np.uint8)
    canvas[:, 80:560] = cv2.resize(cv2.cvtColor(skimage.data.astronaut(), cv2.COLOR_RGB2BGR), (480, 480))
    return canvas


def _ms(samples_s: list[float]) -> dict[str, float]:
    ms = np.asarray(samples_s) * 1e3
    return {"p50": float(np.percentile(ms, 50)), "p90": float(np.percentile(ms, 90)), "mean": float(ms.mean()), "n": int(ms.size)}


def bench_camera(n_frames: int = CAMERA_FRAMES) -> dict[str, Any]:
    """``camera_fps`` of the camera source on a video file and per-stage ms (``camera``); or why skipped."""
    try:
        import cv2

        from services.perception.camera.blazepose import BlazePose
        from services.perception.camera.geometry import blazepose_skeleton, camera_matrix, optical_to_robot
        from services.perception.camera.model import ModelError, locate_models, model_dir
        from services.perception.sources import open_source

        frame = _camera_frame()
        conf = PerceptionConfig(source="camera", realtime=False)
        paths = locate_models(model_dir(conf.camera.model_dir))
        estimator = BlazePose(paths, threads=conf.camera.threads)
    except (ImportError, ModelError) as exc:
        return {"camera": {"skipped": str(exc)}, "camera_fps": None}
    rgb = cv2.cvtColor(frame, cv2.COLOR_BGR2RGB)
    k = camera_matrix(conf.camera.intrinsics, 640, 480)
    to_robot = optical_to_robot(conf.camera.extrinsics)
    stages: dict[str, list[float]] = {"convert": [], "landmarks": [], "geometry": [], "detector": []}
    clock = time.perf_counter
    pose = estimator(rgb)
    for _ in range(n_frames // 3):
        start = clock()
        estimator.detector(rgb)
        stages["detector"].append(clock() - start)
        start = clock()
        converted = cv2.cvtColor(frame, cv2.COLOR_BGR2RGB)
        stages["convert"].append(clock() - start)
        start = clock()
        pose = estimator.landmarker(converted, pose.next_roi)
        stages["landmarks"].append(clock() - start)
        start = clock()
        blazepose_skeleton(pose.image, pose.world, pose.confidence, k, np.zeros(0), to_robot, conf.point_filter.min_confidence)
        stages["geometry"].append(clock() - start)
    with tempfile.TemporaryDirectory(prefix="safemimic-bench-") as folder:
        video = Path(folder) / "astronaut.avi"
        writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), FPS, (640, 480))
        for _ in range(n_frames):
            writer.write(frame)
        writer.release()
        source = open_source(conf.model_copy(update={"camera": conf.camera.model_copy(update={"device": str(video)})}))
        start = clock()
        produced = sum(1 for _ in source.frames(threading.Event()))
        elapsed = clock() - start
    counters = source.counters()
    return {
        "camera_fps": produced / elapsed,
        "camera": {
            "what": "camera source on a 640x480 MJPG video of astronaut.png: decode + BlazePose (tracking) + PnP + robot frame",
            "frames": produced,
            "no_person": counters["no_person"],
            "threads": conf.camera.threads,
            "stage_ms": {name: _ms(samples) for name, samples in stages.items()},
        },
    }
