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
from collections.abc import Sequence
from dataclasses import dataclass
from itertools import chain

import numpy as np

from shared.config import PointFilterConfig, PointFilterKind
from shared.messages import MAX_COORD_M
from shared.lowpass import lowpass_gain

#: a point (x, y, z) in metres, or a velocity in m/s
Vec = Sequence[float]
#: the estimate of a point never seen (NaN: its ``points`` row)
_NEVER_SEEN: Vec = (math.nan, math.nan, math.nan)


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
        self._gain = 1.0  # α of this frame

    def alpha(self, dt: float, speed: float = 0.0) -> float:
        tau = self.conf.ema_tau_s
        return 1.0 if tau <= 0.0 else -math.expm1(-dt / tau)

    def begin_frame(self, dt: float) -> None:
        """A frame ``dt`` s after the previous one begins."""
        self._gain = self.alpha(dt)

    def gain(self, k: int, velocity: Vec) -> float:
        """α of point ``k``, accepted with history, its raw velocity ``velocity`` (m/s)."""
        return self._gain

    def restart(self, k: int) -> None:
        """Point ``k`` starts afresh."""

    def reset(self) -> None:
        pass


class _OneEuro:
    """The One Euro smoothing step: per-point gain from the low-passed speed (module docstring)."""

    def __init__(self, conf: PointFilterConfig, n_points: int) -> None:
        self.conf = conf
        self._velocity: list[Vec] = [(0.0, 0.0, 0.0)] * n_points  # ẋ̂ (m/s)
        # this frame's Δt, α_d, min_cutoff_hz and beta (:meth:`begin_frame`)
        self._dt = self._velocity_gain = self._min_cutoff = self._beta = 0.0

    def alpha(self, dt: float, speed: float = 0.0) -> float:
        return lowpass_gain(dt, self.conf.min_cutoff_hz + self.conf.beta * speed)

    def begin_frame(self, dt: float) -> None:
        """A frame ``dt`` s after the previous one begins (dt = 0: the first; no point has history)."""
        conf = self.conf
        self._dt, self._min_cutoff, self._beta = dt, conf.min_cutoff_hz, conf.beta
        if dt > 0.0:
            self._velocity_gain = lowpass_gain(dt, conf.d_cutoff_hz)

    def gain(self, k: int, velocity: Vec) -> float:
        """α of point ``k``, accepted with history, from its raw velocity ``velocity`` (m/s): ẋ̂ is
        updated and f_c = ``min_cutoff_hz`` + ``beta``·‖ẋ̂‖."""
        s0, s1, s2 = self._velocity[k]
        a_d = self._velocity_gain
        v0, v1, v2 = s0 + a_d * (velocity[0] - s0), s1 + a_d * (velocity[1] - s1), s2 + a_d * (velocity[2] - s2)
        self._velocity[k] = (v0, v1, v2)
        return lowpass_gain(self._dt, self._min_cutoff + self._beta * math.sqrt(v0 * v0 + v1 * v1 + v2 * v2))

    def restart(self, k: int) -> None:
        """Point ``k`` starts afresh: ẋ̂ = 0."""
        self._velocity[k] = (0.0, 0.0, 0.0)

    def reset(self) -> None:
        self._velocity = [(0.0, 0.0, 0.0)] * len(self._velocity)


_SMOOTHING = {PointFilterKind.EMA: _Ema, PointFilterKind.ONE_EURO: _OneEuro}


