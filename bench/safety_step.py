"""Benchmark: one full safety step (FK + every pair distance and row + QP + integration).

architecture §8 budget: p50 ≤ 0.25 ms, p99 ≤ 1 ms with the paper's worst case (72 constraints).
In the same run:

* the 72-row step per QP backend (daqp, osqp) on the same trajectory and scene, with the QP share;
* the floor of the step: forward kinematics with the capsule Jacobians alone
  (``RobotKinematics.compute``) and the bare QP alone (``daqp.solve`` on exactly the problems the
  filter's backend passed it, recorded along the same trajectory), timed in the same round-robin
  blocks as the step, and the ratio step / (FK + QP);
* DAQP's iterations per step, warm-started (the previous active set as DAQP ``sense`` flags)
  against cold on the same problems;
* the step at 400 and 126 rows (more people around the robot); oscbf's published speed is an
  *external* figure (StanfordASL/oscbf README, Morton & Pavone, IROS 2025: "kilohertz speed even
  with over 400 active safety constraints"), quoted beside it, never measured here;
* mink (architecture §10): the same MJCF in MuJoCo, the 7 robot CBF capsules as capsule geoms with the
  same endpoints and radii, the human capsules as mocap geoms, ``CollisionAvoidanceLimit`` over
  exactly our pair set + ``ConfigurationLimit`` + ``VelocityLimit`` + a ``PostureTask`` tracking
  q_nom, ``solve_ik`` (DAQP with our iteration limit and tolerance) and ``integrate_inplace``:

  - **mink-8**, the fair comparison: a reduced model with only our 8 joints (every other joint
    removed, its links fixed where they are), the detection distance covering every pair;
  - mink-8 at mink's default detection distance (almost no pair evaluated);
  - **mink-29**: the full 29-joint model with the 21 other joints locked by zero velocity limits
    (the comparison's model size is in that ratio).

  Removing joints welds their links to the world, and mink then silently drops every pair of a
  static link with a (world-parented) mocap person (architecture §10): the reduced model gets our full
  pair list back (``pairs_dropped_by_mink`` says how many it had dropped) and the pair counts are
  checked equal.

Scene (robot frame: x forward, y left, z up, pelvis at 0.793 m): person 1 stands 0.52 m to
the robot's left, side by side, with the right arm reaching in front of the robot's chest;
person 2 faces the robot 0.80 m in front (its capsules pad the preset to 72 rows); persons
3–8 stand around the robot (400/126-row runs). Humans are static (a HumanState arrives at
30 Hz, the step runs at 500 Hz; the velocity term is still evaluated for every row). The
robot tracks a q_nom of sinusoids: both arms sweep forward/up and across the body, elbows
flex, the waist rolls and pitches, so self rows and robot–human rows bind part of the time.

Timing: every configuration (daqp, osqp, 400 rows, 126 rows, mink ×3, the two floor parts) steps the same q_nom from
home, 500 untimed warm-up steps, then 8,000 timed steps in 40 round-robin blocks, so load from
other processes on this shared 2-core machine falls on all of them alike. Wall time
(perf_counter) is the reported figure; thread CPU time is recorded too (worst cases without
preemption). ``breakdown_us`` splits one step into FK, rows, QP and overhead.
"""

from __future__ import annotations

import contextlib
import ctypes
import gc
import math
import os
import sys
import time
import warnings
from dataclasses import dataclass
from typing import Any

import numpy as np

from bench.common import percentiles_us
from services.safety.assembly import build_pipeline, make_geometry, make_static_barrier
from services.safety.barriers.capsules import CapsuleBarrier
from services.safety.filter import FilterParams, SafetyFilter
from services.safety.pairs import N_ROBOT, PairSet, sized_pair_set
from shared.config import load_config
from shared.messages import SafetyMode
from shared.names import CAPSULE_NAMES
from shared.realtime import realtime

DT = 0.002
WARMUP = 500
STEPS = 8000
ROUNDS = 40
BUDGET_P50_MS = 0.25
BUDGET_P99_MS = 1.0
#: oscbf (Morton & Pavone): an external claim, not measured here (no oscbf code runs in this repository)
OSCBF_EXTERNAL = {
    "source": "external: StanfordASL/oscbf README and Morton & Pavone, 'Safe, Task-Consistent Manipulation with "
              "Operational Space Control Barrier Functions', IROS 2025 (a 7-DoF Franka, JAX, on the authors' machine)",
    "claim": "kilohertz speed even with over 400 active safety constraints",
    "hz_at_400_constraints": 1000.0,
    "measured_here": False,
}
#: DAQP settings of our backend, given to mink's solve_ik too (same iteration limit and tolerance)
DAQP_SETTINGS = {"iter_limit": 1000, "primal_tol": 1e-9}
#: mink's CollisionAvoidanceLimit defaults (mink 1.3)
MINK_DEFAULT_DETECTION = 0.01
MINK_DEFAULT_MIN_DISTANCE = 0.005


