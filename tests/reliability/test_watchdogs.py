"""Watchdogs and rate limits on a running stack, in one process (one drive, four checks: a test each).

The executor (MuJoCo), the safety service (500 Hz) and perception (a scripted person beside the
robot, looping) run in threads, each with its own Zenoh session, as clients of a router session
(mutual TLS, each session with its own service's certificate from a throwaway CA, the router
enforcing the access control generated from the service table) that also records every ``robot/command``, ``robot/joint_state`` and ``safety/status``. Then, in
turn: configuration changes (gain, γ/φ, the control rate 500 → 250 → 500 Hz, the 72-row pair
preset, mirrored retargeting), a calibration (θ_home from the person's current pose, published as
the config API does), and perception, the executor and the safety service each stopped for a while
and restarted. Checks:

- ``rate_limit``: every command differs from the one before by at most u_max·Δt per joint
  (Δt = the control period, the longest one used across a restart's gap; 2 u_max·Δt for a command
  ``settled`` onto the measured robot), every command finite;
- ``watchdog_human``: with perception gone the status shows ``human_source_lost`` and then
  ``human_stale``, both counted, and the robot stops imitating (|u*| ≈ 0);
- ``watchdog_joint_state``: with the executor gone the status shows ``joint_state_stale`` and
  commands keep coming (integrated from q_cbf); after the executor's restart (at home: a resync
  when that is more than the tolerance away) the watchdog clears;
- ``watchdog_executor_command``: with the safety service gone the executor reports its commands
  stale and holds still; the restarted safety service shows ``executor_holding`` (counted) and
  continues from the executor's target.
"""

from __future__ import annotations

import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from safemimic.certs import make_stack
from safemimic.launch import free_port
from services.executor.service import ExecutorService
from services.perception.service import PerceptionService
from services.perception.sources import open_source
from services.safety.service import SafetyService
from shared.bus import Bus, router_config
from shared.config import StackConfig, TlsConfig, load_config
from shared.messages import ConfigUpdate, JointCommand
from tests.reliability.check import Check, CheckResult
from tests.support.bus import BusRecorder

STARTUP_TIMEOUT_S = 60.0
#: |u*| (rad/s, any joint) below which the robot counts as no longer imitating
STILL_SPEED = 0.05


