"""Retargeting by arm directions: the robot's arms point where the person's do.

The paper's map (eq. 2, :class:`~services.safety.retarget.Retargeter`) adds the person's angles to
the robot's home pose joint by joint. On the G1 that leaves the arm 20–40° off the person's even
with perfect tracking: its home holds the arms 22° out and the elbows bent, its shoulder axes are
tilted against the torso, and its elbow stops 30° short of straight. This retargeter keeps eq. 2
for the waist (roll, pitch) and solves the arms through the robot's own kinematics:

    q_arm = argmin_{q_min ≤ q ≤ q_max} Σ_s ‖d_s(q) − p_s‖² + μ ‖q − q_prev‖²,

over the shoulder pitch, shoulder roll and elbow of each arm (the waist at its eq.-2 target, every
other joint at the robot description's home), s the arm's upper arm and forearm, p_s the person's
segment direction in the person's torso frame F_T and d_s(q) the robot's capsule axis in the
robot's F_T (:mod:`shared.torso_frame`: the same definition the evaluator's direction error uses;
facing the person the robot's left arm takes the person's right, reflected), q_prev the previous
state's target and μ = :data:`ANCHOR` a small anchor: where a joint does not move the segments (an
arm held straight out sideways: its shoulder pitch turns it about its own axis) the directions
leave it undetermined, and without the anchor the slightest noise of the person's forearm swung
it at the velocity bound; where the directions do determine a joint (curvature σ² ≈ 0.3–1 per
rad²) the anchor holds the target back by μ/(σ² + μ), 1–3 % of one state's motion. A projected
Levenberg–Marquardt iteration from the previous solution (the eq.-2 target at the start) solves it:

    Δ = (JᵀJ + (λ + μ) I)⁻¹ (Jᵀ (p − d) − μ (q − q_prev)),   q ← Π_[q_min, q_max](q + Δ),

J_s = R (I − û ûᵀ) (J_b − J_a) / ‖b − a‖ with û the capsule axis (a → b) in world axes, J_a, J_b
its endpoints' point Jacobians and R the robot's F_T (held for the step). Warm-started, the
solution moves continuously with the person (no jump between branches of the inverse); at most
:data:`MAX_ITERATIONS` a state, a target not converged continues at the next. A segment whose
keypoints are invalid drops out of the sum; an arm whose upper arm is invalid keeps its last
target (as eq. 2 keeps the last valid angle). Where the optimum itself leaps (the person's arm passes where the robot's
cannot follow, e.g. a windmill past the shoulder's pitch stop, and the nearest solution moves to
another branch) the target moves there at most at ``max_speed`` (the filter's velocity bound
u_max): no faster than the robot may move, as the pose estimator spreads its branch switches.

The target is a pose the robot can take: with ``body`` (the self-collision barriers the filter
enforces, h = d − r_A − r_B − φ with the filter's φ) each step keeps every self pair the arms move
at h ≥ ``clearance`` to first order,

    min_Δ ½ Δᵀ(JᵀJ + (λ + μ)I)Δ − (Jᵀ(p − d) − μ(q − q_prev))ᵀΔ   s.t.   ∇h_i Δ ≥ clearance − h_i,

a QP (the filter's backend, after the change of variables v = Lᵀ Δ with LLᵀ = JᵀJ + (λ + μ)I), its step
projected onto the joint ranges like the unconstrained one (the next iteration corrects what the
projection costs a row). Without
it an arm hanging along the person's side would put the robot's arm into its own torso: the
filter would stop it at its barrier, every step bound, and the arm's h would ride its margin.
Where that QP has no solution (an arm already deeper than one step can undo) the iteration stops
at the last pose: the filter's self rows still hold the robot. The clearance the stack uses is
the barrier's own margin φ (:func:`services.safety.assembly.make_retargeter`): the target sits as
far inside the safe set as the barrier sits from contact, so a tracking error or a push (a person
leaning on the arm) of up to φ at the surface still leaves the robot clear of itself; and a self
row cannot bind while the robot settles onto a still target at h ≥ ε (the self margin) when
γ ≥ K: the row asks ∇h u ≥ −γ(h − ε), tracking gives ∇h u ≈ −K(h − h_target) ≥ −K(h − ε).

The rate q̇_nom of an arm joint is the difference of its consecutive targets through the same
rate filter as the person's θ̇ (``perception.angles``' rate parameters,
:class:`shared.lowpass.RateFilter`, the contract of ``HumanState.theta_rate``): the two
retargetings' rates trail the person alike. It restarts from 0 where the difference would span
a gap: the arm not solved in the previous state, or the person's rates restarted (all of the
arm's three θ̇ exactly 0: the perception's "not computable"). It is 0 on a joint at its limit.
The waist's rate is eq. 2's.
"""

