"""Valid messages for tests: one realistic message of every type (deterministic: the codec, bus and
security tests), a HumanState with everything valid (the codec benchmark, the flood) and random ones
(the fuzz's valid traffic)."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np

from shared.bus import TOPICS
from shared.config import StackConfig
from shared.messages import ConfigUpdate, HumanState, JointCommand, JointState, Message, SafetyMode, SafetyStatus


def rng_for(seed: int = 0) -> np.random.Generator:
    return np.random.default_rng(seed)


def make(cls: type[Message], **changes: Any) -> Message:
    """A deterministic, realistic valid instance of ``cls`` (every optional field set)."""
    rng = rng_for(hash(cls.__name__) & 0xFFFF)
    base: dict[str, Any] = {"stamp": 1234.5, "seq": 42, "source": "test"}
    if cls is HumanState:
        base |= dict(
            keypoints=rng.normal(size=(15, 3)),
            keypoint_valid=rng.random(15) > 0.2,
            theta=rng.uniform(-1, 1, 8),
            theta_valid=rng.random(8) > 0.2,
            theta_rate=rng.normal(size=8),
            capsules=rng.normal(size=(7, 2, 3)),
            capsule_radii=rng.uniform(0.03, 0.2, 7),
            capsule_valid=rng.random(7) > 0.2,
            capsule_velocities=rng.normal(size=(7, 2, 3)),
            frame_id="robot",
            capture_stamp=1234.4,
        )
    elif cls in (JointState, JointCommand):
        base |= dict(q=rng.uniform(-1, 1, 8), dq=rng.uniform(-2, 2, 8))
        if cls is JointState:
            base |= dict(q_command=rng.uniform(-1, 1, 8), command_stale=True)
        if cls is JointCommand:
            base |= dict(mode=SafetyMode.ACTIVE, human_stamp=1234.4, human_seq=7, ddq=rng.uniform(-50, 50, 8))
    elif cls is SafetyStatus:
        base |= dict(
            mode=SafetyMode.ACTIVE,
            min_h_self=0.05,
            min_h_human=0.31,
            active_constraints=2,
            total_constraints=21,
            qp_solve_time_ms=0.04,
            step_time_ms=0.3,
            deadline_misses=1,
            human_stale=True,
            joint_state_stale=True,
            human_source_lost=True,
            executor_holding=True,
            resyncing=True,
            human_lost=True,
            relaxed_pairs=["left_forearm|human.torso"],
            binding_pairs=["left_forearm|human.torso", "left_forearm|right_forearm"],
            q_nom=rng.uniform(-1, 1, 8),
            person_intrusion=True,
            backing_out=True,
            human_lateness_ms=12.5,
            watchdog_trips={"human_state": 2, "resync": 1},
            dropped={"human/state": 3},
            config_version=4,
            backend="daqp",
        )
    elif cls is ConfigUpdate:
        base |= dict(version=3, changed=["safety.gamma"], config=StackConfig().model_dump(mode="json"))
    return cls(**(base | changes))


def one_of_every_message() -> dict[str, Message]:
    """topic → a :func:`make` message of the topic's type, unpublished (seq 0, no source)."""
    return {topic: make(cls, seq=0, source="") for topic, cls in TOPICS.items()}


def human_state() -> HumanState:
    """A HumanState with every keypoint, angle and capsule valid (the codec benchmark's and the flood's)."""
    rng = np.random.default_rng(0)
    return HumanState(
        stamp=1.0,
        keypoints=rng.normal(size=(15, 3)),
        keypoint_valid=np.ones(15, bool),
        theta=rng.normal(size=8),
        theta_valid=np.ones(8, bool),
        capsules=rng.normal(size=(7, 2, 3)),
        capsule_radii=np.full(7, 0.06),
        capsule_valid=np.ones(7, bool),
        capsule_velocities=rng.normal(size=(7, 2, 3)),
    )


def random_message(cls: type[Message], rng: np.random.Generator, config: Callable[[], dict[str, Any]],
                   stamp: float = 0.0, seq: int = 0, source: str = "") -> Message:
    """A random valid message of ``cls`` drawn from ``rng`` (finite, in range; a ConfigUpdate carries
    ``config()``, a valid configuration): the fuzz's valid traffic."""

    def pick(options: list[Any]) -> Any:
        return options[int(rng.integers(len(options)))]

    common: dict[str, Any] = {"stamp": stamp, "seq": seq, "source": source}
    if cls is HumanState:
        return HumanState(
            **common, keypoints=rng.normal([0.8, 0.0, 1.1], 0.4, (15, 3)), keypoint_valid=rng.random(15) > 0.1,
            theta=rng.uniform(-math.pi, math.pi, 8), theta_valid=rng.random(8) > 0.1,
            capsules=rng.normal([0.8, 0.0, 1.0], 0.4, (7, 2, 3)), capsule_radii=rng.uniform(0.02, 0.2, 7),
            capsule_valid=rng.random(7) > 0.1,
            capsule_velocities=rng.normal(0.0, 0.5, (7, 2, 3)) if rng.random() < 0.5 else None,
            capture_stamp=stamp - 0.03 if rng.random() < 0.5 else None,
        )
    if cls is JointState:
        return JointState(**common, q=rng.uniform(-0.5, 0.5, 8), dq=rng.normal(0.0, 0.5, 8),
                          q_command=rng.uniform(-0.5, 0.5, 8) if rng.random() < 0.5 else None,
                          command_stale=bool(rng.random() < 0.2))
    if cls is JointCommand:
        return JointCommand(**common, q=rng.uniform(-0.5, 0.5, 8), dq=rng.normal(0.0, 0.5, 8),
                            ddq=rng.normal(0.0, 20.0, 8), mode=pick(list(SafetyMode)), human_stamp=stamp - 0.02, human_seq=int(rng.integers(0, 2**40)))
    if cls is SafetyStatus:
        return SafetyStatus(
            **common, mode=pick(list(SafetyMode)), min_h_self=float(rng.normal(0.1, 0.1)),
            min_h_human=float(rng.normal(0.3, 0.3)) if rng.random() < 0.7 else None,
            active_constraints=int(rng.integers(0, 72)), total_constraints=int(rng.integers(0, 200)),
            qp_solve_time_ms=float(rng.uniform(0, 1)), step_time_ms=float(rng.uniform(0, 2)),
            binding_pairs=["left_forearm|human.torso"] if rng.random() < 0.5 else [],
            q_nom=rng.uniform(-0.5, 0.5, 8) if rng.random() < 0.5 else None,
            backing_out=bool(rng.random() < 0.2), human_lateness_ms=float(rng.exponential(5.0)),
            dropped={"human/state": int(rng.integers(0, 1000))}, config_version=int(rng.integers(0, 2**31)),
        )
    if cls is ConfigUpdate:
        return ConfigUpdate(**common, version=int(rng.integers(1, 2**31)), changed=["safety.gamma"], config=config())
    raise TypeError(f"no factory for {cls.__name__}")
