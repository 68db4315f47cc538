"""The first-order low-pass used for rates and point filters on both sides of the bus."""

from __future__ import annotations

import math

import numpy as np


def lowpass_gain(dt: float, cutoff_hz: float | np.ndarray) -> float | np.ndarray:
    """Gain α = 1/(1 + τ/Δt), τ = 1/(2π f_c), of a first-order low-pass at ``cutoff_hz`` sampled every ``dt`` s."""
    return 1.0 / (1.0 + 1.0 / (2.0 * math.pi * cutoff_hz * dt))
