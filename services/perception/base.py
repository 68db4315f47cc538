"""The skeleton-source interface and the paced playback shared by the replay and scenario sources.

A source yields :class:`SkeletonFrame` objects: 15 canonical keypoints in the robot frame
(x forward, y left, z up, metres, floor z = 0, the robot's pelvis above x = y = 0; NaN where a
point is missing) with confidences, the source time ``t`` (seconds, increasing: the filters'
clock) and ``captured`` (``time.monotonic()`` when the frame was taken: the message's
``capture_stamp``). The live sources (``camera``, ``zed``: services.perception.camera) implement
the same protocol.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Protocol

import numpy as np


@dataclass(frozen=True)
class SkeletonFrame:
    """One skeleton: ``xyz`` (15, 3) robot frame, ``conf`` (15,) in [0, 1], times in seconds.

    ``discontinuity`` marks a frame that does not follow the previous one (a replay starting
    over): the filters reset instead of treating the gap as motion.
    """

    t: float
    xyz: np.ndarray
    conf: np.ndarray
    captured: float
    discontinuity: bool = False


class SkeletonSource(Protocol):
    """Anything that yields skeleton frames until exhausted or until ``stop`` is set."""

    name: str
    fps: float

    def frames(self, stop: threading.Event) -> Iterator[SkeletonFrame]: ...


class Pacer:
    """Releases source times on the wall clock: time ``t`` is due at start + (t − t_first).

    With ``realtime`` off every time is due at once (as fast as possible). Waiting uses
    ``stop.wait`` (never a busy loop). A consumer that falls behind is not made to catch up in a
    burst: the schedule restarts from the late frame.
    """

    #: Behind schedule by more than this (s): restart the schedule instead of bursting.
    MAX_BEHIND_S = 0.25

    def __init__(self, realtime: bool) -> None:
        self.realtime = realtime
        self._origin: tuple[float, float] | None = None  # (source time, monotonic time)

    def wait(self, t: float, stop: threading.Event) -> bool:
        """Wait until source time ``t`` is due; False if ``stop`` was set meanwhile."""
        if not self.realtime:
            return not stop.is_set()
        now = time.monotonic()
        if self._origin is None:
            self._origin = (t, now)
        due = self._origin[1] + (t - self._origin[0])
        if now - due > self.MAX_BEHIND_S:
            self._origin = (t, now)
            return not stop.is_set()
        return not stop.wait(max(0.0, due - now))


class PlayedSource:
    """A source of frames computed from their source time: a recording or a scripted motion.

    ``pose(i)`` gives (xyz (15, 3), conf (15,)) of frame i at source time ``times[i]``; with
    ``loop`` the sequence starts over (times continue by one period per lap) and, unless
    ``seamless`` (a periodic motion), the first frame of every lap is a discontinuity.
    """

    def __init__(
        self,
        name: str,
        times: np.ndarray,
        pose: Callable[[int], tuple[np.ndarray, np.ndarray]],
        fps: float,
        realtime: bool,
        loop: bool,
        seamless: bool = False,
    ) -> None:
        self.name = name
        self.fps = fps
        self.times = np.asarray(times, dtype=np.float64)
        self.pose = pose
        self.realtime = realtime
        self.loop = loop
        self.seamless = seamless
        self.period = float(self.times[-1] - self.times[0]) + 1.0 / fps

    def frames(self, stop: threading.Event) -> Iterator[SkeletonFrame]:
        pacer = Pacer(self.realtime)
        lap = 0
        while True:
            offset = lap * self.period
            for i, t in enumerate(self.times):
                if not pacer.wait(t + offset, stop):
                    return
                xyz, conf = self.pose(i)
                yield SkeletonFrame(
                    t=float(t + offset), xyz=xyz, conf=conf, captured=time.monotonic(),
                    discontinuity=lap > 0 and i == 0 and not self.seamless,
                )
            if not self.loop:
                return
            lap += 1
