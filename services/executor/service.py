"""``safemimic executor``: the robot end of the bus (architecture §1, §5).

Subscribes to ``robot/command`` (:class:`~shared.messages.JointCommand`) and ``human/state``
(:class:`~shared.messages.HumanState`), drives an :class:`~services.executor.base.Executor`
(``executor.backend``: the MuJoCo simulation, or the real Unitree G1 through
:mod:`services.executor.g1.executor`) at ``executor.rate_hz`` in real time and publishes
``robot/joint_state`` (:class:`~shared.messages.JointState`) at ``executor.state_rate_hz``.
Holds the liveliness token ``alive/executor``.

Every tick:

1. the newest command, if younger than ``executor.command_timeout_s`` (local receive time:
   stamps of other hosts' monotonic clocks are not comparable), becomes the servo target with its
   velocity as feed-forward; a protective stop's (``JointCommand.protective_stop``, counted in
   ``stop_commands``) with the servos damped by ``executor.stop_damping``. An older one makes the
   robot hold the last commanded position with zero velocity, damped as in a stop: counted per tick
   (``stale_ticks``) and per episode (``command_timeouts``). Before the first command the robot holds
   home;
2. a new human state (robot frame only; others are dropped and counted) moves the person's
   capsules in the simulation; the last one stays while none arrives;
3. one control period of physics, then the contacts of that step are tallied (robot–robot and
   robot–human, architecture §10) into the counters logged every ``executor.stats_interval_s`` and
   returned by :func:`main`.

Ticks are scheduled at absolute times and the thread sleeps on a ``threading.Event`` between them,
never spinning (architecture §8). A tick that starts a whole period late counts the skipped slots as
deadline misses and keeps the schedule's phase (simulated time then lags wall time by as much).
Undecodable or invalid payloads are dropped and counted by the bus, never reach the robot.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import sys
import threading
import time
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import numpy as np

from services.executor.contacts import ContactTally
from services.executor.base import Executor
from shared.bus import Bus, Latest, Received
from shared.cli_args import add_bus_arguments, config_from_args
from shared.config import ExecutorBackend, G1Mode, StackConfig
from shared.messages import HumanState, JointCommand, JointState
from shared.robot_spec import configured_robot_spec
from shared.schedule import FixedRateSchedule
from shared.service import Refusals, ScheduledService, StepErrors, StepTimes
from shared.stop_signals import stop_on_signals

log = logging.getLogger("safemimic.executor")

SERVICE_NAME = "executor"
#: The frame HumanState capsules must be expressed in (the robot frame, z up, floor at 0).
#: Tick compute times kept for the percentiles (a ring buffer: 20 s at 500 Hz).
_TICK_TIME_WINDOW = 10_000
#: Unexpected exceptions in consecutive ticks after which the service gives up (a bug, not noise).
_MAX_CONSECUTIVE_ERRORS = 100


@runtime_checkable
class ReportsCounters(Protocol):
    """An executor with counters of its own (the G1's ramps, faults, frames) for the final report."""

    def counters(self) -> dict[str, Any]: ...


def build_executor(conf: StackConfig) -> Executor:
    """The executor of ``executor.backend``, its modules imported only then: the simulation needs
    MuJoCo, the G1 CycloneDDS, and neither needs the other."""
    c = conf.executor
    spec = configured_robot_spec(conf)
    if c.backend is ExecutorBackend.G1:
        from services.executor.g1.executor import G1Executor

        return G1Executor(spec, c.g1, 1.0 / c.rate_hz)
    from services.executor.mujoco.executor import MujocoExecutor
    from services.executor.mujoco.model import PDGains

    return MujocoExecutor(spec, PDGains.from_config(c), 1.0 / c.rate_hz, c.viewer)


class ExecutorService(ScheduledService):
    """The executor service's state and one control tick; :meth:`run` drives it in real time.

    ``executor`` defaults to :func:`build_executor` (``executor.backend`` of the configured
    robot); ``bus`` to a new :class:`~shared.bus.Bus` from ``conf.bus`` (closed by :meth:`close`).
    The executor is started here and stopped by :meth:`close`.
    """

    def __init__(self, conf: StackConfig, executor: Executor | None = None, bus: Bus | None = None) -> None:
        self.conf = conf
        self.executor = executor or build_executor(conf)
        n = len(self.executor.joint_names)
        self.ticks = 0
        self.schedule = FixedRateSchedule(1.0 / conf.executor.rate_hz)
        self.tick_errors = StepErrors(log, "executor tick", _MAX_CONSECUTIVE_ERRORS)
        self.commands_applied = 0
        self.stop_commands = 0
        self.clipped_commands = 0
        self.stale_ticks = 0
        self.command_timeouts = 0
        self.human_updates = 0
        self.tally = ContactTally()
        self.tick_times = StepTimes(_TICK_TIME_WINDOW)
        self._target = self.executor.q_home
        self._zero = np.zeros(n)
        self._applied: Received[JointCommand] | None = None
        self._human_seen: Received[HumanState] | None = None
        self._stale = False
        self._next_state = -math.inf
        self.refusals = Refusals()
        self.command: Latest[JointCommand] = Latest()
        self.commander = OneCommander(self.command, conf.executor.command_timeout_s, self.refusals)
        self.human: Latest[HumanState] = Latest()

        self.executor.start()
        try:
            self.open_bus(conf, SERVICE_NAME, bus)
            self._state_pub = self.bus.publisher("robot/joint_state")
            self.bus.subscribe("robot/command", self.commander.offer)
            self.bus.subscribe("human/state", self.human.set)  # HumanState is validated in the robot frame
            self.bus.declare_alive(SERVICE_NAME)
        except Exception:
            self.executor.stop()
            raise

    def close(self) -> None:
        self.executor.stop()
        super().close()

    @property
    def period(self) -> float:
        """The control period (s)."""
        return 1.0 / self.conf.executor.rate_hz

    # subscriber callback (Zenoh threads) ----------------------------------------------------
    # control tick (the loop's thread) -------------------------------------------------------
    def tick(self, now: float) -> None:
        """One control period at monotonic time ``now``: command → human → physics → state."""
        started = time.perf_counter()
        self._apply_command(now)
        received = self.human.get()
        if received is not None and received is not self._human_seen:
            m = received.message
            self.executor.set_human(m.capsules, m.capsule_radii, m.capsule_valid)
            self._human_seen = received
            self.human_updates += 1
        self.executor.tick()
        report = self.executor.contacts()
        if report is not None:
            self.tally.update(report)
        if now >= self._next_state:
            reading = self.executor.read_state()
            self._state_pub.put(JointState(stamp=now, q=reading.q, dq=reading.dq, q_command=self._target,
                                           command_stale=self._stale))
            state_period = 1.0 / self.conf.executor.state_rate_hz
            self._next_state = max(self._next_state + state_period, now + 0.5 * state_period)
        self.tick_times.record(time.perf_counter() - started)
        self.ticks += 1

    def _apply_command(self, now: float) -> None:
        received = self.command.get()
        if received is None:
            return  # no command yet: the executor holds home
        if now - received.received <= self.conf.executor.command_timeout_s:
            if received is not self._applied:
                message = received.message
                self._target = self.executor.apply_command(message.q, message.dq, message.ddq, message.protective_stop)
                self.clipped_commands += int(not np.array_equal(self._target, message.q))
                self.commands_applied += 1
                self.stop_commands += int(message.protective_stop)
                self._applied = received
                if self._stale:
                    log.info("commands resumed after %d stale ticks so far", self.stale_ticks)
                self._stale = False
            return
        if not self._stale:
            self.command_timeouts += 1
            self._stale = True
            self.executor.apply_command(self._target, self._zero, stop=True)  # held at rest: a stop, damped as one
            log.warning("newest command is %.3f s old (timeout %.3f s): holding the last commanded position",
                        now - received.received, self.conf.executor.command_timeout_s)
        self.stale_ticks += 1

    def dropped(self) -> dict[str, int]:
        """Invalid or refused messages per topic: undecodable, failing callbacks, rejected."""
        return self.refusals.by_topic(self.bus)

    # the loop --------------------------------------------------------------------------------
    def run(self, stop: threading.Event, duration: float | None = None) -> dict[str, Any]:
        """Tick at ``executor.rate_hz`` until ``stop`` is set (or ``duration`` s passed); counters."""
        c = self.conf.executor
        log.info("executor started: %.0f Hz, joint state at %.0f Hz, command timeout %.3f s, robot_id %s, bus %s",
                 c.rate_hz, c.state_rate_hz, c.command_timeout_s, self.conf.robot_id, self.conf.bus.mode.value)
        schedule = self.schedule
        schedule.start(stop, duration)
        begin = schedule.begin
        next_stats = begin + c.stats_interval_s
        while (now := schedule.wait()) is not None:
            self.tick_errors.run(lambda: self.tick(now))
            if now >= next_stats:
                log.info("%s", self.summary_line(now - begin))
                next_stats += c.stats_interval_s
        counters = self.counters(time.monotonic() - begin)
        log.info("executor stopped: %s", self.summary_line(counters["elapsed_s"]))
        return counters

    def summary_line(self, elapsed_s: float) -> str:
        """One line: rate, commands, staleness, human updates, drops, contacts."""
        hz = self.ticks / elapsed_s if elapsed_s > 0 else 0.0
        return (
            f"{self.ticks} ticks ({hz:.1f} Hz), {self.deadline_misses} misses, {self.commands_applied} commands "
            f"({self.clipped_commands} clipped, {self.stop_commands} stops), {self.stale_ticks} stale ticks in "
            f"{self.command_timeouts} timeouts, "
            f"{self.human_updates} human updates, dropped {self.dropped()}, {self.tally.line()}"
        )

    def counters(self, elapsed_s: float | None = None) -> dict[str, Any]:
        """Counters so far (JSON-ready): ticks, timing, commands, staleness, drops, contacts."""
        tick_us = self.tick_times.recent() * 1e6
        out: dict[str, Any] = {
            "ticks": self.ticks,
            "rate_hz": self.conf.executor.rate_hz,
            "deadline_misses": self.deadline_misses,
            "max_late_ms": self.max_late_s * 1e3,
            "tick_p50_us": float(np.percentile(tick_us, 50)),
            "tick_p99_us": float(np.percentile(tick_us, 99)),
            "tick_errors": self.tick_errors.total,
            "commands_received": self.command.count,
            "commander_switches": self.commander.switches,
            "commands_applied": self.commands_applied,
            "clipped_commands": self.clipped_commands,
            "stop_commands": self.stop_commands,
            "stale_ticks": self.stale_ticks,
            "command_timeouts": self.command_timeouts,
            "human_updates": self.human_updates,
            "dropped": self.dropped(),
            "contacts": self.tally.summary(),
        }
        if isinstance(self.executor, ReportsCounters):
            out["robot"] = self.executor.counters()
        out.update(self.rate_counters(elapsed_s))
        return out


def main(conf: StackConfig, stop: threading.Event, duration: float | None = None) -> dict[str, Any]:
    """Run the executor service until ``stop`` is set or ``duration`` s passed; counters."""
    with ExecutorService(conf) as service:
        return service.run(stop, duration)


def build_parser(parser: argparse.ArgumentParser | None = None) -> argparse.ArgumentParser:
    parser = parser or argparse.ArgumentParser(prog="safemimic executor")
    parser.description = (
        "Run the executor: a MuJoCo simulation of the robot (pelvis welded) that follows JointCommands "
        "at executor.rate_hz in real time, holds the last position when commands stop, shows the "
        "person's capsules from HumanState, counts robot-robot and robot-human contacts and publishes "
        "JointState at executor.state_rate_hz. Headless unless --viewer. With --backend g1 it drives a "
        "real Unitree G1 over CycloneDDS instead (rt/arm_sdk or rt/lowcmd, settings in executor.g1; "
        "README: 'Running on a real G1')."
    )
    add_bus_arguments(parser)
    parser.add_argument("--robot-model", metavar="PATH",
                        help="MJCF of the robot to simulate instead of the robot description's "
                        "(e.g. Menagerie's unitree_g1/g1.xml with meshes)")
    parser.add_argument("--viewer", action="store_true",
                        help="open MuJoCo's passive viewer (needs a display; otherwise a warning and headless)")
    parser.add_argument("--duration", type=float, metavar="SECONDS", help="stop after this many seconds")
    g1 = parser.add_argument_group("real robot")
    g1.add_argument("--backend", choices=[b.value for b in ExecutorBackend],
                    help="mujoco (simulation) or g1 (the real Unitree G1); default: executor.backend")
    g1.add_argument("--interface", metavar="IFACE", help="g1: network interface facing the robot, e.g. eth0")
    g1.add_argument("--dry-run", action="store_true",
                    help="g1: read rt/lowstate, build and check every frame, print them, send nothing")
    return parser


class OneCommander:
    """The executor follows one commanding source at a time (a ``JointCommand``'s ``source``: one
    safety service's session). A command from another source is refused (counted on the
    ``robot/command`` topic) while the current one has commanded within ``hold_s`` (the command
    timeout, after which the executor holds anyway): two safety services alive at once, an old one
    left running, would otherwise interleave two trajectories tick by tick. After that silence the
    first source heard is followed (a restarted safety service: a new session). Thread-safe: called
    from Zenoh's threads."""

    def __init__(self, latest: Latest[JointCommand], hold_s: float, refusals: Refusals) -> None:
        self._latest = latest
        self._hold_s = hold_s
        self._refusals = refusals
        self._lock = threading.Lock()
        self._source: str | None = None
        self._heard = -math.inf
        self.switches = 0

    def offer(self, message: JointCommand) -> None:
        """Take ``message`` (into the newest command) if its source is the one followed, or may become it."""
        now = time.monotonic()
        with self._lock:
            if message.source != self._source:
                if now - self._heard <= self._hold_s:
                    self._refusals.refuse("robot/command")
                    return
                if self._source is not None:
                    self.switches += 1
                    log.warning("commands now from %s (%s silent for %.3f s)", message.source, self._source,
                                now - self._heard)
                self._source = message.source
            self._heard = now
        self._latest.set(message)


def _warn_if_only_here(conf: StackConfig, shared_conf: StackConfig) -> None:
    """Warn when the real G1 in arm_sdk mode was chosen by this command's ``--backend`` flag alone:
    the other services read ``shared_conf`` (the file and the environment), so the safety layer
    would plan with the robot description's waist range, not ``executor.g1.arm_sdk_waist_range``
    (:func:`~shared.robot_spec.configured_robot_spec`)."""
    g1 = conf.executor.g1
    if (conf.executor.backend is ExecutorBackend.G1 and g1.mode is G1Mode.ARM_SDK and g1.arm_sdk_waist_range
            and shared_conf.executor.backend is not ExecutorBackend.G1):
        log.warning("--backend g1 is set for this executor only: put executor.backend: g1 in the configuration every "
                    "service reads (or SAFEMIMIC__EXECUTOR__BACKEND=g1 for each), so that the safety layer plans within "
                    "executor.g1.arm_sdk_waist_range %s as this executor drives the waist",
                    {joint: list(bounds) for joint, bounds in g1.arm_sdk_waist_range.items()})


def run(args: argparse.Namespace) -> int:
    extra: dict[str, Any] = {}
    if args.robot_model:
        extra["robot"] = {"model": str(Path(args.robot_model).expanduser().resolve())}
    executor: dict[str, Any] = {}
    if args.viewer:
        executor["viewer"] = True
    if args.backend:
        executor["backend"] = args.backend
    g1: dict[str, Any] = {}
    if args.interface:
        g1["network_interface"] = args.interface
    if args.dry_run:
        g1["dry_run"] = True
    if g1:
        executor["g1"] = g1
    if executor:
        extra["executor"] = executor
    if args.duration is not None and not args.duration > 0:
        print("--duration must be > 0", file=sys.stderr)
        return 2
    conf = config_from_args(args, extra)
    _warn_if_only_here(conf, config_from_args(args))
    with stop_on_signals() as stop:  # a ConfigError, RobotSpecError, ExecutorStartError: shared.entrypoint, exit 2
        counters = main(conf, stop, args.duration)
    print(json.dumps({"event": "stopped", "service": SERVICE_NAME, **counters}), flush=True)
    return 0

