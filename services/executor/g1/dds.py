"""CycloneDDS transport to a Unitree G1: the ``unitree_hg`` message types and a domain participant.

The message definitions follow the IDL of unitree_sdk2 (``unitree_hg/msg/dds_/LowCmd_``,
``MotorCmd_``, ``LowState_``, ``MotorState_``, ``IMUState_``; in unitree_sdk2_python under
``unitree_sdk2py/idl/unitree_hg/msg/dds_/``): same type names, member order, member types and
array sizes, ``@final`` with sequential member ids, so that the robot's own readers and writers
match ours. Topic names and the participant's configuration (one network interface, domain 0) are
the SDK's conventions (``ChannelFactoryInitialize(0, "eth0")``). QoS are CycloneDDS defaults, as
the SDK uses.

Speed: CycloneDDS's generic Python (de)serializer takes 0.35–0.45 ms for one of these 1–2 kB
messages, which at 500 Hz in both directions is most of a core. For the plain little-endian CDR
(XCDR1) encoding every CycloneDDS writer uses by default, LowCmd_ and LowState_ override
``serialize``/``deserialize`` with a NumPy path (≈ 0.03 ms): that CDR body is the C struct of
:mod:`services.executor.g1.frames` with the first motor's ``mode`` byte moved into the padding
before it and everything after it 4 bytes earlier. Any other encoding takes the generic path; the
tests check both paths give the same bytes and the same messages.

Needs the ``cyclonedds`` Python package (``pip install safemimic[g1]``); importing this module
without it raises :class:`ImportError` with that hint.
"""

# No ``from __future__ import annotations``: CycloneDDS reads the IDL member types from the class
# annotations at run time and cannot resolve them from strings.
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any
from xml.sax.saxutils import quoteattr

import numpy as np

try:
    import cyclonedds.idl.annotations as annotate
    from cyclonedds.core import Qos
    from cyclonedds.domain import Domain, DomainParticipant
    from cyclonedds.idl import IdlStruct, types
    from cyclonedds.pub import DataWriter
    from cyclonedds.qos import Policy
    from cyclonedds.sub import DataReader
    from cyclonedds.topic import Topic
except ImportError as exc:  # pragma: no cover - exercised only where the package is missing
    raise ImportError(f"the G1 backend needs CycloneDDS's Python package: pip install 'safemimic[g1]' ({exc})") from exc

from services.executor.g1.state import G1State
from services.executor.g1.frames import LOWCMD_DTYPE, LOWSTATE_DTYPE, MOTOR_CMD_DTYPE, MOTOR_STATE_DTYPE
from services.executor.g1.layout import NUM_BODY_MOTORS, NUM_MOTOR_SLOTS

__all__ = [
    "DdsLink",
    "IMUState_",
    "LowCmd_",
    "LowState_",
    "MotorCmd_",
    "MotorState_",
    "frame_to_lowcmd",
    "lowcmd_to_frame",
    "lowstate_to_record",
    "lowstate_to_state",
    "participant_config",
    "record_to_lowstate",
]

#: Encapsulation of plain CDR (XCDR1), little endian (the options bytes may count end padding).
_CDR_LE = b"\x00\x01"
#: Offset of the first motor's ``mode`` byte in the CDR body (in the C struct it sits 2 bytes later).
_LOWCMD_MODE0 = 2
_LOWSTATE_MODE0 = 70


def _struct_to_cdr(struct: bytes, mode0: int) -> bytes:
    """The CDR message (header + body) of a C struct whose first motor starts at ``mode0 + 2``."""
    return _CDR_LE + b"\x00\x00" + struct[:mode0] + struct[mode0 + 2:mode0 + 3] + b"\x00" + struct[mode0 + 6:]


def _cdr_to_record(data: bytes, dtype: np.dtype, mode0: int) -> np.ndarray | None:
    """The C-struct record of a plain little-endian CDR message (with header), None for any other encoding."""
    body = data[4:]
    if data[:2] != _CDR_LE or len(body) < dtype.itemsize - 4:
        return None
    struct = body[:mode0] + b"\x00\x00" + body[mode0:mode0 + 1] + b"\x00\x00\x00" + body[mode0 + 2:dtype.itemsize - 4]
    return np.frombuffer(struct, dtype=dtype)[0].copy()


def _serialize(message: IdlStruct, cls: type, to_record: Callable[[Any], np.ndarray], mode0: int,
               buffer: Any, endianness: Any, use_version_2: Any) -> bytes:
    """``cls.serialize``: plain little-endian CDR straight from the C-struct record (``to_record``),
    cyclonedds's own serializer for any other encoding."""
    if buffer is None and endianness is None and not use_version_2:
        return _struct_to_cdr(to_record(message).tobytes(), mode0)
    return super(cls, message).serialize(buffer=buffer, endianness=endianness, use_version_2=use_version_2)


