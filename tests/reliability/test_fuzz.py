"""Bad input, a test per check: hostile messages never crash a service, are all
counted, and never reach the QP; glitching keypoints leave the robot safe.

Everything runs the real code, in this process, with no mocks:

``fuzz_codec``
    :func:`shared.codec.decode` of every message type against payloads built to be refused
    (:data:`BAD_KINDS`: random bytes, truncations, oversized payloads, a wrong schema name or
    version, wrong shapes and types, NaN/Inf in arrays and scalars, a HumanState in another frame,
    out-of-range integers, deep nesting, unknown or missing fields, another message type), valid
    payloads with random bytes flipped, and valid payloads. A bad payload raises a
    :class:`~shared.codec.CodecError` (the expected subclass where the kind implies one); a flipped
    one either raises one or decodes to a message that encodes and decodes again unchanged; a valid
    one round-trips byte for byte; no other exception ever escapes.
``fuzz_<service>_subscribers``
    every subscriber of every service (safety: human state, joint state, config; executor: command,
    human state; perception: config; config API: safety status, human state), each service on its
    own Zenoh session on 127.0.0.1 fed by a second session through :meth:`shared.bus.Bus.put_raw`,
    in bursts that mix those bad payloads with valid messages from a few sources, their replays and
    out-of-order copies (seq and stamp not newer than one already accepted from the source) and
    restarted publishers (seq from 0 again with a newer stamp). Every burst ends with a new valid
    message; Zenoh delivers one session's samples in order, so once the service holds (or has
    applied) that message, the whole burst has arrived. Then the service's refusal counters (the
    bus's ``dropped`` and ``callback_errors``, the service's own rejections) must have grown by
    exactly the number of bad and replayed payloads of the burst, the service must hold exactly the
    burst's last valid message, and the control tick, run all along, must have produced finite
    commands from finite QP inputs (u_ref, barrier rows) with no exception.
``fuzz_keypoint_glitches``
    scripted people (:mod:`services.perception.scenarios`) whose keypoints jump 1 m for fewer frames
    than the point filter takes to re-anchor (``reacquire_frames``: staying longer is a real move),
    vanish (NaN) or come with zero confidence, through perception → retargeting → CBF-QP → MuJoCo in
    lockstep (:func:`safemimic.evaluate.episode.run_episode`, the services' code): every q_cbf
    finite, every step within u_max·Δt (a protective stop's settling step, which first brings q_cbf
    to the robot's joints, within 2 u_max·Δt), and never a step in which the robot's own motion took it
    deeper than −1 mm into the *true* person (:func:`robot_deepening`). A person who moves into the
    robot while unseen can end up inside it whatever the robot does (it stops and holds the last
    capsules it saw: ``safety.lost_human_hold_s``); the robot must never be the one that closes in.
    The min h the filter saw and the true one are reported.
``fuzz_messages``
    the number of hostile messages sent in all (≥ 100,000 in the full run).
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import logging
import math
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

import msgpack
import numpy as np
import pytest

from safemimic.launch import free_port
from services.config_api.link import BusLink
from safemimic.evaluate.episode import MODES, run_episode
from safemimic.evaluate.evaluation import true_person_of
from safemimic.evaluate.person import perceive
from safemimic.evaluate.source import EvaluationInput, open_input
from services.safety.kinematics import RobotKinematics
from shared.robot_spec import configured_robot_spec
from services.executor.service import ExecutorService
from services.perception.service import PerceptionService
from services.perception.sources import open_source
from services.safety.filter import VIOLATION_TOL
from services.safety.assembly import build_pipeline
from services.safety.human_memory import external_capsules
from services.safety.service import SafetyService
from shared.bus import TOPICS, Bus
from shared.codec import (
    MAX_MESSAGE_BYTES,
    CodecError,
    InvalidMessage,
    MessageTooLarge,
    SchemaVersionMismatch,
    UnknownSchema,
    decode,
    encode,
)
from shared.config import BusConfig, StackConfig, load_config
from shared.messages import MESSAGE_TYPES, ConfigUpdate, HumanState, Message
from tests.reliability.check import Check, CheckResult
from tests.support.bus import BusRecorder, await_route
from tests.support.messages import random_message

#: Payload kinds that every decoder must refuse; ``wrong_frame`` applies to HumanState only and
#: ``invalid_config`` (a well-formed ConfigUpdate whose configuration does not validate) to the
#: config subscribers only, which refuse it themselves.
BAD_KINDS = (
    "random_bytes", "truncated", "oversized", "wrong_schema", "wrong_version", "wrong_shape", "nonfinite",
    "wrong_type", "huge_int", "nested_junk", "extra_field", "missing_field", "other_message", "wrong_frame",
)
#: The CodecError subclass a bad kind must raise, where the kind implies one.
EXPECTED_ERROR: dict[str, type[CodecError]] = {
    "oversized": MessageTooLarge,
    "wrong_version": SchemaVersionMismatch,
    "other_message": UnknownSchema,
    "wrong_shape": InvalidMessage,
    "nonfinite": InvalidMessage,
    "wrong_frame": InvalidMessage,
    "wrong_type": InvalidMessage,
    "extra_field": InvalidMessage,
    "missing_field": InvalidMessage,
}
#: Publishers the subscriber streams impersonate (ordering is tracked per source).
SOURCES = ("perception", "fuzz-a", "fuzz-b")
#: The source of bad payloads: a well-formed one refused by the service itself (``invalid_config``)
#: is still new for the bus's ordering, and must not move the other sources' seq and stamp.
BAD_SOURCE = "bad-input"
#: Shares of a subscriber burst: new valid messages, restarted publishers, replays (the rest is bad).
VALID_SHARE, RESTART_SHARE, REPLAY_SHARE = 0.3, 0.03, 0.15
#: How long a burst may take to arrive and be counted (s) before the check reports it.
SETTLE_TIMEOUT_S = 20.0
#: Zenoh's receive limit of the services' sessions here (the deployed one equals the codec's limit).
#: Zenoh drops a share of the payloads above its limit silently (measured: ≈ 1–3 % of 0.26–3 MB
#: payloads over loopback, the rest passes), so with this headroom every oversized payload of the
#: fuzz (up to twice the codec's limit) reaches the decoder and must be counted there.
TRANSPORT_LIMIT_BYTES = 4 * MAX_MESSAGE_BYTES
#: Problems kept per check (the figures stay readable when something fails everywhere).
_KEPT = 5
#: Probability per frame that a glitch of each kind starts, and the longest vanish/zero-confidence run (frames).
GLITCH_RATE = {"jump": 0.06, "vanish": 0.04, "zero_confidence": 0.04}
GLITCH_MAX_FRAMES = 20
JUMP_M = 1.0


@dataclass(frozen=True)
class Budget:
    """How much each check does: the full run (``make reliability``) or the quick one (``make test``)."""

    codec: int  # payloads decoded directly
    per_target: dict[str, int]  # payloads sent to each subscriber
    burst: int  # payloads per burst
    scenarios: tuple[str, ...]  # glitching people
    seconds: float | None  # of each scenario (None: one period)


_TARGET_NAMES = (
    "safety human/state", "safety robot/joint_state", "safety config", "executor robot/command",
    "executor human/state", "perception config", "config_api safety/status", "config_api human/state",
)
FULL = Budget(
    codec=60_000,
    per_target=dict(zip(_TARGET_NAMES, (12_000, 6_000, 3_000, 6_000, 4_000, 2_000, 5_000, 4_000), strict=True)),
    burst=400,
    scenarios=("side-by-side-arm-raise", "reach-forward", "cross-arm-reach"),
    seconds=None,
)
QUICK = Budget(
    codec=2_400,
    per_target=dict(zip(_TARGET_NAMES, (500, 250, 150, 250, 150, 100, 150, 150), strict=True)),
    burst=125,
    scenarios=("side-by-side-arm-raise",),
    seconds=None,
)
#: Messages the full run must send in all (the issue's figure).
REQUIRED_MESSAGES = 100_000


# ------------------------------------------------------------------------------------- payloads
def _wire(message: Message) -> dict[str, Any]:
    """The msgpack map of an encoded message (arrays stay opaque extension blobs)."""
    return msgpack.unpackb(encode(message), raw=False)


def _pack(payload: Any) -> bytes:
    return msgpack.packb(payload, use_bin_type=True)


class Hostile:
    """Seeded factory of valid messages and of payloads that every decoder must refuse.

    Bad payloads are valid messages spoiled one way (:data:`BAD_KINDS`): attributes replaced after
    validation (``encode`` does not validate again) or the encoded msgpack map edited.
    """

    def __init__(self, seed: int, config: dict[str, Any]) -> None:
        self.rng = np.random.default_rng(seed)
        self.config = config  # a stack configuration (JSON) with "safety" and "human" sections

    def pick(self, options: Any) -> Any:
        """One of ``options`` (a sequence), uniformly."""
        return options[int(self.rng.integers(len(options)))]

    # valid -----------------------------------------------------------------------------------
    def message(self, cls: type[Message], stamp: float = 0.0, seq: int = 0, source: str = "") -> Message:
        """A random valid message of ``cls`` (a ConfigUpdate carries :meth:`valid_config`)."""
        return random_message(cls, self.rng, self.valid_config, stamp=stamp, seq=seq, source=source)

    def valid_config(self) -> dict[str, Any]:
        """The base configuration with parameters every service applies in place changed at random
        (valid for a subscriber if the base configuration is)."""
        r = self.rng
        config = {**self.config, "safety": {**self.config["safety"]}, "human": {**self.config["human"]}}
        config["safety"].update(gamma=float(r.uniform(5, 15)), phi=float(r.uniform(0.01, 0.05)))
        config["human"]["torso_radius"] = float(r.uniform(0.1, 0.2))
        return config

    def invalid_config(self) -> dict[str, Any]:
        """The base configuration with one field out of range, of a wrong type, or unknown."""
        config = {**self.config, "safety": {**self.config["safety"]}}
        key, value = self.pick([("gamma", -1.0), ("gamma", 1e9), ("phi", "wide"), ("u_max", [1.0] * 3),
                                ("rate_hz", 0.0), ("no_such_field", 1)])
        config["safety"][key] = value
        return config

    # bad -------------------------------------------------------------------------------------
    def bad(self, cls: type[Message], kind: str) -> bytes:
        """A payload of ``kind`` (:data:`BAD_KINDS` or ``invalid_config``) spoiling a ``cls`` message."""
        r = self.rng
        base = self.message(cls, stamp=float(r.uniform(0, 1e4)), seq=int(r.integers(0, 2**31)), source=BAD_SOURCE)
        fields = [name for name in type(base).model_fields if name != "schema_"]
        if kind == "random_bytes":
            return self.pick([b"", b"\x8f", b"\xde\x00\x10", b"\x81\xa6schema"]) + r.bytes(int(r.integers(0, 700)))
        if kind == "truncated":
            data = encode(base)
            return data[: int(r.integers(0, len(data)))]
        if kind == "oversized":
            payload = _wire(base)
            payload[self.pick(fields)] = bytes(int(r.integers(MAX_MESSAGE_BYTES, 2 * MAX_MESSAGE_BYTES)))
            return _pack(payload)
        if kind == "wrong_schema":
            payload = _wire(base)
            names = [n for n in MESSAGE_TYPES if n != cls.SCHEMA_NAME]
            payload["schema"] = self.pick([
                {"name": self.pick(["", "Message", cls.SCHEMA_NAME.lower(), cls.SCHEMA_NAME + "\x00", "x" * 70]), "version": 1},
                {"name": self.pick(names), "version": 1}, {"version": 1}, {"name": 7, "version": 1},
                [cls.SCHEMA_NAME, 1], cls.SCHEMA_NAME, None,
            ])
            if r.random() < 0.2:
                del payload["schema"]
            return _pack(payload)
        if kind == "wrong_version":
            payload = _wire(base)
            wrong = [0, cls.SCHEMA_VERSION - 1 or 2, cls.SCHEMA_VERSION + 1, -1, 99, 2**40, "1", None, [1], {"v": 1}]
            payload["schema"] = {"name": cls.SCHEMA_NAME, "version": self.pick(wrong)}
            return _pack(payload)
        if kind == "wrong_shape":  # of an array or a scalar (pydantic takes an empty array for an empty list)
            name = self.pick([n for n in fields if not isinstance(getattr(base, n), (dict, list))])
            value = getattr(base, name)
            shape = value.shape if isinstance(value, np.ndarray) else ()
            wrong = self.pick([(*shape[:-1], shape[-1] + 1) if shape else (3,), shape[::-1] + (2,), (0,), (2, *shape)])
            return self._replaced(base, name, r.normal(size=wrong))
        if kind == "nonfinite":
            return self._nonfinite(base)
        if kind == "wrong_type":
            name = self.pick(fields)
            return self._replaced(base, name, self._wrong_value(getattr(base, name)))
        if kind == "huge_int":
            return self._replaced(base, "seq", self.pick([2**63, 2**64 - 1, -1, -(2**63)]))
        if kind == "nested_junk":
            payload = _wire(base)
            name = self.pick([n for n in fields if not isinstance(getattr(base, n), (dict, list))])
            depth = int(r.integers(2, 3000))
            marker = b"\x00\x00\x00\x00\xff"  # a packed map value to splice the nesting into
            payload[name] = marker
            packed = _pack(payload)
            return packed.replace(b"\xc4\x05" + marker, b"\x91" * depth + self.pick([b"\xc0", b"\xa1x", b"\x80", b"\xcb" + bytes(8)]))
        if kind == "extra_field":
            payload = _wire(base)
            payload[self.pick(["extra", "frame", "schema_version", "q_cbf", "x" * 40])] = self.pick([1, None, "x", [1.0], {"a": 1}])
            return _pack(payload)
        if kind == "missing_field":
            payload = _wire(base)
            del payload[self.pick([n for n, f in cls.model_fields.items() if f.is_required()])]
            return _pack(payload)
        if kind == "other_message":
            return encode(self.message(self.pick([c for c in MESSAGE_TYPES.values() if c is not cls]), base.stamp, base.seq, base.source))
        if kind == "wrong_frame":
            return self._replaced(base, "frame_id", self.pick(["camera", "world", "", "Robot", "robot ", "map"]))
        if kind == "invalid_config":
            return self._replaced(base, "config", self.invalid_config())
        raise ValueError(f"unknown payload kind {kind!r}")

    def kinds(self, cls: type[Message]) -> tuple[str, ...]:
        """The bad kinds that apply to ``cls``."""
        return tuple(k for k in BAD_KINDS if k != "wrong_frame" or cls is HumanState)

    def mutated(self, cls: type[Message]) -> bytes:
        """A valid encoding with one to eight bytes flipped, overwritten, inserted or deleted."""
        r = self.rng
        data = bytearray(encode(self.message(cls, stamp=float(r.uniform(0, 1e4)), seq=int(r.integers(0, 2**31)))))
        for _ in range(int(r.integers(1, 9))):
            i = int(r.integers(len(data)))
            action = int(r.integers(4))
            if action == 0:
                data[i] ^= 1 << int(r.integers(8))
            elif action == 1:
                data[i] = int(r.integers(256))
            elif action == 2:
                data[i:i] = r.bytes(int(r.integers(1, 5)))
            elif len(data) > 1:
                del data[i]
        return bytes(data)

    def _replaced(self, base: Message, name: str, value: Any) -> bytes:
        spoiled = base.model_copy()
        setattr(spoiled, name, value)  # no validation on assignment: the receiver must catch it
        return encode(spoiled)

    def _nonfinite(self, base: Message) -> bytes:
        """NaN or ±Inf in one float: an array element (float64 or float32), a scalar, or deep in a config."""
        bad = self.pick([math.nan, math.inf, -math.inf])
        floats = [n for n, v in base if isinstance(v, float) or (isinstance(v, np.ndarray) and v.dtype.kind == "f")]
        if isinstance(base, ConfigUpdate) and self.rng.random() < 0.7:
            config = {**base.config, "safety": {**base.config["safety"], "gamma": bad}}
            return self._replaced(base, "config", config)
        name = self.pick(floats)
        value = getattr(base, name)
        if isinstance(value, np.ndarray):
            value = value.astype(self.pick([np.float64, np.float32]))
            value.flat[int(self.rng.integers(value.size))] = bad
        else:
            value = bad
        return self._replaced(base, name, value)

    def _wrong_value(self, value: Any) -> Any:
        """A value of a type no field of this kind accepts (pydantic's lax coercions avoided:
        no numeric strings, bytes or bools)."""
        if isinstance(value, (dict, list)):
            return self.pick(["text", 7.5, [["nested"]]] if isinstance(value, dict) else ["text", 7.5, {"k": 1}])
        if isinstance(value, str):
            return self.pick([{"k": 1}, [1, 2], 7])
        return self.pick(["not a number", {"k": 1}, [["x"]]])


# ---------------------------------------------------------------------------------- codec check
def fuzz_codec(n: int, seed: int, config: dict[str, Any]) -> CheckResult:
    """Decode ``n`` hostile, flipped and valid payloads spread over every message type (see module
    doc); ConfigUpdates carry ``config`` (a part of a stack configuration keeps this fast)."""
    hostile = Hostile(seed, config)
    kinds = {cls: (*hostile.kinds(cls), "mutated", "valid") for cls in MESSAGE_TYPES.values()}
    per_kind: Counter[str] = Counter()
    errors: Counter[str] = Counter()
    problems: list[str] = []
    crashes = accepted_bad = wrong_error = unstable = 0
    started = time.monotonic()
    for i in range(n):
        cls = list(MESSAGE_TYPES.values())[i % len(MESSAGE_TYPES)]
        kind = kinds[cls][(i // len(MESSAGE_TYPES)) % len(kinds[cls])]
        per_kind[kind] += 1
        valid = hostile.message(cls, stamp=float(i), seq=i, source="codec") if kind == "valid" else None
        data = encode(valid) if valid is not None else hostile.mutated(cls) if kind == "mutated" else hostile.bad(cls, kind)
        try:
            message = decode(data, cls)
        except CodecError as exc:
            errors[type(exc).__name__] += 1
            if kind == "valid":
                problems.append(f"valid {cls.__name__} refused: {exc}")
            elif kind in EXPECTED_ERROR and not isinstance(exc, EXPECTED_ERROR[kind]):
                wrong_error += 1
                problems.append(f"{kind} {cls.__name__}: {type(exc).__name__} instead of {EXPECTED_ERROR[kind].__name__}: {exc}")
            continue
        except Exception as exc:  # anything else escaping the codec is a crash of the subscriber
            crashes += 1
            problems.append(f"{kind} {cls.__name__}: {type(exc).__name__}: {exc}")
            continue
        errors["decoded"] += 1
        if kind in kinds[cls][:-2]:
            accepted_bad += 1
            problems.append(f"{kind} {cls.__name__} accepted: {data[:80]!r}")
        elif encode(message) != (data if kind == "valid" else encode(decode(encode(message), cls))):
            unstable += 1
            problems.append(f"{kind} {cls.__name__} does not round-trip")
    return CheckResult("fuzz_codec", crashes == accepted_bad == wrong_error == unstable == 0 and not problems, {
        "messages": n, "crashes": crashes, "bad_accepted": accepted_bad, "wrong_error_class": wrong_error,
        "not_round_tripping": unstable, "per_kind": dict(per_kind), "outcomes": dict(errors),
        "seconds": round(time.monotonic() - started, 1), "problems": problems[:_KEPT],
    })


# --------------------------------------------------------------------------- subscriber streams
@dataclass
class Burst:
    """Payloads for one subscriber, in sending order; the last one is a new valid message."""

    payloads: list[bytes]
    refused: int  # bad or replayed: the service must refuse and count each
    replayed: int
    accepted: int
    last: Message
    kinds: Counter[str]


@dataclass
class _Heard:
    seq: int
    stamp: float
    payload: bytes


class Stream:
    """Messages for one topic from :data:`SOURCES`: new ones (seq and stamp advancing, with gaps),
    restarts (seq from 0, newer stamp), replays (an exact copy of a source's last accepted message,
    or an older seq and stamp with new content), and bad payloads of every kind that applies.

    A replay is only sent for a source already accepted earlier in the same burst, well within
    :data:`shared.bus.RESTART_SILENCE_S`, so the subscriber cannot take it for a restart.
    """

    def __init__(self, hostile: Hostile, cls: type[Message], kinds: tuple[str, ...],
                 sources: tuple[str, ...] = SOURCES) -> None:
        self.hostile = hostile
        self.cls = cls
        self.kinds = kinds
        self.sources = sources
        self.clock = 1000.0
        self.heard: dict[str, _Heard] = {}

    def _valid(self, source: str, seq: int) -> tuple[Message, bytes]:
        self.clock += 0.001
        message = self.hostile.message(self.cls, stamp=self.clock, seq=seq, source=source)
        if isinstance(message, ConfigUpdate):
            message.version = int(self.clock * 1000)  # increasing, so the newest applied is the last sent
        payload = encode(message)
        self.heard[source] = _Heard(seq, message.stamp, payload)
        return message, payload

    def burst(self, n: int) -> Burst:
        h, r = self.hostile, self.hostile.rng
        out = Burst([], 0, 0, 0, None, Counter())  # type: ignore[arg-type]
        in_burst: list[str] = []
        for _ in range(n - 1):
            u = r.random()
            source = h.pick(self.sources)
            if u < VALID_SHARE + RESTART_SHARE:
                restart = u >= VALID_SHARE and source in self.heard
                last = self.heard.get(source)
                seq = int(r.integers(0, 3)) if restart or last is None else last.seq + int(r.integers(1, 4))
                _, payload = self._valid(source, seq)
                out.accepted += 1
                out.kinds["restart" if restart else "valid"] += 1
                in_burst.append(source)
            elif u < VALID_SHARE + RESTART_SHARE + REPLAY_SHARE and in_burst:
                source = h.pick(in_burst)
                last = self.heard[source]
                if r.random() < 0.5:
                    payload = last.payload
                else:
                    payload = encode(h.message(self.cls, stamp=last.stamp - float(r.uniform(0, 5)),
                                               seq=int(r.integers(0, last.seq + 1)), source=source))
                out.replayed += 1
                out.refused += 1
                out.kinds["replayed"] += 1
            else:
                kind = h.pick(self.kinds)
                payload = h.bad(self.cls, kind)
                out.refused += 1
                out.kinds[kind] += 1
            out.payloads.append(payload)
        source = h.pick(self.sources)
        last = self.heard.get(source)
        out.last, payload = self._valid(source, 0 if last is None else last.seq + 1)
        out.payloads.append(payload)
        out.accepted += 1
        out.kinds["valid"] += 1
        return out


# ----------------------------------------------------------------------------- subscriber checks
@dataclass
class Target:
    """One subscriber under test.

    ``refused()``: the service's count of refused messages on the topic so far; ``accepted()``: of
    valid ones taken in (None where the service keeps none); ``holds(message)``: whether the service
    now holds or has applied ``message``; ``tick()``: one step of the service, returning problems.
    ``superseded()``: for a :class:`~shared.bus.Newest` input (decoded when the tick reads it, the
    older samples of one read superseded unseen), whose payloads are therefore sent one at a time,
    each read by a tick before the next, so every one is decoded: none may be superseded.
    """

    name: str
    topic: str
    refused: Callable[[], int]
    holds: Callable[[Message], bool]
    tick: Callable[[], list[str]]
    accepted: Callable[[], int] | None = None
    superseded: Callable[[], int] | None = None
    sources: tuple[str, ...] = SOURCES


@dataclass
class TargetOutcome:
    """What one subscriber was sent and what it counted."""

    sent: int = 0
    accepted_expected: int = 0
    refused_expected: int = 0
    refused_counted: int = 0
    accepted_counted: int | None = None
    replayed: int = 0
    superseded: int = 0
    ticks: int = 0
    kinds: Counter[str] = field(default_factory=Counter)
    problems: list[str] = field(default_factory=list)

    def figures(self) -> dict[str, Any]:
        return {
            "sent": self.sent, "valid": self.accepted_expected, "refused_expected": self.refused_expected,
            "refused_counted": self.refused_counted, "accepted_counted": self.accepted_counted,
            "replayed": self.replayed, "superseded": self.superseded, "ticks": self.ticks, "kinds": dict(self.kinds),
        }


def fuzz_target(target: Target, stream: Stream, injector: Bus, n: int, burst: int) -> TargetOutcome:
    """Send ``n`` payloads to ``target`` in bursts; after each, wait for it to settle and check the counts."""
    out = TargetOutcome()
    await_route(injector, target.topic)
    refused0 = target.refused()
    accepted0 = target.accepted() if target.accepted else 0
    superseded0 = target.superseded() if target.superseded else 0

    def read(sent: int) -> bool:
        """A Newest input has read ``sent`` payloads (ticking it until then, bounded)."""
        assert target.accepted is not None
        deadline = time.monotonic() + SETTLE_TIMEOUT_S
        while (target.refused() - refused0 + target.accepted() - accepted0 + target.superseded() - superseded0) < sent:
            out.problems += _tick(target)
            out.ticks += 1
            if time.monotonic() > deadline:
                return False
        return True
    while out.sent < n:
        b = stream.burst(min(burst, n - out.sent))
        for i, payload in enumerate(b.payloads, start=1):
            injector.put_raw(target.topic, payload)
            if target.superseded is not None and not read(out.sent + i):
                out.problems.append(f"{target.name}: payload {out.sent + i} never read")
                break
        out.sent += len(b.payloads)
        out.refused_expected += b.refused
        out.accepted_expected += b.accepted
        out.replayed += b.replayed
        out.kinds.update(b.kinds)
        deadline = time.monotonic() + SETTLE_TIMEOUT_S
        while True:
            out.problems += _tick(target)
            out.ticks += 1
            if target.refused() - refused0 == out.refused_expected and target.holds(b.last):
                break
            if time.monotonic() > deadline:
                out.problems.append(
                    f"{target.name}: after {out.sent} payloads {target.refused() - refused0} refused "
                    f"(expected {out.refused_expected}), "
                    f"last valid message {'held' if target.holds(b.last) else 'not held'}"
                )
                break
            time.sleep(0.001)
        if out.problems:
            break
    out.refused_counted = target.refused() - refused0
    if target.superseded is not None:
        out.superseded = target.superseded() - superseded0
        if out.superseded:
            out.problems.append(f"{target.name}: {out.superseded} payloads superseded unread")
    if target.accepted is not None:
        out.accepted_counted = target.accepted() - accepted0
        if out.accepted_counted != out.accepted_expected:
            out.problems.append(f"{target.name}: {out.accepted_counted} valid messages taken, {out.accepted_expected} sent")
    return out


def _tick(target: Target) -> list[str]:
    try:
        return target.tick()
    except Exception as exc:  # a crash of the service's step: the fuzz's worst finding
        return [f"{target.name}: tick raised {type(exc).__name__}: {exc}"]


def _holds_latest(latest: Any) -> Callable[[Message], bool]:
    """``holds`` for a :class:`~shared.bus.Latest`: it holds exactly that message (same encoding)."""

    def holds(message: Message) -> bool:
        received = latest.get()
        return received is not None and encode(received.message) == encode(message)

    return holds


def _finite(**arrays: Any) -> list[str]:
    return [f"{name} not finite" for name, value in arrays.items() if not np.isfinite(np.asarray(value, dtype=float)).all()]


def _bus_refused(bus: Bus, topic: str) -> Callable[[], int]:
    """``refused`` for a service without counters of its own: its bus's drops and callback errors."""
    return lambda: bus.dropped[topic] + bus.callback_errors[topic]


