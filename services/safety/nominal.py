"""The nominal target between camera frames: q_nom and its rate q̇_nom at the control rate.

A human state arrives once per camera frame (≈ 30 Hz); the safety filter steps at 500 Hz. Held as a
staircase, q_nom jumps once a frame and the robot trails it by a frame more than it must. Instead
the newest state's target is extrapolated by its own rate (retargeted θ̇, :meth:`Retargeter.rate`):

    q_nom(t) = Π_[q_min, q_max]( q + q̇ · clip(t − t_s, 0, T) ),   q̇_nom(t) = q̇ while t − t_s < T
               and the joint is inside its limits, else 0,

with t_s the time the state became available and T one frame period — the interval between the
stamps of the newest two states, at most ``safety.extrapolate_max_s`` (0 turns extrapolation off;
the first state, and a state with the same stamp, are never extrapolated further than before). So
q_nom never runs more than one frame ahead of the newest state, never leaves the joint limits, and
stops (holds, q̇_nom = 0) after that frame, on a joint whose angle is invalid (its rate is 0) and
wherever q_nom is clipped. A stale or lost person is the caller's business: it then holds q_cbf.

Used by the safety service and the offline evaluator alike (one implementation).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Nominal:
    """One human state's target: ``q`` (n,) rad and its rate ``dq`` (n,) rad/s from time ``since``
    (s, the caller's clock), extrapolated at most ``horizon`` s within [``q_min``, ``q_max``]."""

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
               q_min: np.ndarray, q_max: np.ndarray) -> Nominal:
        """A state with ``stamp`` (its own clock) took effect at ``since`` with target ``q`` and rate
        ``dq``, to be extrapolated within the joint limits [``q_min``, ``q_max``].

        The same stamp again (re-applied after a config change or a stale spell) keeps the first
        ``since`` and horizon, so it never extrapolates further than the first time.
        """
        cur = self.current
        if self._stamp is not None and stamp == self._stamp:
            since, horizon = cur.since, cur.horizon
        else:
            horizon = 0.0 if self._stamp is None else min(max(stamp - self._stamp, 0.0), max_horizon)
        self._stamp = stamp
        self.current = Nominal(np.asarray(q, float), np.asarray(dq, float), since, horizon,
                               np.asarray(q_min, float), np.asarray(q_max, float))
        return self.current

    def at(self, now: float) -> tuple[np.ndarray, np.ndarray]:
        return self.current.at(now)
