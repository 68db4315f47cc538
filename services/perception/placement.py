"""Where a recorded or scripted person stands relative to the robot (a rigid yaw + translation).

Robot frame: x forward, y left, z up, floor z = 0, the robot's pelvis above x = y = 0 (at the
robot description's ``base_height``). A placement maps a person standing at the origin of its own
frame and facing +x (left +y, floor z = 0 — the mocap clips' and the scenarios' frame) into the
robot frame: p_robot = R_z(yaw) p + (x, y, 0).

Named placements (distances from :class:`shared.config.PerceptionConfig`):

* ``side-by-side``: beside the robot, same heading, at y = ``side_by_side_y`` (0.70 m: the person's
  near arm reaches the robot's arm workspace — shoulders at y = ±0.10 m, arms 0.55 m — and the
  robot's arm on that side, imitating the person's far arm, can reach the person, while the
  torsos, radii 0.15 m and 0.114 m, stay about 0.44 m apart);
* ``facing``: ``facing_distance`` (0.95 m) in front of the robot, turned 180° to face it (arms
  reaching forward meet the robot's reaching arms; the torsos of a person standing in place stay
  about 0.69 m apart — a recording that walks forward walks into the robot);
* ``recorded``: the identity, no normalisation (a recording already in the robot frame);
* ``x,y,yaw``: explicit (m, m, rad).

A recording is normalised before it is placed (except ``recorded``): its first frames are moved
so the pelvis is at x = y = 0 and the person faces +x, the heading taken from the hip and
shoulder lines over the first 0.5 s.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from shared.config import PerceptionConfig
from shared.names import KEYPOINT_INDEX
from shared.skeleton import Recording

_K = KEYPOINT_INDEX
#: Frames used to find the person's initial heading and position (s).
HEADING_WINDOW_S = 0.5
NAMED = ("side-by-side", "facing", "recorded")


@dataclass(frozen=True)
class Placement:
    """p_robot = R_z(yaw) p + (x, y, 0); ``normalize``: first bring the person to the origin, facing +x."""

    x: float = 0.0
    y: float = 0.0
    yaw: float = 0.0
    normalize: bool = True

    def apply(self, xyz: np.ndarray) -> np.ndarray:
        """Points (..., 3) in the person's frame → robot frame (NaN stays NaN)."""
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        rotation = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        return xyz @ rotation.T + np.array([self.x, self.y, 0.0])

    @property
    def near_arm(self) -> str:
        """The person's arm on the robot's side: "right" if the robot is to the person's right.

        The robot's origin in the person's frame is −R_zᵀ(yaw) (x, y); its lateral (left)
        coordinate is x sin(yaw) − y cos(yaw). Straight ahead or behind counts as "right".
        """
        robot_left = self.x * math.sin(self.yaw) - self.y * math.cos(self.yaw)
        return "right" if robot_left <= 1e-9 else "left"


def parse_placement(text: str, conf: PerceptionConfig, auto: str = "side-by-side") -> Placement:
    """A placement from its config/CLI text (``auto`` means ``auto``, e.g. a scenario's own)."""
    name = auto if text == "auto" else text
    if name == "side-by-side":
        return Placement(y=conf.side_by_side_y)
    if name == "facing":
        return Placement(x=conf.facing_distance, yaw=math.pi)
    if name == "recorded":
        return Placement(normalize=False)
    try:
        x, y, yaw = (float(part) for part in name.split(","))
    except ValueError:
        raise ValueError(f"placement {text!r}: expected auto, {', '.join(NAMED)} or x,y,yaw (m, m, rad)") from None
    if not all(math.isfinite(v) for v in (x, y, yaw)):
        raise ValueError(f"placement {text!r} is not finite")
    return Placement(x=x, y=y, yaw=yaw)


def check_placement(text: str, argument: str) -> None:
    """Raise ValueError, naming the command-line ``argument``, unless ``text`` is one of
    :func:`parse_placement`'s forms; no configuration needed (a command checks it before any work)."""
    try:
        parse_placement(text, PerceptionConfig())
    except ValueError as exc:
        raise ValueError(f"{argument}: {exc}") from None


def initial_pose(recording: Recording) -> tuple[float, float, float]:
    """(x, y, heading) of the person at the start: pelvis position and facing direction (rad).

    The facing direction is the left axis (hips and shoulders, left − right) turned by −90°,
    averaged over the first :data:`HEADING_WINDOW_S`; 0 if no such line is visible.
    """
    valid = recording.valid
    window = recording.t <= recording.t[0] + HEADING_WINDOW_S
    left = np.zeros(2)
    for a, b in (("left_hip", "right_hip"), ("left_shoulder", "right_shoulder")):
        seen = window & valid[:, _K[a]] & valid[:, _K[b]]
        lines = recording.xyz[seen, _K[a], :2] - recording.xyz[seen, _K[b], :2]
        lengths = np.linalg.norm(lines, axis=1, keepdims=True)
        lines = lines[lengths[:, 0] > 1e-6] / lengths[lengths[:, 0] > 1e-6]
        left += lines.sum(axis=0)
    heading = math.atan2(-left[0], left[1]) if np.linalg.norm(left) > 1e-9 else 0.0
    pelvis_seen = np.flatnonzero(valid[:, _K["pelvis"]])
    x, y = recording.xyz[pelvis_seen[0], _K["pelvis"], :2] if len(pelvis_seen) else (0.0, 0.0)
    return float(x), float(y), heading


def place_recording(recording: Recording, placement: Placement) -> Recording:
    """The recording moved into the robot frame by ``placement`` (normalised first if asked)."""
    xyz = recording.xyz
    if placement.normalize:
        x0, y0, heading = initial_pose(recording)
        xyz = Placement(yaw=-heading).apply(xyz - np.array([x0, y0, 0.0]))
    return replace(recording, xyz=placement.apply(xyz))
