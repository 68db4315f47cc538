"""What the executor service drives: a robot that servos the 8 imitation joints (architecture §1).

:class:`Executor` is the interface; :class:`~services.executor.mujoco.executor.MujocoExecutor`
(the MuJoCo simulation) implements it here, the G1 hardware adapter is the second
implementation. The service calls, once per control period: :meth:`Executor.apply_command`
(the target to hold), :meth:`Executor.tick` (advance the simulation / send the low-level
command), :meth:`Executor.read_state`. Angles in rad, velocities in rad/s, in the order of
:attr:`Executor.joint_names` (shared.names.IMITATION_JOINT_NAMES for the G1).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass

import numpy as np

from services.executor.contacts import ContactReport

__all__ = ["Executor", "JointReading"]


@dataclass(frozen=True)
class JointReading:
    """Measured imitation joint angles ``q`` (rad) and velocities ``dq`` (rad/s)."""

    q: np.ndarray
    dq: np.ndarray


class Executor(ABC):
    """A robot (simulated or real) taking joint position targets for the imitation joints.

    Lifecycle: :meth:`start`, then ticks, then :meth:`stop`. Not thread-safe: one control thread
    calls every method.
    """

    @property
    @abstractmethod
    def joint_names(self) -> tuple[str, ...]:
        """The imitation joints, in the order of every vector this interface takes or returns."""

    @property
    @abstractmethod
    def q_home(self) -> np.ndarray:
        """The home angles (rad): the target before any command arrives."""

    @abstractmethod
    def start(self) -> None:
        """Connect / open what the executor needs (idempotent)."""

    @abstractmethod
    def stop(self) -> None:
        """Release it (idempotent); the robot is left holding its last target."""

    @abstractmethod
    def apply_command(self, q: np.ndarray, dq: np.ndarray, ddq: np.ndarray | None = None,
                      stop: bool = False) -> np.ndarray:
        """Hold target angles ``q`` (rad) with velocity feed-forward ``dq`` (rad/s) from now on;
        ``ddq`` (rad/s²) the command's acceleration, for an executor that can feed it forward
        through the robot's inertia (None: zero). ``stop``: the command is a protective stop
        (:attr:`~shared.messages.JointCommand.protective_stop`), braking to rest: the servos damp
        with their ``stop_damping`` until a command that is not.

        Targets outside the joint ranges are clipped; returns the target applied.
        """

    @abstractmethod
    def tick(self) -> None:
        """One control period: a simulation advances its physics, hardware sends the command."""

    @abstractmethod
    def read_state(self) -> JointReading:
        """The newest measured joint state."""

    def set_human(self, capsules: np.ndarray, radii: np.ndarray, valid: np.ndarray) -> None:
        """Show the person's 7 capsules (robot frame, m) to a simulation; hardware ignores them."""

    def contacts(self) -> ContactReport | None:
        """Contacts found during the last tick; None where nobody can measure them (hardware)."""
        return None
