"""The QP's box and the integration step, compiled (numba): two calls instead of ~16 numpy calls
on 8-element arrays, the Python overhead that dominated the safety step (the profile in docs/benchmarks.md).

Element by element the same IEEE operations as the numpy expressions they replace, so results
are bit-identical:

    upper = min(u_max, (q_max − q)/dt)      lower = min(max(u_min, (q_min − q)/dt), upper)
    u ← min(max(u, lower), upper)           q⁺ = clip(q + dt·u, q_min, q_max)
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
