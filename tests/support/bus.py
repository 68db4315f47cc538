"""What a test sees on the bus: one recorder of messages and liveliness changes, and a wait for a route."""

from __future__ import annotations

import bisect
import threading
import time
from collections import defaultdict
from collections.abc import Callable, Iterable
from typing import Any

from shared.bus import Bus, topic_key
from shared.messages import Message

#: Called (under the recorder's lock) with each message as it is recorded: topic, arrival time, message.
OnMessage = Callable[[str, float, Message], None]


class BusRecorder:
    """Every message on ``topics`` that ``bus`` receives, with its local arrival time (monotonic s),
    and with ``alive`` every liveliness change of a service token; thread-safe. ``robot_id``: the
    robot whose topics to record (default: the bus's own).

    ``on_message`` sees each message as it is recorded (under the lock), for checks that follow the
    stream as it comes (e.g. a rate limit between consecutive commands).
    """

    def __init__(self, bus: Bus, topics: Iterable[str], *, alive: bool = False,
                 on_message: OnMessage | None = None, robot_id: str | None = None) -> None:
        self.bus = bus
        self.lock = threading.Lock()
        self._on_message = on_message
        self._timed: dict[str, list[tuple[float, Message]]] = defaultdict(list)
        self._arrivals: dict[str, list[float]] = defaultdict(list)
        self._alive: dict[str, bool] = {}
        self._alive_events: list[tuple[float, str, bool]] = []
        for topic in topics:
            bus.subscribe(topic, self._recorder(topic), robot_id=robot_id)
        if alive:
            bus.watch_alive(self._on_alive)

    def _recorder(self, topic: str) -> Callable[[Message], None]:
        def record(message: Message) -> None:
            now = time.monotonic()
            with self.lock:
                self._timed[topic].append((now, message))
                self._arrivals[topic].append(now)
                if self._on_message is not None:
                    self._on_message(topic, now, message)

        return record

    def _on_alive(self, service: str, up: bool) -> None:
        with self.lock:
            self._alive[service] = up
            self._alive_events.append((time.monotonic(), service, up))

    # messages -----------------------------------------------------------------------------------
    def timed(self, topic: str) -> list[tuple[float, Any]]:
        """(arrival time, message) of every message on ``topic`` so far, in arrival order."""
        with self.lock:
            return list(self._timed[topic])

    def between(self, topic: str, start: float = float("-inf"), end: float = float("inf")) -> list[Any]:
        """The messages on ``topic`` that arrived in [start, end]."""
        with self.lock:
            return [m for t, m in self._timed[topic] if start <= t <= end]

    def count(self, topic: str) -> int:
        with self.lock:
            return len(self._timed[topic])

    def last(self, topic: str) -> Any | None:
        """The newest message on ``topic`` (None: none yet)."""
        with self.lock:
            return self._timed[topic][-1][1] if self._timed[topic] else None

    def first_after(self, topic: str, start: float, predicate: Callable[[Any], bool] | None = None) -> float | None:
        """When the first message on ``topic`` after ``start`` (satisfying ``predicate``) arrived; None: none."""
        with self.lock:
            if predicate is None:
                arrivals = self._arrivals[topic]
                i = bisect.bisect_right(arrivals, start)
                return arrivals[i] if i < len(arrivals) else None
            return next((t for t, m in self._timed[topic] if t > start and predicate(m)), None)

    def max_gap(self, topic: str, start: float, end: float) -> float:
        """The longest stretch of [start, end] without a message on ``topic`` (s)."""
        with self.lock:
            times = [start, *(a for a in self._arrivals[topic] if start < a < end), end]
        return max(b - a for a, b in zip(times, times[1:]))

    def wait_timed(self, topic: str, predicate: Callable[[Any], bool], timeout_s: float,
                   since: float | None = None) -> tuple[float, Any]:
        """(arrival time, message) of the first message on ``topic`` arrived at or after ``since``
        (default: now) satisfying ``predicate``; fails with the last one seen after ``timeout_s``."""
        since = time.monotonic() if since is None else since
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            with self.lock:
                found = next(((t, m) for t, m in self._timed[topic] if t >= since and predicate(m)), None)
            if found is not None:
                return found
            time.sleep(0.005)
        raise AssertionError(f"no matching message on {topic} within {timeout_s} s; last: {self.last(topic)}")

    def wait_count(self, topic: str, n: int, timeout_s: float) -> None:
        """Wait until ``n`` messages on ``topic`` have arrived; fails after ``timeout_s``."""
        deadline = time.monotonic() + timeout_s
        while self.count(topic) < n:
            if time.monotonic() > deadline:
                raise AssertionError(f"{self.count(topic)} of {n} messages on {topic} within {timeout_s} s")
            time.sleep(0.005)

    def wait(self, topic: str, predicate: Callable[[Any], bool], timeout_s: float, since: float | None = None) -> Any:
        """The message of :meth:`wait_timed`."""
        return self.wait_timed(topic, predicate, timeout_s, since)[1]

    # liveliness ---------------------------------------------------------------------------------
    def alive_tokens(self) -> set[str]:
        """The service tokens up now."""
        with self.lock:
            return {token for token, up in self._alive.items() if up}

    def wait_token(self, token: str, up: bool, timeout_s: float) -> float:
        """When ``token`` was first seen up (or gone), waiting up to ``timeout_s``; fails with the changes seen."""
        deadline = time.monotonic() + timeout_s
        while True:
            with self.lock:
                at = next((when for when, name, state in self._alive_events if name == token and state == up), None)
                events = list(self._alive_events)
            if at is not None:
                return at
            if time.monotonic() > deadline:
                raise AssertionError(f"token {token} up={up} not seen within {timeout_s} s: {events}")
            time.sleep(0.005)

    def is_alive(self, token: str) -> bool:
        with self.lock:
            return bool(self._alive.get(token))

    def token_event_after(self, token: str, up: bool, start: float) -> float | None:
        """When ``token`` was first seen up (or gone) after ``start``, and still is if ``up``; None: not."""
        with self.lock:
            if up and not self._alive.get(token):
                return None
            return next((when for when, name, state in self._alive_events
                         if when > start and name == token and state == up), None)


def await_route(bus: Bus, topic: str, timeout_s: float = 10.0) -> None:
    """Wait until ``bus``'s session knows a subscriber of ``topic`` (samples put before are lost)."""
    probe = bus.session.declare_publisher(topic_key(bus.robot_id, topic))
    try:
        deadline = time.monotonic() + timeout_s
        while not probe.matching_status.matching:
            if time.monotonic() > deadline:
                raise RuntimeError(f"no subscriber of {topic} reachable from the session")
            time.sleep(0.01)
    finally:
        probe.undeclare()