class Running:
    """A service's ``run(stop)`` in a thread; :meth:`stop` ends it and closes the service."""

    def __init__(self, service: Any) -> None:
        self.service = service
        self._stop = threading.Event()
        self._thread = threading.Thread(target=service.run, args=(self._stop,), daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(10)
        self.service.close()


def stack_config(endpoint: str, robot_id: str, certs: Path) -> StackConfig:
    """Defaults, every service a client of the router at ``endpoint`` with its own certificate from
    ``certs``, the person beside the robot."""
    return load_config(environ={}, overrides={
        "robot_id": robot_id,
        "bus": {"mode": "client", "connect": [endpoint], "multicast_scouting": False, "tls": {"dir": str(certs)}},
        "perception": {"source": "scenario", "scenario": "side-by-side-arm-raise", "loop": True},
    })


def _wait(condition: Callable[[], bool], timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.01)
    return True


def rate_limit_ratios(commands: list[JointCommand], u_max: np.ndarray, periods: np.ndarray) -> np.ndarray:
    """max_j |q_{k+1,j} − q_{k,j}| / (u_max_j Δt_k · ticks_k) for consecutive received commands.

    Δt_k (``periods``, N − 1) is the nominal control period: the stamps are the ticks' actual start
    times, which jitter, while q_cbf advances by exactly Δt·u* per tick. ticks_k is the seq gap
    (commands lost in transport in between: several ticks' motion); 1 across a restart (seq starts
    over), so a restarted service must continue exactly where its predecessor's commands left off;
    one more for a command ``settled`` onto the measured robot (a protective stop).
    """
    q = np.array([c.q for c in commands])
    seq = np.array([c.seq for c in commands])
    ticks = np.where(np.diff(seq) > 0, np.diff(seq), 1) + np.array([c.settled for c in commands[1:]], dtype=int)
    return (np.abs(np.diff(q, axis=0)) / (u_max * (periods * ticks)[:, None])).max(axis=1)


@dataclass(frozen=True)
class Drive:
    """What one drive through changes and restarts recorded, when each phase began, and the configuration."""

    recorder: BusRecorder
    marks: dict[str, float]
    conf: StackConfig


def drive(pause: float) -> Drive:
    """Drive the stack through changes, calibration and restarts (``pause`` s between events)."""
    port = free_port()
    endpoint = f"tls/127.0.0.1:{port}"
    robot_id = f"rel{port}"
    certs_dir = tempfile.TemporaryDirectory(prefix="safemimic-watchdogs-certs-")  # removed when drive() returns
    certs = Path(certs_dir.name)
    make_stack(certs, router_hosts=["127.0.0.1"])
    conf = stack_config(endpoint, robot_id, certs)
    marks: dict[str, float] = {}
    # the hub is the router itself: its own session (which publishes the config changes, as the
    # config API would) is local to the router; every service reaches it through the access control
    with Bus(router_config([endpoint], tls=TlsConfig(dir=str(certs))), robot_id, "router") as hub:
        recorder = BusRecorder(hub, ("robot/command", "robot/joint_state", "safety/status", "human/state"))
        configs = hub.publisher("config")
        version = [0]

        def change(**sections: dict[str, Any]) -> None:
            tree = conf.model_dump(mode="json")
            for section, values in sections.items():
                tree[section].update(values)
            version[0] += 1
            configs.put(ConfigUpdate(stamp=time.monotonic(), version=version[0], config=tree,
                                     changed=[f"{s}.{k}" for s, v in sections.items() for k in v]))
            time.sleep(pause / 2)

        def start_perception() -> Running:
            return Running(PerceptionService(conf, open_source(conf.perception)))

        executor = Running(ExecutorService(conf))
        safety = Running(SafetyService(conf))
        perception = start_perception()
        try:
            if not _wait(lambda: any(c.human_seq is not None for c in recorder.between("robot/command")),
                         STARTUP_TIMEOUT_S):
                raise RuntimeError("the stack did not start imitating")
            time.sleep(pause)
            marks["configs"] = time.monotonic()
            change(safety={"gain": 20.0})
            change(safety={"gamma": 3.0, "phi": 0.05})
            marks["rate_250"] = time.monotonic()
            change(safety={"rate_hz": 250.0})
            marks["rate_500"] = time.monotonic()
            change(safety={"rate_hz": 500.0})
            change(safety={"pairs": "paper72"})
            change(retargeting={"mirror": True})
            change()
            human = recorder.last("human/state")
            theta = human.theta.tolist() if human is not None else [0.1] * 8
            change(retargeting={"theta_home": theta})
            change()
            time.sleep(pause)

            marks["perception_down"] = time.monotonic()
            perception.stop()
            time.sleep(conf.safety.human_timeout_s + pause)
            marks["perception_up"] = time.monotonic()
            perception = start_perception()
            _wait(lambda: any(not s.human_stale for s in recorder.between("safety/status", marks["perception_up"])),
                  STARTUP_TIMEOUT_S)
            time.sleep(pause)

            marks["executor_down"] = time.monotonic()
            executor.stop()
            time.sleep(pause)
            marks["executor_up"] = time.monotonic()
            executor = Running(ExecutorService(conf))
            time.sleep(2 * pause)

            marks["safety_down"] = time.monotonic()
            safety.stop()
            time.sleep(conf.executor.command_timeout_s + pause)
            marks["safety_up"] = time.monotonic()
            safety = Running(SafetyService(conf))
            _wait(lambda: bool(recorder.between("robot/command", marks["safety_up"])), STARTUP_TIMEOUT_S)
            time.sleep(pause)
            marks["end"] = time.monotonic()
        finally:
            for service in (perception, safety, executor):
                service.stop()
    return Drive(recorder, marks, conf)


def _seconds_after(recorder: BusRecorder, start: float, predicate: Callable[[Any], bool]) -> float:
    """Seconds from ``start`` to the first status after it satisfying ``predicate`` (NaN: none)."""
    at = recorder.first_after("safety/status", start, predicate)
    return float("nan") if at is None else at - start


def _rate_limit(recorder: BusRecorder, marks: dict[str, float], conf: StackConfig) -> CheckResult:
    timed = recorder.timed("robot/command")
    commands = [c for _, c in timed]
    finite = all(np.isfinite(c.q).all() and np.isfinite(c.dq).all() for c in commands)
    arrived = np.array([t for t, _ in timed[1:]])
    # 250 Hz from the change's arrival until shortly after the change back (a tick of slack)
    slow = (arrived >= marks["rate_250"]) & (arrived <= marks["rate_500"] + 0.1)
    periods = np.where(slow, 1 / 250.0, 1 / conf.safety.rate_hz)
    ratios = rate_limit_ratios(commands, np.asarray(conf.safety.u_max), periods)
    worst = float(ratios.max()) if ratios.size else float("nan")
    seq_steps = np.diff([c.seq for c in commands])
    return CheckResult("rate_limit", finite and len(commands) > 1000 and worst <= 1 + 1e-6, {
        "commands": len(commands), "max_step_over_limit": round(worst, 6), "all_finite": finite,
        "lost_in_transport": int(np.sum(seq_steps[seq_steps > 1] - 1)), "restarts_seen": int(np.sum(seq_steps <= 0)),
        "events": "gain, gamma/phi, rate 500→250→500 Hz, paper72 pairs, mirror, calibration, "
                  "perception/executor/safety restarts",
    })


def _watchdog_human(recorder: BusRecorder, marks: dict[str, float], conf: StackConfig) -> CheckResult:
    down, up = marks["perception_down"], marks["perception_up"]
    statuses = recorder.between("safety/status", down, up)
    stale = [s for s in statuses if s.human_stale]
    trips = statuses[-1].watchdog_trips if statuses else {}
    late = recorder.between("robot/command", down + conf.safety.human_timeout_s + 0.1, up)
    speed = max((float(np.abs(c.dq).max()) for c in late), default=float("nan"))
    after = recorder.between("safety/status", up, marks["executor_down"])
    recovered = bool(after) and not after[-1].human_stale
    passed = (any(s.human_source_lost for s in statuses) and bool(stale) and trips.get("human_source", 0) >= 1 and trips.get("human_state", 0) >= 1
              and speed <= STILL_SPEED and recovered)
    lost_after = _seconds_after(recorder, down, lambda s: s.human_source_lost)
    return CheckResult("watchdog_human", passed, {
        "source_lost_after_s": round(lost_after, 3), "stale_statuses": len(stale), "trips": trips,
        "max_speed_while_stale": round(speed, 4), "recovered": recovered,
    })


def _watchdog_joint_state(recorder: BusRecorder, marks: dict[str, float], conf: StackConfig) -> CheckResult:
    down, up = marks["executor_down"], marks["executor_up"]
    stale_after = _seconds_after(recorder, down, lambda s: s.joint_state_stale)
    during = recorder.between("robot/command", down + 0.2, up)
    statuses = recorder.between("safety/status", up, marks["safety_down"])
    trips = statuses[-1].watchdog_trips if statuses else {}
    cleared = bool(statuses) and not statuses[-1].joint_state_stale and not statuses[-1].resyncing
    passed = (stale_after <= conf.safety.joint_state_timeout_s + 0.1 and len(during) > 50
              and trips.get("joint_state", 0) >= 1 and cleared)
    return CheckResult("watchdog_joint_state", passed, {
        "stale_after_s": round(stale_after, 3), "commands_while_executor_gone": len(during), "trips": trips,
        "cleared_after_restart": cleared,
    })


def _watchdog_executor_command(recorder: BusRecorder, marks: dict[str, float]) -> CheckResult:
    down, up = marks["safety_down"], marks["safety_up"]
    holding = [s for s in recorder.between("robot/joint_state", down, up) if s.command_stale]
    held_motion = float(np.ptp([s.q_command for s in holding], axis=0).max()) if holding else float("nan")
    statuses = recorder.between("safety/status", up, marks["end"])
    shown = any(s.executor_holding for s in statuses)
    trips = statuses[-1].watchdog_trips if statuses else {}
    cleared = bool(statuses) and not statuses[-1].executor_holding
    passed = bool(holding) and held_motion == 0.0 and shown and trips.get("executor_command", 0) == 1 and cleared
    return CheckResult("watchdog_executor_command", passed, {
        "holding_states": len(holding), "held_target_motion_rad": held_motion, "status_showed_holding": shown,
        "trips": trips, "cleared": cleared,
    })


@pytest.fixture(scope="module")
def driven(long_run: bool) -> Iterator[Drive]:
    """One drive through changes and restarts for the four checks (pauses 0.6 s quick, 1.5 s long)."""
    yield drive(1.5 if long_run else 0.6)


@pytest.mark.integration
def test_rate_limit(driven: Drive, check: Check) -> None:
    check(_rate_limit(driven.recorder, driven.marks, driven.conf))


@pytest.mark.integration
def test_watchdog_human(driven: Drive, check: Check) -> None:
    check(_watchdog_human(driven.recorder, driven.marks, driven.conf))


@pytest.mark.integration
def test_watchdog_joint_state(driven: Drive, check: Check) -> None:
    check(_watchdog_joint_state(driven.recorder, driven.marks, driven.conf))


@pytest.mark.integration
def test_watchdog_executor_command(driven: Drive, check: Check) -> None:
    check(_watchdog_executor_command(driven.recorder, driven.marks))
