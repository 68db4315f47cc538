"""Sphere decomposition of the capsules (paper §IV-B, Table I: "Spheres (k)", center-to-center distance).

A capsule with segment [a, b] (length L) and radius r becomes N + 1 spheres centred at

    c_j = (1 − λ_j) a + λ_j b,   λ_j = j / N,   j = 0 … N,   N = N₀ · 2^k,   N₀ = ⌈L / 2r⌉:

level 0 spaces the centres at most 2r apart (a chain of touching spheres of the capsule's own
radius: no subsampling), each of the k levels of subsampling halves the spacing δ = L / N (puts
a sphere between every two). Every sphere has the *covering* radius

    ρ = √(r² + (δ/2)²):

a point within r of the axis lies within √(r² + δ²/4) of the nearest centre, so the spheres
contain the capsule and h ≥ 0 for every sphere pair keeps the capsules apart too. The price is
conservatism: ρ/r ≤ √2 at level 0, ≤ 1.118 at level 1, ≤ 1.031 at level 2.

Row of a sphere pair (i, j) (the capsule rows of :mod:`services.safety.barriers.capsules` for zero-length
segments, computed by the same kernel):

    h = ‖c_i − c_j‖ − (ρ_i + ρ_j + φ),   ∂h/∂q = nᵀ (J_ci − J_cj),   J_c = (1 − λ) J_a + λ J_b,

a sphere centre being a fixed convex combination of its capsule's two body-fixed endpoints.
Every sphere of capsule A meets every sphere of capsule B for each monitored pair (A, B).

External (human) capsules change length with the person while the QP keeps its size: their
interval count N comes from a nominal adult (:func:`nominal_human`) once; the centres and the
covering radius follow the measured capsule at every update, so the covering always holds.
"""

from __future__ import annotations

import math

import numpy as np

from services.safety.barriers.pairs import BarrierRows, CollisionGeometry, segment_rows, swept_witness_points
from services.safety.errors import SafetyConfigError
from services.safety.pairs import N_ROBOT, PairSet
from shared.body import Body, capsule_radii
from shared.config import HumanConfig
from shared.names import CAPSULE_NAMES


def intervals(length: float, radius: float, k: int) -> int:
    """N = ⌈L / 2r⌉ · 2^k: the number of intervals between sphere centres (0: one sphere)."""
    return math.ceil(length / (2.0 * radius)) * 2**k


def nominal_human(human: HumanConfig) -> np.ndarray:
    """(7, 2) nominal (length, radius) of the human capsules (CAPSULE_NAMES order): the segments of
    the synthetic 1.75 m adult (:class:`~shared.body.Body`; the forearm reaches
    ``hand_extension`` past the wrist, the torso from the pelvis to the base of the neck) with the
    configured radii."""
    body = Body()
    length = {
        "torso": body.torso_length + body.neck,
        "upper_arm": body.upper_arm,
        "forearm": body.forearm + human.hand_extension,
        "thigh": body.thigh,
    }
    lengths = [length[name.removeprefix("left_").removeprefix("right_")] for name in CAPSULE_NAMES]
    return np.column_stack([lengths, capsule_radii(human)])


def _interpolation(counts: list[int]) -> tuple[np.ndarray, np.ndarray]:
    """For capsules with ``counts`` intervals: W (S, 2C) with c_s = W @ endpoints.reshape(2C, 3)
    and the capsule index (S,) of every sphere."""
    rows, owner = [], []
    for c, n in enumerate(counts):
        lam = np.linspace(0.0, 1.0, n + 1) if n else np.zeros(1)
        for value in lam:
            row = np.zeros(2 * len(counts))
            row[2 * c], row[2 * c + 1] = 1.0 - value, value
            rows.append(row)
            owner.append(c)
    return np.array(rows), np.array(owner, dtype=np.intp)


