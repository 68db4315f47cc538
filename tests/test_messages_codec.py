"""Bus messages and their msgpack codec (architecture §5, §11).

* every message type round-trips exactly (arrays, dtypes, optional fields, every SafetyMode);
* arrays travel as raw binary ND_EXT blobs, not as lists of msgpack floats;
* validation: NaN/Inf, wrong shapes, unknown fields, schema name/version, size limits;
* fuzzing: well over 10,000 hostile payloads, through which only ``CodecError`` may escape and
  anything decoded is a valid, finite message of its declared shapes.
"""

from __future__ import annotations

import math
import struct
from collections import Counter
from typing import Any

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp
from pydantic import ValidationError

from shared import codec
from shared.codec import (
    MAX_MESSAGE_BYTES,
    ND_EXT,
    CodecError,
    InvalidMessage,
    MalformedPayload,
    MessageTooLarge,
    SchemaVersionMismatch,
    UnknownSchema,
    decode,
    encode,
)
from shared.config import StackConfig
from shared.messages import (
    MAX_ANGLE_RAD,
    MAX_COORD_M,
    MAX_RATE_RADPS,
    MAX_SPEED_MPS,
    MESSAGE_TYPES,
    ConfigUpdate,
    HumanState,
    JointCommand,
    JointState,
    Message,
    SafetyMode,
    SafetyStatus,
    Schema,
)
from tests.support.messages import make

F8 = np.dtype("<f8")
B1 = np.dtype("|b1")

#: Every array field, as architecture §3/§5 declare it (independent of the models' own annotations).
ARRAY_FIELDS: dict[type[Message], dict[str, tuple[tuple[int, ...], np.dtype]]] = {
    HumanState: {
        "keypoints": ((15, 3), F8),
        "keypoint_valid": ((15,), B1),
        "theta": ((8,), F8),
        "theta_valid": ((8,), B1),
        "theta_rate": ((8,), F8),
        "capsules": ((7, 2, 3), F8),
        "capsule_radii": ((7,), F8),
        "capsule_valid": ((7,), B1),
        "capsule_velocities": ((7, 2, 3), F8),
    },
    JointState: {"q": ((8,), F8), "dq": ((8,), F8), "q_command": ((8,), F8)},
    JointCommand: {"q": ((8,), F8), "dq": ((8,), F8), "ddq": ((8,), F8)},
    SafetyStatus: {"q_nom": ((8,), F8)},
    ConfigUpdate: {},
}
OPTIONAL_ARRAYS = {(HumanState, "capsule_velocities"), (JointState, "q_command"), (SafetyStatus, "q_nom")}
#: Every scalar float field (NaN/Inf must be rejected in each).
FLOAT_SCALARS: dict[type[Message], tuple[str, ...]] = {
    HumanState: ("stamp", "capture_stamp"),
    JointState: ("stamp",),
    JointCommand: ("stamp", "human_stamp"),
    SafetyStatus: ("stamp", "min_h_self", "min_h_human", "qp_solve_time_ms", "step_time_ms"),
    ConfigUpdate: ("stamp",),
}
FLOAT_ARRAYS = [(cls, name) for cls, fields in ARRAY_FIELDS.items() for name, (_, dt) in fields.items() if dt == F8]
BAD_FLOATS = [math.nan, math.inf, -math.inf]


# --------------------------------------------------------------------------------------------
# helpers


def unpack(data: bytes) -> dict[str, Any]:
    """The raw payload dict of an encoding (arrays as writable numpy copies)."""
    payload = msgpack.unpackb(data, raw=False, ext_hook=codec._ext_hook, strict_map_key=False)
    return {k: (v.copy() if isinstance(v, np.ndarray) else v) for k, v in payload.items()}


def pack(payload: Any) -> bytes:
    """Re-pack a (patched) payload exactly as the codec would."""
    return msgpack.packb(payload, default=codec._default, use_bin_type=True)


def assert_tree_equal(a: Any, b: Any) -> None:
    """Exact structural equality: same types, same dtypes/shapes, bitwise-equal floats (incl. −0.0)."""
    stack = [(a, b, "$")]
    while stack:
        x, y, path = stack.pop()
        if isinstance(x, np.ndarray):
            assert isinstance(y, np.ndarray), path
            assert x.dtype == y.dtype, (path, x.dtype, y.dtype)
            assert x.shape == y.shape, (path, x.shape, y.shape)
            assert x.tobytes() == y.tobytes(), path
        elif isinstance(x, dict):
            assert isinstance(y, dict) and list(x) == list(y), (path, x, y)
            stack.extend((x[k], y[k], f"{path}.{k}") for k in x)
        elif isinstance(x, list):
            assert isinstance(y, list) and len(x) == len(y), path
            stack.extend((xi, yi, f"{path}[{i}]") for i, (xi, yi) in enumerate(zip(x, y)))
        elif isinstance(x, float):
            assert type(y) is float and struct.pack("<d", x) == struct.pack("<d", y), (path, x, y)
        else:
            assert type(x) is type(y) and x == y, (path, x, y)


def assert_messages_equal(a: Message, b: Message) -> None:
    assert type(a) is type(b)
    assert a.schema_ == b.schema_
    assert_tree_equal(a.model_dump(), b.model_dump())


def assert_all_finite(tree: Any) -> None:
    """No NaN/Inf anywhere: python floats, numpy arrays, nested dicts and lists."""
    stack = [tree]
    while stack:
        x = stack.pop()
        if isinstance(x, float):
            assert math.isfinite(x)
        elif isinstance(x, (np.ndarray, np.generic)):
            if x.dtype.kind in "fc":
                assert np.isfinite(x).all()
        elif isinstance(x, dict):
            stack.extend(x.values())
        elif isinstance(x, list):
            stack.extend(x)


