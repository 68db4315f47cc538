"""The nominal target between camera frames: q_nom and its rate q̇_nom at the control rate.

A human state arrives once per camera frame (≈ 30 Hz); the safety filter steps at 500 Hz. Held as a
staircase, q_nom jumps once a frame and the robot trails it by a frame more than it must. Instead
q_nom follows a path towards the newest state's target extrapolated by its own rate (retargeted θ̇,
:meth:`Retargeter.rate`) one frame period ahead. A state with target q and rate q̇ that becomes
available at t_s makes the path

    q_nom(t) = q₀ + v · clip(t − t_s, 0, T),   q̇_nom(t) = v while t − t_s < T, else 0,
    q_end = Π_[q_min, q_max]( q + q̇ T ),

with T one frame period — the interval between the frame stamps of the newest two states
(:func:`frame_stamp`: when each frame was taken, so a camera late now and then, whose states arrive
in bunches after a stall, still gets one period per state), at most ``safety.extrapolate_max_s``
(0 turns this off: a staircase; the first state, and a state with the same stamp, are never
extrapolated further than before) — and, by ``safety.target_path``:

* ``jump`` (the default): q_nom(t) = Π(q + q̇ · clip(t − t_s, 0, T)), q̇_nom = q̇ (0 where Π clips):
  q_nom jumps to the newest state at each frame and is extrapolated from there by the state's own
  rate (a straight path too, clipped where it leaves the limits); the tracking gain K closes the
  jump (the new frame's surprise: the person's position against the last frame's extrapolation) in
  ≈ 1/K = 125 ms, which also smooths a camera's jitter.
* ``continuous``: q₀ = the previous path's q_nom at t_s, v = (q_end − q₀)/T. q_nom never jumps at a
  new frame: it moves from where it was to where the newest state says the person will be one frame
  later, arriving exactly when the next frame is due, and q̇_nom, fed forward, is the velocity of
  that very path, so the surprise is followed within one frame. Measured (README "Velocity
  feed-forward and targets between frames"): on clean skeletons (the motion-capture development
  set) the median lag 129.5 → 110 ms with its safety goals still met (on the test variants
  robot-caused contact steps 174 → 207); with a noisy camera the robot follows the jitter too (lag
  156 → 172 ms, robot-caused contact steps 22 → 123), hence not the default.

Either way q_nom never runs more than one frame ahead of the newest state (it ends at q_end, the
newest state extrapolated by one frame period), never leaves the joint limits (continuous: both
ends of the straight path lie within them), and stops (holds, q̇_nom = 0) after that frame, on a
joint whose angle is invalid (its rate is 0: the path ends at the state's own angle) and at a
limit. A stale or lost person is the caller's business: it then holds q_cbf.

Used by the safety service and the offline evaluator alike (one implementation).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from shared.config import TargetPath
from shared.messages import HumanState


def frame_stamp(state: HumanState) -> float:
    """When ``state``'s camera frame was taken (s, the perception's clock): its ``capture_stamp``, or
    its publication ``stamp`` from a source that gives none. Two of them are a frame period apart
    whatever delays the frames met after the capture (inference, transport), where the publication
    stamps of a late frame and the one after it may be a few milliseconds apart."""
    return state.stamp if state.capture_stamp is None else state.capture_stamp


@dataclass(frozen=True)
class Nominal:
    """One frame's path: from ``q`` (n,) rad at time ``since`` (s, the caller's clock) at the rate ``dq``
    (n,) rad/s for at most ``horizon`` s, within [``q_min``, ``q_max``]."""

    q: np.ndarray
    dq: np.ndarray
    since: float
    horizon: float
    q_min: np.ndarray
    q_max: np.ndarray

    def at(self, now: float) -> tuple[np.ndarray, np.ndarray]:
        """(q_nom, q̇_nom) at time ``now`` (module docstring)."""
        tau = min(max(now - self.since, 0.0), self.horizon)
        raw = self.q + self.dq * tau
        q = np.minimum(np.maximum(raw, self.q_min), self.q_max)
        moving = (now - self.since < self.horizon) & (raw == q)
        return q, np.where(moving, self.dq, 0.0)


class NominalTrack:
    """The newest state's :class:`Nominal`; :meth:`update` once per applied human state."""

    def __init__(self, q: np.ndarray) -> None:
        q = np.asarray(q, dtype=np.float64)
        self.current = Nominal(q, np.zeros_like(q), 0.0, 0.0, np.full_like(q, -np.inf), np.full_like(q, np.inf))
        self._stamp: float | None = None

    def update(self, q: np.ndarray, dq: np.ndarray, stamp: float, since: float, max_horizon: float,
               q_min: np.ndarray, q_max: np.ndarray, path: TargetPath = TargetPath.JUMP) -> Nominal:
        """A state with ``stamp`` (its own clock) took effect at ``since`` with target ``q`` and rate
        ``dq``, within the joint limits [``q_min``, ``q_max``]; the path to follow by ``path``
        (module docstring).

        The same stamp again (re-applied after a config change or a stale spell) keeps the first
        ``since``, horizon and (continuous) start, so it never extrapolates further than the first
        time and never jumps back.
        """
        cur = self.current
        q, dq = np.asarray(q, float), np.asarray(dq, float)
        q_min, q_max = np.asarray(q_min, float), np.asarray(q_max, float)
        again = self._stamp is not None and stamp == self._stamp
        if again:
            since, horizon = cur.since, cur.horizon
        else:
            horizon = 0.0 if self._stamp is None else min(max(stamp - self._stamp, 0.0), max_horizon)
        self._stamp = stamp
        if path == TargetPath.JUMP or horizon <= 0.0:
            self.current = Nominal(q, dq, since, horizon, q_min, q_max)
            return self.current
        end = np.clip(q + dq * horizon, q_min, q_max)
        start = np.clip(cur.q if again else cur.at(since)[0], q_min, q_max)
        self.current = Nominal(start, (end - start) / horizon, since, horizon, q_min, q_max)
        return self.current

    def at(self, now: float) -> tuple[np.ndarray, np.ndarray]:
        return self.current.at(now)
