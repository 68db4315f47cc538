"""One realistic, valid message of every type (deterministic), for tests of the codec and the bus."""

from __future__ import annotations

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
            base |= dict(mode=SafetyMode.ACTIVE, human_stamp=1234.4, human_seq=7)
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