def check_decoded(m: Any) -> None:
    """What anything ``decode`` returns must satisfy."""
    cls = type(m)
    assert cls in MESSAGE_TYPES.values() and MESSAGE_TYPES[cls.SCHEMA_NAME] is cls
    assert m.schema_ == Schema(name=cls.SCHEMA_NAME, version=cls.SCHEMA_VERSION)
    for name, (shape, dtype) in ARRAY_FIELDS[cls].items():
        value = getattr(m, name)
        if value is None:
            assert (cls, name) in OPTIONAL_ARRAYS, name
            continue
        assert isinstance(value, np.ndarray), name
        assert value.shape == shape and value.dtype == dtype, (name, value.shape, value.dtype)
        if dtype.kind == "f":
            assert np.isfinite(value).all(), name
    for name in FLOAT_SCALARS[cls]:
        value = getattr(m, name)
        assert value is None or (type(value) is float and math.isfinite(value)), (name, value)
    assert isinstance(m.seq, int) and 0 <= m.seq < 2**63
    dumped = m.model_dump()
    assert_all_finite(dumped)
    assert_messages_equal(cls.model_validate(dumped), m)  # re-validates
    assert_messages_equal(decode(encode(m), expected=cls), m)  # and travels again unchanged


# --------------------------------------------------------------------------------------------
# realistic instances: one hypothesis factory per message type

FINITE = st.floats(allow_nan=False, allow_infinity=False)


def text(max_size: int) -> st.SearchStrategy[str]:
    return st.text(st.characters(exclude_categories=("Cs",)), max_size=max_size)


def f64(*shape: int, elements: st.SearchStrategy[float] = FINITE) -> st.SearchStrategy[np.ndarray]:
    return hnp.arrays(F8, shape, elements=elements)


def within(limit: float) -> st.SearchStrategy[float]:
    """Floats a message field bounded by ``limit`` accepts (its bounds included)."""
    return st.floats(-limit, limit)


def bools(*shape: int) -> st.SearchStrategy[np.ndarray]:
    return hnp.arrays(B1, shape)


def optional(strategy: st.SearchStrategy) -> st.SearchStrategy:
    return st.none() | strategy


HEADER = {"stamp": FINITE, "seq": st.integers(0, 2**63 - 1), "source": text(64)}
JSON_FINITE = st.recursive(
    st.none() | st.booleans() | st.integers(-(2**63), 2**64 - 1) | FINITE | text(16),
    lambda children: st.lists(children, max_size=4) | st.dictionaries(text(12), children, max_size=4),
    max_leaves=24,
)

FACTORIES: dict[type[Message], st.SearchStrategy[Message]] = {
    HumanState: st.builds(
        HumanState,
        **HEADER,
        keypoints=f64(15, 3, elements=within(MAX_COORD_M)),
        keypoint_valid=bools(15),
        theta=f64(8, elements=within(MAX_ANGLE_RAD)),
        theta_valid=bools(8),
        theta_rate=f64(8, elements=within(MAX_RATE_RADPS)),
        capsules=f64(7, 2, 3, elements=within(MAX_COORD_M)),
        capsule_radii=f64(7, elements=st.floats(0.0, 1.0)),
        capsule_valid=bools(7),
        capsule_velocities=optional(f64(7, 2, 3, elements=within(MAX_SPEED_MPS))),
        frame_id=st.just("robot"),
        capture_stamp=optional(FINITE),
    ),
    JointState: st.builds(
        JointState, **HEADER, q=f64(8, elements=within(MAX_ANGLE_RAD)), dq=f64(8, elements=within(MAX_RATE_RADPS)),
        q_command=optional(f64(8, elements=within(MAX_ANGLE_RAD))), command_stale=st.booleans()
    ),
    JointCommand: st.builds(
        JointCommand,
        **HEADER,
        q=f64(8, elements=within(MAX_ANGLE_RAD)),
        dq=f64(8, elements=within(MAX_RATE_RADPS)),
        mode=st.sampled_from(SafetyMode),
        human_stamp=optional(FINITE),
        human_seq=optional(st.integers(0, 2**64 - 1)),
    ),
    SafetyStatus: st.builds(
        SafetyStatus,
        **HEADER,
        mode=st.sampled_from(SafetyMode),
        min_h_self=optional(FINITE),
        min_h_human=optional(FINITE),
        active_constraints=st.integers(0, 10_000),
        total_constraints=st.integers(0, 10_000),
        qp_solve_time_ms=st.floats(0.0, 1e6),
        step_time_ms=st.floats(0.0, 1e6),
        deadline_misses=st.integers(0, 2**63),
        human_stale=st.booleans(),
        joint_state_stale=st.booleans(),
        human_source_lost=st.booleans(),
        executor_holding=st.booleans(),
        resyncing=st.booleans(),
        human_lost=st.booleans(),
        binding_pairs=st.lists(text(64), max_size=4),
        q_nom=optional(f64(8)),
        watchdog_trips=st.dictionaries(text(32), st.integers(0, 2**63), max_size=5),
        dropped=st.dictionaries(text(32), st.integers(0, 2**63), max_size=6),
        config_version=st.integers(0, 2**32),
        backend=text(32),
    ),
    ConfigUpdate: st.builds(
        ConfigUpdate,
        **HEADER,
        version=st.integers(0, 2**63),
        changed=st.lists(text(40), max_size=8),
        config=st.just(StackConfig().model_dump(mode="json"))
        | st.dictionaries(text(12), JSON_FINITE, max_size=6),
    ),
}
ANY_MESSAGE = st.one_of(*FACTORIES.values())


# --------------------------------------------------------------------------------------------
# round trips


