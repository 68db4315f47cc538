"""The evaluator's lockstep loop: perceived person → safety → MuJoCo, judged against the true person.

:func:`run_episode` steps at the safety rate. At each control step t_k:

1. MuJoCo's person 0 is the *true* person at t_k (:class:`~safemimic.evaluate.person.TruePerson`);
   person 1, drawn translucent, is the perceived one the barrier holds;
2. the newest *available* perceived state (``HumanTrack.t`` ≤ t_k: its frame time plus the
   camera latency; zero-order hold, stale after ``safety.human_timeout_s``; capsules that turn
   invalid held by :class:`~services.safety.human_memory.HumanMemory`, as in the safety service)
   sets the barrier's external capsules and q_nom, extrapolated between frames by its rate and that
   rate fed forward as the service does (:mod:`services.safety.nominal`; q_cbf while stale or lost);
3. one CBF-QP step gives q_cbf and u*, the MuJoCo executor servos to them for one control period;
   the step knows the robot's joints as the service does, from a JointState sampled every
   ``executor.state_rate_hz`` period and extrapolated by its velocity (a stop brings q_cbf
   there: :mod:`services.safety.filter`);
4. the outcome is measured: MuJoCo's robot–robot contacts, robot–human contacts with the true
   person (every robot surface, with the robot's own closing speed at each contact) and with the
   perceived one, and :class:`~safemimic.evaluate.truth.TruthProbe`'s clearances at q_sim.

``enforce=False`` is the same loop with the CBF rows left out of the QP (u* = clip(u_ref)); every
h is still evaluated. Time is source time from the first frame (s); the loop is deterministic for
a given input.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from safemimic.evaluate.person import HumanTrack, TruePerson
from safemimic.evaluate.truth import CLOSING_SPEED, TruthProbe, fixed_bodies
from services.executor.contacts import ContactReport, ContactTally
from services.executor.mujoco.contacts import body_contacts
from services.executor.mujoco.executor import MujocoExecutor
from services.executor.mujoco.model import PDGains
from services.safety.assembly import SafetyPipeline, build_pipeline, make_geometry
from services.safety.human_memory import HumanMemory
from services.safety.nominal import NominalTrack, frame_stamp
from services.safety.kinematics import RobotKinematics
from services.safety.pairs import PairSet
from shared.config import StackConfig
from shared.messages import SafetyMode

#: Modes in the order of :attr:`Episode.mode` codes.
MODES: tuple[SafetyMode, ...] = tuple(SafetyMode)
#: MuJoCo's person 0 is the true person, person 1 the perceived one.
TRUE_PERSON, PERCEIVED_PERSON = 0, 1


@dataclass
class Episode:
    """What one run did, per control step k at time ``t[k]`` (N steps, m monitored pairs, M truth pairs).

    The filter's own view: ``q_nom``/``q_cbf``/``u`` (N, 8) rad, rad/s (retargeted target,
    commanded safe target and velocity); ``h`` (N, m) m, every monitored pair's barrier at the
    step's start against the perceived person as measured (NaN: capsule missing; with
    ``safety.human_predict_s`` the rows hold that person swept ahead, whose h is at most this);
    ``active`` (N, m) pair rows binding in the QP; ``binding`` (N,) some QP row binds (a pair or a joint barrier) or the speed and separation cap
    slowed the reference (``safety.human_speed_mps``): a constraint shaped the motion; ``mode``
    (N,) index into :data:`MODES`; ``qp_ms`` (N,) solve time (wall clock); ``human`` (N,) index
    of the perceived state in force (−1: none yet); ``settled`` (N,) the step first brought q_cbf
    to the robot's joints (a stop: the step then ran from q_cbf[k] − Δt u*[k], not from
    q_cbf[k−1]); ``stopped`` (N,) the step was a protective stop (:attr:`StepResult.protective_stop`),
    ``backing_out`` (N,) one that backed an arm out of a still person; ``person_lost`` (N,) the step
    aimed at q_cbf instead of imitating because the person's state was stale
    (``safety.human_timeout_s``) or a capsule was lost (``safety.lost_human_hold_s``, as the safety
    service does); ``pairs`` names the columns of ``h``.

    The world: ``q_sim``/``dq_sim`` (N, 8) simulated joints after the step; ``qpos`` (N, nq) the
    whole MuJoCo pose; ``robot_capsules`` (N, 7, 2, 3) the CBF capsules at q_sim;
    ``true_clearance``/``true_rate``/``true_rate_commanded`` (N, M) per truth row
    (:attr:`TruthProbe.names`; the rate at q̇_sim and at the command u*),
    ``truth_is_self`` (M,) which of them are robot–robot rows;
    ``true_contact`` (N,) some robot surface penetrates the true person, ``true_depth`` (N,) m the
    deepest, ``robot_caused`` (N,) the robot closed some touching pair faster than
    :data:`CLOSING_SPEED`, ``robot_caused_commanded`` (N,) such a pair that the command u* itself
    closes faster than that too (at the robot's pose), ``closing_speed`` (N,) m/s the fastest
    closing of a touching pair (0: none), ``fixed_contact`` (N,) some touching robot body is one no imitation
    joint moves (:func:`~safemimic.evaluate.truth.fixed_bodies`: no controller avoids it);
    ``torque_saturated`` (N,) some imitation joint's motor gave its whole torque at the step's last
    physics step (:attr:`~services.executor.mujoco.sim.SimRobot.saturated`: the servo asked for more than
    the motor has);
    ``contact_steps`` (N, 3) robot–robot, robot–perceived person and
    robot–true person contacts after the step; ``tally``/``true_tally`` the contacts per pair
    (robot–robot with the perceived person / the true person's robot–human ones).
    """

    enforce: bool
    t: np.ndarray
    q_nom: np.ndarray
    q_cbf: np.ndarray
    u: np.ndarray
    q_sim: np.ndarray
    dq_sim: np.ndarray
    qpos: np.ndarray
    robot_capsules: np.ndarray
    h: np.ndarray
    active: np.ndarray
    binding: np.ndarray
    mode: np.ndarray
    qp_ms: np.ndarray
    human: np.ndarray
    settled: np.ndarray
    stopped: np.ndarray
    backing_out: np.ndarray
    person_lost: np.ndarray
    true_clearance: np.ndarray
    true_rate: np.ndarray
    true_rate_commanded: np.ndarray
    true_contact: np.ndarray
    true_depth: np.ndarray
    robot_caused: np.ndarray
    robot_caused_commanded: np.ndarray
    closing_speed: np.ndarray
    fixed_contact: np.ndarray
    torque_saturated: np.ndarray
    contact_steps: np.ndarray
    tally: ContactTally
    true_tally: ContactTally
    home_contacts: tuple[tuple[str, str], ...]
    pairs: PairSet
    truth_is_self: np.ndarray


def make_executor(conf: StackConfig, kinematics: RobotKinematics) -> MujocoExecutor:
    """The MuJoCo executor of the evaluated robot, advancing one safety period per tick, with the
    true and the perceived person in its scene."""
    return MujocoExecutor(kinematics.spec, PDGains.from_config(conf.executor), 1.0 / conf.safety.rate_hz, people=2)


def per_pair(values: np.ndarray, row_pair: np.ndarray, n_pairs: int, reduce: np.ufunc) -> np.ndarray:
    """Per-pair reduction (``np.fmin``: min ignoring NaN, ``np.logical_or``: any) of per-row values."""
    if len(row_pair) == n_pairs:
        return values
    out = np.full(n_pairs, np.nan if reduce is np.fmin else False, dtype=values.dtype)
    reduce.at(out, row_pair, values)
    return out


def _empty_episode(enforce: bool, n: int, safety: SafetyPipeline, truth: TruthProbe, nq: int,
                   home_contacts: tuple[tuple[str, str], ...], dt: float) -> Episode:
    m, j, mt = len(safety.pairs), len(safety.kinematics.joint_names), len(truth.names)
    return Episode(
        enforce=enforce, t=np.arange(n) * dt,
        q_nom=np.empty((n, j)), q_cbf=np.empty((n, j)), u=np.empty((n, j)), q_sim=np.empty((n, j)),
        dq_sim=np.empty((n, j)), qpos=np.empty((n, nq)), robot_capsules=np.empty((n, 7, 2, 3)),
        h=np.empty((n, m)), active=np.zeros((n, m), bool), binding=np.zeros(n, bool), mode=np.empty(n, np.int8),
        qp_ms=np.empty(n), human=np.full(n, -1, np.int64), settled=np.zeros(n, bool), stopped=np.zeros(n, bool),
        backing_out=np.zeros(n, bool), person_lost=np.zeros(n, bool),
        true_clearance=np.empty((n, mt)), true_rate=np.empty((n, mt)), true_rate_commanded=np.empty((n, mt)),
        true_contact=np.zeros(n, bool), true_depth=np.zeros(n), robot_caused=np.zeros(n, bool),
        robot_caused_commanded=np.zeros(n, bool), closing_speed=np.zeros(n), fixed_contact=np.zeros(n, bool),
        torque_saturated=np.zeros(n, bool),
        contact_steps=np.zeros((n, 3), np.int64),
        tally=ContactTally(), true_tally=ContactTally(), home_contacts=home_contacts,
        pairs=safety.pairs, truth_is_self=truth.is_self,
    )


class MeasuredBarrier:
    """The pipeline's pair barrier again (same geometry, pairs, radii and person margin), holding the
    perceived person as measured: h at the filter's state, where the filter's rows hold the person
    swept ahead (``safety.human_predict_s``). It shares the pipeline's kinematics, as
    :class:`~safemimic.evaluate.truth.TruthProbe` does: the filter computes its own forward
    kinematics at the start of every step."""

    def __init__(self, conf: StackConfig, safety: SafetyPipeline) -> None:
        self._kinematics = safety.kinematics
        self.barrier = make_geometry(conf, safety.pairs, self._kinematics)
        self._params = safety.filter.params

    def h(self, q: np.ndarray) -> np.ndarray:
        """(m,) every row's h (m) at joint angles ``q`` (NaN: capsule missing)."""
        endpoints, jacobians = self._kinematics.compute(q)
        return self.barrier.evaluate(endpoints, jacobians, self._params.gamma, self._params.phi).h


def run_episode(
    conf: StackConfig,
    human: HumanTrack,
    person: TruePerson,
    enforce: bool,
    kinematics: RobotKinematics | None = None,
    progress: Callable[[int], None] | None = None,
) -> Episode:
    """Run the lockstep loop over ``person.t`` (the control steps) with (``enforce``) or without
    the CBF rows; ``human`` is the perceived person."""
    safety: SafetyPipeline = build_pipeline(conf, kinematics=kinematics)
    dt = 1.0 / conf.safety.rate_hz
    safety.warm_up(dt)  # numba and the QP's first setup, as the service does before its loop
    safety.filter.enforce = enforce
    executor = make_executor(conf, safety.kinematics)
    sim = executor.sim
    truth = TruthProbe(conf, safety.kinematics)
    fixed = fixed_bodies(sim.model, safety.kinematics.joint_names)
    ep = _empty_episode(enforce, len(person.t), safety, truth, sim.model.nq, sim.home_contacts, dt)
    n_rows = len(safety.pairs)
    row_pair = safety.barrier.row_pair  # a geometry may monitor a pair with several rows (spheres)
    use_velocity, predict_s = conf.safety.human_velocity_term, conf.safety.human_predict_s
    # the person swept ahead (human_predict_s) is the rows' hypothesis: h is reported against the
    # perceived person as measured, by a second barrier of the same geometry
    seen = None if predict_s <= 0.0 else MeasuredBarrier(conf, safety)
    timeout, hold = conf.safety.human_timeout_s, conf.safety.lost_human_hold_s
    memory = HumanMemory()
    nominal = NominalTrack(safety.filter.q_cbf.copy())  # no human yet: hold
    feedforward, horizon, path = conf.safety.feedforward, conf.safety.extrapolate_max_s, conf.safety.target_path
    newest, applied, stale = -1, -1, False
    # the executor's JointState as the service receives it: published on the executor service's schedule
    # (every state period, keeping its phase), extrapolated by dq·age
    state_period, next_state = 1.0 / conf.executor.state_rate_hz, -math.inf
    executor.start()
    for k, t in enumerate(ep.t):
        if t >= next_state:
            sampled, q_seen, dq_seen = t, sim.q, sim.dq
            next_state = max(next_state + state_period, t + 0.5 * state_period)
        q_robot = q_seen + dq_seen * (t - sampled)
        sim.set_human(person.capsules[k], person.radii, person.capsule_valid[k], TRUE_PERSON)
        while newest + 1 < len(human.t) and human.t[newest + 1] <= t + 1e-9:
            newest += 1
        if newest >= 0:
            state = human.states[newest]
            now_stale = t - human.t[newest] > timeout
            if newest != applied or now_stale != stale:
                memory.update(state, human.t[newest], hold)
                safety.barrier.set_external(*memory.capsules(safety.pairs.n_external, use_velocity, predict_s, now_stale))
                if seen is not None:
                    seen.barrier.set_external(*memory.capsules(safety.pairs.n_external, use_velocity, stale=now_stale))
                if not now_stale:  # stale: the safety service stops imitating (q_nom = q_cbf)
                    r = safety.retargeter
                    nominal.update(*r.track(state), frame_stamp(state), human.t[newest], horizon, r.q_min, r.q_max,
                                   path)
                if newest != applied:
                    sim.set_human(state.capsules, state.capsule_radii, state.capsule_valid, PERCEIVED_PERSON)
                applied, stale = newest, now_stale
        q_nom, dq_nom = nominal.at(t)
        h_seen = None if seen is None else seen.h(safety.filter.q_cbf)
        ep.person_lost[k] = stale or memory.lost
        if ep.person_lost[k]:
            result = safety.filter.step(safety.filter.q_cbf.copy(), dt, q_robot=q_robot)
        else:
            result = safety.filter.step(q_nom, dt, dq_nom if feedforward else None, q_robot)
        executor.apply_command(result.q_cbf, result.u, result.ddq, result.protective_stop)
        executor.tick()

        touching = sim.surface_contacts(TRUE_PERSON)
        report = sim.contacts(sim.surface_contacts(PERCEIVED_PERSON))
        true_report = ContactReport(robot_robot=report.robot_robot, robot_human=body_contacts(touching))
        ep.tally.update(report)
        ep.true_tally.update(true_report)
        ep.q_sim[k], ep.dq_sim[k], ep.qpos[k] = sim.q, sim.dq, sim.data.qpos
        ep.torque_saturated[k] = sim.saturated.any()
        step = truth.measure(ep.q_sim[k], ep.dq_sim[k], person.capsules[k], person.radii, person.capsule_valid[k],
                             result.u)
        ep.true_clearance[k], ep.true_rate[k], ep.robot_capsules[k] = step.clearance, step.rate, step.robot
        ep.true_rate_commanded[k] = step.commanded
        if touching:
            ep.true_contact[k] = True
            ep.true_depth[k] = max(c.depth for c in touching)
            closing = [c for c in touching if c.closing_speed > CLOSING_SPEED]
            ep.robot_caused[k] = bool(closing)
            ep.robot_caused_commanded[k] = any(sim.commanded_closing_speed(c, result.u) > CLOSING_SPEED for c in closing)
            ep.closing_speed[k] = max(0.0, max(c.closing_speed for c in touching))
            ep.fixed_contact[k] = any(c.robot_body in fixed for c in touching)

        rows = result.rows
        ep.q_nom[k], ep.q_cbf[k], ep.u[k] = q_nom, result.q_cbf, result.u
        ep.h[k] = per_pair(rows.h if h_seen is None else h_seen, row_pair, n_rows, np.fmin)
        if enforce and result.active_rows:
            ep.active[k] = per_pair(rows.enabled & (rows.A @ result.u - rows.b <= 1e-6), row_pair, n_rows, np.logical_or)
            ep.binding[k] = True
        ep.binding[k] |= result.speed_capped
        ep.mode[k] = MODES.index(result.mode)
        ep.qp_ms[k] = result.qp_time_s * 1e3
        ep.human[k] = newest
        ep.settled[k], ep.stopped[k], ep.backing_out[k] = result.settled, result.protective_stop, result.backing_out
        ep.contact_steps[k] = len(report.robot_robot), len(report.robot_human), len(true_report.robot_human)
        if progress is not None:
            progress(k + 1)
    executor.stop()
    return ep
