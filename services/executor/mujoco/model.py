"""The MuJoCo model of the simulation: the robot spec's MJCF, edited and compiled (architecture §1, §10).

:func:`build_model` loads the robot spec's MJCF (our mesh-free G1-class model by default, or another
one such as Menagerie's G1 with meshes) and edits it with ``mujoco.MjSpec`` before compiling:

- **welded base**: the base body's joints (the free joint) are removed and the body is placed at
  ``(0, 0, base_height)`` with identity orientation, so the world frame is the robot frame of
  architecture §3 (x forward, y left, z up, floor at z = 0). The robot's own balance controller holds
  the lower body in the paper; here the pelvis is simply fixed;
- **joint servos**: the model's actuators and sensors are replaced by one position servo per joint
  (:func:`servo_name`; torque = kp (q_ref − q) − kd q̇, limited by the joint's ``actuatorfrcrange``).
  The 8 imitation joints use ``kp``/``kd``; every other joint is held at its home angle with
  ``hold_kp``/``hold_kd`` (:class:`PDGains`). Optional gravity compensation goes through the same
  servos (MuJoCo ``gravcomp`` + ``actuatorgravcomp``), so it respects the torque limits too;
- **the people**: 7 mocap bodies per person (one capsule geom each, CAPSULE_NAMES order, named
  :func:`human_body_name`, geom group :data:`HUMAN_GEOM_GROUP`), parked at :data:`PARK_POSITION`.
  Their geoms collide with nothing (contype = conaffinity = 0): a person driven by a recording must
  not push the simulated robot (a person walking into it would bend its legs into each other,
  "robot–robot" contacts the robot never made); robot–human contacts are measured instead
  (:mod:`services.executor.mujoco.contacts`);
- **stiction**: every robot joint's dry friction (``frictionloss``) holds a joint loaded below it
  still (:data:`STICTION_IMPEDANCE`), where MuJoCo's default soft friction lets it creep;
- **adjacent links**: MuJoCo ignores parent–child contacts except when the parent is welded to
  the world, so each static body (the welded base and whatever hangs on it without a joint) gets
  an explicit exclusion with each jointed child;
- **home contacts**: robot–robot pairs already in contact at the home pose are excluded from the
  physics (and measured instead, :class:`~services.executor.mujoco.contacts.ContactMeter`).

Units SI: metres, radians, seconds, newton-metres.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import mujoco
import numpy as np

from services.executor.errors import ExecutorStartError
from services.executor.mujoco.contacts import robot_pairs_in_contact
from shared.config import ExecutorConfig
from shared.names import CAPSULE_NAMES
from shared.robot_spec import RobotSpec

__all__ = [
    "HUMAN_GEOM_GROUP",
    "PARK_POSITION",
    "PDGains",
    "SimModel",
    "STICTION_IMPEDANCE",
    "SimModelError",
    "build_model",
    "human_body_name",
    "servo_name",
]

#: Geom group of the human capsules (robot visuals are group 2, robot collision geoms group 3).
HUMAN_GEOM_GROUP = 4
#: Where unused human capsules wait (m): far below the floor, out of every contact.
PARK_POSITION = np.array([0.0, 0.0, -1000.0])
#: Colours of person 0 (the world's person) and of any further person (e.g. the perceived one).
_HUMAN_RGBA = ((0.95, 0.7, 0.55, 0.5), (0.3, 0.55, 0.95, 0.25))
#: Impedance (MuJoCo ``solimp`` d_min = d_max) of every robot joint's dry-friction constraint: stiction.
#: MuJoCo's friction is soft: a joint loaded below its ``frictionloss`` f still creeps at
#: q̇ ≈ (1 − d)/d · (τ/I) / b (b = 2/(d · timeconst)); at the default d = 0.9 a servo holding an arm
#: within its dead band (|kp e| < f) drifts ≈ 1 mrad/s for as long as it holds. A geared joint
#: does not: below f it sticks. MuJoCo's largest impedance makes the creep ≈ 1000× smaller
#: (< 0.01 mrad/s); motion at or above f (sliding) is unchanged.
STICTION_IMPEDANCE = mujoco.mjMAXIMP
#: Longest physics step a caller may ask for (s).
_MAX_TIMESTEP = 0.05


class SimModelError(ExecutorStartError, ValueError):
    """The robot model cannot be loaded or does not fit the robot spec (message says why)."""


@dataclass(frozen=True)
class PDGains:
    """Joint servo gains (kp in N·m/rad, kd in N·m·s/rad): ``kp``/``kd`` for the imitation joints,
    ``hold_kp``/``hold_kd`` for the joints held at home, ``per_joint`` overriding either by name;
    ``stop_damping`` (≥ 1) multiplies the imitation joints' kd while a command is a protective stop."""

    kp: float
    kd: float
    hold_kp: float
    hold_kd: float
    per_joint: Mapping[str, tuple[float, float]] = field(default_factory=dict)
    gravity_compensation: bool = True
    torque_feedforward: bool = True
    stop_damping: float = 1.0

    @classmethod
    def from_config(cls, conf: ExecutorConfig) -> PDGains:
        return cls(conf.kp, conf.kd, conf.hold_kp, conf.hold_kd, dict(conf.joint_gains), conf.gravity_compensation,
                   conf.torque_feedforward, conf.stop_damping)

    def of(self, joint: str, imitation: bool) -> tuple[float, float]:
        """(kp, kd) of ``joint``; ``imitation``: whether it is one of the 8 imitation joints."""
        default = (self.kp, self.kd) if imitation else (self.hold_kp, self.hold_kd)
        return self.per_joint.get(joint, default)