def test_registry_lists_every_message_type() -> None:
    assert set(MESSAGE_TYPES) == {"HumanState", "JointState", "JointCommand", "SafetyStatus", "ConfigUpdate"}
    assert set(FACTORIES) == set(MESSAGE_TYPES.values()) == set(ARRAY_FIELDS)
    for name, cls in MESSAGE_TYPES.items():
        assert cls.SCHEMA_NAME == name
        # the test's table of array fields matches the models' ndarray fields
        array_fields = {f for f, info in cls.model_fields.items() if "ndarray" in str(info.annotation)}
        assert array_fields == set(ARRAY_FIELDS[cls]), name


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(ANY_MESSAGE)
def test_every_message_round_trips(message: Message) -> None:
    data = encode(message)
    assert isinstance(data, bytes)
    decoded = decode(data)
    assert_messages_equal(decoded, message)
    assert_messages_equal(decode(data, expected=type(message)), message)
    check_decoded(decoded)


@pytest.mark.parametrize("cls", list(MESSAGE_TYPES.values()), ids=list(MESSAGE_TYPES))
def test_round_trip_deterministic_and_buffer_types(cls: type[Message]) -> None:
    message = make(cls)
    data = encode(message)
    assert encode(message) == data  # deterministic
    for buffer in (data, bytearray(data), memoryview(data)):
        assert_messages_equal(decode(buffer), message)


def test_array_dtypes_preserved() -> None:
    decoded = decode(encode(make(HumanState)))
    for name, (shape, dtype) in ARRAY_FIELDS[HumanState].items():
        value = getattr(decoded, name)
        assert value.dtype == dtype and value.shape == shape, name
    assert decoded.keypoint_valid.dtype == np.bool_
    joint = decode(encode(make(JointState)))
    assert joint.q.dtype == np.float64 and joint.dq.dtype == np.float64
    # float32 input is widened to the declared float64 on construction, and stays so on the wire
    joint32 = make(JointState, q=np.arange(8, dtype=np.float32))
    assert decode(encode(joint32)).q.dtype == np.float64


@pytest.mark.parametrize(
    ("cls", "field", "value"),
    [
        (HumanState, "capsule_velocities", None),
        (HumanState, "capture_stamp", None),
        (JointCommand, "human_stamp", None),
        (JointCommand, "human_seq", None),
        (SafetyStatus, "min_h_self", None),
        (SafetyStatus, "min_h_human", None),
        (HumanState, "capture_stamp", -0.0),
        (JointCommand, "human_seq", 2**64 - 1),
        (SafetyStatus, "dropped", {}),
        (ConfigUpdate, "config", {}),
    ],
)
def test_optional_fields_none_and_set(cls: type[Message], field: str, value: Any) -> None:
    unset = make(cls, **{field: value})
    decoded = decode(encode(unset))
    assert_messages_equal(decoded, unset)
    if value is None:
        assert getattr(decoded, field) is None
    full = make(cls)
    assert getattr(full, field) is not None
    assert_messages_equal(decode(encode(full)), full)


def test_defaults_of_optional_fields_are_none() -> None:
    minimal = HumanState(
        stamp=0.0,
        keypoints=np.zeros((15, 3)),
        keypoint_valid=np.zeros(15, bool),
        theta=np.zeros(8),
        theta_valid=np.zeros(8, bool),
        capsules=np.zeros((7, 2, 3)),
        capsule_radii=np.zeros(7),
        capsule_valid=np.zeros(7, bool),
    )
    decoded = decode(encode(minimal))
    assert decoded.capsule_velocities is None and decoded.capture_stamp is None
    np.testing.assert_array_equal(decoded.theta_rate, np.zeros(8))  # no rates: zeros (not computable)
    assert decoded.seq == 0 and decoded.source == "" and decoded.frame_id == "robot"
    command = decode(encode(JointCommand(stamp=1.0, q=np.zeros(8), dq=np.zeros(8))))
    assert command.mode is SafetyMode.NOMINAL and command.human_stamp is None and command.human_seq is None
    assert command.settled is False and command.protective_stop is False
    assert decode(encode(JointCommand(stamp=1.0, q=np.zeros(8), dq=np.zeros(8), settled=True))).settled is True
    stop = decode(encode(JointCommand(stamp=1.0, q=np.zeros(8), dq=np.zeros(8), protective_stop=True)))
    assert stop.protective_stop is True and stop.settled is False


@pytest.mark.parametrize("mode", list(SafetyMode))
def test_every_safety_mode_round_trips(mode: SafetyMode) -> None:
    for cls in (JointCommand, SafetyStatus):
        message = make(cls, mode=mode)
        decoded = decode(encode(message))
        assert decoded.mode is mode
        assert_messages_equal(decoded, message)
        assert unpack(encode(message))["mode"] == mode.value  # a plain string on the wire


def test_unknown_safety_mode_rejected() -> None:
    with pytest.raises(ValidationError):
        make(JointCommand, mode="panic")
    payload = unpack(encode(make(JointCommand)))
    payload["mode"] = "panic"
    with pytest.raises(InvalidMessage):
        decode(pack(payload))


# --------------------------------------------------------------------------------------------
# arrays travel as binary


def test_arrays_travel_as_raw_binary() -> None:
    message = make(HumanState)
    data = encode(message)
    # structurally: every array field is an ND_EXT extension blob, not a msgpack list
    raw = msgpack.unpackb(data, raw=False)
    for name in ARRAY_FIELDS[HumanState]:
        assert isinstance(raw[name], msgpack.ExtType) and raw[name].code == ND_EXT, name
    # the keypoints' little-endian float64 bytes appear verbatim, C order ...
    assert message.keypoints.astype("<f8").tobytes() in data
    assert message.capsules.astype("<f8").tobytes() in data
    # ... and not one keypoint is encoded as a msgpack float64 (0xcb + big-endian double)
    for value in message.keypoints.ravel():
        assert b"\xcb" + struct.pack(">d", value) not in data
    # size: raw array bytes plus a small fixed overhead, and smaller than a list-of-floats encoding
    n_floats = sum(math.prod(s) for s, d in ARRAY_FIELDS[HumanState].values() if d == F8)
    n_bools = sum(math.prod(s) for s, d in ARRAY_FIELDS[HumanState].values() if d == B1)
    assert len(data) <= 8 * n_floats + n_bools + 400
    as_lists = msgpack.packb(message.model_dump(mode="json", by_alias=True), use_bin_type=True)
    assert len(data) < len(as_lists)
    assert as_lists.count(b"\xcb") >= n_floats  # the list encoding is full of float markers


