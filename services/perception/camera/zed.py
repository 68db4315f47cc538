"""The ``zed`` skeleton source: a Stereolabs ZED camera's body tracking (the paper's camera).

The ZED SDK (``pyzed``, installed with the SDK, not from PyPI) measures the person in metres by
stereo, so no monocular depth is needed. The camera is opened with
``COORDINATE_SYSTEM.RIGHT_HANDED_Z_UP_X_FWD`` (the camera body frame of
:mod:`~services.perception.camera.geometry`: x forward, y left, z up) and body tracking in
``perception.camera.zed_body_format`` (BODY_18 or BODY_34); ``perception.camera.extrinsics`` put
the skeleton in the robot frame. ``perception.camera.device``: a camera index, or an ``.svo``
recording. One person is followed: the tracked id of the previous frame while it is seen, else
the body nearest to the camera. Keypoint confidences (0–100 in the SDK) are divided by 100;
below ``perception.point_filter.min_confidence`` a point is missing.

:func:`zed_skeleton` (the mapping) needs no SDK; the source itself imports ``pyzed`` when opened.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Iterator
from typing import Any

import numpy as np

from services.perception.camera.geometry import (
    KeypointMap,
    RigidTransform,
    body_to_robot,
    map_keypoints,
    mark_missing,
    missing_skeleton,
)
from services.perception.sources import SourceUnavailable
from services.perception.base import SkeletonFrame
from shared.config import PerceptionConfig

log = logging.getLogger("safemimic.perception.zed")

#: ZED BODY_18 (COCO-18 order: 0 nose, 1 neck, 2–4 right arm, 5–7 left arm, 8–10 right leg,
#: 11–13 left leg, 14–17 eyes and ears) → canonical keypoints (pelvis: hip centre, head: ear centre).
BODY_18: KeypointMap = {
    "pelvis": (8, 11),
    "spine_chest": (1,),
    "head": (16, 17),
    "left_shoulder": (5,),
    "left_elbow": (6,),
    "left_wrist": (7,),
    "right_shoulder": (2,),
    "right_elbow": (3,),
    "right_wrist": (4,),
    "left_hip": (11,),
    "left_knee": (12,),
    "left_ankle": (13,),
    "right_hip": (8,),
    "right_knee": (9,),
    "right_ankle": (10,),
}
#: ZED BODY_34 (0 pelvis, 1 naval spine, 2 chest spine, 3 neck, 4–10 left clavicle → thumb,
#: 11–17 right, 18–21 left hip → foot, 22–25 right, 26 head, 27 nose, 28–31 eyes/ears, 32–33 heels).
BODY_34: KeypointMap = {
    "pelvis": (0,),
    "spine_chest": (3,),
    "head": (26,),
    "left_shoulder": (5,),
    "left_elbow": (6,),
    "left_wrist": (7,),
    "right_shoulder": (12,),
    "right_elbow": (13,),
    "right_wrist": (14,),
    "left_hip": (18,),
    "left_knee": (19,),
    "left_ankle": (20,),
    "right_hip": (22,),
    "right_knee": (23,),
    "right_ankle": (24,),
}
BODY_FORMATS: dict[str, tuple[int, KeypointMap]] = {"body_18": (18, BODY_18), "body_34": (34, BODY_34)}


def zed_skeleton(
    keypoints: np.ndarray, confidence: np.ndarray, body_format: str, to_robot: RigidTransform, min_confidence: float
) -> tuple[np.ndarray, np.ndarray]:
    """A ZED body (keypoints (N, 3) m in the camera body frame, confidences (N,) in 0–100, NaN if unseen)
    → canonical robot-frame keypoints (15, 3) and confidences (15,) in [0, 1]; below ``min_confidence``: NaN."""
    count, mapping = BODY_FORMATS[body_format]
    keypoints = np.asarray(keypoints, dtype=np.float64)
    if keypoints.shape != (count, 3) or np.shape(confidence) != (count,):
        raise ValueError(f"{body_format}: expected ({count}, 3) keypoints and ({count},) confidences, "
                         f"got {keypoints.shape} and {np.shape(confidence)}")
    conf = np.nan_to_num(np.asarray(confidence, dtype=np.float64) / 100.0, nan=0.0).clip(0.0, 1.0)
    xyz, conf = map_keypoints(to_robot.apply(keypoints), conf, mapping)
    return mark_missing(xyz, conf, min_confidence)


class ZedSource:
    """A :class:`~services.perception.base.SkeletonSource` over an opened ``pyzed.sl.Camera``."""

    def __init__(self, sl: Any, camera: Any, conf: PerceptionConfig, is_file: bool) -> None:
        self.sl = sl
        self.zed = camera
        self.body_format = conf.camera.zed_body_format
        self.min_confidence = conf.point_filter.min_confidence
        self.to_robot = body_to_robot(conf.camera.extrinsics)
        self.is_file = is_file
        self.fps = float(camera.get_camera_information().camera_configuration.fps) or conf.camera.fps
        self.name = f"zed {conf.camera.device}"
        self._tracked_id: int | None = None

    def _choose(self, bodies: list[Any]) -> Any | None:
        """The body tracked so far if still seen, else the nearest one (None if nobody)."""
        for body in bodies:
            if body.id == self._tracked_id:
                return body
        if not bodies:
            return None
        nearest = min(bodies, key=lambda body: float(np.linalg.norm(body.position)))
        self._tracked_id = nearest.id
        return nearest

    def frames(self, stop: threading.Event) -> Iterator[SkeletonFrame]:
        sl = self.sl
        runtime = sl.RuntimeParameters()
        runtime.measure3D_reference_frame = sl.REFERENCE_FRAME.CAMERA
        body_runtime = sl.BodyTrackingRuntimeParameters()
        bodies = sl.Bodies()
        try:
            while not stop.is_set():
                status = self.zed.grab(runtime)
                captured = time.monotonic()
                if status != sl.ERROR_CODE.SUCCESS:
                    log.log(logging.INFO if self.is_file else logging.ERROR, "%s: grab returned %s: stream ends", self.name, status)
                    return
                self.zed.retrieve_bodies(bodies, body_runtime)
                body = self._choose(list(bodies.body_list))
                if body is None:
                    xyz, conf = missing_skeleton()
                else:
                    xyz, conf = zed_skeleton(body.keypoint, body.keypoint_confidence, self.body_format,
                                             self.to_robot, self.min_confidence)
                yield SkeletonFrame(t=captured, xyz=xyz, conf=conf, captured=captured)
        finally:
            self.zed.close()


def open_zed(conf: PerceptionConfig) -> ZedSource:
    """Open the ZED camera (or ``.svo`` file) with body tracking; :class:`SourceUnavailable` if impossible."""
    try:
        import pyzed.sl as sl
    except ImportError as exc:
        raise SourceUnavailable(
            f"the zed source needs the ZED SDK's Python API (pyzed: install the ZED SDK, then its "
            f"get_python_api.py); cannot import pyzed.sl: {exc}"
        ) from None
    camera_conf = conf.camera
    init = sl.InitParameters()
    init.coordinate_units = sl.UNIT.METER
    init.coordinate_system = sl.COORDINATE_SYSTEM.RIGHT_HANDED_Z_UP_X_FWD
    init.camera_fps = int(camera_conf.fps)
    is_file = isinstance(camera_conf.device, str)
    if is_file:
        init.set_from_svo_file(str(camera_conf.device))
    else:
        init.set_from_camera_id(camera_conf.device)
    zed = sl.Camera()
    status = zed.open(init)
    if status != sl.ERROR_CODE.SUCCESS:
        raise SourceUnavailable(f"cannot open the ZED camera {camera_conf.device}: {status}")
    tracking = sl.BodyTrackingParameters()
    tracking.enable_tracking = True
    tracking.enable_body_fitting = camera_conf.zed_body_format == "body_34"  # BODY_34 is fitted by the SDK
    tracking.body_format = sl.BODY_FORMAT.BODY_34 if camera_conf.zed_body_format == "body_34" else sl.BODY_FORMAT.BODY_18
    status = zed.enable_positional_tracking(sl.PositionalTrackingParameters())  # body tracking needs it
    if status == sl.ERROR_CODE.SUCCESS:
        status = zed.enable_body_tracking(tracking)
    if status != sl.ERROR_CODE.SUCCESS:
        zed.close()
        raise SourceUnavailable(f"ZED body tracking cannot start: {status}")
    return ZedSource(sl, zed, conf, is_file)
