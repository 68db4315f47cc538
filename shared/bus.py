"""Typed pub/sub over Zenoh (DESIGN §1, §5, §11).

Key expressions: ``safemimic/{robot_id}/{topic}`` with the topics of :data:`TOPICS`, liveliness
tokens ``safemimic/{robot_id}/alive/{service}``. A payload that fails to decode or validate is
dropped and counted per topic; a subscriber callback that raises is counted and logged, never
propagated into Zenoh. Sessions, publishers and tokens are context managers / closed with the bus.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from typing import Generic, TypeVar

import zenoh

from shared.codec import CodecError, decode, encode
from shared.config import BusConfig, BusMode
from shared.messages import ConfigUpdate, HumanState, JointCommand, JointState, Message, SafetyStatus

log = logging.getLogger(__name__)
M = TypeVar("M", bound=Message)

#: topic (suffix after ``safemimic/{robot_id}/``) → message type carried on it.
TOPICS: dict[str, type[Message]] = {
    "human/state": HumanState,
    "robot/joint_state": JointState,
    "robot/command": JointCommand,
    "safety/status": SafetyStatus,
    "config": ConfigUpdate,
}
KEY_PREFIX = "safemimic"


def topic_key(robot_id: str, topic: str) -> str:
    """The Zenoh key expression of a topic for one robot."""
    return f"{KEY_PREFIX}/{robot_id}/{topic}"


def alive_key(robot_id: str, service: str) -> str:
    """The liveliness token key of a service."""
    return f"{KEY_PREFIX}/{robot_id}/alive/{service}"


def zenoh_config(bus: BusConfig) -> zenoh.Config:
    """A ``zenoh.Config`` from our bus settings: mode, endpoints, scouting, lease, message size."""
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(bus.mode.value))
    conf.insert_json5("connect/endpoints", json.dumps(bus.connect))
    conf.insert_json5("listen/endpoints", json.dumps(bus.listen))
    conf.insert_json5("scouting/multicast/enabled", json.dumps(bus.multicast_scouting))
    conf.insert_json5("transport/link/tx/lease", str(bus.lease_ms))
    conf.insert_json5("transport/link/rx/max_message_size", str(bus.max_message_bytes))
    return conf


def open_session(bus: BusConfig) -> zenoh.Session:
    """Open a Zenoh session (use as a context manager)."""
    return zenoh.open(zenoh_config(bus))


@dataclass
class Received(Generic[M]):
    """A message and the local monotonic time it arrived."""

    message: M
    received: float


class TypedPublisher(Generic[M]):
    """Publishes one message type on one topic, stamping ``seq`` and ``source``."""

    def __init__(self, publisher: zenoh.Publisher, message_type: type[M], source: str) -> None:
        self._publisher = publisher
        self._type = message_type
        self._source = source
        self._seq = 0

    def put(self, message: M) -> None:
        """Set seq (per publisher, from 0) and source, encode, publish."""
        if not isinstance(message, self._type):
            raise TypeError(f"this publisher carries {self._type.__name__}, not {type(message).__name__}")
        message.seq = self._seq
        message.source = message.source or self._source
        self._seq += 1
        self._publisher.put(encode(message))


class Latest(Generic[M]):
    """Thread-safe holder of the newest message received on a topic (zero-order hold)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._value: Received[M] | None = None
        self.count = 0
        self.updated = threading.Event()

    def set(self, message: M) -> None:
        with self._lock:
            self._value = Received(message, time.monotonic())
            self.count += 1
        self.updated.set()

    def get(self) -> Received[M] | None:
        with self._lock:
            return self._value


