"""The ``unitree_hg`` LowCmd_ and LowState_ messages as NumPy records with the robot's C struct
layout, and the LowCmd_ CRC.

The robot checks ``LowCmd_.crc`` against a CRC over the C struct of the message, not over the DDS
(CDR) bytes. The structs are little-endian with natural alignment: unitree_sdk2_python
(``unitree_sdk2py/utils/crc.py``) packs them as ``'<2B2x' + 'B3x5fI' * 35 + '5I'`` (LowCmd_) and
``'<2I2B2xI' + '13fh2x' + 'B3x4f2hf7I' * 35 + '40B5I'`` (LowState_). LowCmd_::

    offset    0  uint8  mode_pr          (0: ankle/waist motors in pitch/roll, 1: A/B)
              1  uint8  mode_machine     (echo of LowState_.mode_machine)
              4  MotorCmd_[35], 28 bytes each:
                    +0 uint8 mode (1 = enable) · +4 float32 q (rad) · +8 dq (rad/s)
                    +12 tau (N·m, feed-forward) · +16 kp · +20 kd · +24 uint32 reserve
            984  uint32[4] reserve
           1000  uint32 crc                          (1004 bytes in all)

The CRC is the one of that file and of the STM32 CRC unit: CRC-32 with polynomial 0x04C11DB7, initial
value 0xFFFFFFFF, no bit reflection and no final XOR (catalogued as CRC-32/MPEG-2), fed the
struct's 32-bit little-endian words most significant bit first, every word but the last (the crc
field itself). :func:`crc32_words` computes it with :func:`binascii.crc32` (the reflected CRC-32)
on bit-reversed bytes, which gives the same value about 100 times faster than a bit loop.
"""

from __future__ import annotations

import binascii

import numpy as np

from services.executor.g1.layout import NUM_MOTOR_SLOTS

__all__ = [
    "IMU_STATE_DTYPE",
    "LOWCMD_DTYPE",
    "LOWSTATE_DTYPE",
    "MOTOR_CMD_DTYPE",
    "MOTOR_STATE_DTYPE",
    "crc32_words",
    "lowcmd_crc",
    "new_lowcmd",
    "seal",
]


def _struct(fields: list[tuple[str, str | np.dtype | tuple, int]], itemsize: int) -> np.dtype:
    """A structured dtype from (name, format, offset) and the total size (bytes)."""
    names, formats, offsets = zip(*fields, strict=True)
    return np.dtype({"names": list(names), "formats": list(formats), "offsets": list(offsets), "itemsize": itemsize})


#: One ``MotorCmd_`` in the C struct (28 bytes; padding after ``mode``).
MOTOR_CMD_DTYPE = _struct([("mode", "u1", 0), ("q", "<f4", 4), ("dq", "<f4", 8), ("tau", "<f4", 12),
                           ("kp", "<f4", 16), ("kd", "<f4", 20), ("reserve", "<u4", 24)], 28)
#: ``unitree_hg`` ``LowCmd_`` as the C struct the CRC covers (1004 bytes).
LOWCMD_DTYPE = _struct([("mode_pr", "u1", 0), ("mode_machine", "u1", 1),
                        ("motor_cmd", (MOTOR_CMD_DTYPE, (NUM_MOTOR_SLOTS,)), 4),
                        ("reserve", ("<u4", (4,)), 984), ("crc", "<u4", 1000)], 1004)
#: One ``MotorState_`` in the C struct (56 bytes).
MOTOR_STATE_DTYPE = _struct([("mode", "u1", 0), ("q", "<f4", 4), ("dq", "<f4", 8), ("ddq", "<f4", 12),
                             ("tau_est", "<f4", 16), ("temperature", ("<i2", (2,)), 20), ("vol", "<f4", 24),
                             ("sensor", ("<u4", (2,)), 28), ("motorstate", "<u4", 36),
                             ("reserve", ("<u4", (4,)), 40)], 56)
#: ``IMUState_`` in the C struct (56 bytes, 2 of them padding).
IMU_STATE_DTYPE = _struct([("quaternion", ("<f4", (4,)), 0), ("gyroscope", ("<f4", (3,)), 16),
                           ("accelerometer", ("<f4", (3,)), 28), ("rpy", ("<f4", (3,)), 40),
                           ("temperature", "<i2", 52)], 56)
#: ``unitree_hg`` ``LowState_`` as a C struct (2092 bytes).
LOWSTATE_DTYPE = _struct([("version", ("<u4", (2,)), 0), ("mode_pr", "u1", 8), ("mode_machine", "u1", 9),
                          ("tick", "<u4", 12), ("imu_state", IMU_STATE_DTYPE, 16),
                          ("motor_state", (MOTOR_STATE_DTYPE, (NUM_MOTOR_SLOTS,)), 72),
                          ("wireless_remote", ("u1", (40,)), 2032), ("reserve", ("<u4", (4,)), 2072),
                          ("crc", "<u4", 2088)], 2092)

#: :func:`binascii.crc32` complements its result; undone here.
_CRC32_XOROUT = 0xFFFFFFFF
#: Byte → the byte with its bit order reversed.
_REVERSED_BITS = bytes(int(f"{i:08b}"[::-1], 2) for i in range(256))


def new_lowcmd() -> np.ndarray:
    """A zeroed LowCmd_ frame (a 0-d record of :data:`LOWCMD_DTYPE`; padding bytes are zero)."""
    return np.zeros((), dtype=LOWCMD_DTYPE)


def crc32_words(words: np.ndarray) -> int:
    """CRC-32/MPEG-2 of ``words`` (uint32), each fed most significant bit first.

    Equivalent bit loop, per word w, per bit b from 31 down to 0:
    ``crc = (crc << 1) ^ (0x04C11DB7 if (crc >> 31) ^ ((w >> b) & 1) else 0)``, starting at
    0xFFFFFFFF. Here: the words as big-endian bytes, each byte bit-reversed, through the reflected
    CRC-32 (which also starts at 0xFFFFFFFF but complements its result), then the result's 32 bits
    reversed and the complement undone.
    """
    data = np.ascontiguousarray(words, dtype=">u4").tobytes().translate(_REVERSED_BITS)
    reflected = binascii.crc32(data)
    return int(f"{reflected:032b}"[::-1], 2) ^ _CRC32_XOROUT


def lowcmd_crc(frame: np.ndarray) -> int:
    """The CRC the robot expects in ``frame['crc']``: over every 32-bit word of the struct but the last."""
    if frame.dtype != LOWCMD_DTYPE:
        raise TypeError(f"expected a LOWCMD_DTYPE record, got {frame.dtype}")
    return crc32_words(np.frombuffer(frame.tobytes(), dtype="<u4")[:-1])


def seal(frame: np.ndarray) -> np.ndarray:
    """Write the CRC into ``frame`` (in place) and return it."""
    frame["crc"] = lowcmd_crc(frame)
    return frame
