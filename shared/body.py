"""The human body model behind the seven human capsules, shared by perception and safety.

:class:`Body` holds the segment lengths (m) of a typical adult (the synthetic person of
:mod:`services.perception.synthetic`, the nominal human the sphere geometry is sized for);
:func:`capsule_radii` the capsule radii (m) of :class:`shared.config.HumanConfig` in
:data:`shared.names.CAPSULE_NAMES` order (paper §III-A).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from shared.config import HumanConfig
from shared.names import CAPSULE_NAMES


@dataclass(frozen=True)
class Body:
    """Segment lengths (m) of the synthetic person; defaults: a 1.75 m adult."""

    shoulder_width: float = 0.36  # between the shoulder joint centres (people: 0.20–0.37)
    hip_width: float = 0.18
    pelvis_height: float = 0.95
    torso_length: float = 0.50  # pelvis → shoulder centre
    neck: float = 0.04  # shoulder centre → spine_chest (base of the neck)
    head: float = 0.10  # spine_chest → head (skull base)
    upper_arm: float = 0.29
    forearm: float = 0.26
    hip_drop: float = 0.04  # pelvis → hip joints, downwards
    thigh: float = 0.42
    shank: float = 0.42

    def __post_init__(self) -> None:
        for name, value in self.__dict__.items():
            if not (math.isfinite(value) and 0.0 < value < 2.0):
                raise ValueError(f"body {name} must be in (0, 2) m, got {value}")


def capsule_radii(human: HumanConfig) -> np.ndarray:
    """(7,) radii (m) in CAPSULE_NAMES order."""
    by_part = {"torso": human.torso_radius, "upper_arm": human.upper_arm_radius,
               "forearm": human.forearm_radius, "thigh": human.thigh_radius}
    return np.array([by_part[name.removeprefix("left_").removeprefix("right_")] for name in CAPSULE_NAMES])
