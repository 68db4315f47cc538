"""The QP's box and the integration step, compiled (numba): a step's QP inputs (u_ref, its first
box, the rows a velocity can move, all in DAQP's layout: :func:`prepare_qp`) in one call and its end
(clip, integration, ddq: :func:`integrate`) in another, instead of ~16 numpy calls on 8-element arrays (and ~40 for
the acceleration bound), the Python overhead that dominated the safety step (the profile in
docs/benchmarks.md).

Element by element the same IEEE operations as the numpy expressions they replace, so results
are bit-identical:

    upper = min(u_max, (q_max − q)/dt)      lower = min(max(u_min, (q_min − q)/dt), upper)
    u ← min(max(u, lower), upper)           q⁺ = clip(q + dt·u, q_min, q_max)

and for an acceleration bound a (rad/s², braking share β; h = β a Δt / 2):

    upper ← min(upper, √(2 β a max(q_max − q, 0) + h²) − h)
    lower ← min(max(lower, h − √(2 β a max(q − q_min, 0) + h²)), upper)
    [lo, hi] = clip(u_prev ∓ f a Δt, lower, upper)

and u_ref = K (q_nom − q) (+ q̇_nom), the QP's linear term f = −W u_ref, ddq = (u − u_prev)/Δt.
The helpers (``inline="always"``) are inlined into :func:`prepare_qp` and :func:`integrate`, as in
:mod:`services.safety.barriers.kernel` (the same operations, without a compiled call's overhead).
"""

from __future__ import annotations

import os
from pathlib import Path

# numba caches compiled code on disk: as services.safety.barriers.kernel, in the user's cache folder
os.environ.setdefault("NUMBA_CACHE_DIR", str(Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "safemimic" / "numba"))

import numpy as np  # noqa: E402
from numba import njit  # noqa: E402

from services.safety.barriers.kernel import row_moves  # noqa: E402


@njit(cache=True, nogil=True, inline="always")
def _box(q, q_min, q_max, u_min, u_max, negate_min, dt, lower, upper):  # pragma: no cover - compiled
    for j in range(q.shape[0]):
        hi = min(u_max[j], (q_max[j] - q[j]) / dt)
        lo = max(-u_max[j] if negate_min else u_min[j], (q_min[j] - q[j]) / dt)
        upper[j] = hi
        lower[j] = min(lo, hi)


@njit(cache=True, nogil=True, inline="always")
def _step(u, lower, upper, q, dt, q_min, q_max, u_out, q_out):  # pragma: no cover - compiled
    finite = True
    for j in range(q.shape[0]):
        uj = min(max(u[j], lower[j]), upper[j])
        u_out[j] = uj
        qj = q[j] + dt * uj
        if not np.isfinite(qj):
            finite = False
        q_out[j] = min(max(qj, q_min[j]), q_max[j])
    return finite


@njit(cache=True, nogil=True, inline="always")
def _brake(q, q_min, q_max, a, share, dt, lower, upper):  # pragma: no cover - compiled
    for j in range(q.shape[0]):
        brake = share * a[j]
        half = 0.5 * brake * dt
        hi = min(upper[j], np.sqrt(2.0 * brake * max(q_max[j] - q[j], 0.0) + half * half) - half)
        lower[j] = min(max(lower[j], half - np.sqrt(2.0 * brake * max(q[j] - q_min[j], 0.0) + half * half)), hi)
        upper[j] = hi


@njit(cache=True, nogil=True, inline="always")
def _reach(u_prev, a, factor, dt, lower, upper, low, high):  # pragma: no cover - compiled
    within = True
    for j in range(u_prev.shape[0]):
        reach = factor * a[j] * dt
        lo, hi = u_prev[j] - reach, u_prev[j] + reach
        within = within and lo <= upper[j] and hi >= lower[j]
        low[j] = min(max(lo, lower[j]), upper[j])
        high[j] = min(max(hi, lower[j]), upper[j])
    return within


@njit(cache=True, nogil=True, inline="always")
def _bounded(q, q_min, q_max, u_min, u_max, negate_min, accel, share, u_prev, factor, dt, lower, upper, low,
             high):  # pragma: no cover - compiled
    _box(q, q_min, q_max, u_min, u_max, negate_min, dt, lower, upper)
    _brake(q, q_min, q_max, accel, share, dt, lower, upper)
    return _reach(u_prev, accel, factor, dt, lower, upper, low, high)


