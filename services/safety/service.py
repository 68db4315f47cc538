"""``safemimic safety``: the CBF safety service at a fixed control rate (architecture §1, §4, §5, §8).

Every tick (default 500 Hz, ``safety.rate_hz``):

1. apply a pending :class:`~shared.messages.ConfigUpdate` (validated in the subscriber, structural
   changes — robot, pair preset, QP backend — built off the control thread, swapped in here);
2. the newest :class:`~shared.messages.JointState`: the first one sets q_cbf to the target the
   executor holds (``q_command``; a restarted safety service continues where its predecessor
   stopped) or else the measured q. A later one more than :data:`RESYNC_TOLERANCE` rad from q_cbf on
   any joint (robot pushed, executor restarted) starts a *resync*: q_nom becomes the measured q until
   q_cbf is within :data:`RESYNC_DONE` of it, so q_cbf moves there through the CBF-QP at ≤ u_max,
   never in a jump;
3. the newest :class:`~shared.messages.HumanState`: its capsules become the barrier's external
   capsules (held until the next one) and θ is retargeted to q_nom, θ̇ to q̇_nom (S ⊙ θ̇, 0 where
   clipped or invalid); between camera frames q_nom moves towards the newest state extrapolated by
   q̇_nom one frame period ahead (:mod:`services.safety.nominal`, ``safety.target_path``), and that
   path's velocity is fed forward (``safety.feedforward``,
   u_ref = q̇_nom + K (q_nom − q_cbf)). No human yet: no external capsules,
   q_nom = q_cbf (hold). A capsule that turns invalid is held from memory for
   ``safety.lost_human_hold_s`` (:class:`~services.safety.human_memory.HumanMemory`).
4. one CBF-QP step with Δt = the nominal period; the command (q_cbf, u*) is checked finite and
   published on ``robot/command`` (a non-finite one is replaced by the last command, counted).
   Every command differs from the previous one by at most u_max·Δt per joint, except on the ticks
   of a stop that first move q_cbf by at most u_max·Δt more onto the robot's measured joints
   (a protective stop's first, the first after a command aiming at rest is at rest, and after it those
   at which a servo would push its joint along its motion; the newest
   JointState extrapolated by its dq, :meth:`_robot_at`; the filter's module docstring says why),
   which the command says (``JointCommand.settled``);
5. at ``safety.status_rate_hz``, a :class:`~shared.messages.SafetyStatus`, with that tick's q_nom
   and the pairs whose rows bind at its u* (:func:`~services.safety.filter.binding_rows`).

Watchdogs (:mod:`services.safety.watchdogs`: ``human_state``, ``human_source``, ``human_lost``,
``joint_state``, ``executor_command``, ``resync``), each shown in SafetyStatus and counted in
``watchdog_trips`` when it trips.

Scheduling is absolute (tick k is due at start + k·Δt) and the thread sleeps on a
``threading.Event`` between ticks — never a busy loop, which would hold the GIL and delay the
Zenoh callbacks (architecture §8). A tick that completes after the next tick's due time is a deadline
miss; tick slots skipped entirely after a long stall are misses too and the schedule moves on
(keeping its phase) instead of bursting to catch up.
"""

from __future__ import annotations

import argparse
import dataclasses
import gc
import logging
import math
import sys
import threading
import time
from collections import Counter
from dataclasses import dataclass
from typing import Any

import numpy as np

from services.safety.assembly import SafetyPipeline, build_pipeline, make_retargeter
from services.safety.filter import FilterParams, StepResult, binding_rows
from services.safety.human_memory import HumanMemory
from services.safety.nominal import NominalTrack, frame_stamp
from services.safety.watchdogs import Watchdogs
from shared.bus import Bus, Latest, Newest, Received
from shared.realtime import DEFAULT_RT_PRIORITY, realtime
from shared.schedule import FixedRateSchedule
from shared.service import Pending, Refusals, ScheduledService, StepErrors, StepTimes, validated_update
from shared.cli_args import add_bus_arguments, config_from_args
from shared.config import RetargetMethod, StackConfig
from shared.messages import ConfigUpdate, HumanState, JointCommand, JointState, SafetyMode, SafetyStatus
from shared.stop_signals import stop_on_signals