@contextlib.contextmanager
def _endpoints(robot_id: str, service: str) -> Iterator[tuple[Bus, Bus]]:
    """The service's session listening on a free loopback port, and the injector's connected to it."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    listen = BusConfig(mode="peer", listen=[endpoint], multicast_scouting=False, max_message_bytes=TRANSPORT_LIMIT_BYTES)
    with Bus(listen, robot_id, service) as bus, \
            Bus(BusConfig(mode="peer", connect=[endpoint], multicast_scouting=False), robot_id, "fuzz") as injector:
        yield bus, injector


def _stack(robot_id: str) -> StackConfig:
    return load_config(environ={}, overrides={"robot_id": robot_id, "bus": {"multicast_scouting": False}})


def _service_result(name: str, outcomes: dict[str, TargetOutcome], extra: list[str], figures: dict[str, Any]) -> CheckResult:
    problems = [p for o in outcomes.values() for p in o.problems] + extra
    return CheckResult(name, not problems, {
        "messages": sum(o.sent for o in outcomes.values()), **figures,
        "subscribers": {topic: o.figures() for topic, o in outcomes.items()}, "problems": problems[:_KEPT],
    })


def _run_targets(targets: list[Target], hostile: Hostile, injector: Bus, budget: Budget) -> dict[str, TargetOutcome]:
    outcomes: dict[str, TargetOutcome] = {}
    for target in targets:
        cls = TOPICS[target.topic]
        kinds = (*hostile.kinds(cls), *(("invalid_config",) * 3 if cls is ConfigUpdate else ()))
        outcomes[target.topic] = fuzz_target(target, Stream(hostile, cls, kinds, target.sources), injector,
                                             budget.per_target[target.name], budget.burst)
    return outcomes


def fuzz_safety(budget: Budget, hostile: Hostile) -> CheckResult:
    """The safety service's human state, joint state and config subscribers, its tick run throughout."""
    robot_id = f"fuzzsafety{free_port()}"
    with _endpoints(robot_id, "safety") as (bus, injector):
        commands = BusRecorder(injector, ("robot/command",))
        with SafetyService(_stack(robot_id), bus=bus) as svc:

            def refused(topic: str) -> Callable[[], int]:
                return lambda: svc.dropped().get(topic, 0)

            def tick() -> list[str]:
                result = svc.tick()
                rows = result.rows
                return _finite(q_cbf=result.q_cbf, u=result.u, u_ref=result.u_ref, A=rows.A, b=rows.b,
                               h=rows.h[rows.enabled])

            def config_applied(message: Message) -> bool:
                assert isinstance(message, ConfigUpdate)
                return svc.config_version == message.version and svc.pipeline.filter.params.gamma == message.config["safety"]["gamma"]

            targets = [
                Target("safety human/state", "human/state", refused("human/state"), _holds_latest(svc.human), tick,
                       lambda: svc.human.count, lambda: svc.bus.superseded["human/state"]),
                Target("safety robot/joint_state", "robot/joint_state", refused("robot/joint_state"),
                       _holds_latest(svc.joint_state), tick, lambda: svc.joint_state.count),
                Target("safety config", "config", refused("config"), config_applied, tick),
            ]
            outcomes = _run_targets(targets, hostile, injector, budget)
            extra = _command_problems(commands, svc)
            figures = {"ticks": svc.ticks, "nonfinite_holds": svc.nonfinite_holds, "commands_observed": commands.count("robot/command"),
                       "status_dropped": svc.dropped()}
            if svc.nonfinite_holds:
                extra.append(f"{svc.nonfinite_holds} non-finite commands replaced")
    return _service_result("fuzz_safety_subscribers", outcomes, extra, figures)