def test_arrays_of_any_layout_encode_as_little_endian_c_order() -> None:
    """encode writes what msgpack.packb of the field dict writes, whatever the arrays' byte order and strides."""
    reference = make(HumanState)
    message = make(HumanState)
    message.keypoints = message.keypoints.astype(">f8")  # validate_assignment is off: encode gets them as they are
    message.capsules = np.asfortranarray(message.capsules)
    message.theta = np.repeat(message.theta, 2)[::2]
    data = encode(message)
    fields = {name: getattr(message, name) for name in HumanState.model_fields if name != "schema_"}
    assert data == pack({"schema": {"name": "HumanState", "version": HumanState.SCHEMA_VERSION}} | fields)
    for name in ("keypoints", "capsules", "theta"):
        assert getattr(reference, name).astype("<f8").tobytes() in data, name
    assert_messages_equal(decode(data), reference)


def test_decoded_arrays_do_not_share_state_with_the_sender() -> None:
    message = make(JointState)
    decoded = decode(encode(message))
    message.q[0] += 1.0
    assert decoded.q[0] != message.q[0]


# --------------------------------------------------------------------------------------------
# validation


def _bad_array(value: np.ndarray, bad: float) -> np.ndarray:
    patched = np.array(value, dtype=np.float64, copy=True)
    patched.flat[patched.size // 2] = bad
    return patched


def _assert_refused(good: Message, field: str, patched: Any) -> dict[str, Any]:
    """``good`` with ``field`` = ``patched`` is refused when built and when decoded; the payload."""
    with pytest.raises(ValidationError):
        make(type(good), **{field: patched})
    payload = unpack(encode(good))
    payload[field] = patched
    with pytest.raises(InvalidMessage):
        decode(pack(payload))
    return payload


@pytest.mark.parametrize("bad", BAD_FLOATS, ids=["nan", "inf", "-inf"])
@pytest.mark.parametrize(
    ("cls", "field"),
    [(cls, f) for cls, fields in FLOAT_SCALARS.items() for f in fields] + FLOAT_ARRAYS,
    ids=lambda x: x.__name__ if isinstance(x, type) else x,
)
def test_nan_and_inf_rejected_everywhere(cls: type[Message], field: str, bad: float) -> None:
    good = make(cls)
    value = getattr(good, field)
    patched = _bad_array(value, bad) if isinstance(value, np.ndarray) else bad
    payload = _assert_refused(good, field, patched)
    # NaN as float32 array on the wire (another whitelisted dtype) too
    if isinstance(value, np.ndarray):
        payload[field] = patched.astype(np.float32)
        with pytest.raises(InvalidMessage):
            decode(pack(payload))


@pytest.mark.parametrize("field", ["keypoint_valid", "theta_valid", "capsule_valid"])
def test_a_bool_field_refuses_numbers_of_another_kind(field: str) -> None:
    """A validity mask given as floats (a NaN among them would be cast to True) or as integers is
    refused when built and when decoded, with a message naming the dtype; bools pass, and a float
    field still takes integers and bools (they convert within their kind)."""
    good = make(HumanState)
    mask = getattr(good, field)
    for wrong in (mask.astype(np.float64), np.where(mask, np.nan, 0.0), mask.astype(np.int64)):
        _assert_refused(good, field, wrong)
    with pytest.raises(ValidationError, match="float64 values are not bool"):
        make(HumanState, **{field: mask.astype(np.float64)})
    assert getattr(make(HumanState, **{field: mask.tolist()}), field).dtype == np.bool_
    joint = make(JointState, q=np.arange(8), dq=np.zeros(8, bool))
    assert joint.q.dtype == np.float64 and joint.dq.dtype == np.float64


@pytest.mark.parametrize("sign", [1.0, -1.0])
@pytest.mark.parametrize(("cls", "field"), [(JointCommand, "ddq")])
def test_finite_arrays_whose_sum_overflows_are_accepted(cls: type[Message], field: str, sign: float) -> None:
    """The finite check's cheap sum overflows here: its element-wise fallback accepts, and still refuses
    NaN/Inf (on a field without a magnitude bound: the bounded ones refuse such values anyway,
    test_finite_values_no_robot_or_person_has_are_refused)."""
    huge = np.full(ARRAY_FIELDS[cls][field][0], sign * np.finfo(np.float64).max)
    message = make(cls, **{field: huge})
    decoded = decode(encode(message))
    assert getattr(decoded, field).tobytes() == huge.tobytes()
    for bad in BAD_FLOATS:
        _assert_refused(message, field, _bad_array(huge, bad))


def _wrong_shapes(shape: tuple[int, ...]) -> list[np.ndarray]:
    n = math.prod(shape)
    candidates = [
        np.zeros(n),  # flattened
        np.zeros((shape[0] + 1, *shape[1:])),  # one too many
        np.zeros((shape[0] - 1, *shape[1:])),  # one too few
        np.zeros((*shape, 1)),  # extra trailing dim
        np.zeros((1, *shape)),  # extra leading dim
        np.zeros(()),  # scalar
        np.zeros((0,)),  # empty
    ]
    return [c for c in candidates if c.shape != shape]


@pytest.mark.parametrize(
    ("cls", "field"),
    [(cls, f) for cls, fields in ARRAY_FIELDS.items() for f in fields],
    ids=lambda x: x.__name__ if isinstance(x, type) else x,
)
def test_wrong_shapes_rejected(cls: type[Message], field: str) -> None:
    shape, dtype = ARRAY_FIELDS[cls][field]
    good_payload = unpack(encode(make(cls)))
    for wrong in _wrong_shapes(shape):
        wrong = wrong.astype(dtype)
        with pytest.raises(ValidationError):
            make(cls, **{field: wrong})
        with pytest.raises(ValidationError):
            make(cls, **{field: wrong.tolist()})
        payload = dict(good_payload)
        payload[field] = wrong
        with pytest.raises(InvalidMessage):
            decode(pack(payload))
        payload[field] = wrong.tolist()
        with pytest.raises(InvalidMessage):
            decode(pack(payload))
    # non-numeric content
    for junk in ("abc", b"abc", {"a": 1}, [["x"] * 3] * 15):
        with pytest.raises(ValidationError):
            make(cls, **{field: junk})


def test_capsule_radii_range_and_schema_consistency() -> None:
    with pytest.raises(ValidationError):
        make(HumanState, capsule_radii=np.full(7, -0.01))
    with pytest.raises(ValidationError):
        make(HumanState, capsule_radii=np.full(7, 1.5))
    with pytest.raises(ValidationError, match="does not match"):
        make(HumanState, schema={"name": "JointState", "version": 1})
    with pytest.raises(ValidationError, match="does not match"):
        make(JointState, schema={"name": "JointState", "version": 2})
    with pytest.raises(ValidationError):
        make(JointState, seq=-1)
    with pytest.raises(ValidationError):
        make(JointState, source="x" * 65)


@pytest.mark.parametrize("cls", list(MESSAGE_TYPES.values()), ids=list(MESSAGE_TYPES))
def test_unknown_fields_rejected(cls: type[Message]) -> None:
    with pytest.raises(ValidationError, match="bogus"):
        make(cls, bogus=1)
    payload = unpack(encode(make(cls)))
    payload["bogus"] = 1
    with pytest.raises(InvalidMessage, match="bogus"):
        decode(pack(payload))
    payload = unpack(encode(make(cls)))
    payload["schema"] = {**payload["schema"], "extra": True}
    with pytest.raises(InvalidMessage):
        decode(pack(payload))


@pytest.mark.parametrize("cls", list(MESSAGE_TYPES.values()), ids=list(MESSAGE_TYPES))
def test_missing_required_field_rejected(cls: type[Message]) -> None:
    payload = unpack(encode(make(cls)))
    del payload["stamp"]
    with pytest.raises(InvalidMessage, match="stamp"):
        decode(pack(payload))


@pytest.mark.parametrize("version", [0, 2, -1, 2**32, "1", 1.5, None, [1]])
def test_wrong_schema_version(version: Any) -> None:
    payload = unpack(encode(make(JointState)))
    payload["schema"] = {"name": "JointState", "version": version}
    with pytest.raises(SchemaVersionMismatch):
        decode(pack(payload))
    del payload["schema"]["version"]
    with pytest.raises(SchemaVersionMismatch):
        decode(pack(payload))


@pytest.mark.parametrize("name", ["Nope", "humanstate", "HumanState ", "Message", "message", "", "x" * 10_000])
def test_unknown_schema_name(name: str) -> None:
    payload = unpack(encode(make(HumanState)))
    payload["schema"] = {"name": name, "version": 1}
    with pytest.raises(UnknownSchema) as info:
        decode(pack(payload))
    assert len(str(info.value)) < 200  # a hostile name is not echoed at length


@pytest.mark.parametrize("schema", [None, "HumanState", 1, [], {"version": 1}, {"name": 5, "version": 1}])
def test_malformed_schema(schema: Any) -> None:
    payload = unpack(encode(make(HumanState)))
    if schema is None:
        del payload["schema"]
    else:
        payload["schema"] = schema
    with pytest.raises(MalformedPayload):
        decode(pack(payload))


def test_expected_type_enforced() -> None:
    human = encode(make(HumanState))
    with pytest.raises(UnknownSchema):
        decode(human, expected=JointState)
    with pytest.raises(UnknownSchema):
        decode(encode(make(JointState)), expected=JointCommand)  # same fields, different schema
    assert isinstance(decode(human, expected=HumanState), HumanState)


def test_oversized_payloads() -> None:
    with pytest.raises(MessageTooLarge):
        decode(b"\x80" + b"\x00" * MAX_MESSAGE_BYTES)
    data = encode(make(HumanState))
    with pytest.raises(MessageTooLarge):
        decode(data, max_bytes=len(data) - 1)
    assert isinstance(decode(data, max_bytes=len(data)), HumanState)
    # a valid message too large to send
    huge = make(ConfigUpdate, config={"blob": "x" * MAX_MESSAGE_BYTES})
    with pytest.raises(MessageTooLarge):
        encode(huge)
    # a small payload announcing huge containers is refused, not allocated
    for header in (b"\xdd\x7f\xff\xff\xff", b"\xdf\x7f\xff\xff\xff", b"\xdb\x7f\xff\xff\xff", b"\xc6\x7f\xff\xff\xff"):
        with pytest.raises(MalformedPayload):
            decode(header + b"\x00" * 16)


def test_config_update_rejects_nan_nested_deep() -> None:
    for bad in BAD_FLOATS:
        config = {"safety": {"gamma": 1.0, "weights": [1.0, {"deep": [0.0, bad]}]}}
        with pytest.raises(ValidationError, match=r"config\.safety\.weights\[1\]\.deep\[1\]"):
            make(ConfigUpdate, config=config)
        payload = unpack(encode(make(ConfigUpdate)))
        payload["config"] = config
        with pytest.raises(InvalidMessage):
            decode(pack(payload))
        # also when hidden in a binary array blob inside the tree
        payload["config"] = {"safety": {"weights": np.array([1.0, bad])}}
        with pytest.raises(InvalidMessage):
            decode(pack(payload))
        payload["config"] = {"a": [np.array([[bad]], dtype=np.float32)]}
        with pytest.raises(InvalidMessage):
            decode(pack(payload))
    with pytest.raises(ValidationError):
        make(ConfigUpdate, config={"a": np.array([np.nan])})


def test_deeply_nested_payloads_do_not_crash() -> None:
    for depth in (10, 200, 900, 1000, 5000, 100_000):
        nested = b"\x91" * depth + b"\xcb" + struct.pack(">d", 1.0)
        data = pack({"schema": {"name": "ConfigUpdate", "version": 1}, "stamp": 0.0, "version": 0})
        assert data[0] == 0x83  # a 3-entry fixmap: add a fourth entry, config = {"x": [[[...1.0]]]}
        data = b"\x84" + data[1:] + b"\xa6config\x81\xa1x" + nested
        try:
            message = decode(data)
        except CodecError:
            continue
        check_decoded(message)


# --------------------------------------------------------------------------------------------
# fuzzing: only CodecError escapes; whatever decodes is valid

FUZZ_BUDGET = {
    "random_bytes": 4000,
    "truncated": 2000,
    "mutated_bytes": 1800,
    "random_maps": 1000,
    "mutated_payloads": 1000,
    "nd_ext": 1200,
    "oversized": 500,
}
FUZZ_COUNTS: Counter[str] = Counter()
FUZZ_OUTCOMES: Counter[str] = Counter()
FUZZ_FINISHED: set[str] = set()


def fuzz_decode(kind: str, data: bytes, **kwargs: Any) -> Message | None:
    """Decode hostile bytes: a CodecError or a message passing :func:`check_decoded`, nothing else."""
    FUZZ_COUNTS[kind] += 1
    try:
        message = decode(data, **kwargs)
    except CodecError as exc:
        FUZZ_OUTCOMES[type(exc).__name__] += 1
        return None
    FUZZ_OUTCOMES["decoded"] += 1
    check_decoded(message)
    if "expected" in kwargs:
        assert type(message) is kwargs["expected"]
    return message


def fuzz_settings(kind: str):
    return settings(
        max_examples=FUZZ_BUDGET[kind],
        deadline=None,
        suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large, HealthCheck.filter_too_much],
    )