log = logging.getLogger("safemimic.safety")

SERVICE_NAME = "safety"
#: The liveliness token (``alive/{name}``) of the human source: while it is absent the human is stale.
HUMAN_SOURCE_SERVICE = "perception"
#: |q_measured − q_cbf| (rad) on any joint above which q_cbf is brought back to the robot (a resync).
RESYNC_TOLERANCE = 0.3
#: A resync ends when q_cbf is within this (rad, every joint) of the measured q.
RESYNC_DONE = 0.05
#: A JointState whose q (or q_command) lies further than this (rad) outside the joint limits is not
#: a robot's: refused and counted (a joint rests a little past its limit, pressed, never this far).
OUTSIDE_LIMITS_REFUSED = 0.1
#: The executor whose JointState the loop waits for at start (when its liveliness token is present).
EXECUTOR_SERVICE = "executor"
#: At start, how long to wait for a live executor's first JointState (s): a restarted safety service
#: then continues from the target the executor holds instead of commanding home first.
EXECUTOR_WAIT_S = 2.0
#: At start, no executor liveliness token within this (s): start without a joint state.
EXECUTOR_DISCOVERY_S = 0.5
#: The frame HumanState capsules must be expressed in (the robot frame, z up, floor at 0).
#: GIL switch interval of the service process (s): bounds how long the control thread waits for
#: a Zenoh callback thread holding the GIL (CPython's default is 5 ms, 2.5 periods at 500 Hz).
SWITCH_INTERVAL_S = 0.0005
#: Step times kept for the exit summary's percentiles (a ring buffer: 20 s at 500 Hz).
_STEP_TIME_WINDOW = 10_000
#: At most one deadline-miss warning per this many seconds (never per tick).
_MISS_LOG_INTERVAL_S = 5.0
#: Unexpected exceptions in consecutive ticks after which the service gives up (a bug, not noise).
_MAX_CONSECUTIVE_ERRORS = 100


#: safety.* fields applied in place at the next tick: the filter's parameters (FilterParams, same
#: names as in SafetyConfig) and the ones this service reads every tick. A change to any other
#: robot.* or safety.* field (model, pair preset, backend, and whatever is added later) rebuilds
#: the pipeline, so no setting is ever silently ignored.
_HOT_SAFETY_FIELDS = frozenset(f.name for f in dataclasses.fields(FilterParams)) | {
    "rate_hz", "status_rate_hz", "human_timeout_s", "human_velocity_term", "lost_human_hold_s",
    "human_predict_s",
    "feedforward", "extrapolate_max_s", "target_path",
}


def needs_new_pipeline(old: StackConfig, new: StackConfig) -> bool:
    """Whether going from ``old`` to ``new`` needs a rebuilt pipeline (else: parameters in place)."""
    if new.robot != old.robot:
        return True
    before, after = old.safety.model_dump(), new.safety.model_dump()
    changed = {name for name in before.keys() | after.keys() if before.get(name) != after.get(name)}
    return bool(changed - _HOT_SAFETY_FIELDS)


def _finite_or_none(value: float | None) -> float | None:
    return value if value is not None and math.isfinite(value) else None


@dataclass
class _PendingConfig:
    """An accepted configuration waiting for the next tick (pipeline: a rebuilt one, or None)."""

    version: int
    conf: StackConfig
    pipeline: SafetyPipeline | None


