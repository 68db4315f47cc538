"""The CBF-QP safety filter: one control step (paper eqs. 7–9; DESIGN §4).

    u_ref = K (q_nom − q_cbf)
    u* = argmin ½ ‖u − u_ref‖²_W  s.t.  A(q_cbf) u ≥ b,  u_lo ≤ u ≤ u_hi
    q_cbf⁺ = q_cbf + Δt u*

with u_lo/u_hi the velocity bounds intersected with the joint limits reachable in one step; u* is
clipped to them whatever the solver returns, so |q_cbf⁺ − q_cbf| ≤ u_max Δt holds exactly.
If the rows are infeasible (or the solver fails) a relaxed problem with one slack shared by
every row, min … + ½ ρ σ²  s.t.  A u + σ 1 ≥ b, σ ≥ 0, is solved instead: the smallest uniform
violation (no row is given up for the others) in n + 1 variables however many rows there are.
If that fails too the filter holds (u* = 0). The mode says which happened; the output is always finite. A state that is
already inside a barrier (h < −1 mm: the person moved into the robot faster than it could
retreat) is reported as RELAXED too: the constraints are not being honoured there.

The robot description's joint barriers (``joint_barriers``: links the capsules cannot see) add
one row each: u_j ≥ −γ (q_j − lower_j) or −u_j ≥ −γ (upper_j − q_j).

With ``enforce`` off the rows are still evaluated (h is monitored) but left out of the QP, so
u* = clip(u_ref) within the bounds: the same integrator without the safety layer (the offline
evaluator's no-CBF run).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.safety.barrier import BarrierRows, CapsuleBarrier
from services.safety.qp import QPBackend, QPProblem, QPStatus, make_backend
from shared.messages import SafetyMode

#: upper bound of a slack variable (m/s of barrier rate): effectively unbounded
_SLACK_MAX = 1e6
#: a barrier below −VIOLATION_TOL (m) at the start of a step counts as violated
VIOLATION_TOL = 1e-3


@dataclass
class FilterParams:
    """The tunable parameters of one step (subset of shared.config.SafetyConfig)."""

    gamma: float
    phi: float
    gain: float
    weights: np.ndarray
    u_max: np.ndarray
    relax_penalty: float
    u_min: np.ndarray | None = None  # lower velocity bound (n,); None: −u_max
    human_lookahead_s: float = 0.0  # T of the human velocity term (s; see barrier.py)

    @classmethod
    def from_config(cls, safety) -> FilterParams:  # shared.config.SafetyConfig
        return cls(
            gamma=safety.gamma,
            phi=safety.phi,
            gain=safety.gain,
            weights=np.asarray(safety.weights, dtype=np.float64),
            u_max=np.asarray(safety.u_max, dtype=np.float64),
            relax_penalty=safety.relax_penalty,
            u_min=None if safety.u_min is None else np.asarray(safety.u_min, dtype=np.float64),
            human_lookahead_s=safety.human_lookahead_s,
        )


@dataclass
class StepResult:
    """Outcome of one step: the new q_cbf (n,), u* (n,), mode, barrier rows and solver facts."""

    q_cbf: np.ndarray
    u: np.ndarray
    u_ref: np.ndarray
    mode: SafetyMode
    rows: BarrierRows
    active_rows: int
    qp_time_s: float
    qp_status: QPStatus


def _joint_barriers(spec, joint_names: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Joint-barrier rows (k, n) and per row: joint index, sign, bound (sign (q_j − bound) ≥ 0 holds)."""
    rows = []
    for joint, (lower, upper) in spec.joint_barriers.items():
        j = joint_names.index(joint)
        rows += [(j, 1.0, lower)] if lower is not None else []
        rows += [(j, -1.0, upper)] if upper is not None else []
    index, sign, bound = (np.array(v, dtype=float) for v in (zip(*rows) if rows else ((), (), ())))
    index = index.astype(np.intp)
    return sign[:, None] * np.eye(len(joint_names))[index], index, sign, bound


