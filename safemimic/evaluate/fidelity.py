"""Imitation fidelity: how well the simulated robot follows the true person (the paper's future work).

Against ``q_true`` (the retargeted angles of the true skeleton: same estimator, calibration and
mirror as the stack) and the simulated joints q_sim, per run:

- ``lag_ms``: for each joint whose ``q_true`` moves more than :data:`MOVING_RAD` (peak to peak),
  the delay τ ∈ [−:data:`MAX_LEAD_S`, :data:`MAX_LAG_S`] minimising the mean of
  (q_sim(t) − q_true(t − τ))² over one common window, in control steps; the median over those
  joints (null: no joint moves, or the run is shorter than the search range);
- ``rms_true`` / ``rms_true_free``: RMS of q_sim − q_true (rad) over every step and joint / over
  the free steps (no constraint binds in the CBF run);
- ``direction_error_deg_p50`` / ``_p95``: over the free steps, the angle between the robot's and
  the person's upper arm (shoulder → elbow) and forearm (elbow → wrist) directions, each in its
  own torso frame F_T (:func:`services.perception.angles.torso_axes`: e_x right, e_y forward, e_z
  up). The robot's segments are its CBF capsules' axes at q_sim (torso capsule base as pelvis,
  upper-arm capsule bases as shoulders); facing the person (mirror), the robot's left arm is
  compared with the person's right arm reflected across the sagittal plane (lateral sign
  flipped). Percentiles over every (step, segment) sample with both directions defined.
"""

from __future__ import annotations

import numpy as np

from services.perception.angles import torso_axes
from shared.names import CAPSULE_NAMES, KEYPOINT_INDEX

#: A joint "moves" when its true target spans more than this (rad).
MOVING_RAD = 0.2
#: Delay search range (s): how far the robot may trail / lead the person.
MAX_LAG_S = 1.0
MAX_LEAD_S = 0.2
_MIN_SEGMENT = 0.05  # m: shorter torso or limb segments give no direction

_K = KEYPOINT_INDEX
_C = {name: i for i, name in enumerate(CAPSULE_NAMES)}
#: Per arm side: the person's (start, end) keypoints of upper arm and forearm; the robot's capsule.
_ARMS = {
    side: ((_K[f"{side}_shoulder"], _K[f"{side}_elbow"]), (_K[f"{side}_elbow"], _K[f"{side}_wrist"]),
           _C[f"{side}_upper_arm"], _C[f"{side}_forearm"])
    for side in ("left", "right")
}


def best_delay(reference: np.ndarray, follower: np.ndarray, dt: float) -> float | None:
    """The delay τ (s) with follower(t) ≈ reference(t − τ), by least squares over one window; None
    if the series is too short for the search range. Both (N,), sampled every ``dt`` seconds."""
    lag, lead = round(MAX_LAG_S / dt), round(MAX_LEAD_S / dt)
    n = len(reference)
    if n <= lag + lead + round(0.5 / dt):
        return None
    window = slice(lag, n - lead)
    target = follower[window]
    errors = [np.mean((target - reference[lag - d: n - lead - d]) ** 2) for d in range(-lead, lag + 1)]
    return (int(np.argmin(errors)) - lead) * dt


def lag_ms(q_true: np.ndarray, q_sim: np.ndarray, dt: float) -> float | None:
    """Median over the moving joints of :func:`best_delay` (ms); None if none moves or too short."""
    moving = [j for j in range(q_true.shape[1]) if np.ptp(q_true[:, j]) > MOVING_RAD]
    delays = [best_delay(q_true[:, j], q_sim[:, j], dt) for j in moving]
    delays = [d for d in delays if d is not None]
    return round(1e3 * float(np.median(delays)), 3) if delays else None


def _in_torso(axes, vectors: np.ndarray) -> np.ndarray:
    e_x, e_y, e_z = (np.asarray(a) for a in axes)
    return np.stack([vectors @ e_x, vectors @ e_y, vectors @ e_z], axis=-1)


def _unit(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return np.where(n > _MIN_SEGMENT, v / np.where(n > 0, n, 1.0), np.nan)


def direction_errors(keypoints: np.ndarray, valid: np.ndarray, robot: np.ndarray, mirror: bool) -> np.ndarray:
    """Angles (deg) between the person's and the robot's arm segments at each step: (N, 4) in the
    order left upper arm, left forearm, right upper arm, right forearm (of the robot); NaN where a
    direction is undefined. ``keypoints`` (N, 15, 3) and ``valid`` (N, 15) the true skeleton,
    ``robot`` (N, 7, 2, 3) the robot capsules."""
    n = len(keypoints)
    out = np.full((n, 4), np.nan)
    pelvis, l_sh, r_sh = _K["pelvis"], _K["left_shoulder"], _K["right_shoulder"]
    for k in range(n):
        if not (valid[k, pelvis] and valid[k, l_sh] and valid[k, r_sh]):
            continue
        p = keypoints[k]
        person_axes = torso_axes(p[pelvis].tolist(), p[l_sh].tolist(), p[r_sh].tolist(), _MIN_SEGMENT)
        r = robot[k]
        robot_axes = torso_axes(r[_C["torso"], 0].tolist(), r[_C["left_upper_arm"], 0].tolist(),
                                r[_C["right_upper_arm"], 0].tolist(), _MIN_SEGMENT)
        if person_axes is None or robot_axes is None:
            continue
        column = 0
        for side in ("left", "right"):
            person_side = ("right" if side == "left" else "left") if mirror else side
            upper, fore, robot_upper, robot_fore = _ARMS[side]
            person_upper, person_fore, _, _ = _ARMS[person_side]
            for (a, b), capsule in ((person_upper, robot_upper), (person_fore, robot_fore)):
                if valid[k, a] and valid[k, b]:
                    human_dir = _unit(_in_torso(person_axes, p[b] - p[a]))
                    if mirror:
                        human_dir = human_dir * np.array([-1.0, 1.0, 1.0])
                    robot_dir = _unit(_in_torso(robot_axes, r[capsule, 1] - r[capsule, 0]))
                    cosine = float(np.clip(np.dot(human_dir, robot_dir), -1.0, 1.0))
                    out[k, column] = np.degrees(np.arccos(cosine))
                column += 1
    return out


def fidelity(q_true: np.ndarray, q_sim: np.ndarray, free: np.ndarray, directions: np.ndarray,
             dt: float) -> dict[str, float | None]:
    """The ``fidelity`` object of one run (module docstring); ``directions`` from
    :func:`direction_errors`, ``free`` (N,) the free steps."""
    error = q_sim - q_true
    free_directions = directions[free]
    samples = free_directions[np.isfinite(free_directions)]

    def rms(e: np.ndarray) -> float | None:
        return round(float(np.sqrt(np.mean(e**2))), 6) if e.size else None

    def percentile(p: float) -> float | None:
        return round(float(np.percentile(samples, p)), 3) if samples.size else None

    return {
        "lag_ms": lag_ms(q_true, q_sim, dt),
        "rms_true": rms(error),
        "rms_true_free": rms(error[free]),
        "direction_error_deg_p50": percentile(50),
        "direction_error_deg_p95": percentile(95),
    }