# --------------------------------------------------------------------------- scene
def _person(x: float, y: float, yaw: float, reach: str | None = None, height: float = 1.75) -> tuple[np.ndarray, np.ndarray]:
    """The 7 capsules (CAPSULE_NAMES order) of a standing adult at (x, y) facing ``yaw``.

    ``reach``: ``"right"``/``"left"`` puts that arm forward and inwards (towards the person's
    other side), as a hand reaching across in front of a neighbour. Returns ((7,2,3), (7,)).
    """
    k = height / 1.75
    pelvis_z, neck_z, shoulder_z, shoulder_y, hip_y = 0.97 * k, 1.40 * k, 1.42 * k, 0.18 * k, 0.09 * k
    local = np.zeros((7, 2, 3))
    local[0] = [[0.0, 0.0, pelvis_z], [0.0, 0.0, neck_z]]  # torso
    for side, (ua, fa, th) in ((1.0, (1, 2, 5)), (-1.0, (3, 4, 6))):  # left (+y), right (−y)
        shoulder = np.array([0.0, side * shoulder_y, shoulder_z])
        elbow = shoulder + [0.0, side * 0.02, -0.28 * k]
        wrist = elbow + [0.03, 0.0, -0.26 * k]
        if reach == ("left" if side > 0 else "right"):
            elbow = shoulder + np.array([0.17, -side * 0.12, -0.20]) * k
            wrist = elbow + np.array([0.16, -side * 0.14, -0.14]) * k
        local[ua] = [shoulder, elbow]
        local[fa] = [elbow, wrist]
        local[th] = [[0.0, side * hip_y, 0.93 * k], [0.02, side * (hip_y + 0.01), 0.50 * k]]
    c, s = math.cos(yaw), math.sin(yaw)
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    world = local @ rot.T + [x, y, 0.0]
    radii = np.array([0.12, 0.05, 0.04, 0.05, 0.04, 0.075, 0.075]) * k
    return world, radii


#: (x, y, yaw, reach, height) of up to 8 people; 1 beside (reaching in), 2 in front, 3–8 around.
PEOPLE = (
    (0.05, 0.52, 0.0, "right", 1.75),
    (0.80, -0.05, math.pi, "left", 1.70),
    (0.05, -0.60, 0.0, None, 1.65),
    (-0.70, 0.10, 0.0, None, 1.80),
    (0.55, 0.75, -2.3, "right", 1.60),
    (0.60, -0.80, 2.3, None, 1.75),
    (-0.55, 0.70, -0.8, None, 1.70),
    (-0.60, -0.70, 0.8, None, 1.85),
)


def external_capsules(n_external: int) -> tuple[np.ndarray, np.ndarray]:
    """Endpoints (E,2,3) and radii (E,) of the first ``n_external`` // 7 people of PEOPLE."""
    n_people = n_external // N_ROBOT
    if n_people > len(PEOPLE):
        raise ValueError(f"scene has {len(PEOPLE)} people, {n_people} needed")
    parts = [_person(*p) for p in PEOPLE[:n_people]]
    return np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])


def q_nom_trajectory(q_home: np.ndarray, q_min: np.ndarray, q_max: np.ndarray, n: int) -> np.ndarray:
    """(n, 8) nominal targets at DT: arms sweeping forward/up and across, elbows, waist."""
    t = np.arange(n)[:, None] * DT
    #            wr     wp     lsp    lsr    le     rsp    rsr    re
    offset = np.array([0.0, 0.10, -0.80, 0.15, 0.85, -0.70, -0.15, 0.90])
    amp = np.array([0.15, 0.10, 1.00, 0.50, 0.60, 0.90, 0.50, 0.60])
    period = np.array([5.3, 4.1, 3.0, 3.7, 2.3, 3.3, 4.3, 2.9])
    phase = np.array([0.0, 0.7, 0.0, 1.0, 0.4, 2.0, 0.5, 1.0])
    q = offset + amp * np.sin(2.0 * math.pi * t / period + phase)
    return np.clip(q, q_min, q_max)


# --------------------------------------------------------------------------- our filter
@dataclass
class Run:
    step_s: np.ndarray
    qp_s: np.ndarray
    modes: np.ndarray  # SafetyMode values as str
    active_rows: np.ndarray
    min_h: np.ndarray
    q: np.ndarray  # q_cbf after each step (for clearance checks)
    cpu_s: np.ndarray  # thread CPU time of each step (excludes preemption by other processes)


def make_filter(kinematics, pairs: PairSet, conf, backend: str) -> SafetyFilter:
    """As assembly.build_pipeline does: the configured collision geometry (``safety.geometry``,
    capsules by default) of ``pairs`` with the scene's people, and a SafetyFilter with the static
    capsule rows (so the floor's recorded QP has the rows of the step it is compared with)."""
    barrier = make_geometry(conf, pairs, kinematics)
    ends, radii = external_capsules(pairs.n_external)
    barrier.set_external(ends, radii, np.ones(len(radii), bool), np.zeros_like(ends))
    return SafetyFilter(kinematics, barrier, FilterParams.from_config(conf.safety), backend,
                        extra=[make_static_barrier(conf, kinematics)])


class FilterRunner:
    """Steps one SafetyFilter along q_nom from home: WARMUP untimed steps, then timed blocks."""

    def __init__(self, safety_filter: SafetyFilter, q_nom: np.ndarray, steps: int) -> None:
        self.filter, self.q_nom, self.k, self.i = safety_filter, q_nom, WARMUP, 0
        self.quiet = safety_filter.backend_name == "osqp"
        safety_filter.reset(safety_filter.kinematics.q_home)
        self.run = Run(np.empty(steps), np.empty(steps), np.empty(steps, dtype=object), np.empty(steps, int),
                       np.empty(steps), np.empty((steps, q_nom.shape[1])), np.empty(steps))
        with _quiet_stdout(self.quiet):
            for k in range(WARMUP):
                safety_filter.step(q_nom[k], DT)

    def block(self, n: int) -> None:
        run, q_nom, step, clock, cpu = self.run, self.q_nom, self.filter.step, time.perf_counter, time.thread_time
        for i in range(self.i, self.i + n):
            q = q_nom[self.k]
            cpu_start = cpu()
            start = clock()
            r = step(q, DT)
            end = clock()
            run.cpu_s[i] = cpu() - cpu_start
            run.step_s[i] = end - start
            run.qp_s[i] = r.qp_time_s
            run.modes[i] = r.mode.value
            run.active_rows[i] = r.active_rows
            run.min_h[i] = np.nanmin(r.rows.h)
            run.q[i] = r.q_cbf
            self.k += 1
        self.i += n