def _deserialize(cls: type, data: bytes, dtype: np.dtype, mode0: int, from_record: Callable[[np.ndarray], Any],
                 has_header: bool, use_version_2: Any) -> Any:
    """``cls.deserialize``: plain little-endian CDR through the C-struct record (``from_record``),
    cyclonedds's own deserializer for any other encoding."""
    record = _cdr_to_record(data, dtype, mode0) if has_header and not use_version_2 else None
    if record is None:
        return super(cls, cls).deserialize(data, has_header=has_header, use_version_2=use_version_2)
    return from_record(record)


@dataclass
@annotate.final
@annotate.autoid("sequential")
class MotorCmd_(IdlStruct, typename="unitree_hg.msg.dds_.MotorCmd_"):
    """One motor's command: enable ``mode``, target ``q`` (rad), ``dq`` (rad/s), feed-forward
    ``tau`` (N·m), gains ``kp`` (N·m/rad), ``kd`` (N·m·s/rad)."""

    mode: types.uint8
    q: types.float32
    dq: types.float32
    tau: types.float32
    kp: types.float32
    kd: types.float32
    reserve: types.uint32


@dataclass
@annotate.final
@annotate.autoid("sequential")
class LowCmd_(IdlStruct, typename="unitree_hg.msg.dds_.LowCmd_"):
    """The G1 low-level command (``rt/lowcmd``, and ``rt/arm_sdk`` with the blend weight in slot 29)."""

    mode_pr: types.uint8
    mode_machine: types.uint8
    motor_cmd: types.array[MotorCmd_, NUM_MOTOR_SLOTS]
    reserve: types.array[types.uint32, 4]
    crc: types.uint32

    def serialize(self, buffer=None, endianness=None, use_version_2=None) -> bytes:
        return _serialize(self, LowCmd_, lowcmd_to_frame, _LOWCMD_MODE0, buffer, endianness, use_version_2)

    @classmethod
    def deserialize(cls, data, has_header=True, use_version_2=None):
        return _deserialize(LowCmd_, data, LOWCMD_DTYPE, _LOWCMD_MODE0, frame_to_lowcmd, has_header, use_version_2)


@dataclass
@annotate.final
@annotate.autoid("sequential")
class MotorState_(IdlStruct, typename="unitree_hg.msg.dds_.MotorState_"):
    """One motor's measurement: ``q`` (rad), ``dq`` (rad/s), ``ddq``, ``tau_est`` (N·m), temperatures
    (°C), voltage (V), sensor and status words."""

    mode: types.uint8
    q: types.float32
    dq: types.float32
    ddq: types.float32
    tau_est: types.float32
    temperature: types.array[types.int16, 2]
    vol: types.float32
    sensor: types.array[types.uint32, 2]
    motorstate: types.uint32
    reserve: types.array[types.uint32, 4]


@dataclass
@annotate.final
@annotate.autoid("sequential")
class IMUState_(IdlStruct, typename="unitree_hg.msg.dds_.IMUState_"):
    """The pelvis IMU: quaternion (w, x, y, z), gyroscope (rad/s), accelerometer (m/s²), rpy (rad)."""

    quaternion: types.array[types.float32, 4]
    gyroscope: types.array[types.float32, 3]
    accelerometer: types.array[types.float32, 3]
    rpy: types.array[types.float32, 3]
    temperature: types.int16


@dataclass
@annotate.final
@annotate.autoid("sequential")
class LowState_(IdlStruct, typename="unitree_hg.msg.dds_.LowState_"):
    """The G1 low-level state (``rt/lowstate``, 500 Hz); ``mode_machine`` names the model variant."""

    version: types.array[types.uint32, 2]
    mode_pr: types.uint8
    mode_machine: types.uint8
    tick: types.uint32
    imu_state: IMUState_
    motor_state: types.array[MotorState_, NUM_MOTOR_SLOTS]
    wireless_remote: types.array[types.uint8, 40]
    reserve: types.array[types.uint32, 4]
    crc: types.uint32

    def serialize(self, buffer=None, endianness=None, use_version_2=None) -> bytes:
        return _serialize(self, LowState_, lowstate_to_record, _LOWSTATE_MODE0, buffer, endianness, use_version_2)

    @classmethod
    def deserialize(cls, data, has_header=True, use_version_2=None):
        return _deserialize(LowState_, data, LOWSTATE_DTYPE, _LOWSTATE_MODE0, record_to_lowstate, has_header,
                            use_version_2)


_MOTOR_CMD_FIELDS = MOTOR_CMD_DTYPE.names
_MOTOR_STATE_FIELDS = MOTOR_STATE_DTYPE.names
_IMU_FIELDS = ("quaternion", "gyroscope", "accelerometer", "rpy", "temperature")


def frame_to_lowcmd(frame: np.ndarray) -> LowCmd_:
    """The DDS message of a :data:`~services.executor.g1.frames.LOWCMD_DTYPE` frame (float32 values
    as the frame holds them, its CRC as sealed)."""
    return LowCmd_(
        mode_pr=int(frame["mode_pr"]),
        mode_machine=int(frame["mode_machine"]),
        motor_cmd=[MotorCmd_(*m) for m in frame["motor_cmd"].tolist()],
        reserve=frame["reserve"].tolist(),
        crc=int(frame["crc"]),
    )


