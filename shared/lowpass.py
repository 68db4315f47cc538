"""The first-order low-pass used for rates and point filters on both sides of the bus."""

from __future__ import annotations

import math
from collections.abc import Sequence

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from shared.config import PoseAnglesConfig


def lowpass_gain(dt: float, cutoff_hz: float | np.ndarray) -> float | np.ndarray:
    """Gain α = 1/(1 + τ/Δt), τ = 1/(2π f_c), of a first-order low-pass at ``cutoff_hz`` sampled every ``dt`` s."""
    return 1.0 / (1.0 + 1.0 / (2.0 * math.pi * cutoff_hz * dt))


class RateFilter:
    """The rate at the newest sample of n signals sampled together, low-passed with a cut-off that
    grows with speed (the One Euro filter's idea, Casiez et al. CHI 2012, applied to a derivative).

    Per channel i, from the difference Δ_i = x_i(t) − x_i(t_prev) (the caller's, e.g. wrapped) over
    Δt = t − t_prev > 0, and the previous interval's slope s'_i over Δt' (when that difference was
    usable too):

        s_i = Δ_i / Δt,   ω_i = s_i + (s_i − s'_i) Δt / (Δt' + Δt)   (``second_order``; else ω_i = s_i),

    the slope at t of the parabola through the last three samples: exact for a constant acceleration,
    where the first-order difference is the rate half an interval back (Δt/2 late: 17 ms at 30 Hz).
    Then ω̂_i ← ω̂_i + α_i (ω_i − ω̂_i), α_i = 1/(1 + τ_i/Δt), τ_i = 1/(2π f_i),

        f_i = ``cutoff_hz`` + ``beta`` · |ω̂_i|   (ω̂_i before the update; ``beta`` Hz per unit/s),

    so a still channel (whose ω is noise) is smoothed at ``cutoff_hz`` and a fast one barely delayed.
    A channel whose difference is not usable returns 0 and restarts: its next usable difference is
    first order and its low-pass starts from 0. Outputs are finite for finite inputs.
    """

    def __init__(self, n: int, cutoff_hz: float, beta: float = 0.0, second_order: bool = False) -> None:
        self.configure(cutoff_hz, beta, second_order)
        # per channel, in Python floats (for a few channels numpy's cost per call was most of the work)
        self._rate = [0.0] * n  # ω̂ (unit/s)
        self._slope = [0.0] * n  # s' of the previous usable interval
        self._interval = [0.0] * n  # its Δt' (s); 0: none

    @property
    def rate(self) -> np.ndarray:
        """ω̂ (n,) unit/s, a fresh array."""
        return np.array(self._rate)

    def configure(self, cutoff_hz: float, beta: float = 0.0, second_order: bool = False) -> None:
        """New parameters from the next update on (the state is kept)."""
        self.cutoff_hz, self.beta, self.second_order = float(cutoff_hz), float(beta), bool(second_order)

    def reset(self, channels: Sequence[bool] | np.ndarray | None = None) -> None:
        """Restart the ``channels`` (n,) marked True (None: all): rate 0, no previous interval."""
        marked = [True] * len(self._rate) if channels is None else _as_list(channels)
        for i, restart in enumerate(marked):
            if restart:
                self._rate[i] = self._interval[i] = 0.0

    def update(self, dt: float, step: Sequence[float] | np.ndarray, usable: Sequence[bool] | np.ndarray) -> np.ndarray:
        """ω̂ (n,) after a sample ``dt`` s after the previous one (> 0) with differences ``step`` (n,);
        channels not ``usable`` (n,) restart (class docstring). Returns a fresh array."""
        cutoff, beta, second_order = self.cutoff_hz, self.beta, self.second_order
        rate, previous, interval = self._rate, self._slope, self._interval
        for i, (difference, use) in enumerate(zip(_as_list(step), _as_list(usable))):
            slope = difference / dt if use else 0.0
            omega = slope
            if second_order and interval[i] > 0.0:
                omega += (slope - previous[i]) * (dt / (interval[i] + dt))
            r = rate[i]
            r += lowpass_gain(dt, cutoff + beta * abs(r)) * (omega - r)
            previous[i] = slope
            rate[i], interval[i] = (r, dt) if use else (0.0, 0.0)
        return np.array(rate)


def _as_list(x: Sequence | np.ndarray) -> list:
    """``x`` (n,) as a list of Python scalars."""
    return x.tolist() if isinstance(x, np.ndarray) else list(x)


def angle_rate_parameters(conf: PoseAnglesConfig) -> tuple[float, float, bool]:
    """(cut-off Hz, β Hz per rad/s, second order) of ``perception.angles``' rate filter."""
    return conf.rate_cutoff_hz, conf.rate_beta, conf.rate_second_order


def angle_rate_filter(n: int, conf: PoseAnglesConfig) -> RateFilter:
    """The rate filter of ``perception.angles`` for n channels: the person's θ̇ and the retargeted
    rates that must trail the person alike."""
    return RateFilter(n, *angle_rate_parameters(conf))
