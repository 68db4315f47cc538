"""Scheduling: a control thread in real time (Linux SCHED_FIFO), an onlooker process in the
background (Linux SCHED_IDLE), each with a graceful fallback."""

from __future__ import annotations

import logging
import os
from collections.abc import Iterator
from contextlib import contextmanager

log = logging.getLogger(__name__)

#: SCHED_FIFO priority the safety service asks for its control loop (modest: below threaded IRQs at
#: 50); a container's ``rtprio`` limit must allow it (safemimic.stack).
DEFAULT_RT_PRIORITY = 10


def enter_realtime(priority: int) -> str:
    """Put the calling thread under ``SCHED_FIFO`` at ``priority`` (1–99) if the OS allows it.

    A 500 Hz loop under plain time sharing misses deadlines whenever other processes keep both
    cores busy (measured here: 1–6 % misses, stalls of 4–9 ms, with three CPU-bound neighbours;
    0 misses and ≤ 0.3 ms lateness with SCHED_FIFO). Like ros2_control's controller manager, try
    and fall back with a warning when refused (no CAP_SYS_NICE / RLIMIT_RTPRIO, non-Linux).
    Returns a description for the log. The loop sleeps between ticks, so it cannot starve the CPU.
    """
    if priority <= 0:
        return "normal scheduling"
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except (AttributeError, OSError) as exc:  # AttributeError: no sched_setscheduler on this OS
        log.warning("could not switch the control thread to SCHED_FIFO %d (%s): normal scheduling, "
                    "expect deadline misses on a busy machine", priority, exc)
        return "normal scheduling (SCHED_FIFO refused)"
    return f"SCHED_FIFO priority {priority}"


def leave_realtime() -> None:
    """Back to normal time sharing for the calling thread (no-op if it never left it)."""
    try:
        if os.sched_getscheduler(0) != os.SCHED_OTHER:
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    except (AttributeError, OSError):
        pass


@contextmanager
def realtime(priority: int) -> Iterator[str]:
    """``with realtime(p) as scheduling:`` the block runs under :func:`enter_realtime` (its
    description bound to ``scheduling``) and the thread returns to normal scheduling after."""
    scheduling = enter_realtime(priority)
    try:
        yield scheduling
    finally:
        if priority > 0:
            leave_realtime()


#: Niceness of a background process where SCHED_IDLE is not available (the lowest priority).
BACKGROUND_NICENESS = 19


def enter_background() -> str:
    """Put every thread of this process, and every thread it starts later, under ``SCHED_IDLE``.

    On a busy core Linux gives a SCHED_IDLE thread the smallest share there is (weight 3 against a
    nice-0 thread's 1024), and a waking normal or real-time thread (a control loop's tick) preempts
    it at once, whereas a niced thread may still finish its slice first. For a process that only watches (the live viewer) on a host shared with the
    500 Hz loop. Elsewhere, or if refused, the process is niced to :data:`BACKGROUND_NICENESS`.
    Returns a description for the log.
    """
    try:
        for thread in os.listdir("/proc/self/task"):  # threads already started (Zenoh's, Rerun's)
            try:
                os.sched_setscheduler(int(thread), os.SCHED_IDLE, os.sched_param(0))
            except ProcessLookupError:  # it ended meanwhile
                pass
        return "SCHED_IDLE"
    except (AttributeError, OSError, ValueError) as exc:  # not Linux, no /proc, refused
        log.info("SCHED_IDLE not available (%s): nice %d instead", exc, BACKGROUND_NICENESS)
    try:
        os.nice(BACKGROUND_NICENESS - os.nice(0))
    except (AttributeError, OSError) as exc:
        log.warning("could not lower this process's CPU priority (%s)", exc)
        return "normal scheduling"
    return f"nice {BACKGROUND_NICENESS}"
