"""A parametrised synthetic person whose pose angles are known exactly (tests, scenarios).

:func:`skeleton` builds the 15 canonical keypoints from θ (:data:`shared.names.POSE_ANGLE_NAMES`
order, radians) so that the estimators of :mod:`services.perception.angles` read θ back:

* torso: the global up in torso coordinates is k_T = unit(tan roll, −tan pitch, 1) (the paper's
  torso formulas inverted); the torso is the minimal rotation taking k_T to the vertical, so the
  person keeps its heading. |torso roll|, |torso pitch| < π/2.
* arms: :func:`arm_direction` inverts the continuous estimator (and, in its zone, the paper's):
  at or above the shoulder the robot-order chain (o, f, d) = (sin r, cos r sin p, cos r cos p);
  below it the blended chart, solved for its blend weight by bisection. The forearm is the upper
  arm bent by the elbow angle towards the chain's forward axis (0, cos p, −sin p).
* legs hang straight below the hips; the pelvis stays level (a torso lean is a waist bend).

The person stands at the origin of its own frame (x forward, y left, z up, floor z = 0), pelvis
above x = y = 0, facing +x; :class:`shared.body.Body` sets the proportions.
"""

from __future__ import annotations

import math

import numpy as np

from services.perception.angles import smoothstep
from shared.body import Body
from shared.config import PoseAnglesConfig
from shared.names import KEYPOINT_INDEX, KEYPOINT_NAMES

#: Columns e_x (right), e_y (forward), e_z (up) of an upright torso in the person's frame.
_UPRIGHT = np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
_BISECTION_STEPS = 60
#: The estimator's default paper zone (config ``perception.angles.paper_zone``).
DEFAULT_PAPER_ZONE = PoseAnglesConfig().paper_zone


def _rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The minimal rotation taking unit vector ``a`` to unit vector ``b`` (a ≠ −b), Rodrigues."""
    v = np.cross(a, b)
    c = float(a @ b)
    vx = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    return np.eye(3) + vx + vx @ vx / (1.0 + c)


def torso_rotation(roll: float, pitch: float) -> np.ndarray:
    """(3, 3) columns e_x, e_y, e_z of a torso leaning by (roll, pitch), in the person's frame."""
    if not (abs(roll) < math.pi / 2 and abs(pitch) < math.pi / 2):
        raise ValueError("synthetic torso roll and pitch must lie in (−π/2, π/2)")
    up_in_torso = np.array([math.tan(roll), -math.tan(pitch), 1.0])
    up_in_torso /= np.linalg.norm(up_in_torso)
    return _UPRIGHT @ _rotation_between(up_in_torso, np.array([0.0, 0.0, 1.0]))


def arm_direction(pitch: float, roll: float, paper_zone: float) -> np.ndarray:
    """Unit upper arm (outward, forward, down) that the continuous estimator reads as (pitch, roll).

    On the branch reached by moving continuously from the arm hanging down; ``paper_zone`` must
    match the estimator's (config ``perception.angles.paper_zone``).
    """
    chain = np.array([math.sin(roll), math.cos(roll) * math.sin(pitch), math.cos(roll) * math.cos(pitch)])
    if chain[2] <= 0.0:  # at or above the shoulder: the estimator inverts the chain exactly
        return chain
    if math.cos(roll) < 0.0:  # a below-shoulder direction written on the other branch
        pitch -= math.copysign(math.pi, pitch)
        roll = math.copysign(math.pi, roll) - roll
    tan_roll = math.tan(roll)

    def direction(blend: float) -> np.ndarray:
        t = tan_roll * math.cos((1.0 - blend) * pitch)
        s = 1.0 / math.sqrt(1.0 + t * t)
        return np.array([t * s, s * math.sin(pitch), s * math.cos(pitch)])

    low, high = 0.0, 1.0  # blend = smoothstep((zone − d(blend))/zone): g(0) ≤ 0 ≤ g(1)
    for _ in range(_BISECTION_STEPS):
        mid = 0.5 * (low + high)
        if mid - smoothstep((paper_zone - direction(mid)[2]) / paper_zone) < 0.0:
            low = mid
        else:
            high = mid
    return direction(0.5 * (low + high))


def forearm_direction(upper: np.ndarray, pitch: float, elbow: float) -> np.ndarray:
    """Unit forearm (outward, forward, down) at angle ``elbow`` from ``upper``, bent forward-ish."""
    bend = np.array([0.0, math.cos(pitch), -math.sin(pitch)])
    bend -= float(bend @ upper) * upper
    if np.linalg.norm(bend) < 1e-9:
        bend = np.array([1.0, 0.0, 0.0]) - upper[0] * upper
    bend /= np.linalg.norm(bend)
    return math.cos(elbow) * upper + math.sin(elbow) * bend


def skeleton(theta: np.ndarray, body: Body = Body(), paper_zone: float = DEFAULT_PAPER_ZONE) -> np.ndarray:
    """(15, 3) canonical keypoints of ``body`` in pose θ, in the person's own frame (metres)."""
    theta = np.asarray(theta, dtype=np.float64)
    points = np.empty((len(KEYPOINT_NAMES), 3))
    index = KEYPOINT_INDEX
    torso = torso_rotation(theta[0], theta[1])
    e_x, e_z = torso[:, 0], torso[:, 2]
    pelvis = np.array([0.0, 0.0, body.pelvis_height])
    centre = pelvis + body.torso_length * e_z
    points[index["pelvis"]] = pelvis
    points[index["spine_chest"]] = centre + body.neck * e_z
    points[index["head"]] = centre + (body.neck + body.head) * e_z
    for side, sign, first in (("left", -1.0, 2), ("right", 1.0, 5)):
        pitch, roll, elbow = theta[first], theta[first + 1], theta[first + 2]
        upper = arm_direction(pitch, roll, paper_zone)
        fore = forearm_direction(upper, pitch, elbow)
        to_torso = np.diag([sign, 1.0, -1.0])  # (outward, forward, down) → torso (x right, y fwd, z up)
        shoulder = centre + sign * 0.5 * body.shoulder_width * e_x
        elbow_point = shoulder + body.upper_arm * (torso @ (to_torso @ upper))
        points[index[f"{side}_shoulder"]] = shoulder
        points[index[f"{side}_elbow"]] = elbow_point
        points[index[f"{side}_wrist"]] = elbow_point + body.forearm * (torso @ (to_torso @ fore))
        hip = pelvis + np.array([0.0, -sign * 0.5 * body.hip_width, -body.hip_drop])
        points[index[f"{side}_hip"]] = hip
        points[index[f"{side}_knee"]] = hip - np.array([0.0, 0.0, body.thigh])
        points[index[f"{side}_ankle"]] = hip - np.array([0.0, 0.0, body.thigh + body.shank])
    return points
