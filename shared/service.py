"""The lifecycle every service shares: a bus it was given or opened itself, closed with it.

A service is a context manager; :meth:`BusService.close` closes the bus only if the service
opened it (tests and in-process drivers pass their own). :class:`ScheduledService` adds the
deadline counters of a fixed-rate control loop (:class:`~shared.schedule.FixedRateSchedule`).
What every loop keeps the same way: :class:`StepErrors` (a step that raises), :class:`StepTimes`
(how long its steps take), :class:`Refusals` (messages refused, per topic) and :class:`Pending`
(a configuration accepted on a callback thread, applied by the loop at its next step), and
:func:`validated_update` (a configuration update checked on arrival, or counted refused).
"""

from __future__ import annotations

import logging
import threading
from collections import Counter
from collections.abc import Callable
from typing import Generic, Self, TypeVar

import numpy as np

from shared.bus import Bus
from shared.config import ConfigError, StackConfig, validate_config
from shared.messages import ConfigUpdate
from shared.schedule import FixedRateSchedule

T = TypeVar("T")


class StepErrors:
    """Unexpected exceptions of a loop's steps (a control tick, a camera frame): each is counted
    (``total``) and logged (the first of every streak and the first ten overall, never one per
    step of a long streak), and the loop goes on — until ``limit`` steps in a row failed: that is
    a bug, not bad input, and the exception is raised."""

    def __init__(self, log: logging.Logger, what: str, limit: int) -> None:
        self.total = 0
        self._streak = 0
        self._log, self._what, self._limit = log, what, limit

    def run(self, step: Callable[[], T]) -> T | None:
        """``step()``'s result, or None after a counted, logged exception (raised at the limit)."""
        try:
            result = step()
        except Exception:
            self.total += 1
            self._streak += 1
            if self._streak == 1 or self.total <= 10:
                self._log.exception("%s failed (%d so far)", self._what, self.total)
            if self._streak >= self._limit:
                raise
            return None
        self._streak = 0
        return result


class StepTimes:
    """How long a loop's steps took (s): the last one, and the most recent ``window`` of them."""

    def __init__(self, window: int = 10_000) -> None:
        self.last_s = 0.0
        self._times = np.zeros(window)
        self._count = 0

    def record(self, seconds: float) -> None:
        self.last_s = seconds
        self._times[self._count % self._times.size] = seconds
        self._count += 1

    def recent(self) -> np.ndarray:
        """The recorded step times (s), at most ``window`` of them; a single 0 before the first."""
        n = min(self._count, self._times.size)
        return self._times[:n] if n else np.zeros(1)


class Refusals:
    """Messages a service refused, per topic: the bus's (undecodable, invalid, replayed, a failing
    callback: :attr:`~shared.bus.Bus.dropped`, :attr:`~shared.bus.Bus.callback_errors`) and the
    service's own (valid messages it would not take: :meth:`refuse`). Counted from any thread."""

    def __init__(self) -> None:
        self._own: Counter[str] = Counter()

    def refuse(self, topic: str) -> None:
        """One valid message on ``topic`` refused by the service itself."""
        self._own[topic] += 1

    def own(self, topic: str) -> int:
        """The service's own refusals on ``topic`` so far."""
        return self._own[topic]

    def by_topic(self, bus: Bus) -> dict[str, int]:
        """Every refusal so far, per topic (topics with none left out)."""
        total = Counter(bus.dropped)
        total.update(bus.callback_errors)
        total.update(self._own)
        return {topic: int(count) for topic, count in total.items() if count}


def validated_update(update: ConfigUpdate, refusals: Refusals, log: logging.Logger) -> StackConfig | None:
    """``update``'s configuration validated, or None when it is invalid: then counted as refused on the
    ``config`` topic and logged with the reason (:class:`~shared.config.ConfigError` names the bad
    fields); a service goes on with the configuration it has."""
    try:
        return validate_config(update.config, origin=f"config update v{update.version}")
    except ConfigError as exc:
        refusals.refuse("config")
        log.warning("rejected config update v%d: %s", update.version, exc)
        return None


class Pending(Generic[T]):
    """The newest item a callback thread hands to the loop (e.g. a configuration accepted, applied
    at the loop's next step): :meth:`put` replaces what is waiting, :meth:`take` empties the slot."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._item: T | None = None

    def put(self, item: T) -> None:
        with self._lock:
            self._item = item

    def peek(self) -> T | None:
        """What is waiting, left in place (None: nothing)."""
        with self._lock:
            return self._item

    def take(self) -> T | None:
        """What is waiting, removed (None: nothing)."""
        with self._lock:
            item, self._item = self._item, None
        return item


class BusService:
    """Owns ``self.bus`` when it opened it (:meth:`open_bus`); ``with`` closes what it owns."""

    bus: Bus
    _owns_bus: bool = False

    def open_bus(self, conf: StackConfig, name: str, bus: Bus | None) -> Bus:
        """``bus``, or a new one from ``conf.bus`` for service ``name`` (then closed by :meth:`close`)."""
        self._owns_bus = bus is None
        self.bus = bus if bus is not None else Bus(conf.bus, conf.robot_id, name)
        return self.bus

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Close the bus if this service opened it (idempotent)."""
        if self._owns_bus and hasattr(self, "bus"):
            self.bus.close()


class ScheduledService(BusService):
    """A bus service whose loop runs on ``self.schedule`` and counts its ticks in ``self.ticks``."""

    schedule: FixedRateSchedule
    ticks: int

    @property
    def deadline_misses(self) -> int:
        """Control slots missed: ticks that started a whole period late (or, where the loop reports
        its ends, finished after the next one was due)."""
        return self.schedule.missed

    @property
    def max_late_s(self) -> float:
        """The latest a tick has started (s)."""
        return self.schedule.max_late_s

    def rate_counters(self, elapsed_s: float | None) -> dict[str, float]:
        """``elapsed_s`` (s) and the tick rate achieved over it (Hz); empty without an elapsed time."""
        if elapsed_s is None:
            return {}
        return {"elapsed_s": elapsed_s, "achieved_hz": self.ticks / elapsed_s if elapsed_s > 0 else 0.0}
