"""The first-order low-pass used for rates and point filters on both sides of the bus."""

from __future__ import annotations

import math

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
        self.rate = np.zeros(n)  # ω̂ (unit/s)
        self._slope = np.zeros(n)  # s' of the previous usable interval
        self._interval = np.zeros(n)  # its Δt' (s); 0: none

    def configure(self, cutoff_hz: float, beta: float = 0.0, second_order: bool = False) -> None:
        """New parameters from the next update on (the state is kept)."""
        self.cutoff_hz, self.beta, self.second_order = float(cutoff_hz), float(beta), bool(second_order)

    def reset(self, channels: np.ndarray | slice = slice(None)) -> None:
        """Restart ``channels`` (all by default): rate 0, no previous interval."""
        self.rate[channels] = 0.0
        self._interval[channels] = 0.0

    def update(self, dt: float, step: np.ndarray, usable: np.ndarray) -> np.ndarray:
        """ω̂ (n,) after a sample ``dt`` s after the previous one (> 0) with differences ``step`` (n,);
        channels not ``usable`` (n,) restart (class docstring). Returns a copy."""
        slope = np.where(usable, step, 0.0) / dt
        omega = slope.copy()
        if self.second_order:
            known = self._interval > 0.0
            omega[known] += (slope[known] - self._slope[known]) * (dt / (self._interval[known] + dt))
        gain = lowpass_gain(dt, self.cutoff_hz + self.beta * np.abs(self.rate))
        self.rate += gain * (omega - self.rate)
        self._slope[:] = slope
        self._interval[:] = dt
        self.reset(~usable)
        return self.rate.copy()


def angle_rate_parameters(conf: PoseAnglesConfig) -> tuple[float, float, bool]:
    """(cut-off Hz, β Hz per rad/s, second order) of ``perception.angles``' rate filter."""
    return conf.rate_cutoff_hz, conf.rate_beta, conf.rate_second_order


def angle_rate_filter(n: int, conf: PoseAnglesConfig) -> RateFilter:
    """The rate filter of ``perception.angles`` for n channels: the person's θ̇ and the retargeted
    rates that must trail the person alike."""
    return RateFilter(n, *angle_rate_parameters(conf))
