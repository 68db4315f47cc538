"""MuJoCo simulation of the robot with the person in its world (architecture §1, §7, §10).

:class:`SimRobot` is the simulation core shared by the executor service and the offline
evaluator: no Zenoh, no clock, deterministic for the same calls.

The model is the robot spec's MJCF (our mesh-free G1-class model by default, or another one such
as Menagerie's G1 with meshes), edited with ``mujoco.MjSpec`` before compiling:

- **welded base**: the base body's joints (the free joint) are removed and the body is placed at
  ``(0, 0, base_height)`` with identity orientation, so the world frame is the robot frame of
  architecture §3 (x forward, y left, z up, floor at z = 0). The robot's own balance controller holds
  the lower body in the paper; here the pelvis is simply fixed;
- **joint servos**: the model's actuators and sensors are replaced by one position servo per joint
  (torque = kp (q_ref − q) − kd q̇, limited by the joint's ``actuatorfrcrange``). The 8 imitation
  joints use ``kp``/``kd`` and follow :meth:`SimRobot.set_command`; a velocity feed-forward makes
  it kp (q_ref − q) + kd (q̇_ref − q̇). Every other joint is held at its home angle with
  ``hold_kp``/``hold_kd``. Optional gravity compensation goes through the same servos
  (MuJoCo ``gravcomp`` + ``actuatorgravcomp``), so it respects the torque limits too;
- **the person**: 7 mocap bodies per person (``people``; one capsule geom each, CAPSULE_NAMES
  order, geom group 4). Their pose, length and radius follow :meth:`SimRobot.set_human`; the
  capsule's size is changed in the compiled model together with its bounding sphere and boxes
  (the geom's and its body's BVH root). The person's geoms collide with nothing (contype =
  conaffinity = 0): a person driven by a recording must not push the simulated robot (a person
  walking into it would bend its legs into each other, "robot–robot" contacts the robot never
  made). Robot–human contacts are measured instead (:meth:`SimRobot.surface_contacts`:
  ``mj_geomDistance`` between every placed human capsule and every *surface* geom of the robot);
- **adjacent links**: MuJoCo ignores parent–child contacts except when the parent is welded to
  the world, so each static body (the welded base and whatever hangs on it without a joint) gets
  an explicit exclusion with each jointed child;
- **home contacts**: robot–robot pairs already in contact at the home pose are excluded from the
  physics and listed in :attr:`SimRobot.home_contacts`; they are still measured
  (``mj_geomDistance``) and reported as a contact once they press more than
  :data:`HOME_PRESS_TOLERANCE` deeper than at home.

The robot's *surface* (what a person could touch) is every collision geom of the robot plus every
visual geom that no collision geom of its body duplicates (same shape, size and pose): the real
G1 model's rubber hands are visual-only meshes, so without them no hand contact would ever be
counted. Distances to surfaces need no contact forces, and they also cover the architecture §10 trap
(MuJoCo reports no contact between a mocap capsule and the welded, DOF-less pelvis).
Units SI: metres, radians, seconds, newton-metres.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import mujoco
import numpy as np

from services.executor.contacts import BodyContact, ContactReport, SurfaceContact
from services.executor.errors import ExecutorStartError
from shared.config import ExecutorConfig
from shared.names import CAPSULE_NAMES
from shared.robot_spec import RobotSpec

__all__ = [
    "HOME_PRESS_TOLERANCE",
    "HUMAN_GEOM_GROUP",
    "PDGains",
    "SimModelError",
    "SimRobot",
    "body_contacts",
    "human_body_name",
]

#: Geom group of the human capsules (robot visuals are group 2, robot collision geoms group 3).
HUMAN_GEOM_GROUP = 4
#: Colours of person 0 (the world's person) and of any further person (e.g. the perceived one).
_HUMAN_RGBA = ((0.95, 0.7, 0.55, 0.5), (0.3, 0.55, 0.95, 0.25))
#: A pair touching at home is a contact once it presses this much deeper than at home (m).
HOME_PRESS_TOLERANCE = 1e-3
#: Capsule endpoints farther than this from the robot (m) are treated as invalid.
MAX_HUMAN_COORD = 100.0
#: Where unused human capsules wait (m): far below the floor, out of every contact.
_PARK = np.array([0.0, 0.0, -1000.0])
#: Smallest radius / half-length given to a human capsule (m): MuJoCo needs positive sizes.
_MIN_SIZE = 1e-4
_SERVO_PREFIX = "servo_"
_ROBOT, _HUMAN = 1, 2


class SimModelError(ExecutorStartError, ValueError):
    """The robot model cannot be loaded or does not fit the robot spec (message says why)."""


@dataclass(frozen=True)
class PDGains:
    """Joint servo gains (kp in N·m/rad, kd in N·m·s/rad): ``kp``/``kd`` for the imitation joints,
    ``hold_kp``/``hold_kd`` for the joints held at home, ``per_joint`` overriding either by name."""

    kp: float
    kd: float
    hold_kp: float
    hold_kd: float
    per_joint: Mapping[str, tuple[float, float]] = field(default_factory=dict)
    gravity_compensation: bool = True
    torque_feedforward: bool = True

    @classmethod
    def from_config(cls, conf: ExecutorConfig) -> PDGains:
        return cls(conf.kp, conf.kd, conf.hold_kp, conf.hold_kd, dict(conf.joint_gains), conf.gravity_compensation,
                   conf.torque_feedforward)

    def of(self, joint: str, imitation: bool) -> tuple[float, float]:
        """(kp, kd) of ``joint``; ``imitation``: whether it is one of the 8 imitation joints."""
        default = (self.kp, self.kd) if imitation else (self.hold_kp, self.hold_kd)
        return self.per_joint.get(joint, default)


def human_body_name(capsule: str, person: int = 0) -> str:
    """Name of the mocap body (and of its geom) carrying human capsule ``capsule`` of ``person``
    (``human_<capsule>`` for person 0, ``human<p>_<capsule>`` for person p ≥ 1)."""
    return f"human_{capsule}" if person == 0 else f"human{person}_{capsule}"


# ----------------------------------------------------------------------------- model building
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
        servo = mjs.add_actuator(name=_SERVO_PREFIX + joint.name, target=joint.name, trntype=mujoco.mjtTrn.mjTRN_JOINT)
        servo.set_to_position(kp=kp, kv=kd)
        servo.ctrllimited = mujoco.mjtLimited.mjLIMITED_FALSE
        joint.actgravcomp = gains.gravity_compensation
    if gains.gravity_compensation:
        for body in [base, *base.find_all(mujoco.mjtObj.mjOBJ_BODY)]:
            body.gravcomp = 1.0


def _add_human(mjs: mujoco.MjSpec, people: int) -> None:
    """7 mocap capsule bodies per person; their geoms collide with nothing (measured, not simulated)."""
    for person in range(people):
        for capsule in CAPSULE_NAMES:
            body = mjs.worldbody.add_body(name=human_body_name(capsule, person), mocap=True, pos=_PARK.tolist())
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


def _surface_geoms(model: mujoco.MjModel, robot_geom: np.ndarray, collides: np.ndarray) -> np.ndarray:
    """Robot geoms a person could touch: every collision geom, and every visual geom that no
    collision geom of the same body duplicates (same type, mesh, size and pose)."""
    surface = []
    for g in np.flatnonzero(robot_geom):
        if not collides[g]:
            twins = np.flatnonzero(robot_geom & collides & (model.geom_bodyid == model.geom_bodyid[g]))
            if any(
                model.geom_type[c] == model.geom_type[g] and model.geom_dataid[c] == model.geom_dataid[g]
                and np.allclose(model.geom_size[c], model.geom_size[g]) and np.allclose(model.geom_pos[c], model.geom_pos[g])
                and np.allclose(model.geom_quat[c], model.geom_quat[g])
                for c in twins
            ):
                continue
        surface.append(g)
    return np.array(surface, dtype=np.int64)


def _robot_pairs_in_contact(model: mujoco.MjModel, qpos: np.ndarray, robot_body: np.ndarray) -> list[tuple[str, str]]:
    """Robot–robot body pairs in contact at ``qpos`` (names, each pair sorted)."""
    data = mujoco.MjData(model)
    data.qpos[:] = qpos
    mujoco.mj_forward(model, data)
    pairs = set()
    for g1, g2 in data.contact.geom[: data.ncon]:
        b1, b2 = model.geom_bodyid[g1], model.geom_bodyid[g2]
        if robot_body[b1] and robot_body[b2]:
            pairs.add(tuple(sorted((model.body(b1).name, model.body(b2).name))))
    return sorted(pairs)


def body_contacts(surface: tuple[SurfaceContact, ...]) -> tuple[BodyContact, ...]:
    """Surface contacts merged per (robot body, capsule), deepest first kept; sorted by names."""
    deepest: dict[tuple[str, str], float] = {}
    for c in surface:
        deepest[(c.robot_body, c.capsule)] = max(deepest.get((c.robot_body, c.capsule), 0.0), c.depth)
    return tuple(sorted(BodyContact(a, b, depth) for (a, b), depth in deepest.items()))


# ----------------------------------------------------------------------------- the simulation
class SimRobot:
    """The welded robot, its joint servos and the person's capsules in one MuJoCo model.

    Args:
        spec: the robot description (model file, base body and height, imitation joints, home).
        gains: servo gains of the imitation and held joints.
        timestep: physics step (s); None keeps the model's ``<option timestep>``.
        people: how many persons' capsule sets the scene holds (the evaluator shows the true and
            the perceived person; person 0 is the one :meth:`contacts` reports).

    Raises:
        SimModelError: the model is missing, does not compile, or lacks a joint/body the spec names.
    """

    def __init__(self, spec: RobotSpec, gains: PDGains, timestep: float | None = None, people: int = 1) -> None:
        if people < 1:
            raise SimModelError(f"the scene needs at least one person's capsule set, got people={people}")
        self.spec = spec
        self.gains = gains
        self.people = people
        mjs = _load_spec(spec)
        missing = [j for j in spec.imitation_joints if mjs.joint(j) is None]
        if missing:
            raise SimModelError(f"robot model {spec.model} lacks the imitation joints {missing}")
        base = _weld_base(mjs, spec)
        _add_servos(mjs, base, spec, gains)
        _add_human(mjs, people)
        if timestep is not None:
            if not 0 < timestep <= 0.05:
                raise SimModelError(f"physics timestep {timestep} s is outside (0, 0.05]")
            mjs.option.timestep = timestep
        model = _compile(mjs, spec.model)
        robot_body = model.body_rootid == model.body(spec.base_body).id  # the base's subtree
        self._qpos_home = _home_qpos(model, spec)
        #: Robot–robot body pairs touching at home: excluded from contacts (and from physics).
        self.home_contacts: tuple[tuple[str, str], ...] = tuple(
            _robot_pairs_in_contact(model, self._qpos_home, robot_body)
        )
        if self.home_contacts:
            for a, b in self.home_contacts:
                mjs.add_exclude(bodyname1=a, bodyname2=b)
            model = _compile(mjs, spec.model)
        self.model = model
        self.data = mujoco.MjData(model)
        self._index(robot_body)
        self.reset()
        self._home_pairs = self._home_geom_pairs()

    def _index(self, robot_body: np.ndarray) -> None:
        m = self.model
        jids = [m.joint(name).id for name in self.spec.imitation_joints]
        self.joint_names: tuple[str, ...] = tuple(self.spec.imitation_joints)
        self._qadr = m.jnt_qposadr[jids].copy()
        self._dadr = m.jnt_dofadr[jids].copy()
        self._act = np.array([m.actuator(_SERVO_PREFIX + name).id for name in self.joint_names])
        limited = m.jnt_limited[jids].astype(bool)
        #: Joint ranges of the imitation joints (rad); commands are clipped to them.
        self.q_min = np.where(limited, m.jnt_range[jids, 0], -np.inf)
        self.q_max = np.where(limited, m.jnt_range[jids, 1], np.inf)
        #: Home angles of the imitation joints (rad).
        self.q_home = self._qpos_home[self._qadr].copy()
        # ctrl at home: each servo's joint angle at home (every joint is 1-DoF: qposadr = its index)
        self._ctrl_home = self._qpos_home[m.jnt_qposadr[m.actuator_trnid[:, 0]]].copy()
        # feed-forward folded into the servo's ctrl: kp (q_ref + kd/kp q̇_ref + τ_ff/kp − q) − kd q̇
        kp_kd = np.array([self.gains.of(j, True) for j in self.joint_names])
        self._ff = kp_kd[:, 1] / kp_kd[:, 0]
        self._inv_kp = 1.0 / kp_kd[:, 0]
        self._inertia = np.zeros((m.nv, m.nv))  # the joint-space inertia, dense (mj_fullM)

        self._body_names = [m.body(b).name for b in range(m.nbody)]
        collides = (m.geom_contype != 0) | (m.geom_conaffinity != 0)
        robot_geom = robot_body[m.geom_bodyid]
        self._role = np.where(robot_geom & collides, _ROBOT, 0).astype(np.int8)
        #: Robot geoms a person could touch (collision geoms + visual-only surfaces such as hands).
        self.surface_geoms = _surface_geoms(m, robot_geom, collides)
        self._human_geom = np.array([[m.geom(human_body_name(c, p)).id for c in CAPSULE_NAMES] for p in range(self.people)])
        human_bodies = np.array([[m.body(human_body_name(c, p)).id for c in CAPSULE_NAMES] for p in range(self.people)])
        self._human_mocap = m.body_mocapid[human_bodies]
        self._human_bvh = m.body_bvhadr[human_bodies]  # each body's one-node BVH: its geom's box
        self._role[self._human_geom.ravel()] = _HUMAN
        self._capsule_of_geom = {int(g): c for row in self._human_geom for g, c in zip(row, CAPSULE_NAMES)}
        self._human_placed = np.zeros((self.people, len(CAPSULE_NAMES)), dtype=bool)
        #: Per person and capsule: segment endpoints (m) and radius, for the distance broad phase.
        self._human_segments = np.zeros((self.people, len(CAPSULE_NAMES), 2, 3))
        self._human_radii = np.zeros((self.people, len(CAPSULE_NAMES)))
        self._jacp = np.zeros((3, m.nv))

    def _home_geom_pairs(self) -> list[tuple[tuple[str, str], list[tuple[int, int]], float]]:
        """Per body pair touching at home: its collision geom pairs and its penetration at home (m)."""
        m, d = self.model, self.data
        pairs = []
        for a, b in self.home_contacts:
            geoms_a = [int(g) for g in np.flatnonzero((m.geom_bodyid == m.body(a).id) & (self._role == _ROBOT))]
            geoms_b = [int(g) for g in np.flatnonzero((m.geom_bodyid == m.body(b).id) & (self._role == _ROBOT))]
            geom_pairs = [(ga, gb) for ga in geoms_a for gb in geoms_b]
            depth = max((-mujoco.mj_geomDistance(m, d, ga, gb, 0.0, None) for ga, gb in geom_pairs), default=0.0)
            pairs.append(((a, b), geom_pairs, depth))
        return pairs

    # ------------------------------------------------------------------------- state
    def reset(self) -> None:
        """Back to time 0: every joint at home and still, servos at home, the person removed."""
        mujoco.mj_resetData(self.model, self.data)
        self.data.qpos[:] = self._qpos_home
        self.data.ctrl[:] = self._ctrl_home
        self.clear_human()
        mujoco.mj_forward(self.model, self.data)

    @property
    def timestep(self) -> float:
        """Physics step (s)."""
        return float(self.model.opt.timestep)

    @property
    def time(self) -> float:
        """Simulated time since :meth:`reset` (s)."""
        return float(self.data.time)

    @property
    def q(self) -> np.ndarray:
        """Imitation joint angles (rad), ``joint_names`` order (a copy)."""
        return self.data.qpos[self._qadr].copy()

    @property
    def dq(self) -> np.ndarray:
        """Imitation joint velocities (rad/s), ``joint_names`` order (a copy)."""
        return self.data.qvel[self._dadr].copy()

    # ------------------------------------------------------------------------- inputs
    def set_command(self, q: np.ndarray, dq: np.ndarray | None = None, ddq: np.ndarray | None = None) -> np.ndarray:
        """Servo the imitation joints to ``q`` (rad) with velocity feed-forward ``dq`` (rad/s) and,
        with ``gains.torque_feedforward``, the torque of the commanded acceleration ``ddq`` (rad/s²):

            τ_ff = M_II(q) q̈_ref + c_I(q, q̇)

        (I: the imitation joints; M from the last physics step's state; c = the bias forces minus
        the servos' gravity compensation: Coriolis and centrifugal torques, which a fast arm puts on
        the waist). ``q`` is clipped to the joint ranges; returns the target actually applied.
        Raises ValueError for a wrong shape or a non-finite value.
        """
        n = len(self.joint_names)
        q = np.asarray(q, dtype=float)
        dq, ddq = (np.zeros(n) if v is None else np.asarray(v, dtype=float) for v in (dq, ddq))
        if q.shape != (n,) or dq.shape != (n,) or ddq.shape != (n,):
            raise ValueError(f"q, dq and ddq must have shape ({n},), got {q.shape}, {dq.shape} and {ddq.shape}")
        if not (np.isfinite(q).all() and np.isfinite(dq).all() and np.isfinite(ddq).all()):
            raise ValueError("q, dq and ddq must be finite")
        target = np.clip(q, self.q_min, self.q_max)
        ctrl = target + self._ff * dq
        if self.gains.torque_feedforward:
            ctrl += self._inv_kp * self.feedforward_torque(ddq)
        self.data.ctrl[self._act] = ctrl
        return target

    def feedforward_torque(self, ddq: np.ndarray) -> np.ndarray:
        """τ_ff (N·m, imitation joints) of :meth:`set_command` for the acceleration ``ddq`` (rad/s²)."""
        mujoco.mj_fullM(self.model, self.data, self._inertia)
        bias = self.data.qfrc_bias[self._dadr] - self.data.qfrc_gravcomp[self._dadr]
        return self._inertia[np.ix_(self._dadr, self._dadr)] @ ddq + bias

    def set_human(self, capsules: np.ndarray, radii: np.ndarray, valid: np.ndarray, person: int = 0) -> None:
        """Place ``person``'s capsules: ``capsules[i] = (a_i, b_i)`` in the world/robot frame (m),
        radius ``radii[i]`` (m), used where ``valid[i]``; the others (and any with a non-finite or
        implausibly far endpoint) are parked far away. Takes effect at once (the person is
        kinematic: nothing in the physics depends on it)."""
        capsules = np.asarray(capsules, dtype=float)
        radii = np.asarray(radii, dtype=float)
        valid = np.asarray(valid, dtype=bool)
        n = len(CAPSULE_NAMES)
        if capsules.shape != (n, 2, 3) or radii.shape != (n,) or valid.shape != (n,):
            raise ValueError(f"expected capsules ({n}, 2, 3), radii ({n},), valid ({n},); got "
                             f"{capsules.shape}, {radii.shape}, {valid.shape}")
        usable = (
            valid
            & np.isfinite(capsules).all(axis=(1, 2))
            & (np.abs(np.nan_to_num(capsules, nan=np.inf)) <= MAX_HUMAN_COORD).all(axis=(1, 2))
            & np.isfinite(radii)
            & (radii >= 0)
        )
        if not 0 <= person < self.people:
            raise ValueError(f"person {person} is not in the scene (people={self.people})")
        for i in range(n):
            if usable[i]:
                self._place(person, i, capsules[i, 0], capsules[i, 1], float(radii[i]))
            else:
                self._park(person, i)
        self._human_placed[person] = usable
        mujoco.mj_kinematics(self.model, self.data)  # the capsules' world poses, for distances now

    def clear_human(self) -> None:
        """Remove every person from the scene (every capsule parked)."""
        for person in range(self.people):
            for i in range(len(CAPSULE_NAMES)):
                self._park(person, i)
        self._human_placed[:] = False

    def _place(self, person: int, i: int, a: np.ndarray, b: np.ndarray, radius: float) -> None:
        axis = b - a
        length = float(np.linalg.norm(axis))
        quat = np.array([1.0, 0.0, 0.0, 0.0])
        if length > _MIN_SIZE:
            mujoco.mju_quatZ2Vec(quat, axis / length)
        self._shape(person, i, max(radius, _MIN_SIZE), max(0.5 * length, _MIN_SIZE))
        self._human_segments[person, i] = a, b
        self._human_radii[person, i] = radius
        self.data.mocap_pos[self._human_mocap[person, i]] = 0.5 * (a + b)
        self.data.mocap_quat[self._human_mocap[person, i]] = quat

    def _park(self, person: int, i: int) -> None:
        self._shape(person, i, _MIN_SIZE, _MIN_SIZE)
        self.data.mocap_pos[self._human_mocap[person, i]] = _PARK
        self.data.mocap_quat[self._human_mocap[person, i]] = (1.0, 0.0, 0.0, 0.0)

    def _shape(self, person: int, i: int, radius: float, half_length: float) -> None:
        """Resize human capsule geom i, with the bounding sphere and boxes the drawing and distance
        phases use (the geom's and its body's BVH root: the geom sits at the body origin, unrotated)."""
        g = self._human_geom[person, i]
        box = (0.0, 0.0, 0.0, radius, radius, radius + half_length)
        self.model.geom_size[g, :2] = radius, half_length
        self.model.geom_rbound[g] = radius + half_length
        self.model.geom_aabb[g] = box
        if self._human_bvh[person, i] >= 0:
            self.model.bvh_aabb[self._human_bvh[person, i]] = box

    # ------------------------------------------------------------------------- physics
    def step(self, n: int = 1) -> None:
        """Advance the physics by ``n`` steps of :attr:`timestep`; positions (geoms, bodies) are then
        those of the new joint angles, so distances and contacts are taken where the robot is."""
        mujoco.mj_step(self.model, self.data, nstep=n)
        mujoco.mj_kinematics(self.model, self.data)
        mujoco.mj_comPos(self.model, self.data)

    def contacts(self, surface: tuple[SurfaceContact, ...] | None = None) -> ContactReport:
        """Body pairs in contact after the last step: robot–robot from MuJoCo's contact list (pairs
        touching at home once they press :data:`HOME_PRESS_TOLERANCE` deeper than at home) and
        robot–human from ``surface`` (default: :meth:`surface_contacts` of person 0)."""
        m, d = self.model, self.data
        robot_robot: dict[tuple[str, str], float] = {}
        names = self._body_names
        for (g1, g2), dist in zip(d.contact.geom[: d.ncon], d.contact.dist[: d.ncon]):
            if dist < 0.0 and self._role[g1] == _ROBOT and self._role[g2] == _ROBOT:
                pair = tuple(sorted((names[m.geom_bodyid[g1]], names[m.geom_bodyid[g2]])))
                robot_robot[pair] = max(robot_robot.get(pair, 0.0), -float(dist))
        for pair, geom_pairs, home_depth in self._home_pairs:
            depth = max(-mujoco.mj_geomDistance(m, d, ga, gb, 0.0, None) for ga, gb in geom_pairs)
            if depth > home_depth + HOME_PRESS_TOLERANCE:
                robot_robot[pair] = depth - home_depth  # pressed beyond the home contact
        return ContactReport(
            robot_robot=tuple(sorted(BodyContact(a, b, depth) for (a, b), depth in robot_robot.items())),
            robot_human=body_contacts(self.surface_contacts(0) if surface is None else surface),
        )

    def surface_contacts(self, person: int = 0) -> tuple[SurfaceContact, ...]:
        """Every (robot surface geom, placed capsule of ``person``) pair that penetrates, after the
        last step: ``mj_geomDistance`` (no contact forces), with the robot's own velocity at its
        deepest point along the normal, −nᵀ J_p q̇ (n from the person toward the robot).

        A broad phase comes first (``mj_geomDistance`` has none of its own): a surface geom is
        examined only if its bounding sphere comes within the capsule's radius of its segment.
        """
        placed = self._human_placed[person]
        if not placed.any() or not len(self.surface_geoms):
            return ()
        m, d = self.model, self.data
        humans = self._human_geom[person][placed]
        surface = self.surface_geoms
        a, b = self._human_segments[person][placed, 0], self._human_segments[person][placed, 1]  # (H, 3)
        axis = b - a
        centres = d.geom_xpos[surface]  # (S, 3)
        along = np.einsum("hsk,hk->hs", centres[None] - a[:, None], axis) / np.maximum((axis * axis).sum(1), 1e-12)[:, None]
        closest = a[:, None] + np.clip(along, 0.0, 1.0)[..., None] * axis[:, None]
        gap = np.linalg.norm(centres[None] - closest, axis=2)
        near = gap <= self._human_radii[person][placed, None] + m.geom_rbound[None, surface]
        found = []
        fromto = np.zeros(6)
        for hi, si in zip(*np.nonzero(near)):
            h, s = int(humans[hi]), int(surface[si])
            dist = mujoco.mj_geomDistance(m, d, s, h, 0.0, fromto)
            if dist >= 0.0:
                continue
            point = fromto[:3].copy()
            toward_person = fromto[3:] - point
            length = float(np.linalg.norm(toward_person))
            if length > 1e-9:  # fromto runs from the robot's surface to the person's, signed by dist
                normal = -toward_person / (length * np.sign(dist))
            else:  # touching at one point: fall back to the geom centres
                normal = d.geom_xpos[s] - d.geom_xpos[h]
                normal = normal / max(float(np.linalg.norm(normal)), 1e-12)
            body = int(m.geom_bodyid[s])
            mujoco.mj_jac(m, d, self._jacp, None, point, body)
            closing = -float(normal @ (self._jacp @ d.qvel))
            found.append(SurfaceContact(self._body_names[body], self._capsule_of_geom[h], -float(dist), point,
                                        normal, closing))
        return tuple(found)
