"""Speed and separation: near a person the tracking asks for no speed the robot could not stop from in time.

ISO/TS 15066 speed and separation monitoring keeps the robot slow enough that it stops before a person,
moving at an assumed speed v_h whatever a sensor says, reaches it: the person covers v_h T_s while the
robot brakes for its stopping time T_s, and the robot covers its own stopping distance. Here, per joint j
and per enabled robot–person row i (``soft``) of the step, with ℓ_ij = |A_ij| (m/rad: how fast joint j
alone closes that pair's distance, the barrier's normal rate), h_i the pair's barrier value (m: the
person capsule swept ahead, beyond φ and the person margin) and a_j the acceleration bound
(``safety.accel_max``): joint j moving at |u| brakes in T_s = |u|/a_j over ℓ_ij u²/(2 a_j), so

    v_h |u|/a_j + ℓ_ij u²/(2 a_j) ≤ h_i   ⇔   |u| ≤ c_ij = 2 h_i / (v_h/a_j + √((v_h/a_j)² + 2 ℓ_ij h_i/a_j)),

and c_ij = 0 where h_i ≤ 0; |u_j| ≤ c_j = min_i c_ij, a row joint j does not move (ℓ_ij ≤
:data:`STATIC_LEVER`) capping nothing. Both directions are capped, as ISO/TS 15066 limits the robot's
speed, not its direction, near a person: the normal of a row is that of the person as seen a latency ago,
and a fist that starts to move may arrive from another side (measured: capping only the closing direction
left 68 of the side-stepping punches' 86 robot-caused contact steps, both directions 52).
v_h = ``safety.human_speed_mps`` (1.6 m/s, ISO/TS 15066's and ISO 13855's walking speed of a person; 0:
off, the paper). It is a bound per joint, as though that joint alone moved: a heuristic, not a guarantee.

It caps only the *reference*: u_ref_j ← clip(u_ref_j, −c_j, c_j) by the caps above, and the QP's
linear term f_j = −W_j u_ref_j with it. The rows, the velocity and acceleration boxes and the relaxation
are untouched, so the feasibility argument of :mod:`services.safety.filter` holds as it is, and every
safety row binds exactly as before: the cap can only make the robot track more slowly toward a person
(tested on random states, ``tests/test_separation.py``). A protective stop aims at rest and is not
capped (there is nothing to slow).

Why: the camera shows a person a latency late and a fist that starts to move is not in the measured
velocity, so the rows let the robot move near a person at any speed the barrier allows; when that
person's arm then arrives, the robot is still braking into it (docs/safety-measurements.md
"Speed and separation: the robot slows near a person").
"""

from __future__ import annotations

import numpy as np

from services.safety.qp.box import njit  # numba's, imported after box.py sets numba's cache folder

__all__ = ["STATIC_LEVER", "cap_reference", "speed_caps"]

#: m/rad: a row whose |A_ij| is at most this is not moved by joint j (a static link's pair, a far lever)
STATIC_LEVER = 1e-9


@njit(cache=True, nogil=True)
def speed_caps(A, h, soft, enabled, accel, v_h, caps):  # pragma: no cover - compiled
    """Write into ``caps`` (n,) ≥ 0 (rad/s) the caps c_j of the module docstring from the rows ``A`` (m, n),
    ``h`` (m,) m, ``soft`` and ``enabled`` (m,) bool, ``accel`` (n,) rad/s² and ``v_h`` (m/s, > 0); inf where
    no row caps joint j."""
    for j in range(caps.shape[0]):
        caps[j] = np.inf
        c = v_h / accel[j]
        for i in range(A.shape[0]):
            hi = h[i]
            if not (soft[i] and enabled[i]) or not (hi == hi):  # hard, disabled or NaN
                continue
            lever = abs(A[i, j])
            if lever <= STATIC_LEVER:
                continue
            cap = 0.0 if hi <= 0.0 else 2.0 * hi / (c + np.sqrt(c * c + 2.0 * lever * hi / accel[j]))
            caps[j] = min(caps[j], cap)


@njit(cache=True, nogil=True)
def cap_reference(A, h, soft, enabled, accel, v_h, weights, u_ref, f, caps):  # pragma: no cover - compiled
    """Clip ``u_ref`` (n,) in place to ±the caps of :func:`speed_caps` (written into ``caps`` (n,)) and set
    the QP's linear term ``f`` (at least n,) to −``weights`` ⊙ u_ref where it changed; the number of
    joints capped."""
    speed_caps(A, h, soft, enabled, accel, v_h, caps)
    capped = 0
    for j in range(u_ref.shape[0]):
        u = min(max(u_ref[j], -caps[j]), caps[j])
        if u != u_ref[j]:
            u_ref[j] = u
            f[j] = -weights[j] * u
            capped += 1
    return capped
