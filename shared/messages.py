"""Messages exchanged on the bus (architecture §5): pydantic v2 models, validated on both ends.

Every message carries ``schema`` (name, version), ``stamp`` (float seconds), ``seq``
(per-publisher counter) and ``source`` (publisher id). Arrays are numpy arrays with a
declared shape and dtype; NaN and Inf are rejected wherever a float appears, and so is a
magnitude no robot or person has (:data:`MAX_COORD_M`, :data:`MAX_SPEED_MPS`, :data:`MAX_ANGLE_RAD`,
:data:`MAX_RATE_RADPS`): finite garbage such as 1e300 m would overflow the safety layer's distance
arithmetic into NaN rows, which no QP can honour. Unknown fields are rejected (``extra="forbid"``).
"""

from __future__ import annotations

import math
from enum import Enum
from typing import Annotated, Any, ClassVar, Literal

import numpy as np
from pydantic import (
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    PlainSerializer,
    StringConstraints,
    field_validator,
    model_validator,
)

from shared.names import CAPSULE_NAMES, IMITATION_JOINT_NAMES, KEYPOINT_NAMES, POSE_ANGLE_NAMES

N_KEYPOINTS = len(KEYPOINT_NAMES)
N_ANGLES = len(POSE_ANGLE_NAMES)
N_CAPSULES = len(CAPSULE_NAMES)
N_JOINTS = len(IMITATION_JOINT_NAMES)

#: Bounds of a valid message's values, far beyond anything real and far below an overflow: a point
#: (m) from the robot, a point's speed (m/s), an angle (rad; a joint or pose angle never needs more
#: than two turns) and an angle's rate (rad/s; a person's fastest joint turns at ≈ 40, a G1 motor at 37).
MAX_COORD_M = 100.0
MAX_SPEED_MPS = 100.0
MAX_ANGLE_RAD = 4.0 * math.pi
MAX_RATE_RADPS = 1000.0


def _array_validator(shape: tuple[int, ...], dtype: type, limit: float | None = None) -> BeforeValidator:
    """Coerce to a C-contiguous ``dtype`` array of exactly ``shape``; floats must be finite (and, with
    ``limit``, of magnitude at most ``limit``); values of another kind that do not convert within
    their kind (numpy's ``same_kind``: floats into a bool field, where a NaN would become True) are
    refused, not cast."""
    expected = np.dtype(dtype)
    is_float = expected.kind == "f"

    def coerce(value: Any) -> np.ndarray:
        if type(value) is np.ndarray and value.dtype == expected and value.flags.c_contiguous:
            array = value  # the decoder's fast path: no copy
        elif isinstance(value, (str, bytes)):
            raise ValueError(f"expected an array of shape {shape}, got {type(value).__name__}")
        else:
            try:
                given = np.asarray(value)
                if not np.can_cast(given.dtype, expected, casting="same_kind"):
                    raise ValueError(f"{given.dtype} values are not {expected.name}")
                array = np.ascontiguousarray(given, dtype=expected)
            except (TypeError, ValueError) as exc:
                raise ValueError(f"expected a {expected.name} array of shape {shape}: {exc}") from None
        if array.shape != shape:
            raise ValueError(f"expected shape {shape}, got {array.shape}")
        # A NaN or ±Inf makes the sum non-finite, so a finite sum clears the array; a non-finite sum
        # (NaN/Inf, or finite values overflowing) is settled element by element. Summing Python
        # floats beats a numpy reduction on arrays as small as the messages' (≤ 45 elements).
        values = array.ravel().tolist() if is_float else ()  # the checks below are the floats'
        if is_float and not math.isfinite(sum(values)) and not np.isfinite(array).all():
            raise ValueError("array contains NaN or Inf")
        if limit is not None and values and max(max(values), -min(values)) > limit:
            raise ValueError(f"array holds a value of magnitude above {limit:g}")
        return array

    return BeforeValidator(coerce)


_as_list = PlainSerializer(lambda a: a.tolist(), when_used="json")


def Array(*shape: int, dtype: type = np.float64, limit: float | None = None) -> Any:
    """Annotated numpy array type of a declared shape, its values of magnitude at most ``limit``
    (None: any finite value) (use as a field type)."""
    return Annotated[np.ndarray, _array_validator(tuple(shape), dtype, limit), _as_list]


