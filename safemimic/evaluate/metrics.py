"""``metrics.json``: what the two runs did, as numbers (metres, radians, seconds, milliseconds).

``{"cbf": {...}, "nominal": {...}, "input": {...}}``. Each run has exactly the keys of
:data:`RUN_KEYS`:

- ``min_h_self`` / ``min_h_human``: the smallest barrier value h (m) over the self pairs / the
  robot–human pairs, over every control step (null: no such pair was ever evaluated);
- ``frames_h_negative``: control steps at which some monitored h < 0;
- ``contacts_robot_robot``: control steps at which MuJoCo found the simulated robot's own
  collision geometry touching itself (non-adjacent bodies; a pair touching at home once it presses
  more than 1 mm deeper). The person never pushes the robot (its capsules collide with nothing),
  so these come from the robot's own motion only;
- ``contacts_robot_human``: control steps at which some robot surface penetrates the *perceived*
  person's capsules (what the filter saw, drawn translucent in the snapshot);
- ``rms_tracking``: RMS of q_cbf − q_nom over every step and joint (rad);
- ``rms_tracking_free``: the same over the steps at which no constraint binds in the CBF run (no
  capsule pair, no joint barrier) — the same steps for both runs, so the two numbers compare
  like with like;
- ``max_joint_speed``: the largest commanded joint speed |u*| (rad/s);
- ``qp_ms_p50`` / ``qp_ms_p99``: QP solve time percentiles (ms, wall clock: the only values
  that differ between two runs of the same input);
- ``relaxed_steps`` / ``hold_steps``: steps the filter reported RELAXED (rows infeasible or the
  state already inside a barrier) / HOLD;
- ``protective_stop_steps`` / ``backing_out_steps``: steps that were a protective stop (the robot
  aiming at rest: a person inside a margin, ``safety.on_intrusion``) / of those, the steps that
  backed an arm out of a person standing still inside it (``safety.intrusion_backout_mps``): how
  long the robot stood instead of imitating;
- ``person_lost_steps``: steps at which the robot stood instead of imitating because the person's
  state was stale (``safety.human_timeout_s``) or one of their capsules was lost (a body part
  perception stopped seeing, held for ``safety.lost_human_hold_s``): what a camera that loses
  keypoints costs the imitation (``--dropout`` with ``--dropout-frames``);
- ``nan_count``: non-finite values in q_cbf, u* and the simulated joints (must be 0).

Those are the filter's own view (q_cbf against the perceived person: delayed, filtered, held).
The world's view (:mod:`safemimic.evaluate.truth`: the simulated joints q_sim against the true
person, every pair, every robot surface):

- ``true_min_h_self``: the smallest self-pair barrier h = d − r_A − r_B − φ at q_sim (m; the
  robot description's self pairs and static pairs);
- ``true_min_clearance_human``: the smallest robot–person capsule surface distance at q_sim
  (m, no φ; null: the person never had a capsule);
- ``true_contacts_robot_human``: steps at which some robot surface (collision geoms and
  visual-only meshes such as the G1's hands) penetrates the true person's capsules;
- ``true_contacts_fixed_bodies``: of those, the steps at which the true person is inside a robot
  body that no imitation joint moves (pelvis, legs, waist yaw link): contacts no controller of
  these joints can avoid, a floor under ``true_contacts_robot_human``;
- ``true_max_depth_human``: the deepest such penetration (m);
- ``robot_caused_contact_steps``: contact steps at which the robot moved a touching pair closer
  faster than 1 mm/s (its own velocity at the contact point along the normal);
  ``person_caused_contact_steps``: the other contact steps (the person moved into a robot that
  was still or retreating);
- ``robot_approach_steps``: steps at which some robot–person pair's true clearance is below φ
  and the robot closes it faster than 1 mm/s;
- ``robot_caused_contact_steps_commanded`` / ``robot_approach_steps_commanded``: of those, the
  steps at which the command u* itself closes such a pair faster than 1 mm/s (its velocity at the
  robot's pose, along the same normal): what the filter asked for. The other steps are the
  servos moving where their command does not — trailing it, or settling on it after the command
  stopped (the simulated joints stick within their friction's dead band, f/kp = 2 mrad on an arm,
  as a geared joint does: :data:`~services.executor.mujoco.model.STICTION_IMPEDANCE`);
- ``robot_caused_contact_mm`` / ``robot_approach_mm``: how far the robot closed in over those
  steps, Σ_k Δt · (the fastest closing speed of a touching / an approached pair at step k), mm:
  the size of what the step counts count;
- ``torque_saturated_steps``: steps at which some imitation joint's simulated motor gave its whole
  torque (the joint's ``actuatorfrcrange``: the G1's 25 N·m at the arms, 50 at the waist): its
  servo asked for more (its error, the torque feed-forward of the commanded acceleration with the
  other joints' reactions, gravity) than the motor has, so the joint did not move as commanded and
  the robot left the path its barriers were computed for;
- ``fidelity``: lag, RMS and arm-direction error against the true person
  (:mod:`safemimic.evaluate.fidelity`).

Values are rounded (lengths and angles to 1e-6, times to 1e-4 ms) so the file is stable and
readable; everything but the two QP timings is a pure function of the input and configuration.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from safemimic.evaluate.episode import MODES, Episode
from safemimic.evaluate.fidelity import delayed, direction_errors, fidelity, limited_follower
from safemimic.evaluate.person import CameraModel, HumanTrack, TruePerson
from safemimic.evaluate.source import EvaluationInput
from safemimic.evaluate.truth import CLOSING_SPEED
from shared.config import IntrusionResponse, PointFilterKind, RetargetMethod, SafetyConfig, StackConfig, TargetPath
from shared.messages import SafetyMode

RUN_KEYS: tuple[str, ...] = (
    "min_h_self", "min_h_human", "frames_h_negative", "contacts_robot_robot", "contacts_robot_human",
    "rms_tracking", "rms_tracking_free", "max_joint_speed", "qp_ms_p50", "qp_ms_p99",
    "relaxed_steps", "hold_steps", "protective_stop_steps", "backing_out_steps", "person_lost_steps", "nan_count",
    "true_min_h_self", "true_min_clearance_human", "true_contacts_robot_human", "true_contacts_fixed_bodies",
    "true_max_depth_human",
    "robot_caused_contact_steps", "person_caused_contact_steps", "robot_approach_steps",
    "robot_caused_contact_steps_commanded", "robot_approach_steps_commanded", "robot_caused_contact_mm",
    "robot_approach_mm", "torque_saturated_steps", "fidelity",
)
#: The wall-clock keys of a run (excluded when two evaluations are compared for determinism).
TIMING_KEYS: tuple[str, ...] = ("qp_ms_p50", "qp_ms_p99")


def _length(value: float) -> float | None:
    return round(float(value), 6) + 0.0 if np.isfinite(value) else None  # + 0.0: no "-0.0"




def _millimetres(metres: float) -> float:
    return round(1e3 * float(metres), 3) + 0.0


def _rms(error: np.ndarray) -> float:
    return _length(np.sqrt(np.mean(error**2))) if error.size else 0.0


def free_steps(cbf: Episode) -> np.ndarray:
    """(N,) bool: steps at which no constraint binds in the CBF run (no QP row, and the speed and
    separation cap does not slow the reference: :attr:`Episode.binding`)."""
    return ~cbf.binding


def _nanmin(values: np.ndarray) -> float | None:
    """The smallest non-NaN value (rounded), or None when there is none."""
    return _length(np.nanmin(values)) if values.size and not np.isnan(values).all() else None


def truth_metrics(ep: Episode, phi: float) -> dict[str, Any]:
    """The ``true_*``, contact-cause and motor-saturation keys of one run (``phi``: the safety margin φ, m)."""
    is_self = ep.truth_is_self
    dt = float(ep.t[1] - ep.t[0]) if len(ep.t) > 1 else 0.0
    human_clearance = ep.true_clearance[:, ~is_self]
    rate = np.nan_to_num(ep.true_rate[:, ~is_self], nan=0.0)
    commanded = np.nan_to_num(ep.true_rate_commanded[:, ~is_self], nan=0.0) < -CLOSING_SPEED
    approach = (np.nan_to_num(human_clearance, nan=np.inf) < phi) & (rate < -CLOSING_SPEED)  # (N, pairs)
    approach_speed = np.where(approach, -rate, 0.0).max(axis=1, initial=0.0)
    self_clearance = _nanmin(ep.true_clearance[:, is_self])
    robot_caused = int(np.count_nonzero(ep.robot_caused))
    contacts = int(np.count_nonzero(ep.true_contact))
    return {
        "true_min_h_self": None if self_clearance is None else _length(self_clearance - phi),
        "true_min_clearance_human": _nanmin(human_clearance),
        "true_contacts_robot_human": contacts,
        "true_contacts_fixed_bodies": int(np.count_nonzero(ep.fixed_contact)),
        "true_max_depth_human": _length(ep.true_depth.max(initial=0.0)),
        "robot_caused_contact_steps": robot_caused,
        "person_caused_contact_steps": contacts - robot_caused,
        "robot_approach_steps": int(np.count_nonzero(approach.any(axis=1))),
        "robot_caused_contact_steps_commanded": int(np.count_nonzero(ep.robot_caused_commanded)),
        "robot_approach_steps_commanded": int(np.count_nonzero((approach & commanded).any(axis=1))),
        "robot_caused_contact_mm": _millimetres(ep.closing_speed[ep.robot_caused].sum() * dt),
        "robot_approach_mm": _millimetres(approach_speed.sum() * dt),
        "torque_saturated_steps": int(np.count_nonzero(ep.torque_saturated)),
    }


def run_metrics(ep: Episode, free: np.ndarray, person: TruePerson, phi: float, mirror: bool,
                target: tuple[np.ndarray, np.ndarray], latency_s: float, in_view: np.ndarray,
                q_limits_floor: np.ndarray) -> dict[str, Any]:
    """The :data:`RUN_KEYS` of one run; ``free``: the steps counted by the ``*_free`` keys;
    ``person``: the true person; ``phi``: the safety margin (m); ``mirror``: facing the person;
    ``latency_s``: the camera latency (s) of the fidelity floor; ``in_view`` (N,): the perceived
    state in force shows the person (:meth:`HumanTrack.in_view`; fidelity is judged from 1 s after
    the first such step);
    ``target``: :func:`direction_errors` of the robot placed at q_true and at q_true one latency
    late (the same for every run of one input: :func:`target_directions`); ``q_limits_floor``:
    :func:`limits_floor_joints` (the same for every run of one input)."""
    is_self = ep.pairs.is_self
    error = ep.q_cbf - ep.q_nom
    negative = np.nan_to_num(ep.h, nan=np.inf) < 0.0
    modes = np.bincount(ep.mode, minlength=len(MODES))
    qp = np.percentile(ep.qp_ms, [50, 99])
    nonfinite = sum(int(np.count_nonzero(~np.isfinite(a))) for a in (ep.q_cbf, ep.u, ep.q_sim))
    metrics = {
        "min_h_self": _nanmin(ep.h[:, is_self]),
        "min_h_human": _nanmin(ep.h[:, ~is_self]),
        "frames_h_negative": int(np.count_nonzero(negative.any(axis=1))),
        "contacts_robot_robot": ep.tally.robot_robot.steps,
        "contacts_robot_human": ep.tally.robot_human.steps,
        "rms_tracking": _rms(error),
        "rms_tracking_free": _rms(error[free]),
        "max_joint_speed": _length(np.max(np.abs(ep.u))),
        "qp_ms_p50": round(float(qp[0]), 4),
        "qp_ms_p99": round(float(qp[1]), 4),
        "relaxed_steps": int(modes[MODES.index(SafetyMode.RELAXED)]),
        "hold_steps": int(modes[MODES.index(SafetyMode.HOLD)]),
        "protective_stop_steps": int(np.count_nonzero(ep.stopped)),
        "backing_out_steps": int(np.count_nonzero(ep.backing_out)),
        "person_lost_steps": int(np.count_nonzero(ep.person_lost)),
        "nan_count": nonfinite,
        **truth_metrics(ep, phi),
        "fidelity": fidelity(person.q_true, ep.q_sim, free,
                             direction_errors(person.keypoints, person.valid, ep.robot_capsules, mirror),
                             target[0], in_view, _step(ep.t), latency_s, q_nom=ep.q_nom, q_cbf=ep.q_cbf,
                             directions_seen_late=target[1], q_limits_floor=q_limits_floor),
    }
    assert tuple(metrics) == RUN_KEYS
    return metrics


def _step(t: np.ndarray) -> float:
    """The control period (s) of the time steps ``t`` (1 for a single step: nothing to delay)."""
    return float(t[1] - t[0]) if len(t) > 1 else 1.0


def target_directions(person: TruePerson, mirror: bool, latency_s: float) -> tuple[np.ndarray, np.ndarray]:
    """(N, 4) deg each: :func:`direction_errors` of the robot placed exactly at the true person's q_true,
    and at q_true one camera latency ``latency_s`` late (against the person now: the latency floor)."""
    late = delayed(person.robot_at_target, round(latency_s / _step(person.t)))
    return (direction_errors(person.keypoints, person.valid, person.robot_at_target, mirror),
            direction_errors(person.keypoints, person.valid, late, mirror))


def limits_floor_joints(person: TruePerson, safety: SafetyConfig, latency_s: float) -> np.ndarray:
    """(N, 8) rad: :func:`limited_follower` of the true person's q_true seen one camera latency
    ``latency_s`` late, within ``safety.u_max`` and ``safety.accel_max`` (the lag's limits floor; the
    same for every run of one input)."""
    dt = _step(person.t)
    return limited_follower(delayed(person.q_true, round(latency_s / dt)), dt, safety.u_max, safety.accel_max)


#: Below this share of the steps with the whole true person, the contact figures miss part of them.
COMPLETE_WARNING = 0.9


def input_metrics(
    conf: StackConfig, source: EvaluationInput, human: HumanTrack, cbf: Episode, placement: str, camera: CameraModel,
    person_complete: float,
) -> dict[str, Any]:
    """What was evaluated: source, duration, robot, the safety parameters, perception counters, and
    ``true_person_complete`` (``person_complete``: the share of the control steps at which every
    capsule of the true person exists; where one does not, the recording does not say where that
    body part was, and no contact with it can be counted)."""
    c = human.counters
    s = conf.safety
    return {
        "source": source.name,
        "placement": placement,
        "robot_model": Path(conf.robot.model).name if conf.robot.model else "default",
        "frames": len(source.frames),
        "fps": round(source.fps, 6),
        "seconds": round(len(cbf.t) / s.rate_hz, 6),
        "control_steps": len(cbf.t),
        "rate_hz": s.rate_hz,
        "gamma": s.gamma,
        "phi": s.phi,
        "gain": s.gain,
        "human_velocity_term": s.human_velocity_term,
        "human_lookahead_s": s.human_lookahead_s,
        "human_predict_s": s.human_predict_s,
        "human_margin": s.human_margin,
        "human_standoff_m": s.human_standoff_m,
        "self_margin": s.self_margin,
        "feedforward": s.feedforward,
        "target_path": TargetPath(s.target_path).value,
        "retargeting": RetargetMethod(conf.retargeting.method).value,
        "point_filter": PointFilterKind(conf.perception.point_filter.kind).value,
        "on_intrusion": IntrusionResponse(s.on_intrusion).value,
        "intrusion_backout_mps": s.intrusion_backout_mps,
        "human_speed_mps": s.human_speed_mps,
        **camera.settings(),
        "self_pairs": int(np.count_nonzero(cbf.pairs.is_self)),
        "human_pairs": int(np.count_nonzero(~cbf.pairs.is_self)),
        "free_steps": int(np.count_nonzero(free_steps(cbf))),
        "true_person_complete": round(person_complete, 6),
        "home_contacts_pressed_only": [f"{a}|{b}" for a, b in cbf.home_contacts],
        "perception": {
            "rejected_jumps": c.rejected_jumps,
            "filter_resets": c.filter_resets,
            "missing_points": c.missing_points,
            "invalid_frames": c.invalid_frames,
        },
    }


def deterministic_part(metrics: dict[str, Any]) -> dict[str, Any]:
    """``metrics`` without the wall-clock :data:`TIMING_KEYS` of each run."""
    return {
        section: {k: v for k, v in values.items() if k not in TIMING_KEYS} if section in ("cbf", "nominal") else values
        for section, values in metrics.items()
    }


def write_metrics(path: Path, metrics: dict[str, Any]) -> Path:
    """Write ``metrics`` as indented JSON with a trailing newline (keys in a fixed order)."""
    path.write_text(json.dumps(metrics, indent=2, allow_nan=False) + "\n")
    return path
