"""How fast a person was *seen* to move over the last second of frames: the intrusion stop's stillness.

Not their measured velocities, nor a displacement between two states: a camera's noise moves a
still person's capsules by centimetres from frame to frame (on the camera source's still
photographs their endpoints show 0.8–2 m/s by either measure), and perception reports a velocity
of 0 where it cannot compute one (a capsule that just appeared, keypoints re-initialised after a
jump). Over a window the noise averages out while any motion, steady or back and forth, spreads
the endpoints (:class:`SeenMotion`).
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np

#: The window (s) over which :class:`SeenMotion` judges how a person moved: long enough for a camera's
#: frame-to-frame noise to average out.
STILL_WINDOW_S = 1.0
#: The least time (s) a person must have been seen for :class:`SeenMotion` to know their speed: longer
#: than a keypoint glitch or the turning point of a swing. Over a span this short the noise counts
#: twice as much (v = √12 σ / span), so a noisy camera is judged over more of the window.
STILL_SEEN_FOR_S = 0.5


class SeenMotion:
    """The speed a person's capsules were seen to move at over the last :data:`STILL_WINDOW_S` of
    frames (m/s, :attr:`speed`): the speed of a uniform motion that would spread a capsule endpoint
    as far as the frames show,

        v = max over endpoints k of √12 · rms_k / W_k,   rms_k² = mean_j ‖e_k(t_j) − ē_k‖²,

    over the capsules valid in the newest frame, each over the window's frames where it is valid
    (ē_k their mean, W_k = t_newest − the first of them: their span). An endpoint moving at a steady
    v over W has rms v W / √12, so v is its speed; back-and-forth motion (a punch out and back within
    the window, which a fitted slope would call still) spreads it as well; a still endpoint whose
    noise has RMS σ has rms σ, so v = √12 σ / W: 3.5 cm/s per cm of noise at W = 1 s.

    :attr:`speed` is inf (unknown: as moving) until the frames span :data:`STILL_SEEN_FOR_S`, when a
    capsule valid in the newest frame was valid in fewer than half of the window's frames (it just
    appeared, or was seen too rarely to say), or was seen over no time; 0 when none is valid in the
    newest frame.

    The window keeps the frames since the newest stamp − :data:`STILL_WINDOW_S` and the one just
    before (so that it spans the whole window). A frame with the newest stamp again (the same
    message) changes nothing; one older than the newest (the stream started over) starts the window
    again.

    Cost: O(E) per frame whatever the frame rate (E capsule slots), so a perception publishing at
    the control rate costs the control loop no more per state than a 30 Hz camera (the window
    recomputed in full cost ≈ 0.4 ms per state at 300 Hz). Per slot the window keeps count n_k,
    Σ d and Σ ‖d‖² of d = e − c_k, the endpoints less a reference c_k (the slot's endpoints when it
    entered an empty window: d is of the size of the capsule's motion since, so the variance
    Σ‖d‖²/n − ‖Σd/n‖² loses no digits to where the person stands, and a capsule still where it
    entered has d = 0 exactly), added as a frame enters and subtracted as it leaves; a slot's sums
    restart from exactly 0 when none of its frames is left. The variance is clipped at 0 (rounding);
    it equals the window's computed in full to rounding (tested on random streams).
    """

    def __init__(self, n_slots: int) -> None:
        #: (stamp, d (E,2,3), ‖d‖² (E,2), valid (E,)) per frame, oldest first
        self._frames: deque[tuple[float, np.ndarray, np.ndarray, np.ndarray]] = deque()
        self._valid_stamps: list[deque[float]] = [deque() for _ in range(n_slots)]  # per slot, oldest first
        self._reference = np.zeros((n_slots, 2, 3))
        self._count = np.zeros(n_slots, dtype=np.int64)
        self._sum = np.zeros((n_slots, 2, 3))
        self._sum_sq = np.zeros((n_slots, 2))
        #: m/s, inf while unknown (see the class doc).
        self.speed = math.inf

    @property
    def frames(self) -> int:
        """How many frames the window holds."""
        return len(self._frames)

    def see(self, stamp: float, endpoints: np.ndarray, valid: np.ndarray) -> float:
        """Add a frame taken at ``stamp`` (s, the frames' clock) with capsule ``endpoints`` (E,2,3) m
        valid where ``valid`` (E,) bool; the new :attr:`speed`."""
        frames = self._frames
        if frames and stamp == frames[-1][0]:
            return self.speed
        if frames and stamp < frames[-1][0]:
            self._clear()
        self._add(stamp, endpoints, valid)
        while len(frames) > 1 and frames[1][0] <= stamp - STILL_WINDOW_S:
            self._remove_oldest()
        self.speed = self._speed(stamp, valid) if frames[0][0] <= stamp - STILL_SEEN_FOR_S else math.inf
        return self.speed

    def _add(self, stamp: float, endpoints: np.ndarray, valid: np.ndarray) -> None:
        valid = valid.copy()
        entering = valid & (self._count == 0)
        self._reference[entering] = endpoints[entering]
        d = np.where(valid[:, None, None], endpoints - self._reference, 0.0)
        squared = (d * d).sum(axis=2)
        self._frames.append((stamp, d, squared, valid))
        self._count += valid
        self._sum += d
        self._sum_sq += squared
        for slot in np.flatnonzero(valid):
            self._valid_stamps[slot].append(stamp)

    def _remove_oldest(self) -> None:
        _, d, squared, valid = self._frames.popleft()
        self._count -= valid
        self._sum -= d
        self._sum_sq -= squared
        for slot in np.flatnonzero(valid):
            self._valid_stamps[slot].popleft()
        emptied = valid & (self._count == 0)
        self._sum[emptied], self._sum_sq[emptied] = 0.0, 0.0

    def _clear(self) -> None:
        self._frames.clear()
        for stamps in self._valid_stamps:
            stamps.clear()
        self._count[:], self._sum[:], self._sum_sq[:] = 0, 0.0, 0.0

    def _speed(self, stamp: float, now: np.ndarray) -> float:
        """The class doc's v over the window, from its sums, for the slots valid ``now``."""
        if not now.any():
            return 0.0
        count = self._count[now]
        span = stamp - np.array([self._valid_stamps[slot][0] for slot in np.flatnonzero(now)])
        if (2 * count < len(self._frames)).any() or not (span > 0.0).all():
            return math.inf
        mean = self._sum[now] / count[:, None, None]
        variance = self._sum_sq[now] / count[:, None] - (mean * mean).sum(axis=2)  # (C, 2)
        rms = np.sqrt(np.maximum(variance, 0.0))
        return math.sqrt(12.0) * float((rms.max(axis=1) / span).max())
