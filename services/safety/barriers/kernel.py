"""Compiled (numba) inner loops of the barriers: one pass over the monitored pairs, the joint
barriers' rows, the rows a velocity can move, the smallest h of a row group.

The math is the same as ``shared.geometry.segment_closest_points`` (Ericson §5.1.9, cross-product
form, three clamped steps) and ``services.safety.barriers.capsules`` (eqs. 4–7), written as scalar loops
so that a 72-pair step costs a few microseconds instead of ~100 numpy calls. Tests check both
kernels against the vectorised geometry and against finite differences. The other kernels do the
same IEEE operations as the numpy expressions they replace (a NaN propagates through a maximum or a
minimum as in numpy), so their results are bit-identical.

The helpers the row writers call (``inline="always"``) are inlined into their callers by numba: a
call between compiled functions passes every array as its fields and checks for an exception, which
cost the safety step ~0.8 µs; inlining changes no operation, so no value.
"""

from __future__ import annotations

import os
from pathlib import Path

# Compiled kernels are cached on disk; an installed package's __pycache__ may not be writable,
# so default numba's cache to the user's cache folder (an explicit NUMBA_CACHE_DIR wins).
os.environ.setdefault("NUMBA_CACHE_DIR", str(Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "safemimic" / "numba"))

import numpy as np  # noqa: E402
from numba import njit  # noqa: E402

from shared.geometry import EPS_NORMAL  # noqa: E402

_TINY = 1e-300
#: b of a disabled row (A = 0): 0 ≥ −1e9 always holds.
DISABLED_B = -1e9


@njit(cache=True, nogil=True, inline="always")
def pair_distances(endpoints, radii, first, second, phi, eps, distance, h, s_out, t_out, normal):  # pragma: no cover - compiled
    """Closest points of every pair (first[i], second[i]) of ``endpoints`` (S, 2, 3).

    Writes ``distance`` (m,), ``h = d − (r_A + r_B + φ)``, the segment parameters ``s_out``,
    ``t_out`` and the unit normal n = (p_A − p_B)/d (NaN row where d < eps: the caller supplies a
    fallback). Returns the number of rows that need a fallback normal.
    """
    need = 0
    for i in range(first.shape[0]):
        ia, ib = first[i], second[i]
        d1x = endpoints[ia, 1, 0] - endpoints[ia, 0, 0]
        d1y = endpoints[ia, 1, 1] - endpoints[ia, 0, 1]
        d1z = endpoints[ia, 1, 2] - endpoints[ia, 0, 2]
        d2x = endpoints[ib, 1, 0] - endpoints[ib, 0, 0]
        d2y = endpoints[ib, 1, 1] - endpoints[ib, 0, 1]
        d2z = endpoints[ib, 1, 2] - endpoints[ib, 0, 2]
        rx = endpoints[ia, 0, 0] - endpoints[ib, 0, 0]
        ry = endpoints[ia, 0, 1] - endpoints[ib, 0, 1]
        rz = endpoints[ia, 0, 2] - endpoints[ib, 0, 2]
        # n = d1 × d2, m = d2 × r (well conditioned for near-parallel segments)
        nx, ny, nz = d1y * d2z - d1z * d2y, d1z * d2x - d1x * d2z, d1x * d2y - d1y * d2x
        mx, my, mz = d2y * rz - d2z * ry, d2z * rx - d2x * rz, d2x * ry - d2y * rx
        a = max(d1x * d1x + d1y * d1y + d1z * d1z, _TINY)
        e = max(d2x * d2x + d2y * d2y + d2z * d2z, _TINY)
        den = max(nx * nx + ny * ny + nz * nz, _TINY)
        b = d1x * d2x + d1y * d2y + d1z * d2z
        c = d1x * rx + d1y * ry + d1z * rz
        f = d2x * rx + d2y * ry + d2z * rz
        s = min(max((mx * nx + my * ny + mz * nz) / den, 0.0), 1.0)
        t = min(max((b * s + f) / e, 0.0), 1.0)
        s = min(max((b * t - c) / a, 0.0), 1.0)
        px = rx + s * d1x - t * d2x  # p_A − p_B
        py = ry + s * d1y - t * d2y
        pz = rz + s * d1z - t * d2z
        d = np.sqrt(px * px + py * py + pz * pz)
        distance[i] = d
        h[i] = d - (radii[ia] + radii[ib] + phi)
        s_out[i] = s
        t_out[i] = t
        if d >= eps:
            normal[i, 0], normal[i, 1], normal[i, 2] = px / d, py / d, pz / d
        else:
            normal[i, 0] = normal[i, 1] = normal[i, 2] = np.nan
            need += 1
    return need


