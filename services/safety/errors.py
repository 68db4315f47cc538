"""Typed errors of the safety service."""

from __future__ import annotations

from shared.errors import SafemimicError

__all__ = ["KinematicsError", "SafetyConfigError", "SafetyError"]


class SafetyError(SafemimicError):
    """Base class of the safety service's own errors."""


class SafetyConfigError(SafetyError, ValueError):
    """A safety setting that cannot be built: an unknown pair preset or QP backend, a self pair
    that does not name two robot capsules, retargeting values that are not 8 finite numbers or
    limits that cross, a negative sphere subsampling level. The message names the value."""


class KinematicsError(SafetyError, ValueError):
    """The robot model and its spec do not fit together, or a kinematics query is invalid.

    Raised for a missing model file, a joint/body/frame named in the spec that the model
    lacks, an imitation joint that is not a 1-DoF joint, limits without a finite range, a
    home value outside a joint's range, or a configuration of the wrong shape / not finite.
    The message names what is missing or wrong.
    """