#: rows of the filter's per-joint table (:func:`limits_table`): the constants Q_MIN … WEIGHT, then the
#: boxes :func:`prepare_qp` writes at every step (the velocity box, the acceleration-bounded box)
Q_MIN, Q_MAX, U_MIN, U_MAX, ACCEL, WEIGHT, LOWER, UPPER, LOW, HIGH = range(10)


def limits_table(q_min: np.ndarray, q_max: np.ndarray, u_min: np.ndarray | None, u_max: np.ndarray,
                 accel: np.ndarray | None, weights: np.ndarray) -> np.ndarray:
    """(10, n) the per-joint table of a step: the constants, rows :data:`Q_MIN` … :data:`WEIGHT` (the
    joint limits, the velocity bounds (u_min None: −u_max, the same values as negating in the
    kernel), the acceleration bound (None: 0, never read) and the QP weights w), then rows
    :data:`LOWER` … :data:`HIGH` (zero) for the boxes :func:`prepare_qp` writes (one array: one
    argument of the compiled step)."""
    return np.ascontiguousarray(np.stack([q_min, q_max, -u_max if u_min is None else u_min, u_max,
                                          np.zeros_like(u_max) if accel is None else accel, weights,
                                          *np.zeros((4, u_max.shape[0]))]), dtype=np.float64)


@njit(cache=True, nogil=True)
def prepare_qp(q_nom, dq_nom, feed, gain, q, limits, share, u_prev, bounded, dt, u_ref, A_all, b_all, shift,
               shifted, tol, enforce, A_qp, kept, stacked):  # pragma: no cover - compiled
    """A step's QP inputs in one call; returns (k, within).

    First, if ``shifted``, ``b_all`` (M,) ← ``b_all`` + ``shift`` (M,) in place, every row (the self
    margin's b shift: the same values as ``np.add(b_all, shift, out=b_all)``; the stacked b keeps it).
    ``u_ref`` ← ``gain`` (q_nom − q) (+ ``dq_nom`` if ``feed``); rows LOWER, UPPER of ``limits``
    (:func:`limits_table`, whose constant rows it reads) ← :func:`velocity_box` and, if ``bounded``,
    rows LOW, HIGH and within ← :func:`bounded_box` at factor 1 (within True when not bounded). With ``enforce``, the
    k stacked rows (``A_all``, ``b_all``) a velocity can move (their largest |A_ij| > ``tol``,
    ``services.safety.barriers.kernel``) are copied in order into ``A_qp`` and their indices into
    ``kept`` (k = 0 without). ``stacked`` (3, n + M) is the QP in DAQP's layout:
    row 0 [:n] ← f = −W u_ref, row 1 [:n + k] ← [box lower; b of the kept rows], row 2 [:n] ← box
    upper (the box used: LOW/HIGH if bounded, else LOWER/UPPER; row 2 [n:] holds ``INF_BOUND``, the caller's)."""
    n = q.shape[0]
    if shifted:
        for i in range(b_all.shape[0]):
            b_all[i] += shift[i]
    for j in range(n):
        u = gain * (q_nom[j] - q[j])
        u_ref[j] = u + dq_nom[j] if feed else u
        stacked[0, j] = -limits[WEIGHT, j] * u_ref[j]
    lower, upper = limits[LOWER], limits[UPPER]
    within = True
    if bounded:
        within = _bounded(q, limits[Q_MIN], limits[Q_MAX], limits[U_MIN], limits[U_MAX], False, limits[ACCEL], share,
                          u_prev, 1.0, dt, lower, upper, limits[LOW], limits[HIGH])
        lower, upper = limits[LOW], limits[HIGH]
    else:
        _box(q, limits[Q_MIN], limits[Q_MAX], limits[U_MIN], limits[U_MAX], False, dt, lower, upper)
    for j in range(n):
        stacked[1, j] = lower[j]
        stacked[2, j] = upper[j]
    k = 0
    if enforce:
        for i in range(A_all.shape[0]):
            if row_moves(A_all, i, tol):
                for j in range(n):
                    A_qp[k, j] = A_all[i, j]
                stacked[1, n + k] = b_all[i]
                kept[k] = i
                k += 1
    return k, within


