"""The CBF-QP problem, its solution type and the backend interface."""

from __future__ import annotations

import abc
import math
from dataclasses import dataclass, field
from enum import Enum

import numpy as np


#: a bound of this magnitude or more is infinite (DAQP's convention; a row A_i u ≥ b_i's upper bound)
INF_BOUND = 1e30


class QPStatus(str, Enum):
    OPTIMAL = "optimal"
    INFEASIBLE = "infeasible"
    FAILED = "failed"  # iteration limit, numerical trouble, non-finite output


@dataclass
class QPProblem:
    """min ½ (u − u_ref)ᵀ diag(w) (u − u_ref)  s.t.  A u ≥ b,  lower ≤ u ≤ upper.

    Shapes: ``w``, ``u_ref``, ``lower``, ``upper`` (n,); ``A`` (m, n); ``b`` (m,). ``stacked``
    (optional, a producer that already has them): (f, bounds_lower, bounds_upper) = (−W u_ref (n,),
    [lower; b] (n + m,), [upper; INF_BOUND] (n + m,)), the same values in the layout a dense solver
    with simple bounds first takes (DAQP uses them as they are; the other backends ignore them).
    """

    w: np.ndarray
    u_ref: np.ndarray
    A: np.ndarray
    b: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    stacked: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None

    @property
    def n(self) -> int:
        return self.u_ref.shape[0]

    @property
    def m(self) -> int:
        return self.b.shape[0]

    def violation(self, u: np.ndarray, slack: np.ndarray) -> float:
        """Largest violation of rows (``slack`` = A u − b) and bounds by ``u`` (≥ 0; 0: feasible)."""
        return max(0.0, -float(slack.min(initial=0.0)), float((self.lower - u).max()), float((u - self.upper).max()))


@dataclass
class QPSolution:
    """A backend's answer: ``u`` (n,) when OPTIMAL, the status, residuals and timing.

    ``primal_residual`` (max violation of rows and bounds by u) is computed when first read: the
    filter never needs it, so its step does not pay for it.
    """

    u: np.ndarray | None
    status: QPStatus
    solve_time_s: float
    iterations: int = 0
    active_rows: int = 0  # rows within tolerance of equality at u
    problem: QPProblem | None = field(default=None, repr=False)  # what u solves (for the residual)
    slack: np.ndarray | None = field(default=None, repr=False)  # A u − b

    @property
    def primal_residual(self) -> float:
        if self.u is None or self.problem is None or self.slack is None:
            return float("nan")
        return self.problem.violation(self.u, self.slack)


class QPBackend(abc.ABC):
    """Solves :class:`QPProblem` instances of a (mostly) fixed size, warm-starting from the last one."""

    name: str = "abstract"
    #: rows with A_i u − b_i below this count as active (binding)
    active_tol: float = 1e-6

    @abc.abstractmethod
    def solve(self, problem: QPProblem) -> QPSolution:
        """Solve ``problem``; never raises for a numerical failure (returns FAILED/INFEASIBLE)."""

    def _finish(self, problem: QPProblem, u: np.ndarray | None, status: QPStatus, seconds: float, iterations: int) -> QPSolution:
        """Common post-processing: reject non-finite output, compute residual and active rows."""
        if u is None or not math.isfinite(u.dot(u)):  # NaN/Inf (or an absurd |u| > 1e154) anywhere
            return QPSolution(None, QPStatus.FAILED if status is QPStatus.OPTIMAL else status, seconds, iterations)
        if status is not QPStatus.OPTIMAL:
            return QPSolution(None, status, seconds, iterations)
        slack = problem.A @ u
        slack -= problem.b
        return QPSolution(u, status, seconds, iterations, int(np.count_nonzero(slack <= self.active_tol)), problem, slack)