class PointFilter:
    """Smoothing (EMA or One Euro) + jump rejection for K keypoints; counters ``rejected``,
    ``reacquired``, ``resets``. Assigning ``conf`` applies new parameters from the next frame on
    (a new ``kind`` starts its smoothing state afresh).

    The state is kept per point in Python floats: for 15 points numpy's cost per call was most of
    the work (``python -m bench.run perception``)."""

    def __init__(self, conf: PointFilterConfig, n_points: int) -> None:
        self.n_points = n_points
        self._smoothing: _Ema | _OneEuro | None = None
        self.conf = conf
        self.rejected = 0
        self.reacquired = 0
        self.resets = 0
        self._t: float | None = None
        self._estimate: list[Vec] = [_NEVER_SEEN] * n_points
        self._accepted: list[Vec] = [(0.0, 0.0, 0.0)] * n_points
        self._accepted_t = [-math.inf] * n_points
        self._candidate: list[Vec] = [(0.0, 0.0, 0.0)] * n_points
        self._candidate_t = [-math.inf] * n_points
        self._candidate_n = [0] * n_points

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
        n = self.n_points
        self._t = None
        self._estimate = [_NEVER_SEEN] * n
        self._accepted_t = [-math.inf] * n
        self._candidate_t = [-math.inf] * n
        self._candidate_n = [0] * n
        self._smoothing.reset()

    def __call__(self, t: float, xyz: np.ndarray, confidence: np.ndarray, discontinuity: bool = False) -> FilteredSkeleton:
        """Filter one frame: ``xyz`` (K, 3) metres (NaN = missing), ``confidence`` (K,) in [0, 1]."""
        points, valid, fresh = self.update(t, xyz, confidence, discontinuity)
        return FilteredSkeleton(t=t, points=points_array(points), valid=np.array(valid, bool),
                                fresh=np.array(fresh, bool))

    def update(
        self, t: float, xyz: np.ndarray, confidence: np.ndarray, discontinuity: bool = False,
    ) -> tuple[list[Vec], list[bool], list[bool]]:
        """:meth:`__call__` with the output as new Python lists (points, valid, fresh), K each: what
        the perception pipeline hands on to the angle and capsule stages without array round trips."""
        conf = self.conf
        if self._t is not None and (discontinuity or not (0.0 < t - self._t <= conf.reset_gap_s)):
            self.reset()
            self.resets += 1
        dt = 0.0 if self._t is None else t - self._t
        self._t = t
        hold_s, max_speed, min_confidence = conf.hold_s, conf.max_speed, conf.min_confidence
        accepted, accepted_t, candidate_n = self._accepted, self._accepted_t, self._candidate_n
        estimate, smoothing = self._estimate, self._smoothing
        smoothing.begin_frame(dt)
        fresh = [False] * self.n_points
        for k, (x, c) in enumerate(zip(xyz.tolist(), confidence.tolist())):
            x0, x1, x2 = x
            # A sum is finite iff all three coordinates are; a NaN confidence compares False. A point
            # beyond MAX_COORD_M is no person's (a detector's garbage) and no HumanState could carry it.
            if not (math.isfinite(x0 + x1 + x2) and c >= min_confidence
                    and max(abs(x0), abs(x1), abs(x2)) <= MAX_COORD_M):
                candidate_n[k] = 0
                continue
            since = t - accepted_t[k]
            if since <= hold_s:  # anchored: its last accepted measurement is recent
                a0, a1, a2 = accepted[k]
                d0, d1, d2 = x0 - a0, x1 - a1, x2 - a2
                if d0 * d0 + d1 * d1 + d2 * d2 > (max_speed * since) ** 2:  # a jump
                    if not self._reacquires(k, t, x):
                        self.rejected += 1
                        continue
                    self.reacquired += 1
                else:  # accepted with history: x̂ ← x̂ + α (x − x̂)
                    candidate_n[k] = 0
                    g = smoothing.gain(k, (d0 / since, d1 / since, d2 / since))
                    e0, e1, e2 = estimate[k]
                    estimate[k] = (e0 + g * (x0 - e0), e1 + g * (x1 - e1), e2 + g * (x2 - e2))
                    accepted[k], accepted_t[k] = x, t  # x: this frame's own list
                    continue
            else:
                candidate_n[k] = 0
            # (re)initialised (fresh): x̂ ← x, no velocity history
            fresh[k] = True
            smoothing.restart(k)
            estimate[k] = accepted[k] = x
            accepted_t[k] = t
        return estimate[:], [t - a <= hold_s for a in accepted_t], fresh

    def _reacquires(self, k: int, t: float, x: Vec) -> bool:
        """Point ``k``'s rejected measurement ``x`` at ``t`` extends its run of mutually consistent
        rejected measurements (the same speed bound between consecutive ones) or starts one; True:
        the run is ``reacquire_frames`` long, re-anchor the point there."""
        bound = self.conf.max_speed * (t - self._candidate_t[k])
        consistent = self._candidate_n[k] > 0 and _squared_distance(x, self._candidate[k]) <= bound * bound
        count = self._candidate_n[k] + 1 if consistent else 1
        self._candidate[k], self._candidate_t[k] = x, t
        if count >= self.conf.reacquire_frames:
            self._candidate_n[k] = 0
            return True
        self._candidate_n[k] = count
        return False


def points_array(points: list[Vec]) -> np.ndarray:
    """``points`` (K tuples (x, y, z)) as a (K, 3) array."""
    return np.fromiter(chain.from_iterable(points), np.float64, 3 * len(points)).reshape(len(points), 3)


def _squared_distance(a: Sequence[float], b: Sequence[float]) -> float:
    d0, d1, d2 = a[0] - b[0], a[1] - b[1], a[2] - b[2]
    return d0 * d0 + d1 * d1 + d2 * d2
