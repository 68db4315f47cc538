"""Typed pub/sub over Zenoh (architecture §1, §5, §11).

Key expressions: ``safemimic/{robot_id}/{topic}`` with the topics of :data:`TOPICS`, liveliness
tokens ``safemimic/{robot_id}/alive/{service}``. A payload that fails to decode or validate is
dropped and counted per topic, and so is a valid message that is a replay or arrives out of order
(:class:`SourceOrder`); a subscriber callback that raises is counted and logged, never propagated
into Zenoh. Sessions, publishers and tokens are context managers / closed with the bus.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections import Counter, OrderedDict
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Generic, TypeVar

import zenoh

from shared.codec import CodecError, decode, encode
from shared.config import BusConfig, BusMode, ConfigError, TlsConfig, check_secure_bus
from shared.messages import ConfigUpdate, HumanState, JointCommand, JointState, Message, SafetyStatus
from shared.tls import tls_files, zenoh_tls

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
#: Silence (s, local receive time) after which a source's next message is taken as a restarted
#: publisher, whatever its seq and stamp (:class:`SourceOrder`).
RESTART_SILENCE_S = 1.0
#: Sources one subscription remembers for ordering; the one heard from least recently is forgotten.
MAX_ORDERED_SOURCES = 64
#: Zenoh's connect/retry settings: how soon a client rejoins a restarted router.
CONNECT_RETRY = {"period_init_ms": 200, "period_max_ms": 500, "period_increase_factor": 2}
#: Samples a :class:`Newest` queue holds between two reads (Zenoh's Rust FIFO; a burst of 1,000
#: messages between two 2 ms control ticks fits with room to spare).
NEWEST_QUEUE = 4096


def topic_key(robot_id: str, topic: str) -> str:
    """The Zenoh key expression of a topic for one robot."""
    return f"{KEY_PREFIX}/{robot_id}/{topic}"


def alive_key(robot_id: str, service: str) -> str:
    """The liveliness token key of a service."""
    return f"{KEY_PREFIX}/{robot_id}/alive/{service}"


def zenoh_config(bus: BusConfig, identity: str = "", ingress_max_hz: Mapping[str, float] | None = None) -> zenoh.Config:
    """A ``zenoh.Config`` from our bus settings: mode, endpoints, scouting, lease, message size, and
    with ``bus.tls`` mutual TLS as ``identity`` (its certificate; a router also gets its access
    control). ``ingress_max_hz`` (key expression → Hz) downsamples what this session receives
    (:func:`ingress_downsampling`). :class:`ConfigError` for unusable settings or files (:mod:`shared.tls`)."""
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(bus.mode.value))
    conf.insert_json5("connect/endpoints", json.dumps(bus.connect))
    conf.insert_json5("listen/endpoints", json.dumps(bus.listen))
    conf.insert_json5("scouting/multicast/enabled", json.dumps(bus.multicast_scouting))
    conf.insert_json5("transport/link/tx/lease", str(bus.lease_ms))
    conf.insert_json5("transport/link/rx/max_message_size", str(bus.max_message_bytes))
    # A client that lost its router (restarted) retries every 0.2 s, backing off to 0.5 s at most
    # (Zenoh's default backs off to 4 s: a rejoin 2–4 s after the router is back).
    conf.insert_json5("connect/retry", json.dumps(CONNECT_RETRY))
    if bus.tls is not None:
        _insert_tls(conf, bus, identity)
    if ingress_max_hz:
        conf.insert_json5("downsampling", json.dumps(ingress_downsampling(ingress_max_hz)))
    return conf


def ingress_downsampling(max_hz: Mapping[str, float]) -> list[dict]:
    """Zenoh's ``downsampling`` block (zenoh 1.x interceptor) that lets through at most ``max_hz[key]``
    puts a second on each key expression *into* this session, on every link: the rest are dropped in
    Zenoh's Rust transport, before any Python runs or any queue holds them. Zenoh forwards a sample
    when 1/f has passed since the last one it forwarded on that key, so the newest sample before a
    publisher goes silent may be one of those dropped."""
    if not all(0.0 < hz < float("inf") for hz in max_hz.values()):
        raise ValueError(f"ingress rates must be positive and finite, got {dict(max_hz)}")
    return [{"id": "ingress_max_hz", "flows": ["ingress"], "messages": ["put"],
             "rules": [{"key_expr": key, "freq": float(hz)} for key, hz in max_hz.items()]}]


def _insert_tls(conf: zenoh.Config, bus: BusConfig, identity: str) -> None:
    """Mutual TLS only (no other link protocol), and at a router its access control file."""
    check_secure_bus(bus)
    assert bus.tls is not None
    router = bus.mode == BusMode.ROUTER
    files = tls_files(bus.tls, identity, router=router)
    conf.insert_json5("transport/link/protocols", json.dumps(["tls"]))
    conf.insert_json5("transport/link/tls", json.dumps(zenoh_tls(files, router)))
    if router and files.access_control is not None:
        try:
            conf.insert_json5("access_control", files.access_control.read_text())
        except Exception as exc:  # zenoh.ZError: not JSON5, or not Zenoh's access_control schema
            raise ConfigError(f"bus.tls: {files.access_control} is not a valid Zenoh access_control block: {exc}") from None


_warned_open = False


def _warn_if_open(bus: BusConfig) -> None:
    global _warned_open
    if bus.tls is None and not _warned_open:
        _warned_open = True
        log.warning("INSECURE BUS: no TLS and no access control (bus.tls: null / --insecure): anyone who can reach "
                    "this Zenoh network can command the robot and switch its safety layer off; development only")


def open_session(bus: BusConfig, identity: str = "", ingress_max_hz: Mapping[str, float] | None = None) -> zenoh.Session:
    """Open a Zenoh session as ``identity`` (use as a context manager; ``ingress_max_hz``: :func:`zenoh_config`);
    an open bus logs a warning once."""
    conf = zenoh_config(bus, identity, ingress_max_hz)
    _warn_if_open(bus)
    return zenoh.open(conf)


#: How long closing a session may take (s): a client whose router goes away at the same moment
#: (a whole stack stopped at once) can block in Zenoh's close.
CLOSE_TIMEOUT_S = 3.0
_hung_closes = 0


def close_bounded(close: Callable[[], None], timeout_s: float = CLOSE_TIMEOUT_S) -> bool:
    """Run ``close`` (a session's shutdown) for at most ``timeout_s``; False (logged, counted in
    :func:`hung_closes`) if it did not return: the process is then left to end without it."""
    global _hung_closes
    closer = threading.Thread(target=close, name="zenoh-close", daemon=True)
    closer.start()
    closer.join(timeout_s)
    if closer.is_alive():
        _hung_closes += 1
        log.warning("closing the Zenoh session did not finish within %.1f s: leaving it", timeout_s)
        return False
    return True


def hung_closes() -> int:
    """Session closes in this process that did not finish (:func:`close_bounded`): exit without waiting for them."""
    return _hung_closes


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


@dataclass
class _Heard:
    """The last message accepted from one source: its seq and stamp, and when it arrived (monotonic)."""

    seq: int
    stamp: float
    received: float


class SourceOrder:
    """Refuses replayed and out-of-order messages, per publishing source (one per subscription).

    Every message carries ``source`` (its publisher, set by :class:`TypedPublisher`), ``seq``
    (increasing per publisher) and ``stamp`` (the publisher's clock). A message from source s is
    **refused** when the last message accepted from s had a seq ≥ its seq *and* a stamp ≥ its
    stamp: a duplicate, a replay, or an older message overtaken by a newer one. Everything else is
    accepted and becomes s's last message:

    * the first message of a source, and a higher seq (a gap is a lost message, nothing more);
    * a lower or equal seq with a newer stamp: the publisher restarted (seq from 0 again) on the
      same clock (a process restart on the same host, whose monotonic clock goes on);
    * anything that arrives more than ``restart_silence_s`` (local receive time) after the last
      message accepted from s: a publisher restarted on another clock (another host, a reboot)
      is accepted again after at most that long, never ignored forever.

    Sources are told apart by name only: two live publishers with one name and interleaved seqs
    have their older-stamped messages refused. At most ``max_sources`` sources are remembered (the
    least recently heard is forgotten first), so random source names cannot grow memory.
    """

    def __init__(self, restart_silence_s: float = RESTART_SILENCE_S, max_sources: int = MAX_ORDERED_SOURCES) -> None:
        self.restart_silence_s = restart_silence_s
        self.max_sources = max_sources
        self._heard: OrderedDict[str, _Heard] = OrderedDict()
        self._lock = threading.Lock()

    def accept(self, message: Message, received: float) -> bool:
        """Whether ``message``, received at monotonic time ``received``, is new for its source (then remembered)."""
        with self._lock:
            last = self._heard.get(message.source)
            if (
                last is not None
                and message.seq <= last.seq
                and message.stamp <= last.stamp
                and received - last.received <= self.restart_silence_s
            ):
                return False
            self._heard[message.source] = _Heard(message.seq, message.stamp, received)
            self._heard.move_to_end(message.source)
            if len(self._heard) > self.max_sources:
                self._heard.popitem(last=False)
            return True


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


class Newest(Generic[M]):
    """The newest valid message on a topic, decoded only when read: a control loop's input.

    Samples wait in Zenoh's own FIFO (:data:`NEWEST_QUEUE`; no Python runs per sample on Zenoh's
    threads, so a burst does not compete with the control loop for the GIL). :meth:`get` drains
    it and decodes from the newest sample back until one is valid and new for its source
    (:class:`SourceOrder`): that one is held (received = when it was read: at most one control
    period late) and the older samples of the same read are *superseded* — never decoded, never
    used, counted in ``bus.superseded[topic]``. Samples that fail to decode, or are replayed or out
    of order, are counted in ``bus.dropped[topic]`` as with :meth:`Bus.subscribe`. Thread-safe;
    the same interface as :class:`Latest` (``set``, ``get``, ``count``). Within one read the
    newest-first order means a valid sample that arrived after a newer one from the same source
    (a replay) can be used instead of it; it is still valid, and real publishers never reorder.
    """

    def __init__(self, bus: Bus, topic: str, subscriber: zenoh.Subscriber) -> None:
        self._bus = bus
        self._topic = topic
        self._type = _topic_type(topic)
        self._subscriber = subscriber
        self._order = SourceOrder()
        self._lock = threading.Lock()
        self._value: Received[M] | None = None
        self.count = 0

    def set(self, message: M) -> None:
        """Hold ``message`` now, as if it had just been read (in-process drivers and tests)."""
        with self._lock:
            self._value = Received(message, time.monotonic())
            self.count += 1

    def get(self) -> Received[M] | None:
        """The newest valid message read so far (after draining what arrived since the last call)."""
        with self._lock:
            samples = []
            while (sample := self._subscriber.try_recv()) is not None:
                samples.append(sample)
            now = time.monotonic()
            for i in range(len(samples) - 1, -1, -1):
                message = self._bus._accept(self._topic, self._type, samples[i].payload.to_bytes(), self._order, now)
                if message is not None:
                    self._value = Received(message, now)  # type: ignore[arg-type]
                    self.count += 1
                    self._bus.superseded[self._topic] += i
                    break
            return self._value


class Bus:
    """One Zenoh session for one service of one robot, with typed topics and counters.

    ``dropped[topic]`` counts payloads refused on ``topic``: those that failed to decode/validate
    and valid messages refused as replayed or out of order (:class:`SourceOrder`), which
    ``out_of_order[topic]`` counts again on their own; ``callback_errors[topic]`` counts exceptions
    raised by user callbacks (logged, never propagated). ``max_hz`` (topic → Hz) caps what this
    session receives of those topics, dropped in Zenoh before Python sees it
    (:func:`ingress_downsampling`): a viewer's bound on what the control-rate topics cost it.
    """

    def __init__(self, bus: BusConfig, robot_id: str, service: str, max_hz: Mapping[str, float] | None = None) -> None:
        self.robot_id = robot_id
        self.service = service
        self.dropped: Counter[str] = Counter()
        self.out_of_order: Counter[str] = Counter()
        self.superseded: Counter[str] = Counter()
        self.callback_errors: Counter[str] = Counter()
        for topic in max_hz or {}:
            _topic_type(topic)  # an unknown topic is a clear error
        ingress = {topic_key(robot_id, topic): hz for topic, hz in (max_hz or {}).items()}
        self._session = open_session(bus, identity=service, ingress_max_hz=ingress)
        self._entities: list[object] = []

    # context manager -------------------------------------------------------------------------
    def __enter__(self) -> Bus:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> bool:
        """Undeclare everything this bus declared and close the session (idempotent, bounded by
        :data:`CLOSE_TIMEOUT_S`); False if the close hung (:func:`close_bounded`)."""
        entities, self._entities = self._entities, []

        def close_now() -> None:
            for entity in reversed(entities):
                try:
                    entity.undeclare()  # type: ignore[attr-defined]
                except Exception:  # already undeclared or session closing
                    pass
            if not self._session.is_closed():
                self._session.close()

        return close_bounded(close_now)

    @property
    def session(self) -> zenoh.Session:
        return self._session

    @property
    def source_id(self) -> str:
        """``service@zid``: the ``source`` this session's publishers stamp. The Zenoh session id makes it
        unique per process, so two instances of one service (a restart overlapping the old one, two
        config APIs on one bus) are ordered as two sources, never one refusing the other's messages."""
        return f"{self.service[:31]}@{self._session.zid()}"

    # pub/sub ---------------------------------------------------------------------------------
    def publisher(self, topic: str, robot_id: str | None = None) -> TypedPublisher[Message]:
        """A typed publisher on ``topic`` (a key of :data:`TOPICS`), of this or another robot."""
        message_type = _topic_type(topic)
        publisher = self._session.declare_publisher(
            topic_key(robot_id or self.robot_id, topic), congestion_control=zenoh.CongestionControl.DROP, express=True
        )
        self._entities.append(publisher)
        return TypedPublisher(publisher, message_type, self.source_id)

    def subscribe(
        self, topic: str, callback: Callable[[Message], None], robot_id: str | None = None
    ) -> zenoh.Subscriber:
        """Call ``callback(message)`` for every valid message on ``topic`` that is new for its source
        (:class:`SourceOrder`); invalid, replayed and out-of-order ones are counted in ``dropped``."""
        message_type = _topic_type(topic)
        order = SourceOrder()

        def on_sample(sample: zenoh.Sample) -> None:
            message = self._accept(topic, message_type, sample.payload.to_bytes(), order, time.monotonic())
            if message is None:
                return
            try:
                callback(message)
            except Exception:
                self.callback_errors[topic] += 1
                log.exception("callback on %s raised", topic)

        subscriber = self._session.declare_subscriber(topic_key(robot_id or self.robot_id, topic), on_sample)
        self._entities.append(subscriber)
        return subscriber

    def _accept(self, topic: str, message_type: type[Message], payload: bytes, order: SourceOrder,
                received: float) -> Message | None:
        """``payload`` decoded if it is valid and new for its source; else None, counted in ``dropped``."""
        try:
            message = decode(payload, message_type)
        except CodecError as exc:
            self.dropped[topic] += 1
            log.debug("dropped payload on %s: %s", topic, exc)
            return None
        if not order.accept(message, received):
            self.dropped[topic] += 1
            self.out_of_order[topic] += 1
            log.debug("dropped %s seq %d from %r on %s: replayed or out of order",
                      message_type.__name__, message.seq, message.source, topic)
            return None
        return message

    def newest(self, topic: str) -> Newest[Message]:
        """Queue ``topic``'s samples in Zenoh and decode only the newest valid one when read (:class:`Newest`)."""
        _topic_type(topic)
        subscriber = self._session.declare_subscriber(
            topic_key(self.robot_id, topic), zenoh.handlers.FifoChannel(NEWEST_QUEUE)
        )
        self._entities.append(subscriber)
        return Newest(self, topic, subscriber)

    def latest(self, topic: str) -> Latest[Message]:
        """Subscribe to ``topic`` and keep only the newest valid message."""
        holder: Latest[Message] = Latest()
        self.subscribe(topic, holder.set)
        return holder

    def put_raw(self, topic: str, payload: bytes) -> None:
        """Publish raw bytes on a topic (fault injection and tests only); blocks rather than drops
        when the link is congested, so every payload injected is delivered."""
        self._session.put(topic_key(self.robot_id, topic), payload, congestion_control=zenoh.CongestionControl.BLOCK)

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


def router_config(listen: list[str], lease_ms: int = 1000, multicast_scouting: bool = False,
                  tls: TlsConfig | None = None) -> BusConfig:
    """Bus settings of a Zenoh router listening on ``listen`` (zenoh's own router, architecture §1)."""
    return BusConfig(mode=BusMode.ROUTER, listen=listen, multicast_scouting=multicast_scouting, lease_ms=lease_ms,
                     tls=tls)