class SafetyService(ScheduledService):
    """The safety service's state and one control tick; :meth:`run` drives it at the fixed rate.

    ``bus`` defaults to a new :class:`~shared.bus.Bus` from ``conf.bus`` (closed by :meth:`close`).
    Inputs: ``human`` (:class:`~shared.bus.Newest`: decoded when a tick reads it), ``joint_state``
    (a :class:`~shared.bus.Latest` holder fed by the bus) and
    :meth:`on_config` (the ``config`` subscriber). :meth:`tick` runs one control step.
    The public counters (``ticks``, ``deadline_misses``, ``watchdogs.trips``, ``nonfinite_holds``,
    ``config_version``) and :meth:`counters` describe what happened so far.
    """

    def __init__(self, conf: StackConfig, bus: Bus | None = None) -> None:
        self.conf = conf
        self.pipeline = build_pipeline(conf)
        self.pipeline.warm_up(self.period)
        # control state
        self.ticks = 0
        self.schedule = FixedRateSchedule(self.period)
        self.watchdogs = Watchdogs(log)
        self.nonfinite_holds = 0
        self.config_version = 0
        self.tick_errors = StepErrors(log, "safety tick", _MAX_CONSECUTIVE_ERRORS)
        self.modes: Counter[str] = Counter()
        self.step_times = StepTimes(_STEP_TIME_WINDOW)
        self._q_nom = self.pipeline.filter.q_cbf.copy()  # retargeted from the newest human state
        self._nominal = NominalTrack(self._q_nom)  # ... and extrapolated between frames
        self._last_q = self.pipeline.filter.q_cbf.copy()  # last published command
        self._human_used: Received[HumanState] | None = None  # the human state the barrier holds
        self._human_stale = False
        self._memory = HumanMemory()  # the barrier's external capsules: held while a person is lost
        self._human_source_lost = False  # the perception service's liveliness token went away
        self._executor_seen = False  # an executor's liveliness token has been seen
        self._human_dirty = True  # re-apply the human state (new message, config change)
        self._joint_state_seen: Received[JointState] | None = None  # the newest accepted
        self._joint_state_looked: Received[JointState] | None = None  # the newest looked at
        self._synced = False
        self._resync_target: np.ndarray | None = None  # measured q that q_nom follows during a resync
        self._next_status = -math.inf
        self._relaxed_since_status: set[str] = set()  # pairs that gave way since the last status
        self._intrusion_since_status = False
        self._backing_out_since_status = False  # the intrusion stop backed out of a still person since the last status

        # inputs, fed by the bus (Zenoh threads); everything above exists before the first callback
        self.refusals = Refusals()  # and valid messages we refused (config, frame, output)
        self._pending: Pending[_PendingConfig] = Pending()
        self.open_bus(conf, SERVICE_NAME, bus)
        try:
            self._command_pub = self.bus.publisher("robot/command")
            self._status_pub = self.bus.publisher("safety/status")
            # decoded when a tick reads it: a burst of human states costs the loop no GIL (HumanState
            # is validated in the robot frame)
            self.human: Newest[HumanState] = self.bus.newest("human/state")  # type: ignore[assignment]
            self.joint_state: Latest[JointState] = self.bus.latest("robot/joint_state")  # type: ignore[assignment]
            self.bus.subscribe("config", self.on_config)
            self.bus.watch_alive(self.on_alive)
            self.bus.declare_alive(SERVICE_NAME)
        except Exception:
            self.close()
            raise

    @property
    def period(self) -> float:
        """The nominal control period Δt (s)."""
        return 1.0 / self.conf.safety.rate_hz

    @property
    def resyncs(self) -> int:
        """Resyncs started so far (the robot was found more than RESYNC_TOLERANCE from q_cbf)."""
        return self.watchdogs.trips["resync"]

    # subscriber callbacks (Zenoh threads) ---------------------------------------------------
    def on_alive(self, service: str, alive: bool) -> None:
        """Liveliness of another service: the human source's token vanishing makes the human stale at once."""
        if service == EXECUTOR_SERVICE and alive:
            self._executor_seen = True
        if service == HUMAN_SOURCE_SERVICE and self._human_source_lost == alive:
            self._human_source_lost = not alive
            if alive:
                log.info("human source %s is back (liveliness)", service)
            else:
                log.warning("human source %s lost (liveliness token gone): human state is stale", service)

    def on_config(self, update: ConfigUpdate) -> None:
        """Validate an update; build a new pipeline here if the structure changed; queue it.

        An update older than the one applied or queued is refused and counted: versions only grow
        (the config API numbers past any it saw reported), so a lower one is a delayed copy or a
        second writer, and applying it would roll back a change already acknowledged."""
        queued = self._pending.peek()
        newest = max(self.config_version, queued.version if queued else 0)
        if update.version < newest:
            self.refusals.refuse("config")
            log.warning("refused config update v%d: v%d is newer (a delayed update or a second writer)",
                        update.version, newest)
            return
        new = validated_update(update, self.refusals, log)
        if new is None:
            return
        # The session and the key expressions are fixed for this process's life.
        if new.bus != self.conf.bus or new.robot_id != self.conf.robot_id:
            new = new.model_copy(update={"bus": self.conf.bus, "robot_id": self.conf.robot_id})
        queued = self._pending.peek()
        reference = queued.conf if queued else self.conf
        pipeline = queued.pipeline if queued else None
        if needs_new_pipeline(reference, new):
            try:
                pipeline = build_pipeline(new)
                # here, off the control thread, near the live operating point
                human = self.human.get()
                pipeline.warm_up(1.0 / new.safety.rate_hz, self._last_q, human.message if human is not None else None)
            except Exception as exc:  # a model that does not load, an unknown preset, ...
                self.refusals.refuse("config")
                log.warning("rejected config update v%d: cannot build the safety pipeline: %s", update.version, exc)
                return
        else:
            try:  # applied in place: the velocity bounds must still fit the robot
                (pipeline or self.pipeline).spec.check_velocity_bounds(new.safety.u_max, new.safety.u_min)
            except ValueError as exc:
                self.refusals.refuse("config")
                log.warning("rejected config update v%d: %s", update.version, exc)
                return
        self._pending.put(_PendingConfig(update.version, new, pipeline))

    # control tick (the loop's thread) -------------------------------------------------------
    def tick(self, now: float | None = None) -> StepResult:
        """One control step at monotonic time ``now``: inputs → CBF-QP → command (+ status when due)."""
        started = time.perf_counter()
        now = time.monotonic() if now is None else now
        self._apply_pending_config()
        self._sync_joint_state(now)
        human = self._update_human(now)
        pipeline = self.pipeline
        dq_nom = None
        if self._resync_target is not None:
            q_nom = self._resync_target
        elif human is not None and not self._human_stale and not self._memory.lost:
            q_nom, dq = self._nominal.at(now)
            dq_nom = dq if self.conf.safety.feedforward else None
        else:  # no person, not a current one, or part of one lost: stop imitating, keep avoiding
            q_nom = pipeline.filter.q_cbf.copy()
        result = pipeline.filter.step(q_nom, self.period, dq_nom, self._robot_at(now))

        q, u, ddq, mode = result.q_cbf, result.u, result.ddq, result.mode
        settled, stop = result.settled, result.protective_stop
        if not (np.isfinite(q).all() and np.isfinite(u).all() and np.isfinite(ddq).all()):  # the filter promises this never happens
            self.nonfinite_holds += 1
            self.refusals.refuse("robot/command")
            q, u, ddq, mode = self._last_q.copy(), np.zeros_like(self._last_q), np.zeros_like(self._last_q), SafetyMode.HOLD
            settled, stop = False, True  # held at rest: a stop
            pipeline.filter.reset(q)
        message = human.message if human is not None else None
        self._command_pub.put(
            JointCommand(
                stamp=now, q=q, dq=u, ddq=ddq, mode=mode,
                human_stamp=message.stamp if message is not None else None,
                human_seq=message.seq if message is not None else None, settled=settled,
                protective_stop=stop,
            )
        )
        self._last_q = q.copy()
        self.modes[mode.value] += 1
        self.step_times.record(time.perf_counter() - started)
        self.ticks += 1
        self._relaxed_since_status.update(result.gave_way)
        self._intrusion_since_status |= result.intrusion
        self._backing_out_since_status |= result.backing_out
        if now >= self._next_status:
            self._publish_status(now, result, mode, q_nom)
            status_period = 1.0 / self.conf.safety.status_rate_hz
            self._next_status = max(self._next_status + status_period, now + 0.5 * status_period)
        return result

    def _apply_pending_config(self) -> None:
        pending = self._pending.take()
        if pending is None:
            return
        old, new = self.conf, pending.conf
        old_retargeter = self.pipeline.retargeter
        if pending.pipeline is not None and pending.pipeline is not self.pipeline:
            q_cbf = self.pipeline.filter.q_cbf
            self.pipeline = pending.pipeline
            self.pipeline.filter.reset(q_cbf)
        else:
            self.pipeline.filter.params = FilterParams.from_config(new.safety)
            self.pipeline.barrier.person_margin = new.safety.human_margin  # from the next human state on
            # the retargeting by directions also reads the safety section (self pairs, φ, u_max) and θ̇'s low-pass
            by_directions = new.retargeting.method == RetargetMethod.DIRECTIONS
            if new.retargeting != old.retargeting or by_directions and (
                    (new.safety, new.perception.angles) != (old.safety, old.perception.angles)):
                self.pipeline.retargeter = make_retargeter(new, self.pipeline.spec, self.pipeline.retarget_kinematics)
        retargeter = self.pipeline.retargeter
        if retargeter is not old_retargeter:
            # Joints whose angles the new retargeter has not seen valid yet keep the current q_nom
            # (the retargeter's hold value, which it otherwise initialises to home).
            retargeter.hold(self._q_nom)
        self.conf = new
        self.config_version = pending.version
        self._human_dirty = True
        self._next_status = -math.inf  # report the applied version right away
        log.info("applied config v%d (rate %.0f Hz, backend %s, pairs %s)", pending.version,
                 new.safety.rate_hz, new.safety.backend.value, new.safety.pairs)

    def _sync_joint_state(self, now: float) -> None:
        """The joint-state and executor watchdogs; the first sync of q_cbf; resync start and end.

        A joint state further than :data:`OUTSIDE_LIMITS_REFUSED` outside the joint limits is refused
        and counted: it is neither the robot the filter settles on nor fresh for the watchdog."""
        received = self.joint_state.get()
        filt = self.pipeline.filter
        fresh = received is not None and received is not self._joint_state_looked
        if fresh:
            self._joint_state_looked = received
            outside = max(float(np.max(np.maximum(filt.q_min - q, q - filt.q_max)))
                          for q in (received.message.q, received.message.q_command) if q is not None)
            if outside > OUTSIDE_LIMITS_REFUSED:
                self.refusals.refuse("robot/joint_state")
                if self.refusals.own("robot/joint_state") == 1:  # once: at 200 Hz a log line each would flood
                    log.warning("refused a joint state %.2f rad outside the joint limits (not a robot's); further "
                                "ones are counted in the status's dropped['robot/joint_state']", outside)
                fresh = False
            else:
                self._joint_state_seen = received
        accepted = self._joint_state_seen
        if accepted is None:
            return
        age = now - accepted.received
        self.watchdogs.watch("joint_state", age > self.conf.safety.joint_state_timeout_s, f"newest is {age:.3f} s old")
        if not fresh:
            return
        message = accepted.message
        self.watchdogs.watch("executor_command", message.command_stale, "the executor holds its last target")
        if not self._synced:
            self._synced = True
            if self.ticks == 0:  # nothing commanded yet: continue from where the executor is, no jump
                filt.reset(message.q_command if message.q_command is not None else message.q)
                log.info("q_cbf synchronised to the executor's %s",
                         "target" if message.q_command is not None else "measured q")
                return
            # commands already went out from q_cbf (an executor that came late): jumping q_cbf to it
            # would break the rate limit; a robot elsewhere is joined at ≤ u_max, as any displaced one
            log.info("the executor's first joint state came after %d ticks: joined through the resync", self.ticks)
        deviation = float(np.max(np.abs(message.q - filt.q_cbf)))
        if self._resync_target is None and not self.watchdogs.watch("resync", deviation > RESYNC_TOLERANCE,
                                                          f"measured q is {deviation:.2f} rad from q_cbf"):
            return
        if deviation <= RESYNC_DONE:
            self._resync_target = None
            self.watchdogs.watch("resync", False)
        else:
            self._resync_target = np.clip(message.q, filt.q_min, filt.q_max)

    def _robot_at(self, now: float) -> np.ndarray | None:
        """The robot's joints at monotonic time ``now`` (rad): the newest JointState's q extrapolated
        by its dq over the time since it arrived (a state period at most, 5 ms at 200 Hz, while the
        executor is live); None before the first one or while the ``joint_state`` watchdog is tripped.
        The filter brings q_cbf there as a protective stop begins and once a command aiming at rest
        is at rest (:meth:`SafetyFilter.step`)."""
        received = self._joint_state_seen
        if received is None or self.watchdogs.tripped("joint_state"):
            return None
        return received.message.q + received.message.dq * (now - received.received)

    def _update_human(self, now: float) -> Received[HumanState] | None:
        """Put the newest human state into the barrier and q_nom; None while there never was one."""
        received = self.human.get()
        if received is None:
            if self._human_dirty:
                self.pipeline.barrier.set_external(None)
                self._human_dirty = False
            return None
        source_lost = self.watchdogs.watch("human_source", self._human_source_lost, "perception's liveliness token is gone")
        age = now - received.received
        timed_out = self.watchdogs.watch("human_state", age > self.conf.safety.human_timeout_s, f"newest is {age:.2f} s old")
        stale = source_lost or timed_out
        if received is self._human_used and stale == self._human_stale and not self._human_dirty:
            return received
        message = received.message
        safety = self.conf.safety
        self._memory.update(message, received.received, safety.lost_human_hold_s)
        self.pipeline.barrier.set_external(*self._memory.capsules(self.pipeline.pairs.n_external, safety.human_velocity_term,
                                                                  safety.human_predict_s, stale))
        if not stale:  # stale: the tick stops imitating (q_nom = q_cbf)
            retargeter = self.pipeline.retargeter
            self._q_nom, dq_nom = retargeter.track(message)
            self._nominal.update(self._q_nom, dq_nom, frame_stamp(message), received.received,
                                 safety.extrapolate_max_s, retargeter.q_min, retargeter.q_max, safety.target_path)
        self._human_used, self._human_stale, self._human_dirty = received, stale, False
        self.watchdogs.watch("human_lost", self._memory.lost, f"held: {', '.join(self._memory.lost_capsules)}")
        return received

    def _publish_status(self, now: float, result: StepResult, mode: SafetyMode, q_nom: np.ndarray) -> None:
        rows = result.rows
        binding: list[str] = []
        if mode in (SafetyMode.ACTIVE, SafetyMode.RELAXED):
            names = self.pipeline.pairs.names
            binding = sorted({names[i] for i in self.pipeline.barrier.row_pair[binding_rows(rows, result.u)]})
        self._status_pub.put(
            SafetyStatus(
                stamp=now,
                mode=mode,
                min_h_self=_finite_or_none(result.min_h_self),
                min_h_human=_finite_or_none(rows.min_h(False)),
                active_constraints=int(result.active_rows),
                total_constraints=int(np.count_nonzero(rows.enabled)),
                qp_solve_time_ms=max(0.0, result.qp_time_s * 1e3) if math.isfinite(result.qp_time_s) else 0.0,
                step_time_ms=self.step_times.last_s * 1e3,
                deadline_misses=self.deadline_misses,
                human_stale=self._human_stale,
                joint_state_stale=self._joint_state_seen is None or self.watchdogs.tripped("joint_state"),
                human_source_lost=self._human_source_lost,
                human_lost=self._memory.lost,
                relaxed_pairs=sorted(self._relaxed_since_status)[:256],
                binding_pairs=binding[:256],
                q_nom=q_nom if np.isfinite(q_nom).all() else None,
                person_intrusion=self._intrusion_since_status,
                backing_out=self._backing_out_since_status,
                human_lateness_ms=1e3 * self._memory.lateness,
                executor_holding=self.watchdogs.tripped("executor_command"),
                resyncing=self._resync_target is not None,
                watchdog_trips=dict(self.watchdogs.trips),
                dropped=self.dropped(),
                config_version=self.config_version,
                backend=self.pipeline.filter.backend_name,
            )
        )
        self._relaxed_since_status.clear()
        self._intrusion_since_status = self._backing_out_since_status = False

    def dropped(self) -> dict[str, int]:
        """Invalid or refused messages per topic: undecodable, failing callbacks, rejected."""
        return self.refusals.by_topic(self.bus)

    # the loop --------------------------------------------------------------------------------
    def run(self, stop: threading.Event, duration: float | None = None, rt_priority: int = 0) -> dict[str, Any]:
        """Tick at ``safety.rate_hz`` until ``stop`` is set (or ``duration`` s passed); final counters.

        ``rt_priority`` > 0: run the loop's thread under SCHED_FIFO at that priority if permitted
        (see :func:`shared.realtime.enter_realtime`); the thread returns to normal scheduling afterwards.
        """
        self.await_executor(stop)
        with realtime(rt_priority) as scheduling:
            return self._loop(stop, duration, scheduling)

    def await_executor(self, stop: threading.Event, timeout_s: float = EXECUTOR_WAIT_S) -> bool:
        """Wait for the first JointState (the first tick then syncs q_cbf to the target the executor
        holds) while an executor may be there: up to ``timeout_s`` once its liveliness token is seen,
        :data:`EXECUTOR_DISCOVERY_S` if none is; True if one arrived."""
        started = time.monotonic()
        while self.joint_state.get() is None:
            waited = time.monotonic() - started
            if stop.wait(0.005) or waited > timeout_s:
                log.warning("the executor is alive but sent no joint state within %.1f s: starting from home", timeout_s)
                return False
            if waited > EXECUTOR_DISCOVERY_S and not self._executor_seen:
                return False
        return True

    def _loop(self, stop: threading.Event, duration: float | None, scheduling: str) -> dict[str, Any]:
        p = self.pipeline
        log.info(
            "safety service started: %.0f Hz (%s), backend %s, pairs %s (%d rows), robot %s (%s), "
            "robot_id %s, bus %s",
            self.conf.safety.rate_hz, scheduling, p.filter.backend_name, self.conf.safety.pairs, len(p.pairs),
            p.spec.name, self.conf.robot.spec, self.conf.robot_id, self.conf.bus.mode.value,
        )
        gc.collect()
        gc.freeze()  # long-lived objects leave the collector: shorter gen-2 pauses in the loop
        schedule = self.schedule
        schedule.start(stop, duration)
        misses_logged, last_miss_log = 0, -math.inf
        while (now := schedule.wait()) is not None:
            self.tick_errors.run(lambda: self.tick(now))
            done = time.monotonic()
            schedule.finished(done)
            if schedule.missed != misses_logged and done - last_miss_log >= _MISS_LOG_INTERVAL_S:
                log.warning("%d deadline misses so far (this tick: started %.2f ms late, took %.2f ms)",
                            schedule.missed, (now - schedule.due) * 1e3, self.step_times.last_s * 1e3)
                misses_logged, last_miss_log = schedule.missed, done
            schedule.set_period(self.period)  # a config update may have changed the rate
        counters = self.counters(time.monotonic() - schedule.begin)
        log.info("safety service stopped after %d ticks", self.ticks)
        return counters

    def counters(self, elapsed_s: float | None = None) -> dict[str, Any]:
        """Final (or current) counters: ticks, deadline misses, step times, resyncs, drops, ..."""
        steps = self.step_times.recent() * 1e3
        slots = self.ticks + self.deadline_misses
        out: dict[str, Any] = {
            "ticks": self.ticks,
            "deadline_misses": self.deadline_misses,
            "miss_ratio": self.deadline_misses / slots if slots else 0.0,
            "rate_hz": self.conf.safety.rate_hz,
            "step_p50_ms": float(np.percentile(steps, 50)),
            "step_p99_ms": float(np.percentile(steps, 99)),
            "step_max_ms": float(steps.max()),
            "max_late_ms": self.max_late_s * 1e3,
            "resyncs": self.resyncs,
            "superseded": {topic: int(n) for topic, n in self.bus.superseded.items() if n},
            "watchdog_trips": dict(self.watchdogs.trips),
            "nonfinite_holds": self.nonfinite_holds,
            "tick_errors": self.tick_errors.total,
            "config_version": self.config_version,
            "modes": dict(self.modes),
            "dropped": self.dropped(),
            "backend": self.pipeline.filter.backend_name,
        }
        out.update(self.rate_counters(elapsed_s))
        return out