def finish(kind: str) -> None:
    assert FUZZ_COUNTS[kind] >= FUZZ_BUDGET[kind], (kind, FUZZ_COUNTS[kind])
    FUZZ_FINISHED.add(kind)


ENCODED = ANY_MESSAGE.map(encode)
SCHEMA_NAMES = [*MESSAGE_TYPES, "", "Message", "message", "humanstate", "JointState\x00", "Config Update", "x" * 65]
FIELD_NAMES = sorted({"schema", "schema_", *(f for cls in MESSAGE_TYPES.values() for f in cls.model_fields)})
HOSTILE_LEAF = (
    st.none()
    | st.booleans()
    | st.integers(-(2**63), 2**64 - 1)
    | st.floats()  # NaN and ±Inf included
    | st.floats(width=32)
    | text(20)
    | st.binary(max_size=20)
    | st.builds(msgpack.Timestamp, st.integers(0, 2**34 - 1), st.integers(0, 999_999_999))  # ext type −1
)


@st.composite
def nd_ext_blobs(draw) -> msgpack.ExtType:
    """ND_EXT extension blobs, mostly broken: dtype codes, ndim, shape and byte counts."""
    ext_code = draw(st.sampled_from([ND_EXT] * 8 + [0, 2, 5, 127]))
    dtype_code = draw(st.sampled_from([0, 0, 0, 1, 2, 3, 4, 5]) | st.integers(0, 255))
    dims = draw(
        st.lists(
            st.sampled_from([0, 1, 2, 3, 7, 8, 15, 45]) | st.sampled_from([2**31, 2**32 - 1]) | st.integers(0, 2**32 - 1),
            max_size=6,
        )
    )
    ndim = draw(st.just(len(dims)) | st.integers(0, 255))
    n_items = math.prod(dims)
    itemsize = codec._DTYPES[dtype_code].itemsize if dtype_code < len(codec._DTYPES) else 1
    exact = n_items * itemsize
    body_len = draw(
        (st.just(exact) if exact <= 4096 else st.nothing())
        | (st.integers(max(0, exact - 9), exact + 9).filter(lambda n: n <= 4096) if exact <= 4105 else st.nothing())
        | st.integers(0, 600)
    )
    body = draw(array_bodies(body_len, codec._DTYPES[dtype_code] if dtype_code < len(codec._DTYPES) else None))
    blob = struct.pack("<BB", dtype_code, ndim) + b"".join(struct.pack("<I", d) for d in dims) + body
    cut = draw(st.none() | st.integers(0, len(blob)))
    return msgpack.ExtType(ext_code, blob if cut is None else blob[:cut])