class SphereBarrier(CollisionGeometry):
    """Each capsule as N + 1 enclosing spheres (k levels of subsampling); one row per sphere pair."""

    name = "spheres"

    def __init__(
        self,
        pairs: PairSet,
        robot_capsules: np.ndarray,
        robot_radii: np.ndarray,
        n_joints: int,
        k: int,
        external_nominal: np.ndarray,
    ) -> None:
        """``robot_capsules`` (7, 2, 3) the capsule endpoints in their bodies' frames;
        ``external_nominal`` (E, 2) nominal (length, radius) of the external capsules."""
        super().__init__(pairs, robot_radii, n_joints)
        if k < 0:
            raise SafetyConfigError(f"sphere subsampling level k must be ≥ 0, got {k}")
        self.k = k
        robot_length = np.linalg.norm(robot_capsules[:, 1] - robot_capsules[:, 0], axis=1)
        robot_n = [intervals(L, r, k) for L, r in zip(robot_length, self.robot_radii)]
        nominal = np.asarray(external_nominal, dtype=np.float64).reshape(pairs.n_external, 2)
        self._external_n = np.array([intervals(L, r, k) for L, r in nominal], dtype=np.float64)
        self._w_robot, robot_owner = _interpolation(robot_n)
        self._w_external, external_owner = _interpolation(self._external_n.astype(int).tolist())
        self._external_owner = external_owner
        n_rs, n_es = len(robot_owner), len(external_owner)
        self.n_robot_spheres = n_rs
        #: (S,) capsule (stack index) of every sphere: the robot's, then the external ones.
        self.sphere_capsule = np.concatenate([robot_owner, N_ROBOT + external_owner])

        # Every sphere of A against every sphere of B, pair by pair.
        spheres_of = [np.flatnonzero(self.sphere_capsule == c) for c in range(N_ROBOT + pairs.n_external)]
        first, second, row_pair = [], [], []
        for p, (a, b) in enumerate(zip(pairs.first, pairs.second)):
            sa, sb = np.meshgrid(spheres_of[a], spheres_of[b], indexing="ij")
            first.append(sa.ravel())
            second.append(sb.ravel())
            row_pair.append(np.full(sa.size, p))
        self._first = np.ascontiguousarray(np.concatenate(first), dtype=np.int64)
        self._second = np.ascontiguousarray(np.concatenate(second), dtype=np.int64)
        self._set_rows(np.concatenate(row_pair))

        self._segments = np.zeros((n_rs + n_es, 2, 3))  # zero-length segments [c, c]
        self._sphere_radii = np.zeros(n_rs + n_es)
        self._sphere_velocities = np.zeros((n_rs + n_es, 2, 3))
        spacing = robot_length / np.maximum(robot_n, 1)
        self._sphere_radii[:n_rs] = np.hypot(self.robot_radii, spacing / 2.0)[robot_owner]
        self._jacobians = np.zeros((n_rs, 2, 3, n_joints))  # end 1 has weight s = 0: stays zero

    @property
    def spheres(self) -> tuple[np.ndarray, np.ndarray]:
        """Centres (S, 3) and radii (S,) of every sphere at the last evaluation (robot first)."""
        return self._segments[:, 0].copy(), self._sphere_radii.copy()

    def _external_changed(self) -> None:
        ext = self._endpoints[N_ROBOT:]
        n_rs = self.n_robot_spheres
        centres = self._w_external @ ext.reshape(-1, 3)
        self._segments[n_rs:, 0] = centres
        self._segments[n_rs:, 1] = centres
        velocity = self._w_external @ self._velocities[N_ROBOT:].reshape(-1, 3)
        self._sphere_velocities[n_rs:, 0] = velocity
        self._sphere_velocities[n_rs:, 1] = velocity
        length = np.linalg.norm(ext[:, 1] - ext[:, 0], axis=1)
        spacing = length / np.maximum(self._external_n, 1.0)
        self._sphere_radii[n_rs:] = np.hypot(self._radii[N_ROBOT:], spacing / 2.0)[self._external_owner]

    def evaluate(
        self, robot_endpoints: np.ndarray, robot_jacobians: np.ndarray, gamma: float, phi: float, lookahead: float = 0.0
    ) -> BarrierRows:
        n_rs = self.n_robot_spheres
        centres = self._w_robot @ robot_endpoints.reshape(2 * N_ROBOT, 3)
        self._segments[:n_rs, 0] = centres
        self._segments[:n_rs, 1] = centres
        flat = self._w_robot @ robot_jacobians.reshape(2 * N_ROBOT, 3 * self.n_joints)
        self._jacobians[:, 0] = flat.reshape(n_rs, 3, self.n_joints)
        A, b, h, distance, min_h = segment_rows(
            self._segments, self._sphere_radii, self._jacobians, self._sphere_velocities, self._first, self._second,
            n_rs, gamma, phi, lookahead,
        )
        return self._rows(A, b, h, distance, robot_endpoints, phi, min_h)

    def witness_points(self) -> np.ndarray:
        return swept_witness_points(self._segments, self._sphere_radii, self._first, self._second)