def _ms(samples_s: np.ndarray) -> dict[str, float]:
    st = percentiles_us(samples_s)
    return {k: (v / 1000.0 if k != "n" else v) for k, v in st.items()}


def summarize(run: Run) -> dict[str, Any]:
    st = _ms(run.step_s)
    qp = _ms(run.qp_s)
    n = len(run.modes)
    frac = {m.value: float(np.count_nonzero(run.modes == m.value)) / n for m in SafetyMode}
    return {
        "p50_ms": st["p50"],
        "p99_ms": st["p99"],
        "max_ms": st["max"],
        "mean_ms": st["mean"],
        "qp_p50_ms": qp["p50"],
        "qp_p99_ms": qp["p99"],
        "qp_share_p50": qp["p50"] / st["p50"],
        "mode_fraction": frac,
        "active_fraction": frac[SafetyMode.ACTIVE.value],
        "relaxed_fraction": frac[SafetyMode.RELAXED.value],
        "active_rows_mean": float(run.active_rows.mean()),
        "active_rows_max": int(run.active_rows.max()),
        "min_h_m": float(run.min_h.min()),
        "steps": n,
        "cpu_p50_ms": float(np.median(run.cpu_s) * 1e3),
        "cpu_p99_ms": float(np.percentile(run.cpu_s, 99) * 1e3),
        "cpu_max_ms": float(run.cpu_s.max() * 1e3),
    }


def breakdown(safety_filter: SafetyFilter, q_nom: np.ndarray) -> dict[str, float]:
    """Per-part p50 (µs) of one step, measured in situ by wrapping this instance's parts.

    Parts: FK (kinematics.compute), rows (every barrier's write_rows: closest points, h, normals and
    rows in the compiled kernels), QP backend call (wrapper + daqp/osqp, QPSolution.solve_time_s);
    overhead = the step minus those (u_ref, bounds, QPProblem, mode logic, integration,
    StepResult). The wrappers add ~0.2 µs each; only this pass is instrumented.
    """
    acc: dict[str, float] = {}
    clock = time.perf_counter

    def timed(key, fn):
        def wrapper(*args, **kwargs):
            start = clock()
            out = fn(*args, **kwargs)
            acc[key] = acc.get(key, 0.0) + clock() - start
            return out
        return wrapper

    kin, barriers = safety_filter.kinematics, safety_filter.barriers
    qp = safety_filter._qp  # the filter's QP backend instance (private attribute)
    kin.compute = timed("fk", kin.compute)
    for barrier in barriers:
        barrier.write_rows = timed("barrier", barrier.write_rows)
    qp.solve = timed("qp_call", qp.solve)
    parts: dict[str, list[float]] = {k: [] for k in ("step", "fk", "rows", "qp_call", "overhead")}
    try:
        safety_filter.reset(kin.q_home)
        for k, q in enumerate(q_nom):
            acc.clear()
            start = clock()
            safety_filter.step(q, DT)
            total = clock() - start
            if k < WARMUP:
                continue
            parts["step"].append(total)
            parts["fk"].append(acc.get("fk", 0.0))
            parts["rows"].append(acc.get("barrier", 0.0))
            parts["qp_call"].append(acc.get("qp_call", 0.0))
            parts["overhead"].append(total - acc.get("fk", 0.0) - acc.get("barrier", 0.0) - acc.get("qp_call", 0.0))
    finally:
        del kin.compute, qp.solve  # back to the class methods
        for barrier in barriers:
            del barrier.write_rows
    out = {f"{k}_p50_us": float(np.median(v) * 1e6) for k, v in parts.items()}
    total = sum(out[f"{k}_p50_us"] for k in ("fk", "rows", "qp_call", "overhead"))
    out["share_of_sum"] = {k: out[f"{k}_p50_us"] / total for k in ("fk", "rows", "qp_call", "overhead")}
    return out


def clearance(kinematics, pairs: PairSet, qs: np.ndarray, phi: float) -> dict[str, float]:
    """Minimum surface distance (m) over self and robot–human pairs along configurations ``qs``."""
    conf = load_config()
    barrier = CapsuleBarrier(pairs, kinematics.radii, len(kinematics.joint_names))
    ends, radii = external_capsules(pairs.n_external)
    barrier.set_external(ends, radii)
    lo_self, lo_human = np.inf, np.inf
    for q in qs:
        e, j = kinematics.compute(q)
        rows = barrier.evaluate(e, j, conf.safety.gamma, 0.0)
        lo_self = min(lo_self, rows.min_h(True))
        lo_human = min(lo_human, rows.min_h(False))
    return {"min_self_clearance_m": float(lo_self), "min_human_clearance_m": float(lo_human), "phi_m": phi}