def valid_nd_ext(shape: tuple[int, ...], dtype_code: int) -> st.SearchStrategy[msgpack.ExtType]:
    """A well-formed ND_EXT header with random content (finite values, or raw bits: NaN, Inf, ...)."""
    dtype = codec._DTYPES[dtype_code]
    header = struct.pack("<BB", dtype_code, len(shape)) + b"".join(struct.pack("<I", d) for d in shape)
    return array_bodies(math.prod(shape) * dtype.itemsize, dtype).map(lambda body: msgpack.ExtType(ND_EXT, header + body))


def array_bodies(n: int, dtype: np.dtype | None) -> st.SearchStrategy[bytes]:
    """``n`` bytes of array content: zeros, seeded random bits, seeded finite values, or a drawn blob."""

    def seeded(kind: str, seed: int) -> bytes:
        rng = np.random.default_rng(seed)
        if kind != "bits" and dtype is not None and n % dtype.itemsize == 0 and n > 0:
            count = n // dtype.itemsize
            values = rng.normal(0, 0.5, count) if dtype.kind == "f" else rng.integers(0, 2, count)
            values = values.astype(dtype)
            if kind == "poison" and dtype.kind == "f":  # one NaN or ±Inf among finite values
                values[rng.integers(count)] = rng.choice([np.nan, np.inf, -np.inf])
            return values.tobytes()
        return rng.bytes(n) if kind == "bits" else bytes(n)

    kinds = st.sampled_from(["zeros", "bits", "values", "values", "poison", "poison"])
    options = st.builds(seeded, kinds, st.integers(0, 2**32))
    return options | st.binary(min_size=n, max_size=n) if n <= 32 else options


