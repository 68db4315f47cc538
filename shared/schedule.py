"""Fixed-rate schedule of a control loop (architecture §8: sleep until the next tick, never spin).

Tick k is due at ``anchor + k · period`` (absolute: no drift). :meth:`FixedRateSchedule.wait`
sleeps with ``threading.Event.wait`` until the next tick is due; whole periods that passed
meanwhile (a stall) are counted as missed and skipped, keeping the phase rather than bursting to
catch up. A loop that also holds itself to finishing within the period reports each tick's end
with :meth:`FixedRateSchedule.finished`.
"""

from __future__ import annotations

import math
import threading
import time


class FixedRateSchedule:
    """Absolute-time ticks at ``period`` seconds; counts missed deadlines and the worst lateness."""

    def __init__(self, period: float) -> None:
        self.period = period
        self.missed = 0
        self.max_late_s = 0.0
        self.begin = self.due = self._anchor = time.monotonic()
        self._end = math.inf
        self._k = 0
        self._stop = threading.Event()

    def start(self, stop: threading.Event, duration: float | None = None) -> None:
        """Tick 0 is due now; :meth:`wait` ends when ``stop`` is set or ``duration`` s have passed."""
        self.begin = self._anchor = time.monotonic()
        self._end = math.inf if duration is None else self.begin + duration
        self._k = 0
        self._stop = stop

    def wait(self) -> float | None:
        """Sleep until the next tick is due: its start time (monotonic s), or None when over."""
        if self._stop.is_set():
            return None
        due = self._anchor + self._k * self.period
        now = time.monotonic()
        if now < due:
            if self._stop.wait(min(due, self._end) - now):
                return None
            now = time.monotonic()
        if now >= self._end:
            return None
        late = now - due
        self.max_late_s = max(self.max_late_s, late)
        if late >= self.period:  # whole slots passed: count them, keep the phase
            skipped = int(late // self.period)
            self.missed += skipped
            self._k += skipped
            due += skipped * self.period
        self.due = due
        self._k += 1
        return now

    def finished(self, done: float) -> None:
        """The current tick ended at ``done``: a miss if that is after the next tick's due time."""
        if done > self.due + self.period:
            self.missed += 1

    def set_period(self, period: float) -> None:
        """Change the rate: the next tick is due one new period from now."""
        if period != self.period:
            self.period, self._anchor, self._k = period, time.monotonic(), 1
