"""The MuJoCo simulation as an :class:`~services.executor.base.Executor`, with an optional
passive viewer window."""

from __future__ import annotations

import logging
import math
import os
import time
import warnings

import mujoco
import numpy as np

from services.executor.contacts import ContactReport
from services.executor.base import Executor, JointReading
from services.executor.mujoco.model import HUMAN_GEOM_GROUP, PDGains
from services.executor.mujoco.sim import SimRobot
from shared.robot_spec import RobotSpec

__all__ = ["MAX_PHYSICS_STEP_S", "MujocoExecutor", "open_viewer"]

log = logging.getLogger("safemimic.executor")

#: Longest physics step (s); a control period is split into equal steps no longer than this.
MAX_PHYSICS_STEP_S = 0.002
#: Viewer refresh rate (frames per second).
VIEWER_FPS = 60.0


def _display_error() -> str | None:
    """Why no window can open here, or None. GLFW is probed first because the viewer's own GLFW
    failure ends the process (MuJoCo's error handler exits) instead of raising."""
    if not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        return "neither DISPLAY nor WAYLAND_DISPLAY is set"
    try:
        import glfw  # a dependency of mujoco's viewer

        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            usable = glfw.init()
        if usable:
            glfw.terminate()
            return None
        return "GLFW cannot open the display: " + "; ".join(str(w.message) for w in caught)
    except Exception as exc:
        return f"GLFW is unusable ({type(exc).__name__}: {exc})"


def open_viewer(model: mujoco.MjModel, data: mujoco.MjData):  # -> mujoco.viewer.Handle | None
    """MuJoCo's passive viewer on ``model``/``data`` with the human capsules shown, or None (logged)
    when there is no usable display or the window cannot open. The caller steps; ``handle.sync()``
    shows the current state."""
    error = _display_error()
    if error is not None:
        log.warning("--viewer needs a display, but %s: running headless", error)
        return None
    try:
        from mujoco import viewer  # imported on demand: it loads GLFW

        handle = viewer.launch_passive(model, data)
    except Exception as exc:  # no OpenGL, GLFW cannot init, macOS without mjpython, ...
        log.warning("cannot open the MuJoCo viewer (%s: %s): running headless", type(exc).__name__, exc)
        return None
    with handle.lock():
        handle.opt.geomgroup[HUMAN_GEOM_GROUP] = 1
    return handle


class MujocoExecutor(Executor):
    """:class:`~services.executor.mujoco.sim.SimRobot` advanced by one control ``period`` (s) per tick.

    The period is split into ``ceil(period / MAX_PHYSICS_STEP_S)`` equal physics steps, so
    simulated time advances exactly one period per tick. ``viewer``: open MuJoCo's passive viewer
    at :meth:`start` (when a display exists; otherwise a warning and headless). ``people``: capsule
    sets in the scene (:class:`~services.executor.mujoco.sim.SimRobot`).
    """

    def __init__(self, spec: RobotSpec, gains: PDGains, period: float, viewer: bool = False, people: int = 1) -> None:
        if not period > 0:
            raise ValueError(f"control period must be > 0, got {period}")
        self.substeps = max(1, math.ceil(period / MAX_PHYSICS_STEP_S - 1e-9))
        self.sim = SimRobot(spec, gains, timestep=period / self.substeps, people=people)
        log.info("simulating %s: %d physics steps of %.2f ms per tick; robot-robot pairs touching at home "
                 "(excluded from contacts): %s", spec.model, self.substeps, 1e3 * self.sim.timestep,
                 [f"{a}|{b}" for a, b in self.sim.home_contacts] or "none")
        self._want_viewer = viewer
        self._viewer = None
        self._next_frame = 0.0

    @property
    def joint_names(self) -> tuple[str, ...]:
        return self.sim.joint_names

    @property
    def q_home(self) -> np.ndarray:
        return self.sim.q_home.copy()

    def start(self) -> None:
        if self._want_viewer and self._viewer is None:
            self._viewer = open_viewer(self.sim.model, self.sim.data)
            self._want_viewer = False  # one attempt: a failure was logged, a closed window stays closed

    def stop(self) -> None:
        if self._viewer is not None:
            self._viewer.close()
            self._viewer = None

    def apply_command(self, q: np.ndarray, dq: np.ndarray, ddq: np.ndarray | None = None,
                      stop: bool = False) -> np.ndarray:
        """The servos follow the command's trajectory over the coming period: ``q`` is where the
        joints should be at its end (:meth:`SimRobot.set_command` ``lead_s``)."""
        return self.sim.set_command(q, dq, ddq, lead_s=self.substeps * self.sim.timestep, stop=stop)

    def tick(self) -> None:
        self.sim.step(self.substeps)
        if self._viewer is not None:
            self._refresh_viewer()

    def read_state(self) -> JointReading:
        return JointReading(self.sim.q, self.sim.dq)

    def set_human(self, capsules: np.ndarray, radii: np.ndarray, valid: np.ndarray) -> None:
        self.sim.set_human(capsules, radii, valid)

    def contacts(self) -> ContactReport:
        return self.sim.contacts()

    def _refresh_viewer(self) -> None:
        now = time.monotonic()
        if now < self._next_frame:
            return
        if not self._viewer.is_running():
            log.info("viewer window closed: continuing headless")
            self._viewer = None
            return
        self._viewer.sync()
        self._next_frame = now + 1.0 / VIEWER_FPS