DECLARED_SHAPES = sorted({s for fields in ARRAY_FIELDS.values() for s, _ in fields.values()})
VALID_ND_EXT = st.tuples(st.sampled_from(DECLARED_SHAPES), st.sampled_from([0, 0, 0, 1, 1, 2, 3, 4, 5])).flatmap(
    lambda shape_code: valid_nd_ext(*shape_code)
)
ANY_ND_EXT = st.one_of(nd_ext_blobs(), VALID_ND_EXT, VALID_ND_EXT)
HOSTILE_TREE = st.recursive(
    HOSTILE_LEAF | ANY_ND_EXT,
    lambda children: st.lists(children, max_size=4) | st.dictionaries(text(12), children, max_size=4),
    max_leaves=10,
)
SCHEMA_VALUE = (
    st.fixed_dictionaries(
        {"name": st.sampled_from(SCHEMA_NAMES) | text(12), "version": st.just(1) | st.integers(-3, 3) | HOSTILE_LEAF}
    )
    | st.fixed_dictionaries({"name": st.sampled_from(list(MESSAGE_TYPES)), "version": st.just(1)})
    | HOSTILE_TREE
)


@st.composite
def random_maps(draw) -> bytes:
    payload: dict[Any, Any] = draw(
        st.dictionaries(st.sampled_from(FIELD_NAMES) | text(10), HOSTILE_TREE, max_size=6)
    )
    if draw(st.integers(0, 9)):
        payload["schema"] = draw(SCHEMA_VALUE)
    outer = draw(st.sampled_from(["map", "map", "map", "map", "list", "scalar", "bytes-key"]))
    if outer == "list":
        return pack([payload])
    if outer == "scalar":
        return pack(draw(HOSTILE_LEAF))
    if outer == "bytes-key":
        payload[b"schema"] = payload.pop("schema", None)
    return pack(payload)


@st.composite
def mutated_payloads(draw) -> bytes:
    """A valid message's payload with one to three fields replaced, deleted, added or swapped."""
    payload = unpack(draw(ENCODED))
    other = unpack(encode(make(draw(st.sampled_from(list(MESSAGE_TYPES.values()))))))
    for _ in range(draw(st.integers(1, 3))):
        action = draw(st.sampled_from(["set", "set", "ext", "nest", "delete", "swap", "schema"]))
        key = draw(st.sampled_from(sorted(payload)) | st.sampled_from(FIELD_NAMES) | text(8))
        if action == "set":
            payload[key] = draw(HOSTILE_TREE)
        elif action == "ext":
            payload[key] = draw(ANY_ND_EXT)
        elif action == "nest":  # a blob hidden inside a map (e.g. ConfigUpdate.config, SafetyStatus.dropped)
            payload[key] = {draw(text(8)): draw(ANY_ND_EXT | st.lists(ANY_ND_EXT, min_size=1, max_size=2))}
        elif action == "delete":
            payload.pop(key, None)
        elif action == "swap" and other:
            payload[key] = other[draw(st.sampled_from(sorted(other)))]
        else:
            payload["schema"] = draw(SCHEMA_VALUE)
    return pack(payload)


def test_fuzz_random_bytes() -> None:
    @fuzz_settings("random_bytes")
    @given(st.binary(max_size=600) | st.binary(max_size=8).map(lambda b: b"\x8f" + b))
    def run(data: bytes) -> None:
        fuzz_decode("random_bytes", data)

    run()
    finish("random_bytes")


def test_fuzz_truncated_encodings() -> None:
    @fuzz_settings("truncated")
    @given(ENCODED, st.data())
    def run(data: bytes, choice: st.DataObject) -> None:
        cut = choice.draw(st.integers(0, len(data) - 1))
        fuzz_decode("truncated", data[:cut])

    run()
    finish("truncated")


def test_fuzz_mutated_encodings() -> None:
    @fuzz_settings("mutated_bytes")
    @given(ENCODED, st.data())
    def run(data: bytes, choice: st.DataObject) -> None:
        buffer = bytearray(data)
        for _ in range(choice.draw(st.integers(1, 8))):
            index = choice.draw(st.integers(0, len(buffer) - 1))
            action = choice.draw(st.sampled_from(["flip", "flip", "byte", "insert", "delete"]))
            if action == "flip":
                buffer[index] ^= 1 << choice.draw(st.integers(0, 7))
            elif action == "byte":
                buffer[index] = choice.draw(st.integers(0, 255))
            elif action == "insert":
                buffer[index:index] = choice.draw(st.binary(min_size=1, max_size=4))
            elif len(buffer) > 1:
                del buffer[index]
        expected = choice.draw(st.none() | st.sampled_from(list(MESSAGE_TYPES.values())))
        fuzz_decode("mutated_bytes", bytes(buffer), **({"expected": expected} if expected else {}))

    run()
    finish("mutated_bytes")


def test_fuzz_random_msgpack_maps() -> None:
    @fuzz_settings("random_maps")
    @given(random_maps())
    def run(data: bytes) -> None:
        fuzz_decode("random_maps", data)

    run()
    finish("random_maps")


