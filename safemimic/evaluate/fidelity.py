"""Imitation fidelity: how well the simulated robot follows the true person (the paper's future work).

Against ``q_true`` (the true skeleton retargeted as the stack retargets: same estimator,
calibration, mirror and retargeting method) and the simulated joints q_sim, per run, over the *judged steps*: from
:data:`ACQUIRE_S` after the person is first perceived (a state with a valid pose angle: not a frame
without a skeleton, before they walk into view) to the end (before, the robot is still moving from
its home pose to the person's first pose, which says nothing of how it follows a motion):

- ``lag_ms``: for each joint whose ``q_true`` moves more than :data:`MOVING_RAD` (peak to peak),
  the delay τ ∈ [−:data:`MAX_LEAD_S`, :data:`MAX_LAG_S`] minimising the mean of
  (q_sim(t) − q_true(t − τ))² over the judged steps of q_sim (q_true may reach back before them),
  in control steps; the median over those
  joints (null: no joint moves, or the run is shorter than the search range);
- ``lag_ms_target`` / ``lag_ms_command`` / ``lag_ms_servo``: the same delay stage by stage, where
  the lag comes from: the retargeted target q_nom behind q_true (camera latency, point filter, the
  rate that carries q_nom between frames), the safe command q_cbf behind q_nom (the filter's
  tracking: K, the fed-forward rate, binding rows, the acceleration bound) and the simulated joints
  behind q_cbf (the servos). Each is a median over the joints its reference moves, so the three
  need not add up to ``lag_ms`` exactly;
- ``rms_true`` / ``rms_true_free``: RMS of q_sim − q_true (rad) over every step and joint / over
  the free steps (no constraint binds in the CBF run);
- ``rms_true_free_latency_floor``: RMS of q_true(t − L) − q_true(t) over the same free steps, L
  the camera latency: the score of a robot exactly at the target it was last shown, L late
  (perfect perception and tracking, no prediction). No causal controller that does not predict
  the person does better on average, so a run cannot meet an ``rms_true_free`` goal below it;
- ``direction_error_deg_p50`` / ``_p95``: over the free steps, the angle between the robot's and
  the person's upper arm (shoulder → elbow) and forearm (elbow → wrist) directions, each in its
  own torso frame F_T (:func:`shared.torso_frame.torso_axes`: e_x right, e_y forward, e_z
  up). The robot's segments are its CBF capsules' axes at q_sim (torso capsule base as pelvis,
  upper-arm capsule bases as shoulders); facing the person (mirror), the robot's left arm is
  compared with the person's right arm reflected across the sagittal plane (lateral sign
  flipped). Percentiles over every (step, segment) sample with both directions defined;
- ``direction_error_deg_p50_at_target`` / ``_p95_at_target``: the same with the robot placed
  exactly at ``q_true`` (perfect tracking), over the same samples: the share of the direction error
  that the retargeting (``retargeting.method``: by directions, or the paper's eq. 2) and the
  robot's kinematics leave, which no controller can remove;
- ``direction_error_deg_p50_latency_floor`` / ``_p95_latency_floor``: the same with the robot placed
  at ``q_true(t − L)``, L the camera latency, against the person at t, over the same samples: the
  retargeting's error and the latency's together, what a robot exactly at the target it was last
  shown scores (the directions' counterpart of ``rms_true_free_latency_floor``);
- ``lag_ms_limits_floor``: the lag of a robot that sees the true target one latency late, perfectly
  (no point filter, its exact rate) and follows it as fast as its bounds allow
  (:func:`limited_follower`: the joint speed bound ``safety.u_max``, the acceleration bound
  ``safety.accel_max``; no safety row): where the person moves faster than the robot can
  accelerate, this already exceeds the latency, and a lag goal below it is met by no controller
  within those bounds;
- ``judged_from_s``: where the judged steps begin (s; null: the person was never perceived).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from shared.torso_frame import person_arm_directions, robot_arm_directions

#: The judged steps begin this long after the first perceived state (s): at the default bounds
#: (u_max 3 / 10 rad/s, accel_max 10 / 60 rad/s², waist / arms) a joint crosses its whole range in
#: under 1 s, so the robot has reached the person's first pose by then.
ACQUIRE_S = 1.0
#: A joint "moves" when its true target spans more than this (rad).
MOVING_RAD = 0.2
#: Delay search range (s): how far the robot may trail / lead the person.
MAX_LAG_S = 1.0
MAX_LEAD_S = 0.2
#: The stages of the lag (``lag_ms_<stage>``), each a (reference, follower) pair: q_nom behind q_true,
#: q_cbf behind q_nom, q_sim behind q_cbf.
LAG_STAGES = ("target", "command", "servo")
_MIN_SEGMENT = 0.05  # m: shorter torso or limb segments give no direction


def best_delay(reference: np.ndarray, follower: np.ndarray, dt: float, start: int = 0) -> float | None:
    """The delay τ (s) with follower(t) ≈ reference(t − τ), by least squares over one window of the
    follower from step ``start`` on (the reference may reach back before it); None if that window is
    shorter than 0.5 s after the search range. Both (N,), sampled every ``dt`` seconds."""
    lag, lead = round(MAX_LAG_S / dt), round(MAX_LEAD_S / dt)
    n = len(reference)
    first = max(lag, start)
    if n - lead - first <= round(0.5 / dt):
        return None
    target = follower[first: n - lead]
    errors = [np.mean((target - reference[first - d: n - lead - d]) ** 2) for d in range(-lead, lag + 1)]
    return (int(np.argmin(errors)) - lead) * dt


def limited_follower(reference: np.ndarray, dt: float, u_max: ArrayLike, accel_max: ArrayLike | None) -> np.ndarray:
    """The joints (N, n) rad of a robot that follows ``reference`` (N, n) rad, sampled every ``dt`` s,
    as closely as its speed bound ``u_max`` (n,) rad/s and acceleration bound ``accel_max`` (n,)
    rad/s² (None: unbounded) allow, starting at rest on ``reference[0]``.

    At each step k, from q_k, it takes the velocity nearest to
    v* = ṙ_k + sign(e) min(√(2 a |e|), |e|/Δt), e = r_k − q_k, ṙ_k = (r_{k+1} − r_k)/Δt (the reference's
    own rate; the fastest approach from which it still brakes onto the reference at a, and no further
    than the error in one step) within |v| ≤ u_max and |v − v_prev| ≤ a Δt, then q_{k+1} = q_k + v Δt.
    A near time-optimal tracker of the reference within the bounds (up to a chatter of a Δt² rad),
    not a controller the stack runs: the bounds' own share of the lag.
    """
    reference = np.asarray(reference, dtype=np.float64)
    u_max = np.asarray(u_max, dtype=np.float64)
    accel = None if accel_max is None else np.asarray(accel_max, dtype=np.float64)
    rate = np.diff(reference, axis=0, append=reference[-1:]) / dt
    q, v = reference[0].copy(), np.zeros_like(u_max)
    out = np.empty_like(reference)
    for k in range(len(reference)):
        out[k] = q
        e = reference[k] - q
        closing = np.abs(e) / dt if accel is None else np.minimum(np.sqrt(2.0 * accel * np.abs(e)), np.abs(e) / dt)
        v_next = np.clip(rate[k] + np.sign(e) * closing, -u_max, u_max)
        v = v_next if accel is None else np.clip(v_next, v - accel * dt, v + accel * dt)
        q = q + v * dt
    return out


def lag_ms(q_true: np.ndarray, q_sim: np.ndarray, dt: float, start: int = 0) -> float | None:
    """Median over the joints moving from step ``start`` on of :func:`best_delay` (ms); None if none
    moves or the series is too short."""
    judged = q_true[start:]
    moving = [j for j in range(q_true.shape[1]) if len(judged) and np.ptp(judged[:, j]) > MOVING_RAD]
    delays = [best_delay(q_true[:, j], q_sim[:, j], dt, start) for j in moving]
    delays = [d for d in delays if d is not None]
    return round(1e3 * float(np.median(delays)), 3) if delays else None


def direction_errors(keypoints: np.ndarray, valid: np.ndarray, robot: np.ndarray, mirror: bool) -> np.ndarray:
    """Angles (deg) between the person's and the robot's arm segments at each step: (N, 4) in the
    order of :data:`shared.torso_frame.ARM_SEGMENTS` (of the robot); NaN where a direction is
    undefined. ``keypoints`` (N, 15, 3) and ``valid`` (N, 15) the true skeleton, ``robot``
    (N, 7, 2, 3) the robot capsules."""
    out = np.full((len(keypoints), 4), np.nan)
    for k in range(len(keypoints)):
        person = person_arm_directions(keypoints[k], valid[k], mirror, _MIN_SEGMENT)
        if np.isnan(person).all():
            continue
        cosine = np.clip(np.einsum("ij,ij->i", person, robot_arm_directions(robot[k], _MIN_SEGMENT)), -1.0, 1.0)
        out[k] = np.degrees(np.arccos(cosine))
    return out


def judged_from(perceived: np.ndarray, dt: float) -> int | None:
    """The first judged step: :data:`ACQUIRE_S` after the first step whose perceived state in force
    shows the person (``perceived`` (N,) bool: some pose angle valid); None if there is none."""
    first = np.flatnonzero(perceived)
    return int(first[0]) + round(ACQUIRE_S / dt) if first.size else None


def delayed(q: np.ndarray, steps: int) -> np.ndarray:
    """``q`` (N, …) delayed by ``steps`` ≥ 0 samples: out[k] = q[max(k − steps, 0)]."""
    return q[np.maximum(np.arange(len(q)) - steps, 0)]


def fidelity(q_true: np.ndarray, q_sim: np.ndarray, free: np.ndarray, directions: np.ndarray,
             directions_at_target: np.ndarray, perceived: np.ndarray, dt: float,
             latency_s: float, *, q_nom: np.ndarray, q_cbf: np.ndarray,
             directions_seen_late: np.ndarray, q_limits_floor: np.ndarray) -> dict[str, float | None]:
    """The ``fidelity`` object of one run (module docstring): ``q_true``/``q_sim`` (N, 8) rad,
    ``free`` (N,) the free steps, ``directions``/``directions_at_target``/``directions_seen_late``
    (N, 4) deg from :func:`direction_errors` at q_sim / at q_true / at q_true one latency late,
    ``perceived`` (N,) the perceived state in force shows the person, ``latency_s`` the camera
    latency (s), ``q_nom``/``q_cbf`` (N, 8) rad the run's target and safe command (the stages of
    the lag), ``q_limits_floor`` (N, 8) rad :func:`limited_follower` of q_true seen one latency late."""
    start = judged_from(perceived, dt)
    first = len(q_true) if start is None else min(start, len(q_true))
    lag = lag_ms(q_true, q_sim, dt, first)
    chain = (q_true, q_nom, q_cbf, q_sim)
    stages = {f"lag_ms_{stage}": lag_ms(chain[i], chain[i + 1], dt, first) for i, stage in enumerate(LAG_STAGES)}
    limits_floor = lag_ms(q_true, q_limits_floor, dt, first)
    judged = slice(first, None)
    late = delayed(q_true, round(latency_s / dt))[judged]
    q_true, q_sim, free = q_true[judged], q_sim[judged], free[judged]
    error = q_sim - q_true
    judged_free = [d[judged][free] for d in (directions, directions_at_target, directions_seen_late)]
    defined = np.isfinite(judged_free[0]) & np.isfinite(judged_free[1]) & np.isfinite(judged_free[2])
    samples, at_target, seen_late = (d[defined] for d in judged_free)

    def rms(e: np.ndarray) -> float | None:
        return round(float(np.sqrt(np.mean(e**2))), 6) if e.size else None

    def percentile(values: np.ndarray, p: float) -> float | None:
        return round(float(np.percentile(values, p)), 3) if values.size else None

    return {
        "lag_ms": lag,
        **stages,
        "rms_true": rms(error),
        "rms_true_free": rms(error[free]),
        "rms_true_free_latency_floor": rms((late - q_true)[free]),
        "direction_error_deg_p50": percentile(samples, 50),
        "direction_error_deg_p95": percentile(samples, 95),
        "direction_error_deg_p50_at_target": percentile(at_target, 50),
        "direction_error_deg_p95_at_target": percentile(at_target, 95),
        "direction_error_deg_p50_latency_floor": percentile(seen_late, 50),
        "direction_error_deg_p95_latency_floor": percentile(seen_late, 95),
        "lag_ms_limits_floor": limits_floor,
        "judged_from_s": None if start is None else round(start * dt, 6),
    }
