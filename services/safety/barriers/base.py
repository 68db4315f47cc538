"""The barrier interface: every kind of CBF row is one class under :class:`Barrier` (like mink's limits).

A barrier turns the robot's state at the start of a step into linear rows on the joint velocity u,

    A u ≥ b        (A (m, n), b (m,)),

each with a priority (:class:`RowBlock.soft`):

- **hard** rows (joint barriers, self-collision pairs) are always honoured; one that is already
  violated at the step's start (b_i > 0 although u = 0 must satisfy it: it must not happen) is
  softened like a soft row, at a much higher cost;
- **soft** rows (robot–person pairs) may give way when the rows are infeasible together, each by
  its own slack σ_i ∈ [0, max(b_i, 0)], i.e. never below A_i u ≥ min(b_i, 0): at worst the robot
  keeps its distance to that person capsule, it never closes in.

:class:`~services.safety.filter.SafetyFilter` stacks the blocks of any list of barriers and
solves one QP over all of them; it knows no barrier kind. Its step asks every barrier to write its
rows in place (:meth:`Barrier.write_rows`): by default the stacked :meth:`Barrier.constraint_rows`,
overridden with one compiled call by the barriers that have a kernel (capsule, static and joint rows).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import ClassVar

import numpy as np


#: :meth:`RowBlock.minima` of rows that are no distances (joint angles): no such row
NO_DISTANCE = (float("inf"), float("inf"))


@dataclass
class RowBlock:
    """One barrier's rows for one step: ``A`` (m, n), ``b`` (m,), ``soft`` (m,) bool (True: may give
    way down to A_i u ≥ min(b_i, 0)), ``h`` (m,) m the barrier values (NaN: not a distance)."""

    A: np.ndarray
    b: np.ndarray
    soft: np.ndarray
    h: np.ndarray

    def minima(self) -> tuple[float, float]:
        """(smallest h over the enabled distance rows, over the enabled self-collision distance rows);
        inf: no such row. Rows that are not distances (here: none) count for neither."""
        return NO_DISTANCE


class Barrier(ABC):
    """A kind of CBF row. Subclasses name themselves (:attr:`name`) and build their rows."""

    #: The barrier kind (``safety.geometry`` names for pair barriers, ``joint`` for joint barriers).
    name: ClassVar[str]
    #: Whether h is a distance between surfaces (m): the hard ones then aim ``safety.self_margin``
    #: beyond φ (:mod:`services.safety.filter`); False for rows on joint angles.
    measures_distance: ClassVar[bool] = True

    @abstractmethod
    def constraint_rows(self, q: np.ndarray, endpoints: np.ndarray, jacobians: np.ndarray, gamma: float, phi: float,
                        lookahead: float, accel: np.ndarray | None = None) -> RowBlock:
        """Rows at joint angles ``q`` (n,) rad whose forward kinematics gave the robot capsules'
        ``endpoints`` (7, 2, 3) m and ``jacobians`` (7, 2, 3, n); ``gamma`` (1/s) the CBF rate,
        ``phi`` (m) the distance margin, ``lookahead`` (s) the human velocity term's T, ``accel``
        (n,) rad/s² the joints' acceleration bound (None: none; a joint-space barrier then lets a
        joint approach no faster than it can stop)."""

    def write_rows(self, q: np.ndarray, endpoints: np.ndarray, jacobians: np.ndarray, gamma: float, phi: float,
                   lookahead: float, accel: np.ndarray | None, start: int, A: np.ndarray, b: np.ndarray,
                   soft: np.ndarray, h: np.ndarray) -> tuple[float, float]:
        """The rows of :meth:`constraint_rows` (same arguments, same values) written in place, into
        rows ``start`` … ``start + m − 1`` of the stacked ``A`` (M, n), ``b``, ``soft``, ``h`` (M,) of
        every barrier; returns :meth:`RowBlock.minima` of them. This default stacks
        :meth:`constraint_rows`; a barrier with a compiled kernel overrides it (the filter's step then
        allocates nothing for its rows) and may call it through
        :class:`~services.safety.barriers.kernel.BoundKernel`: every call passes the same types, as
        the filter's step does (``A``, ``b``, ``h`` C-contiguous float64, ``soft`` bool, ``q``
        and ``accel`` float64 (n,), the scalars float, ``start`` int, the forward kinematics' own
        arrays)."""
        block = self.constraint_rows(q, endpoints, jacobians, gamma, phi, lookahead, accel)
        stop = start + block.b.shape[0]
        A[start:stop], b[start:stop], soft[start:stop], h[start:stop] = block.A, block.b, block.soft, block.h
        return block.minima()

    @abstractmethod
    def row_names(self) -> tuple[str, ...]:
        """One readable name per row, in row order (what ``SafetyStatus.relaxed_pairs`` reports when
        that row gives way), e.g. ``left_forearm|human.torso`` or ``left_shoulder_roll_joint>=0.1``."""
