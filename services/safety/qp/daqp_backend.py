"""DAQP backend: a dual active-set solver, dense, fastest here on 8 variables × O(100) rows."""

from __future__ import annotations

import os
import time
from pathlib import Path

# numba caches compiled code on disk: as services.safety.barriers.kernel, in the user's cache folder
os.environ.setdefault("NUMBA_CACHE_DIR", str(Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "safemimic" / "numba"))

import daqp  # noqa: E402
import numpy as np  # noqa: E402
from numba import njit  # noqa: E402

from services.safety.compiled import BoundKernel  # noqa: E402
from services.safety.qp.base import INF_BOUND, QPBackend, QPProblem, QPSolution, QPStatus  # noqa: E402

#: DAQP's constraint flags (``sense``; include/constants.h): bit 1 = in the working set (active),
#: bit 2 = active at its *lower* bound (clear: at its upper bound)
DAQP_ACTIVE = 1
DAQP_LOWER = 2
#: a multiplier beyond ±this marks its constraint active (DAQP's own daqp_dual_init_active threshold)
_DUAL_TOL = 1e-12


@njit(cache=True, nogil=True, inline="always")
def _warm_sense(lam, tol, sense):  # pragma: no cover - compiled
    for i in range(lam.shape[0]):
        if lam[i] > tol:
            sense[i] = DAQP_ACTIVE
        elif lam[i] < -tol:
            sense[i] = DAQP_ACTIVE | DAQP_LOWER
        else:
            sense[i] = 0


