"""Capsule CBF rows (paper eqs. 4–7; architecture §4).

For a pair (A, B) with closest points p_A = a_A + s*(b_A − a_A), p_B = a_B + t*(b_B − a_B),
d = ‖p_A − p_B‖ and unit normal n = (p_A − p_B)/d:

    h = d − (r_A + r_B + φ),      ∂h/∂q = nᵀ (J_pA − J_pB),   J_pA = (1 − s*) J_aA + s* J_bA

(envelope theorem: s*, t* held fixed). A human capsule has J = 0; its measured endpoint
velocity v enters as a known term: the approach speed a = max(nᵀ v_pB, 0) = max(−∂h/∂t, 0).
The human capsules are held between two human states (zero-order hold), so the term is
one-sided and looks ahead by T (``lookahead``, one camera frame plus the pipeline latency):

    ∂h/∂q u ≥ −γ (h − T a) + a,   i.e.  A u ≥ b  with  b = −γ (h − T a) + a.

A person approaching at a makes the robot retreat at a (and keep T a of extra room, the distance
covered before the next human state), so h stays ≥ 0 across the jump of the held capsule at the
next update; a receding person never lets the robot close in on where the person was last seen
(a two-sided term would, and h against the held capsule would dip by |nᵀv|·T every frame).
Rows of missing (invalid) human capsules are kept with A = 0 and b = −∞-like so the QP keeps a
fixed size.
"""

from __future__ import annotations

import numpy as np

from services.safety.barriers.pairs import (
    DISABLED_B, BarrierRows, CollisionGeometry, SegmentRowWriter, segment_rows, swept_witness_points,
)
from services.safety.pairs import N_ROBOT, PairSet

__all__ = ["DISABLED_B", "BarrierRows", "CapsuleBarrier"]


class CapsuleBarrier(CollisionGeometry):
    """The capsules themselves (the default ``safety.geometry``): one row per monitored pair."""

    name = "capsule"

    def __init__(self, pairs: PairSet, robot_radii: np.ndarray, n_joints: int) -> None:
        super().__init__(pairs, robot_radii, n_joints)
        self._first = np.ascontiguousarray(pairs.first, dtype=np.int64)
        self._second = np.ascontiguousarray(pairs.second, dtype=np.int64)
        self._writer = SegmentRowWriter(self._motion, self._radii, self._first, self._second, self._flags)

    def evaluate(
        self, robot_endpoints: np.ndarray, robot_jacobians: np.ndarray, gamma: float, phi: float, lookahead: float = 0.0
    ) -> BarrierRows:
        """Rows at the robot configuration whose FK gave ``robot_endpoints`` (7,2,3) and
        ``robot_jacobians`` (7,2,3,n); ``lookahead`` T (s) of the human velocity term."""
        self._endpoints[:N_ROBOT] = robot_endpoints
        A, b, h, distance, min_h = segment_rows(
            self._endpoints, self._radii, robot_jacobians, self._velocities, self._first, self._second, N_ROBOT,
            gamma, phi, lookahead,
        )
        return self._rows(A, b, h, distance, robot_endpoints, phi, min_h)

    def write_rows(self, q: np.ndarray, endpoints: np.ndarray, jacobians: np.ndarray, gamma: float, phi: float,
                   lookahead: float, accel: np.ndarray | None, start: int, A: np.ndarray, b: np.ndarray,
                   soft: np.ndarray, h: np.ndarray) -> tuple[float, float]:
        """:meth:`evaluate`'s rows in one compiled call (:class:`SegmentRowWriter`); :attr:`last_rows`
        views them in ``A``, ``b``, ``h``."""
        distance = np.empty(self._first.shape[0])
        low, low_self = self._writer.write(endpoints, jacobians, gamma, phi, lookahead, start, A, b, soft, h, distance)
        stop = start + distance.shape[0]
        h_measured = self.measured_h(endpoints, h[start:stop], phi) if low < 0.0 else None
        self.last_rows = BarrierRows(A[start:stop], b[start:stop], self._row_soft, h[start:stop], distance,
                                     self._row_enabled, self._row_is_self, low, h_measured)
        return low, low_self

    def witness_points(self) -> np.ndarray:
        return swept_witness_points(self._endpoints, self._radii, self._first, self._second)