def lowcmd_to_frame(message: LowCmd_) -> np.ndarray:
    """A LowCmd_ as a :data:`~services.executor.g1.frames.LOWCMD_DTYPE` frame (zero padding)."""
    frame = np.zeros((), dtype=LOWCMD_DTYPE)
    frame["mode_pr"] = message.mode_pr
    frame["mode_machine"] = message.mode_machine
    frame["motor_cmd"] = np.array([tuple(getattr(m, f) for f in _MOTOR_CMD_FIELDS) for m in message.motor_cmd],
                                  dtype=MOTOR_CMD_DTYPE)
    frame["reserve"] = message.reserve
    frame["crc"] = message.crc
    return frame


def lowstate_to_record(message: LowState_) -> np.ndarray:
    """A LowState_ as a :data:`~services.executor.g1.frames.LOWSTATE_DTYPE` record (zero padding)."""
    record = np.zeros((), dtype=LOWSTATE_DTYPE)
    for name in ("version", "mode_pr", "mode_machine", "tick", "reserve", "crc"):
        record[name] = getattr(message, name)
    record["wireless_remote"] = np.frombuffer(bytes(message.wireless_remote), dtype=np.uint8)  # list or bytes
    record["imu_state"] = tuple(getattr(message.imu_state, f) for f in _IMU_FIELDS)
    record["motor_state"] = np.array([tuple(getattr(m, f) for f in _MOTOR_STATE_FIELDS) for m in message.motor_state],
                                     dtype=MOTOR_STATE_DTYPE)
    return record


def _rows(records: np.ndarray) -> list[tuple[Any, ...]]:
    """Structured records as tuples of Python values in field order (sub-arrays as lists)."""
    return list(zip(*(records[name].tolist() for name in records.dtype.names), strict=True))


def record_to_lowstate(record: np.ndarray) -> LowState_:
    """The LowState_ message of a :data:`~services.executor.g1.frames.LOWSTATE_DTYPE` record."""
    return LowState_(
        version=record["version"].tolist(), mode_pr=int(record["mode_pr"]), mode_machine=int(record["mode_machine"]),
        tick=int(record["tick"]), imu_state=IMUState_(*_rows(record["imu_state"].reshape(1))[0]),
        motor_state=[MotorState_(*m) for m in _rows(record["motor_state"])],
        wireless_remote=record["wireless_remote"].tobytes(),  # CycloneDDS gives uint8 arrays as bytes
        reserve=record["reserve"].tolist(), crc=int(record["crc"]),
    )


def lowstate_to_state(message: LowState_, received: float) -> G1State:
    """The fields of a LowState_ the executor uses, stamped with the local receive time (s)."""
    motors = message.motor_state[:NUM_BODY_MOTORS]
    return G1State(
        q=np.array([m.q for m in motors]),
        dq=np.array([m.dq for m in motors]),
        tau_est=np.array([m.tau_est for m in motors]),
        mode_machine=int(message.mode_machine),
        received=received,
    )


def participant_config(interface: str) -> str:
    """CycloneDDS XML restricting the domain to one network interface (the SDK's
    ``ChannelFactoryInitialize(domain, interface)``)."""
    return ("<CycloneDDS><Domain Id=\"any\"><General><Interfaces>"
            f"<NetworkInterface name={quoteattr(interface)} priority=\"default\" multicast=\"default\"/>"
            "</Interfaces></General></Domain></CycloneDDS>")


class DdsLink:
    """A CycloneDDS domain participant on ``domain_id``, bound to ``interface`` when given (else
    CycloneDDS's own choice, or ``$CYCLONEDDS_URI``). Readers keep the newest ``depth`` samples."""

    def __init__(self, domain_id: int, interface: str | None) -> None:
        self.domain_id = domain_id
        self.interface = interface
        self._domain = Domain(domain_id, participant_config(interface)) if interface else None
        self.participant = DomainParticipant(domain_id)
        self._topics: dict[str, Topic] = {}

    def _topic(self, name: str, data_type: type[IdlStruct]) -> Topic:
        if name not in self._topics:
            self._topics[name] = Topic(self.participant, name, data_type)
        return self._topics[name]

    def writer(self, topic: str, data_type: type[IdlStruct]) -> DataWriter:
        return DataWriter(self.participant, self._topic(topic, data_type))

    def reader(self, topic: str, data_type: type[IdlStruct], depth: int = 1) -> DataReader:
        qos = None if depth == 1 else Qos(Policy.History.KeepLast(depth))
        return DataReader(self.participant, self._topic(topic, data_type), qos=qos)

    def describe(self) -> dict[str, Any]:
        return {"domain_id": self.domain_id, "interface": self.interface or "cyclonedds default"}
