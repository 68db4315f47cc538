"""The unitree_hg messages over CycloneDDS: our fast CDR path gives the same bytes and messages as
CycloneDDS's own serializer, and the bytes unitree_sdk2_python produces for the same command."""

from __future__ import annotations

import hashlib

import numpy as np
import pytest

pytest.importorskip("cyclonedds", reason="CycloneDDS's Python package is not installed: pip install 'safemimic[g1]'")

from cyclonedds.idl import IdlStruct  # noqa: E402
from cyclonedds.idl._support import Endianness  # noqa: E402

from services.executor.g1.dds import (  # noqa: E402
    IMUState_,
    LowCmd_,
    LowState_,
    MotorState_,
    frame_to_lowcmd,
    lowcmd_to_frame,
    lowstate_to_state,
    participant_config,
)
from services.executor.g1.frames import lowcmd_crc, seal  # noqa: E402
from tests.test_g1_frames import golden_frame, random_frame  # noqa: E402

#: SHA-256 of unitree_sdk2_python 1.0.1's ``LowCmd_.serialize()`` of :func:`golden_frame` (with its CRC).
SDK_GOLDEN_SHA256 = "3aaca07b2066438381d2c68fc7c999267c149b475b0e4542d252cf191cbb36ff"


def random_lowstate(rng: np.random.Generator, absent: set[int]) -> LowState_:
    motors = [MotorState_(
        mode=int(i not in absent), q=float(np.float32(rng.normal())), dq=float(np.float32(rng.normal())),
        ddq=float(np.float32(rng.normal())), tau_est=float(np.float32(rng.normal())),
        temperature=rng.integers(-40, 90, 2).tolist(), vol=float(np.float32(48.5)),
        sensor=rng.integers(0, 2**32, 2, dtype=np.uint64).tolist(), motorstate=int(rng.integers(0, 2**32)),
        reserve=[0, 1, 2, 3]) for i in range(35)]
    imu = IMUState_(quaternion=[1.0, 0.0, 0.0, 0.0], gyroscope=[0.5, -0.25, 0.125], accelerometer=[0.0, 0.0, 9.8125],
                    rpy=[0.0, 0.5, -0.5], temperature=-7)
    return LowState_(version=[1, 2], mode_pr=1, mode_machine=6, tick=int(rng.integers(0, 2**32)), imu_state=imu,
                     motor_state=motors, wireless_remote=bytes(rng.integers(0, 256, 40, dtype=np.uint8)),
                     reserve=[4, 3, 2, 1], crc=int(rng.integers(0, 2**32)))


def test_lowcmd_fast_path_matches_cyclonedds_and_the_sdk() -> None:
    message = frame_to_lowcmd(seal(golden_frame()))
    fast, generic = message.serialize(), IdlStruct.serialize(message)
    assert fast == generic
    assert hashlib.sha256(fast).hexdigest() == SDK_GOLDEN_SHA256
    rng = np.random.default_rng(3)
    for _ in range(10):
        message = frame_to_lowcmd(seal(random_frame(rng)))
        data = IdlStruct.serialize(message)
        assert message.serialize() == data
        assert LowCmd_.deserialize(data) == LowCmd_.__idl__.deserialize(data) == message
        frame = lowcmd_to_frame(LowCmd_.deserialize(data))
        assert int(frame["crc"]) == lowcmd_crc(frame)


def test_lowstate_fast_path_matches_cyclonedds() -> None:
    rng = np.random.default_rng(4)
    for absent in (set(), {13, 14}, set(range(29, 35))):
        message = random_lowstate(rng, absent)
        data = IdlStruct.serialize(message)
        assert message.serialize() == data
        decoded = LowState_.deserialize(data)
        assert decoded == LowState_.__idl__.deserialize(data) == message
        state = lowstate_to_state(decoded, received=1.5)
        assert state.q.shape == (29,) and state.mode_machine == 6 and state.received == 1.5
        assert state.q[3] == message.motor_state[3].q and state.tau_est[28] == message.motor_state[28].tau_est


def test_other_encodings_take_the_generic_path() -> None:
    rng = np.random.default_rng(5)
    message = random_lowstate(rng, set())
    big = IdlStruct.serialize(message, endianness=Endianness.Big)
    assert big[:2] == b"\x00\x00"  # CDR big endian
    assert LowState_.deserialize(big) == message
    command = frame_to_lowcmd(seal(random_frame(rng)))
    assert LowCmd_.deserialize(IdlStruct.serialize(command, endianness=Endianness.Big)) == command


def test_participant_config_names_one_interface() -> None:
    assert '<NetworkInterface name="eth0"' in participant_config("eth0")
    assert "<Peers" not in participant_config('eth0"/><Peers')  # quoted, not injected
