"""The real Unitree G1 as an :class:`~services.executor.base.Executor` (``safemimic executor
--backend g1``), over CycloneDDS with unitree_sdk2's topics and messages.

Every tick: the newest ``rt/lowstate`` is taken, :class:`~services.executor.g1.control.G1Controller`
builds and checks one LowCmd_ frame (ramps, limits, watchdogs, CRC), and the frame goes out on
``rt/arm_sdk`` (default) or ``rt/lowcmd``. :meth:`G1Executor.start` waits for the robot's state and
refuses to start on an unfit unit; :meth:`G1Executor.stop` ramps out before it returns. In dry-run
mode nothing is ever published (no DDS writer exists): the frames are built and checked as for the
robot and one in every ``dry_run_print_s`` is printed as a JSON line.
"""

from __future__ import annotations

import json
import logging
import time
from types import ModuleType
from typing import Any

import numpy as np

from services.executor.g1.control import G1Controller
from services.executor.g1.errors import G1StartError
from services.executor.g1.state import G1State
from services.executor.g1.layout import TOPIC_ARM_SDK, TOPIC_LOWCMD, TOPIC_LOWSTATE
from services.executor.base import Executor, JointReading
from shared.config import G1Config, G1Mode
from shared.robot_spec import RobotSpec

__all__ = ["FINAL_FRAMES", "G1Executor"]

log = logging.getLogger("safemimic.executor.g1")

#: Frames with weight 0 (arm_sdk) or zero stiffness (lowcmd) sent after the stop ramp, one period apart.
FINAL_FRAMES = 10
#: Poll period while waiting for the first rt/lowstate (s).
_WAIT_POLL_S = 0.005
#: Samples taken from the rt/lowstate reader per tick (the newest one is used).
_TAKE = 8


