"""DAQP backend: a dual active-set solver, dense, fastest here on 8 variables × O(100) rows."""

from __future__ import annotations

import time

import daqp
import numpy as np

from services.safety.qp.base import QPBackend, QPProblem, QPSolution, QPStatus

_INF = 1e30  # DAQP treats |bound| ≥ 1e30 as infinite


class DaqpBackend(QPBackend):
    """min ½ uᵀHu + fᵀu with H = diag(w), f = −W u_ref; simple bounds first, then rows A u ≥ b.

    Warm start: the previous solution's active set is passed as ``sense`` = 1 (active) flags
    when the problem size is unchanged.
    """

    name = "daqp"

    def __init__(self, iter_limit: int = 1000, primal_tol: float = 1e-9) -> None:
        self._settings = {"iter_limit": iter_limit, "primal_tol": primal_tol}
        self._sense: np.ndarray | None = None
        self._w: np.ndarray | None = None
        self._H = np.empty((0, 0))
        self._upper = np.empty(0)
        self._lower = np.empty(0)

    def _buffers(self, problem: QPProblem) -> None:
        """(Re)build H and the bound vectors only when the weights or the sizes change."""
        n, m = problem.n, problem.m
        if self._w is None or self._w.shape != problem.w.shape or not np.array_equal(self._w, problem.w):
            self._w = problem.w.copy()
            self._H = np.diag(self._w)
        if self._upper.shape[0] != n + m:
            self._upper = np.full(n + m, _INF)
            self._lower = np.empty(n + m)
            self._sense = np.zeros(n + m, dtype=np.int32)

    def solve(self, problem: QPProblem) -> QPSolution:
        start = time.perf_counter()
        n = problem.n
        self._buffers(problem)
        H = self._H
        f = -problem.w * problem.u_ref
        upper, lower = self._upper, self._lower
        upper[:n] = problem.upper
        lower[:n] = problem.lower
        lower[n:] = problem.b
        if self._sense is None:
            self._sense = np.zeros(upper.shape[0], dtype=np.int32)
        x, _, exitflag, info = daqp.solve(H, f, problem.A, upper, lower, self._sense, **self._settings)
        if exitflag in (1, 2):
            status = QPStatus.OPTIMAL
            self._sense = (info["lam"] != 0.0).astype(np.int32)
        else:
            status = QPStatus.INFEASIBLE if exitflag == -1 else QPStatus.FAILED
            self._sense = None
        return self._finish(problem, x, status, time.perf_counter() - start, int(info["iterations"]))
