"""Message ↔ msgpack bytes (architecture §5, §11).

Wire format: a msgpack map ``{"schema": {"name", "version"}, <fields>...}``. numpy arrays travel
as msgpack extension type ``ND_EXT`` (a dtype code, the shape and the raw little-endian C-order
bytes), never as lists of floats. Decoding enforces a maximum size, a dtype
whitelist, strict map keys, and validation by the message model; whatever the bytes, it raises
only :class:`CodecError` (or a subclass).
"""

from __future__ import annotations

import functools
import math
import struct
from enum import Enum
from typing import Any, TypeVar

import msgpack
import numpy as np
from pydantic import ValidationError

from shared.errors import SafemimicError
from shared.messages import MESSAGE_TYPES, Message

ND_EXT = 1
#: Default upper bound of an encoded message (bytes); a HumanState is ≈ 1.1 kB.
MAX_MESSAGE_BYTES = 256 * 1024
#: dtype code (one byte on the wire) ↔ little-endian numpy dtype: the only dtypes accepted.
_DTYPES: tuple[np.dtype, ...] = tuple(np.dtype(d) for d in ("<f8", "<f4", "|b1", "|u1", "<i4", "<i8"))
_DTYPE_CODE = {d: i for i, d in enumerate(_DTYPES)}
_MAX_ARRAY_DIMS = 4
_HEADER = struct.Struct("<BB")
_DIMS = tuple(struct.Struct(f"<{n}I") for n in range(_MAX_ARRAY_DIMS + 1))

M = TypeVar("M", bound=Message)


class CodecError(SafemimicError):
    """Base of every decoding/encoding failure."""


class MessageTooLarge(CodecError):
    """The payload exceeds the maximum message size."""


class MalformedPayload(CodecError):
    """The bytes are not a well-formed safemimic msgpack message."""


class UnknownSchema(CodecError):
    """The schema name is not a known message type (or not the expected one)."""


class SchemaVersionMismatch(CodecError):
    """The schema name is known but the version is not the one this build speaks."""


class InvalidMessage(CodecError):
    """Well-formed, known schema, but the content fails validation (shape, NaN, range, ...)."""


@functools.lru_cache(maxsize=256)
def _array_header(dtype: np.dtype, shape: tuple[int, ...]) -> tuple[bytes, np.dtype]:
    """Wire header ``[dtype code u8][ndim u8][shape u32 × ndim]`` and the little-endian dtype."""
    wire_dtype = dtype.newbyteorder("<") if dtype.byteorder == ">" else dtype
    code = _DTYPE_CODE.get(wire_dtype)
    if code is None or len(shape) > _MAX_ARRAY_DIMS:
        raise TypeError(f"cannot encode array of dtype {dtype} and {len(shape)} dims")
    return _HEADER.pack(code, len(shape)) + _DIMS[len(shape)].pack(*shape), _DTYPES[code]


def _array_bytes(array: np.ndarray) -> bytes:
    """ND_EXT payload of an array: wire header + raw little-endian C-order bytes."""
    header, wire_dtype = _array_header(array.dtype, array.shape)
    if array.dtype is not wire_dtype:  # big-endian (or an equal dtype object: no copy then)
        array = np.ascontiguousarray(array, dtype=wire_dtype)
    return header + array.tobytes()  # tobytes() is C order whatever the strides


def _default(obj: Any) -> Any:
    """msgpack hook: ndarray → ExtType(ND_EXT, header + raw little-endian C-order bytes)."""
    if isinstance(obj, np.ndarray):
        return msgpack.ExtType(ND_EXT, _array_bytes(obj))
    if isinstance(obj, np.generic):
        return obj.item()
    raise TypeError(f"cannot encode {type(obj).__name__}")


@functools.lru_cache(maxsize=256)
def _parse_header(header: bytes) -> tuple[np.dtype, tuple[int, ...], int]:
    """(dtype, shape, payload byte count) of a wire header; :class:`MalformedPayload` if invalid."""
    dtype_code, ndim = _HEADER.unpack_from(header)
    if dtype_code >= len(_DTYPES) or ndim > _MAX_ARRAY_DIMS or len(header) != _HEADER.size + _DIMS[ndim].size:
        raise MalformedPayload(f"array dtype code {dtype_code} or ndim {ndim} not allowed")
    shape = _DIMS[ndim].unpack_from(header, _HEADER.size)
    dtype = _DTYPES[dtype_code]
    return dtype, shape, dtype.itemsize * math.prod(shape)