# --------------------------------------------------------------------------- mink anchor
class MinkAnchor:
    """The same robot, capsules, people and pair set in mink (see module docstring).

    ``reduced`` (mink-8): every joint but the 8 imitation joints is removed, their links fixed at
    home: nv = 8 like our filter. Those links are then welded to the world and mink drops their
    pairs with the (world-parented) mocap people as "parent–child" (architecture §10); our full pair
    list is given back to the limit (``pairs_dropped_by_mink`` counts what it had dropped; such a
    pair's row has a zero gradient, like ours).

    Not reduced (mink-29): every other joint is *kept*, locked by a zero VelocityLimit with target
    home in the posture task (nv = 29). In both the pelvis free joint is removed (base welded at
    base_height): no CBF capsule sits on the pelvis.
    """

    def __init__(self, kinematics, pairs: PairSet, conf, detection: float, min_distance: float, gain: float,
                 reduced: bool = False) -> None:
        import mink
        import mujoco

        self.mink, self.mujoco = mink, mujoco
        spec = kinematics.spec
        ms = mujoco.MjSpec.from_file(str(spec.model_path))
        for key in list(ms.keys):
            ms.delete(key)  # keyframes hold the free joint's qpos
        for joint in list(ms.joints):
            if joint.type == mujoco.mjtJoint.mjJNT_FREE:
                ms.delete(joint)
        base = ms.body(spec.base_body)
        base.pos = [0.0, 0.0, spec.base_height]
        base.quat = [1.0, 0.0, 0.0, 0.0]
        self.reduced = reduced
        if reduced:
            keep = set(kinematics.joint_names)
            for actuator in list(ms.actuators):
                ms.delete(actuator)
            for joint in list(ms.joints):
                if joint.name not in keep:
                    ms.delete(joint)
        self.robot_geoms = []
        for name in CAPSULE_NAMES:
            cap = spec.capsules[name]
            geom = ms.body(cap.frame).add_geom(
                name=f"cbf/{name}", type=mujoco.mjtGeom.mjGEOM_CAPSULE, fromto=[*cap.a, *cap.b],
                size=[cap.radius, 0.0, 0.0], contype=1, conaffinity=1, group=5, density=0.0,
            )
            self.robot_geoms.append(geom.name)
        ends, radii = external_capsules(pairs.n_external)
        self.human_geoms = []
        for p in range(len(radii) // N_ROBOT):
            body = ms.worldbody.add_body(name=f"human{p + 1}", mocap=True)
            for c in range(N_ROBOT):
                e = p * N_ROBOT + c
                geom = body.add_geom(
                    name=f"human{p + 1}/{CAPSULE_NAMES[c]}", type=mujoco.mjtGeom.mjGEOM_CAPSULE,
                    fromto=[*ends[e, 0], *ends[e, 1]], size=[radii[e], 0.0, 0.0], contype=2, conaffinity=1,
                    group=5, density=0.0,
                )
                self.human_geoms.append(geom.name)
        model = ms.compile()
        self.model = model
        stacked = self.robot_geoms + self.human_geoms
        self.pair_names = [(stacked[a], stacked[b]) for a, b in zip(pairs.first, pairs.second)]
        self.joint_qpos = np.array([model.joint(n).qposadr[0] for n in kinematics.joint_names])
        self.joint_dof = np.array([model.joint(n).dofadr[0] for n in kinematics.joint_names])
        self.q_full_home = model.qpos0.copy()
        self.q_full_home[self.joint_qpos] = kinematics.q_home
        self.configuration = mink.Configuration(model, self.q_full_home)
        self.collision = mink.CollisionAvoidanceLimit(
            model, geom_pairs=[([a], [b]) for a, b in self.pair_names], gain=gain,
            minimum_distance_from_collisions=min_distance, collision_detection_distance=detection,
        )
        ids = [tuple(sorted((model.geom(a).id, model.geom(b).id))) for a, b in self.pair_names]
        self.pairs_dropped_by_mink = len(set(ids) - set(self.collision.geom_id_pairs))
        if self.pairs_dropped_by_mink:  # the static-link trap: give mink our pair list back
            self.collision.geom_id_pairs = ids
            self.collision.max_num_contacts = len(ids)
            self.collision._init_broadphase(model)  # its per-pair broad-phase tables (mink 1.3)
        s = conf.safety
        velocities = {}
        for jid in range(model.njnt):
            name = model.joint(jid).name
            if name in kinematics.joint_names:
                velocities[name] = s.u_max[kinematics.joint_names.index(name)]
            else:
                velocities[name] = 0.0  # locked
        self.limits = [mink.ConfigurationLimit(model), mink.VelocityLimit(model, velocities), self.collision]
        # Δq = −gain·e per step: gain K·dt gives u = K (q_nom − q), our u_ref.
        self.posture = mink.PostureTask(model, cost=1.0, gain=s.gain * DT)
        self.tasks = [self.posture]
        self.target = self.q_full_home.copy()
        self.failures = 0

    def reset(self) -> None:
        self.configuration.update(self.q_full_home)
        self.failures = 0

    def step(self, q_nom: np.ndarray, solver: str = "daqp") -> None:
        target = self.target
        target[self.joint_qpos] = q_nom
        self.posture.set_target(target)
        settings = DAQP_SETTINGS if solver == "daqp" else {}
        try:
            v = self.mink.solve_ik(self.configuration, self.tasks, DT, solver=solver, limits=self.limits, **settings)
        except self.mink.NoSolutionFound:
            self.failures += 1
            self.configuration.update()
            return
        self.configuration.integrate_inplace(v, DT)

    def q(self) -> np.ndarray:
        return self.configuration.q[self.joint_qpos].copy()

    def rows_computed(self) -> int:
        """Rows of the collision constraint mink actually evaluated at the current q."""
        c = self.collision.compute_qp_inequalities(self.configuration, DT)
        return int(np.count_nonzero(np.isfinite(c.h)))


class MinkRunner:
    """Steps a MinkAnchor along q_nom from home, like FilterRunner."""

    def __init__(self, anchor: MinkAnchor, q_nom: np.ndarray, steps: int, solver: str = "daqp") -> None:
        self.anchor, self.q_nom, self.solver, self.k, self.i = anchor, q_nom, solver, WARMUP, 0
        self.quiet = solver == "osqp"
        self.step_s = np.empty(steps)
        self.q = np.empty((steps, q_nom.shape[1]))
        self.rows: list[int] = []
        anchor.reset()
        with _quiet_stdout(self.quiet):
            for k in range(WARMUP):
                anchor.step(q_nom[k], solver)

    def block(self, n: int) -> None:
        anchor, q_nom, solver, clock = self.anchor, self.q_nom, self.solver, time.perf_counter
        for i in range(self.i, self.i + n):
            q = q_nom[self.k]
            start = clock()
            anchor.step(q, solver)
            self.step_s[i] = clock() - start
            self.q[i] = anchor.q()
            if i % 200 == 0:
                self.rows.append(anchor.rows_computed())  # untimed check
            self.k += 1
        self.i += n

    def summary(self) -> dict[str, Any]:
        st = _ms(self.step_s[: self.i])
        anchor = self.anchor
        locked = np.delete(np.arange(anchor.model.nq), anchor.joint_qpos)
        return {
            "p50_ms": st["p50"],
            "p99_ms": st["p99"],
            "mean_ms": st["mean"],
            "max_ms": st["max"],
            "steps": self.i,
            "solver": self.solver,
            "solver_failures": anchor.failures,
            "rows_evaluated_mean": float(np.mean(self.rows)),
            "rows_evaluated_min": int(np.min(self.rows)),
            "locked_joint_drift_rad": float(np.abs(anchor.configuration.q[locked] - anchor.q_full_home[locked]).max(initial=0.0)),
        }


# --------------------------------------------------------------------------- the floor
class FloorRecorder:
    """Steps a fresh filter along q_nom and records, for every timed step, the configuration FK is
    evaluated at and the exact arguments its DAQP backend passed to ``daqp.solve`` (the relaxed
    stages' solves are not recorded: the floor is the plain step's one QP)."""

    def __init__(self, safety_filter: SafetyFilter, q_nom: np.ndarray) -> None:
        import daqp

        from services.safety.qp import daqp_backend

        if safety_filter.backend_name != "daqp":
            raise ValueError("the bare-QP floor is recorded from the daqp backend")
        self.qs: list[np.ndarray] = []
        self.calls: list[tuple] = []
        backend, solve, main = safety_filter._qp, daqp.solve, [False]

        def spy(H, f, A, upper, lower, sense, **settings):
            if main[0]:
                self.calls.append((H, f.copy(), A.copy(), upper.copy(), lower.copy(), sense.copy(), settings))
            return solve(H, f, A, upper, lower, sense, **settings)

        def backend_solve(problem, _solve=backend.solve):
            main[0] = True
            try:
                return _solve(problem)
            finally:
                main[0] = False

        daqp_backend.daqp = _Namespace(solve=spy)  # only this module's view of daqp
        backend.solve = backend_solve
        try:
            safety_filter.reset(safety_filter.kinematics.q_home)
            for k, q in enumerate(q_nom):
                if k == WARMUP:
                    self.calls.clear()
                if k >= WARMUP:
                    self.qs.append(safety_filter.q_cbf.copy())
                n_calls = len(self.calls)
                safety_filter.step(q, DT)
                if k >= WARMUP and len(self.calls) == n_calls + 2:  # a failed warm solve repeated cold
                    del self.calls[n_calls]
        finally:
            daqp_backend.daqp = daqp
            del backend.solve


class _Namespace:
    def __init__(self, **kw) -> None:
        self.__dict__.update(kw)


class FKRunner:
    """Times ``kinematics.compute`` (FK + every capsule endpoint's Jacobian) at recorded configurations."""

    quiet = False

    def __init__(self, kinematics, qs: list[np.ndarray]) -> None:
        self.kinematics, self.qs, self.i = kinematics, qs, 0
        self.step_s = np.empty(len(qs))
        for q in qs[:WARMUP]:
            kinematics.compute(q)

    def block(self, n: int) -> None:
        compute, qs, clock = self.kinematics.compute, self.qs, time.perf_counter
        for i in range(self.i, min(self.i + n, len(qs))):
            q = qs[i]
            start = clock()
            compute(q)
            self.step_s[i] = clock() - start
        self.i = min(self.i + n, len(qs))


class BareQPRunner:
    """Times ``daqp.solve`` alone on the recorded problems (H, f, A, bounds, warm-start flags)."""

    quiet = False

    def __init__(self, calls: list[tuple]) -> None:
        import daqp

        self.solve, self.calls, self.i = daqp.solve, calls, 0
        self.step_s = np.empty(len(calls))
        self.iterations = np.empty(len(calls), int)
        for c in calls[:WARMUP]:
            self.solve(*c[:6], **c[6])

    def block(self, n: int) -> None:
        """Time the next ``n`` recorded solves, each called as the backend calls it (the settings as
        explicit keywords: unpacking a dict per call would cost the floor ≈ 0.5 µs the step does not pay)."""
        solve, calls, clock = self.solve, self.calls, time.perf_counter
        for i in range(self.i, min(self.i + n, len(calls))):
            H, f, A, upper, lower, sense, settings = calls[i]
            iter_limit, primal_tol = settings["iter_limit"], settings["primal_tol"]
            start = clock()
            out = solve(H, f, A, upper, lower, sense, iter_limit=iter_limit, primal_tol=primal_tol)
            self.step_s[i] = clock() - start
            self.iterations[i] = out[3]["iterations"]
        self.i = min(self.i + n, len(calls))


def daqp_iterations(kinematics, pairs: PairSet, conf, q_nom: np.ndarray) -> dict[str, Any]:
    """DAQP iterations per plain-step QP along q_nom: warm-started (the backend's default), cold, and
    with the flags the backend used to set (1 = "active at the upper bound" for every row
    with λ ≠ 0, although a row A u ≥ b is DAQP's lower bound). Same problems for the three: the
    solutions agree to solver precision, so the trajectories are the same."""
    from services.safety.qp import daqp_backend

    def count(warm: bool, old_flags: bool = False) -> np.ndarray:
        f = make_filter(kinematics, pairs, conf, "daqp")
        f._qp = backend = daqp_backend.DaqpBackend(**DAQP_SETTINGS, warm_start=warm)
        its: list[int] = []
        solve = backend.solve

        def counted(problem):
            r = solve(problem)
            its.append(r.iterations)
            return r

        backend.solve = counted
        settle = daqp_backend._settle  # what DaqpBackend.solve calls after each optimal solve (it sets the flags)

        def old_settle(lam, *args):
            active = settle(lam, *args)
            np.copyto(args[1], (lam != 0.0).astype(np.intc))  # args[1]: the sense flags
            return active

        if old_flags:  # the filter's problems are stacked: their _settle is the backend's bound one
            daqp_backend._settle = backend._settle_stacked.call = old_settle
        try:
            f.reset(kinematics.q_home)
            for q in q_nom:
                f.step(q, DT)
        finally:
            daqp_backend._settle = settle
        return np.array(its[WARMUP:])

    out: dict[str, Any] = {}
    for name, warm, old in (("warm", True, False), ("cold", False, False), ("old_flags", True, True)):
        its = count(warm, old)
        out[name] = {"mean": float(its.mean()), "p50": float(np.median(its)), "max": int(its.max()), "solves": int(its.size)}
    out["warm_over_cold"] = out["warm"]["mean"] / out["cold"]["mean"]
    out["flags"] = "sense = ACTIVE (1) | LOWER (2) per DAQP include/constants.h: λ < 0 → 3, λ > 0 → 1, else 0"
    return out


@contextlib.contextmanager
def _quiet_stdout(quiet: bool = True):
    """Send fd 1 to /dev/null (OSQP 1.1 prints "Polishing not needed ..." on every solve
    without an active constraint, even with verbose=False)."""
    if not quiet:
        yield
        return
    sys.stdout.flush()
    libc = ctypes.CDLL(None)
    saved = os.dup(1)
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, 1)
    try:
        yield
    finally:
        libc.fflush(None)
        os.dup2(saved, 1)
        os.close(saved)
        os.close(devnull)