class Schema(BaseModel):
    """Name and version of a message type; the codec dispatches on it."""

    model_config = ConfigDict(extra="forbid", frozen=True, strict=True)
    name: str = Field(max_length=64)
    version: int = Field(ge=1)


class Message(BaseModel):
    """Base of every bus message: schema, stamp, seq, source."""

    model_config = ConfigDict(
        extra="forbid",
        strict=True,  # no lax coercion from the wire: a stamp of "1.5" or True, a seq of 1.0 are refused
        allow_inf_nan=False,
        arbitrary_types_allowed=True,
        populate_by_name=True,
        validate_assignment=False,
    )
    SCHEMA_NAME: ClassVar[str] = "message"
    SCHEMA_VERSION: ClassVar[int] = 1

    schema_: Schema = Field(default=None, alias="schema", validate_default=True)  # type: ignore[assignment]
    stamp: float = Field(description="seconds: monotonic for control, wall clock for logs")
    seq: int = Field(default=0, ge=0, lt=2**63)
    source: str = Field(default="", max_length=64)

    @field_validator("schema_", mode="before")
    @classmethod
    def _default_schema(cls, value: Any) -> Any:
        return {"name": cls.SCHEMA_NAME, "version": cls.SCHEMA_VERSION} if value is None else value

    @model_validator(mode="after")
    def _schema_matches_class(self) -> Message:
        if self.schema_.name != self.SCHEMA_NAME or self.schema_.version != self.SCHEMA_VERSION:
            raise ValueError(
                f"schema {self.schema_.name}/v{self.schema_.version} does not match "
                f"{self.SCHEMA_NAME}/v{self.SCHEMA_VERSION}"
            )
        return self


class HumanState(Message):
    """The filtered human as perception sees it, in the robot frame (z up, metres).

    ``keypoints[k]`` is canonical keypoint k (shared.names.KEYPOINT_NAMES), meaningful only where
    ``keypoint_valid[k]``. ``theta`` is the reduced pose (paper eq. 1), valid where ``theta_valid``.
    ``capsules[i] = (a_i, b_i)`` endpoints of human capsule i (CAPSULE_NAMES) with radius
    ``capsule_radii[i]``, valid where ``capsule_valid``. ``capsule_velocities`` (m/s, same shape as
    ``capsules``) are the measured endpoint velocities when perception provides them.

    ``theta_rate`` (rad/s, POSE_ANGLE_NAMES order) is dθ/dt of the published ``theta``: the finite
    difference of consecutive valid θ (differences wrapped into [−π, π)), low-passed
    (services.perception.angles.AngleRates). It is 0 wherever it is not computable: θ invalid in
    this or the previous frame, the first frame after a filter reset, or a keypoint the angle uses
    re-initialised this frame (no differencing across a gap); its low-pass restarts from 0 there.
    Finite always; a sender without rates sends zeros (the default). Schema version 2 added it.
    """

    SCHEMA_NAME: ClassVar[str] = "HumanState"
    SCHEMA_VERSION: ClassVar[int] = 2
    keypoints: Array(N_KEYPOINTS, 3, limit=MAX_COORD_M)
    keypoint_valid: Array(N_KEYPOINTS, dtype=np.bool_)
    theta: Array(N_ANGLES, limit=MAX_ANGLE_RAD)
    theta_valid: Array(N_ANGLES, dtype=np.bool_)
    theta_rate: Array(N_ANGLES, limit=MAX_RATE_RADPS) = Field(
        default_factory=lambda: np.zeros(N_ANGLES), description="dθ/dt (rad/s); 0 where not computable"
    )
    capsules: Array(N_CAPSULES, 2, 3, limit=MAX_COORD_M)
    capsule_radii: Array(N_CAPSULES)
    capsule_valid: Array(N_CAPSULES, dtype=np.bool_)
    capsule_velocities: Array(N_CAPSULES, 2, 3, limit=MAX_SPEED_MPS) | None = None
    frame_id: Literal["robot"] = Field(
        default="robot", description="always the robot frame: anything else is rejected when decoded"
    )
    capture_stamp: float | None = Field(default=None, description="when the camera frame was taken")

    @field_validator("capsule_radii")
    @classmethod
    def _radii_non_negative(cls, value: np.ndarray) -> np.ndarray:
        radii = value.tolist()  # finite already (the array validator ran first)
        if min(radii) < 0.0 or max(radii) > 1.0:
            raise ValueError("capsule radii must lie in [0, 1] m")
        return value