class SafetyFilter:
    """Holds q_cbf and filters nominal targets through the capsule CBF-QP."""

    def __init__(self, kinematics, barrier: CapsuleBarrier, params: FilterParams, backend: str = "daqp") -> None:
        self.kinematics = kinematics
        #: Whether the CBF rows constrain the QP (False: rows only monitored, u* = clip(u_ref)).
        self.enforce = True
        self.barrier = barrier
        self.params = params
        self.backend_name = backend
        self._qp: QPBackend = make_backend(backend)
        self._relaxed_qp: QPBackend = make_backend(backend)
        self.q_min = np.asarray(kinematics.q_min, dtype=np.float64)
        self.q_max = np.asarray(kinematics.q_max, dtype=np.float64)
        self.q_cbf = np.clip(np.asarray(kinematics.q_home, dtype=np.float64), self.q_min, self.q_max)
        self._joint_barriers = _joint_barriers(kinematics.spec, kinematics.joint_names)

    def reset(self, q: np.ndarray) -> None:
        """Restart integration from configuration ``q`` (e.g. the measured joint state)."""
        q = np.asarray(q, dtype=np.float64)
        if q.shape == self.q_cbf.shape and np.isfinite(q).all():
            self.q_cbf = np.clip(q, self.q_min, self.q_max)

    def rows_at(self, q: np.ndarray) -> BarrierRows:
        """The barrier rows at configuration ``q`` (no QP, no state change)."""
        endpoints, jacobians = self.kinematics.compute(q)
        p = self.params
        return self.barrier.evaluate(endpoints, jacobians, p.gamma, p.phi, p.human_lookahead_s)

    def step(self, q_nom: np.ndarray, dt: float) -> StepResult:
        """One control step towards ``q_nom`` (n,) over ``dt`` seconds."""
        p = self.params
        q = self.q_cbf
        rows = self.rows_at(q)
        u_ref = p.gain * (np.asarray(q_nom, dtype=np.float64) - q)
        upper = np.minimum(p.u_max, (self.q_max - q) / dt)
        u_min = -p.u_max if p.u_min is None else p.u_min
        lower = np.minimum(np.maximum(u_min, (self.q_min - q) / dt), upper)
        if self.enforce:
            joint_rows, index, sign, bound = self._joint_barriers
            A = np.vstack([rows.A, joint_rows])
            b = np.concatenate([rows.b, -p.gamma * sign * (q[index] - bound)])
        else:
            A, b = rows.A[:0], rows.b[:0]
        problem = QPProblem(w=p.weights, u_ref=u_ref, A=A, b=b, lower=lower, upper=upper)
        solution = self._qp.solve(problem)
        qp_time = solution.solve_time_s
        u = solution.u
        if u is not None:
            mode = SafetyMode.ACTIVE if solution.active_rows else SafetyMode.NOMINAL
            if self.enforce and rows.min_h_all < -VIOLATION_TOL:
                mode = SafetyMode.RELAXED
            active = solution.active_rows
        else:
            relaxed = self._relaxed_qp.solve(self._relaxed(problem))
            qp_time += relaxed.solve_time_s
            if relaxed.u is not None:
                u, mode = relaxed.u[: problem.n], SafetyMode.RELAXED
                active = int(np.count_nonzero(rows.A @ u - rows.b <= 1e-6))
            else:
                u, mode, active = np.zeros(problem.n), SafetyMode.HOLD, 0
        u = np.minimum(np.maximum(u, lower), upper)  # an iterative solver's tolerance never exceeds u_max
        q_next = q + dt * u
        if not np.isfinite(q_next).all():
            u, q_next, mode = np.zeros(problem.n), q.copy(), SafetyMode.HOLD
        self.q_cbf = np.minimum(np.maximum(q_next, self.q_min), self.q_max)
        return StepResult(
            q_cbf=self.q_cbf.copy(), u=u, u_ref=u_ref, mode=mode, rows=rows, active_rows=active,
            qp_time_s=qp_time, qp_status=solution.status,
        )

    def _relaxed(self, problem: QPProblem) -> QPProblem:
        """[u; σ]: min ½‖u − u_ref‖²_W + ½ρσ²  s.t.  A u + σ 1 ≥ b,  σ ∈ [0, ∞)."""
        return QPProblem(
            w=np.append(problem.w, self.params.relax_penalty),
            u_ref=np.append(problem.u_ref, 0.0),
            A=np.hstack([problem.A, np.ones((problem.m, 1))]),
            b=problem.b,
            lower=np.append(problem.lower, 0.0),
            upper=np.append(problem.upper, _SLACK_MAX),
        )