@njit(cache=True, nogil=True)
def integrate(u, lower, upper, q, dt, limits, u_prev, has_prev, out):  # pragma: no cover - compiled
    """The integration step and the command's acceleration: ``out`` (4, n) rows ← u clipped to
    [``lower``, ``upper``], q⁺ = q + dt·u clipped to the joint limits (rows :data:`Q_MIN`,
    :data:`Q_MAX` of ``limits``, :func:`limits_table`), a copy of q⁺, ddq = (u −
    u_prev)/dt (zero unless ``has_prev``); False (``out`` partly written) when q⁺ is not finite."""
    u_out, q_out = out[0], out[1]
    if not _step(u, lower, upper, q, dt, limits[Q_MIN], limits[Q_MAX], u_out, q_out):
        return False
    for j in range(q.shape[0]):
        out[2, j] = q_out[j]
        out[3, j] = (u_out[j] - u_prev[j]) / dt if has_prev else 0.0
    return True


def velocity_box(q: np.ndarray, q_min: np.ndarray, q_max: np.ndarray, u_min: np.ndarray | None, u_max: np.ndarray,
                 dt: float) -> tuple[np.ndarray, np.ndarray]:
    """(lower, upper) (n,): the velocity bounds (u_min; None: −u_max) intersected with the joint
    limits reachable from ``q`` in ``dt``; lower ≤ upper always."""
    lower, upper = np.empty(q.shape[0]), np.empty(q.shape[0])
    _box(q, q_min, q_max, u_max if u_min is None else u_min, u_max, u_min is None, dt, lower, upper)
    return lower, upper


def reach_box(u_prev: np.ndarray, accel: np.ndarray, factor: float, dt: float, lower: np.ndarray,
              upper: np.ndarray) -> tuple[np.ndarray, np.ndarray, bool]:
    """(low, high, within) (n,): ``[u_prev − factor·accel·dt, u_prev + factor·accel·dt]`` clipped into
    ``[lower, upper]``; ``within``: no joint's reach lies wholly beyond the box (the clipped box is
    still that reach)."""
    low, high = np.empty(u_prev.shape[0]), np.empty(u_prev.shape[0])
    within = _reach(u_prev, accel, factor, dt, lower, upper, low, high)
    return low, high, within


def braking_box(low: np.ndarray, high: np.ndarray, u_prev: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(low, high) (n,): the box ``[low, high]`` narrowed per joint to the velocities between rest
    and ``u_prev``, [min(u_prev, 0), max(u_prev, 0)]: a joint may slow down, not speed up or turn
    back (a protective stop only brakes).

    Never empty and its point nearest rest unchanged, for any box of :func:`reach_box` in a
    velocity box containing 0 (every box the filter builds): that point p is clip(0, low, high). If
    0 ∈ [low, high], p = 0. Otherwise, say low > 0: low = max(u_prev − r, lower) with lower ≤ 0, so
    low = u_prev − r ≤ u_prev, or the reach lies wholly above the velocity box and p = upper ∈ [0,
    u_prev). Either way 0 < p ≤ u_prev (and symmetrically for high < 0), so p lies in both boxes."""
    return np.maximum(low, np.minimum(u_prev, 0.0)), np.minimum(high, np.maximum(u_prev, 0.0))


def bounded_box(q: np.ndarray, q_min: np.ndarray, q_max: np.ndarray, u_min: np.ndarray | None, u_max: np.ndarray,
                accel: np.ndarray, share: float, u_prev: np.ndarray, factor: float,
                dt: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, bool]:
    """(lower, upper, low, high, within): :func:`velocity_box` narrowed so that every joint can still
    stop at its limit decelerating at ``share`` × ``accel`` (n,) rad/s² in steps of ``dt`` (module
    docstring; lower ≤ upper stays), and :func:`reach_box` of ``factor`` in it (the same values), in
    one compiled call."""
    n = q.shape[0]
    lower, upper, low, high = np.empty(n), np.empty(n), np.empty(n), np.empty(n)
    within = _bounded(q, q_min, q_max, u_max if u_min is None else u_min, u_max, u_min is None, accel, share, u_prev,
                      factor, dt, lower, upper, low, high)
    return lower, upper, low, high, within
