"""Canonical names shared by every service (architecture §3).

Order matters: arrays in messages and recordings are indexed by these tuples.
"""

from __future__ import annotations

#: The 15 canonical skeleton keypoints; every skeleton source maps into these.
KEYPOINT_NAMES: tuple[str, ...] = (
    "pelvis",
    "spine_chest",
    "head",
    "left_shoulder",
    "left_elbow",
    "left_wrist",
    "right_shoulder",
    "right_elbow",
    "right_wrist",
    "left_hip",
    "left_knee",
    "left_ankle",
    "right_hip",
    "right_knee",
    "right_ankle",
)
KEYPOINT_INDEX: dict[str, int] = {name: i for i, name in enumerate(KEYPOINT_NAMES)}

#: The reduced human pose θ ∈ R^8 (paper eq. 1), same order as the robot joints.
POSE_ANGLE_NAMES: tuple[str, ...] = (
    "torso_roll",
    "torso_pitch",
    "left_shoulder_pitch",
    "left_shoulder_roll",
    "left_elbow",
    "right_shoulder_pitch",
    "right_shoulder_roll",
    "right_elbow",
)

#: The robot's 8 imitation joints (G1 names), q ∈ R^8 (paper §II-B).
IMITATION_JOINT_NAMES: tuple[str, ...] = (
    "waist_roll_joint",
    "waist_pitch_joint",
    "left_shoulder_pitch_joint",
    "left_shoulder_roll_joint",
    "left_elbow_joint",
    "right_shoulder_pitch_joint",
    "right_shoulder_roll_joint",
    "right_elbow_joint",
)

#: The seven capsules of robot and human alike (paper §III-A).
CAPSULE_NAMES: tuple[str, ...] = (
    "torso",
    "left_upper_arm",
    "left_forearm",
    "right_upper_arm",
    "right_forearm",
    "left_thigh",
    "right_thigh",
)

#: Services that announce themselves with a liveliness token ``alive/{service}``.
SERVICE_NAMES: tuple[str, ...] = ("perception", "safety", "executor", "config_api")
