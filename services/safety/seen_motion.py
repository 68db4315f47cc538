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
    recomputed in full cost 0.4–0.8 ms more per state at 300 Hz: ``python -m bench.run
    human_update``). Per slot (:class:`_Slot`, in Python floats: for 7 slots numpy's per-call cost
    is most of the work) the window keeps count n_k,
    Σ d and Σ ‖d‖² of d = e − c_k, the endpoints less a reference c_k (the slot's endpoints when it
    entered an empty window: d is of the size of the capsule's motion since, so the variance
    Σ‖d‖²/n − ‖Σd/n‖² loses no digits to where the person stands, and a capsule still where it
    entered has d = 0 exactly), added as a frame enters and subtracted as it leaves; a slot's sums
    restart from exactly 0 when none of its frames is left. The variance is clipped at 0 (rounding);
    it equals the window's computed in full to rounding (tested on random streams).
    """

    def __init__(self, n_slots: int) -> None:
        #: (stamp, the slots valid in it with their contribution) per frame, oldest first
        self._frames: deque[tuple[float, list[tuple[_Slot, _Contribution]]]] = deque()
        self._slots = [_Slot() for _ in range(n_slots)]
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
        points = endpoints.reshape(len(self._slots), 6).tolist()  # Python floats: 7 slots cost less than numpy's calls
        seen = [(slot, slot.add(stamp, point))
                for slot, point, is_valid in zip(self._slots, points, valid.tolist(), strict=True) if is_valid]
        frames.append((stamp, seen))
        while len(frames) > 1 and frames[1][0] <= stamp - STILL_WINDOW_S:
            for slot, contribution in frames.popleft()[1]:
                slot.remove(contribution)
        if not frames[0][0] <= stamp - STILL_SEEN_FOR_S:
            self.speed = math.inf
        else:
            speeds = [slot.speed(stamp, len(frames)) for slot, _ in seen]
            self.speed = math.sqrt(12.0) * max(speeds) if speeds else 0.0
        return self.speed

    def _clear(self) -> None:
        self._frames.clear()
        self._slots = [_Slot() for _ in self._slots]


#: One frame's share of a slot's sums: d (6 floats: both endpoints less the reference), ‖d_a‖², ‖d_b‖².
_Contribution = tuple[list[float], float, float]


class _Slot:
    """One capsule slot's running sums over the window's frames where it is valid (see
    :class:`SeenMotion`): count n, Σ d, Σ ‖d‖² per endpoint, the stamps of those frames."""

    __slots__ = ("count", "reference", "sums", "squares", "stamps")

    def __init__(self) -> None:
        self.count = 0
        self.reference = [0.0] * 6
        self.sums = [0.0] * 6
        self.squares = [0.0, 0.0]
        self.stamps: deque[float] = deque()

    def add(self, stamp: float, point: list[float]) -> _Contribution:
        """Count a frame at ``stamp`` where the slot's endpoints are ``point`` (a then b, x y z, m)."""
        if not self.count:
            self.reference = point
        d = [p - r for p, r in zip(point, self.reference)]
        square_a, square_b = d[0] * d[0] + d[1] * d[1] + d[2] * d[2], d[3] * d[3] + d[4] * d[4] + d[5] * d[5]
        self.sums = [s + x for s, x in zip(self.sums, d)]
        self.squares = [self.squares[0] + square_a, self.squares[1] + square_b]
        self.count += 1
        self.stamps.append(stamp)
        return d, square_a, square_b

    def remove(self, contribution: _Contribution) -> None:
        """Forget a frame that left the window (the oldest one this slot counts)."""
        d, square_a, square_b = contribution
        self.count -= 1
        self.stamps.popleft()
        if not self.count:  # restart from exactly 0, not from what rounding left
            self.sums, self.squares = [0.0] * 6, [0.0, 0.0]
            return
        self.sums = [s - x for s, x in zip(self.sums, d)]
        self.squares = [self.squares[0] - square_a, self.squares[1] - square_b]

    def speed(self, stamp: float, frames: int) -> float:
        """max over the two endpoints of rms / span (1/√12 of :class:`SeenMotion`'s v) at ``stamp``,
        with ``frames`` in the window; inf when counted in under half of them or over no time."""
        n, span = self.count, stamp - self.stamps[0]
        if 2 * n < frames or not span > 0.0:
            return math.inf
        s, worst = self.sums, 0.0
        for end, square in enumerate(self.squares):
            mx, my, mz = s[3 * end] / n, s[3 * end + 1] / n, s[3 * end + 2] / n
            worst = max(worst, square / n - (mx * mx + my * my + mz * mz))
        return math.sqrt(worst) / span