@njit(cache=True, nogil=True, inline="always")
def pair_rows(normal, s, t, h, jacobians, velocities, first, second, n_robot, gamma, lookahead, A, b):  # pragma: no cover - compiled
    """CBF rows A u ≥ b: A_i = nᵀ(J_pA − J_pB), b_i = −γ (h_i − T a_i) + a_i with a_i = max(nᵀ v_pB, 0).

    ``jacobians`` (n_robot, 2, 3, n) are the robot endpoint Jacobians; ``velocities`` (S, 2, 3)
    the known endpoint velocities of external capsules (zero for robot capsules); ``lookahead``
    T (s) how far ahead an approaching capsule is anticipated (see barrier.py).
    """
    n_joints = jacobians.shape[3]
    for i in range(first.shape[0]):
        ia, ib = first[i], second[i]
        wa0, wa1 = 1.0 - s[i], s[i]
        wb0, wb1 = 1.0 - t[i], t[i]
        # column k sums its terms from 0.0 in the order c = 0, 1, 2 (A then B) as a scalar loop
        # would, in a register (A may alias the Jacobians as far as the compiler knows)
        n0, n1, n2 = normal[i, 0], normal[i, 1], normal[i, 2]
        robot = ib < n_robot
        for k in range(n_joints):
            acc = 0.0
            acc += n0 * (wa0 * jacobians[ia, 0, 0, k] + wa1 * jacobians[ia, 1, 0, k])
            if robot:
                acc -= n0 * (wb0 * jacobians[ib, 0, 0, k] + wb1 * jacobians[ib, 1, 0, k])
            acc += n1 * (wa0 * jacobians[ia, 0, 1, k] + wa1 * jacobians[ia, 1, 1, k])
            if robot:
                acc -= n1 * (wb0 * jacobians[ib, 0, 1, k] + wb1 * jacobians[ib, 1, 1, k])
            acc += n2 * (wa0 * jacobians[ia, 0, 2, k] + wa1 * jacobians[ia, 1, 2, k])
            if robot:
                acc -= n2 * (wb0 * jacobians[ib, 0, 2, k] + wb1 * jacobians[ib, 1, 2, k])
            A[i, k] = acc
        v_known = 0.0
        if ib >= n_robot:
            for c in range(3):
                v_known += normal[i, c] * (wb0 * velocities[ib, 0, c] + wb1 * velocities[ib, 1, c])
        approach = max(v_known, 0.0)
        b[i] = -gamma * (h[i] - lookahead * approach) + approach


@njit(cache=True, nogil=True)
def segment_pairs(segments, radii, jacobians, velocities, first, second, n_robot, gamma, phi, lookahead, eps,
                  distance, h, s, t, normal, A, b):  # pragma: no cover - compiled
    """:func:`pair_distances`, then :func:`pair_rows` in the same call unless a row needs a fallback
    normal; returns (how many do (then A and b are not written: the caller supplies the normals and
    calls :func:`pair_rows`), the smallest h (NaN if any h is; inf: no row))."""
    need = pair_distances(segments, radii, first, second, phi, eps, distance, h, s, t, normal)
    if need == 0:
        pair_rows(normal, s, t, h, jacobians, velocities, first, second, n_robot, gamma, lookahead, A, b)
    low = np.inf
    for i in range(h.shape[0]):
        if h[i] != h[i]:
            return need, h[i]
        low = min(low, h[i])
    return need, low