class JointState(Message):
    """Measured state of the 8 imitation joints (IMITATION_JOINT_NAMES order): rad, rad/s.

    ``q_command`` is the position target the executor is holding (the last command, or home before
    the first one): a restarted safety service continues from it without a jump.
    ``command_stale`` is True while the executor's newest command is older than its timeout (it holds).
    """

    SCHEMA_NAME: ClassVar[str] = "JointState"
    q: Array(N_JOINTS, limit=MAX_ANGLE_RAD)
    dq: Array(N_JOINTS, limit=MAX_RATE_RADPS)
    q_command: Array(N_JOINTS, limit=MAX_ANGLE_RAD) | None = None
    command_stale: bool = False


class SafetyMode(str, Enum):
    """What the safety layer did this step."""

    NOMINAL = "nominal"  # no CBF row binds: u* = u_ref
    ACTIVE = "active"  # some CBF rows bind: u* bent away from u_ref
    RELAXED = "relaxed"  # rows infeasible: slack-relaxed QP solved
    HOLD = "hold"  # relaxed QP failed too (or no valid input): hold position, u* = 0


class JointCommand(Message):
    """Safe joint target q_cbf (rad), velocity u* (rad/s) and acceleration (rad/s²) for the 8
    imitation joints (paper eq. 9).

    ``ddq`` = (u* − u*_prev)/Δt, bounded by ``safety.accel_max`` except where the bound gave way:
    an executor feeds it forward through the robot's inertia (zero: velocity feed-forward only, the
    default for a sender without it). Schema version 2 added it.

    ``settled``: q was first brought to the robot's measured joints this tick (a stop
    settling, or holding a joint its servo would push on, :mod:`services.safety.protective_stop`: the
    command moves to where the robot is), so q may
    differ from the previous command by u_max·Δt more than the one step's rate limit. Schema
    version 3 added it.

    ``protective_stop``: the command brakes to rest (the safety filter's protective stop,
    :mod:`services.safety.protective_stop`); the executor damps its servos harder while it lasts
    (``executor.stop_damping``, ``executor.g1.stop_damping``). Schema version 4 added it.
    """

    SCHEMA_NAME: ClassVar[str] = "JointCommand"
    SCHEMA_VERSION: ClassVar[int] = 4
    q: Array(N_JOINTS, limit=MAX_ANGLE_RAD)
    dq: Array(N_JOINTS, limit=MAX_RATE_RADPS)
    ddq: Array(N_JOINTS) = Field(
        default_factory=lambda: np.zeros(N_JOINTS), description="commanded acceleration (rad/s²)"
    )
    mode: SafetyMode = Field(default=SafetyMode.NOMINAL, strict=False)  # the wire carries the value
    human_stamp: float | None = Field(default=None, description="stamp of the HumanState used")
    human_seq: int | None = Field(default=None, ge=0)
    settled: bool = Field(default=False, description="q first brought to the measured joints this tick")
    protective_stop: bool = Field(default=False, description="the command brakes to rest (a protective stop)")


