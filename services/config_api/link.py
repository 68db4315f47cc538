"""The config API's Zenoh side: publishes ``ConfigUpdate``, follows ``SafetyStatus`` and ``HumanState``.

The current configuration is published again whenever another service's liveliness token
appears, so a service (re)started after a change gets the accepted configuration, not its own
file's. Versions stay monotonic across a lost store: :attr:`BusLink.highest_version_seen` is the
highest ``config_version`` any safety service reported, and the next version goes above it.
"""

from __future__ import annotations

import asyncio
import logging
import threading
import time
from collections.abc import Callable
from typing import Any

from shared.bus import Bus, Latest, Received
from shared.messages import ConfigUpdate, HumanState, SafetyStatus

log = logging.getLogger("safemimic.config_api")

SERVICE_NAME = "config_api"


class BusLink:
    """Publishes accepted configurations and keeps the newest status and human state.

    ``current()`` returns the version and the (public) configuration JSON to republish when a
    service appears.
    """

    def __init__(self, bus: Bus, current: Callable[[], tuple[int, dict[str, Any]]]) -> None:
        self._bus = bus
        self._current = current
        self._publish_lock = threading.Lock()
        self._alive_lock = threading.Lock()
        self._alive: set[str] = set()
        self.highest_version_seen = 0
        self.status: Latest[SafetyStatus] = Latest()
        # requests waiting in :meth:`wait_applied`: their event loop and the event a new status sets
        self._waiters_lock = threading.Lock()
        self._waiters: set[tuple[asyncio.AbstractEventLoop, asyncio.Event]] = set()
        self._publisher = bus.publisher("config")
        self.human: Latest[HumanState] = bus.latest("human/state")  # type: ignore[assignment]
        bus.subscribe("safety/status", self._on_status)
        bus.watch_alive(self._on_alive)
        bus.declare_alive(SERVICE_NAME)

    def _on_status(self, status: SafetyStatus) -> None:
        self.highest_version_seen = max(self.highest_version_seen, status.config_version)
        self.status.set(status)
        with self._waiters_lock:
            waiters = list(self._waiters)
        for loop, event in waiters:
            try:
                loop.call_soon_threadsafe(event.set)
            except RuntimeError:  # that request's event loop has closed (server shutting down)
                pass

    def _on_alive(self, service: str, alive: bool) -> None:
        with self._alive_lock:
            (self._alive.add if alive else self._alive.discard)(service)
        if alive and service != SERVICE_NAME:
            version, config = self._current()
            log.info("%s is up: publishing config v%d", service, version)
            self.publish(version, [], config)

    @property
    def services_alive(self) -> list[str]:
        """Services whose liveliness token is present, sorted."""
        with self._alive_lock:
            return sorted(self._alive)

    def publish(self, version: int, changed: list[str], config: dict[str, Any]) -> None:
        """Publish one ``ConfigUpdate`` (thread-safe: requests and liveliness callbacks both publish)."""
        update = ConfigUpdate(stamp=time.time(), version=version, changed=changed, config=config)
        with self._publish_lock:
            self._publisher.put(update)

    def applied(self, version: int, since: float) -> bool:
        """A SafetyStatus received after monotonic time ``since`` reports ``version`` (or newer) applied."""
        newest: Received[SafetyStatus] | None = self.status.get()
        return newest is not None and newest.received >= since and newest.message.config_version >= version

    async def wait_applied(self, version: int, since: float, timeout_s: float) -> bool:
        """Wait (without blocking the event loop) until :meth:`applied`, at most ``timeout_s``.

        Woken by each new SafetyStatus (no polling): the answer leaves as soon as the status
        reporting ``version`` arrives.
        """
        loop = asyncio.get_running_loop()
        waiter = (loop, asyncio.Event())
        deadline = loop.time() + timeout_s
        with self._waiters_lock:
            self._waiters.add(waiter)
        try:
            while True:
                waiter[1].clear()  # before the check: a status arriving after it sets the event again
                if self.applied(version, since):
                    return True
                remaining = deadline - loop.time()
                if remaining <= 0:
                    return False
                try:
                    await asyncio.wait_for(waiter[1].wait(), remaining)
                except TimeoutError:
                    pass
        finally:
            with self._waiters_lock:
                self._waiters.discard(waiter)