def _command_problems(commands: BusRecorder, svc: SafetyService) -> list[str]:
    """Every command ``commands`` (the injector's view of ``robot/command``) saw decoded and finite (a
    non-finite one would be refused by its decoder and show in its drop count), and the newest one
    built from the held human state."""
    held = svc.human.get()
    deadline = time.monotonic() + 5.0
    while time.monotonic() < deadline and not ((last := commands.last("robot/command")) is not None and held is not None
                                               and last.human_seq == held.message.seq):
        svc.tick()
        time.sleep(0.005)
    last = commands.last("robot/command")
    out = [f"{n} commands refused by a receiver" for n in (commands.bus.dropped["robot/command"],) if n]
    if last is None:
        out.append("no command observed")
    elif held is None or (last.human_seq, last.human_stamp) != (held.message.seq, held.message.stamp):
        out.append("the newest command does not use the last valid human state")
    return out


def fuzz_executor(budget: Budget, hostile: Hostile) -> CheckResult:
    """The executor's command and human state subscribers, its MuJoCo tick run throughout."""
    robot_id = f"fuzzexec{free_port()}"
    with _endpoints(robot_id, "executor") as (bus, injector):
        with ExecutorService(_stack(robot_id), bus=bus) as svc:

            def refused(topic: str) -> Callable[[], int]:
                return lambda: svc.dropped().get(topic, 0)

            def tick() -> list[str]:
                svc.tick(time.monotonic())
                state = svc.executor.read_state()
                return _finite(q=state.q, dq=state.dq)

            targets = [
                # one commanding session: the executor refuses a second's commands by design (OneCommander)
                Target("executor robot/command", "robot/command", refused("robot/command"), _holds_latest(svc.command),
                       tick, lambda: svc.command.count, sources=("safety",)),
                Target("executor human/state", "human/state", refused("human/state"), _holds_latest(svc.human), tick,
                       lambda: svc.human.count),
            ]
            outcomes = _run_targets(targets, hostile, injector, budget)
            figures = {"ticks": svc.ticks, "commands_applied": svc.commands_applied, "human_updates": svc.human_updates,
                       "dropped": svc.dropped()}
    return _service_result("fuzz_executor_subscribers", outcomes, [], figures)


