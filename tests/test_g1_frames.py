"""G1 hardware facts and the LowCmd_ frame: layout against unitree_sdk2_python's struct formats,
the CRC against its bit-by-bit definition and against a value computed by the SDK itself, the joint
table against the real G1 model, the mode_machine table."""

from __future__ import annotations

import struct

import mujoco
import numpy as np
import pytest

from services.executor.g1.frames import (
    LOWCMD_DTYPE,
    LOWSTATE_DTYPE,
    crc32_words,
    lowcmd_crc,
    new_lowcmd,
    seal,
)
from services.executor.g1.layout import (
    ARM_SDK_SLOTS,
    G1_JOINTS,
    LOWCMD_HOLD_GAINS,
    NUM_BODY_MOTORS,
    WEIGHT_SLOT,
    joint_slot,
    variant_of,
)
from shared.names import IMITATION_JOINT_NAMES
from shared.robot_spec import default_robot_spec_path, load_robot_spec
from tests.support.team import G1_MJCF

#: unitree_sdk2py/utils/crc.py packs these (4-byte aligned, little endian).
SDK_LOWCMD_FORMAT = "<2B2x" + "B3x5fI" * 35 + "5I"
SDK_LOWSTATE_FORMAT = "<2I2B2xI" + "13fh2x" + "B3x4f2hf7I" * 35 + "40B5I"


def crc_reference(words: list[int]) -> int:
    """The CRC as unitree_sdk2py's ``_crc_py`` defines it, bit by bit (slow, obviously right)."""
    crc = 0xFFFFFFFF
    for word in words:
        for bit in range(31, -1, -1):
            msb = crc & 0x80000000
            crc = (crc << 1) & 0xFFFFFFFF
            if msb:
                crc ^= 0x04C11DB7
            if (word >> bit) & 1:
                crc ^= 0x04C11DB7
    return crc


def golden_frame() -> np.ndarray:
    """The frame whose CRC was computed with unitree_sdk2_python 1.0.1 (PyPI ``unitree_sdk2``),
    ``CRC()._crc_py`` over its own packing of the same LowCmd_: 0xE99D25E6."""
    frame = new_lowcmd()
    frame["mode_machine"] = 5
    m = frame["motor_cmd"]
    for i in range(35):
        m[i]["mode"] = 1 if i < 29 else 0
        m[i]["q"], m[i]["dq"], m[i]["kp"], m[i]["kd"] = 0.01 * i, -0.02 * i, 60.0, 1.5
    m[WEIGHT_SLOT]["q"] = 0.75
    return frame


def random_frame(rng: np.random.Generator) -> np.ndarray:
    frame = new_lowcmd()
    frame["mode_pr"], frame["mode_machine"] = rng.integers(0, 2), rng.integers(0, 20)
    m = frame["motor_cmd"]
    m["mode"] = rng.integers(0, 2, 35)
    for f in ("q", "dq", "tau", "kp", "kd"):
        m[f] = rng.normal(size=35)
    m["reserve"] = rng.integers(0, 2**32, 35, dtype=np.uint64)
    frame["reserve"] = rng.integers(0, 2**32, 4, dtype=np.uint64)
    return frame


def sdk_pack(frame: np.ndarray) -> bytes:
    """Pack a frame the way unitree_sdk2py's CRC packs a LowCmd_ (field by field, struct module)."""
    values: list = [int(frame["mode_pr"]), int(frame["mode_machine"])]
    for m in frame["motor_cmd"]:
        values += [int(m["mode"]), *(float(m[f]) for f in ("q", "dq", "tau", "kp", "kd")), int(m["reserve"])]
    values += [int(r) for r in frame["reserve"]] + [int(frame["crc"])]
    return struct.pack(SDK_LOWCMD_FORMAT, *values)


def test_struct_layouts_match_the_sdk_pack_formats() -> None:
    assert LOWCMD_DTYPE.itemsize == struct.calcsize(SDK_LOWCMD_FORMAT) == 1004
    assert LOWSTATE_DTYPE.itemsize == struct.calcsize(SDK_LOWSTATE_FORMAT) == 2092
    rng = np.random.default_rng(1)
    for _ in range(5):
        frame = seal(random_frame(rng))
        assert frame.tobytes() == sdk_pack(frame)


