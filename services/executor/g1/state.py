"""The robot's state as the G1's transport delivers it (``rt/lowstate``), for the controller."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["G1State"]


@dataclass(frozen=True)
class G1State:
    """One ``rt/lowstate`` sample: the 29 motors' ``q`` (rad), ``dq`` (rad/s), ``tau_est`` (N·m) in
    slot order, the unit's ``mode_machine``, and the local monotonic time it was received (s)."""

    q: np.ndarray
    dq: np.ndarray
    tau_est: np.ndarray
    mode_machine: int
    received: float
