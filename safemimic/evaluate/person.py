"""The two people of an evaluation: the true person and the perceived one (architecture §7).

**True person** (:func:`true_person`): the source's skeleton as recorded, with no point filter,
interpolated linearly to the control rate (control time t_k = k Δt from the first frame; a
keypoint is valid at t_k when it is valid in both frames around t_k; after the last frame the
last one is held). Its capsules (built as perception builds them, radii from ``conf.human``) are
MuJoCo's person and what every ``true_*`` metric measures against; its angles (the perception's
estimator) retargeted (same calibration and mirror) give ``q_true``, the imitation's reference.

**Perceived person** (:func:`perceive`): what the safety layer gets. Every frame of the source,
optionally corrupted by a :class:`CameraModel`, goes through the perception pipeline (point
filter → angles + capsules) exactly as the perception service does, and becomes available
``latency_s`` after its capture time:

- depth noise (``depth_noise_m`` = σ, per frame): a common shift of the whole skeleton,
  δ ~ N(0, σ²) along the camera's viewing ray to the skeleton's centroid, plus a per-keypoint
  part ε_k ~ N(0, (σ/2)²) along keypoint k's own ray (the camera at
  ``perception.camera.extrinsics.position``). A monocular or stereo camera is least certain
  along its rays; most of that error is shared by the whole body (the person's scale/distance);
- dropout (``dropout`` = P): each keypoint is missing in a frame with probability P, independently
  from frame to frame, or, with ``dropout_frames`` = L > 0, in runs of L frames on average (an arm
  behind the body, a hand out of view, a detector's confidence flickering below its threshold):
  each keypoint is a two-state Markov chain, hidden → seen with probability 1/L and seen → hidden
  with probability s = P / (L (1 − P)), whose stationary share of hidden frames is
  π = sL / (1 + sL) = P and whose hidden runs are geometric with mean L. Every keypoint starts seen.
  Runs longer than the point filter's ``perception.point_filter.hold_s`` invalidate the capsule:
  the safety layer then remembers it as *lost* (``safety.lost_human_hold_s``), which independent
  dropout of a few percent almost never does;
- ``seed``: the random stream (numpy's default generator): the same seed, the same corruption.

With ``latency_s = 0`` and no noise the perceived person is the pipeline's plain output.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from safemimic.evaluate.source import EvaluationInput
from services.perception.angles import PoseEstimator
from services.perception.capsules import HumanCapsules
from services.perception.pipeline import PerceptionCounters, PerceptionPipeline
from services.perception.point_filter import FilteredSkeleton
from services.perception.base import SkeletonFrame
from services.safety.kinematics import RobotKinematics
from services.safety.direction_retarget import DirectionRetargeter
from services.safety.retarget import Pose, Retargeter
from shared.config import StackConfig
from shared.messages import HumanState

#: Default camera latency (s): one 30 Hz frame of exposure and readout (33 ms) + pose inference
#: (≈ 20–30 ms on this CPU) + transport.
DEFAULT_LATENCY_S = 0.060


@dataclass(frozen=True)
class CameraModel:
    """How the perceived person differs from the true one: delay (s), depth noise σ (m), dropout
    probability and ``dropout_frames`` the mean length of a keypoint's hidden runs (frames; 0:
    independent per frame; module docstring), random seed, and ``jitter_s``: the mean (s) of an extra delay per frame,
    exponentially distributed (a camera late now and then: inference or transport stalling; most
    frames a little late, a few by several times the mean), each frame still arriving after the
    one before it (a publisher's order is kept). Raises ValueError for values outside their ranges."""

    latency_s: float = DEFAULT_LATENCY_S
    depth_noise_m: float = 0.0
    dropout: float = 0.0
    seed: int = 0
    jitter_s: float = 0.0
    dropout_frames: float = 0.0

    def __post_init__(self) -> None:
        if not 0.0 <= self.latency_s <= 2.0:
            raise ValueError(f"latency must be in [0, 2000] ms, got {1e3 * self.latency_s:g} ms")
        if not 0.0 <= self.jitter_s <= 1.0:
            raise ValueError(f"latency jitter must be in [0, 1000] ms, got {1e3 * self.jitter_s:g} ms")
        if not 0.0 <= self.depth_noise_m <= 1.0:
            raise ValueError(f"depth noise must be in [0, 1] m, got {self.depth_noise_m:g}")
        if not 0.0 <= self.dropout < 1.0:
            raise ValueError(f"dropout must be in [0, 1), got {self.dropout:g}")
        if self.dropout_frames != 0.0 and not 1.0 <= self.dropout_frames <= 1e4:
            raise ValueError(f"dropout runs must average 1 to 10000 frames (0: independent), got {self.dropout_frames:g}")
        if self.dropout_frames and not self.dropout:
            raise ValueError("dropout runs need the share of frames hidden: a dropout P > 0")
        if self.dropout_frames and self.dropout > self.dropout_frames * (1.0 - self.dropout):
            raise ValueError(f"a keypoint hidden {100 * self.dropout:g} % of the frames needs runs of at least "
                             f"{self.dropout / (1.0 - self.dropout):g} frames on average, got {self.dropout_frames:g}")

    def settings(self) -> dict[str, float | int]:
        """The ``input`` keys of metrics.json."""
        return {"latency_ms": round(1e3 * self.latency_s, 6), "depth_noise_m": self.depth_noise_m,
                "dropout": self.dropout, "dropout_frames": self.dropout_frames, "seed": self.seed,
                "latency_jitter_ms": round(1e3 * self.jitter_s, 6)}

    def hidden(self, draws: np.ndarray, hidden_before: np.ndarray) -> np.ndarray:
        """(K,) bool, the keypoints hidden in a frame from K uniform ``draws`` in [0, 1) and
        ``hidden_before`` (K,) bool, those hidden in the frame before (module docstring): draw < P
        independently; in runs, draw < 1 − 1/L where hidden before, draw < P / (L (1 − P)) where seen."""
        if not self.dropout_frames:
            return draws < self.dropout
        stay = 1.0 - 1.0 / self.dropout_frames
        start = self.dropout / (self.dropout_frames * (1.0 - self.dropout))
        return draws < np.where(hidden_before, stay, start)

    def arrivals(self, frame_times: np.ndarray) -> np.ndarray:
        """(F,) when each frame's state becomes available (s, on ``frame_times``' clock): its frame
        time + ``latency_s`` + the frame's jitter, never before the previous frame's. The jitter
        has a random stream of its own (``seed``), so noise and dropout are the same with or
        without it; without it, exactly frame time + latency."""
        arrival = np.asarray(frame_times, dtype=np.float64) + self.latency_s
        if self.jitter_s > 0.0:
            arrival = arrival + np.random.default_rng([self.seed, 1]).exponential(self.jitter_s, len(arrival))
            arrival = np.maximum.accumulate(arrival)
        return arrival


def latency_text(settings: dict[str, Any]) -> str:
    """The camera delay of :meth:`CameraModel.settings` (or an ``input`` of metrics.json) in words:
    "60 ms", or "60 ms + jitter (mean) 30 ms"."""
    jitter = settings.get("latency_jitter_ms", 0.0)
    return f"{settings['latency_ms']:g} ms" + (f" + jitter (mean) {jitter:g} ms" if jitter else "")


@dataclass(frozen=True)
class HumanTrack:
    """The perceived person: the HumanState of every frame and when it became available, ``t``
    (F,) s from the first frame (capture time + latency); perception's counters."""

    t: np.ndarray
    states: tuple[HumanState, ...]
    counters: PerceptionCounters

    def in_view(self, index: np.ndarray) -> np.ndarray:
        """Whether the state in force shows the person, per step: ``index`` (N,) the state in force
        (−1: none yet) → (N,) bool, a state is in force and some pose angle of it is valid (a
        frame without a skeleton, e.g. before the person walks into view, shows nobody)."""
        shows = np.array([bool(s.theta_valid.any()) for s in self.states] + [False])
        return shows[np.where(index >= 0, index, len(self.states))]


@dataclass(frozen=True)
class TruePerson:
    """The true person at every control step k (N steps): ``keypoints`` (N, 15, 3) m and
    ``valid`` (N, 15); ``capsules`` (N, 7, 2, 3) m, ``capsule_valid`` (N, 7), ``radii`` (7,) m;
    ``q_true`` (N, 8) rad, the retargeted angles of the true skeleton; ``robot_at_target``
    (N, 7, 2, 3) m, the robot's CBF capsules placed exactly at ``q_true`` (perfect tracking: what
    the retargeting and the robot's joint ranges allow, which no controller can beat)."""

    t: np.ndarray
    keypoints: np.ndarray
    valid: np.ndarray
    capsules: np.ndarray
    capsule_valid: np.ndarray
    radii: np.ndarray
    q_true: np.ndarray
    robot_at_target: np.ndarray


def corrupt(frame: SkeletonFrame, camera_position: np.ndarray, model: CameraModel, rng: np.random.Generator,
            hidden_before: np.ndarray | None = None) -> tuple[SkeletonFrame, np.ndarray]:
    """``frame`` with the depth noise and dropout of ``model`` (module docstring), and (K,) bool the
    keypoints it hid, to pass as ``hidden_before`` with the next frame (None: none hidden before);
    draws the same number of random values whatever the frame holds, so a seed fixes the whole
    stream."""
    common, per_point = rng.normal(0.0, 1.0), rng.normal(0.0, 1.0, len(frame.xyz))
    before = np.zeros(len(frame.xyz), bool) if hidden_before is None else hidden_before
    dropped = model.hidden(rng.random(len(frame.xyz)), before)
    xyz, conf = frame.xyz.copy(), frame.conf.copy()
    sigma = model.depth_noise_m
    present = np.isfinite(xyz).all(axis=1)
    if sigma > 0.0 and present.any():
        rays = xyz - camera_position
        rays /= np.maximum(np.linalg.norm(rays, axis=1, keepdims=True), 1e-9)
        centre = xyz[present].mean(axis=0) - camera_position
        centre /= max(float(np.linalg.norm(centre)), 1e-9)
        xyz += sigma * common * centre + (0.5 * sigma * per_point)[:, None] * rays
    xyz[dropped], conf[dropped] = np.nan, 0.0
    return SkeletonFrame(t=frame.t, xyz=xyz, conf=conf, captured=frame.captured, discontinuity=frame.discontinuity), dropped


def perceive(conf: StackConfig, source: EvaluationInput, model: CameraModel = CameraModel(latency_s=0.0)) -> HumanTrack:
    """Run the perception pipeline over every (corrupted) frame in order; each state becomes
    available ``model.latency_s`` after its frame, later by the model's jitter
    (:meth:`CameraModel.arrivals`; ``HumanState.stamp`` = that time, ``capture_stamp`` the frame's
    own time, both from the first frame)."""
    pipeline = PerceptionPipeline(conf.perception, conf.human)
    rng = np.random.default_rng(model.seed)
    camera = np.asarray(conf.perception.camera.extrinsics.position, dtype=np.float64)
    noisy = model.depth_noise_m > 0.0 or model.dropout > 0.0
    t0 = source.frames[0].t
    arrivals = model.arrivals(np.array([frame.t - t0 for frame in source.frames]))
    states, hidden = [], None
    for frame, arrival in zip(source.frames, arrivals.tolist(), strict=True):
        seen, hidden = corrupt(frame, camera, model, rng, hidden) if noisy else (frame, None)
        states.append(pipeline.step(seen).to_message(stamp=arrival, capture_stamp=frame.t - t0))
    return HumanTrack(t=np.array([s.stamp for s in states]), states=tuple(states), counters=pipeline.counters)


def interpolate_skeleton(source: EvaluationInput, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The source's skeleton at times ``t`` (s from the first frame), linear between frames:
    points (N, 15, 3) m (NaN where invalid) and valid (N, 15). Before the first frame the first
    is used, after the last the last."""
    times = np.array([f.t for f in source.frames]) - source.frames[0].t
    xyz = np.stack([f.xyz for f in source.frames])
    present = np.isfinite(xyz).all(axis=2) & (np.stack([f.conf for f in source.frames]) > 0.0)
    if len(times) > 1:
        upper = np.clip(np.searchsorted(times, t, side="right"), 1, len(times) - 1)
        lower = upper - 1
    else:  # one frame: held throughout
        upper = lower = np.zeros(t.shape, np.intp)
    span = times[upper] - times[lower]
    w = np.clip(np.divide(t - times[lower], span, out=np.zeros_like(t), where=span > 0), 0.0, 1.0)
    # a neighbour with weight 0 does not matter (the last frame held, an exact frame time): a missing
    # one (NaN) is blended as 0, never as 0 · NaN = NaN in a point counted valid
    filled = np.where(present[..., None], xyz, 0.0)
    points = (1.0 - w)[:, None, None] * filled[lower] + w[:, None, None] * filled[upper]
    valid = (present[lower] | (w[:, None] == 1.0)) & (present[upper] | (w[:, None] == 0.0))
    points[~valid] = np.nan
    return points, valid


def true_person(conf: StackConfig, source: EvaluationInput, t: np.ndarray, retargeter: Retargeter | DirectionRetargeter,
                kinematics: RobotKinematics) -> TruePerson:
    """The true person at control times ``t`` (module docstring); ``retargeter`` maps its angles
    to ``q_true`` (a fresh one per call: it keeps the last valid target), ``kinematics`` places the
    robot's capsules there."""
    points, valid = interpolate_skeleton(source, t)
    builder = HumanCapsules(conf.human)
    estimator = PoseEstimator(conf.perception.angles)
    n = len(t)
    capsules, capsule_valid, q_true = np.empty((n, 7, 2, 3)), np.empty((n, 7), bool), np.empty((n, 8))
    robot_at_target = np.empty((n, 7, 2, 3))
    unchanged = np.zeros(points.shape[1], bool)
    for k in range(n):
        capsules[k], capsule_valid[k], _ = builder(FilteredSkeleton(float(t[k]), points[k], valid[k], unchanged))
        theta, theta_valid = estimator(np.nan_to_num(points[k]), valid[k], float(t[k]))
        pose = Pose(theta, theta_valid, np.zeros_like(theta), points[k], valid[k], float(t[k]))
        q_true[k] = retargeter.track(pose)[0]
        robot_at_target[k] = kinematics.compute(q_true[k])[0]
    return TruePerson(t=t, keypoints=points, valid=valid, capsules=capsules, capsule_valid=capsule_valid,
                      radii=builder.radii.copy(), q_true=q_true, robot_at_target=robot_at_target)