from __future__ import annotations

import copy
from collections.abc import Sequence

import numpy as np

from services.safety.barriers.base import Barrier
from services.safety.direction_kernel import direction_normal_equations
from services.safety.errors import SafetyConfigError
from services.safety.kinematics import RobotKinematics
from services.safety.qp import QPBackend, QPProblem
from services.safety.qp.base import INF_BOUND
from services.safety.retarget import Pose, PoseLike, Retargeter, mirror_pose
from shared.lowpass import RateFilter
from shared.names import CAPSULE_NAMES, KEYPOINT_INDEX, KEYPOINT_NAMES
from shared.torso_frame import ARM_CAPSULES, FRAME_CAPSULES, person_arm_directions

#: The imitation joints of each arm (IMITATION_JOINT_NAMES order): shoulder pitch, roll, elbow.
ARM_JOINTS = (np.array([2, 3, 4]), np.array([5, 6, 7]))
#: Each arm's (upper arm, forearm) rows of the (4, 3) direction arrays.
_ARM_ROWS = (np.array([0, 1]), np.array([2, 3]))
#: Segments shorter than this give no direction (m).
MIN_SEGMENT = 0.05
#: Levenberg–Marquardt damping λ (dimensionless: residuals are unit-vector differences).
DAMPING = 1e-4
#: μ of the anchor to the previous state's target (module docstring; per rad², against unit-vector residuals).
ANCHOR = 1e-2
#: Iterations per state, at most: a budget inside the control tick (≈ 0.1 ms each here); a target
#: not converged within it continues from there at the next state. Measured on the development
#: clips at 30 Hz: 2 iterations leave the direction error where 20 do (p50 3.9 / 11.2°, p95
#: 10.4 / 22–23°, dance / punches) at 0.24–0.36 ms a state against 0.5–1.3 ms.
MAX_ITERATIONS = 2
#: Stop once the largest joint step is below this (rad; 0.05 mm at the end of a 0.5 m arm).
STEP_TOLERANCE = 1e-4


