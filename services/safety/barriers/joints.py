"""Joint barriers of the robot description (``joint_barriers``: links the capsules cannot see).

One hard row per bound, h_j = sign (q_j − bound) ≥ 0:

    lower bound:  u_j ≥ −α(q_j − lower_j)         upper bound:  −u_j ≥ −α(upper_j − q_j)

with the class-K function α(h) = γ h, or, where the joint's acceleration is bounded by a_j,
α(h) = min(γ h, √(2 β a_j h)) for h ≥ 0 (β = BRAKE_SHARE of the bound): a joint approaches its
barrier no faster than it can stop at it (γ h alone asks for a deceleration of γ·speed, which at
a fast joint is more than the bound allows).
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from services.safety.barriers.base import NO_DISTANCE, Barrier, RowBlock
from services.safety.barriers.kernel import joint_rows, write_joint_block
from services.safety.compiled import BoundKernel

#: The share of a joint's acceleration bound it counts on to stop at a barrier or a joint limit (the
#: rest is left to the other rows and joints competing for the same step).
BRAKE_SHARE = 0.5


class JointBarrier(Barrier):
    """Rows keeping joints inside the robot description's barrier bounds (rad), all hard."""

    name = "joint"
    measures_distance = False

    def __init__(self, bounds: Mapping[str, tuple[float | None, float | None]], joint_names: tuple[str, ...]) -> None:
        rows = []
        for joint, (lower, upper) in bounds.items():
            j = joint_names.index(joint)
            rows += [(j, 1.0, lower)] if lower is not None else []
            rows += [(j, -1.0, upper)] if upper is not None else []
        index, sign, bound = (np.array(v, dtype=float) for v in (zip(*rows) if rows else ((), (), ())))
        self.index = index.astype(np.intp)
        #: (2, m) each row's sign and bound (one argument of the compiled writer); :attr:`sign` and
        #: :attr:`bound` view it
        self._signed = np.stack([sign, bound])
        self.sign, self.bound = self._signed
        self._unbounded = np.zeros(len(joint_names))  # the kernel's accel argument without a bound (never read)
        self._A = sign[:, None] * np.eye(len(joint_names))[self.index]
        self._soft = np.zeros(len(self.index), bool)
        self._write = BoundKernel(write_joint_block)
        self._names = tuple(f"{joint_names[j]}{'>=' if sgn > 0 else '<='}{bound:g}" for j, sgn, bound in rows)

    def constraint_rows(self, q: np.ndarray, endpoints: np.ndarray, jacobians: np.ndarray, gamma: float, phi: float,
                        lookahead: float, accel: np.ndarray | None = None) -> RowBlock:
        m = self.index.shape[0]
        h, b = np.empty(m), np.empty(m)
        bounded = accel is not None
        joint_rows(q, self.index, self.sign, self.bound, gamma, accel if bounded else self._unbounded, BRAKE_SHARE,
                   bounded, h, b)
        return RowBlock(A=self._A, b=b, soft=self._soft, h=h)

    def write_rows(self, q: np.ndarray, endpoints: np.ndarray, jacobians: np.ndarray, gamma: float, phi: float,
                   lookahead: float, accel: np.ndarray | None, start: int, A: np.ndarray, b: np.ndarray,
                   soft: np.ndarray, h: np.ndarray) -> tuple[float, float]:
        """:meth:`constraint_rows` in one compiled call; joint angles are no distances: (inf, inf)."""
        bounded = accel is not None
        self._write.call(q, self.index, self._signed, gamma, accel if bounded else self._unbounded, BRAKE_SHARE, bounded,
                         self._A, start, A, b, soft, h)
        return NO_DISTANCE

    def row_names(self) -> tuple[str, ...]:
        return self._names
