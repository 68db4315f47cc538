"""Build the safety pipeline (kinematics, pairs, barrier, filter, retargeter) from configuration."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.safety.barriers.capsules import CapsuleBarrier
from services.safety.filter import FilterParams, SafetyFilter
from services.safety.barriers.pairs import CollisionGeometry
from services.safety.barriers.spheres import SphereBarrier, nominal_human
from services.safety.barriers.static import StaticCapsuleBarrier
from services.safety.direction_retarget import DirectionRetargeter
from services.safety.human_memory import external_capsules
from services.safety.kinematics import RobotKinematics
from services.safety.pairs import N_ROBOT, PairSet, make_pair_set, preset_pair_set, select_groups
from services.safety.qp import make_backend
from services.safety.retarget import Retargeter
from services.safety.standoff import apply_standoff
from shared.config import GeometryName, PairGroup, RetargetMethod, StackConfig
from shared.lowpass import angle_rate_filter
from shared.messages import HumanState
from shared.robot_spec import RobotSpec, configured_robot_spec


@dataclass
class SafetyPipeline:
    """Everything one safety step needs, built once (sizes fixed for a pair set)."""

    spec: RobotSpec
    kinematics: RobotKinematics
    pairs: PairSet
    barrier: CollisionGeometry
    filter: SafetyFilter
    retargeter: Retargeter | DirectionRetargeter
    #: The retargeter's own kinematics (:func:`make_retargeter`), apart from the filter's buffers.
    retarget_kinematics: RobotKinematics

    def warm_up(self, dt: float, q: np.ndarray | None = None, human: HumanState | None = None, steps: int = 3) -> None:
        """Throw-away steps from ``q`` (default: the filter's) with ``human``'s capsules, so one-time
        lazy work (numba's compiled-function cache, a QP solver's first setup: 0.2–0.3 s measured
        here; the kernels of the boxes only an infeasible step uses, and the standoff's, which a
        standoff of 0 never calls) and the solver's warm start
        happen now, not inside a control tick. The filter ends at ``q``."""
        filt = self.filter
        q = filt.q_cbf.copy() if q is None else np.array(q, dtype=np.float64)
        if human is None:
            self.barrier.set_external(None)
        else:
            self.barrier.set_external(*external_capsules(human, self.pairs.n_external, False))
        filt.reset(q)
        for _ in range(steps):
            filt.step(q, dt)
        filt.compile_boxes(dt)
        apply_standoff(np.zeros(1), np.zeros(1), np.ones(1, dtype=np.bool_), 1.0, 1.0)  # for a standoff set in place later
        filt.reset(q)
        self.retargeter.warm_up()


def make_retargeter(conf: StackConfig, spec: RobotSpec, kinematics: RobotKinematics) -> Retargeter | DirectionRetargeter:
    """The configured retargeting (``retargeting.method``): paper eq. 2 with q_home =
    ``retargeting.q_home`` or the robot's home pose and S = robot sign ⊙ configured scale; with
    ``directions`` that map drives the waist and the arms are solved by direction. ``kinematics``
    is an instance for the retargeter alone (the direction method overwrites its buffers)."""
    r = conf.retargeting
    linear = Retargeter(
        q_home=kinematics.q_home if r.q_home is None else np.asarray(r.q_home),
        q_min=kinematics.q_min,
        q_max=kinematics.q_max,
        scale=np.asarray(spec.retarget_sign) * np.asarray(r.scale),
        offset=np.asarray(r.offset),
        theta_home=np.asarray(r.theta_home),
        mirror=r.mirror,
    )
    if r.method == RetargetMethod.LINEAR:
        return linear
    self_pairs = select_groups(make_pair_set([tuple(p) for p in spec.self_pairs], n_people=0),
                               {group.value for group in conf.safety.enabled_pair_groups})
    body = [CapsuleBarrier(self_pairs, robot_radii(conf, kinematics), len(kinematics.joint_names)),
            make_static_barrier(conf, kinematics)]
    rates = angle_rate_filter(len(linear.q_min), conf.perception.angles)
    return DirectionRetargeter(linear, kinematics, rates, body, conf.safety.phi, conf.safety.phi,
                               make_backend(conf.safety.backend.value),
                               np.minimum(conf.safety.u_max, np.abs(conf.safety.u_min or conf.safety.u_max)))


def robot_radii(conf: StackConfig, kinematics: RobotKinematics) -> np.ndarray:
    """Robot capsule radii (7,): the robot description's, overridden by ``safety.capsule_radii``."""
    radii = np.array(kinematics.radii, dtype=np.float64)
    for name, radius in conf.safety.capsule_radii.items():
        radii[kinematics.capsule_names.index(name)] = radius
    return radii


def make_geometry(conf: StackConfig, pairs: PairSet, kinematics: RobotKinematics) -> CollisionGeometry:
    """The configured collision geometry (``safety.geometry``; spheres with ``safety.sphere_k``
    levels of subsampling) over ``pairs``, with the configured robot radii and person margin
    (``safety.human_margin``)."""
    radii, n = robot_radii(conf, kinematics), len(kinematics.joint_names)
    geometry = conf.safety.geometry
    barrier: CollisionGeometry
    if geometry is GeometryName.SPHERES:
        external = np.tile(nominal_human(conf.human), (pairs.n_external // N_ROBOT, 1))  # per person
        barrier = SphereBarrier(pairs, kinematics.capsule_local, radii, n, conf.safety.sphere_k, external)
    elif geometry is GeometryName.BOX:
        from services.safety.barriers.boxes import BoxBarrier  # coal only where boxes are used

        barrier = BoxBarrier(pairs, kinematics, radii, n)
    else:
        barrier = CapsuleBarrier(pairs, radii, n)
    barrier.person_margin = conf.safety.human_margin
    return barrier


def make_static_barrier(conf: StackConfig, kinematics: RobotKinematics) -> StaticCapsuleBarrier:
    """The robot description's static capsule rows (the arms against the pelvis), with the
    configured robot radii. Static capsules are part of the trunk: the ``self_torso`` pair group
    switches them with the torso's pairs."""
    spec = kinematics.spec
    enabled = PairGroup.SELF_TORSO in conf.safety.enabled_pair_groups
    pairs = [tuple(p) for p in spec.static_pairs] if enabled else []
    return StaticCapsuleBarrier.for_robot(kinematics, robot_radii(conf, kinematics), pairs)


def build_pipeline(conf: StackConfig, pair_preset: str | None = None, kinematics: RobotKinematics | None = None) -> SafetyPipeline:
    """Assemble the safety pipeline for ``conf`` (optionally another pair preset / shared kinematics)."""
    spec = configured_robot_spec(conf) if kinematics is None else kinematics.spec
    spec.check_velocity_bounds(conf.safety.u_max, conf.safety.u_min)
    kinematics = kinematics or RobotKinematics(spec)
    pairs = preset_pair_set(pair_preset or conf.safety.pairs, [tuple(p) for p in spec.self_pairs])
    pairs = select_groups(pairs, {group.value for group in conf.safety.enabled_pair_groups})
    barrier = make_geometry(conf, pairs, kinematics)
    safety_filter = SafetyFilter(kinematics, barrier, FilterParams.from_config(conf.safety), conf.safety.backend.value,
                                 extra=[make_static_barrier(conf, kinematics)])
    retarget_kinematics = RobotKinematics(spec)
    return SafetyPipeline(spec, kinematics, pairs, barrier, safety_filter,
                          make_retargeter(conf, spec, retarget_kinematics), retarget_kinematics)
