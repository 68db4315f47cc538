"""The torso frame F_T of a body and its arms' directions in it (paper §II-A).

One definition for the person (keypoints) and the robot (its capsules' axes), so that "the robot's
arm points where the person's does" means the same thing to the retargeting and to the evaluator.

F_T, in the frame of the input points: origin at the pelvis,

    e_z = unit(c − pelvis),                 c = shoulder centre,
    e_x = unit(l − (l·e_z) e_z),            l = right_shoulder − left_shoulder  (the body's RIGHT),
    e_y = e_z × e_x                         (the body's FORWARD; right-handed).

Arm directions are given in the *robot's* arm order :data:`ARM_SEGMENTS` (left upper arm, left
forearm, right upper arm, right forearm). Facing the person (``mirror``), the robot's left arm
imitates the person's right arm reflected across the sagittal plane: the person's right segment
with its lateral (e_x) component negated.
"""

from __future__ import annotations

import math

import numpy as np

from shared.names import CAPSULE_NAMES, KEYPOINT_INDEX

Vec = tuple[float, float, float]

#: The robot's arm segments, in the order of every (4, 3) direction array here.
ARM_SEGMENTS = ("left_upper_arm", "left_forearm", "right_upper_arm", "right_forearm")
_K = KEYPOINT_INDEX
_C = {name: i for i, name in enumerate(CAPSULE_NAMES)}
#: (start, end) keypoints of each segment of the person, in :data:`ARM_SEGMENTS` order.
_PERSON_SEGMENTS = np.array([
    (_K[f"{side}_{a}"], _K[f"{side}_{b}"])
    for side in ("left", "right") for a, b in (("shoulder", "elbow"), ("elbow", "wrist"))
])
#: The same with the person's sides swapped (mirror).
_PERSON_SEGMENTS_MIRRORED = np.concatenate([_PERSON_SEGMENTS[2:], _PERSON_SEGMENTS[:2]])
#: The robot's capsule index of each of :data:`ARM_SEGMENTS`.
ARM_CAPSULES = np.array([_C[name] for name in ARM_SEGMENTS])
#: The robot's capsules whose first endpoints are its pelvis, left and right shoulder in F_T.
FRAME_CAPSULES = np.array([_C[name] for name in ("torso", "left_upper_arm", "right_upper_arm")])
_MIRROR_LATERAL = np.array([-1.0, 1.0, 1.0])


def sub(a: Vec, b: Vec) -> Vec:
    return (a[0] - b[0], a[1] - b[1], a[2] - b[2])


def dot(a: Vec, b: Vec) -> float:
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def norm(a: Vec) -> float:
    return math.sqrt(a[0] * a[0] + a[1] * a[1] + a[2] * a[2])


def torso_axes(pelvis: Vec, left_shoulder: Vec, right_shoulder: Vec, min_segment: float) -> tuple[Vec, Vec, Vec] | None:
    """Unit e_x (right), e_y (forward), e_z (up) of F_T in the input frame; None if degenerate.

    Degenerate: torso (pelvis → shoulder centre) or orthogonalised shoulder line shorter than
    ``min_segment`` (m), or non-finite input. Plain float tuples: this runs every frame.
    """
    up = (0.5 * (left_shoulder[0] + right_shoulder[0]) - pelvis[0],
          0.5 * (left_shoulder[1] + right_shoulder[1]) - pelvis[1],
          0.5 * (left_shoulder[2] + right_shoulder[2]) - pelvis[2])
    length = norm(up)
    if not length >= min_segment:  # also catches NaN
        return None
    e_z = (up[0] / length, up[1] / length, up[2] / length)
    line = sub(right_shoulder, left_shoulder)
    along = dot(line, e_z)
    line = (line[0] - along * e_z[0], line[1] - along * e_z[1], line[2] - along * e_z[2])
    width = norm(line)
    if not width >= min_segment:
        return None
    e_x = (line[0] / width, line[1] / width, line[2] / width)
    e_y = (e_z[1] * e_x[2] - e_z[2] * e_x[1], e_z[2] * e_x[0] - e_z[0] * e_x[2], e_z[0] * e_x[1] - e_z[1] * e_x[0])
    return e_x, e_y, e_z


def torso_rotation(pelvis: np.ndarray, left_shoulder: np.ndarray, right_shoulder: np.ndarray,
                   min_segment: float) -> np.ndarray | None:
    """R (3, 3) with rows e_x, e_y, e_z (:func:`torso_axes`): ``R @ v`` is v in F_T; None if degenerate."""
    axes = torso_axes(tuple(pelvis.tolist()), tuple(left_shoulder.tolist()), tuple(right_shoulder.tolist()), min_segment)
    return None if axes is None else np.array(axes)


def _units(vectors: np.ndarray, min_segment: float) -> np.ndarray:
    """Rows of ``vectors`` (…, 3) made unit; NaN where shorter than ``min_segment`` or not finite."""
    n = np.linalg.norm(vectors, axis=-1, keepdims=True)
    return np.where(n >= min_segment, vectors / np.where(n > 0, n, 1.0), np.nan)


def person_arm_directions(points: np.ndarray, valid: np.ndarray, mirror: bool, min_segment: float) -> np.ndarray:
    """(4, 3) unit directions of the person's arm segments in the person's F_T, arranged for the
    robot's arms (:data:`ARM_SEGMENTS`; ``mirror``: sides swapped, lateral component negated); a row
    is NaN where its keypoints or the torso are invalid or degenerate. ``points`` (15, 3) in
    KEYPOINT_NAMES order, ``valid`` (15,) bool."""
    out = np.full((4, 3), np.nan)
    pelvis, left, right = _K["pelvis"], _K["left_shoulder"], _K["right_shoulder"]
    if not (valid[pelvis] and valid[left] and valid[right]):
        return out
    rotation = torso_rotation(points[pelvis], points[left], points[right], min_segment)
    if rotation is None:
        return out
    segments = _PERSON_SEGMENTS_MIRRORED if mirror else _PERSON_SEGMENTS
    usable = valid[segments].all(axis=1)
    vectors = (points[segments[:, 1]] - points[segments[:, 0]]) @ rotation.T
    if mirror:
        vectors = vectors * _MIRROR_LATERAL
    out[usable] = _units(vectors[usable], min_segment)
    return out


def robot_arm_rotation(capsules: np.ndarray, min_segment: float) -> np.ndarray | None:
    """The robot's F_T (:func:`torso_rotation`) from its capsules (7, 2, 3): the torso capsule's base
    as pelvis, the upper-arm capsules' bases as shoulders."""
    pelvis, left, right = capsules[FRAME_CAPSULES, 0]
    return torso_rotation(pelvis, left, right, min_segment)


def robot_arm_directions(capsules: np.ndarray, min_segment: float) -> np.ndarray:
    """(4, 3) unit directions of the robot's arm capsules' axes (a → b) in the robot's F_T
    (:func:`robot_arm_rotation`), :data:`ARM_SEGMENTS` order; NaN rows if degenerate."""
    rotation = robot_arm_rotation(capsules, min_segment)
    if rotation is None:
        return np.full((4, 3), np.nan)
    ends = capsules[ARM_CAPSULES]
    return _units((ends[:, 1] - ends[:, 0]) @ rotation.T, min_segment)