@dataclass(frozen=True)
class SimModel:
    """What :func:`build_model` returns: the compiled model and what building it found out."""

    #: The compiled model: welded robot with its servos, the people's mocap capsules.
    model: mujoco.MjModel
    #: Full qpos at home (spec.home, every other joint at 0).
    qpos_home: np.ndarray
    #: Per body of ``model``: whether it is the robot's (the base's subtree).
    robot_body: np.ndarray
    #: Robot–robot body pairs touching at home (names, each pair sorted): excluded from the physics.
    home_contacts: tuple[tuple[str, str], ...]


def human_body_name(capsule: str, person: int = 0) -> str:
    """Name of the mocap body (and of its geom) carrying human capsule ``capsule`` of ``person``
    (``human_<capsule>`` for person 0, ``human<p>_<capsule>`` for person p ≥ 1)."""
    return f"human_{capsule}" if person == 0 else f"human{person}_{capsule}"


def servo_name(joint: str) -> str:
    """Name of the position servo (actuator) of robot joint ``joint``."""
    return "servo_" + joint


def build_model(spec: RobotSpec, gains: PDGains, timestep: float | None = None, people: int = 1) -> SimModel:
    """The robot of ``spec`` welded at its base, with one servo per joint (``gains``), and
    ``people`` persons' capsule sets; ``timestep`` (s) replaces the model's ``<option timestep>``.

    Raises:
        SimModelError: the model is missing, does not compile, or lacks a joint/body the spec names;
            ``people`` < 1 or ``timestep`` outside (0, 0.05].
    """
    if people < 1:
        raise SimModelError(f"the scene needs at least one person's capsule set, got people={people}")
    mjs = _load_spec(spec)
    missing = [j for j in spec.imitation_joints if mjs.joint(j) is None]
    if missing:
        raise SimModelError(f"robot model {spec.model} lacks the imitation joints {missing}")
    base = _weld_base(mjs, spec)
    _add_servos(mjs, base, spec, gains)
    _add_human(mjs, people)
    if timestep is not None:
        if not 0 < timestep <= _MAX_TIMESTEP:
            raise SimModelError(f"physics timestep {timestep} s is outside (0, {_MAX_TIMESTEP}]")
        mjs.option.timestep = timestep
    model = _compile(mjs, spec.model)
    robot_body = model.body_rootid == model.body(spec.base_body).id  # the base's subtree
    qpos_home = _home_qpos(model, spec)
    home_contacts = tuple(robot_pairs_in_contact(model, qpos_home, robot_body))
    if home_contacts:
        for a, b in home_contacts:
            mjs.add_exclude(bodyname1=a, bodyname2=b)
        model = _compile(mjs, spec.model)
    return SimModel(model, qpos_home, robot_body, home_contacts)


def _load_spec(spec: RobotSpec) -> mujoco.MjSpec:
    path = spec.model_path
    if not path.is_file():
        raise SimModelError(f"robot model {path} does not exist")
    try:
        return mujoco.MjSpec.from_file(str(path))
    except Exception as exc:  # mujoco raises ValueError with the parser's message
        raise SimModelError(f"cannot load robot model {path}: {exc}") from exc


def _compile(mjs: mujoco.MjSpec, origin: str) -> mujoco.MjModel:
    try:
        return mjs.compile()
    except Exception as exc:
        raise SimModelError(f"cannot compile robot model {origin}: {exc}") from exc


