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
from services.safety.barrier_kernel import pair_distances, pair_rows
from shared.geometry import EPS_NORMAL, safe_normal

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
    min_h_all: float = float("inf")  # min h over enabled rows (inf: none)

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
        self._first = np.ascontiguousarray(pairs.first, dtype=np.int64)
        self._second = np.ascontiguousarray(pairs.second, dtype=np.int64)
        self._all_enabled = True

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
        else:
            self._endpoints[ext] = endpoints
            self._radii[ext] = radii
            self._valid[ext] = True if valid is None else valid
            self._velocities[ext] = 0.0 if velocities is None else velocities
        self._all_enabled = bool(self._valid.all())

    def evaluate(self, robot_endpoints: np.ndarray, robot_jacobians: np.ndarray, gamma: float, phi: float) -> BarrierRows:
        """Rows at the robot configuration whose FK gave ``robot_endpoints`` (7,2,3) and
        ``robot_jacobians`` (7,2,3,n)."""
        self._endpoints[:N_ROBOT] = robot_endpoints
        m = len(self._first)
        distance, h, s, t = np.empty(m), np.empty(m), np.empty(m), np.empty(m)
        normal = np.empty((m, 3))
        first, second = self._first, self._second
        need = pair_distances(self._endpoints, self._radii, first, second, phi, EPS_NORMAL, distance, h, s, t, normal)
        if need:  # segments touching or crossing: the documented deterministic fallback normal
            rows = np.flatnonzero(distance < EPS_NORMAL)
            ea, eb = self._endpoints[first[rows]], self._endpoints[second[rows]]
            normal[rows] = safe_normal(np.zeros((len(rows), 3)), np.zeros((len(rows), 3)), (ea[:, 0], ea[:, 1], eb[:, 0], eb[:, 1]))
        A, b = np.empty((m, self.n_joints)), np.empty(m)
        pair_rows(normal, s, t, h, robot_jacobians, self._velocities, first, second, N_ROBOT, gamma, A, b)
        enabled = self._valid[second]
        if not self._all_enabled:
            A[~enabled] = 0.0
            b[~enabled] = DISABLED_B
            h[~enabled] = np.nan
            min_h_all = float(h[enabled].min()) if enabled.any() else float("inf")
        else:
            min_h_all = float(h.min()) if m else float("inf")
        return BarrierRows(A=A, b=b, h=h, distance=distance, enabled=enabled, is_self=self._is_self, min_h_all=min_h_all)