def fuzz_perception(budget: Budget, hostile: Hostile) -> CheckResult:
    """The perception service's config subscriber while it streams a looping scripted person."""
    robot_id = f"fuzzperc{free_port()}"
    conf = _stack(robot_id)
    conf = conf.model_copy(update={"perception": conf.perception.model_copy(update={"loop": True})})
    stop = threading.Event()
    with _endpoints(robot_id, "perception") as (bus, injector), PerceptionService(conf, open_source(conf.perception), bus) as svc:
        with contextlib.redirect_stdout(io.StringIO()):  # the service's JSON event lines
            runner = threading.Thread(target=svc.run, args=(stop,), daemon=True)
            runner.start()
            try:
                published = svc.published

                def tick() -> list[str]:
                    time.sleep(0.002)  # the service runs in its own thread: give it the GIL
                    problems = [] if runner.is_alive() else ["the perception service stopped"]
                    return problems + ([f"{svc.errors} frames failed"] if svc.errors else [])

                def applied(message: Message) -> bool:
                    assert isinstance(message, ConfigUpdate)
                    return svc.config_version == message.version

                bus_refused = _bus_refused(bus, "config")
                target = Target("perception config", "config", lambda: bus_refused() + svc.rejected_configs, applied, tick)
                outcomes = _run_targets([target], hostile, injector, budget)
            finally:
                stop.set()
                runner.join(10)
        extra = [] if svc.published > published else ["no human state published during the fuzz"]
        figures = {"published": svc.published, "errors": svc.errors, "rejected_configs": svc.rejected_configs,
                   "config_version": svc.config_version}
    return _service_result("fuzz_perception_subscribers", outcomes, extra, figures)


