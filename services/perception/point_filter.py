"""Point filter: per-keypoint smoothing (EMA or One Euro) with jump rejection, hold and reset (paper §II-A).

Every keypoint k is filtered independently, in the frame the points arrive in (metres, seconds):

* **present**: the measurement is finite and its confidence ≥ ``min_confidence``.
* **jump rejection**: a present point whose speed since its last *accepted* measurement,
  ‖x − x_acc‖ / (t − t_acc), exceeds ``max_speed`` is rejected (counted) and the point is held.
  Rejected measurements that agree with each other (the same speed bound between consecutive
  ones) for ``reacquire_frames`` frames re-anchor the point there (counted): the previous anchor
  was the outlier, or the person really moved that fast.
* **smoothing** (``kind``; the only step that differs between the two): x̂ ← x̂ + α (x − x̂) for an
  accepted point with history, Δt the frame period.

  - ``ema`` (the paper's): α = 1 − exp(−Δt/τ) (``ema_tau_s`` = τ; τ = 0: no smoothing). A point
    moving at constant velocity v is followed with the steady-state lag Δt (1 − α)/α seconds
    (≈ τ − Δt/2): x̂ = x − v·lag (:meth:`PointFilter.steady_state_lag`).
  - ``one_euro`` (Casiez, Roussel, Vogel, CHI 2012): the velocity ẋ = (x − x_acc)/(t − t_acc)
    from the previous accepted measurement (as the authors' reference code: raw samples) is
    low-passed, ẋ̂ ← ẋ̂ + α_d (ẋ − ẋ̂); the cut-off grows with its speed,
    f_c = ``min_cutoff_hz`` + ``beta``·‖ẋ̂‖ (one cut-off per keypoint from the 3-D speed, so the
    filter does not depend on the frame's orientation); α = 1/(1 + τ/Δt) with τ = 1/(2π f_c), and
    α_d the same with f_c = ``d_cutoff_hz``. ẋ̂ = 0 where a point is fresh; a held point keeps it.
    At constant velocity v (ẋ̂ = v) the steady-state lag is Δt (1 − α)/α = τ = 1/(2π (f_c,min + β v)):
    a still point is smoothed at ``min_cutoff_hz``, a fast one barely delayed.
* **hold**: a point without an accepted measurement is held for ``hold_s`` and valid until then,
  invalid afterwards; a point that returns after that starts afresh (no blending with stale data).
* **reset**: a frame more than ``reset_gap_s`` after the previous one, a frame whose time does not
  increase, or one flagged as a discontinuity (a replay loop restarting) resets every point.

``fresh[k]`` marks points (re)initialised this frame: they have no history, so velocities must
not be differenced across them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from shared.config import PointFilterConfig, PointFilterKind
from shared.lowpass import lowpass_gain


@dataclass(frozen=True)
class FilteredSkeleton:
    """Filter output at time ``t``: ``points`` (K, 3) (NaN where never seen), ``valid`` and ``fresh`` (K,)."""

    t: float
    points: np.ndarray
    valid: np.ndarray
    fresh: np.ndarray


class _Ema:
    """The paper's smoothing step: one gain α = 1 − exp(−Δt/τ) for every point."""

    def __init__(self, conf: PointFilterConfig, n_points: int) -> None:
        self.conf = conf

    def alpha(self, dt: float, speed: float = 0.0) -> float:
        tau = self.conf.ema_tau_s
        return 1.0 if tau <= 0.0 else -math.expm1(-dt / tau)

    def gains(self, dt: float, velocity: np.ndarray, update: np.ndarray, fresh: np.ndarray) -> float | np.ndarray:
        return self.alpha(dt)

    def reset(self) -> None:
        pass


class _OneEuro:
    """The One Euro smoothing step: per-point gain from the low-passed speed (module docstring)."""

    def __init__(self, conf: PointFilterConfig, n_points: int) -> None:
        self.conf = conf
        self._velocity = np.zeros((n_points, 3))  # ẋ̂ (m/s)

    def alpha(self, dt: float, speed: float = 0.0) -> float:
        return float(lowpass_gain(dt, self.conf.min_cutoff_hz + self.conf.beta * speed))

    def gains(self, dt: float, velocity: np.ndarray, update: np.ndarray, fresh: np.ndarray) -> float | np.ndarray:
        conf, smoothed = self.conf, self._velocity
        if dt <= 0.0:
            return 1.0
        smoothed += np.where(update[:, None], lowpass_gain(dt, conf.d_cutoff_hz) * (velocity - smoothed), 0.0)
        smoothed[fresh] = 0.0
        speed = np.sqrt(np.einsum("ij,ij->i", smoothed, smoothed))
        return lowpass_gain(dt, conf.min_cutoff_hz + conf.beta * speed)

    def reset(self) -> None:
        self._velocity[:] = 0.0


_SMOOTHING = {PointFilterKind.EMA: _Ema, PointFilterKind.ONE_EURO: _OneEuro}


