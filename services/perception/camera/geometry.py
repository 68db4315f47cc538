"""From landmarks to the 15 canonical keypoints in the robot frame.

Frames: the OpenCV optical frame of the camera (x right, y down, z forward along the optical axis,
metres); the camera body frame (x forward along the optical axis, y left, z up: ROS
``camera_link``, the ZED SDK's ``RIGHT_HANDED_Z_UP_X_FWD``); the robot frame (x forward, y left,
z up, floor z = 0). The camera's mounting (:class:`shared.config.CameraExtrinsics`) is the body
frame's pose in the robot frame: p_robot = position + R_z(yaw) R_y(pitch) R_x(roll) p_body, and
p_body = :data:`OPTICAL_TO_BODY` p_optical.

Monocular depth: the landmark model gives metric, hip-centred world landmarks W_i but not where
the person is. :func:`solve_camera_points` finds the rigid motion (R, t) that projects W_i onto
the image landmarks u_i through the intrinsics K (``cv2.solvePnP``, Levenberg–Marquardt started
from R = I and the least-squares translation): the person's camera-frame points are R W_i + t.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from shared.config import CameraExtrinsics, CameraIntrinsics
from shared.names import KEYPOINT_NAMES

#: p_body = OPTICAL_TO_BODY @ p_optical (z forward → x forward, x right → −y, y down → −z).
OPTICAL_TO_BODY = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
#: Fewer confident landmarks than this: no 3D pose in that frame.
MIN_PNP_POINTS = 6

#: A keypoint mapping: canonical name → the source indices whose mean it is.
KeypointMap = dict[str, tuple[int, ...]]

#: BlazePose's 33 body landmarks → canonical keypoints (spine_chest: shoulder centre, head: ear centre).
BLAZEPOSE_KEYPOINTS: KeypointMap = {
    "pelvis": (23, 24),
    "spine_chest": (11, 12),
    "head": (7, 8),
    "left_shoulder": (11,),
    "left_elbow": (13,),
    "left_wrist": (15,),
    "right_shoulder": (12,),
    "right_elbow": (14,),
    "right_wrist": (16,),
    "left_hip": (23,),
    "left_knee": (25,),
    "left_ankle": (27,),
    "right_hip": (24,),
    "right_knee": (26,),
    "right_ankle": (28,),
}


@dataclass(frozen=True)
class RigidTransform:
    """p ↦ rotation @ p + translation (rotation (3, 3) orthonormal, translation (3,) metres)."""

    rotation: np.ndarray
    translation: np.ndarray

    def apply(self, points: np.ndarray) -> np.ndarray:
        """Points (..., 3) → (..., 3); NaN stays NaN."""
        return points @ self.rotation.T + self.translation


def rpy_matrix(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """R_z(yaw) R_y(pitch) R_x(roll) (radians)."""
    cr, sr, cp, sp, cy, sy = (math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch),
                              math.cos(yaw), math.sin(yaw))
    rz = np.array([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]])
    ry = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
    rx = np.array([[1.0, 0.0, 0.0], [0.0, cr, -sr], [0.0, sr, cr]])
    return rz @ ry @ rx


def body_to_robot(extrinsics: CameraExtrinsics) -> RigidTransform:
    """Camera body frame (x forward, y left, z up) → robot frame."""
    return RigidTransform(rpy_matrix(*extrinsics.rpy), np.asarray(extrinsics.position, dtype=np.float64))


def optical_to_robot(extrinsics: CameraExtrinsics) -> RigidTransform:
    """OpenCV optical frame (x right, y down, z forward) → robot frame."""
    body = body_to_robot(extrinsics)
    return RigidTransform(body.rotation @ OPTICAL_TO_BODY, body.translation)


def camera_matrix(intrinsics: CameraIntrinsics, width: int, height: int) -> np.ndarray:
    """K (3, 3) for a ``width`` × ``height`` image; null entries from ``hfov_deg`` and the image centre."""
    focal = (width / 2) / math.tan(math.radians(intrinsics.hfov_deg) / 2)
    fx = intrinsics.fx if intrinsics.fx is not None else focal
    fy = intrinsics.fy if intrinsics.fy is not None else fx if intrinsics.fx is not None else focal
    cx = intrinsics.cx if intrinsics.cx is not None else width / 2
    cy = intrinsics.cy if intrinsics.cy is not None else height / 2
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def solve_camera_points(
    image: np.ndarray, world: np.ndarray, usable: np.ndarray, k: np.ndarray, distortion: np.ndarray
) -> np.ndarray | None:
    """Camera-frame points R W + t (N, 3) of world landmarks ``world`` (N, 3) seen at ``image`` (N, 2) px.

    Only the ``usable`` (N,) points constrain (R, t); every point is transformed. None if fewer
    than :data:`MIN_PNP_POINTS` are usable or the solution puts the person behind the camera.
    The start: R = I (the world landmarks' axes are the camera's) and t from the linear
    least-squares of x_n (Z + t_z) = X + t_x, y_n (Z + t_z) = Y + t_y over the undistorted
    normalised image points (x_n, y_n).
    """
    if np.count_nonzero(usable) < MIN_PNP_POINTS:
        return None
    object_points = world[usable].astype(np.float64)
    image_points = image[usable].astype(np.float64).reshape(-1, 1, 2)
    normalised = cv2.undistortPoints(image_points, k, distortion).reshape(-1, 2)
    n = len(object_points)
    a = np.zeros((2 * n, 3))
    a[:n, 0] = a[n:, 1] = 1.0
    a[:n, 2], a[n:, 2] = -normalised[:, 0], -normalised[:, 1]
    b = np.concatenate([normalised[:, 0] * object_points[:, 2] - object_points[:, 0],
                        normalised[:, 1] * object_points[:, 2] - object_points[:, 1]])
    t0 = np.linalg.lstsq(a, b, rcond=None)[0]
    if not t0[2] > 0:
        return None
    ok, rvec, tvec = cv2.solvePnP(object_points, image_points, k, distortion, rvec=np.zeros((3, 1)),
                                  tvec=t0.reshape(3, 1).copy(), useExtrinsicGuess=True, flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok or not tvec[2, 0] > 0:
        return None
    rotation, _ = cv2.Rodrigues(rvec)
    return world @ rotation.T + tvec.reshape(3)


def map_keypoints(points: np.ndarray, confidence: np.ndarray, mapping: KeypointMap) -> tuple[np.ndarray, np.ndarray]:
    """Source points (N, 3) + confidences (N,) → canonical (15, 3), (15,) in KEYPOINT_NAMES order.

    A canonical point is the mean of its source points, its confidence their minimum (a point
    made of a missing one is missing). Names absent from ``mapping`` are NaN with confidence 0.
    """
    xyz = np.full((len(KEYPOINT_NAMES), 3), np.nan)
    conf = np.zeros(len(KEYPOINT_NAMES))
    for i, name in enumerate(KEYPOINT_NAMES):
        sources = mapping.get(name)
        if sources:
            xyz[i] = points[list(sources)].mean(axis=0)
            conf[i] = confidence[list(sources)].min()
    return xyz, conf


def missing_skeleton() -> tuple[np.ndarray, np.ndarray]:
    """Every canonical point missing: (15, 3) NaN and (15,) zero confidences."""
    return np.full((len(KEYPOINT_NAMES), 3), np.nan), np.zeros(len(KEYPOINT_NAMES))


def mark_missing(xyz: np.ndarray, conf: np.ndarray, min_confidence: float) -> tuple[np.ndarray, np.ndarray]:
    """Points with confidence < ``min_confidence`` or not finite become NaN with confidence 0."""
    missing = (conf < min_confidence) | ~np.isfinite(xyz).all(axis=-1) | ~np.isfinite(conf)
    return np.where(missing[:, None], np.nan, xyz), np.where(missing, 0.0, conf)


def blazepose_skeleton(
    image: np.ndarray, world: np.ndarray, confidence: np.ndarray, k: np.ndarray, distortion: np.ndarray,
    to_robot: RigidTransform, min_confidence: float,
) -> tuple[np.ndarray, np.ndarray]:
    """BlazePose landmarks (33 image px, 33 world m, 33 confidences) → canonical robot-frame (15, 3), (15,).

    Landmarks at or above ``min_confidence`` fix the person's place (:func:`solve_camera_points`);
    canonical points below it are NaN (missing), never guessed. No solution: every point missing.
    """
    camera = solve_camera_points(image, world, confidence >= min_confidence, k, distortion)
    if camera is None:
        return missing_skeleton()
    xyz, conf = map_keypoints(to_robot.apply(camera), confidence, BLAZEPOSE_KEYPOINTS)
    return mark_missing(xyz, conf, min_confidence)
