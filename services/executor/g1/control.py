"""What the G1 executor sends, tick by tick: hand-over ramps, limits and watchdogs (no I/O here).

:class:`G1Controller` turns imitation targets (the safety service's ``q_cbf``, ``u*``) and the
robot's measured state into one sealed ``unitree_hg`` LowCmd_ frame per tick
(:data:`~services.executor.g1.frames.LOWCMD_DTYPE`). The transport (:mod:`services.executor.g1.executor`)
only moves frames and states.

Phases::

    IDLE ──fresh command & fresh state──▶ RAMP_IN ──w = 1──▶ ACTIVE
      ▲                                     │                  │  command older than command_timeout_s,
      └──────────w = 0─────────── RAMP_OUT ◀┴──────────────────┘  state older than state_timeout_s,
                                     │ fault (latched)             stop(), or a fault
                                     ▼
                                   FAULT (w = 0 until restart)

The blend weight ``w`` ∈ [0, 1] moves linearly: 0 → 1 in ``ramp_in_s``, → 0 in ``ramp_out_s``, by
the time each tick covers, at most :data:`_MAX_STEP_PERIODS` control periods (a stalled loop resumes
the ramp where it was: the weight never jumps, as the targets never do).
``rt/arm_sdk``: ``w`` is sent in ``motor_cmd[29].q`` and the robot blends our upper-body command
with its balance controller's. ``rt/lowcmd``: there is no balance controller, so ``w`` scales the
stiffness (kp·w, kd kept): at 0 every motor only damps.

What is commanded: in ``arm_sdk`` mode all 17 upper-body motors (12–28) as Unitree's example does
(``arm_sdk_joints: upper_body``, the default), or the imitation joints only, so every other motor
keeps whatever the firmware makes of an unset slot (``imitation``); in ``lowcmd`` mode all 29. Imitated joints follow
the targets; every other commanded joint holds the pose measured when the ramp-in began. Motors the unit lacks (locked waist, 23-DoF wrists) are
never commanded. While IDLE the frame carries ``w = 0`` and the measured pose, so a ramp-in always
starts where the robot is.

Limits, imitated joints, every tick: the target is clipped into the joint range (hardware table ∩
robot description limits, ``position_margin`` inside the hardware range; in ``arm_sdk`` mode the waist
also within ``arm_sdk_waist_range``, because leaning over the balance controller tips the robot
forward: unitree_sdk2_python issues #146, #173), moves towards the newest
command at most ``max_speed`` (rad/s), and stays within ``torque_fraction · τ_max / kp`` of the
measured angle (so the PD torque stays below the motor's limit). Velocity feed-forward is the
command's ``dq`` clipped to ``max_speed``, 0 while the rate limit holds the target back.
Faults (latched: ramp out, stay out until restart): a commanded joint measured faster than
``fault_speed``; a commanded joint's estimated torque above its limit for
:data:`TORQUE_FAULT_SAMPLES` states in a row; a frame failing :func:`check_frame`.
Non-finite states are dropped and counted (they age into a state timeout).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterable
from enum import Enum
from typing import Any

import numpy as np

from services.executor.g1.errors import G1StartError
from services.executor.g1.frames import lowcmd_crc, new_lowcmd, seal
from services.executor.g1.layout import (
    ARM_SDK_HOLD_GAINS,
    ARM_SDK_SLOTS,
    G1_JOINTS,
    LOWCMD_HOLD_GAINS,
    NUM_BODY_MOTORS,
    WEIGHT_SLOT,
    joint_slot,
    variant_of,
)
from services.executor.g1.state import G1State
from shared.config import G1ArmSdkJoints, G1Config, G1LockedWaistPolicy, G1Mode, G1Waist
from shared.robot_spec import RobotSpec

__all__ = ["TORQUE_FAULT_SAMPLES", "G1Controller", "Phase", "check_frame"]

log = logging.getLogger("safemimic.executor.g1")

#: A commanded joint's |tau_est| above its torque limit in this many consecutive states is a fault.
TORQUE_FAULT_SAMPLES = 5
#: The rate limit never lets more than this many control periods of motion through in one tick
#: (a late tick does not turn into a jump).
_MAX_STEP_PERIODS = 2.0
#: Slack for float32 rounding in :func:`check_frame` (rad).
_CHECK_TOLERANCE = 1e-4
_WAIST_ROLL_PITCH = frozenset({13, 14})
#: A joint the unit cannot move should be limited to about this much either way in the robot description (rad).
_LOCKED_RANGE = 0.01


class Phase(str, Enum):
    IDLE = "idle"
    RAMP_IN = "ramp_in"
    ACTIVE = "active"
    RAMP_OUT = "ramp_out"
    FAULT = "fault"


def _absent_slots(mode_machine: int, waist: G1Waist) -> tuple[frozenset[int], str]:
    """Motor slots this unit lacks and a description of it; G1StartError when it cannot be told."""
    variant = variant_of(mode_machine)
    if variant is None and waist is G1Waist.AUTO:
        raise G1StartError(
            f"rt/lowstate reports mode_machine {mode_machine}, which is not in Unitree's G1 table, so whether "
            "the waist can move is unknown: set executor.g1.waist to 'locked' or 'unlocked'"
        )
    absent = variant.absent_slots if variant else frozenset()
    name = f"mode_machine {mode_machine} ({variant.name if variant else 'unknown variant'})"
    if waist is G1Waist.LOCKED:
        return absent | _WAIST_ROLL_PITCH, name + ", waist configured locked"
    if waist is G1Waist.UNLOCKED:
        if variant is not None and variant.waist_locked:
            log.warning("%s reports a locked waist, but executor.g1.waist is 'unlocked': commanding the waist", name)
        return absent - _WAIST_ROLL_PITCH, name + ", waist configured unlocked"
    return absent, name


class G1Controller:
    """The tick-by-tick logic of the G1 executor for the imitation joints of ``spec``.

    Call :meth:`attach` with the first state (it decides which motors exist), then per tick
    :meth:`update_state` (when a state arrived), :meth:`command` (when a target arrived) and
    :meth:`step`, which returns the frame to send. :meth:`begin_stop` ramps out for good; the ramp
    has ended when :attr:`finished`. ``period`` is the nominal control period (s).
    """

    def __init__(self, spec: RobotSpec, conf: G1Config, period: float) -> None:
        self.conf = conf
        self.period = period
        self.joint_names = tuple(spec.imitation_joints)
        try:
            self.slots = np.array([joint_slot(j) for j in self.joint_names])
        except ValueError as exc:
            raise G1StartError(f"the robot description {spec.name!r} does not fit the G1: {exc}") from None
        table = {j.slot: j for j in G1_JOINTS}
        lower, upper = [], []
        for name, slot in zip(self.joint_names, self.slots, strict=True):
            lo = table[slot].lower + conf.position_margin
            hi = table[slot].upper - conf.position_margin
            if name in spec.limits:
                lo, hi = max(lo, spec.limits[name][0]), min(hi, spec.limits[name][1])
            if conf.mode is G1Mode.ARM_SDK and name in conf.arm_sdk_waist_range:
                w_lo, w_hi = conf.arm_sdk_waist_range[name]
                wider = w_lo > lo or w_hi < hi  # the description the safety layer reads allows more
                log.log(logging.WARNING if wider else logging.INFO,
                        "arm_sdk: %s imitated within [%.2f, %.2f] rad (executor.g1.arm_sdk_waist_range: leaning over "
                        "the balance controller tips the robot)%s", name, max(lo, w_lo), min(hi, w_hi),
                        f"; the robot description given allows [{lo:.2f}, {hi:.2f}]: the safety layer plans within "
                        "this range only when it reads it too (shared.robot_spec.configured_robot_spec)" if wider else "")
                lo, hi = max(lo, w_lo), min(hi, w_hi)
            if not lo < hi:
                raise G1StartError(f"{name}: no admissible range left ({lo:.3f} ≥ {hi:.3f}) after position_margin "
                                 "and the robot description's limits")
            lower.append(lo)
            upper.append(hi)
        self.lower, self.upper = np.array(lower), np.array(upper)
        self.torque_limit = np.array([table[s].torque_limit for s in self.slots])
        self.q_home = np.clip([spec.home.get(j, 0.0) for j in self.joint_names], self.lower, self.upper)
        self.kp, self.kd = np.array(conf.kp), np.array(conf.kd)
        self.max_speed = np.array(conf.max_speed)
        self._hw_lower = np.array([j.lower for j in G1_JOINTS])
        self._hw_upper = np.array([j.upper for j in G1_JOINTS])
        self._hw_torque = np.array([j.torque_limit for j in G1_JOINTS])

        # decided by attach()
        self.unit = ""
        self.mode_machine = 0
        self.commanded = np.zeros(NUM_BODY_MOTORS, bool)  # slots we send to
        self.imitated = np.ones(len(self.slots), bool)  # imitation joints we can move
        self._slot_kp = np.zeros(NUM_BODY_MOTORS)
        self._slot_kd = np.zeros(NUM_BODY_MOTORS)
        self._slot_speed = np.zeros(NUM_BODY_MOTORS)  # how fast each slot's target may move (rad/s)
        self._slot_speed[self.slots] = self.max_speed

        self.phase = Phase.IDLE
        self.weight = 0.0
        self.state: G1State | None = None
        self._stopping = False
        self._last_step: float | None = None
        self._target = np.zeros(NUM_BODY_MOTORS)  # slot targets (rad)
        self._ff = np.zeros(NUM_BODY_MOTORS)  # slot velocity feed-forward (rad/s)
        self._desired = self.q_home.copy()  # newest commanded target, per imitation joint
        self._desired_dq = np.zeros(len(self.slots))
        self._damping = 1.0  # the imitated joints' kd scale of the newest command (stop_damping in a stop)
        self._command_time = -math.inf
        self._over_torque = np.zeros(NUM_BODY_MOTORS, int)
        self._last_frame = None
        self.counters: dict[str, Any] = {
            "ramp_ins": 0, "ramp_outs": {}, "faults": [], "commands": 0, "stop_commands": 0, "clipped_commands": 0,
            "waist_commands_dropped": 0, "max_waist_drop_rad": 0.0, "invalid_states": 0,
            "rate_limited_ticks": 0, "torque_clamped_ticks": 0, "frames_rejected": 0,
        }

    # setup ----------------------------------------------------------------------------------
    def attach(self, state: G1State) -> None:
        """Decide from the first state which motors this unit has and what to command; raises
        :class:`G1StartError` when an imitated joint cannot move and ``on_locked_waist`` is refuse."""
        absent, self.unit = _absent_slots(state.mode_machine, self.conf.waist)
        self.mode_machine = state.mode_machine
        if self.conf.mode is G1Mode.LOWCMD:
            channel: Iterable[int] = range(NUM_BODY_MOTORS)
        elif self.conf.arm_sdk_joints is G1ArmSdkJoints.IMITATION:
            channel = self.slots.tolist()
        else:
            channel = ARM_SDK_SLOTS
        self.commanded[:] = False
        self.commanded[[s for s in channel if s not in absent]] = True
        self.imitated = np.array([s not in absent for s in self.slots])
        dropped = [n for n, ok in zip(self.joint_names, self.imitated, strict=True) if not ok]
        if dropped and self.conf.on_locked_waist is G1LockedWaistPolicy.REFUSE:
            raise G1StartError(
                f"this G1 ({self.unit}) cannot move {dropped}, which the robot description imitates. "
                "Either set executor.g1.on_locked_waist: arms_only (those targets are then dropped and counted; "
                "also limit those joints to ±0.01 rad in the robot description so the safety layer does not count "
                "on them), or executor.g1.waist: unlocked if the waist is in fact free"
            )
        if dropped:
            log.warning("%s: imitating the arms only; targets for %s are dropped and counted", self.unit, dropped)
            wide = [n for n, lo, hi, ok in zip(self.joint_names, self.lower, self.upper, self.imitated, strict=True)
                    if not ok and hi - lo > 2 * _LOCKED_RANGE]
            if wide:
                log.warning("the robot description lets the safety layer move %s, which this unit cannot: limit them "
                            "to ±%.2f rad (limits: in the robot description) so it does not count on that motion",
                            wide, _LOCKED_RANGE)
        if self.conf.mode is G1Mode.ARM_SDK:
            self._slot_kp[:], self._slot_kd[:] = ARM_SDK_HOLD_GAINS
        else:
            self._slot_kp[:] = [g[0] for g in LOWCMD_HOLD_GAINS]
            self._slot_kd[:] = [g[1] for g in LOWCMD_HOLD_GAINS]
        self._slot_kp[self.slots] = self.kp
        self._slot_kd[self.slots] = self.kd
        self.update_state(state)
        log.info("G1 %s: %s mode, commanding slots %s, imitating %s", self.unit, self.conf.mode.value,
                 np.flatnonzero(self.commanded).tolist(), [n for n, ok in zip(self.joint_names, self.imitated) if ok])

    @property
    def dropped_joints(self) -> list[str]:
        return [n for n, ok in zip(self.joint_names, self.imitated, strict=True) if not ok]

    # inputs ---------------------------------------------------------------------------------
    def update_state(self, state: G1State) -> bool:
        """Take a new measurement; False (dropped, counted) when it holds NaN/Inf. Checks for a
        fault while the weight is above 0."""
        if not (np.isfinite(state.q).all() and np.isfinite(state.dq).all() and np.isfinite(state.tau_est).all()):
            self.counters["invalid_states"] += 1
            return False
        self.state = state
        if self.weight == 0.0 or self.faulted:  # only while we have authority; one fault is enough
            self._over_torque[:] = 0
        else:
            c = self.commanded
            fast = c & (np.abs(state.dq) > self.conf.fault_speed)
            self._over_torque = np.where(c & (np.abs(state.tau_est) > self._hw_torque), self._over_torque + 1, 0)
            if fast.any():
                self.fault(f"joint speed above {self.conf.fault_speed} rad/s at slots "
                           f"{np.flatnonzero(fast).tolist()}: {np.abs(state.dq[fast]).round(2).tolist()}")
            elif (self._over_torque >= TORQUE_FAULT_SAMPLES).any():
                slots = np.flatnonzero(self._over_torque >= TORQUE_FAULT_SAMPLES).tolist()
                self.fault(f"estimated torque above the motor limit at slots {slots}")
        return True

    def command(self, now: float, q: np.ndarray, dq: np.ndarray, stop: bool = False) -> np.ndarray:
        """New imitation target ``q`` (rad) with feed-forward ``dq`` (rad/s) at time ``now``;
        ``stop``: it is a protective stop, and until a command that is not, the imitated joints'
        kd is ``stop_damping`` times ``kd`` (the motor's τ = kp (q − q_m) + kd (dq − dq_m): the extra
        damping resists only a departure from the commanded velocity).

        Returns the target applied: ``q`` clipped into the joint ranges; joints this unit cannot
        move (locked waist) hold their home angle, and targets away from it are counted as dropped.
        """
        q = np.asarray(q, float)
        applied = np.clip(q, self.lower, self.upper)
        self.counters["clipped_commands"] += int(not np.array_equal(applied, q))
        if not self.imitated.all():
            held = ~self.imitated
            drop = np.abs(q[held] - self.q_home[held]).max()
            if drop > 1e-3:
                self.counters["waist_commands_dropped"] += 1
                self.counters["max_waist_drop_rad"] = max(self.counters["max_waist_drop_rad"], float(drop))
            applied[held] = self.q_home[held]
        self._desired = applied
        self._desired_dq = np.clip(np.asarray(dq, float), -self.max_speed, self.max_speed)
        self._command_time = now
        self._damping = self.conf.stop_damping if stop else 1.0
        self.counters["commands"] += 1
        self.counters["stop_commands"] += int(stop)
        return applied.copy()

    def begin_stop(self) -> None:
        """Ramp out and stay out (the executor is stopping)."""
        self._stopping = True
        if self.phase in (Phase.RAMP_IN, Phase.ACTIVE):
            self._enter(Phase.RAMP_OUT, "stop")

    def fault(self, reason: str) -> None:
        """Latch a fault: ramp out now, never ramp in again."""
        self.counters["faults"].append(reason)
        log.error("G1 fault: %s; ramping out and staying out until restart", reason)
        if self.phase in (Phase.RAMP_IN, Phase.ACTIVE):
            self._enter(Phase.RAMP_OUT, "fault")
        elif self.phase is Phase.IDLE:
            self._enter(Phase.FAULT, "fault")

    @property
    def finished(self) -> bool:
        """After :meth:`begin_stop`: the ramp-out is over (w = 0)."""
        return self._stopping and self.phase in (Phase.IDLE, Phase.FAULT)

    @property
    def faulted(self) -> bool:
        return bool(self.counters["faults"])

    # the tick ----------------------------------------------------------------------------------
    def step(self, now: float) -> np.ndarray | None:
        """The frame to send at monotonic time ``now`` (sealed with its CRC), or None when no frame
        passes :func:`check_frame` (then nothing may be sent; counted)."""
        if self.state is None:
            raise RuntimeError("G1Controller.step before attach()")
        dt = self.period if self._last_step is None else min(max(now - self._last_step, 0.0), _MAX_STEP_PERIODS * self.period)
        self._last_step = now
        self._advance_phase(now, dt)
        self._update_targets(dt)
        frame = self._frame()
        problems = self._check(frame)
        if problems:
            self.counters["frames_rejected"] += 1
            self.fault("frame check: " + "; ".join(problems))
            if self._last_frame is None:
                return None
            self._target[:] = self._last_frame["motor_cmd"]["q"][:NUM_BODY_MOTORS]
            self._ff[:] = 0.0
            frame = self._frame()
            if self._check(frame):
                return None
        self._last_frame = frame
        return frame

    def _check(self, frame: np.ndarray) -> list[str]:
        # targets are only bound to move smoothly while they have authority (w > 0)
        previous = self._last_frame if self.weight > 0.0 else None
        return check_frame(frame, self.commanded, previous, self._hw_lower, self._hw_upper,
                           self._slot_speed * _MAX_STEP_PERIODS * self.period)

    def _fresh_state(self, now: float) -> bool:
        return self.state is not None and now - self.state.received <= self.conf.state_timeout_s

    def _fresh_command(self, now: float) -> bool:
        return now - self._command_time <= self.conf.command_timeout_s

    def _enter(self, phase: Phase, reason: str) -> None:
        if phase is Phase.RAMP_IN:
            self.counters["ramp_ins"] += 1
        elif phase is Phase.RAMP_OUT:
            self.counters["ramp_outs"][reason] = self.counters["ramp_outs"].get(reason, 0) + 1
        log.info("G1 %s → %s (%s), weight %.3f", self.phase.value, phase.value, reason, self.weight)
        self.phase = phase

    def _advance_phase(self, now: float, dt: float) -> None:
        """The phase at ``now`` and the weight ramped by ``dt`` s (the tick's, capped: module docstring);
        a ramp entered at this tick starts from the weight it had."""
        ramping = self.phase
        if self.phase is Phase.IDLE and not self._stopping and not self.faulted:
            if self._fresh_command(now) and self._fresh_state(now):
                self._enter(Phase.RAMP_IN, "commands arriving")
        elif self.phase in (Phase.RAMP_IN, Phase.ACTIVE):
            if not self._fresh_state(now):
                self._enter(Phase.RAMP_OUT, "state timeout")
            elif not self._fresh_command(now):
                self._enter(Phase.RAMP_OUT, "command timeout")
        if self.phase is Phase.RAMP_IN:
            self.weight = min(1.0, self.weight + (dt if ramping is Phase.RAMP_IN else 0.0) / self.conf.ramp_in_s)
            if self.weight >= 1.0:
                self._enter(Phase.ACTIVE, "ramp-in done")
        elif self.phase is Phase.RAMP_OUT:
            self.weight = max(0.0, self.weight - (dt if ramping is Phase.RAMP_OUT else 0.0) / self.conf.ramp_out_s)
            if self.weight <= 0.0:
                self._enter(Phase.FAULT if self.faulted else Phase.IDLE, "ramp-out done")
        elif self.phase in (Phase.IDLE, Phase.FAULT):
            self.weight = 0.0

    def _update_targets(self, dt: float) -> None:
        assert self.state is not None
        measured = self.state.q
        if self.phase in (Phase.IDLE, Phase.FAULT):
            # a ramp-in starts where the robot is (a reading past a hard stop counts as at the stop)
            self._target[:] = np.where(self.commanded, np.clip(measured, self._hw_lower, self._hw_upper), 0.0)
            self._ff[:] = 0.0
            return
        if self.phase is Phase.RAMP_OUT:
            self._ff[:] = 0.0  # targets frozen while the weight falls
            return
        # desired → within torque reach of the measured angle → inside the range → rate limited.
        # The rate limit comes last: a fast push on the arm drags the goal, never the target.
        i = self.imitated
        joints = self.slots[i]
        desired = self._desired[i]
        reach = self.conf.torque_fraction * self.torque_limit[i] / self.kp[i]
        goal = np.clip(np.clip(desired, measured[joints] - reach, measured[joints] + reach), self.lower[i], self.upper[i])
        current = self._target[joints]
        step = self.max_speed[i] * dt
        target = current + np.clip(goal - current, -step, step)
        torque_held = np.abs(goal - desired) > 1e-9
        rate_held = np.abs(target - goal) > 1e-9
        self.counters["torque_clamped_ticks"] += int(torque_held.any())
        self.counters["rate_limited_ticks"] += int(rate_held.any())
        self._target[joints] = target
        self._ff[joints] = np.where(rate_held | torque_held, 0.0, self._desired_dq[i])

    def _frame(self) -> np.ndarray:
        frame = new_lowcmd()
        frame["mode_pr"] = 0  # pitch/roll joint convention, as in Unitree's examples
        frame["mode_machine"] = self.mode_machine
        motors = frame["motor_cmd"]
        c = np.flatnonzero(self.commanded)
        motors["mode"][c] = 1
        motors["q"][c] = self._target[c]
        if self.conf.mode is G1Mode.ARM_SDK:
            motors["dq"][c] = self._ff[c]
            motors["kp"][c] = self._slot_kp[c]
            motors["q"][WEIGHT_SLOT] = self.weight
        else:
            motors["dq"][c] = self.weight * self._ff[c]
            motors["kp"][c] = self.weight * self._slot_kp[c]
        kd = self._slot_kd.copy()
        kd[self.slots[self.imitated]] *= self._damping
        motors["kd"][c] = kd[c]
        return seal(frame)

    # reporting -----------------------------------------------------------------------------------
    def summary(self) -> dict[str, Any]:
        """Counters and the current phase (JSON-ready)."""
        return {"phase": self.phase.value, "weight": round(self.weight, 4), "unit": self.unit,
                "mode": self.conf.mode.value, "dropped_joints": self.dropped_joints, **self.counters}


def check_frame(frame: np.ndarray, commanded: np.ndarray, previous: np.ndarray | None,
                lower: np.ndarray, upper: np.ndarray, max_step: np.ndarray) -> list[str]:
    """Problems of a frame about to be sent (empty: fit to send).

    Checks: finite numbers; CRC; only ``commanded`` slots (bool, 29) enabled and carrying gains;
    targets inside the hardware range [``lower``, ``upper``] (rad, 29); blend weight in [0, 1];
    non-negative gains; each target within ``max_step`` (rad, 29; 0 for a held joint) of the
    ``previous`` frame's (None: not checked) where both command it.
    """
    problems: list[str] = []
    motors = frame["motor_cmd"]
    numbers = np.concatenate([motors[f].ravel() for f in ("q", "dq", "tau", "kp", "kd")])
    if not np.isfinite(numbers).all():
        return ["non-finite value"]
    if int(frame["crc"]) != lowcmd_crc(frame):
        problems.append("CRC mismatch")
    body = motors[:NUM_BODY_MOTORS]
    stray = ~commanded & ((body["mode"] != 0) | (body["kp"] != 0) | (body["kd"] != 0))
    if stray.any():
        problems.append(f"slots {np.flatnonzero(stray).tolist()} are not to be commanded")
    q = body["q"].astype(float)
    outside = commanded & ((q < lower - _CHECK_TOLERANCE) | (q > upper + _CHECK_TOLERANCE))
    if outside.any():
        problems.append(f"targets outside the joint range at slots {np.flatnonzero(outside).tolist()}")
    weight = float(motors["q"][WEIGHT_SLOT])
    if not 0.0 <= weight <= 1.0:
        problems.append(f"blend weight {weight} outside [0, 1]")
    if (body["kp"] < 0).any() or (body["kd"] < 0).any():
        problems.append("negative gains")
    if previous is not None:
        both = commanded & (previous["motor_cmd"]["mode"][:NUM_BODY_MOTORS] == 1)
        jump = both & (np.abs(q - previous["motor_cmd"]["q"][:NUM_BODY_MOTORS]) > max_step + _CHECK_TOLERANCE)
        if jump.any():
            problems.append(f"targets jump at slots {np.flatnonzero(jump).tolist()}")
    return problems