class PointFilter:
    """Smoothing (EMA or One Euro) + jump rejection for K keypoints; counters ``rejected``,
    ``reacquired``, ``resets``. Assigning ``conf`` applies new parameters from the next frame on
    (a new ``kind`` starts its smoothing state afresh)."""

    def __init__(self, conf: PointFilterConfig, n_points: int) -> None:
        self.n_points = n_points
        self._smoothing: _Ema | _OneEuro | None = None
        self.conf = conf
        self.rejected = 0
        self.reacquired = 0
        self.resets = 0
        self._t: float | None = None
        self._estimate = np.full((n_points, 3), np.nan)
        self._accepted = np.zeros((n_points, 3))
        self._accepted_t = np.full(n_points, -np.inf)
        self._candidate = np.zeros((n_points, 3))
        self._candidate_t = np.full(n_points, -np.inf)
        self._candidate_n = np.zeros(n_points, dtype=np.int64)
        self._candidates_pending = False  # some _candidate_n > 0

    @property
    def conf(self) -> PointFilterConfig:
        return self._conf

    @conf.setter
    def conf(self, conf: PointFilterConfig) -> None:
        self._conf = conf
        kind = _SMOOTHING[conf.kind]
        if type(self._smoothing) is kind:
            self._smoothing.conf = conf
        else:
            self._smoothing = kind(conf, self.n_points)

    def steady_state_lag(self, dt: float, speed: float = 0.0) -> float:
        """Seconds behind a point moving steadily at ``speed`` (m/s), frame period ``dt``: Δt (1 − α)/α
        (EMA: independent of the speed; One Euro: 1/(2π (min_cutoff_hz + beta·speed)))."""
        alpha = self._smoothing.alpha(dt, speed)
        return dt * (1.0 - alpha) / alpha

    def reset(self) -> None:
        """Forget every point (the next frame initialises them)."""
        self._t = None
        self._estimate[:] = np.nan
        self._accepted_t[:] = -np.inf
        self._candidate_t[:] = -np.inf
        self._candidate_n[:] = 0
        self._candidates_pending = False
        self._smoothing.reset()

    def __call__(self, t: float, xyz: np.ndarray, confidence: np.ndarray, discontinuity: bool = False) -> FilteredSkeleton:
        """Filter one frame: ``xyz`` (K, 3) metres (NaN = missing), ``confidence`` (K,) in [0, 1]."""
        conf = self.conf
        if self._t is not None and (discontinuity or not (0.0 < t - self._t <= conf.reset_gap_s)):
            self.reset()
            self.resets += 1
        dt = 0.0 if self._t is None else t - self._t
        self._t = t

        # A row sum is finite iff all three coordinates are; NaN confidences compare False.
        present = np.isfinite(np.add.reduce(xyz, axis=1)) & (confidence >= conf.min_confidence)
        x = np.where(present[:, None], xyz, 0.0)
        since_accepted = t - self._accepted_t
        anchored = since_accepted <= conf.hold_s
        jump = present & anchored & (_squared_distance(x, self._accepted) > (conf.max_speed * since_accepted) ** 2)
        if jump.any():
            reacquire = self._track_candidates(t, x, jump)
            rejected = jump & ~reacquire
            self.rejected += int(rejected.sum())
            self.reacquired += int(reacquire.sum())
            accept = present & ~rejected
            fresh = accept & (~anchored | reacquire)
        else:
            if self._candidates_pending:
                self._candidate_n[:] = 0
            accept = present
            fresh = accept & ~anchored

        # x̂ ← x where fresh, x̂ + α (x − x̂) where accepted with history, unchanged elsewhere.
        estimate = self._estimate
        update = accept & ~fresh
        with np.errstate(invalid="ignore", divide="ignore"):  # rows outside ``update`` are not used
            velocity = (x - self._accepted) / (t - self._accepted_t)[:, None]
        alpha = self._smoothing.gains(dt, velocity, update, fresh)
        gain = np.where(fresh, 1.0, np.where(accept, alpha, 0.0))[:, None]
        np.copyto(estimate, 0.0, where=fresh[:, None])  # NaN-free before blending
        estimate += gain * (x - estimate)
        np.copyto(self._accepted, x, where=accept[:, None])
        np.copyto(self._accepted_t, t, where=accept)
        valid = (t - self._accepted_t) <= conf.hold_s
        return FilteredSkeleton(t=t, points=estimate.copy(), valid=valid, fresh=fresh)

    def _track_candidates(self, t: float, x: np.ndarray, jump: np.ndarray) -> np.ndarray:
        """Update the per-point run of mutually consistent rejected measurements; True: re-anchor."""
        speed_bound = self.conf.max_speed * (t - self._candidate_t)
        consistent = (self._candidate_n > 0) & (_squared_distance(x, self._candidate) <= speed_bound**2)
        self._candidate_n = np.where(jump, np.where(consistent, self._candidate_n + 1, 1), 0)
        np.copyto(self._candidate, x, where=jump[:, None])
        np.copyto(self._candidate_t, t, where=jump)
        reacquire = jump & (self._candidate_n >= self.conf.reacquire_frames)
        self._candidate_n[reacquire] = 0
        self._candidates_pending = bool(self._candidate_n.any())
        return reacquire


def _squared_distance(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    diff = a - b
    return np.einsum("ij,ij->i", diff, diff)