@njit(cache=True, nogil=True, inline="always")
def joint_rows(q, index, sign, bound, gamma, accel, share, bounded, h, b):  # pragma: no cover - compiled
    """Joint barrier rows: h_i = sign_i (q_{index_i} − bound_i), b_i = −α(h_i) with α(h) = γ h, or where
    ``bounded`` and h > 0, min(γ h, √(2 ``share`` a h)) (a = ``accel`` of that joint)."""
    for i in range(index.shape[0]):
        hi = sign[i] * (q[index[i]] - bound[i])
        alpha = gamma * hi
        if bounded and hi > 0.0:
            alpha = min(alpha, np.sqrt(2.0 * share * accel[index[i]] * hi))
        h[i] = hi
        b[i] = -alpha


@njit(cache=True, nogil=True, inline="always")
def row_moves(A, i, tol):  # pragma: no cover - compiled
    """Row i's largest |A_ij| (NaN if any is NaN, 0 for an empty row) exceeds ``tol``."""
    largest = 0.0
    for j in range(A.shape[1]):
        v = abs(A[i, j])
        if v != v:
            return False
        largest = max(largest, v)
    return largest > tol


@njit(cache=True, nogil=True)
def measured_rows(stack, radii, first, second, measured, h, phi, out):  # pragma: no cover - compiled
    """``out`` (m,) ← ``h`` (m,), except each row i with ``measured[i]`` and h[i] < 0: the h of the
    pair (first[i], second[i]) of ``stack`` (S, 2, 3) with ``radii`` (S,) and margin ``phi``
    (:func:`pair_distances`). Returns how many rows were computed."""
    scratch, normal = np.empty(4), np.empty((1, 3))
    count = 0
    for i in range(h.shape[0]):
        out[i] = h[i]
        if measured[i] and h[i] < 0.0:
            pair_distances(stack, radii, first[i:i + 1], second[i:i + 1], phi, 0.0, scratch[0:1], scratch[1:2],
                           scratch[2:3], scratch[3:4], normal)
            out[i] = scratch[1]
            count += 1
    return count


@njit(cache=True, nogil=True)
def movable_mask(A, tol, out):  # pragma: no cover - compiled
    """out_i = row i of A moves (:func:`row_moves`)."""
    for i in range(A.shape[0]):
        out[i] = row_moves(A, i, tol)


@njit(cache=True, nogil=True)
def raise_to_standoff(b, h, soft, gamma, standoff, creep):  # pragma: no cover - compiled
    """b_i ← max(b_i, −γ max(h_i − D, 0) − c) on the ``soft`` rows whose h is not NaN, in place
    (:func:`services.safety.standoff.apply_standoff`: D = ``standoff``, c = ``creep``)."""
    for i in range(b.shape[0]):
        if soft[i] and h[i] == h[i]:
            floor = -gamma * max(h[i] - standoff, 0.0) - creep
            if floor > b[i]:
                b[i] = floor


@njit(cache=True, nogil=True)
def any_positive(values, rows):  # pragma: no cover - compiled
    """Whether values[i] > 0 for some i in ``rows`` (a NaN is not)."""
    for i in rows:
        if values[i] > 0.0:
            return True
    return False


@njit(cache=True, nogil=True)
def masked_min(h, enabled, group, want):  # pragma: no cover - compiled
    """(count, min h) over the rows with ``enabled`` and ``group == want`` (a NaN among them: NaN)."""
    count, low = 0, np.inf
    for i in range(h.shape[0]):
        if enabled[i] and group[i] == want:
            count += 1
            if h[i] != h[i]:
                return count, h[i]
            low = min(low, h[i])
    return count, low


@njit(cache=True, nogil=True, inline="always")
def _nan_min(low, value):  # pragma: no cover - compiled
    """min(low, value), NaN once either is NaN (numpy's minimum)."""
    return value if value != value or value < low else low


@njit(cache=True, nogil=True, inline="always")
def block_minima(h, enabled, is_self):  # pragma: no cover - compiled
    """(min h over the ``enabled`` rows, min h over the enabled rows with ``is_self``); inf: no such
    row, NaN: a NaN among them (as ``masked_min``)."""
    low, low_self = np.inf, np.inf
    for i in range(h.shape[0]):
        if enabled[i]:
            low = _nan_min(low, h[i])
            if is_self[i]:
                low_self = _nan_min(low_self, h[i])
    return low, low_self