def interleave(runners: dict[str, Any], steps: int, rounds: int = ROUNDS) -> None:
    """Time every runner in ``rounds`` blocks, round-robin with a rotating order, so that load
    from other processes on this shared machine falls on every configuration alike."""
    names = list(runners)
    sizes = [steps // rounds + (1 if r < steps % rounds else 0) for r in range(rounds)]
    for r, n in enumerate(sizes):
        for name in names[r % len(names):] + names[: r % len(names)]:
            runner = runners[name]
            with _quiet_stdout(runner.quiet):
                runner.block(n)


def verify_mink(anchor: MinkAnchor, safety_filter: SafetyFilter, pairs: PairSet, qs: np.ndarray, phi: float) -> dict[str, Any]:
    """Pair-count and geometry agreement of the mink model with ours.

    * mink's pair list equals ours (72 geom-id pairs, same set);
    * at sample configurations every row is evaluated and mink's surface distance equals our
      d − r_A − r_B (a person's r without ``safety.human_margin``, which mink's scene does not
      have), and its row's imitation columns equal −∂h/∂q of ours.
    """
    mujoco = anchor.mujoco
    model = anchor.model
    gid = {name: mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, name) for pair in anchor.pair_names for name in pair}
    ours = [(min(gid[a], gid[b]), max(gid[a], gid[b])) for a, b in anchor.pair_names]
    mink_pairs = list(anchor.collision.geom_id_pairs)
    index = {p: i for i, p in enumerate(mink_pairs)}
    dist_err, grad_err = 0.0, 0.0
    fromto = np.empty(6)
    margin = np.where(pairs.is_self, 0.0, safety_filter.barrier.person_margin)  # h counts it on person rows
    for q in qs:
        full = anchor.q_full_home.copy()
        full[anchor.joint_qpos] = q
        anchor.configuration.update(full)
        c = anchor.collision.compute_qp_inequalities(anchor.configuration, DT)
        rows = safety_filter.rows_at(q)
        for r, (g1, g2) in enumerate(ours):
            d = mujoco.mj_geomDistance(model, anchor.configuration.data, g1, g2, 10.0, fromto)
            dist_err = max(dist_err, abs(d - (rows.h[r] + phi + margin[r])))
            if d > 1e-3:
                grad = -c.G[index[(g1, g2)], anchor.joint_dof]  # G = −∂d/∂q (d ≥ 0)
                grad_err = max(grad_err, float(np.abs(grad - rows.A[r]).max()))
    return {
        "pairs_ours": len(pairs),
        "pairs_mink": len(mink_pairs),
        "same_pair_set": set(ours) == set(mink_pairs) and len(set(ours)) == len(ours),
        "constraint_rows": int(c.G.shape[0]),
        "max_distance_diff_m": dist_err,
        "max_gradient_diff": grad_err,
        "configurations_checked": len(qs),
    }