def test_fuzz_mutated_payloads() -> None:
    @fuzz_settings("mutated_payloads")
    @given(mutated_payloads())
    def run(data: bytes) -> None:
        fuzz_decode("mutated_payloads", data)

    run()
    finish("mutated_payloads")


def test_fuzz_nd_ext_blobs() -> None:
    @fuzz_settings("nd_ext")
    @given(ENCODED, st.data())
    def run(data: bytes, choice: st.DataObject) -> None:
        payload = unpack(data)
        fields = sorted(payload)  # arrays, scalars, schema: an ND_EXT blob may land anywhere
        key = choice.draw(st.sampled_from(fields))
        blob = choice.draw(ANY_ND_EXT)
        where = choice.draw(st.sampled_from(["field", "field", "field", "nested", "nested", "top", "key"]))
        if where == "field":
            payload[key] = blob
        elif where == "nested":  # inside a map field (ConfigUpdate.config, SafetyStatus.dropped) if any
            key = choice.draw(st.sampled_from([k for k in ("config", "dropped") if k in payload] or fields))
            payload[key] = {"x": choice.draw(st.just(blob) | st.just([blob]) | st.just({"y": [1.0, blob]}))}
        elif where == "top":
            fuzz_decode("nd_ext", pack(blob))
            return
        else:
            payload[blob] = 1  # an extension type as a map key
        fuzz_decode("nd_ext", pack(payload))

    run()
    finish("nd_ext")


def test_fuzz_oversized() -> None:
    @fuzz_settings("oversized")
    @given(ENCODED, st.integers(1, 4096), st.integers(0, 255), st.booleans())
    def run(data: bytes, excess: int, fill: int, shrink_limit: bool) -> None:
        if shrink_limit:  # a valid message, above a caller-chosen limit
            data, limit = data, max(0, len(data) - excess)
        else:  # anything above the default limit, even starting with a valid message
            data, limit = data + bytes([fill]) * (MAX_MESSAGE_BYTES - len(data) + excess), MAX_MESSAGE_BYTES
        FUZZ_COUNTS["oversized"] += 1
        with pytest.raises(MessageTooLarge):
            decode(data, max_bytes=limit)
        FUZZ_OUTCOMES["MessageTooLarge"] += 1

    run()
    finish("oversized")


def test_fuzz_total_at_least_10000() -> None:
    """Runs last (file order): the fuzz tests above fed ≥ 10,000 payloads to ``decode``."""
    assert sum(FUZZ_BUDGET.values()) >= 10_000
    if FUZZ_FINISHED != set(FUZZ_BUDGET):
        pytest.skip(f"only {sorted(FUZZ_FINISHED)} of the fuzz tests ran in this session")
    total = sum(FUZZ_COUNTS.values())
    print(f"fuzz: {total} payloads decoded, outcomes {dict(FUZZ_OUTCOMES)}")
    assert total >= 10_000
    # the fuzzers reached every outcome: decoded messages and each kind of rejection
    for outcome in ("decoded", "MalformedPayload", "InvalidMessage", "UnknownSchema", "SchemaVersionMismatch", "MessageTooLarge"):
        assert FUZZ_OUTCOMES[outcome] > 0, (outcome, dict(FUZZ_OUTCOMES))


@pytest.mark.parametrize(
    ("field", "value"),
    [("stamp", "1.5"), ("stamp", True), ("seq", 1.0), ("seq", "3"), ("source", b"bytes"), ("human_stamp", "0.5")],
)
def test_lax_coercions_from_the_wire_are_refused(field: str, value: Any) -> None:
    payload = unpack(encode(make(JointCommand)))
    payload[field] = value
    with pytest.raises(InvalidMessage):
        decode(pack(payload))


def test_a_schema_version_of_another_type_is_refused() -> None:
    for version in (True, 1.0, "1"):
        payload = unpack(encode(make(JointState)))
        payload["schema"] = {"name": "JointState", "version": version}
        with pytest.raises(CodecError):
            decode(pack(payload))


@pytest.mark.parametrize(("message", "field", "value"), [
    (HumanState, "capsules", MAX_COORD_M * 1.01), (HumanState, "capsules", 1e300), (HumanState, "keypoints", -1e200),
    (HumanState, "capsule_velocities", 1e300), (HumanState, "theta_rate", 1e300), (HumanState, "theta", 1e6),
    (JointState, "q", 1e6), (JointState, "dq", -1e6), (JointState, "q_command", 100.0), (JointCommand, "q", 1e6),
])
def test_finite_values_no_robot_or_person_has_are_refused(message: type[Message], field: str, value: float) -> None:
    """Finite garbage (1e300 m) would overflow the safety layer's distances into NaN rows: refused
    when decoded, naming the field, like NaN."""
    valid = {
        HumanState: lambda: HumanState(stamp=1.0, keypoints=np.zeros((15, 3)), keypoint_valid=np.ones(15, bool),
                                       theta=np.zeros(8), theta_valid=np.ones(8, bool), capsules=np.zeros((7, 2, 3)),
                                       capsule_radii=np.full(7, 0.05), capsule_valid=np.ones(7, bool),
                                       capsule_velocities=np.zeros((7, 2, 3))),
        JointState: lambda: JointState(stamp=1.0, q=np.zeros(8), dq=np.zeros(8), q_command=np.zeros(8)),
        JointCommand: lambda: JointCommand(stamp=1.0, q=np.zeros(8), dq=np.zeros(8)),
    }[message]()
    fields = valid.model_dump()
    array = np.array(fields[field], dtype=float)
    array.flat[1] = value
    with pytest.raises(ValidationError, match=f"{field}[\\s\\S]*magnitude above"):
        message(**{**fields, field: array})
    with pytest.raises(CodecError):
        decode(encode(valid.model_copy(update={field: array})))
