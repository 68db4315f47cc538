"""The robot measured against the true person, at its simulated joints (architecture §7).

:class:`TruthProbe` evaluates, at every control step, the robot's CBF capsules at the simulated
joint angles q_sim against the *true* person's capsules, over *every* pair (the robot
description's self pairs, all 7 × 7 robot–human pairs and its static pairs such as the arms
against the pelvis, whatever the safety configuration monitors):

    clearance_i = d_i − (r_A + r_B)            (m, capsule surfaces, no margin φ)
    rate_i      = (∂d_i/∂q) q̇_sim = nᵀ J_pA q̇_sim   (m/s, the robot's own motion only: the
                                                      person's capsule has no Jacobian)
    commanded_i = nᵀ J_pA u*                         (m/s, the same for the commanded velocity
                                                      u*: what the filter asked for at this pose,
                                                      apart from the servos trailing behind it)

with n the unit normal from the person's (or the other link's) closest point toward the robot's
(:mod:`services.safety.barriers.capsules`). A negative rate is the robot closing that pair. The rows come
from the safety service's own :class:`~services.safety.barriers.capsules.CapsuleBarrier` (φ = 0), so the
geometry is exactly the one the filter protects, now at the robot's real pose and the person's
real place.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from services.safety.assembly import robot_radii
from services.safety.barriers.capsules import CapsuleBarrier
from services.safety.barriers.static import StaticCapsuleBarrier
from services.safety.kinematics import RobotKinematics
from services.safety.pairs import PairSet, make_pair_set
from shared.config import StackConfig

#: A pair closes "faster than" this (m/s) when its clearance shrinks by the robot's motion.
CLOSING_SPEED = 1e-3


def fixed_bodies(model: mujoco.MjModel, joint_names: tuple[str, ...]) -> frozenset[str]:
    """The names of the bodies of ``model`` that none of the imitation joints ``joint_names`` moves
    (no such joint on their chain to the world: the G1's pelvis, legs and waist yaw link; the world
    and the people's bodies are among them too, and carry no robot surface).

    A person inside one of them touches the robot whatever the controller does: a lower bound on
    the contact steps of any run (``true_contacts_fixed_bodies``)."""
    imitation = {mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, name) for name in joint_names}
    fixed = set()
    for body in range(model.nbody):
        chain, moved = body, False
        while chain > 0 and not moved:
            first = model.body_jntadr[chain]
            moved = any(first + i in imitation for i in range(model.body_jntnum[chain]))
            chain = model.body_parentid[chain]
        if not moved:
            fixed.add(model.body(body).name)
    return frozenset(fixed)


@dataclass(frozen=True)
class StepTruth:
    """One step: ``clearance``, ``rate`` and ``commanded`` (M,) per truth row of
    :attr:`TruthProbe.names` (NaN where the person's capsule is missing; ``commanded`` NaN
    throughout when no command was given), the robot capsules at q_sim ``robot`` (7, 2, 3) m."""

    clearance: np.ndarray
    rate: np.ndarray
    commanded: np.ndarray
    robot: np.ndarray


class TruthProbe:
    """Every pair's clearance and robot closing rate at q_sim against the true person."""

    def __init__(self, conf: StackConfig, kinematics: RobotKinematics) -> None:
        self.kinematics = kinematics
        spec, radii, n = kinematics.spec, robot_radii(conf, kinematics), len(kinematics.joint_names)
        #: Every self pair of the robot description, then every robot × person capsule pair.
        self.pairs: PairSet = make_pair_set([tuple(p) for p in spec.self_pairs], n_people=1)
        self._barrier = CapsuleBarrier(self.pairs, radii, n)
        #: Every static pair of the robot description (the arms against the pelvis).
        self._static = StaticCapsuleBarrier.for_robot(kinematics, radii, [tuple(p) for p in spec.static_pairs])
        #: (M,) the name of each truth row: :attr:`pairs`, then the static pairs.
        self.names: tuple[str, ...] = self.pairs.names + self._static.row_names()
        #: (M,) bool: the row is a robot–robot (self or static) pair.
        self.is_self: np.ndarray = np.concatenate([self.pairs.is_self, np.ones(len(self._static.row_names()), bool)])

    def measure(self, q_sim: np.ndarray, dq_sim: np.ndarray, capsules: np.ndarray, radii: np.ndarray,
                valid: np.ndarray, u: np.ndarray | None = None) -> StepTruth:
        """Clearances and rates at joints ``q_sim`` (8,) rad moving at ``dq_sim`` (8,) rad/s, the true
        person's ``capsules`` (7, 2, 3) m with ``radii`` (7,) m where ``valid`` (7,); ``u`` (8,) rad/s
        the commanded velocity (None: ``commanded`` is NaN)."""
        self._barrier.set_external(capsules, radii, valid)
        endpoints, jacobians = self.kinematics.compute(q_sim)
        robot = endpoints.copy()
        rows = self._barrier.evaluate(endpoints, jacobians, gamma=1.0, phi=0.0)
        static = self._static.constraint_rows(q_sim, endpoints, jacobians, gamma=1.0, phi=0.0, lookahead=0.0)

        def rate_of(velocity: np.ndarray) -> np.ndarray:
            return np.concatenate([np.where(rows.enabled, rows.A @ velocity, np.nan), static.A @ velocity])

        commanded = np.full(len(self.names), np.nan) if u is None else rate_of(u)
        return StepTruth(clearance=np.concatenate([rows.h, static.h]), rate=rate_of(dq_sim), commanded=commanded,
                         robot=robot)