def main(conf: StackConfig, stop: threading.Event, duration: float | None = None, rt_priority: int = 0) -> dict[str, Any]:
    """Run the safety service until ``stop`` is set or ``duration`` seconds passed; final counters.

    ``rt_priority`` > 0 runs the control loop under SCHED_FIFO when the OS permits it.
    """
    with SafetyService(conf) as service:
        return service.run(stop, duration, rt_priority)


def build_parser(parser: argparse.ArgumentParser | None = None) -> argparse.ArgumentParser:
    parser = parser or argparse.ArgumentParser(prog="safemimic safety")
    parser.description = (
        "Run the CBF safety service: newest HumanState → retargeting → capsule CBF-QP → JointCommand "
        "at a fixed rate (safety.rate_hz), SafetyStatus at safety.status_rate_hz; ConfigUpdates apply "
        "at the next step."
    )
    add_bus_arguments(parser)
    parser.add_argument("--duration", type=float, metavar="SECONDS", help="stop after this many seconds (tests, demos)")
    parser.add_argument("--rate", type=float, metavar="HZ", help="control rate, overriding safety.rate_hz")
    parser.add_argument(
        "--rt-priority", type=int, default=DEFAULT_RT_PRIORITY, metavar="N",
        help=f"run the control loop under SCHED_FIFO at priority N (1-99) when permitted, else warn and "
        f"use normal scheduling; 0 disables (default {DEFAULT_RT_PRIORITY})",
    )
    return parser


def run(args: argparse.Namespace) -> int:
    extra: dict[str, Any] = {"safety": {"rate_hz": args.rate}} if args.rate is not None else {}
    conf = config_from_args(args, extra)  # a ConfigError: shared.entrypoint says it, exit 2
    if args.duration is not None and args.duration <= 0:
        print("--duration must be > 0", file=sys.stderr)
        return 2
    if not 0 <= args.rt_priority <= 99:
        print("--rt-priority must lie in 0..99", file=sys.stderr)
        return 2
    sys.setswitchinterval(SWITCH_INTERVAL_S)
    with stop_on_signals() as stop:
        c = main(conf, stop, args.duration, args.rt_priority)
    print(
        f"safety: {c['ticks']} ticks in {c['elapsed_s']:.2f} s ({c['achieved_hz']:.1f} Hz of {c['rate_hz']:.0f}), "
        f"{c['deadline_misses']} deadline misses ({100 * c['miss_ratio']:.2f} %), "
        f"step p50 {c['step_p50_ms']:.3f} ms p99 {c['step_p99_ms']:.3f} ms max {c['step_max_ms']:.2f} ms, "
        f"resyncs {c['resyncs']}, dropped {c['dropped']}",
        flush=True,
    )
    return 0

