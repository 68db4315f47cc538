"""Oriented bounding boxes of the capsules (paper §IV-B, Table I: "Boxes"), distances from coal.

The box of a capsule [a, b] with radius r and length L = ‖b − a‖ has its centre at (a + b)/2, its
long axis along u = (b − a)/L and half extents e = (r, r, L/2 + r): the tightest box around the
capsule along its axis. Its edges and corners are rounded with radius ρ = ``EDGE_ROUNDING`` · r:
the collider is the inner box of half extents e − ρ swept by a sphere of radius ρ (coal's
swept-sphere radius),

    B_ρ = Box(e − ρ) ⊕ Ball(ρ),   0 ≤ ρ ≤ r,

whose six faces are the bounding box's faces. It contains the capsule for every ρ ≤ r: with S the
capsule's segment and C(r − ρ) the cube of half side r − ρ, which contains Ball(r − ρ),

    capsule = S ⊕ Ball(r) = S ⊕ Ball(r − ρ) ⊕ Ball(ρ) ⊆ S ⊕ C(r − ρ) ⊕ Ball(ρ) = B_ρ.

Every excess over the capsule scales with r − ρ: (√2 − 1)(r − ρ) across a long edge,
(√3 − 1)(r − ρ) at an end corner; ρ = 0 is the sharp box, ρ = r the capsule itself.

Why not sharp boxes (ρ = 0): beside a person (the side-by-side arm raise) the robot's hanging
forearm sits in a slot between the top corner of its own thigh's box ((√3 − 1) r = 49 mm off
the thigh capsule) and the person's hand box, which touch *opposite faces* of the forearm's box.
The two rows then have exactly opposite normals n and −n (a face normal does not change while
the forearm slides along the face, so no joint velocity increases both distances), and once the hand
approaches faster than γ (h₁ + h₂) the QP is infeasible while every h > 0: the filter relaxes and the
boxes come to overlap (h = −35 mm). The rows are exact (they match finite differences); the
one-step CBF just has no room left. Halving every excess with ρ = r/2 leaves the slot open while
the faces, and so the boxes' conservatism across them, stay those of the bounding box (measured on
that scenario: ρ = r/4 still fails with h = −11 mm; 0.4 r, r/2 and 0.6 r keep h ≥ −1 mm, with 70,
9 and 0 relaxed steps; ``bench/results/geometry.md`` has both scenarios at r/2).

The box is symmetric under u → −u, so its axis is taken as ±u, the sign towards a
reference axis a (a · u ≥ 0), and its rotation comes from the minimal rotation taking a to ±u,

    R(a → u) = I + [v]_× + [v]_×² / (1 + c),   v = a × u,   c = a · u ≥ 0   (never singular).

A robot box is fixed in its capsule's body: R = R_body R(e_z → u_local). An external box has no
body frame (a capsule is two points), so it is carried along with minimal twist: at every update
R ← R(R e_z → u) R (parallel transport, starting from R(e_z → u)); a fixed rule such as
R(e_z → u) alone would spin the square cross-section about the axis whenever ±u changes sign,
moving the box under a still person.

Per monitored pair, coal (GJK, EPA when the boxes overlap) gives the signed distance d between the
rounded boxes (< 0: the penetration depth), the witness points p_A, p_B on their surfaces and coal's normal n_c (p_B − p_A = d n_c). With
n = −n_c (pointing from B towards A, as in every other geometry):

    h = d − φ,   ∂h/∂q = nᵀ (J_pA − J_pB),   J_p = J_a − [p − a]_× J_ω,

by the envelope theorem (the witness points held fixed in their bodies); J_a is the point
Jacobian of the capsule's endpoint a and J_ω its body's angular Jacobian
(:meth:`~services.safety.kinematics.RobotKinematics.capsule_frames`). An external witness point
moves with the capsule, v_p = (1 − λ) v_a + λ v_b, λ its position along the axis. The rows come
from the shared kernel :func:`~services.safety.barriers.kernel.pair_rows`, the witness points
being zero-length segments with those Jacobians and velocities.
"""

from __future__ import annotations

import coal
import numpy as np

from services.safety.barriers.kernel import pair_rows
from services.safety.barriers.pairs import BarrierRows, CollisionGeometry
from services.safety.kinematics import RobotKinematics
from services.safety.pairs import N_ROBOT, PairSet

#: A segment shorter than this (m) has no axis: its box is upright.
_MIN_LENGTH = 1e-12
#: ρ / r: the radius of a box's rounded edges and corners, as a fraction of its capsule's radius.
EDGE_ROUNDING = 0.5