def warm_sense(lam: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """DAQP ``sense`` flags of the active set of multipliers ``lam`` (DAQP's sign convention:
    λ > 0 upper bound active → ACTIVE, λ < 0 lower bound active → ACTIVE | LOWER, else 0)."""
    sense = np.zeros(lam.shape[0], dtype=np.intc) if out is None else out
    _warm_sense(lam, _DUAL_TOL, sense)
    return sense


@njit(cache=True, nogil=True)
def _pack(neg_w, u_ref, lower_u, upper_u, b, f, upper, lower):  # pragma: no cover - compiled
    """f = −W u_ref; DAQP's bounds: the simple bounds first, then the rows' lower bounds b."""
    n = u_ref.shape[0]
    for j in range(n):
        f[j] = neg_w[j] * u_ref[j]
        upper[j] = upper_u[j]
        lower[j] = lower_u[j]
    for i in range(b.shape[0]):
        lower[n + i] = b[i]


@njit(cache=True, nogil=True)
def _settle(lam, dual_tol, sense, A, b, u, tol, slack):  # pragma: no cover - compiled
    """After an optimal solve: ``sense`` ← the warm-start flags of ``lam`` (:func:`warm_sense`); −1 if
    uᵀu is not finite (NaN/Inf, or an absurd |u| > 1e154), else slack = A u − b and the number of
    rows with slack ≤ tol (active)."""
    _warm_sense(lam, dual_tol, sense)
    norm = 0.0
    for j in range(u.shape[0]):
        norm += u[j] * u[j]
    if not np.isfinite(norm):
        return -1
    active = 0
    for i in range(A.shape[0]):
        acc = 0.0
        for j in range(A.shape[1]):
            acc += A[i, j] * u[j]
        slack[i] = acc - b[i]
        if slack[i] <= tol:
            active += 1
    return active


class DaqpBackend(QPBackend):
    """min ½ uᵀHu + fᵀu with H = diag(w), f = −W u_ref; simple bounds first, then rows A u ≥ b.

    Warm start (``warm_start``, on by default): when the problem size is unchanged, the previous
    solution's active set is passed as DAQP ``sense`` flags, each active constraint marked at the
    bound its multiplier's sign says (:func:`warm_sense`; a row A_i u ≥ b_i is DAQP's lower bound).
    A warm solve that fails is repeated cold, so the answer never depends on the warm start.
    """

    name = "daqp"

    def __init__(self, iter_limit: int = 1000, primal_tol: float = 1e-9, warm_start: bool = True) -> None:
        self._iter_limit, self._primal_tol = iter_limit, primal_tol  # passed as keywords (no ** dict per solve)
        self.warm_start = warm_start
        self._warm = False  # _sense holds a usable active set
        self._w: np.ndarray | None = None
        self._w_src: np.ndarray | None = None  # the weights array H was last checked against
        self._H = np.empty((0, 0))
        self._neg_w = np.empty(0)
        self._shape = (0, 0)  # (n, m) of the vectors below
        self._f = np.empty(0)
        self._upper = np.empty(0)
        self._lower = np.empty(0)
        self._sense = np.zeros(0, dtype=np.intc)
        self._cold = np.zeros(0, dtype=np.intc)
        # _settle of a stacked problem (QPProblem.stacked: its producer's own buffers, the same types
        # at every solve) through its entry point; other problems through numba's dispatcher
        self._settle_stacked = BoundKernel(_settle)

    @property
    def _settings(self) -> dict[str, float]:
        """DAQP's settings, as the keywords every solve passes."""
        return {"iter_limit": self._iter_limit, "primal_tol": self._primal_tol}

    def _buffers(self, problem: QPProblem, shape: tuple[int, int]) -> None:
        """(Re)build H only when the weights change (the same array object as last time counts as
        unchanged: FilterParams are replaced, never mutated) and the vectors when the ``shape`` (n, m)
        does."""
        w = problem.w
        if w is not self._w_src:
            if self._w is None or not np.array_equal(self._w, w):
                self._w = w.copy()
                self._H = np.diag(self._w)
                self._neg_w = -self._w
            self._w_src = w
        if shape != self._shape:
            n, m = shape
            self._f = np.empty(n)
            self._upper = np.full(n + m, INF_BOUND)
            self._lower = np.empty(n + m)
            self._sense = np.zeros(n + m, dtype=np.intc)
            self._cold = np.zeros(n + m, dtype=np.intc)
            self._warm = False
            self._shape = shape

    def solve(self, problem: QPProblem) -> QPSolution:
        start = time.perf_counter()
        shape = (problem.u_ref.shape[0], problem.b.shape[0])
        if problem.w is not self._w_src or shape != self._shape:
            self._buffers(problem, shape)
        H = self._H
        if problem.stacked is None:
            f, upper, lower = self._f, self._upper, self._lower
            _pack(self._neg_w, problem.u_ref, problem.lower, problem.upper, problem.b, f, upper, lower)
        else:  # the producer's own f and bounds in DAQP's layout (QPProblem.stacked)
            f, lower, upper = problem.stacked
        warm = self._warm and self.warm_start
        x, _, exitflag, info = daqp.solve(H, f, problem.A, upper, lower, self._sense if warm else self._cold,
                                          iter_limit=self._iter_limit, primal_tol=self._primal_tol)
        iterations = info["iterations"]
        if warm and exitflag not in (1, 2):  # e.g. the old working set is overdetermined now
            x, _, exitflag, info = daqp.solve(H, f, problem.A, upper, lower, self._cold, iter_limit=self._iter_limit,
                                              primal_tol=self._primal_tol)
            iterations += info["iterations"]
        if exitflag in (1, 2):
            slack = np.empty(problem.m)
            settle = _settle if problem.stacked is None else self._settle_stacked.call
            active = settle(info["lam"], _DUAL_TOL, self._sense, problem.A, problem.b, x, self.active_tol, slack)
            self._warm = True
            seconds = time.perf_counter() - start
            if active < 0:
                return QPSolution(None, QPStatus.FAILED, seconds, iterations)
            return QPSolution(x, QPStatus.OPTIMAL, seconds, iterations, active, problem, slack)
        self._warm = False
        status = QPStatus.INFEASIBLE if exitflag == -1 else QPStatus.FAILED
        return self._finish(problem, x, status, time.perf_counter() - start, iterations)
