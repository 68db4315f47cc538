"""The evaluator's input and its lockstep loop: perception → safety → MuJoCo, no Zenoh, no clock.

:func:`open_input` reads the configured skeleton source exactly as the perception service does
(``open_source``: a DESIGN §6 recording, normalised and placed, or a scripted scenario) and
:func:`perceive` runs the perception pipeline over every frame once, so both runs see the same
human. :func:`run_episode` then steps at the safety rate: at each control step the newest human
state (zero-order hold, stale after ``safety.human_timeout_s``; capsules that turn invalid held
by :class:`~services.safety.human_memory.HumanMemory` — both like the safety service) sets the
barrier's external capsules and q_nom (q_cbf while stale or lost), one CBF-QP step gives q_cbf and
u*, and the MuJoCo executor servos to them for one control period and reports its contacts.
``enforce=False`` is the same loop with the CBF rows left out of the QP (u* = clip(u_ref)); every
h is still evaluated.

Time is source time from the first frame (s); the loop is deterministic for a given input.
"""

from __future__ import annotations

import itertools
import threading
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from services.executor.contacts import ContactTally
from services.executor.mujoco_executor import MujocoExecutor
from services.executor.sim import PDGains
from services.perception.pipeline import PerceptionCounters, PerceptionPipeline
from services.perception.sources import open_source
from services.perception.stream import SkeletonFrame
from services.safety.assembly import SafetyPipeline, build_pipeline
from services.safety.kinematics import RobotKinematics
from services.safety.pairs import PairSet
from services.safety.human_memory import HumanMemory
from services.safety.service import warm_up
from shared.config import StackConfig
from shared.messages import HumanState, SafetyMode

#: Modes in the order of :attr:`Episode.mode` codes.
MODES: tuple[SafetyMode, ...] = tuple(SafetyMode)


@dataclass(frozen=True)
class EvaluationInput:
    """The skeleton frames to evaluate (robot frame, times from the source) and where they came from."""

    name: str
    frames: tuple[SkeletonFrame, ...]
    fps: float

    @property
    def seconds(self) -> float:
        """Evaluated duration (s): first frame to one frame period after the last."""
        return self.frames[-1].t - self.frames[0].t + 1.0 / self.fps


def open_input(conf: StackConfig, seconds: float | None = None) -> EvaluationInput:
    """The frames of ``conf.perception``'s source (one pass; with ``seconds``, looped or cut to it).

    Raises :class:`~services.perception.sources.SourceUnavailable` (bad file, unknown scenario)
    and ValueError for a non-positive ``seconds``.
    """
    if seconds is not None and not seconds > 0:
        raise ValueError(f"seconds must be > 0, got {seconds}")
    perception = conf.perception.model_copy(update={"realtime": False, "loop": seconds is not None})
    source = open_source(perception)
    frames = source.frames(threading.Event())
    if seconds is not None:
        first = next(frames)
        frames = itertools.chain([first], itertools.takewhile(lambda f: f.t - first.t < seconds - 1e-9, frames))
    return EvaluationInput(name=source.name, frames=tuple(frames), fps=float(source.fps))


@dataclass(frozen=True)
class HumanTrack:
    """The perception pipeline's output for every frame: ``t`` (F,) s from the first frame."""

    t: np.ndarray
    states: tuple[HumanState, ...]
    counters: PerceptionCounters


def perceive(conf: StackConfig, source: EvaluationInput) -> HumanTrack:
    """Run the perception pipeline (filter → angles + capsules) over every frame, in order."""
    pipeline = PerceptionPipeline(conf.perception, conf.human)
    t0 = source.frames[0].t
    states = tuple(pipeline.step(frame).to_message(stamp=frame.t - t0) for frame in source.frames)
    return HumanTrack(t=np.array([s.stamp for s in states]), states=states, counters=pipeline.counters)


@dataclass
class Episode:
    """What one run did, per control step k at time ``t[k]`` (N steps, m monitored pairs).

    ``q_nom``/``q_cbf``/``u``/``q_sim`` (N, 8) rad, rad/s: retargeted target, commanded safe
    target and velocity, simulated joints after the step; ``qpos`` (N, nq) the whole MuJoCo pose;
    ``h`` (N, m) m, every pair's barrier at the step's start (NaN: human capsule missing);
    ``active`` (N, m) pair rows binding in the QP; ``binding`` (N,) some QP row binds (a pair or a
    joint barrier of the robot description); ``mode`` (N,) index into :data:`MODES`;
    ``qp_ms`` (N,) solve time (wall clock); ``human`` (N,) index of the human state in force
    (−1: none yet); ``contact_steps`` (N, 2) robot–robot and robot–human contacts after the step;
    ``pairs`` names the columns of ``h``.
    """

    enforce: bool
    t: np.ndarray
    q_nom: np.ndarray
    q_cbf: np.ndarray
    u: np.ndarray
    q_sim: np.ndarray
    qpos: np.ndarray
    h: np.ndarray
    active: np.ndarray
    binding: np.ndarray
    mode: np.ndarray
    qp_ms: np.ndarray
    human: np.ndarray
    contact_steps: np.ndarray
    tally: ContactTally
    home_contacts: tuple[tuple[str, str], ...]
    pairs: PairSet


