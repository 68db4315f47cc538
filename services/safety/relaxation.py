"""The lexicographic relaxed solve: the least total violation of the rows first, tracking second
(issue "Safety that holds when the person is faster than the robot", item 1; the policy around it —
which box, when to stop — is :class:`~services.safety.filter.SafetyFilter`'s, module docstring there).

Given rows A u ≥ b in a box lower ≤ u ≤ upper that no u satisfies together, with b⁰ = b − margin
(each row's own bound without the self margin the filter adds to the hard distance rows), row i may
fall to its floor

    f_i = min(b⁰_i, 0)                        a hard row (b⁰_i ≤ 0: it holds)
    f_i = min(b⁰_i, 0, A_i ū)                 a soft (robot–person) row, or a hard one already violated

with ū the braking point: the box's point nearest rest, 0 in a velocity box; inside an
acceleration bound the hardest braking it allows, ū = clip(0, lower, upper). With ``keep_hard``,
where that breaks a hard row that holds (A_i ū < b⁰_i: the arm slides along its own body and
braking every joint at once would turn it in), ū is instead the nearest to rest of the box's
points that keep them, ū = argmin ½‖u‖²_W s.t. A_i u ≥ b⁰_i on those rows
(:meth:`LexicographicSolver.braking`): the robot closes on a person no faster than it can brake
without hitting itself. σ_i ∈ [0, b_i − f_i],
A_i u + σ_i ≥ b_i. Only rows with b_i > f_i get a slack variable: a hard row that holds even with its
margin (b_i ≤ 0) has none, one inside its margin only the margin's. Two QPs in order:

1. least violation: min Σ c_i σ_i + ½ε‖u − u_ref‖²_W + ½ε‖σ‖² (strictly convex), c_i = 1 for a soft
   row and ``relax_penalty`` for a hard row already violated;
2. best tracking among the least-violating: min ½‖u − target‖²_W + ½ε‖σ‖² with σ_i ≤ σ_i* + tol:
   stage 1's solution is feasible here, so the total violation cannot grow. The target is u_ref, or
   ū when a soft row gave way in stage 1 (:func:`intrudes`: the protective stop); with ``rest`` both
   stages aim at ū.

*Feasible by construction*, with ``keep_hard``, whenever some u in the box keeps the hard rows that
hold, A_i u ≥ b⁰_i (then ū exists): u = ū, σ_i = max(b_i − A_i ū, 0) is within every σ_i's bounds (A_i ū ≥ f_i: by the
choice of f_i on a soft or violated row, by the choice of ū on a hard row that holds), and a row
without slack has b_i = f_i. In a velocity box ū = 0 keeps every hard row that holds (b⁰_i ≤ 0 =
A_i 0), so stage 1 is feasible there always (the filter's last box). Without ū (no u in the box
keeps those rows) the solve reports failure at once and the filter tries its next, wider box.
Without ``keep_hard`` a ū that breaks a hard row may leave the box infeasible: the filter's first
boxes, within the motors' torque, keep the person's floors that way when they can
(:class:`~services.safety.filter.SafetyFilter`, "Acceleration bound").

Both stages are solved by DAQP, whatever backend the plain QP uses: an active-set solver is exact
on these small LP-like, badly scaled problems (costs up to ``relax_penalty`` against the
ε-regularisation), where OSQP's first-order iterations stall.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.safety.qp import QPBackend, QPProblem, make_backend

__all__ = ["RELAXED_PRIMAL_TOL", "RELAXED_TOL", "LexicographicSolver", "RelaxedSolution", "intrudes"]

#: strict-convexity regularisation of the relaxed stages (weight of ‖σ‖², and of ‖u − u_ref‖² in stage 1)
_EPS = 1e-4
#: slack above stage 1's a stage-2 row may take (solver tolerance)
_SLACK_TOL = 1e-6
#: DAQP's primal tolerance in the relaxed stages (m/s of barrier rate): near-static rows (|A_i| ~ 1e-4)
#: pin σ_i at its cap, and at 1e-9 DAQP declared such feasible problems infeasible (44 steps of one
#: development clip)
RELAXED_PRIMAL_TOL = 1e-6
#: a slack above this (m/s of barrier rate) means its row gave way
RELAXED_TOL = 1e-6


def intrudes(slack: np.ndarray, soft: np.ndarray) -> bool:
    """Whether a soft (robot–person) row gave way: its ``slack`` (m,) above :data:`RELAXED_TOL`
    (``soft`` (m,) bool). Then the tracking stage aims at rest, not at u_ref (the protective stop)."""
    return bool((slack[soft] > RELAXED_TOL).any())


@dataclass(frozen=True)
class RelaxedSolution:
    """``u`` (n,) rad/s (None: both stages failed numerically), ``slack`` (m,) σ per row (0 where the
    row has none), ``seconds`` spent in the solvers, ``gave``: a soft row gave way (:func:`intrudes`)."""

    u: np.ndarray | None
    slack: np.ndarray
    seconds: float
    gave: bool


class LexicographicSolver:
    """The two stages of the module docstring and the braking point ū, each on its own DAQP instance
    (warm starts kept apart)."""

    def __init__(self) -> None:
        self._least: QPBackend = make_backend("daqp", primal_tol=RELAXED_PRIMAL_TOL)
        self._tracking: QPBackend = make_backend("daqp", primal_tol=RELAXED_PRIMAL_TOL)
        self._braking: QPBackend = make_backend("daqp", primal_tol=RELAXED_PRIMAL_TOL)

    def solve(self, problem: QPProblem, soft: np.ndarray, margin: np.ndarray, relax_penalty: float,
              rest: bool = False, keep_hard: bool = True) -> RelaxedSolution:
        """Relax ``problem``'s rows (``soft`` (m,) bool: the robot–person rows; ``margin`` (m,) each
        row's b shift) at stage-1 cost ``relax_penalty`` for a violated hard row; with ``rest`` both
        stages aim at ū instead of ``problem.u_ref``; ``keep_hard``: ū keeps the hard rows that hold
        (:meth:`braking`; else it is the box's point nearest rest). If only stage 2 fails, stage 1's
        u is returned."""
        n, m = problem.n, problem.m
        own = problem.b - margin
        floor = np.minimum(own, 0.0)
        give = soft | (own > 0.0)
        brake, seconds = self.braking(problem, own, ~give, keep_hard)
        if brake is None:  # no u in this box keeps the hard rows that hold
            return RelaxedSolution(None, np.zeros(m), seconds, False)
        reference = brake if rest else problem.u_ref
        floor[give] = np.minimum(floor[give], problem.A[give] @ brake)
        slack_cap = problem.b - floor
        loose = np.flatnonzero(slack_cap > 0.0)
        k = len(loose)
        cap = slack_cap[loose]  # σ ∈ [0, b − f] on the rows that may give way
        cost = np.where(soft[loose], 1.0, relax_penalty)
        columns = np.zeros((m, k))
        columns[loose, np.arange(k)] = 1.0
        A = np.hstack([problem.A, columns])
        lower = np.concatenate([problem.lower, np.zeros(k)])
        # stage 1: min Σ c σ + ½ε‖u − u_ref‖²_W + ½ε‖σ‖²  (the linear term as ½ε‖σ + c/ε‖²)
        least = QPProblem(w=np.concatenate([_EPS * problem.w, np.full(k, _EPS)]),
                          u_ref=np.concatenate([reference, -cost / _EPS]), A=A, b=problem.b,
                          lower=lower, upper=np.concatenate([problem.upper, cap]))
        first = self._least.solve(least)
        seconds += first.solve_time_s
        slack = np.zeros(m)
        if first.u is None:
            return RelaxedSolution(None, slack, seconds, False)
        sigma = np.clip(first.u[n:], 0.0, cap)
        # stage 2: min ½‖u − target‖²_W + ½ε‖σ‖²  with σ ≤ σ* (stage 1's solution is feasible here);
        # target = u_ref, or ū while a person row gives way (the protective stop)
        gave = intrudes(sigma, soft[loose])
        target = brake if gave else reference
        tracking = QPProblem(w=np.concatenate([problem.w, np.full(k, _EPS)]),
                             u_ref=np.concatenate([target, np.zeros(k)]), A=A, b=problem.b,
                             lower=lower, upper=np.concatenate([problem.upper, np.minimum(sigma + _SLACK_TOL, cap)]))
        second = self._tracking.solve(tracking)
        best = second if second.u is not None else first
        slack[loose] = np.clip(best.u[n:], 0.0, cap)
        return RelaxedSolution(best.u[:n], slack, seconds + second.solve_time_s, gave)

    def braking(self, problem: QPProblem, own: np.ndarray, hard: np.ndarray,
                keep_hard: bool = True) -> tuple[np.ndarray | None, float]:
        """(ū, seconds): the braking point of ``problem``'s box (module docstring): clip(0, lower, upper)
        without ``keep_hard`` or if it keeps the ``hard`` (m,) rows that hold at their own bounds ``own``
        (m,), A_i ū ≥ own_i (within the solver's tolerance), else the point of the box nearest rest in
        the W-norm that keeps them; None when none does."""
        brake = np.clip(0.0, problem.lower, problem.upper)
        A, bound = problem.A[hard], own[hard]
        if not keep_hard or (A @ brake >= bound - RELAXED_PRIMAL_TOL).all():
            return brake, 0.0
        nearest = self._braking.solve(QPProblem(w=problem.w, u_ref=np.zeros(problem.n), A=A, b=bound,
                                                lower=problem.lower, upper=problem.upper))
        return nearest.u, nearest.solve_time_s