def _ext_hook(code: int, data: bytes) -> Any:
    """Inverse of :func:`_default`; the result is a read-only view on the received bytes."""
    if code != ND_EXT:
        raise MalformedPayload(f"unknown msgpack extension type {code}")
    if len(data) < _HEADER.size:
        raise MalformedPayload("array header truncated")
    offset = _HEADER.size + 4 * data[1]
    if len(data) < offset:
        raise MalformedPayload("array shape truncated")
    dtype, shape, nbytes = _parse_header(data[:offset])
    if len(data) - offset != nbytes:
        raise MalformedPayload("array byte count does not match dtype and shape")
    return np.ndarray(shape, dtype, data, offset)  # (shape, dtype, buffer, offset): keywords cost ~2× here


@functools.cache
def _wire_fields(cls: type[Message]) -> tuple[str, ...]:
    """Field names sent after ``schema`` (a validated model needs no second dump/validation pass)."""
    return tuple(name for name in cls.model_fields if name != "schema_")


def encode(message: Message) -> bytes:
    """Encode a validated message to msgpack bytes (fields as attributes, arrays as ND_EXT).

    Written entry by entry with one packer: the bytes ``msgpack.packb`` gives for the field dict
    with :func:`_default`, without building the dict or an ``ExtType`` per array.
    """
    fields = _wire_fields(type(message))
    packer = msgpack.Packer(default=_default, use_bin_type=True, autoreset=False)
    pack = packer.pack
    packer.pack_map_header(len(fields) + 1)
    pack("schema")
    pack({"name": message.SCHEMA_NAME, "version": message.SCHEMA_VERSION})
    for name in fields:
        pack(name)
        value = getattr(message, name)
        if type(value) is np.ndarray:
            packer.pack_ext_type(ND_EXT, _array_bytes(value))
        else:
            pack(value.value if isinstance(value, Enum) else value)
    data = packer.bytes()
    if len(data) > MAX_MESSAGE_BYTES:
        raise MessageTooLarge(f"{type(message).__name__} encodes to {len(data)} B > {MAX_MESSAGE_BYTES} B")
    return data


def decode(data: bytes | bytearray | memoryview, expected: type[M] | None = None, max_bytes: int = MAX_MESSAGE_BYTES) -> M:
    """Decode and validate bytes into a message (of type ``expected`` when given).

    Raises only :class:`CodecError` subclasses, whatever ``data`` holds.
    """
    if len(data) > max_bytes:
        raise MessageTooLarge(f"payload of {len(data)} B exceeds {max_bytes} B")
    try:
        payload = msgpack.unpackb(
            bytes(data),
            raw=False,
            strict_map_key=True,
            ext_hook=_ext_hook,
            max_str_len=max_bytes,
            max_bin_len=max_bytes,
            max_array_len=4096,
            max_map_len=1024,
            max_ext_len=max_bytes,
        )
    except CodecError:
        raise
    except Exception as exc:  # msgpack raises many types (ValueError, ExtraData, StackError, ...)
        raise MalformedPayload(f"not a msgpack message: {type(exc).__name__}: {exc}") from None
    if not isinstance(payload, dict):
        raise MalformedPayload(f"top level is {type(payload).__name__}, not a map")
    schema = payload.get("schema")
    if not isinstance(schema, dict) or not isinstance(schema.get("name"), str):
        raise MalformedPayload("missing or malformed 'schema'")
    cls = MESSAGE_TYPES.get(schema["name"])
    if cls is None:
        raise UnknownSchema(f"unknown message schema {schema['name'][:64]!r}")
    if expected is not None and cls is not expected:
        raise UnknownSchema(f"expected {expected.SCHEMA_NAME}, got {cls.SCHEMA_NAME}")
    if schema.get("version") != cls.SCHEMA_VERSION:
        raise SchemaVersionMismatch(
            f"{cls.SCHEMA_NAME} version {schema.get('version')!r} received, this build speaks v{cls.SCHEMA_VERSION}"
        )
    try:
        return cls.model_validate(payload)  # type: ignore[return-value]
    except ValidationError as exc:
        raise InvalidMessage(f"invalid {cls.SCHEMA_NAME}: {exc.error_count()} error(s): {_first_error(exc)}") from None
    except Exception as exc:  # a validator tripping on exotic input must still surface as a codec error
        raise InvalidMessage(f"invalid {cls.SCHEMA_NAME}: {type(exc).__name__}: {exc}") from None


def _first_error(exc: ValidationError) -> str:
    err = exc.errors(include_url=False)[0]
    return f"{'.'.join(str(p) for p in err['loc'])}: {err['msg']}"
