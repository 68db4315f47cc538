"""Static capsule rows: robot capsules against capsules fixed in the world (robot description
``static_capsules`` / ``static_pairs``), all hard.

A link no imitation joint moves (the G1's pelvis under its rolling and pitching waist) is a capsule
with zero Jacobian and zero velocity. For a robot capsule A against such a capsule P the rows are
the capsule rows of :mod:`services.safety.barriers.capsules` with J_pP = 0 and no approach term:

    h = d − (r_A + r_P + φ),   A = nᵀ J_pA,   b = −γ h        (n from P's closest point toward A's)

They are self-collision rows: hard (never traded for a person's motion), so u = 0 keeps them
whenever h ≥ 0 at the step's start (b ≤ 0), which is the filter's feasibility argument unchanged.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from services.safety.barriers.base import Barrier
from services.safety.barriers.pairs import BarrierRows, SegmentRowWriter, segment_rows
from services.safety.pairs import N_ROBOT
from shared.names import CAPSULE_NAMES


class StaticCapsuleBarrier(Barrier):
    """Hard rows keeping ``pairs`` (robot capsule name, static capsule name) apart.

    ``robot_radii`` (7,) m in CAPSULE_NAMES order; ``static_endpoints`` name → (2, 3) m world
    endpoints; ``static_radii`` name → m; ``n_joints`` the columns of A.
    """

    name = "static"

    def __init__(self, pairs: Sequence[tuple[str, str]], robot_radii: np.ndarray,
                 static_endpoints: Mapping[str, np.ndarray], static_radii: Mapping[str, float], n_joints: int) -> None:
        statics = list(static_endpoints)
        self.names = tuple(f"{robot}|{static}" for robot, static in pairs)
        motion = np.zeros((2, N_ROBOT + len(statics), 2, 3))  # the segments and their (zero) velocities
        self._segments, self._velocities = motion[0], motion[1]
        self._radii = np.concatenate([np.asarray(robot_radii, dtype=np.float64), [static_radii[s] for s in statics]])
        for i, static in enumerate(statics):
            self._segments[N_ROBOT + i] = static_endpoints[static]
        self._first = np.array([CAPSULE_NAMES.index(robot) for robot, _ in pairs], dtype=np.int64)
        self._second = np.array([N_ROBOT + statics.index(static) for _, static in pairs], dtype=np.int64)
        self._n_joints = n_joints
        m = len(self.names)
        self._hard, self._self, self._enabled = np.zeros(m, bool), np.ones(m, bool), np.ones(m, bool)
        self._writer = SegmentRowWriter(motion, self._radii, self._first, self._second,
                                        np.stack([self._enabled, self._self, self._hard]))
        self._distance = np.empty(m)  # write_rows' distances (not returned)

    @classmethod
    def for_robot(cls, kinematics, robot_radii: np.ndarray, pairs: Sequence[tuple[str, str]]) -> StaticCapsuleBarrier:
        """The rows of ``pairs`` (a subset of the robot description's ``static_pairs``) on the static
        capsules ``kinematics`` (:class:`~services.safety.kinematics.RobotKinematics`) placed in the
        world, with the robot capsules' ``robot_radii`` (7,) m."""
        static_radii = {name: cap.radius for name, cap in kinematics.spec.static_capsules.items()}
        return cls(pairs, robot_radii, kinematics.static_endpoints, static_radii, len(kinematics.joint_names))

    def constraint_rows(self, q: np.ndarray, endpoints: np.ndarray, jacobians: np.ndarray, gamma: float, phi: float,
                        lookahead: float, accel: np.ndarray | None = None) -> BarrierRows:
        if not len(self.names):
            empty = np.zeros(0)
            return BarrierRows(A=np.zeros((0, self._n_joints)), b=empty, soft=self._hard, h=empty, distance=empty,
                               enabled=self._enabled, is_self=self._self)
        self._segments[:N_ROBOT] = endpoints
        A, b, h, distance, min_h = segment_rows(self._segments, self._radii, jacobians, self._velocities, self._first,
                                                self._second, N_ROBOT, gamma, phi, 0.0)
        return BarrierRows(A=A, b=b, soft=self._hard, h=h, distance=distance, enabled=self._enabled,
                           is_self=self._self, min_h_all=min_h)

    def write_rows(self, q: np.ndarray, endpoints: np.ndarray, jacobians: np.ndarray, gamma: float, phi: float,
                   lookahead: float, accel: np.ndarray | None, start: int, A: np.ndarray, b: np.ndarray,
                   soft: np.ndarray, h: np.ndarray) -> tuple[float, float]:
        """:meth:`constraint_rows` in one compiled call (:class:`SegmentRowWriter`)."""
        return self._writer.write(endpoints, jacobians, gamma, phi, 0.0, start, A, b, soft, h, self._distance)

    def row_names(self) -> tuple[str, ...]:
        return self.names
