"""Monitored capsule pairs (paper §III-B) as index arrays into the stacked capsule array.

Capsules are stacked as ``[robot_0 … robot_6, external_0 … external_{E-1}]``: the 7 robot
capsules (CAPSULE_NAMES order) then E external capsules (E = 7 per person). A pair
``(first[i], second[i])`` always has a robot capsule first; ``second`` is a robot capsule
(self-collision row) or an external one (robot–human row).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
import numpy as np

from services.safety.errors import SafetyConfigError
from shared.names import CAPSULE_NAMES

N_ROBOT = len(CAPSULE_NAMES)
_ROBOT_INDEX = {name: i for i, name in enumerate(CAPSULE_NAMES)}


@dataclass(frozen=True)
class PairSet:
    """``first`` (m,) robot capsule indices, ``second`` (m,) stacked indices, readable ``names``."""

    first: np.ndarray
    second: np.ndarray
    names: tuple[str, ...]
    n_external: int

    @property
    def is_self(self) -> np.ndarray:
        """(m,) bool: the row is a robot–robot (self-collision) row."""
        return self.second < N_ROBOT

    def __len__(self) -> int:
        return len(self.first)


def _external_name(index: int) -> str:
    person, capsule = divmod(index, N_ROBOT)
    return f"human{'' if person == 0 else person + 1}.{CAPSULE_NAMES[capsule]}"


def make_pair_set(self_pairs: Sequence[tuple[str, str]], n_people: int = 1, max_rows: int | None = None) -> PairSet:
    """Self pairs by name, then every robot capsule × every capsule of ``n_people`` people.

    ``max_rows`` truncates the list (benchmarks sized to a constraint count).
    """
    first: list[int] = []
    second: list[int] = []
    names: list[str] = []
    for a, b in self_pairs:
        if a not in _ROBOT_INDEX or b not in _ROBOT_INDEX or a == b:
            raise SafetyConfigError(f"self pair ({a}, {b}) must name two different robot capsules of {CAPSULE_NAMES}")
        first.append(_ROBOT_INDEX[a])
        second.append(_ROBOT_INDEX[b])
        names.append(f"{a}|{b}")
    for external in range(N_ROBOT * n_people):
        for robot in range(N_ROBOT):
            first.append(robot)
            second.append(N_ROBOT + external)
            names.append(f"{CAPSULE_NAMES[robot]}|{_external_name(external)}")
    rows = slice(0, max_rows)
    return PairSet(
        first=np.array(first[rows], dtype=np.intp),
        second=np.array(second[rows], dtype=np.intp),
        names=tuple(names[rows]),
        n_external=N_ROBOT * n_people,
    )


def sized_pair_set(self_pairs: Sequence[tuple[str, str]], n_rows: int) -> PairSet:
    """Exactly ``n_rows`` rows: the self pairs, then robot × people, as many people as needed."""
    n_people = max(1, -(-(n_rows - len(self_pairs)) // (N_ROBOT * N_ROBOT)))
    pairs = make_pair_set(self_pairs, n_people=n_people, max_rows=n_rows)
    if len(pairs) != n_rows:
        raise SafetyConfigError(f"cannot build {n_rows} rows from {len(self_pairs)} self pairs")
    return pairs


def preset_pair_set(preset: str, default_self_pairs: Sequence[tuple[str, str]]) -> PairSet:
    """Named pair sets: ``default`` (the robot description's self pairs + every robot × human
    pair) or ``paper72`` (the paper's worst case, Table I: the default set padded to 72 rows with
    the capsules of a second person)."""
    if preset == "default":
        return make_pair_set(default_self_pairs)
    if preset == "paper72":
        return sized_pair_set(default_self_pairs, 72)
    raise SafetyConfigError(f"unknown pair preset {preset!r}; known: default, paper72")


def pair_group(robot: str, other: str | None) -> str:
    """The switchable group of a pair (shared.config.PairGroup values): ``human`` for a robot–human
    pair (``other`` None); a self pair is ``self_torso`` with the torso, else ``self_legs`` with a
    thigh, else ``self_arms``."""
    if other is None:
        return "human"
    names = {robot, other}
    if "torso" in names:
        return "self_torso"
    if names & {"left_thigh", "right_thigh"}:
        return "self_legs"
    return "self_arms"


def select_groups(pairs: PairSet, enabled: set[str]) -> PairSet:
    """The pairs whose group is in ``enabled`` (same order, same external capsule count)."""
    keep = np.array(
        [
            pair_group(CAPSULE_NAMES[a], CAPSULE_NAMES[b] if b < N_ROBOT else None) in enabled
            for a, b in zip(pairs.first, pairs.second)
        ],
        dtype=bool,
    )
    return PairSet(
        first=pairs.first[keep],
        second=pairs.second[keep],
        names=tuple(name for name, k in zip(pairs.names, keep) if k),
        n_external=pairs.n_external,
    )