def fuzz_config_api(budget: Budget, hostile: Hostile) -> CheckResult:
    """The config API's Zenoh link: its safety status and human state subscribers."""
    robot_id = f"fuzzapi{free_port()}"
    with _endpoints(robot_id, "config_api") as (bus, injector):
        link = BusLink(bus, lambda: (0, hostile.config))
        targets = [
            Target("config_api safety/status", "safety/status", _bus_refused(bus, "safety/status"),
                   _holds_latest(link.status), lambda: [], lambda: link.status.count),
            Target("config_api human/state", "human/state", _bus_refused(bus, "human/state"),
                   _holds_latest(link.human), lambda: [], lambda: link.human.count),
        ]
        outcomes = _run_targets(targets, hostile, injector, budget)
        figures = {"highest_version_seen": link.highest_version_seen}
    return _service_result("fuzz_config_api_subscribers", outcomes, [], figures)


# ------------------------------------------------------------------------------ keypoint glitches
def glitched(frames: tuple, rng: np.random.Generator, jump_frames: int) -> tuple[list, Counter[str]]:
    """``frames`` with glitches (see :data:`GLITCH_RATE`): a 1 m jump of one point, one arm or the
    whole skeleton for 1..``jump_frames`` frames, points vanishing (NaN) or at zero confidence for
    1..:data:`GLITCH_MAX_FRAMES` frames. A jump starts only ``jump_frames`` + 1 frames after the
    previous one started, so no point is ever displaced for longer (longer is a real move to the
    point filter). Returns the frames and the glitches started per kind."""
    arms = ([3, 4, 5], [6, 7, 8])  # shoulder, elbow, wrist of each side (KEYPOINT_NAMES order)
    active: list[tuple[str, np.ndarray, int, np.ndarray]] = []
    started: Counter[str] = Counter()
    next_jump = 0
    out = []
    for i, frame in enumerate(frames):
        n = frame.xyz.shape[0]
        for kind, rate in GLITCH_RATE.items():
            if rng.random() < rate and (kind != "jump" or i >= next_jump):
                next_jump = i + jump_frames + 1 if kind == "jump" else next_jump
                which = rng.random()
                points = (np.array([rng.integers(n)]) if which < 0.6 else np.array(arms[int(rng.integers(2))])
                          if which < 0.85 else np.arange(n))
                longest = jump_frames if kind == "jump" else GLITCH_MAX_FRAMES
                offset = rng.normal(size=3)
                active.append((kind, points, int(rng.integers(1, longest + 1)), JUMP_M * offset / np.linalg.norm(offset)))
                started[kind] += 1
        xyz, conf = frame.xyz.copy(), frame.conf.copy()
        for kind, points, _, offset in active:
            if kind == "jump":
                xyz[points] += offset
            elif kind == "vanish":
                xyz[points] = np.nan
            else:
                conf[points] = 0.0
        active = [(k, p, left - 1, o) for k, p, left, o in active if left > 1]
        out.append(dataclasses.replace(frame, xyz=xyz, conf=conf))
    return out, started


