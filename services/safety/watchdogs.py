"""The safety service's watchdogs: which are tripped now, how often each tripped, one log line per change.

Each watchdog is shown in :class:`~shared.messages.SafetyStatus` and counted in ``watchdog_trips``
when it trips (a change from clear to tripped); what the service does meanwhile is in
:mod:`services.safety.service`:

- ``human_state``: the newest HumanState is older than ``safety.human_timeout_s`` (local receive
  time) — keep its capsules (the person may still be there) without their velocity term and stop
  imitating: q_nom = q_cbf (``human_stale``);
- ``human_source``: the perception service's liveliness token is gone (its host crashed or its link
  was cut: noticed within the Zenoh lease) — the same as a stale human state (``human_source_lost``);
- ``human_lost``: a fresh HumanState marks invalid a capsule that was valid within
  ``safety.lost_human_hold_s`` (the person vanished from view) — keep its last valid capsule
  without its velocity term and stop imitating: q_nom = q_cbf, until the capsule is valid again or
  forgotten after the hold (``human_lost``);
- ``joint_state``: no JointState for ``safety.joint_state_timeout_s`` — keep integrating from
  q_cbf (``joint_state_stale``);
- ``executor_command``: the executor reports its commands stale and holds (``executor_holding``);
- ``resync``: a resync started (``resyncing``).
"""

from __future__ import annotations

import logging
from collections import Counter

__all__ = ["Watchdogs"]


class Watchdogs:
    """The control thread's watchdog states (not thread-safe: one writer, the tick)."""

    def __init__(self, log: logging.Logger) -> None:
        self.trips: Counter[str] = Counter()  # times each watchdog tripped
        self._tripped: set[str] = set()
        self._log = log

    def watch(self, name: str, tripped: bool, detail: str = "") -> bool:
        """Record watchdog ``name``'s state now; count and log a trip (a change to tripped) and a
        clearing. Returns ``tripped``."""
        if tripped and name not in self._tripped:
            self._tripped.add(name)
            self.trips[name] += 1
            self._log.warning("watchdog %s tripped%s (%d so far)", name, f": {detail}" if detail else "", self.trips[name])
        elif not tripped and name in self._tripped:
            self._tripped.discard(name)
            self._log.info("watchdog %s cleared", name)
        return tripped

    def tripped(self, name: str) -> bool:
        """Whether watchdog ``name`` is tripped now."""
        return name in self._tripped
