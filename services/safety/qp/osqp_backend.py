"""OSQP backend (the design card's solver): sparsity built once, values updated, warm-started."""

from __future__ import annotations

import time

import numpy as np
import osqp
from scipy import sparse

from services.safety.qp.base import QPBackend, QPProblem, QPSolution, QPStatus

_SOLVED = {osqp.SolverStatus.OSQP_SOLVED}
_INFEASIBLE = {osqp.SolverStatus.OSQP_PRIMAL_INFEASIBLE, osqp.SolverStatus.OSQP_PRIMAL_INFEASIBLE_INACCURATE}


class OsqpBackend(QPBackend):
    """OSQP on  P = diag(w), q = −W u_ref,  l ≤ [A; I] u ≤ u  with l = [b; lower], u = [∞; upper].

    The constraint matrix is stored dense-pattern (every entry structurally non-zero) so the
    sparsity never changes for a fixed row count: later steps only call ``update``.
    """

    name = "osqp"

    def __init__(self, eps: float = 1e-6, max_iter: int = 4000) -> None:
        # Iterations are bounded (not wall time, which would make results depend on machine load):
        # an infeasible problem fails within a few thousand cheap iterations and the filter relaxes.
        # Polishing is off: OSQP 1.x prints a line on every solve it does not polish.
        self._settings = dict(
            eps_abs=eps, eps_rel=eps, max_iter=max_iter, polishing=False, verbose=False, warm_starting=True,
        )
        self._solver: osqp.OSQP | None = None
        self._shape: tuple[int, int] | None = None
        self._index: np.ndarray | None = None  # CSC data order → dense (row, col) flat index

    def _setup(self, problem: QPProblem) -> None:
        n, m = problem.n, problem.m
        pattern = sparse.csc_matrix(np.vstack([np.ones((m, n)), np.eye(n)]))
        rows = pattern.indices
        cols = np.repeat(np.arange(n), np.diff(pattern.indptr))
        self._index = rows * n + cols
        A = sparse.csc_matrix((self._stacked(problem).ravel()[self._index], pattern.indices, pattern.indptr), shape=pattern.shape)
        q, lower, upper = self._vectors(problem)
        self._solver = osqp.OSQP()
        self._solver.setup(sparse.csc_matrix(np.diag(problem.w)), q, A, lower, upper, **self._settings)
        self._shape = (m, n)

    @staticmethod
    def _stacked(problem: QPProblem) -> np.ndarray:
        return np.vstack([problem.A, np.eye(problem.n)])

    @staticmethod
    def _vectors(problem: QPProblem) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        q = -problem.w * problem.u_ref
        lower = np.concatenate([problem.b, problem.lower])
        upper = np.concatenate([np.full(problem.m, np.inf), problem.upper])
        return q, lower, upper

    def solve(self, problem: QPProblem) -> QPSolution:
        start = time.perf_counter()
        if self._solver is None or self._shape != (problem.m, problem.n):
            self._setup(problem)
        else:
            q, lower, upper = self._vectors(problem)
            self._solver.update(q=q, l=lower, u=upper, Ax=self._stacked(problem).ravel()[self._index], Px=problem.w.copy())
        assert self._solver is not None
        result = self._solver.solve(raise_error=False)
        seconds = time.perf_counter() - start
        status_val = result.info.status_val
        if status_val in _SOLVED:
            status = QPStatus.OPTIMAL
        elif status_val in _INFEASIBLE:
            status = QPStatus.INFEASIBLE
        else:
            status = QPStatus.FAILED
        u = None if result.x is None else np.array(result.x, dtype=np.float64)
        return self._finish(problem, u, status, seconds, int(result.info.iter))
