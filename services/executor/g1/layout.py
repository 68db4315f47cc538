"""Unitree G1 hardware facts the G1 executor relies on (architecture §11): motor slots, joint ranges and
torque limits, topics, model variants (``mode_machine``) and default servo gains.

Sources (read, not copied):

* motor order — ``G1JointIndex`` of unitree_sdk2_python ``example/g1/low_level/g1_low_level_example.py``
  and ``example/g1/high_level/g1_arm7_sdk_dds_example.py``: legs 0–11, waist yaw/roll/pitch 12–14,
  left arm 15–21, right arm 22–28; slot 29 (``kNotUsedJoint``) carries the ``rt/arm_sdk`` blend
  weight in its ``q``; slots 30–34 are unused. ``unitree_hg`` LowCmd_/LowState_ have 35 slots.
* joint ranges and torque limits — ``range``/``actuatorfrcrange`` of the G1 29-DoF rev 1.0 model
  (MuJoCo Menagerie ``unitree_g1/g1.xml``, Unitree's ``g1_29dof_rev_1_0``); a test checks this
  table against that file.
* ``mode_machine`` → variant (which motors exist, whether the waist is locked) — the table in
  unitree_ros ``robots/g1_description/README.md``.
* gains — ``Kp``/``Kd`` of ``g1_low_level_example.py`` (whole-body hold in low-level mode) and
  ``kp = 60, kd = 1.5`` of ``g1_arm7_sdk_dds_example.py`` (upper body through ``rt/arm_sdk``).

Angles in rad, torques in N·m, gains kp in N·m/rad and kd in N·m·s/rad.
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = [
    "ARM_SDK_HOLD_GAINS",
    "ARM_SDK_SLOTS",
    "G1_JOINTS",
    "LOWCMD_HOLD_GAINS",
    "NUM_BODY_MOTORS",
    "NUM_MOTOR_SLOTS",
    "TOPIC_ARM_SDK",
    "TOPIC_LOWCMD",
    "TOPIC_LOWSTATE",
    "WEIGHT_SLOT",
    "G1Joint",
    "G1Variant",
    "joint_slot",
    "variant_of",
]

#: DDS topics (unitree_sdk2 channel names): joint state from the robot, upper-body commands blended
#: over the running balance controller, whole-body low-level commands (balance controller released).
TOPIC_LOWSTATE = "rt/lowstate"
TOPIC_ARM_SDK = "rt/arm_sdk"
TOPIC_LOWCMD = "rt/lowcmd"

#: Motor slots in ``unitree_hg`` LowCmd_/LowState_ (35), of which the G1 uses the first 29.
NUM_MOTOR_SLOTS = 35
NUM_BODY_MOTORS = 29
#: ``rt/arm_sdk``: ``motor_cmd[WEIGHT_SLOT].q`` ∈ [0, 1] blends our upper-body command (1) with the
#: balance controller's (0).
WEIGHT_SLOT = 29


@dataclass(frozen=True)
class G1Joint:
    """One G1 motor: its slot in LowCmd_/LowState_, joint name (as in the MJCF), range (rad) and
    torque limit (N·m)."""

    slot: int
    name: str
    lower: float
    upper: float
    torque_limit: float


#: The 29 motors in slot order.
G1_JOINTS: tuple[G1Joint, ...] = (
    G1Joint(0, "left_hip_pitch_joint", -2.5307, 2.8798, 88.0),
    G1Joint(1, "left_hip_roll_joint", -0.5236, 2.9671, 139.0),
    G1Joint(2, "left_hip_yaw_joint", -2.7576, 2.7576, 88.0),
    G1Joint(3, "left_knee_joint", -0.087267, 2.8798, 139.0),
    G1Joint(4, "left_ankle_pitch_joint", -0.87267, 0.5236, 50.0),
    G1Joint(5, "left_ankle_roll_joint", -0.2618, 0.2618, 50.0),
    G1Joint(6, "right_hip_pitch_joint", -2.5307, 2.8798, 88.0),
    G1Joint(7, "right_hip_roll_joint", -2.9671, 0.5236, 139.0),
    G1Joint(8, "right_hip_yaw_joint", -2.7576, 2.7576, 88.0),
    G1Joint(9, "right_knee_joint", -0.087267, 2.8798, 139.0),
    G1Joint(10, "right_ankle_pitch_joint", -0.87267, 0.5236, 50.0),
    G1Joint(11, "right_ankle_roll_joint", -0.2618, 0.2618, 50.0),
    G1Joint(12, "waist_yaw_joint", -2.618, 2.618, 88.0),
    G1Joint(13, "waist_roll_joint", -0.52, 0.52, 50.0),
    G1Joint(14, "waist_pitch_joint", -0.52, 0.52, 50.0),
    G1Joint(15, "left_shoulder_pitch_joint", -3.0892, 2.6704, 25.0),
    G1Joint(16, "left_shoulder_roll_joint", -1.5882, 2.2515, 25.0),
    G1Joint(17, "left_shoulder_yaw_joint", -2.618, 2.618, 25.0),
    G1Joint(18, "left_elbow_joint", -1.0472, 2.0944, 25.0),
    G1Joint(19, "left_wrist_roll_joint", -1.97222, 1.97222, 25.0),
    G1Joint(20, "left_wrist_pitch_joint", -1.61443, 1.61443, 5.0),
    G1Joint(21, "left_wrist_yaw_joint", -1.61443, 1.61443, 5.0),
    G1Joint(22, "right_shoulder_pitch_joint", -3.0892, 2.6704, 25.0),
    G1Joint(23, "right_shoulder_roll_joint", -2.2515, 1.5882, 25.0),
    G1Joint(24, "right_shoulder_yaw_joint", -2.618, 2.618, 25.0),
    G1Joint(25, "right_elbow_joint", -1.0472, 2.0944, 25.0),
    G1Joint(26, "right_wrist_roll_joint", -1.97222, 1.97222, 25.0),
    G1Joint(27, "right_wrist_pitch_joint", -1.61443, 1.61443, 5.0),
    G1Joint(28, "right_wrist_yaw_joint", -1.61443, 1.61443, 5.0),
)
_SLOT_OF: dict[str, int] = {j.name: j.slot for j in G1_JOINTS}

#: Slots ``rt/arm_sdk`` drives: waist (12–14) and both arms (15–28), as in Unitree's arm example,
#: which commands all 17 of them. The legs stay with the balance controller.
ARM_SDK_SLOTS: tuple[int, ...] = tuple(range(12, 29))

#: (kp, kd) of every joint that is not imitated but held at its measured pose, per channel.
#: ``rt/arm_sdk``: Unitree's arm example uses (60, 1.5) on all upper-body joints.
ARM_SDK_HOLD_GAINS: tuple[float, float] = (60.0, 1.5)
#: ``rt/lowcmd``: Unitree's low-level example's whole-body table, slot order.
LOWCMD_HOLD_GAINS: tuple[tuple[float, float], ...] = (
    *[(60.0, 1.0), (60.0, 1.0), (60.0, 1.0), (100.0, 2.0), (40.0, 1.0), (40.0, 1.0)] * 2,  # legs
    (60.0, 1.0), (40.0, 1.0), (40.0, 1.0),  # waist yaw, roll, pitch
    *[(40.0, 1.0)] * 14,  # arms
)

_WAIST_ROLL_PITCH = frozenset({13, 14})
_WRIST_PITCH_YAW = frozenset({20, 21, 27, 28})


@dataclass(frozen=True)
class G1Variant:
    """A G1 model as ``LowState_.mode_machine`` reports it: which motor slots it lacks or has
    locked (commands to them are invalid), and a name for messages."""

    mode_machine: int
    name: str
    absent_slots: frozenset[int]

    @property
    def waist_locked(self) -> bool:
        """Waist roll and pitch (slots 13, 14) cannot move on this unit."""
        return _WAIST_ROLL_PITCH <= self.absent_slots


def _variants() -> dict[int, G1Variant]:
    table: dict[int, G1Variant] = {}
    for codes, name, absent in (
        ((2, 5, 11, 13, 15), "29-DoF, waist free", frozenset()),
        ((3, 6, 12, 14, 16), "29-DoF, waist locked", _WAIST_ROLL_PITCH),
        ((1, 4, 10), "23-DoF (waist yaw only, 5-DoF arms)", _WAIST_ROLL_PITCH | _WRIST_PITCH_YAW),
        ((9,), "dual arm (no legs, no waist)", frozenset(range(15))),
    ):
        for code in codes:
            table[code] = G1Variant(code, name, absent)
    return table


_VARIANTS = _variants()


def variant_of(mode_machine: int) -> G1Variant | None:
    """The G1 variant of a ``mode_machine`` value, or None when the value is not in Unitree's table."""
    return _VARIANTS.get(mode_machine)


def joint_slot(name: str) -> int:
    """The LowCmd_/LowState_ slot of a G1 joint; ValueError naming the known joints otherwise."""
    try:
        return _SLOT_OF[name]
    except KeyError:
        raise ValueError(f"{name!r} is not a Unitree G1 joint; known: {sorted(_SLOT_OF)}") from None
