"""Exact, vectorised segment/segment and capsule/capsule geometry (pure numpy).

This module is the geometric core of the capsule CBF safety layer.  Every
robot/human body part is a *capsule*: the set of points within ``radius`` of
a line segment ``[a, b]``.  For two capsules the signed surface distance is

    h = d(S1, S2) - r1 - r2,

where ``d(S1, S2) = min_{s,t in [0,1]} || P(s) - Q(t) ||`` is the distance
between the core segments, ``P(s) = a1 + s (b1 - a1)`` and
``Q(t) = a2 + t (b2 - a2)``.  ``h > 0`` means separated, ``h = 0`` touching,
``h < 0`` penetrating.

Segment/segment algorithm
-------------------------
Ericson, *Real-Time Collision Detection*, section 5.1.9, vectorised over N
pairs (no Python loop, no per-pair branches).  With ``d1 = b1 - a1``,
``d2 = b2 - a2``, ``r = a1 - a2`` and the Gram entries

    A = d1.d1,  B = d1.d2,  C = d1.r,  E = d2.d2,  F = d2.r,

``|P(s) - Q(t)|^2 = |r + s d1 - t d2|^2`` is a convex quadratic in ``(s, t)``
whose unconstrained (line/line) minimiser is

    s* = (B F - C E) / (A E - B^2),        t(s) = (B s + F) / E,
    s(t) = (B t - C) / A.

The constrained minimiser over the unit square is obtained by

    s0 = clamp(s*)            (s0 = 0 when the segments are exactly parallel)
    t  = clamp(t(s0))
    s  = clamp(s(t))

Why this is exact: ``phi(s) = min_t |P(s) - Q(t)|^2`` is convex with minimum
at ``s*``, so ``clamp(s*)`` minimises it over [0, 1]; if ``t(s0)`` is feasible
the pair is optimal (and re-projecting ``s`` cannot increase the distance),
otherwise the optimum lies on the edge ``t = clamp(t(s0))`` and ``s(t)`` is its
minimiser on that edge (Ericson's re-projection step).

Zero-length segments need no special case: ``d1 = 0`` gives ``B = C = 0`` and
so ``s = 0`` with ``t`` the projection of ``a1`` onto segment 2; ``d2 = 0``
gives ``B = F = 0`` and so ``t = 0`` with ``s`` the projection of ``a2`` onto
segment 1.  The divisors are floored at 1e-300, which only matters when
the numerator is itself zero (or when the segment is so short that any
parameter is within rounding of the answer).

Parallel and collinear segments (``n = d1 x d2 = 0``) have a non-unique
minimiser; ``s0 = 0`` is then a deterministic start and the two projections
give a pair on both segments that realises the minimum (for parallel segments
*any* ``s0`` in [0, 1] does, so rounding in ``n`` is harmless).

Numerical refinements over the textbook form:

* ``A E - B^2`` and ``B F - C E`` are evaluated via the Lagrange identity
  ``(u x v).(w x z) = (u.w)(v.z) - (u.z)(v.w)`` as

      A E - B^2 = |n|^2,     B F - C E = (d2 x r).n,     n = d1 x d2,

  avoiding the catastrophic cancellation of ``A E - B^2`` for nearly parallel
  segments (relative error O(eps / sin(theta)) instead of
  O(eps / sin(theta)^2)).
* The distance is recomputed as ``|p - q|`` from the returned points, so it
  is exactly the distance the returned closest points realise.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = [
    "EPS_NORMAL",
    "Capsule",
    "CapsuleDistance",
    "SegmentClosestPoints",
    "capsule_distance",
    "safe_normal",
    "segment_closest_points",
]

FloatArray = NDArray[np.float64]

#: Distance (m) below which ``safe_normal`` switches to its fallback.
EPS_NORMAL: float = 1e-9


@dataclass(frozen=True, slots=True, eq=False)
class Capsule:
    """A capsule: all points within ``radius`` of the segment ``[a, b]``.

    Attributes:
        a: first segment endpoint, shape (3,), metres.
        b: second segment endpoint, shape (3,), metres (``a == b`` is a sphere).
        radius: radius in metres, ``radius >= 0``.

    The endpoints are stored as read-only float64 copies.  Equality and hashing
    are by identity (``eq=False``): element-wise array comparison has no
    single truth value.
    """

    a: FloatArray
    b: FloatArray
    radius: float

    def __post_init__(self) -> None:
        a = np.array(self.a, dtype=np.float64).reshape(3)
        b = np.array(self.b, dtype=np.float64).reshape(3)
        radius = float(self.radius)
        if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))):
            raise ValueError("Capsule endpoints must be finite")
        if not (np.isfinite(radius) and radius >= 0.0):
            raise ValueError(f"Capsule radius must be finite and >= 0, got {radius!r}")
        a.setflags(write=False)
        b.setflags(write=False)
        # Frozen dataclass: bypass __setattr__ to store the normalised copies.
        object.__setattr__(self, "a", a)
        object.__setattr__(self, "b", b)
        object.__setattr__(self, "radius", radius)


class SegmentClosestPoints(NamedTuple):
    """Closest points between N segment pairs.

    Attributes:
        distance: (N,) ``||p - q||``, the segment/segment distance (m).
        p: (N, 3) closest point on segment 1, ``p = a1 + s (b1 - a1)``.
        q: (N, 3) closest point on segment 2, ``q = a2 + t (b2 - a2)``.
        s: (N,) parameter on segment 1, in [0, 1].
        t: (N,) parameter on segment 2, in [0, 1].
    """

    distance: FloatArray
    p: FloatArray
    q: FloatArray
    s: FloatArray
    t: FloatArray


class CapsuleDistance(NamedTuple):
    """Result of :func:`capsule_distance` for a single capsule pair.

    Attributes:
        signed_distance: ``d - r1 - r2`` (m); negative when penetrating.
        distance: segment/segment distance ``d = ||p - q||`` (m).
        p: (3,) closest point on the core segment of capsule 1.
        q: (3,) closest point on the core segment of capsule 2.
        s: parameter of ``p`` on segment 1, in [0, 1].
        t: parameter of ``q`` on segment 2, in [0, 1].
    """

    signed_distance: float
    distance: float
    p: FloatArray
    q: FloatArray
    s: float
    t: float


def _as_points(x: ArrayLike) -> FloatArray:
    """``x`` as a float64 (N, 3) array ((3,) becomes (1, 3))."""
    arr = np.asarray(x, dtype=np.float64)
    if arr.ndim == 1:
        arr = arr[None, :]
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"expected shape (3,) or (N, 3), got {arr.shape}")
    return arr


# Index tables for the vectorised kernel (module constants: no per-call cost).
# V[0:3] (3, 3, N) holds d1, d2, r as component rows; taking rows (y, z, x, y)
# of each lets both cross products be written with plain slices.
_ROLL = np.array([1, 2, 0, 1])
# Rows of the (5, 3, N) stack (d1, d2, r, n, m) paired up for the dot products
#   A = d1.d1, E = d2.d2, den = n.n, B = d1.d2, C = d1.r, F = d2.r, num = m.n
_DOT_L = np.array([0, 1, 3, 0, 0, 1, 4])
_DOT_R = np.array([0, 1, 3, 1, 2, 2, 3])
# Guard for the three divisions; only ever active when the true divisor is
# (numerically) zero, in which case the numerator is zero as well (see notes).
_TINY = 1e-300


def segment_closest_points(
    a1: ArrayLike, b1: ArrayLike, a2: ArrayLike, b2: ArrayLike
) -> SegmentClosestPoints:
    """Closest points between segments ``[a1, b1]`` and ``[a2, b2]``, N pairs at once.

    Solves ``min_{s,t in [0,1]} || a1 + s (b1 - a1) - a2 - t (b2 - a2) ||`` for
    every pair (Ericson 5.1.9, see the module docstring) with three closed-form
    steps and no branches::

        s0 = clamp((d2 x r).n / |n|^2)        n = d1 x d2   (s0 = 0 if n = 0)
        t  = clamp((B s0 + F) / E)            best t for s0
        s  = clamp((B t - C) / A)             best s for t

    Exact up to float64 rounding for general, crossing (``d = 0``), parallel,
    collinear (overlapping or disjoint) and zero-length segments (one or both
    reduced to a point); the module docstring gives the derivation and why
    degenerate and parallel inputs need no special case.  Cost is a fixed
    number of numpy calls independent of N (about 28 us for N = 72).

    Args:
        a1, b1: endpoints of segment 1, each of shape (3,) or (N, 3).
        a2, b2: endpoints of segment 2, each of shape (3,) or (N, 3).
            A (3,) input is treated as (1, 3); the four inputs are broadcast
            against each other along the first axis (e.g. one segment against
            N segments), so N is the broadcast length (N = 1 if all are (3,)).
            Inputs must be finite.

    Returns:
        :class:`SegmentClosestPoints` with ``distance (N,)``, ``p (N,3)``,
        ``q (N,3)``, ``s (N,)``, ``t (N,)``; ``p`` and ``q`` are computed as
        ``a1 + s d1`` and ``a2 + t d2`` and ``distance == ||p - q||``.
    """
    a1 = _as_points(a1)
    b1 = _as_points(b1)
    a2 = _as_points(a2)
    b2 = _as_points(b2)
    if not (a1.shape == b1.shape == a2.shape == b2.shape):
        a1, b1, a2, b2 = np.broadcast_arrays(a1, b1, a2, b2)

    d1 = b1 - a1
    d2 = b2 - a2
    r = a1 - a2
    n_pairs = d1.shape[0]

    # Work in component-row layout: V[k] is the (3, N) array of vector k.
    V = np.empty((5, 3, n_pairs))
    V[0] = d1.T
    V[1] = d2.T
    V[2] = r.T
    # n = d1 x d2 -> V[3], m = d2 x r -> V[4]:  (u x v)_i = u_{i+1} v_{i+2} - u_{i+2} v_{i+1}
    R = V[0:3].take(_ROLL, axis=1)  # rows (y, z, x, y) of d1, d2, r
    cross = V[3:5]
    np.multiply(R[0:2, 0:3], R[1:3, 1:4], out=cross)
    cross -= R[0:2, 1:4] * R[1:3, 0:3]

    G = np.einsum("kin,kin->kn", V.take(_DOT_L, axis=0), V.take(_DOT_R, axis=0))
    B, C, F, num = G[3], G[4], G[5], G[6]
    A_safe, E_safe, den_safe = np.maximum(G[0:3], _TINY)  # A, E, |n|^2

    s = num / den_safe
    np.maximum(s, 0.0, out=s)
    np.minimum(s, 1.0, out=s)

    t = B * s
    t += F
    t /= E_safe
    np.maximum(t, 0.0, out=t)
    np.minimum(t, 1.0, out=t)

    s = B * t
    s -= C
    s /= A_safe
    np.maximum(s, 0.0, out=s)
    np.minimum(s, 1.0, out=s)

    p = s[:, None] * d1
    p += a1
    q = t[:, None] * d2
    q += a2
    diff = p - q
    distance = np.sqrt(np.einsum("ij,ij->i", diff, diff))
    return SegmentClosestPoints(distance=distance, p=p, q=q, s=s, t=t)


def capsule_distance(cap1: Capsule, cap2: Capsule) -> CapsuleDistance:
    """Signed surface distance ``d - r1 - r2`` between two capsules.

    Thin wrapper over :func:`segment_closest_points` with N = 1; ``p`` and
    ``q`` are the closest points of the *core segments* (the closest surface
    points are ``p - r1 n`` and ``q + r2 n`` with ``n = safe_normal(p, q)``).
    """
    res = segment_closest_points(cap1.a, cap1.b, cap2.a, cap2.b)
    d = float(res.distance[0])
    return CapsuleDistance(
        signed_distance=d - cap1.radius - cap2.radius,
        distance=d,
        p=res.p[0],
        q=res.q[0],
        s=float(res.s[0]),
        t=float(res.t[0]),
    )


def _row_dot(x: FloatArray, y: FloatArray) -> FloatArray:
    """Row-wise dot product of two (K, 3) arrays."""
    out: FloatArray = np.einsum("ij,ij->i", x, y)
    return out


def _cross(u: FloatArray, v: FloatArray) -> FloatArray:
    """Row-wise ``u x v`` for (K, 3) arrays (cheaper than ``np.cross`` for small K)."""
    ur = u[:, [1, 2, 0]]
    vr = v[:, [1, 2, 0]]
    # w_i = u_i v_{i+1} - u_{i+1} v_i = (u x v)_{i+2}, so (u x v)_k = w_{k+1}
    return (u * vr - ur * v)[:, [1, 2, 0]]


def _select_rows(x: FloatArray, rows: NDArray[np.intp], n: int) -> FloatArray:
    """``x[rows]`` for an (n, 3) array, or ``x`` repeated if it has a single row."""
    if x.shape[0] == 1:
        return np.repeat(x, rows.size, axis=0)
    if x.shape[0] != n:
        raise ValueError(f"fallback has {x.shape[0]} rows, expected 1 or {n}")
    return x[rows]


def _unit_orthogonal_axis(u: FloatArray) -> FloatArray:
    """Per row, a unit vector orthogonal to ``u`` (rows of ``u`` must be nonzero).

    Takes ``u x e_k`` where ``e_k`` is the coordinate axis along which ``|u|``
    is smallest, so ``|u x e_k| >= |u| sqrt(2/3)`` (well conditioned).
    """
    k = np.argmin(np.abs(u), axis=1)
    e = np.zeros_like(u)
    e[np.arange(u.shape[0]), k] = 1.0
    w = _cross(u, e)
    return w / np.sqrt(_row_dot(w, w))[:, None]


def _normalise_or(
    v: FloatArray, ok: NDArray[np.bool_], norm: FloatArray, other: FloatArray
) -> FloatArray:
    """Rows ``v / norm`` where ``ok``, else the rows of ``other``."""
    return np.where(ok[:, None], v / np.where(ok, norm, 1.0)[:, None], other)


#: Below this ``sin`` of the angle between the segments, ``safe_normal`` treats
#: them as parallel and does not use ``d1 x d2`` as the fallback direction.
_SIN_PARALLEL = 1e-6


def safe_normal(
    p: ArrayLike,
    q: ArrayLike,
    fallback: ArrayLike | tuple[ArrayLike, ArrayLike, ArrayLike, ArrayLike] | None = None,
    eps: float = EPS_NORMAL,
) -> FloatArray:
    """Unit normal ``n = (p - q) / ||p - q||`` with a deterministic finite fallback.

    ``n`` points from segment 2 towards segment 1: for ``d = ||p - q|| > 0`` it
    is the gradient of ``d`` (and of ``h = d - r1 - r2``) w.r.t. ``p``, i.e.
    translating body 1 by ``delta`` changes ``h`` by ``n.delta`` to first
    order.  Where ``d < eps`` (default 1e-9 m: the core segments touch or
    cross) the direction is undefined and a fallback is returned instead,
    always finite with unit norm:

    * ``fallback`` an array ((3,) or (N, 3)): that direction normalised
      (rows shorter than ``eps`` become ``+z``).
    * ``fallback`` a *tuple* of the segment endpoints ``(a1, b1, a2, b2)``
      (each (3,) or (N, 3)).  With ``d1 = b1 - a1``, ``d2 = b2 - a2``,
      ``m = (a1 + b1)/2 - (a2 + b2)/2`` (segment-2 midpoint to segment-1
      midpoint) and ``c = d1 x d2``, the first applicable of

      1. crossing / non-parallel (``|c| >= 1e-6 |d1| |d2|``, both segments
         at least ``eps`` long):
         ``sign(m.c) c / |c|`` (``+c`` when ``m.c = 0``): the direction
         in which the distance between the two lines grows (for exactly
         crossing segments ``m.c = 0``; for nearly crossing ones, ``d > 0``
         but ``< eps``, the sign matches the true ``(p - q) / d``);
      2. the component of ``m`` orthogonal to ``u``,
         ``m - (m.u / u.u) u``, normalised, where ``u = d1`` (or ``d2`` if
         segment 1 is a point; ``m`` itself if both are points);
      3. ``u x e_k / |u x e_k|`` with ``e_k`` the coordinate axis least
         aligned with ``u`` (any axis orthogonal to the segment);
      4. ``+z``.

      (Thresholds in 2 and 3 are ``eps``.)
    * ``fallback=None``: ``+z``.

    Args:
        p, q: closest points, shape (3,) or (N, 3) (broadcast along axis 0).
        fallback: direction(s) or segment endpoints, see above.
        eps: distance threshold (m) for switching to the fallback.

    Returns:
        (N, 3) array of unit vectors.
    """
    diff = _as_points(p) - _as_points(q)
    norm = np.sqrt(_row_dot(diff, diff))
    small = norm < eps
    out = diff / np.where(small, 1.0, norm)[:, None]
    if not small.any():
        return out

    # Fallback, computed for the (few) rows in contact only.
    n_rows = diff.shape[0]
    rows = np.flatnonzero(small)
    k = rows.size
    z = np.zeros((k, 3))
    z[:, 2] = 1.0
    if fallback is None:
        fb = z
    elif isinstance(fallback, tuple) and len(fallback) == 4:
        a1, b1, a2, b2 = (_select_rows(_as_points(x), rows, n_rows) for x in fallback)
        d1 = b1 - a1
        d2 = b2 - a2
        m = 0.5 * (a1 + b1) - 0.5 * (a2 + b2)
        l1 = np.sqrt(_row_dot(d1, d1))
        l2 = np.sqrt(_row_dot(d2, d2))
        # 2./3. reference direction u: segment 1, else segment 2, else none.
        use1 = l1 >= eps
        u = np.where(use1[:, None], d1, d2)
        lu = np.where(use1, l1, l2)
        u_ok = lu >= eps
        uu = np.where(u_ok, lu * lu, 1.0)
        m_perp = m - (np.where(u_ok, _row_dot(m, u), 0.0) / uu)[:, None] * u
        mp_norm = np.sqrt(_row_dot(m_perp, m_perp))
        mp_ok = mp_norm >= eps
        fb = _normalise_or(m_perp, mp_ok, mp_norm, z)
        need_axis = u_ok & ~mp_ok
        if need_axis.any():
            fb[need_axis] = _unit_orthogonal_axis(u[need_axis])
        # 1. non-parallel: +-(d1 x d2), oriented along m.
        c = _cross(d1, d2)
        c_norm = np.sqrt(_row_dot(c, c))
        # (both segments >= eps long, so |c|^2 >= 1e-48 cannot underflow)
        c_ok = use1 & (l2 >= eps) & (c_norm >= _SIN_PARALLEL * l1 * l2)
        c = np.where((_row_dot(m, c) < 0.0)[:, None], -c, c)
        fb = _normalise_or(c, c_ok, c_norm, fb)
    else:
        f = _select_rows(_as_points(fallback), rows, n_rows)
        f_norm = np.sqrt(_row_dot(f, f))
        fb = _normalise_or(f, f_norm >= eps, f_norm, z)

    out[rows] = fb
    return out
