"""MuJoCo simulation of the robot with the person in its world (architecture §1, §7, §10).

:class:`SimRobot` is the simulation core shared by the executor service and the offline
evaluator: no Zenoh, no clock, deterministic for the same calls. It holds the compiled scene
(:func:`~services.executor.mujoco.model.build_model`: the welded robot with one servo per joint and
the people's mocap capsules) and its state; it takes joint commands (:meth:`SimRobot.set_command`:
the 8 imitation joints' servos follow them with a velocity and, optionally, a torque feed-forward;
every other joint is held at home) and the people's capsules (:meth:`SimRobot.set_human`: pose,
length and radius; the capsule's size is changed in the compiled model together with its bounding
sphere and boxes, the geom's and its body's BVH root), steps the physics and reports the contacts
(measured by :class:`~services.executor.mujoco.contacts.ContactMeter`).
Units SI: metres, radians, seconds, newton-metres.
"""

from __future__ import annotations

import math

import mujoco
import numpy as np

from services.executor.contacts import ContactReport, SurfaceContact
from services.executor.mujoco.contacts import ContactMeter, body_contacts
from services.executor.mujoco.model import PARK_POSITION, PDGains, build_model, human_body_name, servo_name
from shared.names import CAPSULE_NAMES
from shared.robot_spec import RobotSpec

__all__ = ["MAX_HUMAN_COORD", "SimRobot"]

#: Capsule endpoints farther than this from the robot (m) are treated as invalid.
MAX_HUMAN_COORD = 100.0
#: Smallest radius / half-length given to a human capsule (m): MuJoCo needs positive sizes.
_MIN_SIZE = 1e-4