def test_crc_equals_the_bitwise_definition_and_the_sdk_value() -> None:
    rng = np.random.default_rng(2)
    for n in (1, 2, 3, 17, 250):
        words = rng.integers(0, 2**32, n, dtype=np.uint64).astype(np.uint32)
        assert crc32_words(words) == crc_reference(words.tolist())
    frame = golden_frame()
    assert lowcmd_crc(frame) == 0xE99D25E6
    words = list(struct.unpack(f"<{1004 // 4}I", sdk_pack(frame)))[:-1]
    assert crc_reference(words) == 0xE99D25E6


def test_crc_covers_every_field_but_itself() -> None:
    frame = seal(golden_frame())
    assert lowcmd_crc(frame) == int(frame["crc"])
    frame["crc"] = 12345  # the crc field is not part of its own input
    assert lowcmd_crc(frame) == 0xE99D25E6
    for field, change in (("mode_pr", 1), ("mode_machine", 6)):
        changed = frame.copy()
        changed[field] = change
        assert lowcmd_crc(changed) != 0xE99D25E6
    for slot in (0, 13, 28, WEIGHT_SLOT, 34):
        changed = frame.copy()
        changed["motor_cmd"]["kd"][slot] += 0.5
        assert lowcmd_crc(changed) != 0xE99D25E6, slot
    changed = frame.copy()
    changed["reserve"][3] = 1
    assert lowcmd_crc(changed) != 0xE99D25E6


def test_joint_table_is_the_real_g1_model() -> None:
    if not G1_MJCF.is_file():
        pytest.skip(f"real G1 model not found at {G1_MJCF} (set SAFEMIMIC_TEAM_SHARED to the team folder)")
    model = mujoco.MjModel.from_xml_path(str(G1_MJCF))
    names = [model.joint(j).name for j in range(model.njnt) if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE]
    # Unitree's motor order is the model's hinge order: legs, waist yaw/roll/pitch, left arm, right arm
    assert names == [j.name for j in G1_JOINTS]
    for j in G1_JOINTS:
        mj = model.joint(j.name)
        np.testing.assert_allclose(mj.range, [j.lower, j.upper], atol=1e-4, err_msg=j.name)
        np.testing.assert_allclose(model.jnt_actfrcrange[mj.id], [-j.torque_limit, j.torque_limit], err_msg=j.name)


def test_slots_of_the_imitation_joints_and_channels() -> None:
    assert [j.slot for j in G1_JOINTS] == list(range(NUM_BODY_MOTORS))
    assert [joint_slot(n) for n in IMITATION_JOINT_NAMES] == [13, 14, 15, 16, 18, 22, 23, 25]
    assert [joint_slot(n) for n in load_robot_spec(default_robot_spec_path()).imitation_joints] == [13, 14, 15, 16, 18, 22, 23, 25]
    assert ARM_SDK_SLOTS == tuple(range(12, 29))  # waist + both arms; legs 0–11 stay with the robot
    assert len(LOWCMD_HOLD_GAINS) == NUM_BODY_MOTORS
    with pytest.raises(ValueError, match="not a Unitree G1 joint"):
        joint_slot("head_joint")


@pytest.mark.parametrize(("mode_machine", "locked", "absent"), [
    (5, False, set()), (11, False, set()), (13, False, set()), (15, False, set()),
    (6, True, {13, 14}), (12, True, {13, 14}), (14, True, {13, 14}), (16, True, {13, 14}), (3, True, {13, 14}),
    (4, True, {13, 14, 20, 21, 27, 28}), (10, True, {13, 14, 20, 21, 27, 28}),
])
def test_variants_from_mode_machine(mode_machine: int, locked: bool, absent: set[int]) -> None:
    variant = variant_of(mode_machine)
    assert variant is not None
    assert variant.waist_locked is locked
    assert variant.absent_slots == absent
    assert variant_of(200) is None
