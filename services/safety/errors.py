"""Typed errors of the safety service."""

from __future__ import annotations

__all__ = ["KinematicsError", "SafetyError"]


class SafetyError(Exception):
    """Base class of the safety service's own errors."""


class KinematicsError(SafetyError, ValueError):
    """The robot model and its spec do not fit together, or a kinematics query is invalid.

    Raised for a missing model file, a joint/body/frame named in the spec that the model
    lacks, an imitation joint that is not a 1-DoF joint, limits without a finite range, a
    home value outside a joint's range, or a configuration of the wrong shape / not finite.
    The message names what is missing or wrong.
    """
