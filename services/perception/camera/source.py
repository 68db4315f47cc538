"""The ``camera`` skeleton source: OpenCV capture → BlazePose → 15 canonical keypoints in the robot frame.

``perception.camera.device`` is a camera index (``/dev/videoN``), a video file or a stream URL. A
camera is asked for ``width`` × ``height`` at ``fps``; frames are stamped with ``time.monotonic()``
when read (``t`` = ``captured``) and never paced (the camera paces). A video file plays at its
own frame rate (``t`` = frame index / file rate, paced unless ``perception.realtime`` is false).

Every frame yields a :class:`~services.perception.base.SkeletonFrame`: the person's keypoints
(:func:`~services.perception.camera.geometry.blazepose_skeleton`), or all missing when nobody is
seen. A frame whose processing raises is counted and skipped. The stream ends when the file ends
or the camera stops delivering frames (unplugged), with the reason in the log and :meth:`counters`.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Iterator
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from services.perception.camera.blazepose import BlazePose
from services.perception.camera.geometry import blazepose_skeleton, camera_matrix, missing_skeleton, optical_to_robot
from services.perception.camera.model import ModelError, locate_models, model_dir
from services.perception.sources import SourceUnavailable
from services.perception.base import Pacer, SkeletonFrame
from shared.config import CameraConfig, PerceptionConfig

log = logging.getLogger("safemimic.perception.camera")

#: Failing frames logged with a traceback (the rest are only counted).
_LOGGED_FAILURES = 10


@dataclass
class CameraCounters:
    """Frames read, frames with nobody seen, frames that failed, and why the stream ended ("" while running)."""

    frames: int = 0
    no_person: int = 0
    failed: int = 0
    ended: str = ""


class CameraSource:
    """A :class:`~services.perception.base.SkeletonSource` over an opened capture (see module doc)."""

    def __init__(self, capture: cv2.VideoCapture, estimator: BlazePose, conf: PerceptionConfig, is_file: bool) -> None:
        self.capture = capture
        self.estimator = estimator
        self.camera: CameraConfig = conf.camera
        self.min_confidence = conf.point_filter.min_confidence
        self.realtime = conf.realtime
        self.is_file = is_file
        reported = capture.get(cv2.CAP_PROP_FPS)
        self.fps = float(reported) if 0 < reported <= 1000 else self.camera.fps
        self.name = f"camera {self.camera.device}"
        self.to_robot = optical_to_robot(self.camera.extrinsics)
        self.distortion = np.asarray(self.camera.intrinsics.distortion, dtype=np.float64)
        self._k: tuple[tuple[int, int], np.ndarray] | None = None  # (image size, K)
        self._counters = CameraCounters()

    def counters(self) -> dict[str, Any]:
        return asdict(self._counters)

    def intrinsics(self, width: int, height: int) -> np.ndarray:
        """K for this image size (computed once per size)."""
        if self._k is None or self._k[0] != (width, height):
            self._k = ((width, height), camera_matrix(self.camera.intrinsics, width, height))
        return self._k[1]

    def skeleton(self, bgr: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """One BGR (or grey) frame → robot-frame keypoints (15, 3) and confidences (15,); all NaN if nobody."""
        rgb = cv2.cvtColor(bgr, cv2.COLOR_GRAY2RGB if bgr.ndim == 2 else cv2.COLOR_BGR2RGB)
        pose = self.estimator(rgb)
        if pose is None:
            self._counters.no_person += 1
            return missing_skeleton()
        height, width = rgb.shape[:2]
        return blazepose_skeleton(pose.image, pose.world, pose.confidence, self.intrinsics(width, height),
                                  self.distortion, self.to_robot, self.min_confidence)

    def frames(self, stop: threading.Event) -> Iterator[SkeletonFrame]:
        pacer = Pacer(self.realtime and self.is_file)
        try:
            while not stop.is_set():
                ok, image = self.capture.read()
                captured = time.monotonic()
                if not ok or image is None:
                    self._counters.ended = "end of the video file" if self.is_file else "the camera stopped delivering frames"
                    (log.info if self.is_file else log.error)("%s: %s after %d frames", self.name, self._counters.ended,
                                                              self._counters.frames)
                    return
                index = self._counters.frames
                self._counters.frames += 1
                t = index / self.fps if self.is_file else captured
                if not pacer.wait(t, stop):
                    return
                try:
                    xyz, conf = self.skeleton(image)
                except Exception:
                    self._counters.failed += 1
                    if self._counters.failed <= _LOGGED_FAILURES:
                        log.exception("%s: frame %d failed (%d so far)", self.name, index, self._counters.failed)
                    continue
                yield SkeletonFrame(t=t, xyz=xyz, conf=conf, captured=captured)
        finally:
            self.capture.release()


def _open_capture(camera: CameraConfig) -> tuple[cv2.VideoCapture, bool]:
    """The opened capture and whether it is a file; :class:`SourceUnavailable` if it cannot be opened."""
    device = camera.device
    if isinstance(device, int):
        capture = cv2.VideoCapture(device)
        if not capture.isOpened():
            raise SourceUnavailable(f"cannot open camera {device} (/dev/video{device}): not connected or busy; "
                                    "set perception.camera.device to another index or a video file")
        capture.set(cv2.CAP_PROP_FRAME_WIDTH, camera.width)
        capture.set(cv2.CAP_PROP_FRAME_HEIGHT, camera.height)
        capture.set(cv2.CAP_PROP_FPS, camera.fps)
        return capture, False
    is_url = "://" in device
    path = device if is_url else str(Path(device).expanduser())
    if not is_url and not Path(path).is_file():
        raise SourceUnavailable(f"no such video file: {path} (perception.camera.device)")
    capture = cv2.VideoCapture(path)
    if not capture.isOpened():
        raise SourceUnavailable(f"OpenCV cannot open {path} as video (perception.camera.device)")
    return capture, not is_url


def open_camera(conf: PerceptionConfig) -> CameraSource:
    """The ``camera`` source of ``conf`` (models located, estimator built, capture opened).

    :class:`SourceUnavailable` with the remedy if the weights, the runtime or the device is missing.
    """
    camera = conf.camera
    try:
        estimator = BlazePose(locate_models(model_dir(camera.model_dir)), camera.detection_threshold,
                              camera.presence_threshold, camera.threads)
    except ModelError as exc:
        raise SourceUnavailable(str(exc)) from None
    capture, is_file = _open_capture(camera)
    return CameraSource(capture, estimator, conf, is_file)