def robot_deepening(conf: StackConfig, episode: Any, truth: Any) -> tuple[int, float]:
    """Steps in which the robot's own motion took it deeper into the *true* (unglitched) person.

    At step k the true person is ``truth``'s state for the frame the filter was using; the robot
    went from q_cbf[k−1] to q_cbf[k], or on a settling step (``episode.settled``: q_cbf first
    brought to where the robot's joints were measured, so the robot was there already) from
    q_cbf[k] − Δt u*[k]. A step counts when the true robot–human h after it is below
    −:data:`VIOLATION_TOL` and lower than before it (the person held still): the robot, not the
    person, closed in. Returns (such steps, lowest true h over the run, m).
    """
    dt = 1.0 / conf.safety.rate_hz
    pipeline = build_pipeline(conf)
    human_rows = ~pipeline.pairs.is_self
    deeper, lowest, frame = 0, math.inf, -2
    for k in range(1, len(episode.t)):
        if episode.human[k] < 0:
            continue
        if episode.human[k] != frame:
            frame = int(episode.human[k])
            pipeline.barrier.set_external(*external_capsules(truth.states[frame], pipeline.pairs.n_external, False))
        start = episode.q_cbf[k] - dt * episode.u[k] if episode.settled[k] else episode.q_cbf[k - 1]
        before = pipeline.filter.rows_at(start)
        after = pipeline.filter.rows_at(episode.q_cbf[k])
        rows = human_rows[: len(after.h)] & after.enabled
        if not rows.any():
            continue
        h_before, h_after = before.h[rows], after.h[rows]
        lowest = min(lowest, float(h_after.min()))
        deeper += int(((h_after < -VIOLATION_TOL) & (h_after < h_before - 1e-9)).any())
    return deeper, lowest