def make_executor(conf: StackConfig, kinematics: RobotKinematics) -> MujocoExecutor:
    """The MuJoCo executor of the evaluated robot, advancing one safety period per tick."""
    return MujocoExecutor(kinematics.spec, PDGains.from_config(conf.executor), 1.0 / conf.safety.rate_hz)


def per_pair(values: np.ndarray, row_pair: np.ndarray, n_pairs: int, reduce: np.ufunc) -> np.ndarray:
    """Per-pair reduction (``np.fmin``: min ignoring NaN, ``np.logical_or``: any) of per-row values."""
    if len(row_pair) == n_pairs:
        return values
    out = np.full(n_pairs, np.nan if reduce is np.fmin else False, dtype=values.dtype)
    reduce.at(out, row_pair, values)
    return out


def run_episode(
    conf: StackConfig,
    human: HumanTrack,
    seconds: float,
    enforce: bool,
    kinematics: RobotKinematics | None = None,
    progress: Callable[[int], None] | None = None,
) -> Episode:
    """Run the lockstep loop for ``seconds`` (s) with (``enforce``) or without the CBF rows."""
    safety: SafetyPipeline = build_pipeline(conf, kinematics=kinematics)
    dt = 1.0 / conf.safety.rate_hz
    warm_up(safety, dt)  # numba and the QP's first setup, as the service does before its loop
    safety.filter.enforce = enforce
    executor = make_executor(conf, safety.kinematics)
    sim = executor.sim
    n_steps, n_rows, n_joints = max(1, round(seconds / dt)), len(safety.pairs), len(safety.kinematics.joint_names)
    row_pair = safety.barrier.row_pair  # a geometry may monitor a pair with several rows (spheres)
    ep = Episode(
        enforce=enforce,
        t=np.arange(n_steps) * dt,
        q_nom=np.empty((n_steps, n_joints)),
        q_cbf=np.empty((n_steps, n_joints)),
        u=np.empty((n_steps, n_joints)),
        q_sim=np.empty((n_steps, n_joints)),
        qpos=np.empty((n_steps, sim.model.nq)),
        h=np.empty((n_steps, n_rows)),
        active=np.zeros((n_steps, n_rows), bool),
        binding=np.zeros(n_steps, bool),
        mode=np.empty(n_steps, np.int8),
        qp_ms=np.empty(n_steps),
        human=np.full(n_steps, -1, np.int64),
        contact_steps=np.zeros((n_steps, 2), np.int64),
        tally=ContactTally(),
        home_contacts=sim.home_contacts,
        pairs=safety.pairs,
    )
    use_velocity = conf.safety.human_velocity_term
    timeout, hold = conf.safety.human_timeout_s, conf.safety.lost_human_hold_s
    memory = HumanMemory()
    q_nom = safety.filter.q_cbf.copy()  # no human yet: hold
    newest, applied, stale = -1, -1, False
    executor.start()
    for k, t in enumerate(ep.t):
        while newest + 1 < len(human.t) and human.t[newest + 1] <= t + 1e-9:
            newest += 1
        if newest >= 0:
            state = human.states[newest]
            now_stale = t - human.t[newest] > timeout
            if newest != applied or now_stale != stale:
                memory.update(state, human.t[newest], hold)
                safety.barrier.set_external(*memory.capsules(safety.pairs.n_external, use_velocity and not now_stale))
                if not now_stale:  # stale: the safety service stops imitating (q_nom = q_cbf)
                    q_nom = safety.retargeter(state.theta, state.theta_valid)
                if newest != applied:
                    executor.set_human(state.capsules, state.capsule_radii, state.capsule_valid)
                applied, stale = newest, now_stale
        result = safety.filter.step(safety.filter.q_cbf.copy() if stale or memory.lost else q_nom, dt)
        executor.apply_command(result.q_cbf, result.u)
        executor.tick()
        report = executor.contacts()
        ep.tally.update(report)
        rows = result.rows
        ep.q_nom[k], ep.q_cbf[k], ep.u[k] = q_nom, result.q_cbf, result.u
        ep.q_sim[k], ep.qpos[k] = sim.q, sim.data.qpos
        ep.h[k] = per_pair(rows.h, row_pair, n_rows, np.fmin)
        if enforce and result.active_rows:
            ep.active[k] = per_pair(rows.enabled & (rows.A @ result.u - rows.b <= 1e-6), row_pair, n_rows, np.logical_or)
            ep.binding[k] = True
        ep.mode[k] = MODES.index(result.mode)
        ep.qp_ms[k] = result.qp_time_s * 1e3
        ep.human[k] = newest
        ep.contact_steps[k] = len(report.robot_robot), len(report.robot_human)
        if progress is not None:
            progress(k + 1)
    executor.stop()
    return ep