class G1Executor(Executor):
    """A Unitree G1 following imitation targets through ``rt/arm_sdk`` or ``rt/lowcmd``.

    ``spec``: the robot description (imitation joints, home, limits); ``conf``: the ``executor.g1``
    section; ``period``: the control period (s) at which the service calls :meth:`tick`.
    """

    def __init__(self, spec: RobotSpec, conf: G1Config, period: float) -> None:
        self.conf = conf
        self.period = period
        self.controller = G1Controller(spec, conf, period)
        self.topic = TOPIC_ARM_SDK if conf.mode is G1Mode.ARM_SDK else TOPIC_LOWCMD
        self.frames_sent = 0
        self.frames_withheld = 0
        self.frames_printed = 0
        self.stop_tick_errors = 0
        self._dds: ModuleType | None = None  # services.executor.g1.dds, imported by start()
        self._link: Any = None
        self._reader: Any = None
        self._writer: Any = None
        self._next_print = 0.0

    @property
    def joint_names(self) -> tuple[str, ...]:
        return self.controller.joint_names

    @property
    def q_home(self) -> np.ndarray:
        return self.controller.q_home.copy()

    # lifecycle ---------------------------------------------------------------------------------
    def start(self) -> None:
        """Join the DDS domain, wait for the first ``rt/lowstate`` (``state_wait_s``) and check the
        unit (:class:`G1StartError` when there is no state or the unit is unfit)."""
        if self._link is not None:
            return
        try:
            from services.executor.g1 import dds as g1_dds
        except ImportError as exc:
            raise G1StartError(str(exc)) from None
        self._dds = g1_dds
        link = g1_dds.DdsLink(self.conf.domain_id, self.conf.network_interface)
        self._reader = link.reader(TOPIC_LOWSTATE, g1_dds.LowState_)
        self._writer = None if self.conf.dry_run else link.writer(self.topic, g1_dds.LowCmd_)
        self._link = link
        deadline = time.monotonic() + self.conf.state_wait_s
        state = None
        while state is None and time.monotonic() < deadline:
            time.sleep(_WAIT_POLL_S)
            state = self._take_state(time.monotonic())
        if state is None:
            self._release()
            raise G1StartError(
                f"no {TOPIC_LOWSTATE} within {self.conf.state_wait_s} s on DDS domain {link.domain_id} "
                f"(interface: {link.describe()['interface']}). Is the robot on, this computer on its network "
                "(e.g. 192.168.123.x), executor.g1.network_interface the interface facing it?"
            )
        try:
            self.controller.attach(state)
        except G1StartError:
            self._release()
            raise
        log.info("G1 executor ready: %s on %s%s, %s", self.controller.unit, self.topic,
                 " (DRY RUN: nothing is sent)" if self.conf.dry_run else "", link.describe())

    def stop(self) -> None:
        """Ramp out (``ramp_out_s``) while still ticking, send :data:`FINAL_FRAMES` more, leave DDS.

        A tick that raises (a DDS write failing, the very failure that may have stopped the service)
        is counted (``stop_tick_errors``) and the ramp goes on: the controller's weight falls with
        every tick whether its frame got out or not, so each frame that gets through carries the
        ramp's weight and the last ones weight 0; stopping at the first failure would leave the
        robot at the last frame's weight, possibly 1."""
        if self._link is None:
            return
        due = time.monotonic()
        self.controller.begin_stop()
        # on time the ramp takes ramp_out_s; late ticks advance it by 2 periods at most each (control.py)
        ramp_end = due + 3.0 * self.conf.ramp_out_s + 1.0
        final = 0
        while final < FINAL_FRAMES:
            try:
                self.tick()
            except Exception as exc:  # noqa: BLE001 - any failure: keep ramping out (docstring)
                if not self.stop_tick_errors:
                    log.error("G1 executor: a tick failed while ramping out (%s: %s); going on", type(exc).__name__, exc)
                self.stop_tick_errors += 1
            if self.controller.finished or time.monotonic() > ramp_end:
                final += 1
            due += self.period
            time.sleep(max(0.0, due - time.monotonic()))
        c = self.controller
        log.info("G1 executor stopped at weight %.3f (%s): %d frames sent, %d ramp-ins, ramp-outs %s, faults %s",
                 c.weight, c.phase.value, self.frames_sent, c.counters["ramp_ins"], c.counters["ramp_outs"],
                 c.counters["faults"])
        self._release()

    def _release(self) -> None:
        self._reader = self._writer = self._link = None  # CycloneDDS deletes the entities with them

    # the tick ------------------------------------------------------------------------------------
    def apply_command(self, q: np.ndarray, dq: np.ndarray, ddq: np.ndarray | None = None,
                      stop: bool = False) -> np.ndarray:
        """``ddq`` is not fed forward: the adapter has no inertia model of the real G1 (its PD gains
        and the velocity feed-forward follow the acceleration-bounded command)."""
        return self.controller.command(time.monotonic(), q, dq, stop)

    def tick(self) -> None:
        now = time.monotonic()
        state = self._take_state(now)
        if state is not None:
            self.controller.update_state(state)
        frame = self.controller.step(now)
        if frame is None:
            self.frames_withheld += 1
            return
        if self._writer is not None:
            self._writer.write(self._dds.frame_to_lowcmd(frame))
            self.frames_sent += 1
        elif now >= self._next_print:
            self._print_frame(frame)
            self._next_print = now + self.conf.dry_run_print_s

    def _take_state(self, now: float) -> G1State | None:
        samples = [s for s in self._reader.take(N=_TAKE) if isinstance(s, self._dds.LowState_)]
        return self._dds.lowstate_to_state(samples[-1], now) if samples else None

    def _print_frame(self, frame: np.ndarray) -> None:
        c = self.controller
        motors = frame["motor_cmd"]
        joints = {name: {f: round(float(motors[f][slot]), 4) for f in ("q", "dq", "kp", "kd")}
                  for name, slot, ok in zip(c.joint_names, c.slots, c.imitated, strict=True) if ok}
        print(json.dumps({
            "event": "g1_frame", "dry_run": True, "topic": self.topic, "phase": c.phase.value,
            "weight": round(c.weight, 4), "mode_machine": int(frame["mode_machine"]), "crc": f"0x{int(frame['crc']):08x}",
            "checked": True, "commanded_slots": np.flatnonzero(motors["mode"]).tolist(), "imitation": joints,
        }), flush=True)
        self.frames_printed += 1

    # state and reporting ------------------------------------------------------------------------
    def read_state(self) -> JointReading:
        """Measured imitation joints; joints the unit cannot move read as their home angle, at rest."""
        c = self.controller
        if c.state is None:
            return JointReading(self.q_home, np.zeros(len(c.slots)))
        q = np.where(c.imitated, c.state.q[c.slots], c.q_home)
        dq = np.where(c.imitated, c.state.dq[c.slots], 0.0)
        return JointReading(q, dq)

    def counters(self) -> dict[str, Any]:
        """What the G1 side did (JSON-ready): phase, ramps, faults, drops, frames."""
        return {"backend": "g1", "topic": self.topic, "dry_run": self.conf.dry_run, "frames_sent": self.frames_sent,
                "frames_withheld": self.frames_withheld, "frames_printed": self.frames_printed,
                "stop_tick_errors": self.stop_tick_errors, **self.controller.summary()}