def _min_human_h(episode: Any) -> float | None:
    """The lowest h over the robot–human pairs of an episode (None: never a person)."""
    human_h = episode.h[:, ~episode.pairs.is_self]
    return float(np.nanmin(human_h)) if np.isfinite(human_h).any() else None


def fuzz_keypoint_glitches(budget: Budget, seed: int) -> CheckResult:
    """Glitching keypoints through perception and the safety filter in lockstep (see module doc)."""
    rng = np.random.default_rng(seed)
    runs: dict[str, dict[str, Any]] = {}
    problems: list[str] = []
    started = time.monotonic()
    for name in budget.scenarios:
        conf = load_config(environ={}, overrides={"perception": {"source": "scenario", "scenario": name, "realtime": False}})
        clean = open_input(conf, budget.seconds)
        frames, glitches = glitched(clean.frames, rng, conf.perception.point_filter.reacquire_frames - 1)
        track = perceive(conf, EvaluationInput(f"{clean.name} glitched", tuple(frames), clean.fps))
        kinematics = RobotKinematics(configured_robot_spec(conf))
        person = true_person_of(conf, clean, kinematics)
        episode = run_episode(conf, track, person, enforce=True, kinematics=kinematics)
        truth = perceive(conf, clean)
        baseline = run_episode(conf, truth, person, enforce=True, kinematics=kinematics)
        deeper, lowest_true_h = robot_deepening(conf, episode, truth)
        dt = 1.0 / conf.safety.rate_hz
        steps = np.abs(np.diff(episode.q_cbf, axis=0)) / (1.0 + episode.settled[1:, None])  # a settle: 2 steps
        rate_ratio = float((steps / (np.asarray(conf.safety.u_max) * dt)).max())
        min_h, min_h_clean = (_min_human_h(e) for e in (episode, baseline))
        finite = bool(np.isfinite(episode.q_cbf).all() and np.isfinite(episode.u).all())
        runs[name] = {
            "frames": len(frames), "steps": len(episode.t), "glitches": dict(glitches),
            "rejected_jumps": track.counters.rejected_jumps, "missing_points": track.counters.missing_points,
            "invalid_frames": track.counters.invalid_frames, "finite": finite, "max_step_over_u_max_dt": round(rate_ratio, 4),
            "min_h_human_m": min_h, "min_h_human_without_glitches_m": min_h_clean, "modes": dict(Counter(MODES[i].value for i in episode.mode)),
            "robot_human_contact_steps": int(episode.true_contact.sum()),
            "robot_deepening_steps": deeper, "min_true_h_m": lowest_true_h,
            "settling_steps": int(episode.settled.sum()),
        }
        if not finite:
            problems.append(f"{name}: non-finite q_cbf or u*")
        if rate_ratio > 1.0 + 1e-9:
            problems.append(f"{name}: a step moved {rate_ratio:.3f} × u_max·Δt")
        if deeper:
            problems.append(f"{name}: in {deeper} steps the robot moved deeper into the true person")
    return CheckResult("fuzz_keypoint_glitches", not problems, {
        "scenarios": runs, "seconds": round(time.monotonic() - started, 1), "problems": problems[:_KEPT],
    })