#: Below this commanded speed (rad/s) the friction feed-forward fades out (tanh): no chatter at rest.
FRICTION_SPEED = 0.05


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
        built = build_model(spec, gains, timestep, people)
        self.spec = spec
        self.gains = gains
        self.people = people
        self._qpos_home = built.qpos_home
        #: Robot–robot body pairs touching at home: excluded from contacts (and from physics).
        self.home_contacts: tuple[tuple[str, str], ...] = built.home_contacts
        self.model = built.model
        self.data = mujoco.MjData(self.model)
        self._index()
        self.reset()
        self._meter = ContactMeter(self.model, self.data, built.robot_body, self._human_geom, self.home_contacts)
        #: Robot geoms a person could touch (collision geoms + visual-only surfaces such as hands).
        self.surface_geoms: np.ndarray = self._meter.surface_geoms

    def _index(self) -> None:
        m = self.model
        jids = [m.joint(name).id for name in self.spec.imitation_joints]
        self.joint_names: tuple[str, ...] = tuple(self.spec.imitation_joints)
        self._qadr = m.jnt_qposadr[jids].copy()
        self._dadr = m.jnt_dofadr[jids].copy()
        self._act = np.array([m.actuator(servo_name(name)).id for name in self.joint_names])
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
        self._kd = kp_kd[:, 1]
        self._inv_kp = 1.0 / kp_kd[:, 0]
        self._damping = math.nan  # the servos' kd scale in force (reset: 1)
        # the servos holding every other joint at home, their dofs and 1/kp (their share of the feed-forward)
        self._held = np.setdiff1d(np.arange(m.nu), self._act)
        self._held_dof = m.jnt_dofadr[m.actuator_trnid[self._held, 0]]
        self._held_inv_kp = 1.0 / m.actuator_gainprm[self._held, 0]
        self._friction = m.dof_frictionloss[self._dadr].copy()  # Coulomb friction of the imitation joints (N·m)
        #: The imitation joints' motor torque limits (N·m, the joints' actuatorfrcrange; ∞ where none).
        limit = np.abs(m.jnt_actfrcrange[jids]).min(axis=1)
        self.torque_limit = np.where(m.jnt_actfrclimited[jids].astype(bool), limit, np.inf)
        self._inertia = np.zeros((m.nv, m.nv))  # the joint-space inertia, dense (mj_fullM)

        self._human_geom = np.array([[m.geom(human_body_name(c, p)).id for c in CAPSULE_NAMES] for p in range(self.people)])
        human_bodies = np.array([[m.body(human_body_name(c, p)).id for c in CAPSULE_NAMES] for p in range(self.people)])
        self._human_mocap = m.body_mocapid[human_bodies]
        self._human_bvh = m.body_bvhadr[human_bodies]  # each body's one-node BVH: its geom's box
        self._human_placed = np.zeros((self.people, len(CAPSULE_NAMES)), dtype=bool)
        #: Per person and capsule: segment endpoints (m) and radius, for the distance broad phase.
        self._human_segments = np.zeros((self.people, len(CAPSULE_NAMES), 2, 3))
        self._human_radii = np.zeros((self.people, len(CAPSULE_NAMES)))

    # ------------------------------------------------------------------------- state
    def reset(self) -> None:
        """Back to time 0: every joint at home and still, servos at home, the person removed."""
        mujoco.mj_resetData(self.model, self.data)
        self.data.qpos[:] = self._qpos_home
        self.data.ctrl[:] = self._ctrl_home
        self._set_damping(1.0)
        self._ctrl_end, self._dq_ref, self._lead_left = self._ctrl_home[self._act].copy(), np.zeros(len(self._act)), 0.0
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

    @property
    def saturated(self) -> np.ndarray:
        """(n,) bool: the imitation joints whose motor gave its whole torque (:attr:`torque_limit`) at
        the last physics step: the servo asked for more (its error, the feed-forward, gravity) than the
        motor has, so the joint did not move as commanded."""
        return np.abs(self.data.qfrc_actuator[self._dadr]) >= self.torque_limit * (1.0 - 1e-9)

    # ------------------------------------------------------------------------- inputs
    def set_command(self, q: np.ndarray, dq: np.ndarray | None = None, ddq: np.ndarray | None = None,
                    lead_s: float = 0.0, stop: bool = False) -> np.ndarray:
        """Servo the imitation joints to ``q`` (rad) with velocity feed-forward ``dq`` (rad/s) and,
        with ``gains.torque_feedforward``, the torque of the commanded acceleration ``ddq`` (rad/s²)
        on every servo, the imitation joints' (I) and those holding the other joints at home (H):

            τ_ff = M_{·I}(q) q̈_ref + c(q, q̇) + f_I tanh(q̇_ref / FRICTION_SPEED)        (rows I and H)

        (M from the last physics step's state; c = the bias forces minus the servos' gravity
        compensation: Coriolis and centrifugal torques, which a fast arm puts on the waist; f_I the
        imitation joints' Coulomb friction (the model's frictionloss), in the direction of the
        commanded velocity: without it a slow motion lags by f/kp, 0.002 rad on an arm). The
        held joints' share is the reaction of the imitation joints' acceleration (an arm swinging
        forward twists the waist yaw and the shoulder yaw): without it they give way by up to
        0.03 rad, and their motion couples back into the imitation joints.

        ``lead_s``: ``q`` is where the joints should be ``lead_s`` seconds from now (a safety command
        q_cbf⁺ = q_cbf + Δt u* is the end of its control period): over the next physics steps the
        servos' position reference is that trajectory, q − (time left) · dq, reaching ``q`` after
        ``lead_s`` and staying there. A PD servo aimed at the end of the period from its start runs
        ahead of the command by ≈ kp Δt |dq| of extra torque (0.01 rad at 6 rad/s on a shoulder).
        ``stop``: the command is a protective stop: until a command that is not, the imitation
        joints' servos damp with kd × ``gains.stop_damping`` (and feed ``dq`` forward through that
        kd, so the damping resists only the joints' departure from the commanded velocity:
        τ = kp (q_ref − q) + kd s (q̇_ref − q̇)).
        ``q`` is clipped to the joint ranges; returns the target actually applied (the clipped q).
        Raises ValueError for a wrong shape, a non-finite value or a negative ``lead_s``.
        """
        n = len(self.joint_names)
        q = np.asarray(q, dtype=float)
        dq, ddq = (np.zeros(n) if v is None else np.asarray(v, dtype=float) for v in (dq, ddq))
        if q.shape != (n,) or dq.shape != (n,) or ddq.shape != (n,):
            raise ValueError(f"q, dq and ddq must have shape ({n},), got {q.shape}, {dq.shape} and {ddq.shape}")
        if not (np.isfinite(q).all() and np.isfinite(dq).all() and np.isfinite(ddq).all()):
            raise ValueError("q, dq and ddq must be finite")
        if not (lead_s >= 0.0 and math.isfinite(lead_s)):
            raise ValueError(f"lead_s must be finite and >= 0, got {lead_s}")
        self._set_damping(self.gains.stop_damping if stop else 1.0)
        target = np.clip(q, self.q_min, self.q_max)
        ctrl = target + self._ff * dq
        if self.gains.torque_feedforward:
            imitation, held = self.feedforward_torque(ddq, dq)
            ctrl += self._inv_kp * imitation
            self.data.ctrl[self._held] = self._ctrl_home[self._held] + self._held_inv_kp * held
        self._ctrl_end, self._dq_ref, self._lead_left = ctrl, dq.copy(), lead_s
        self.data.ctrl[self._act] = ctrl - lead_s * dq
        return target

    def _set_damping(self, scale: float) -> None:
        """The imitation joints' servos damp with kd × ``scale`` (MuJoCo's position servo: bias
        −kd q̇ in ``actuator_biasprm[:, 2]``), their velocity feed-forward kd s/kp q̇_ref with it."""
        if scale == self._damping:
            return
        self.model.actuator_biasprm[self._act, 2] = -scale * self._kd
        self._ff = scale * self._kd * self._inv_kp
        self._damping = scale

    def feedforward_torque(self, ddq: np.ndarray, dq: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """τ_ff (N·m) of :meth:`set_command` for the acceleration ``ddq`` (rad/s²) and velocity ``dq``
        (rad/s): on the imitation joints (8,) and on the held joints (servo order of the others)."""
        mujoco.mj_fullM(self.model, self.data, self._inertia)
        bias = self.data.qfrc_bias - self.data.qfrc_gravcomp
        imitation = (self._inertia[np.ix_(self._dadr, self._dadr)] @ ddq + bias[self._dadr]
                     + self._friction * np.tanh(dq / FRICTION_SPEED))
        held = self._inertia[np.ix_(self._held_dof, self._dadr)] @ ddq + bias[self._held_dof]
        return imitation, held

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
        self.data.mocap_pos[self._human_mocap[person, i]] = PARK_POSITION
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
        """Advance the physics by ``n`` steps of :attr:`timestep` (the servos' reference moving along
        the command's ``lead_s`` trajectory, :meth:`set_command`); positions (geoms, bodies) are then
        those of the new joint angles, so distances and contacts are taken where the robot is."""
        h = self.timestep
        while n > 0 and self._lead_left > 0.0:
            self.data.ctrl[self._act] = self._ctrl_end - self._lead_left * self._dq_ref
            mujoco.mj_step(self.model, self.data)
            self._lead_left = self._lead_left - h if self._lead_left > 1.5 * h else 0.0
            if self._lead_left == 0.0:
                self.data.ctrl[self._act] = self._ctrl_end
            n -= 1
        if n > 0:
            mujoco.mj_step(self.model, self.data, nstep=n)
        mujoco.mj_kinematics(self.model, self.data)
        mujoco.mj_comPos(self.model, self.data)

    def contacts(self, surface: tuple[SurfaceContact, ...] | None = None) -> ContactReport:
        """Body pairs in contact after the last step: robot–robot from MuJoCo's contact list (pairs
        touching at home once they press
        :data:`~services.executor.mujoco.contacts.HOME_PRESS_TOLERANCE` deeper than at home) and
        robot–human from ``surface`` (default: :meth:`surface_contacts` of person 0)."""
        return ContactReport(
            robot_robot=self._meter.robot_robot(self.data),
            robot_human=body_contacts(self.surface_contacts(0) if surface is None else surface),
        )

    def surface_contacts(self, person: int = 0) -> tuple[SurfaceContact, ...]:
        """Every (robot surface geom, placed capsule of ``person``) pair that penetrates, after the
        last step, with the robot's closing speed
        (:meth:`~services.executor.mujoco.contacts.ContactMeter.robot_human`)."""
        return self._meter.robot_human(self.data, person, self._human_placed[person], self._human_segments[person],
                                       self._human_radii[person])

    def commanded_closing_speed(self, contact: SurfaceContact, dq: np.ndarray) -> float:
        """The speed (m/s) at which ``contact``'s robot point would move into the person if the
        imitation joints moved at ``dq`` (8,) rad/s and every other joint stood still, from the
        current pose: −nᵀ J_p[:, I] dq (positive: closing). With the commanded velocity u* it tells
        what the command did at a contact, apart from the servos trailing or settling behind it."""
        qvel = np.zeros(self.model.nv)
        qvel[self._dadr] = dq
        return self._meter.closing_speed(self.data, contact, qvel)
