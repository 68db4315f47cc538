"""The QP's box and the integration step, compiled (numba): a few calls instead of ~16 numpy calls
on 8-element arrays (and ~40 for the acceleration bound), the Python overhead that dominated the
safety step (the profile in docs/benchmarks.md).

Element by element the same IEEE operations as the numpy expressions they replace, so results
are bit-identical:

    upper = min(u_max, (q_max − q)/dt)      lower = min(max(u_min, (q_min − q)/dt), upper)
    u ← min(max(u, lower), upper)           q⁺ = clip(q + dt·u, q_min, q_max)

and for an acceleration bound a (rad/s², braking share β; h = β a Δt / 2):

    upper ← min(upper, √(2 β a max(q_max − q, 0) + h²) − h)
    lower ← min(max(lower, h − √(2 β a max(q − q_min, 0) + h²)), upper)
    [lo, hi] = clip(u_prev ∓ f a Δt, lower, upper)
"""

from __future__ import annotations

import os
from pathlib import Path

# numba caches compiled code on disk: as services.safety.barriers.kernel, in the user's cache folder
os.environ.setdefault("NUMBA_CACHE_DIR", str(Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "safemimic" / "numba"))

import numpy as np  # noqa: E402
from numba import njit  # noqa: E402


@njit(cache=True, nogil=True)
def _box(q, q_min, q_max, u_min, u_max, negate_min, dt, lower, upper):  # pragma: no cover - compiled
    for j in range(q.shape[0]):
        hi = min(u_max[j], (q_max[j] - q[j]) / dt)
        lo = max(-u_max[j] if negate_min else u_min[j], (q_min[j] - q[j]) / dt)
        upper[j] = hi
        lower[j] = min(lo, hi)


@njit(cache=True, nogil=True)
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


@njit(cache=True, nogil=True)
def _brake(q, q_min, q_max, a, share, dt, lower, upper):  # pragma: no cover - compiled
    for j in range(q.shape[0]):
        brake = share * a[j]
        half = 0.5 * brake * dt
        hi = min(upper[j], np.sqrt(2.0 * brake * max(q_max[j] - q[j], 0.0) + half * half) - half)
        lower[j] = min(max(lower[j], half - np.sqrt(2.0 * brake * max(q[j] - q_min[j], 0.0) + half * half)), hi)
        upper[j] = hi


@njit(cache=True, nogil=True)
def _reach(u_prev, a, factor, dt, lower, upper, low, high):  # pragma: no cover - compiled
    within = True
    for j in range(u_prev.shape[0]):
        reach = factor * a[j] * dt
        lo, hi = u_prev[j] - reach, u_prev[j] + reach
        within = within and lo <= upper[j] and hi >= lower[j]
        low[j] = min(max(lo, lower[j]), upper[j])
        high[j] = min(max(hi, lower[j]), upper[j])
    return within


@njit(cache=True, nogil=True)
def _bounded(q, q_min, q_max, u_min, u_max, negate_min, accel, share, u_prev, factor, dt, lower, upper, low,
             high):  # pragma: no cover - compiled
    _box(q, q_min, q_max, u_min, u_max, negate_min, dt, lower, upper)
    _brake(q, q_min, q_max, accel, share, dt, lower, upper)
    return _reach(u_prev, accel, factor, dt, lower, upper, low, high)


def velocity_box(q: np.ndarray, q_min: np.ndarray, q_max: np.ndarray, u_min: np.ndarray | None, u_max: np.ndarray,
                 dt: float) -> tuple[np.ndarray, np.ndarray]:
    """(lower, upper) (n,): the velocity bounds (u_min; None: −u_max) intersected with the joint
    limits reachable from ``q`` in ``dt``; lower ≤ upper always."""
    lower, upper = np.empty(q.shape[0]), np.empty(q.shape[0])
    _box(q, q_min, q_max, u_max if u_min is None else u_min, u_max, u_min is None, dt, lower, upper)
    return lower, upper


def clip_and_step(u: np.ndarray, lower: np.ndarray, upper: np.ndarray, q: np.ndarray, dt: float, q_min: np.ndarray,
                  q_max: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
    """(u clipped to [lower, upper], q + dt·u clipped to the joint limits), the latter None when
    q + dt·u is not finite."""
    u_out, q_out = np.empty(q.shape[0]), np.empty(q.shape[0])
    finite = _step(u, lower, upper, q, dt, q_min, q_max, u_out, q_out)
    return u_out, (q_out if finite else None)


def reach_box(u_prev: np.ndarray, accel: np.ndarray, factor: float, dt: float, lower: np.ndarray,
              upper: np.ndarray) -> tuple[np.ndarray, np.ndarray, bool]:
    """(low, high, within) (n,): ``[u_prev − factor·accel·dt, u_prev + factor·accel·dt]`` clipped into
    ``[lower, upper]``; ``within``: no joint's reach lies wholly beyond the box (the clipped box is
    still that reach)."""
    low, high = np.empty(u_prev.shape[0]), np.empty(u_prev.shape[0])
    within = _reach(u_prev, accel, factor, dt, lower, upper, low, high)
    return low, high, within


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
