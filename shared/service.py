"""The lifecycle every service shares: a bus it was given or opened itself, closed with it.

A service is a context manager; :meth:`BusService.close` closes the bus only if the service
opened it (tests and in-process drivers pass their own). :class:`ScheduledService` adds the
deadline counters of a fixed-rate control loop (:class:`~shared.schedule.FixedRateSchedule`);
:class:`StepErrors` is how every loop survives a step that raises.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Self, TypeVar

from shared.bus import Bus
from shared.config import StackConfig
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
    """A bus service whose loop runs on ``self.schedule``."""

    schedule: FixedRateSchedule

    @property
    def deadline_misses(self) -> int:
        """Control slots missed: ticks that started a whole period late (or, where the loop reports
        its ends, finished after the next one was due)."""
        return self.schedule.missed

    @property
    def max_late_s(self) -> float:
        """The latest a tick has started (s)."""
        return self.schedule.max_late_s
