"""The lifecycle every service shares: a bus it was given or opened itself, closed with it.

A service is a context manager; :meth:`BusService.close` closes the bus only if the service
opened it (tests and in-process drivers pass their own). :class:`ScheduledService` adds the
deadline counters of a fixed-rate control loop (:class:`~shared.schedule.FixedRateSchedule`).
"""

from __future__ import annotations

from typing import Self

from shared.bus import Bus
from shared.config import StackConfig
from shared.schedule import FixedRateSchedule


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