def _static_group(base: mujoco.MjsBody) -> list[mujoco.MjsBody]:
    """The base and every body rigidly attached to it (reached without crossing a joint)."""
    group, todo = [], [base]
    while todo:
        body = todo.pop()
        group.append(body)
        todo.extend(child for child in body.bodies if not child.joints)
    return group


def _weld_base(mjs: mujoco.MjSpec, spec: RobotSpec) -> mujoco.MjsBody:
    """Remove the base's joints, fix it at base_height, exclude the static group's child links;
    returns the base body (the robot is its subtree)."""
    base = mjs.body(spec.base_body)
    if base is None:
        raise SimModelError(f"robot model {spec.model} has no base body {spec.base_body!r}")
    if base.parent is None or base.parent.name != mjs.worldbody.name:
        raise SimModelError(f"base body {spec.base_body!r} must be a child of the world body")
    for joint in list(base.joints):
        mjs.delete(joint)
    base.pos = [0.0, 0.0, spec.base_height]
    base.quat = [1.0, 0.0, 0.0, 0.0]
    excluded = {frozenset((e.bodyname1, e.bodyname2)) for e in mjs.excludes}
    for body in _static_group(base):
        for child in body.bodies:
            if child.joints and frozenset((body.name, child.name)) not in excluded:
                mjs.add_exclude(bodyname1=body.name, bodyname2=child.name)
    return base


def _add_servos(mjs: mujoco.MjSpec, base: mujoco.MjsBody, spec: RobotSpec, gains: PDGains) -> None:
    """Replace actuators (and the sensors that may refer to them) by one position servo per robot
    joint (the base's subtree); gravity compensation on the robot's bodies if asked."""
    for element in [*mjs.actuators, *mjs.sensors, *mjs.keys]:  # keys: qpos sizes change with the weld
        mjs.delete(element)
    imitation = set(spec.imitation_joints)
    joints = base.find_all(mujoco.mjtObj.mjOBJ_JOINT)
    unknown = sorted(set(gains.per_joint) - {joint.name for joint in joints})
    if unknown:
        raise SimModelError(f"servo gains are given for joints the robot model lacks: {unknown}")
    for joint in joints:
        if joint.type not in (mujoco.mjtJoint.mjJNT_HINGE, mujoco.mjtJoint.mjJNT_SLIDE):
            raise SimModelError(f"joint {joint.name!r} is not a hinge or slide joint: no servo can hold it")
        if not joint.name:
            raise SimModelError("the robot model has an unnamed joint")
        kp, kd = gains.of(joint.name, joint.name in imitation)
        servo = mjs.add_actuator(name=servo_name(joint.name), target=joint.name, trntype=mujoco.mjtTrn.mjTRN_JOINT)
        servo.set_to_position(kp=kp, kv=kd)
        servo.ctrllimited = mujoco.mjtLimited.mjLIMITED_FALSE
        joint.actgravcomp = gains.gravity_compensation
        joint.solimp_friction[:2] = STICTION_IMPEDANCE
    if gains.gravity_compensation:
        for body in [base, *base.find_all(mujoco.mjtObj.mjOBJ_BODY)]:
            body.gravcomp = 1.0


def _add_human(mjs: mujoco.MjSpec, people: int) -> None:
    """7 mocap capsule bodies per person; their geoms collide with nothing (measured, not simulated)."""
    for person in range(people):
        for capsule in CAPSULE_NAMES:
            body = mjs.worldbody.add_body(name=human_body_name(capsule, person), mocap=True, pos=PARK_POSITION.tolist())
            body.add_geom(
                name=human_body_name(capsule, person),
                type=mujoco.mjtGeom.mjGEOM_CAPSULE,
                size=[0.05, 0.1, 0.0],
                contype=0,
                conaffinity=0,
                group=HUMAN_GEOM_GROUP,
                rgba=list(_HUMAN_RGBA[min(person, 1)]),
            )


def _home_qpos(model: mujoco.MjModel, spec: RobotSpec) -> np.ndarray:
    """Full qpos at home: spec.home values, every other joint at 0 (every joint is 1-DoF here)."""
    qpos = np.zeros(model.nq)
    for name, value in spec.home.items():
        jid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, name)
        if jid < 0:
            raise SimModelError(f"home names joint {name!r}, which robot model {spec.model} lacks")
        lo, hi = model.jnt_range[jid]
        if model.jnt_limited[jid] and not lo - 1e-9 <= value <= hi + 1e-9:
            raise SimModelError(f"home[{name!r}] = {value} lies outside the joint range [{lo}, {hi}]")
        qpos[model.jnt_qposadr[jid]] = value
    return qpos