@njit(cache=True, nogil=True, inline="always")
def finish_segment_block(flags, A, b, h, soft):  # pragma: no cover - compiled
    """The rows of a missing capsule (``flags[0]`` False: not enabled) become A = 0, b = DISABLED_B,
    h = NaN; ``soft`` ← ``flags[2]``; returns :func:`block_minima` (``flags[1]``: the self rows)."""
    for i in range(h.shape[0]):
        soft[i] = flags[2, i]
        if not flags[0, i]:
            for j in range(A.shape[1]):
                A[i, j] = 0.0
            b[i] = DISABLED_B
            h[i] = np.nan
    return block_minima(h, flags[0], flags[1])


@njit(cache=True, nogil=True)
def write_segment_block(robot_endpoints, motion, radii, jacobians, pairs, flags, gamma, phi, lookahead, distance,
                        scratch, start, A, b, soft, h):  # pragma: no cover - compiled
    """The rows of sphere-swept segment pairs (:func:`segment_pairs`) written in place.

    ``motion`` (2, S, 2, 3) holds the segments and their endpoint velocities; the robot's
    ``robot_endpoints`` (R, 2, 3) are copied into its segments ``[:R]``; row i pairs segment
    ``pairs[0, i]`` with ``pairs[1, i]``; rows ``start`` … ``start + m − 1`` of ``A``, ``b``, ``h`` get
    A, b, h, then :func:`finish_segment_block` with ``flags`` (3, m) = (enabled, self row, soft).
    ``distance`` (m,) and ``scratch`` (5 m,) = (s (m,), t (m,), normals (m, 3) row-major) are written
    too. Returns (rows that need a fallback normal, min h of the enabled rows, of the enabled self
    rows); with a fallback needed (then NaN, NaN) A and b are not written: the caller supplies the
    normals, then :func:`finish_segment_rows`."""
    segments, velocities = motion[0], motion[1]
    n_robot = robot_endpoints.shape[0]
    for c in range(n_robot):
        for e in range(2):
            for k in range(3):
                segments[c, e, k] = robot_endpoints[c, e, k]
    m = pairs.shape[1]
    stop = start + m
    st, normal = scratch[:2 * m].reshape((2, m)), scratch[2 * m:].reshape((m, 3))
    hb = h[start:stop]
    need = pair_distances(segments, radii, pairs[0], pairs[1], phi, EPS_NORMAL, distance, hb, st[0], st[1], normal)
    if need:
        return need, np.nan, np.nan
    Ab, bb = A[start:stop], b[start:stop]
    pair_rows(normal, st[0], st[1], hb, jacobians, velocities, pairs[0], pairs[1], n_robot, gamma, lookahead, Ab, bb)
    low, low_self = finish_segment_block(flags, Ab, bb, hb, soft[start:stop])
    return 0, low, low_self


@njit(cache=True, nogil=True)
def finish_segment_rows(normal, st, jacobians, velocities, pairs, flags, n_robot, gamma, lookahead, start, A, b, soft,
                        h):  # pragma: no cover - compiled
    """The rest of :func:`write_segment_block` once the caller has supplied the fallback normals:
    :func:`pair_rows` and :func:`finish_segment_block` on rows ``start`` …; returns the minima."""
    stop = start + pairs.shape[1]
    Ab, bb, hb = A[start:stop], b[start:stop], h[start:stop]
    pair_rows(normal, st[0], st[1], hb, jacobians, velocities, pairs[0], pairs[1], n_robot, gamma, lookahead, Ab, bb)
    return finish_segment_block(flags, Ab, bb, hb, soft[start:stop])


@njit(cache=True, nogil=True)
def write_joint_block(q, index, signed, gamma, accel, share, bounded, rows, start, A, b, soft, h):  # pragma: no cover - compiled
    """:func:`joint_rows` written in place (``signed`` (2, m): its sign and bound rows): rows ``start`` …
    of ``A`` ← the constant ``rows``, of ``b`` and ``h`` the joint rows' b and h, of ``soft`` False (hard)."""
    stop = start + index.shape[0]
    joint_rows(q, index, signed[0], signed[1], gamma, accel, share, bounded, h[start:stop], b[start:stop])
    for i in range(index.shape[0]):
        soft[start + i] = False
        for j in range(rows.shape[1]):
            A[start + i, j] = rows[i, j]
