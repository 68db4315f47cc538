"""Joint-space retargeting θ → q_nom (paper eq. 2).

q_nom = Π_[q_min, q_max]( q_home + S ⊙ (θ' − θ_home) + b ), with θ' = θ, or in mirror mode
(robot facing the person) θ' = mirror(θ): left and right arms swapped and torso roll negated.
Our θ convention (paper §II-A) already makes shoulder roll positive *outward* on both sides, so
the arm roll angles keep their sign when swapped; only the torso roll, defined about a global
lateral axis, flips. ``q_home`` is the robot's home pose (arms hanging a little away from the
body, clear of every self pair); a person standing neutral (θ = θ_home) maps onto it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from services.safety.errors import SafetyConfigError
from shared.names import POSE_ANGLE_NAMES

#: θ' = θ[_MIRROR_PERMUTATION] * _MIRROR_SIGN swaps arms and flips the torso roll.
_MIRROR_PERMUTATION = np.array([0, 1, 5, 6, 7, 2, 3, 4])
_MIRROR_SIGN = np.array([-1.0, 1, 1, 1, 1, 1, 1, 1])


def mirror_pose(theta: np.ndarray) -> np.ndarray:
    """The pose a mirror image of the person would have (8,): arms swapped, torso roll negated."""
    return theta[..., _MIRROR_PERMUTATION] * _MIRROR_SIGN


class PoseLike(Protocol):
    """What a retargeter reads from one human state (``HumanState`` is one): θ, θ_valid, θ̇ (8,)
    in POSE_ANGLE_NAMES order, the skeleton ``keypoints`` (15, 3) m in the robot frame with
    ``keypoint_valid`` (15,), and ``stamp`` (s)."""

    @property
    def theta(self) -> np.ndarray: ...
    @property
    def theta_valid(self) -> np.ndarray: ...
    @property
    def theta_rate(self) -> np.ndarray: ...
    @property
    def keypoints(self) -> np.ndarray: ...
    @property
    def keypoint_valid(self) -> np.ndarray: ...
    @property
    def stamp(self) -> float: ...


@dataclass(frozen=True)
class Pose:
    """A :class:`PoseLike` built from parts (the evaluator's true person)."""

    theta: np.ndarray
    theta_valid: np.ndarray
    theta_rate: np.ndarray
    keypoints: np.ndarray
    keypoint_valid: np.ndarray
    stamp: float


@dataclass
class Retargeter:
    """Affine map with joint-limit projection; invalid angles keep their last nominal joint value.

    All vectors are (8,) in IMITATION_JOINT_NAMES / POSE_ANGLE_NAMES order; radians.
    """

    q_home: np.ndarray
    q_min: np.ndarray
    q_max: np.ndarray
    scale: np.ndarray
    offset: np.ndarray
    theta_home: np.ndarray
    mirror: bool = False
    _last: np.ndarray = field(init=False, repr=False)
    _moving: np.ndarray = field(init=False, repr=False)  # joints the last call tracked inside the limits

    def __post_init__(self) -> None:
        for name in ("q_home", "q_min", "q_max", "scale", "offset", "theta_home"):
            value = np.asarray(getattr(self, name), dtype=np.float64)
            if value.shape != (len(POSE_ANGLE_NAMES),) or not np.isfinite(value).all():
                raise SafetyConfigError(f"retargeting {name} must be 8 finite numbers, got {value}")
            setattr(self, name, value)
        if (self.q_min > self.q_max).any():
            raise SafetyConfigError("retargeting joint limits have q_min > q_max")
        self._last = np.clip(self.q_home + self.offset, self.q_min, self.q_max)
        self._moving = np.zeros(len(POSE_ANGLE_NAMES), bool)

    def __call__(self, theta: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
        """q_nom (8,) from θ (8,); where ``valid`` is False the previous q_nom entry is kept."""
        theta = np.asarray(theta, dtype=np.float64)
        source_valid = np.ones(theta.shape, bool) if valid is None else np.asarray(valid, bool)
        if self.mirror:
            theta, source_valid = mirror_pose(theta), source_valid[_MIRROR_PERMUTATION]
        raw = self.q_home + self.scale * (theta - self.theta_home) + self.offset
        q = np.clip(raw, self.q_min, self.q_max)
        usable = source_valid & np.isfinite(q)
        self._moving = usable & (raw == q)
        self._last = np.where(usable, q, self._last)
        return self._last.copy()

    def track(self, pose: PoseLike) -> tuple[np.ndarray, np.ndarray]:
        """(q_nom, q̇_nom) for ``pose``: :meth:`__call__` and :meth:`rate` of its angles."""
        return self(pose.theta, pose.theta_valid), self.rate(pose.theta_rate)

    def warm_up(self) -> None:
        """Nothing to prepare (the interface of the retargeters)."""

    def hold_value(self) -> np.ndarray:
        """The q_nom (8,) this retargeter holds where it has no valid angle (a copy)."""
        return self._last.copy()

    def hold(self, q_nom: np.ndarray) -> None:
        """Continue from ``q_nom`` (8,) (clipped to the limits): joints whose angles this retargeter
        has not seen valid yet keep it instead of home (a replacement retargeter takes over the
        current target without a jump)."""
        self._last = np.clip(np.asarray(q_nom, dtype=np.float64), self.q_min, self.q_max)

    def rate(self, theta_rate: np.ndarray) -> np.ndarray:
        """q̇_nom (8,) rad/s of the newest call's q_nom: S ⊙ θ̇' (θ̇ mirrored like θ), 0 where that
        call clipped q_nom at a joint limit or held it (angle invalid), or where θ̇ is not finite."""
        theta_rate = np.asarray(theta_rate, dtype=np.float64)
        if self.mirror:
            theta_rate = mirror_pose(theta_rate)
        dq = self.scale * theta_rate
        return np.where(self._moving & np.isfinite(dq), dq, 0.0)

    def calibrate(self, theta: np.ndarray) -> None:
        """Capture θ_home from the person's current (neutral) pose, in this mode's frame."""
        theta = np.asarray(theta, dtype=np.float64)
        if theta.shape != (8,) or not np.isfinite(theta).all():
            raise SafetyConfigError("calibration needs 8 finite pose angles")
        self.theta_home = mirror_pose(theta) if self.mirror else theta.copy()
