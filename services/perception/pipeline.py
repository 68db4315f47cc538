"""One perception step (paper Fig. 1): point filter → (pose angles θ, human capsules) → HumanState.

The same filtered skeleton feeds both the angle estimator and the capsule builder, exactly as in
the paper. The service, the benchmark and the offline evaluator all run this class; it does no
I/O. Points are in the robot frame (x forward, y left, z up, floor z = 0).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.perception.angles import AngleRates, PoseEstimator
from services.perception.capsules import HumanCapsules
from services.perception.point_filter import PointFilter, points_array
from services.perception.base import SkeletonFrame
from shared.config import HumanConfig, PerceptionConfig
from shared.messages import HumanState
from shared.names import KEYPOINT_NAMES

N_KEYPOINTS = len(KEYPOINT_NAMES)


@dataclass(frozen=True)
class PerceptionResult:
    """Everything a HumanState carries, for one frame (arrays finite; see :class:`HumanState`)."""

    t: float
    keypoints: np.ndarray
    keypoint_valid: np.ndarray
    theta: np.ndarray
    theta_valid: np.ndarray
    theta_rate: np.ndarray
    capsules: np.ndarray
    capsule_radii: np.ndarray
    capsule_valid: np.ndarray
    capsule_velocities: np.ndarray

    def to_message(self, stamp: float, capture_stamp: float | None = None) -> HumanState:
        """The HumanState of this frame (``stamp``: publication time; ``capture_stamp``: camera time)."""
        return HumanState(
            stamp=stamp,
            keypoints=self.keypoints,
            keypoint_valid=self.keypoint_valid,
            theta=self.theta,
            theta_valid=self.theta_valid,
            theta_rate=self.theta_rate,
            capsules=self.capsules,
            capsule_radii=self.capsule_radii,
            capsule_valid=self.capsule_valid,
            capsule_velocities=self.capsule_velocities,
            capture_stamp=capture_stamp,
        )


@dataclass
class PerceptionCounters:
    """What the pipeline saw: frames, filter events, and frames with something invalid."""

    frames: int = 0
    rejected_jumps: int = 0
    reacquired: int = 0
    filter_resets: int = 0
    missing_points: int = 0  # keypoint-frames without a valid point
    invalid_frames: int = 0  # frames with an invalid angle or capsule


class PerceptionPipeline:
    """Filter → angles + capsules for one person, frame by frame."""

    def __init__(self, conf: PerceptionConfig, human: HumanConfig) -> None:
        self.filter = PointFilter(conf.point_filter, N_KEYPOINTS)
        self.estimator = PoseEstimator(conf.angles)
        self.rates = AngleRates(conf.angles)
        self.capsules = HumanCapsules(human)
        self.counters = PerceptionCounters()

    def apply(self, conf: PerceptionConfig, human: HumanConfig) -> None:
        """Use new filter, angle and capsule parameters from the next frame on (state is kept)."""
        self.filter.conf = conf.point_filter
        self.estimator.configure(conf.angles)
        self.rates.configure(conf.angles)
        self.capsules.configure(human)

    def step(self, frame: SkeletonFrame) -> PerceptionResult:
        """Process one frame (points in the robot frame; NaN or low confidence = missing). The stages
        pass Python lists to each other; the arrays are made once, for the result."""
        resets_before = self.filter.resets
        points, valid, fresh = self.filter.update(frame.t, frame.xyz, frame.conf, frame.discontinuity)
        if self.filter.resets != resets_before:
            self.estimator.reset()
            self.rates.reset()
            self.capsules.reset()
        theta, theta_valid = self.estimator.estimate(points, valid, frame.t)
        theta_rate = self.rates.update(frame.t, theta, theta_valid, fresh)
        capsules, capsule_valid, velocities = self.capsules.build(frame.t, points, valid, fresh)
        keypoint_valid = np.array(valid, bool)
        keypoints = points_array(points)
        missing = valid.count(False)
        if missing:  # valid points are finite; the others are sent as 0
            keypoints[np.logical_not(keypoint_valid)] = 0.0

        c = self.counters
        c.frames += 1
        c.rejected_jumps = self.filter.rejected
        c.reacquired = self.filter.reacquired
        c.filter_resets = self.filter.resets
        c.missing_points += missing
        if not (all(theta_valid) and all(capsule_valid)):
            c.invalid_frames += 1
        return PerceptionResult(
            t=frame.t,
            keypoints=keypoints,
            keypoint_valid=keypoint_valid,
            theta=np.array(theta),
            theta_valid=np.array(theta_valid, bool),
            theta_rate=theta_rate,
            capsules=capsules,
            capsule_radii=self.capsules.radii,
            capsule_valid=np.array(capsule_valid, bool),
            capsule_velocities=velocities,
        )
