"""Contacts found in the simulation: one step's report and the tally over a run.

A :class:`ContactReport` lists the body pairs in contact at one physics step, split into
robot–robot (two robot links that are not adjacent and not already touching at home, or touching
at home and pressed deeper) and robot–human (a robot surface and one of the 7 human capsules). Several contact points between
the same two bodies are one :class:`BodyContact` carrying the deepest penetration.
:class:`ContactTally` accumulates reports over a run (the executor's counters, the evaluator's
metrics). Lengths in metres.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field
from typing import Any

import numpy as np

__all__ = ["BodyContact", "ContactReport", "ContactTally", "SurfaceContact"]


@dataclass(frozen=True, order=True)
class BodyContact:
    """Two bodies in contact: ``body_a`` is a robot body, ``body_b`` a robot body or a human
    capsule name (shared.names.CAPSULE_NAMES); ``depth`` is the deepest penetration (m, ≥ 0)."""

    body_a: str
    body_b: str
    depth: float = field(compare=False)

    @property
    def key(self) -> str:
        """``"body_a|body_b"``: a stable name for the pair."""
        return f"{self.body_a}|{self.body_b}"


@dataclass(frozen=True)
class SurfaceContact:
    """A robot surface geom penetrating a human capsule: ``robot_body`` and ``capsule`` names,
    ``depth`` (m, > 0), ``point`` (3,) the robot surface's deepest point (world frame, m),
    ``normal`` (3,) unit, from the person toward the robot, and ``closing_speed`` (m/s) = −nᵀ J_p q̇:
    the robot's own velocity at ``point`` into the person (positive: the robot moves closer; the
    person's motion is not in it)."""

    robot_body: str
    capsule: str
    depth: float
    point: np.ndarray
    normal: np.ndarray
    closing_speed: float


@dataclass(frozen=True)
class ContactReport:
    """The body pairs in contact at one physics step, each list sorted by body names."""

    robot_robot: tuple[BodyContact, ...] = ()
    robot_human: tuple[BodyContact, ...] = ()

    @property
    def empty(self) -> bool:
        return not self.robot_robot and not self.robot_human


@dataclass
class _KindTally:
    """Counters of one contact kind (robot–robot or robot–human)."""

    steps: int = 0  # checked steps with at least one contact of this kind
    onsets: int = 0  # pairs that came into contact (a pair touching over consecutive steps: once)
    max_depth: float = 0.0  # deepest penetration seen (m)
    pair_steps: Counter[str] = field(default_factory=Counter)  # pair key -> steps in contact
    _previous: frozenset[str] = frozenset()

    def update(self, contacts: tuple[BodyContact, ...]) -> None:
        keys = frozenset(c.key for c in contacts)
        if keys:
            self.steps += 1
            self.max_depth = max(self.max_depth, max(c.depth for c in contacts))
            self.pair_steps.update(keys)
        self.onsets += len(keys - self._previous)
        self._previous = keys

    def summary(self) -> dict[str, Any]:
        return {
            "steps": self.steps,
            "onsets": self.onsets,
            "max_depth_m": self.max_depth,
            "pairs": dict(sorted(self.pair_steps.items())),
        }


class ContactTally:
    """Counts contacts over a run, one :meth:`update` per checked step.

    Per kind: ``steps`` (checked steps with a contact), ``onsets`` (a pair coming into contact;
    one long touch counts once), the deepest penetration and the steps each pair spent in contact.
    """

    def __init__(self) -> None:
        self.checked = 0
        self.robot_robot = _KindTally()
        self.robot_human = _KindTally()

    def update(self, report: ContactReport) -> None:
        self.checked += 1
        self.robot_robot.update(report.robot_robot)
        self.robot_human.update(report.robot_human)

    def summary(self) -> dict[str, Any]:
        """``{"checked": n, "robot_robot": {...}, "robot_human": {...}}`` (JSON-ready)."""
        return {
            "checked": self.checked,
            "robot_robot": self.robot_robot.summary(),
            "robot_human": self.robot_human.summary(),
        }

    def line(self) -> str:
        """One human-readable line: steps and onsets per kind."""
        rr, rh = self.robot_robot, self.robot_human
        return (
            f"contacts robot-robot {rr.steps} steps/{rr.onsets} onsets, "
            f"robot-human {rh.steps} steps/{rh.onsets} onsets (of {self.checked} checked)"
        )