def minimal_rotation(a: np.ndarray, u: np.ndarray) -> np.ndarray:
    """(C, 3, 3) minimal rotations taking unit ``a`` (C, 3) to ±``u`` (unit, C, 3), sign with a · u ≥ 0."""
    u = np.where(np.einsum("ij,ij->i", a, u)[:, None] < 0.0, -u, u)
    v, c = np.cross(a, u), np.einsum("ij,ij->i", a, u)
    zero = np.zeros_like(c)
    K = np.stack([np.stack([zero, -v[:, 2], v[:, 1]], -1), np.stack([v[:, 2], zero, -v[:, 0]], -1),
                  np.stack([-v[:, 1], v[:, 0], zero], -1)], 1)
    return np.eye(3) + K + (K @ K) / (1.0 + c)[:, None, None]


def capsule_boxes(
    segments: np.ndarray, radii: np.ndarray, rotations: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Centres (C, 3), rotations (C, 3, 3) and half extents (C, 3) of the boxes of capsules
    ``segments`` (C, 2, 3) with ``radii`` (C,), each rotation ``rotations`` (C, 3, 3) carried to
    the capsule's axis with minimal twist (a zero-length capsule keeps its rotation)."""
    d = segments[:, 1] - segments[:, 0]
    length = np.linalg.norm(d, axis=1)
    axis = rotations[:, :, 2]
    u = np.where(length[:, None] > _MIN_LENGTH, d / np.maximum(length, _MIN_LENGTH)[:, None], axis)
    half = np.column_stack([radii, radii, 0.5 * length + radii])
    return 0.5 * (segments[:, 0] + segments[:, 1]), minimal_rotation(axis, u) @ rotations, half


def set_rounded(shape: coal.Box, half: np.ndarray, rounding: float) -> coal.Box:
    """Make ``shape`` the box of half extents ``half`` (3,) with edges and corners rounded by
    ``rounding`` ρ: Box(half − ρ) ⊕ Ball(ρ), the same faces. Returns ``shape``."""
    shape.halfSide = half - rounding
    shape.setSweptSphereRadius(rounding)
    return shape


def _cross_columns(r: np.ndarray, J: np.ndarray) -> np.ndarray:
    """[r]_× J per row (r × every column of J): ``r`` (m, 3), ``J`` (m, 3, n) → (m, 3, n)."""
    r = r[:, :, None]
    out = np.empty_like(J)
    out[:, 0] = r[:, 1] * J[:, 2] - r[:, 2] * J[:, 1]
    out[:, 1] = r[:, 2] * J[:, 0] - r[:, 0] * J[:, 2]
    out[:, 2] = r[:, 0] * J[:, 1] - r[:, 1] * J[:, 0]
    return out


class BoxBarrier(CollisionGeometry):
    """The oriented bounding box of every capsule, edges rounded (``EDGE_ROUNDING``); one row per
    monitored pair (coal distances)."""

    name = "box"

    def __init__(self, pairs: PairSet, kinematics: RobotKinematics, robot_radii: np.ndarray, n_joints: int) -> None:
        super().__init__(pairs, robot_radii, n_joints)
        self.kinematics = kinematics
        local = np.asarray(kinematics.capsule_local)
        _, self._local_rotation, robot_half = capsule_boxes(local, self.robot_radii, np.tile(np.eye(3), (N_ROBOT, 1, 1)))
        self._local_offset = 0.5 * (local[:, 1] - local[:, 0])  # box centre − a, body frame
        n_stack = N_ROBOT + pairs.n_external
        #: Centres (B, 3), rotations (B, 3, 3), half extents (B, 3) of every box (robot first)
        #: at the last evaluation / external update.
        self.centres = np.zeros((n_stack, 3))
        self.rotations = np.tile(np.eye(3), (n_stack, 1, 1))
        self.half_extents = np.ones((n_stack, 3))
        self.half_extents[:N_ROBOT] = robot_half
        #: (B,) radius ρ of every box's rounded edges: the collider is Box(half_extents − ρ) ⊕ Ball(ρ).
        self.rounding = np.zeros(n_stack)
        self.rounding[:N_ROBOT] = EDGE_ROUNDING * self.robot_radii
        self._shapes = [coal.Box(2.0 * half) for half in self.half_extents]
        for shape, half, rho in zip(self._shapes[:N_ROBOT], robot_half, self.rounding):
            set_rounded(shape, half, rho)
        self._transforms = [coal.Transform3s() for _ in range(n_stack)]
        self._first = np.asarray(pairs.first, dtype=np.intp)
        self._second = np.asarray(pairs.second, dtype=np.intp)
        self._queries = [
            (coal.ComputeDistance(self._shapes[a], self._shapes[b]), self._transforms[a], self._transforms[b])
            for a, b in zip(pairs.first.tolist(), pairs.second.tolist())
        ]
        self._request = coal.DistanceRequest()
        self._result = coal.DistanceResult()

        # Witness points as zero-length segments: slot i holds p_A of row i; then p_B of every
        # self row (robot slots), then p_B of every robot–human row (external slots).
        m = len(pairs)
        self._self_rows = np.flatnonzero(pairs.is_self)
        self._human_rows = np.flatnonzero(~pairs.is_self)
        self._self_other = self._second[self._self_rows]  # robot capsule B of every self row
        self._human_capsule = self._second[self._human_rows]  # external capsule B of every human row
        n_self = len(self._self_rows)
        second_slot = np.empty(m, dtype=np.int64)
        second_slot[self._self_rows] = m + np.arange(n_self)
        second_slot[self._human_rows] = m + n_self + np.arange(len(self._human_rows))
        self._slot_first = np.arange(m, dtype=np.int64)
        self._slot_second = second_slot
        self._n_robot_slots = m + n_self
        self._jacobians = np.zeros((m + n_self, 2, 3, n_joints))  # end 1 has weight s = 0: stays zero
        self._witness_velocities = np.zeros((m + n_self + len(self._human_rows), 2, 3))
        self._zeros = np.zeros(m)
        self._witness = np.zeros((m, 2, 3))  # p_A, p_B of every row at the last evaluation

    def _external_changed(self) -> None:
        ext = slice(N_ROBOT, None)
        self.centres[ext], self.rotations[ext], self.half_extents[ext] = capsule_boxes(
            self._endpoints[ext], self._radii[ext], self.rotations[ext]
        )
        self.rounding[ext] = EDGE_ROUNDING * self._radii[ext]
        for i in range(N_ROBOT, len(self._shapes)):
            set_rounded(self._shapes[i], self.half_extents[i], self.rounding[i])
            self._transforms[i].setRotation(self.rotations[i])
            self._transforms[i].setTranslation(self.centres[i])

    def evaluate(
        self, robot_endpoints: np.ndarray, robot_jacobians: np.ndarray, gamma: float, phi: float, lookahead: float = 0.0
    ) -> BarrierRows:
        body_rotation, angular = self.kinematics.capsule_frames()
        a = robot_endpoints[:, 0]
        rob = slice(0, N_ROBOT)
        self.rotations[rob] = body_rotation @ self._local_rotation
        self.centres[rob] = a + np.einsum("cij,cj->ci", body_rotation, self._local_offset)
        transforms = self._transforms
        for c in range(N_ROBOT):
            transforms[c].setRotation(self.rotations[c])
            transforms[c].setTranslation(self.centres[c])

        m = len(self._queries)
        distance, normal, witness = np.empty(m), np.empty((m, 3)), self._witness
        request, result = self._request, self._result
        for i, (compute, tf_a, tf_b) in enumerate(self._queries):
            result.clear()
            distance[i] = compute(tf_a, tf_b, request, result)
            witness[i, 0] = result.getNearestPoint1()
            witness[i, 1] = result.getNearestPoint2()
            normal[i] = result.normal
        np.negative(normal, out=normal)  # coal's points from A to B; ours from B to A
        h = distance - phi

        first, other, J = self._first, self._self_other, self._jacobians
        J[:m, 0] = robot_jacobians[first, 0] - _cross_columns(witness[:, 0] - a[first], angular[first])
        J[m:, 0] = robot_jacobians[other, 0] - _cross_columns(witness[self._self_rows, 1] - a[other], angular[other])
        if len(self._human_rows):
            cap = self._endpoints[self._human_capsule]
            axis = cap[:, 1] - cap[:, 0]
            along = np.einsum("ij,ij->i", witness[self._human_rows, 1] - cap[:, 0], axis)
            lam = np.clip(along / np.maximum(np.einsum("ij,ij->i", axis, axis), 1e-300), 0.0, 1.0)[:, None]
            v = self._velocities[self._human_capsule]
            self._witness_velocities[self._n_robot_slots:, 0] = (1.0 - lam) * v[:, 0] + lam * v[:, 1]

        A, b = np.empty((m, self.n_joints)), np.empty(m)
        pair_rows(
            normal, self._zeros, self._zeros, h, J, self._witness_velocities, self._slot_first, self._slot_second,
            self._n_robot_slots, gamma, lookahead, A, b,
        )
        return self._rows(A, b, h, distance, robot_endpoints, phi)

    def witness_points(self) -> np.ndarray:
        return self._witness.copy()
