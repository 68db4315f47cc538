"""Capsule CBF rows (paper eqs. 4–7; DESIGN §4).

For a pair (A, B) with closest points p_A = a_A + s*(b_A − a_A), p_B = a_B + t*(b_B − a_B),
d = ‖p_A − p_B‖ and unit normal n = (p_A − p_B)/d:

    h = d − (r_A + r_B + φ),      ∂h/∂q = nᵀ (J_pA − J_pB),   J_pA = (1 − s*) J_aA + s* J_bA

(envelope theorem: s*, t* held fixed). A human capsule has J = 0; its measured endpoint
velocity v enters as the known term ∂h/∂t = −nᵀ v_pB, so the row  ∂h/∂q u ≥ −γ h − ∂h/∂t
reads  A u ≥ b  with  b = −γ h + nᵀ v_pB. Rows of missing (invalid) human capsules are kept
with A = 0 and b = −∞-like so the QP keeps a fixed size.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.safety.pairs import N_ROBOT, PairSet
from shared.geometry import safe_normal, segment_closest_points

#: b of a disabled row (A = 0): 0 ≥ −1e9 always holds.
DISABLED_B = -1e9


@dataclass
class BarrierRows:
    """CBF rows for one step: ``A`` (m, n), ``b`` (m,), barrier values ``h`` (m,, NaN if disabled)."""

    A: np.ndarray
    b: np.ndarray
    h: np.ndarray
    distance: np.ndarray
    enabled: np.ndarray
    is_self: np.ndarray

    def min_h(self, self_rows: bool) -> float | None:
        """Minimum h over enabled self (or robot–human) rows; None if there is none."""
        mask = self.enabled & (self.is_self if self_rows else ~self.is_self)
        return float(self.h[mask].min()) if mask.any() else None


class CapsuleBarrier:
    """Evaluates every monitored pair's h and CBF row from robot FK and external capsules."""

    def __init__(self, pairs: PairSet, robot_radii: np.ndarray, n_joints: int) -> None:
        self.pairs = pairs
        self.robot_radii = np.asarray(robot_radii, dtype=np.float64)
        self.n_joints = n_joints
        n_stack = N_ROBOT + pairs.n_external
        self._endpoints = np.zeros((n_stack, 2, 3))
        self._velocities = np.zeros((n_stack, 2, 3))  # robot rows stay zero (their motion is in J u)
        self._radii = np.zeros(n_stack)
        self._valid = np.ones(n_stack, bool)
        self._radii[:N_ROBOT] = self.robot_radii
        self._is_self = pairs.is_self
        # index arrays scattering closest-point weights onto the robot endpoints (capsule c, end e → 2c + e)
        self._rows = np.arange(len(pairs))
        self._self_rows = np.flatnonzero(self._is_self)
        self._a0, self._a1 = 2 * pairs.first, 2 * pairs.first + 1
        self._b0, self._b1 = 2 * pairs.second[self._self_rows], 2 * pairs.second[self._self_rows] + 1
        self._point_weights = np.zeros((len(pairs), 2 * N_ROBOT))

    def set_external(
        self,
        endpoints: np.ndarray | None,
        radii: np.ndarray | None = None,
        valid: np.ndarray | None = None,
        velocities: np.ndarray | None = None,
    ) -> None:
        """Set the E external capsules ((E,2,3) m, (E,) m, (E,) bool, (E,2,3) m/s); None: none present."""
        ext = slice(N_ROBOT, None)
        if endpoints is None:
            self._valid[ext] = False
            return
        self._endpoints[ext] = endpoints
        self._radii[ext] = radii
        self._valid[ext] = True if valid is None else valid
        self._velocities[ext] = 0.0 if velocities is None else velocities

    def evaluate(self, robot_endpoints: np.ndarray, robot_jacobians: np.ndarray, gamma: float, phi: float) -> BarrierRows:
        """Rows at the robot configuration whose FK gave ``robot_endpoints`` (7,2,3) and
        ``robot_jacobians`` (7,2,3,n)."""
        self._endpoints[:N_ROBOT] = robot_endpoints
        i, j = self.pairs.first, self.pairs.second
        ea, eb = self._endpoints[i], self._endpoints[j]
        closest = segment_closest_points(ea[:, 0], ea[:, 1], eb[:, 0], eb[:, 1])
        normal = safe_normal(closest.p, closest.q, (ea[:, 0], ea[:, 1], eb[:, 0], eb[:, 1]))
        # J_pA − J_pB as one weighted sum over the 14 robot endpoint Jacobians: (m, 14) @ (14, 3n)
        weights = self._point_weights
        weights[self._rows, self._a0] = 1.0 - closest.s
        weights[self._rows, self._a1] = closest.s
        weights[self._self_rows, self._b0] = closest.t[self._self_rows] - 1.0
        weights[self._self_rows, self._b1] = -closest.t[self._self_rows]
        jp = (weights @ robot_jacobians.reshape(2 * N_ROBOT, -1)).reshape(-1, 3, self.n_joints)
        A = np.matmul(normal[:, None, :], jp)[:, 0, :]
        h = closest.distance - (self._radii[i] + self._radii[j] + phi)
        vb = self._velocities[j]
        v_pb = (1.0 - closest.t)[:, None] * vb[:, 0] + closest.t[:, None] * vb[:, 1]
        b = -gamma * h + np.einsum("mk,mk->m", normal, v_pb)
        enabled = self._valid[j]
        if not enabled.all():
            A[~enabled] = 0.0
            b[~enabled] = DISABLED_B
            h = np.where(enabled, h, np.nan)
        return BarrierRows(A=A, b=b, h=h, distance=closest.distance, enabled=enabled, is_self=self._is_self)