# -------------------------------------------------------------------------------------------- run
@contextlib.contextmanager
def _quiet_services() -> Iterator[None]:
    """Silence the services' per-message warnings (thousands of rejected configs) while fuzzing:
    every refusal is counted and checked instead."""
    loggers = [logging.getLogger(name) for name in ("safemimic", "shared", "services")]
    levels = [logger.level for logger in loggers]
    for logger in loggers:
        logger.setLevel(logging.CRITICAL)
    try:
        yield
    finally:
        for logger, level in zip(loggers, levels, strict=True):
            logger.setLevel(level)


class Fuzzed:
    """The fuzz checks of one budget, each run once when a test first asks for its result."""

    def __init__(self, budget: Budget) -> None:
        self.budget = budget
        self._config = load_config(environ={}).model_dump(mode="json")
        self._results: dict[str, CheckResult] = {}

    def _run(self, name: str) -> CheckResult:
        budget, config = self.budget, self._config
        if name == "fuzz_codec":
            return fuzz_codec(budget.codec, seed=1, config={section: config[section] for section in ("safety", "human")})
        if name == "fuzz_keypoint_glitches":
            return fuzz_keypoint_glitches(budget, seed=6)
        fuzz, seed = SUBSCRIBER_CHECKS[name]
        with _quiet_services():
            return fuzz(budget, Hostile(seed, config))

    def result(self, name: str) -> CheckResult:
        if name not in self._results:
            self._results[name] = self._run(name)
        return self._results[name]

    def messages(self) -> CheckResult:
        """``fuzz_messages``: the hostile messages sent by the codec and subscriber checks, against the
        budget's (the full run: at least :data:`REQUIRED_MESSAGES`)."""
        sent = sum(self.result(name).figures["messages"] for name in ("fuzz_codec", *SUBSCRIBER_CHECKS))
        quick = self.budget is QUICK
        required = sum(self.budget.per_target.values()) + self.budget.codec if quick else REQUIRED_MESSAGES
        return CheckResult("fuzz_messages", sent >= required, {"messages": sent, "required": required})


#: check name → (the check, its seed) for the services' subscribers.
SUBSCRIBER_CHECKS: dict[str, tuple[Callable[[Budget, Hostile], CheckResult], int]] = {
    "fuzz_safety_subscribers": (fuzz_safety, 2),
    "fuzz_executor_subscribers": (fuzz_executor, 3),
    "fuzz_perception_subscribers": (fuzz_perception, 4),
    "fuzz_config_api_subscribers": (fuzz_config_api, 5),
}


@pytest.fixture(scope="module")
def fuzzed(long_run: bool) -> Fuzzed:
    """Full (≥ 100,000 messages, a few minutes) in the long run, quick (a few thousand, seconds) otherwise."""
    return Fuzzed(FULL if long_run else QUICK)


def test_fuzz_codec(fuzzed: Fuzzed, check: Check) -> None:
    check(fuzzed.result("fuzz_codec"))


@pytest.mark.integration
@pytest.mark.parametrize("name", SUBSCRIBER_CHECKS)
def test_fuzz_subscribers(name: str, fuzzed: Fuzzed, check: Check) -> None:
    check(fuzzed.result(name))


def test_fuzz_keypoint_glitches(fuzzed: Fuzzed, check: Check) -> None:
    check(fuzzed.result("fuzz_keypoint_glitches"))


@pytest.mark.integration
def test_fuzz_messages(fuzzed: Fuzzed, check: Check) -> None:
    check(fuzzed.messages())