class Bus:
    """One Zenoh session for one service of one robot, with typed topics and counters.

    ``dropped[topic]`` counts payloads that failed to decode/validate; ``callback_errors[topic]``
    counts exceptions raised by user callbacks (logged, never propagated).
    """

    def __init__(self, bus: BusConfig, robot_id: str, service: str) -> None:
        self.robot_id = robot_id
        self.service = service
        self.dropped: Counter[str] = Counter()
        self.callback_errors: Counter[str] = Counter()
        self._session = open_session(bus)
        self._entities: list[object] = []

    # context manager -------------------------------------------------------------------------
    def __enter__(self) -> Bus:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Undeclare everything this bus declared and close the session (idempotent)."""
        for entity in reversed(self._entities):
            try:
                entity.undeclare()  # type: ignore[attr-defined]
            except Exception:  # already undeclared or session closing
                pass
        self._entities.clear()
        if not self._session.is_closed():
            self._session.close()

    @property
    def session(self) -> zenoh.Session:
        return self._session

    # pub/sub ---------------------------------------------------------------------------------
    def publisher(self, topic: str, robot_id: str | None = None) -> TypedPublisher[Message]:
        """A typed publisher on ``topic`` (a key of :data:`TOPICS`), of this or another robot."""
        message_type = _topic_type(topic)
        publisher = self._session.declare_publisher(
            topic_key(robot_id or self.robot_id, topic), congestion_control=zenoh.CongestionControl.DROP, express=True
        )
        self._entities.append(publisher)
        return TypedPublisher(publisher, message_type, self.service)

    def subscribe(
        self, topic: str, callback: Callable[[Message], None], robot_id: str | None = None
    ) -> zenoh.Subscriber:
        """Call ``callback(message)`` for every valid message on ``topic``; invalid ones are counted."""
        message_type = _topic_type(topic)

        def on_sample(sample: zenoh.Sample) -> None:
            try:
                message = decode(sample.payload.to_bytes(), message_type)
            except CodecError as exc:
                self.dropped[topic] += 1
                log.debug("dropped payload on %s: %s", topic, exc)
                return
            try:
                callback(message)
            except Exception:
                self.callback_errors[topic] += 1
                log.exception("callback on %s raised", topic)

        subscriber = self._session.declare_subscriber(topic_key(robot_id or self.robot_id, topic), on_sample)
        self._entities.append(subscriber)
        return subscriber

    def latest(self, topic: str) -> Latest[Message]:
        """Subscribe to ``topic`` and keep only the newest valid message."""
        holder: Latest[Message] = Latest()
        self.subscribe(topic, holder.set)
        return holder

    def put_raw(self, topic: str, payload: bytes) -> None:
        """Publish raw bytes on a topic (fault injection and tests only)."""
        self._session.put(topic_key(self.robot_id, topic), payload)

    # liveliness ------------------------------------------------------------------------------
    def declare_alive(self, service: str | None = None) -> zenoh.LivelinessToken:
        """Declare the token ``alive/{service}``; it disappears when this process or session dies."""
        token = self._session.liveliness().declare_token(alive_key(self.robot_id, service or self.service))
        self._entities.append(token)
        return token

    def watch_alive(self, callback: Callable[[str, bool], None]) -> zenoh.Subscriber:
        """Call ``callback(service, alive)`` for tokens present now and every later change."""
        prefix = alive_key(self.robot_id, "")

        def on_sample(sample: zenoh.Sample) -> None:
            service = str(sample.key_expr)[len(prefix) :]
            try:
                callback(service, sample.kind == zenoh.SampleKind.PUT)
            except Exception:
                self.callback_errors["alive"] += 1
                log.exception("liveliness callback raised")

        subscriber = self._session.liveliness().declare_subscriber(prefix + "*", on_sample, history=True)
        self._entities.append(subscriber)
        return subscriber

    def alive_services(self, timeout_s: float = 1.0) -> set[str]:
        """Services whose liveliness token is present now (a liveliness query)."""
        prefix = alive_key(self.robot_id, "")
        replies = self._session.liveliness().get(prefix + "*", timeout=timeout_s)
        return {str(reply.ok.key_expr)[len(prefix) :] for reply in replies if reply.ok is not None}


def _topic_type(topic: str) -> type[Message]:
    try:
        return TOPICS[topic]
    except KeyError:
        raise ValueError(f"unknown topic {topic!r}; known: {', '.join(TOPICS)}") from None


def router_config(listen: list[str], lease_ms: int = 1000, multicast_scouting: bool = False) -> BusConfig:
    """Bus settings of a Zenoh router listening on ``listen`` (zenoh's own router, DESIGN §1)."""
    return BusConfig(mode=BusMode.ROUTER, listen=listen, multicast_scouting=multicast_scouting, lease_ms=lease_ms)