class SafetyStatus(Message):
    """Periodic report of the safety service (paper eqs. 4–8 quantities, counters).

    ``q_nom`` and ``binding_pairs`` describe the control tick that published it: the target the
    filter tracked and the pairs whose CBF rows bound u* (what the live viewer draws). Schema
    version 2 added both; version 3 added ``backing_out`` and ``human_lateness_ms``.
    """

    SCHEMA_NAME: ClassVar[str] = "SafetyStatus"
    SCHEMA_VERSION: ClassVar[int] = 3
    mode: SafetyMode = Field(strict=False)  # the wire carries the value
    min_h_self: float | None = Field(description="min h over self pairs (m); None if no pair")
    min_h_human: float | None = Field(description="min h over robot–human pairs (m); None if no human")
    active_constraints: int = Field(ge=0)
    total_constraints: int = Field(ge=0)
    qp_solve_time_ms: float = Field(ge=0)
    step_time_ms: float = Field(ge=0)
    deadline_misses: int = Field(default=0, ge=0)
    human_stale: bool = False
    joint_state_stale: bool = Field(default=False, description="no JointState within safety.joint_state_timeout_s")
    human_source_lost: bool = Field(default=False, description="perception's liveliness token is gone")
    executor_holding: bool = Field(default=False, description="the executor reports its commands stale")
    resyncing: bool = Field(default=False, description="q_cbf is moving (rate-limited) to a displaced robot")
    human_lost: bool = Field(default=False, description="capsules of a person that vanished are held")
    relaxed_pairs: list[Annotated[str, StringConstraints(max_length=64)]] = Field(
        default_factory=list, max_length=256,
        description="rows that gave way since the previous status (mode relaxed): robot–person pairs, whose rows held "
        "only A u ≥ min(b, 0), or a hard row (self pair, joint barrier) that was already violated",
    )
    binding_pairs: list[Annotated[str, StringConstraints(max_length=64)]] = Field(
        default_factory=list, max_length=256,
        description="pairs with a CBF row at its bound at this tick's u* (A_i u* ≤ b_i within the QP's active "
        "tolerance; mode active or relaxed): the binding pairs of the paper's figures, sorted",
    )
    q_nom: Array(N_JOINTS) | None = Field(
        default=None, description="the nominal target (rad, IMITATION_JOINT_NAMES order) the filter tracked at this "
        "tick: the retargeted person, q_cbf with no person to imitate, the resync target; None if not finite",
    )
    person_intrusion: bool = Field(
        default=False, description="since the previous status, a person capsule was inside a robot capsule's margin (h < 0): the "
        "robot stopped or retreated (safety.on_intrusion)"
    )
    backing_out: bool = Field(
        default=False, description="since the previous status, the intrusion stop backed a robot arm out of a person "
        "standing still inside its margin (safety.intrusion_backout_mps)"
    )
    human_lateness_ms: float = Field(
        default=0.0, ge=0, description="the newest HumanState was published this much later after its camera frame than "
        "usual (ms; 0 on time): the person capsules are swept ahead by this much more"
    )
    watchdog_trips: dict[str, int] = Field(
        default_factory=dict, description="times each watchdog tripped: human_state, human_source, human_lost, "
        "joint_state, executor_command, resync"
    )
    dropped: dict[str, int] = Field(default_factory=dict, description="invalid messages per topic")
    config_version: int = Field(default=0, ge=0)
    backend: str = Field(default="", max_length=32)


def _check_json_finite(value: Any, path: str = "config") -> None:
    """Reject NaN/Inf anywhere in a JSON-like tree (msgpack lets floats through unchecked)."""
    if isinstance(value, float) and not math.isfinite(value):
        raise ValueError(f"{path} is not finite")
    if isinstance(value, (np.ndarray, np.generic)):  # the codec decodes ND_EXT blobs anywhere in the tree
        if value.dtype.kind in "fc" and not np.isfinite(value).all():
            raise ValueError(f"{path} is not finite")
    elif isinstance(value, dict):
        for key, item in value.items():
            if not isinstance(key, str):
                raise ValueError(f"{path} has a non-string key")
            _check_json_finite(item, f"{path}.{key}")
    elif isinstance(value, list):
        for i, item in enumerate(value):
            _check_json_finite(item, f"{path}[{i}]")


class ConfigUpdate(Message):
    """An accepted configuration change, published by the config API (the single writer).

    ``config`` is the whole validated stack configuration (shared.config.StackConfig as JSON);
    ``changed`` lists the dotted paths that changed; services apply it at their next step.
    """

    SCHEMA_NAME: ClassVar[str] = "ConfigUpdate"
    version: int = Field(ge=0)
    changed: list[str] = Field(default_factory=list, max_length=256)
    config: dict[str, Any]

    @field_validator("config")
    @classmethod
    def _finite(cls, value: dict[str, Any]) -> dict[str, Any]:
        _check_json_finite(value)
        return value


#: Every message type by schema name: the codec's registry.
MESSAGE_TYPES: dict[str, type[Message]] = {
    cls.SCHEMA_NAME: cls for cls in (HumanState, JointState, JointCommand, SafetyStatus, ConfigUpdate)
}