class DirectionRetargeter:
    """q_nom (8,) and q̇_nom (8,) from a human state by arm directions (module docstring).

    ``linear`` is the waist's eq.-2 map (its mirror, calibration and limits are this retargeter's);
    ``kinematics`` an instance only this retargeter calls (it overwrites its buffers);
    ``rates`` the filter of the rates (8 channels, :func:`shared.lowpass.angle_rate_filter`);
    ``body`` the self-collision barriers whose h (with margin ``phi``, m) the target keeps
    ≥ ``clearance`` (m), solved by ``backend``;
    ``max_speed`` (8,) rad/s the fastest an arm target moves between states (None: unbounded).
    """

    def __init__(self, linear: Retargeter, kinematics: RobotKinematics, rates: RateFilter,
                 body: Sequence[Barrier] = (), phi: float = 0.0, clearance: float = 0.0,
                 backend: QPBackend | None = None, max_speed: np.ndarray | None = None) -> None:
        if body and backend is None:
            raise SafetyConfigError("a body to keep clear of needs a QP backend")
        self.linear = linear
        self.kinematics = kinematics
        self.rates = rates
        self.body = tuple(body)
        self.phi = phi
        self.clearance = clearance
        self.backend = backend
        self.max_speed = None if max_speed is None else np.asarray(max_speed, dtype=np.float64)
        # per problem size: unit weights (the backend keeps its buffers while ``w`` is the same object)
        # and no bounds on v (the joint ranges are the projection after the step)
        self._unbounded = {n: (np.ones(n), np.full(n, -INF_BOUND), np.full(n, INF_BOUND)) for n in (3, 6)}
        self._q = linear.hold_value()
        self._solved = np.zeros(2, bool)  # arm solved in the previous state
        self._t: float | None = None

    @property
    def mirror(self) -> bool:
        """Facing the person: the robot's left arm takes the person's right (and the waist mirrors)."""
        return self.linear.mirror

    @property
    def q_min(self) -> np.ndarray:
        return self.linear.q_min

    @property
    def q_max(self) -> np.ndarray:
        return self.linear.q_max

    def hold(self, q_nom: np.ndarray) -> None:
        """Continue from ``q_nom`` (8,): the arms' next solve starts there; no rate across it."""
        self.linear.hold(q_nom)
        self._q = self.linear.hold_value()
        self._solved[:] = False
        self.rates.reset()

    def calibrate(self, theta: np.ndarray) -> None:
        """θ_home for the waist's eq. 2 (the arms need none: directions are absolute)."""
        self.linear.calibrate(theta)

    def warm_up(self) -> None:
        """One throw-away solve of the robot's own arms at its held target, state restored after: the
        first call pays one-time setup (≈ 7 ms measured here) that must not fall inside a tick."""
        saved = (self._q.copy(), self._solved.copy(), copy.deepcopy(self.rates), self._t)
        q = self.linear.hold_value()
        ends = self.kinematics.compute(q)[0]
        c = {name: i for i, name in enumerate(CAPSULE_NAMES)}
        points, valid = np.zeros((len(KEYPOINT_NAMES), 3)), np.zeros(len(KEYPOINT_NAMES), bool)
        points[KEYPOINT_INDEX["pelvis"]] = ends[c["torso"], 0]
        for side in ("left", "right"):
            upper, fore = ends[c[f"{side}_upper_arm"]], ends[c[f"{side}_forearm"]]
            for joint, point in (("shoulder", upper[0]), ("elbow", upper[1]), ("wrist", upper[1] + fore[1] - fore[0])):
                points[KEYPOINT_INDEX[f"{side}_{joint}"]] = point
        valid[[KEYPOINT_INDEX[n] for n in ("pelvis", "left_shoulder", "right_shoulder", "left_elbow", "right_elbow",
                                           "left_wrist", "right_wrist")]] = True
        self.track(Pose(np.zeros(len(q)), np.zeros(len(q), bool), np.zeros(len(q)), points, valid, 0.0))
        if self.body:
            self._clear_step(q, ARM_JOINTS[0], np.full(3, -1.0), np.eye(3), np.zeros(3), *self.kinematics.compute(q))
        self._q, self._solved, self.rates, self._t = saved

    def track(self, pose: PoseLike) -> tuple[np.ndarray, np.ndarray]:
        """(q_nom, q̇_nom) for ``pose`` (module docstring)."""
        q_lin, dq_lin = self.linear.track(pose)
        person = person_arm_directions(np.asarray(pose.keypoints, float), np.asarray(pose.keypoint_valid, bool),
                                       self.mirror, MIN_SEGMENT)
        q_prev = self._q.copy()
        q = q_prev.copy()
        q[:2] = q_lin[:2]
        solved = np.array([bool(np.isfinite(person[rows[0]]).all()) for rows in _ARM_ROWS])
        moving = np.concatenate([ARM_JOINTS[arm] for arm in range(2) if solved[arm]]) if solved.any() else None
        if moving is not None:
            q = self._solve(q, person, moving)
            q = self._speed_limited(q, q_prev, float(pose.stamp), solved)
        self._q = q
        self._update_rates(pose, q, q_prev, solved)
        dq = self.rates.rate.copy()
        dq[:2] = dq_lin[:2]
        return q.copy(), dq

    def _speed_limited(self, q: np.ndarray, q_prev: np.ndarray, t: float, solved: np.ndarray) -> np.ndarray:
        """``q`` with each arm solved in this and the previous state moved from ``q_prev`` by at most
        ``max_speed`` × the time between the states."""
        if self.max_speed is None or self._t is None:
            return q
        reach = self.max_speed * max(t - self._t, 0.0)
        for arm, joints in enumerate(ARM_JOINTS):
            if solved[arm] and self._solved[arm]:
                q[joints] = q_prev[joints] + np.clip(q[joints] - q_prev[joints], -reach[joints], reach[joints])
        return q

    def _solve(self, q: np.ndarray, person: np.ndarray, moving: np.ndarray) -> np.ndarray:
        """Projected Levenberg–Marquardt on the joints ``moving`` (module docstring)."""
        lo, hi = self.q_min[moving], self.q_max[moving]
        rows = np.flatnonzero(np.isfinite(person).all(axis=1))
        capsules, target = ARM_CAPSULES[rows], np.ascontiguousarray(person[rows])
        hessian, gradient = np.empty((len(moving), len(moving))), np.empty(len(moving))
        anchor = q[moving].copy()
        for _ in range(MAX_ITERATIONS):
            endpoints, jacobians = self.kinematics.compute(q)
            if not direction_normal_equations(endpoints, jacobians, FRAME_CAPSULES, capsules, target, moving, DAMPING + ANCHOR,
                                              MIN_SEGMENT, hessian, gradient):
                break
            gradient -= ANCHOR * (q[moving] - anchor)
            step = np.clip(np.linalg.solve(hessian, gradient), lo - q[moving], hi - q[moving])
            if self.body:
                step = self._clear_step(q, moving, step, hessian, gradient, endpoints, jacobians)
                if step is None:
                    break
            new = np.clip(q[moving] + step, lo, hi)
            change = float(np.max(np.abs(new - q[moving])))
            q[moving] = new
            if change < STEP_TOLERANCE:
                break
        return q

    def _clear_step(self, q: np.ndarray, moving: np.ndarray, free_step: np.ndarray, hessian: np.ndarray,
                    gradient: np.ndarray, endpoints: np.ndarray, jacobians: np.ndarray) -> np.ndarray | None:
        """The step Δ of the QP in the module docstring (``free_step``, the unconstrained optimum
        clipped to the joint ranges, where that keeps every self row); None if it has no solution."""
        blocks = [barrier.constraint_rows(q, endpoints, jacobians, 1.0, self.phi, 0.0, None) for barrier in self.body]
        grad_h = np.concatenate([block.A for block in blocks])[:, moving]
        h = np.concatenate([block.h for block in blocks])
        keep = np.isfinite(h) & np.any(grad_h != 0.0, axis=1)
        if (grad_h[keep] @ free_step >= self.clearance - h[keep]).all():
            return free_step
        n = len(moving)
        cholesky = np.linalg.cholesky(hessian)
        inverse_t = np.linalg.inv(cholesky).T  # Δ = L⁻ᵀ v
        unbounded = self._unbounded[n]
        problem = QPProblem(w=unbounded[0], u_ref=np.linalg.solve(cholesky, gradient), A=grad_h[keep] @ inverse_t,
                            b=self.clearance - h[keep], lower=unbounded[1], upper=unbounded[2])
        solution = self.backend.solve(problem)
        return None if solution.u is None else inverse_t @ solution.u

    def _update_rates(self, pose: PoseLike, q: np.ndarray, q_prev: np.ndarray, solved: np.ndarray) -> None:
        t = float(pose.stamp)
        dt = 0.0 if self._t is None else t - self._t
        person_rates = np.asarray(pose.theta_rate, float)
        if self.mirror:
            person_rates = mirror_pose(person_rates)
        usable = np.zeros(len(q), bool)
        for arm, joints in enumerate(ARM_JOINTS):
            restarted = not (person_rates[joints] != 0.0).any()
            usable[joints] = solved[arm] and self._solved[arm] and not restarted
        if dt > 0.0:
            self.rates.update(dt, q - q_prev, usable)
        else:
            self.rates.reset()
        self.rates.reset((q <= self.q_min) | (q >= self.q_max))
        self._solved = solved
        self._t = t