# --------------------------------------------------------------------------- run
#: The benchmark's people stand still, one reaching 58 mm into a robot capsule's margin at home: with
#: the shipped intrusion stop (``safety.on_intrusion: stop``) the robot would stand there for the
#: whole run and every QP be a trivial one at rest; retreating keeps the rows binding and the relaxed
#: two-stage solve in the measurement, the heavier step of the two.
BENCH_SAFETY = {"on_intrusion": "retreat"}


def run(steps: int = STEPS) -> dict[str, Any]:
    conf = load_config(overrides={"safety": BENCH_SAFETY})
    pipeline = build_pipeline(conf, "paper72")
    kin, pairs = pipeline.kinematics, pipeline.pairs
    self_pairs = [tuple(p) for p in kin.spec.self_pairs]
    phi, gamma = conf.safety.phi, conf.safety.gamma
    default_backend = conf.safety.backend.value
    q_nom = q_nom_trajectory(kin.q_home, kin.q_min, kin.q_max, WARMUP + steps)
    ends, radii = external_capsules(pairs.n_external)
    pipeline.barrier.set_external(ends, radii, np.ones(len(radii), bool), np.zeros_like(ends))

    # mink: detection distance covering every pair (the fair comparison) and mink's default
    far = 5.0  # m: larger than any pair's surface distance here (checked: rows_evaluated_min == 72)
    mink_gain = gamma * DT * DT  # mink bounds Δq by gain·(d − d_min)/dt: this is ḋ ≥ −γ (d − φ)
    mink8 = MinkAnchor(kin, pairs, conf, detection=far, min_distance=phi, gain=mink_gain, reduced=True)
    mink8_default = MinkAnchor(kin, pairs, conf, detection=MINK_DEFAULT_DETECTION,
                               min_distance=MINK_DEFAULT_MIN_DISTANCE, gain=mink_gain, reduced=True)
    mink29 = MinkAnchor(kin, pairs, conf, detection=far, min_distance=phi, gain=mink_gain)

    # the floor: FK and the bare QP at exactly what the daqp filter computes along q_nom
    recorded = FloorRecorder(make_filter(kin, pairs, conf, "daqp"), q_nom)

    runners: dict[str, Any] = {default_backend: FilterRunner(pipeline.filter, q_nom, steps)}
    for name in ("daqp", "osqp"):
        if name != default_backend:
            runners[name] = FilterRunner(make_filter(kin, pairs, conf, name), q_nom, steps)
    runners["floor_fk"] = FKRunner(kin, recorded.qs)
    runners["floor_qp"] = BareQPRunner(recorded.calls)
    sized_pairs = {n_rows: sized_pair_set(self_pairs, n_rows) for n_rows in (400, 126)}
    for n_rows, p in sized_pairs.items():
        runners[f"rows{n_rows}"] = FilterRunner(make_filter(kin, p, conf, default_backend), q_nom, steps)
    runners["mink8"] = MinkRunner(mink8, q_nom, steps)
    runners["mink8_default"] = MinkRunner(mink8_default, q_nom, steps)
    runners["mink29"] = MinkRunner(mink29, q_nom, steps)
    gc.collect()
    # Timed as the safety service runs its loop (SCHED_FIFO when the OS allows): the worst case
    # then measures our step, not the preemption by other jobs on this shared 2-core machine.
    load_before = os.getloadavg()
    with realtime(10) as scheduling:
        interleave(runners, steps)
    load_after = os.getloadavg()
    with warnings.catch_warnings():  # qpsolvers: dense P/G converted to CSC for osqp
        warnings.simplefilter("ignore")
        mink_osqp = MinkRunner(MinkAnchor(kin, pairs, conf, detection=far, min_distance=phi, gain=mink_gain, reduced=True),
                               q_nom, min(steps, 1500), solver="osqp")
        with _quiet_stdout():
            mink_osqp.block(min(steps, 1500))

    backends = {name: summarize(runners[name].run) for name in ("daqp", "osqp")}
    main = backends[default_backend]
    sized: dict[str, Any] = {}
    for n_rows, p in sized_pairs.items():
        s = summarize(runners[f"rows{n_rows}"].run)
        s["hz_mean"] = 1.0 / (s["mean_ms"] / 1000.0)
        s["hz_worst"] = 1.0 / (s["max_ms"] / 1000.0)
        s["hz_p999"] = 1.0 / (float(np.percentile(runners[f"rows{n_rows}"].run.step_s, 99.9)))
        s["hz_worst_cpu"] = 1.0 / (s["cpu_max_ms"] / 1000.0)
        s["people"] = p.n_external // N_ROBOT
        sized[str(n_rows)] = s
    m8, m8_default, m29 = (runners[k].summary() for k in ("mink8", "mink8_default", "mink29"))
    sample_q = runners[default_backend].run.q[::400]
    verification = {"mink8": verify_mink(mink8, pipeline.filter, pairs, sample_q, phi),
                    "mink29": verify_mink(mink29, pipeline.filter, pairs, sample_q, phi)}
    ours_clearance = clearance(kin, pairs, runners[default_backend].run.q, phi)
    mink_clearance = {
        "mink8": clearance(kin, pairs, runners["mink8"].q, phi),
        "mink8_default_detection": clearance(kin, pairs, runners["mink8_default"].q, MINK_DEFAULT_MIN_DISTANCE),
        "mink29": clearance(kin, pairs, runners["mink29"].q, phi),
    }
    parts = breakdown(pipeline.filter, q_nom[: WARMUP + min(steps, 4000)])
    iterations = daqp_iterations(kin, pairs, conf, q_nom[: WARMUP + min(steps, 4000)])

    daqp_step = backends["daqp"]
    fk_ms, qp_ms = _ms(runners["floor_fk"].step_s)["p50"], _ms(runners["floor_qp"].step_s)["p50"]
    floor = {
        "what": "p50 of FK + capsule Jacobians alone (RobotKinematics.compute) and of daqp.solve alone on the problems "
                "the daqp filter passed it (same trajectory, same warm-start flags), timed in the same blocks as the step",
        "fk_p50_ms": fk_ms,
        "qp_p50_ms": qp_ms,
        "floor_p50_ms": fk_ms + qp_ms,
        "step_p50_ms": daqp_step["p50_ms"],
        "ratio_step_over_floor": daqp_step["p50_ms"] / (fk_ms + qp_ms),
        "goal_ratio": 2.0,
        "goal_step_p50_ms": 0.04,
        "rows": int(recorded.calls[0][2].shape[0]) if recorded.calls else 0,
        "bare_qp_iterations_mean": float(runners["floor_qp"].iterations.mean()),
    }
    floor["meets_ratio_goal"] = floor["ratio_step_over_floor"] <= floor["goal_ratio"]
    floor["meets_p50_goal"] = floor["step_p50_ms"] <= floor["goal_step_p50_ms"]

    p50, p99 = main["p50_ms"], main["p99_ms"]
    mink_common = {"version": _version("mink"), "solver": "daqp", "solver_settings": DAQP_SETTINGS,
                   "collision_gain": mink_gain, "warm_start": "none (mink's solve_ik passes no initial guess)"}
    return {
        "name": "safety_step",
        "what": "SafetyFilter.step (FK + all pair distances/rows + QP + integration), paper72 preset, arms sweeping next to a reaching person",
        "unit": "ms",
        "p50": p50,
        "p99": p99,
        "constraints": len(pairs),
        "backend": default_backend,
        "scheduling": scheduling,
        "load_avg_during": {"before": list(load_before), "after": list(load_after)},
        "p50_ms": p50,
        "p99_ms": p99,
        "max_ms": main["max_ms"],
        "qp_p50_ms": main["qp_p50_ms"],
        "qp_share_p50": main["qp_share_p50"],
        "active_fraction": main["active_fraction"],
        "relaxed_fraction": main["relaxed_fraction"],
        "mode_fraction": main["mode_fraction"],
        "backends": backends,
        "floor": floor,
        "daqp_iterations": iterations,
        "breakdown_us": parts,
        "clearance": ours_clearance,
        "p50_ms_400": sized["400"]["p50_ms"],
        "p99_ms_400": sized["400"]["p99_ms"],
        "hz_mean_400": sized["400"]["hz_mean"],
        "hz_worst_400": sized["400"]["hz_worst"],
        "hz_worst_cpu_400": sized["400"]["hz_worst_cpu"],
        "p50_ms_126": sized["126"]["p50_ms"],
        "p99_ms_126": sized["126"]["p99_ms"],
        "hz_mean_126": sized["126"]["hz_mean"],
        "hz_worst_126": sized["126"]["hz_worst"],
        "hz_worst_cpu_126": sized["126"]["hz_worst_cpu"],
        "sized": sized,
        "oscbf_external": OSCBF_EXTERNAL,
        "mink8_p50_ms": m8["p50_ms"],
        "mink8_p99_ms": m8["p99_ms"],
        "mink29_p50_ms": m29["p50_ms"],
        "mink29_p99_ms": m29["p99_ms"],
        "mink8_default_p50_ms": m8_default["p50_ms"],
        "speedup_vs_mink8": m8["p50_ms"] / daqp_step["p50_ms"],
        "speedup_vs_mink29": m29["p50_ms"] / daqp_step["p50_ms"],
        "speedup_vs_mink8_default": m8_default["p50_ms"] / daqp_step["p50_ms"],
        "mink": {
            **mink_common,
            "mink8": {**m8, "nv": int(mink8.model.nv), "collision_detection_distance_m": far,
                      "minimum_distance_from_collisions_m": phi, "pairs_dropped_by_mink": mink8.pairs_dropped_by_mink,
                      "model": "reduced: only the 8 imitation joints, every other joint removed (links fixed at home)"},
            "mink8_default_detection": {**m8_default, "nv": int(mink8_default.model.nv),
                                        "collision_detection_distance_m": MINK_DEFAULT_DETECTION,
                                        "minimum_distance_from_collisions_m": MINK_DEFAULT_MIN_DISTANCE},
            "mink29": {**m29, "nv": int(mink29.model.nv), "collision_detection_distance_m": far,
                       "minimum_distance_from_collisions_m": phi, "pairs_dropped_by_mink": mink29.pairs_dropped_by_mink,
                       "model": "full: 29 joints, the 21 others locked by zero velocity limits"},
            "mink8_osqp_p50_ms": mink_osqp.summary()["p50_ms"],
            "verification": verification,
            "same_pair_count": verification["mink8"]["pairs_mink"] == verification["mink29"]["pairs_mink"] == len(pairs),
            "clearance": mink_clearance,
        },
        "budget_p50_ms": BUDGET_P50_MS,
        "budget_p99_ms": BUDGET_P99_MS,
        "within_budget": p50 <= BUDGET_P50_MS and p99 <= BUDGET_P99_MS,
        "dt_s": DT,
        "warmup_steps": WARMUP,
        "timing": f"{steps} timed steps per configuration after {WARMUP} warm-up steps, in {ROUNDS} round-robin blocks",
    }


def _version(dist: str) -> str:
    from importlib.metadata import version

    try:
        return version(dist)
    except Exception:  # pragma: no cover
        return "unknown"
