"""The seven human capsules (paper §III-A) from the filtered skeleton, with endpoint velocities.

Capsule i is the segment [a_i, b_i] (metres, the frame of the points: the robot frame in the
service) with radius r_i from :class:`shared.config.HumanConfig`, in
:data:`shared.names.CAPSULE_NAMES` order:

    torso       pelvis → spine_chest (base of the neck); the shoulder centre if spine_chest is missing
    upper arm   shoulder → elbow
    forearm     elbow → wrist + ``hand_extension`` · unit(wrist − elbow)   (covers the hand)
    thigh       hip → knee

A capsule is valid when the keypoints defining it are valid. Endpoint velocities (m/s) are
backward finite differences of the endpoints between consecutive frames, (e_t − e_{t−1})/Δt;
they are zero for a capsule that was not valid in both frames, whose keypoints were
(re)initialised this frame, or whose torso top switched between spine_chest and shoulder centre.
Endpoints of an invalid capsule are its last ones (zeros before the first): always finite.
"""

from __future__ import annotations

import math

import numpy as np

from services.perception.point_filter import FilteredSkeleton, Vec, points_array
from shared.body import capsule_radii
from shared.config import HumanConfig
from shared.names import CAPSULE_NAMES, KEYPOINT_INDEX

_K = KEYPOINT_INDEX
#: Capsule → (start keypoint, end keypoint) in CAPSULE_NAMES order (the torso's end may fall back).
_SEGMENTS = {
    "torso": (_K["pelvis"], _K["spine_chest"]),
    "left_upper_arm": (_K["left_shoulder"], _K["left_elbow"]),
    "left_forearm": (_K["left_elbow"], _K["left_wrist"]),
    "right_upper_arm": (_K["right_shoulder"], _K["right_elbow"]),
    "right_forearm": (_K["right_elbow"], _K["right_wrist"]),
    "left_thigh": (_K["left_hip"], _K["left_knee"]),
    "right_thigh": (_K["right_hip"], _K["right_knee"]),
}
_PAIRS = [_SEGMENTS[name] for name in CAPSULE_NAMES]
#: The keypoint of every capsule endpoint, flat: capsule i is [ends[2i], ends[2i + 1]].
_ENDPOINT_KEYPOINTS = [k for pair in _PAIRS for k in pair]
_FOREARMS = (CAPSULE_NAMES.index("left_forearm"), CAPSULE_NAMES.index("right_forearm"))
_TORSO = CAPSULE_NAMES.index("torso")
_PELVIS = _K["pelvis"]
_SHOULDERS = [_K["left_shoulder"], _K["right_shoulder"]]
N_CAPSULES = len(CAPSULE_NAMES)


class HumanCapsules:
    """Builds (endpoints (7, 2, 3), valid (7,), velocities (7, 2, 3)) from filtered skeletons."""

    def __init__(self, human: HumanConfig) -> None:
        self.configure(human)
        self._ends: list[Vec] = [(0.0, 0.0, 0.0)] * (2 * N_CAPSULES)  # the endpoints of the last frame, flat
        self._endpoints = np.zeros((N_CAPSULES, 2, 3))  # the same as an array
        self._valid = [False] * N_CAPSULES
        self._t: float | None = None
        self._torso_from_shoulders = False

    def configure(self, human: HumanConfig) -> None:
        """Radii and hand extension for the following frames."""
        self.radii = capsule_radii(human)
        self.hand_extension = human.hand_extension

    def reset(self) -> None:
        """Forget the previous frame (no velocities until the next two valid frames)."""
        self._t = None
        self._valid = [False] * N_CAPSULES

    def __call__(self, skeleton: FilteredSkeleton) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(endpoints (7, 2, 3), valid (7,), velocities (7, 2, 3)) of ``skeleton`` (module docstring)."""
        endpoints, valid, velocities = self.build(
            skeleton.t, skeleton.points.tolist(), skeleton.valid.tolist(), skeleton.fresh.tolist())
        return endpoints, np.array(valid, bool), velocities

    def build(
        self, t: float, points: list[Vec], point_valid: list[bool], point_fresh: list[bool],
    ) -> tuple[np.ndarray, list[bool], np.ndarray]:
        """:meth:`__call__` on the filter's output as Python lists (15 points (x, y, z), valid, fresh);
        ``valid`` is returned as a list. Built in Python floats, made arrays once: for 7 capsules
        numpy's cost per call was most of the work."""
        ends = [points[k] for k in _ENDPOINT_KEYPOINTS]
        valid = [point_valid[a] and point_valid[b] for a, b in _PAIRS]
        fresh = [point_fresh[a] or point_fresh[b] for a, b in _PAIRS]

        left, right = _SHOULDERS
        from_shoulders = not valid[_TORSO] and point_valid[_PELVIS] and point_valid[left] and point_valid[right]
        if from_shoulders:
            (x0, y0, z0), (x1, y1, z1) = points[left], points[right]
            ends[2 * _TORSO + 1] = (0.5 * (x0 + x1), 0.5 * (y0 + y1), 0.5 * (z0 + z1))
            valid[_TORSO] = True
            fresh[_TORSO] = point_fresh[_PELVIS] or point_fresh[left] or point_fresh[right]
        if from_shoulders != self._torso_from_shoulders:
            fresh[_TORSO] = True
            self._torso_from_shoulders = from_shoulders

        for i in _FOREARMS:  # extend past the wrist along the forearm
            (x0, y0, z0), (x1, y1, z1) = ends[2 * i], ends[2 * i + 1]
            fore = (x1 - x0, y1 - y0, z1 - z0)
            length = math.sqrt(fore[0] * fore[0] + fore[1] * fore[1] + fore[2] * fore[2])
            if length > 1e-9:
                scale = self.hand_extension / length
                ends[2 * i + 1] = (x1 + scale * fore[0], y1 + scale * fore[1], z1 + scale * fore[2])

        if not all(valid):  # an invalid capsule keeps its last endpoints
            for i, ok in enumerate(valid):
                if not ok:
                    ends[2 * i:2 * i + 2] = self._ends[2 * i:2 * i + 2]
        endpoints = points_array(ends).reshape(N_CAPSULES, 2, 3)
        if self._t is not None and t > self._t:
            moving = [now and before and not new for now, before, new in zip(valid, self._valid, fresh)]
            velocities = (endpoints - self._endpoints) * (1.0 / (t - self._t))
            if not all(moving):
                velocities[np.logical_not(moving)] = 0.0
        else:
            velocities = np.zeros((N_CAPSULES, 2, 3))
        self._ends, self._endpoints = ends, endpoints
        self._valid = valid
        self._t = t
        return endpoints.copy(), valid, velocities
