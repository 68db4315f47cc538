"""The safety service (`safemimic safety`) as a real process over real Zenoh on 127.0.0.1.

The service runs in its own OS process (peer mode, multicast scouting off, explicit endpoints);
this test process is the other peer: it plays perception (HumanState), the config API
(ConfigUpdate) and a listener of JointCommand / SafetyStatus. A few in-process tests drive
:meth:`SafetyService.tick` directly for the state logic (resync, staleness, config swaps).
"""

from __future__ import annotations

import re
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
import pytest

from pydantic import ValidationError

from services.perception.synthetic import skeleton
from services.safety.protective_stop import STILL_JOINT_SPEED
from services.safety.seen_motion import STILL_WINDOW_S
from services.safety.retarget import Retargeter
from services.safety.service import RESYNC_DONE, RESYNC_TOLERANCE, SafetyService
from shared.bus import Bus
from shared.config import BusConfig, TargetPath, load_config
from shared.messages import ConfigUpdate, HumanState, JointState, SafetyMode
from shared.names import CAPSULE_NAMES, KEYPOINT_NAMES, POSE_ANGLE_NAMES
from shared.realtime import enter_realtime, leave_realtime
from shared.robot_spec import default_robot_spec_path, load_robot_spec
from tests.support.bus import BusRecorder
from tests.support.machine import cpu_times, host_kept_cpu, steal_pct, wake_latency
from tests.support.processes import Proc, free_port

LEFT_SHOULDER_PITCH = POSE_ANGLE_NAMES.index("left_shoulder_pitch")  # θ index = joint index
LEFT_FOREARM = CAPSULE_NAMES.index("left_forearm")
RATE_HZ = 500.0
N_SELF_PAIRS = len(load_robot_spec(default_robot_spec_path()).self_pairs)


# --------------------------------------------------------------------------- helpers
def person(x: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    """15 keypoints and 7 capsules (robot frame: x forward, z up, floor 0) of a person standing
    at distance ``x`` in front of the robot, arms down."""
    k = {
        "pelvis": (x, 0.0, 0.95), "spine_chest": (x, 0.0, 1.25), "head": (x, 0.0, 1.65),
        "left_shoulder": (x, 0.19, 1.45), "left_elbow": (x, 0.21, 1.17), "left_wrist": (x, 0.22, 0.92),
        "right_shoulder": (x, -0.19, 1.45), "right_elbow": (x, -0.21, 1.17), "right_wrist": (x, -0.22, 0.92),
        "left_hip": (x, 0.1, 0.93), "left_knee": (x, 0.1, 0.5), "left_ankle": (x, 0.1, 0.08),
        "right_hip": (x, -0.1, 0.93), "right_knee": (x, -0.1, 0.5), "right_ankle": (x, -0.1, 0.08),
    }
    keypoints = np.array([k[name] for name in KEYPOINT_NAMES], dtype=float)
    segment = {
        "torso": ("pelvis", "spine_chest"), "left_upper_arm": ("left_shoulder", "left_elbow"),
        "left_forearm": ("left_elbow", "left_wrist"), "right_upper_arm": ("right_shoulder", "right_elbow"),
        "right_forearm": ("right_elbow", "right_wrist"), "left_thigh": ("left_hip", "left_knee"),
        "right_thigh": ("right_hip", "right_knee"),
    }
    capsules = np.array([[k[segment[c][0]], k[segment[c][1]]] for c in CAPSULE_NAMES], dtype=float)
    return keypoints, capsules


RADII = np.array([0.13, 0.05, 0.045, 0.05, 0.045, 0.07, 0.07])


def human_state(theta: np.ndarray, capsules: np.ndarray, velocities: np.ndarray | None = None,
                keypoints: np.ndarray | None = None, capture_delay: float | None = None) -> HumanState:
    """A state of a person in pose ``theta`` (its skeleton: the synthetic body in that pose, which the
    retargeting by directions reads) whose capsules the CBF sees at ``capsules``; ``capture_delay``
    (s): its frame was taken this long before it is published (None: no capture stamp)."""
    stamp = time.monotonic()
    return HumanState(
        stamp=stamp,
        capture_stamp=None if capture_delay is None else stamp - capture_delay,
        keypoints=skeleton(theta) if keypoints is None else keypoints,
        keypoint_valid=np.ones(15, bool),
        theta=theta,
        theta_valid=np.ones(8, bool),
        capsules=capsules,
        capsule_radii=RADII,
        capsule_valid=np.ones(7, bool),
        capsule_velocities=np.zeros((7, 2, 3)) if velocities is None else velocities,
    )


def arm_forward() -> np.ndarray:
    theta = np.zeros(8)
    theta[LEFT_SHOULDER_PITCH] = np.pi / 2  # the person's left arm raised straight forward
    return theta


class HumanPublisher:
    """Publishes ``make()`` at 30 Hz on human/state from a thread until stopped."""

    def __init__(self, bus: Bus, make) -> None:
        self.make = make
        self.last_put = 0.0
        self._publisher = bus.publisher("human/state")
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        next_t = time.monotonic()
        while not self._stop.is_set():
            self._publisher.put(self.make())
            self.last_put = time.monotonic()
            next_t += 1 / 30
            self._stop.wait(max(0.0, next_t - time.monotonic()))

    def stop(self) -> float:
        self._stop.set()
        self._thread.join(2)
        return self.last_put


def loopback_bus(port: int) -> BusConfig:
    return BusConfig(mode="peer", listen=[f"tcp/127.0.0.1:{port}"], multicast_scouting=False)


def service_args(port: int, robot_id: str, duration: float) -> list[str]:
    return ["-m", "safemimic.cli", "safety", "--mode", "peer", "--connect", f"tcp/127.0.0.1:{port}",
            "--no-multicast", "--robot-id", robot_id, "--duration", str(duration), "--rate", str(RATE_HZ)]


def wait_first_command(rec: BusRecorder, proc: Proc, timeout: float = 20.0) -> float:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if commands := rec.timed("robot/command"):
            return commands[0][0]
        if proc.popen.poll() is not None:
            break
        time.sleep(0.01)
    raise AssertionError(f"no JointCommand from the service; output:\n{''.join(proc.output)[-3000:]}")


# --------------------------------------------------------------------------- 500 Hz for 5 s
@pytest.fixture(scope="module")
def machine_wake() -> dict:
    """This machine's wake-up latency for a SCHED_FIFO thread (:func:`tests.support.machine.wake_latency`):
    the deadline-miss budgets are held only where it keeps time. On a VM whose idle vCPUs halt, a
    thread doing nothing but sleep to 2 ms deadlines is woken up to 3 ms late (measured on the CI
    VM, idle: p99 ≈ 1 ms), and the budget would measure the host (architecture §8)."""
    return wake_latency(2.0)


@pytest.mark.integration
def test_runs_at_500_hz_over_zenoh_with_under_1_percent_deadline_misses(spawn, machine_wake: dict) -> None:
    port = free_port()
    robot_id = f"rate{port}"
    with Bus(loopback_bus(port), robot_id, "test") as bus:
        rec = BusRecorder(bus, ("robot/command", "safety/status"))
        proc = spawn(*service_args(port, robot_id, 6.5))
        t0 = wait_first_command(rec, proc)
        cpu_before = cpu_times()
        assert "safety" in bus.alive_services(timeout_s=1.0)
        time.sleep(max(0.0, t0 + 5.2 - time.monotonic()))
        steal = steal_pct(cpu_before)
        commands = rec.timed("robot/command")
        status = rec.last("safety/status")
        summary = proc.wait_for(lambda line: line.startswith("safety:") and "ticks" in line, timeout=10)
        assert proc.popen.wait(5) == 0
        decode_failures = dict(bus.dropped)

    # the budgets are held where the machine woke a control thread on time just before and its host
    # took no CPU from it meanwhile (tests.support.machine.host_kept_cpu)
    held = machine_wake["keeps_time"] and host_kept_cpu(steal)
    # ≈ 500 commands in every second, none lost, all finite, nominal (nothing to avoid, nothing to
    # track). Seconds are counted on the commands' own stamps (the service's CLOCK_MONOTONIC, the
    # same clock as ours on one host), so a hiccup of this receiving process does not blur them.
    s0 = commands[0][1].stamp
    window = [m for _, m in commands if s0 <= m.stamp < s0 + 5]
    per_second = [sum(1 for m in window if s0 + s <= m.stamp < s0 + s + 1) for s in range(5)]
    # no second with a burst, nor with a long stall (under half the rate: a loop blocked for half a
    # second, whatever the host); where the machine wakes a control thread on time and its host took no
    # CPU meanwhile, ≥ 90 % in every second and < 1 % of the 2,500 deadlines missed over the 5 s (a
    # skipped slot sends no command). In the full suite on a shared host that stole CPU (7.6 % in the
    # wake-up probe) the service got 297–411 commands a second, 479–500 alone minutes later: a budget.
    assert all(0.5 * RATE_HZ <= n <= 505 for n in per_second), per_second
    if held:
        assert all(n >= 0.9 * RATE_HZ for n in per_second), (per_second, machine_wake, steal)
        assert sum(per_second) >= 0.99 * 5 * RATE_HZ, (per_second, machine_wake, steal)
    # commands are put with Zenoh's default congestion control (drop, the newest command wins): on a
    # machine that wakes threads late the sender's queue can overflow, so losses are a budget there
    seqs = np.array([m.seq for m in window])
    lost = seqs[-1] - seqs[0] + 1 - len(window)
    if held:
        assert lost <= 0.005 * len(window), ("commands lost on loopback", lost, machine_wake)
    assert lost <= 0.05 * len(window), ("commands lost on loopback", lost)  # never a large share
    assert not decode_failures, decode_failures
    assert all(np.isfinite(m.q).all() and np.isfinite(m.dq).all() for m in window)
    assert {m.mode for m in window} == {SafetyMode.NOMINAL}
    assert all(m.human_seq is None for m in window)
    np.testing.assert_allclose(window[-1].q, window[0].q, atol=1e-9)  # q_nom = q_cbf: holds still

    # The service's own account: deadline misses < 1 % of its ticks (ticks = command seq + 1), held
    # where the machine wakes a control thread on time (machine_wake; architecture §8).
    ticks = commands[-1][1].seq + 1
    if held:
        assert status.deadline_misses < 0.01 * ticks, (status, ticks, machine_wake, steal)
    assert status.mode is SafetyMode.NOMINAL and status.min_h_human is None and not status.human_stale
    assert status.min_h_self is not None and status.min_h_self > 0
    assert status.backend == "daqp" and status.total_constraints == N_SELF_PAIRS
    assert 0 < status.step_time_ms < 1000 / RATE_HZ
    m = re.search(r"(\d+) ticks in ([\d.]+) s \(([\d.]+) Hz of 500\), (\d+) deadline misses", summary)
    assert m, summary
    n_ticks, elapsed, achieved, misses = int(m[1]), float(m[2]), float(m[3]), int(m[4])
    assert abs(elapsed - 6.5) < 0.1, summary
    if held:  # the achieved rate is the ticks that kept their deadline: a budget
        assert misses < 0.01 * n_ticks and abs(achieved - RATE_HZ) < 0.01 * RATE_HZ, summary
    assert achieved > 0.5 * RATE_HZ, summary  # never a long stall (≥ 90 % where held: above)
    print(f"\n  {summary.strip()}; per second {per_second}; machine wake-up latency {machine_wake}; host steal {steal} %")


# --------------------------------------------------------------------------- one shared service
@dataclass
class Live:
    bus: Bus
    rec: BusRecorder
    proc: Proc
    port: int


@pytest.fixture(scope="module")
def live() -> Iterator[Live]:
    """One service process for the behavioural checks below (≈ 2 s startup paid once)."""
    port = free_port()
    robot_id = f"live{port}"
    with Bus(loopback_bus(port), robot_id, "test") as bus:
        rec = BusRecorder(bus, ("robot/command", "safety/status"))
        proc = Proc([sys.executable, *service_args(port, robot_id, 60)])
        try:
            wait_first_command(rec, proc)
            rec.wait("safety/status", lambda s: True, timeout_s=5, since=0.0)
            yield Live(bus, rec, proc, port)
        finally:
            proc.stop()


@pytest.mark.integration
def test_follows_the_person_and_keeps_clear_of_an_intruding_forearm(live: Live) -> None:
    _, far = person(2.0)
    state = {"capsules": far, "velocities": np.zeros((7, 2, 3))}
    humans = HumanPublisher(live.bus, lambda: human_state(arm_forward(), state["capsules"], state["velocities"]))
    try:
        # The arm follows the retargeted q_nom (arm forward = negative G1 shoulder pitch).
        command = live.rec.wait("robot/command", lambda c: c.q[2] < -1.2 and c.human_seq is not None, timeout_s=5)
        assert command.mode in (SafetyMode.NOMINAL, SafetyMode.ACTIVE)
        time.sleep(0.5)  # converged onto q_nom (K = 8/s)
        tracking = live.rec.last("robot/command").q
        assert tracking[2] < -1.3
        status = live.rec.wait("safety/status", lambda s: s.min_h_human is not None, timeout_s=2)
        assert status.min_h_human > 1.0  # 2 m away
        assert status.total_constraints == N_SELF_PAIRS + 49 and not status.human_stale
        np.testing.assert_allclose(status.q_nom, tracking, atol=0.05)  # the target it tracks, reported

        # A forearm sweeps in at 0.5 m/s, across the robot's forward-pointing left arm, and stops
        # 0.35 m in front of the chest at shoulder height (robot pelvis z 0.793, torso to ~1.1 m).
        start = time.monotonic()
        x0, x1, speed = 1.0, 0.35, 0.5
        for x in np.arange(x0, x1, -speed / 60):
            capsules = far.copy()
            capsules[LEFT_FOREARM] = [[x, -0.1, 1.1], [x, 0.4, 1.1]]
            velocities = np.zeros((7, 2, 3))
            velocities[LEFT_FOREARM, :, 0] = -speed
            state["capsules"], state["velocities"] = capsules, velocities
            time.sleep(1 / 60)
        capsules = far.copy()
        capsules[LEFT_FOREARM] = [[x1, -0.1, 1.1], [x1, 0.4, 1.1]]
        state["capsules"], state["velocities"] = capsules, np.zeros((7, 2, 3))
        time.sleep(1.0)
        during = live.rec.between("safety/status", start)
    finally:
        humans.stop()

    assert len(during) > 80, len(during)
    bad = [s for s in during if s.min_h_human is not None and s.min_h_human < -1e-3 and s.mode is not SafetyMode.RELAXED]
    assert not bad, bad[:3]
    assert min(s.min_h_human for s in during) < 0.03  # the barrier really engaged
    assert any(s.mode is SafetyMode.ACTIVE for s in during)
    # the binding pairs are named (the forearm's rows against the arm it sweeps across) and only then
    assert any("|human.left_forearm" in name for s in during if s.mode is SafetyMode.ACTIVE for name in s.binding_pairs)
    assert not any(s.binding_pairs for s in during if s.mode is SafetyMode.NOMINAL)
    print(f"\n  intrusion: min h_human {min(s.min_h_human for s in during) * 1e3:.2f} mm, "
          f"modes {sorted({s.mode.value for s in during})}")
    final = live.rec.last("robot/command")
    assert np.isfinite(final.q).all()
    assert np.abs(final.q - tracking).max() > 0.05  # the robot gave way: no longer at q_nom
    assert np.abs(final.q - during[-1].q_nom).max() > 0.05  # ... which the status still reports as the target


@pytest.mark.integration
def test_a_person_inside_the_forearm_is_reported_as_intrusion_and_relaxed_pairs_over_zenoh(live: Live) -> None:
    """A person's forearm pushed through the robot's forward-pointing arm at 2 m/s: the rows become
    infeasible, SafetyStatus names the robot–person pairs that gave way and flags the intrusion, and
    the commands of the protective stop say so to the executor (``JointCommand.protective_stop``)."""
    _, far = person(2.0)
    state = {"capsules": far, "velocities": np.zeros((7, 2, 3))}
    humans = HumanPublisher(live.bus, lambda: human_state(arm_forward(), state["capsules"], state["velocities"]))
    try:
        following = live.rec.wait("robot/command", lambda c: c.q[2] < -1.2 and c.human_seq is not None, timeout_s=5)
        time.sleep(0.5)
        start = time.monotonic()
        for x in np.arange(0.9, -0.05, -2.0 / 60):  # across the arm and into the chest at 2 m/s
            capsules = far.copy()
            capsules[LEFT_FOREARM] = [[x, -0.1, 1.1], [x, 0.4, 1.1]]
            velocities = np.zeros((7, 2, 3))
            velocities[LEFT_FOREARM, :, 0] = -2.0
            state["capsules"], state["velocities"] = capsules, velocities
            time.sleep(1 / 60)
        time.sleep(0.5)
        during = live.rec.between("safety/status", start)
        commands = live.rec.between("robot/command", start)
    finally:
        humans.stop()
    live.rec.wait("safety/status", lambda s: s.human_stale, timeout_s=3)  # leave the service as the next test expects
    assert not following.protective_stop
    assert any(c.protective_stop for c in commands), "no command of the stop said so"
    intrusions = [s for s in during if s.person_intrusion]
    relaxed = [s for s in during if s.relaxed_pairs]
    assert intrusions, sorted({s.mode.value for s in during})
    pairs = [name for s in relaxed for name in s.relaxed_pairs if name != "accel_max"]  # the bound may give way too
    assert pairs and all(name.split("|")[1].startswith("human") for name in pairs), relaxed[:2]
    assert any("|human.left_forearm" in name for s in relaxed for name in s.relaxed_pairs)
    assert any(s.mode is SafetyMode.RELAXED for s in during)  # relaxed_pairs gather every step since the last status
    assert np.isfinite(live.rec.last("robot/command").q).all()


@pytest.mark.integration
def test_a_still_person_inside_the_arm_is_backed_out_of_and_a_late_camera_reported_over_zenoh(live: Live) -> None:
    """A person's forearm jumps across the robot's forward-pointing left arm and stays there, still:
    the stop holds the robot, and once the person has been seen still for a second (the jump has left
    the window) backs the arm out (SafetyStatus.backing_out). Their frames then arrive 80 ms later
    than usual after capture: ``human_lateness_ms`` says so."""
    _, far = person(2.0)
    state = {"capsules": far, "delay": 0.02}
    humans = HumanPublisher(live.bus, lambda: human_state(arm_forward(), state["capsules"],
                                                          capture_delay=state["delay"]))
    try:
        live.rec.wait("robot/command", lambda c: c.q[2] < -1.3 and c.human_seq is not None, timeout_s=5)
        time.sleep(0.3)
        on_time = live.rec.wait("safety/status", lambda s: s.min_h_human is not None, timeout_s=2)
        assert on_time.human_lateness_ms == 0.0 and not on_time.backing_out
        start = time.monotonic()
        inside = far.copy()
        inside[LEFT_FOREARM] = [[0.3, -0.1, 1.1], [0.3, 0.4, 1.1]]  # across the arm, 0.3 m in front of the chest
        state["capsules"] = inside
        backing = live.rec.wait("safety/status", lambda s: s.backing_out, timeout_s=3, since=start)
        during = live.rec.between("safety/status", start)
        state["delay"] = 0.1
        late = live.rec.wait("safety/status", lambda s: s.human_lateness_ms > 0.0, timeout_s=2)
    finally:
        humans.stop()
    live.rec.wait("safety/status", lambda s: s.human_stale, timeout_s=3)  # leave the service as the next test expects
    first_intrusion = next(s.stamp for s in during if s.person_intrusion)
    assert backing.stamp - first_intrusion >= 0.95 * STILL_WINDOW_S  # still for a second first (the service's clock)
    assert backing.person_intrusion  # backing out is what the stop does about an intrusion
    assert late.human_lateness_ms == pytest.approx(80.0, abs=2.0)


@pytest.mark.integration
def test_malformed_human_state_is_counted_and_the_loop_keeps_running(live: Live) -> None:
    before = live.rec.wait("safety/status", lambda s: True, timeout_s=2).dropped.get("human/state", 0)
    seq_before = live.rec.last("robot/command").seq
    for payload in (b"\x93garbage", b"", b"\xc1" * 40, human_state(arm_forward(), person()[1]).model_dump_json().encode()):
        live.bus.put_raw("human/state", payload)
    status = live.rec.wait("safety/status", lambda s: s.dropped.get("human/state", 0) >= before + 4, timeout_s=3)
    # the loop goes on commanding: more than 50 commands (0.1 s at 500 Hz) after the bad payloads, waited for
    # rather than sampled 0.1 s later (on a loaded VM that sample once held exactly 50)
    live.rec.wait("robot/command", lambda c: c.seq > seq_before + 50, timeout_s=2)
    assert status.mode in tuple(SafetyMode)


@pytest.mark.integration
def test_config_updates_apply_and_invalid_ones_are_counted(live: Live) -> None:
    publisher = live.bus.publisher("config")
    full = load_config(environ={}).model_dump(mode="json")
    full["safety"]["gamma"] = 4.0
    publisher.put(ConfigUpdate(stamp=time.monotonic(), version=7, changed=["safety.gamma"], config=full))
    status = live.rec.wait("safety/status", lambda s: s.config_version == 7, timeout_s=3)
    rejected_before = status.dropped.get("config", 0)

    bad = load_config(environ={}).model_dump(mode="json")
    bad["safety"]["gamma"] = -1
    publisher.put(ConfigUpdate(stamp=time.monotonic(), version=8, changed=["safety.gamma"], config=bad))
    status = live.rec.wait("safety/status", lambda s: s.dropped.get("config", 0) == rejected_before + 1, timeout_s=3)
    assert status.config_version == 7
    time.sleep(0.1)
    assert live.rec.between("safety/status", 0.0)[-1].config_version == 7

    # A structural change (QP backend) swaps the pipeline at the next step, the loop keeps its rate.
    full["safety"]["backend"] = "osqp"
    publisher.put(ConfigUpdate(stamp=time.monotonic(), version=9, changed=["safety.backend"], config=full))
    status = live.rec.wait("safety/status", lambda s: s.config_version == 9, timeout_s=5)
    assert status.backend == "osqp"
    assert np.isfinite(live.rec.last("robot/command").q).all()
    full["safety"]["backend"] = "daqp"  # back to the default for the checks that follow
    publisher.put(ConfigUpdate(stamp=time.monotonic(), version=10, changed=["safety.backend"], config=full))
    assert live.rec.wait("safety/status", lambda s: s.config_version == 10, timeout_s=5).backend == "daqp"


@pytest.mark.integration
def test_stale_human_keeps_capsules_and_is_reported(live: Live) -> None:
    humans = HumanPublisher(live.bus, lambda: human_state(np.zeros(8), person(1.5)[1]))
    # The shared service starts stale (the tests before left it so): wait until it holds this test's
    # person (1.5 m away), then keep publishing a few frames, so that the statuses right after the
    # last put are fresh ones and the first stale one is the timeout's (stopping at the first fresh
    # status, the only put could be the first, and a status computed before it arrived was taken
    # for the timeout: stale after 0 s).
    live.rec.wait("safety/status", lambda s: not s.human_stale and s.min_h_human is not None and s.min_h_human > 0.5, timeout_s=3)
    time.sleep(0.2)
    last_put = humans.stop()
    status = live.rec.wait("safety/status", lambda s: s.human_stale, timeout_s=3)
    stale_after = next(r for r, s in live.rec.timed("safety/status") if r > last_put and s.human_stale) - last_put
    assert 0.45 <= stale_after <= 0.5 + 0.3, stale_after  # human_timeout_s = 0.5
    assert status.min_h_human is not None and 0.5 < status.min_h_human < 1.5  # capsules kept


@pytest.mark.integration
def test_sigterm_stops_the_shared_service_cleanly_with_its_summary(live: Live, machine_wake: dict) -> None:
    """Last user of the shared service: SIGTERM → clean exit and a summary that counts its ticks and
    deadline misses across human traffic, malformed payloads and a pipeline swap. The miss rate is
    printed, not asserted: a timing bound belongs to the benchmarks (``make bench``) and to the one
    acceptance test of the rate, test_runs_at_500_hz_over_zenoh_with_under_1_percent_deadline_misses
    (this run is short and its pipeline swap makes it wall-clock fragile on a shared 2-core VM)."""
    live.proc.popen.terminate()
    assert live.proc.popen.wait(10) == 0
    summary = live.proc.wait_for(lambda line: line.startswith("safety:"), timeout=5)
    m = re.search(r"(\d+) ticks in ([\d.]+) s .* (\d+) deadline misses", summary)
    assert m, summary
    assert int(m[1]) > 0 and 0 <= int(m[3]) <= int(m[1]), summary
    print(f"\n  shared service: {summary.strip()}; machine wake-up latency {machine_wake}")


# --------------------------------------------------------------------------- in-process logic
@pytest.fixture
def service() -> Iterator[SafetyService]:
    conf = load_config(environ={}, overrides={"bus": {"multicast_scouting": False}, "robot_id": f"unit{free_port()}"})
    with SafetyService(conf) as svc:
        yield svc


def test_first_joint_state_syncs_to_the_executor_target_and_a_displaced_robot_is_rejoined_at_u_max(
    service: SafetyService,
) -> None:
    home = service.pipeline.filter.q_cbf.copy()
    measured = home + np.array([0, 0, -0.1, 0.05, 0, 0, 0, 0])
    target = measured + 0.01  # what the executor holds (a predecessor's last command)
    service.joint_state.set(JointState(stamp=0.0, q=measured, dq=np.zeros(8), q_command=target))
    service.tick()
    np.testing.assert_allclose(service.pipeline.filter.q_cbf, target, atol=1e-12)  # continues, no jump
    assert service.resyncs == 0

    service.joint_state.set(JointState(stamp=0.0, q=target + 0.8 * RESYNC_TOLERANCE, dq=np.zeros(8)))
    service.tick()
    np.testing.assert_allclose(service.pipeline.filter.q_cbf, target, atol=1e-12)  # within tolerance: kept
    pushed = target.copy()
    pushed[4] += 1.5 * RESYNC_TOLERANCE
    step_limit = np.asarray(service.conf.safety.u_max) * service.period + 1e-12
    q_prev = service.pipeline.filter.q_cbf.copy()
    ticks = 0
    while True:  # the robot stays where it was pushed; q_cbf joins it through the QP at ≤ u_max
        service.joint_state.set(JointState(stamp=0.0, q=pushed, dq=np.zeros(8)))
        service.tick()
        q = service.pipeline.filter.q_cbf.copy()
        assert (np.abs(q - q_prev) <= step_limit).all(), ticks
        q_prev, ticks = q, ticks + 1
        if service._resync_target is None or ticks > 2000:
            break
    assert service.resyncs == 1 and service._resync_target is None, ticks
    assert np.max(np.abs(q - pushed)) <= RESYNC_DONE and ticks > 10  # not a jump: many steps
    assert service.counters()["watchdog_trips"] == {"resync": 1}


def test_an_executor_that_comes_late_is_joined_at_u_max_not_in_one_jump(service: SafetyService) -> None:
    """Commands already went out from home (no executor yet) when the first JointState arrives, far
    from q_cbf: every command still moves at most u_max·Δt; q_cbf joins the robot through the resync."""
    for _ in range(20):
        service.tick()
    q_prev = service.pipeline.filter.q_cbf.copy()
    far = q_prev + np.array([0.3, -0.3, -1.5, 0.8, 0.0, -1.5, -0.8, 0.0])
    far = np.clip(far, service.pipeline.filter.q_min, service.pipeline.filter.q_max)
    step_limit = np.asarray(service.conf.safety.u_max) * service.period + 1e-12
    for ticks in range(3000):
        service.joint_state.set(JointState(stamp=0.0, q=far, dq=np.zeros(8), q_command=far))
        service.tick()
        q = service.pipeline.filter.q_cbf.copy()
        assert (np.abs(q - q_prev) <= step_limit).all(), ticks
        q_prev = q
        if ticks > 0 and service._resync_target is None:
            break
    assert service.resyncs == 1 and np.max(np.abs(q - far)) <= RESYNC_DONE and ticks > 10


def test_a_joint_state_far_outside_the_joint_limits_is_refused_not_followed(service: SafetyService) -> None:
    """q (or q_command) 0.5 rad past a limit is no robot's: refused and counted, q_cbf neither reset
    nor resynced to the limit; a joint resting just past its limit (pressed) is still a robot's."""
    filt = service.pipeline.filter
    home = filt.q_cbf.copy()
    for bad in ({"q": np.where(np.arange(8) == 2, filt.q_max + 0.5, home)},
                {"q": home, "q_command": np.where(np.arange(8) == 5, filt.q_min - 0.5, home)}):
        service.joint_state.set(JointState(stamp=0.0, dq=np.zeros(8), **bad))
        for _ in range(5):
            service.tick()
    assert service.refusals.own("robot/joint_state") == 2 and service.resyncs == 0
    np.testing.assert_allclose(filt.q_cbf, home, atol=1e-9)
    assert service._robot_at(time.monotonic()) is None  # nothing the filter could settle on
    pressed = np.minimum(home + 0.35, filt.q_max + 0.05)  # beyond the resync tolerance, 5 cm past a limit at most
    service.joint_state.set(JointState(stamp=0.0, q=pressed, dq=np.zeros(8)))
    service.tick()
    assert service.refusals.own("robot/joint_state") == 2


def test_a_protective_stop_begins_where_the_measured_robot_is(service: SafetyService) -> None:
    """As a protective stop begins (a person's torso through the robot's left forearm), the command
    is first brought to the robot: the newest JointState's q extrapolated by its dq over the time
    since it arrived, by at most u_max·Δt per joint; once more on the stop's first tick after a
    command at rest; after that only the joints whose servo would push them along their motion
    (the command ahead of a moving joint), none while the robot stands still; without a stop a
    robot a few mrad off q_cbf is left to the servos."""
    filt, period = service.pipeline.filter, service.period
    step_limit = np.asarray(service.conf.safety.u_max) * period
    home = filt.q_cbf.copy()
    service.joint_state.set(JointState(stamp=0.0, q=home, dq=np.zeros(8)))
    service.tick()  # the first joint state: q_cbf synchronised
    service.joint_state.set(JointState(stamp=0.0, q=home + 2e-3, dq=np.zeros(8)))
    result = service.tick()  # nobody there: no stop, the measured q ignored
    assert not result.protective_stop
    np.testing.assert_allclose(result.q_cbf, home + period * result.u, atol=1e-12)
    q = result.q_cbf
    capsules = person(2.0)[1]
    capsules[0] = service.pipeline.kinematics.compute(q)[0][LEFT_FOREARM]
    service.human.set(human_state(np.zeros(8), capsules))
    lag = np.array([-3e-3, 2e-3, -1e-3, 4e-3, 0.0, -2e-3, 0.05, -0.05])  # the last two beyond u_max Δt
    dq = np.linspace(-0.2, 0.2, 8)
    service.joint_state.set(JointState(stamp=0.0, q=q + lag, dq=dq))
    arrived = service.joint_state.get().received
    result = service.tick(arrived + 0.004)
    assert result.protective_stop and result.settled
    robot = np.clip(q + lag + 0.004 * dq, q - step_limit, q + step_limit)
    np.testing.assert_allclose(result.q_cbf - period * result.u, robot, atol=1e-9)
    np.testing.assert_array_equal(result.u, 0.0)  # the robot stood still: the command is at rest at once
    settled = result.q_cbf
    result = service.tick(arrived + 0.006)  # the stop's first tick after a command at rest: once more
    assert result.protective_stop
    robot = np.clip(q + lag + 0.006 * dq, settled - step_limit, settled + step_limit)
    np.testing.assert_allclose(result.q_cbf - period * result.u, robot, atol=1e-9)
    settled = result.q_cbf
    result = service.tick(arrived + 0.008)  # after it, only the joints their servo would push on
    assert result.protective_stop
    robot = q + lag + 0.008 * dq
    pushed = (np.abs(dq) > STILL_JOINT_SPEED) & ((settled - robot) * dq > 0.0)
    assert pushed.any() and not pushed.all()
    start = np.where(pushed, np.clip(robot, settled - step_limit, settled + step_limit), settled)
    np.testing.assert_allclose(result.q_cbf - period * result.u, start, atol=1e-9)
    assert result.settled
    service.joint_state.set(JointState(stamp=0.0, q=robot, dq=np.zeros(8)))  # the robot now still
    still = service.joint_state.get().received
    service.tick(still + 0.001)
    result = service.tick(still + 0.003)
    assert result.protective_stop and not result.settled  # and never again while it stands still


def assert_brakes_to_rest(service: SafetyService, u_before: np.ndarray, u: np.ndarray) -> None:
    """No longer imitating (q_nom = q_cbf, so u_ref = 0): the command slows toward rest as fast as the
    acceleration bound allows, u = sign(u_before) max(|u_before| − aΔt, 0), and is at rest after."""
    reach = np.asarray(service.conf.safety.accel_max) / service.conf.safety.rate_hz
    np.testing.assert_allclose(u, np.sign(u_before) * np.maximum(np.abs(u_before) - reach, 0.0), atol=1e-9)


def test_stale_human_keeps_capsules_and_stops_imitating(service: SafetyService) -> None:
    service.human.set(human_state(arm_forward(), person(1.0)[1]))
    received = service.human.get().received
    result = service.tick(received + 0.01)
    assert service._q_nom[2] < -1.0 and result.rows.min_h(False) is not None and not service._human_stale
    assert np.abs(result.u).max() > 0.1  # imitating: moving towards the raised arm
    u_before = result.u
    result = service.tick(received + service.conf.safety.human_timeout_s + 0.1)
    assert service._human_stale and result.rows.min_h(False) is not None  # the person is still avoided
    assert_brakes_to_rest(service, u_before, result.u)  # q_nom = q_cbf: no longer imitating
    assert service.watchdogs.trips["human_state"] == 1
    service.tick(received + service.conf.safety.human_timeout_s + 0.2)
    assert service.watchdogs.trips["human_state"] == 1  # counted once per trip
    # a HumanState in another frame is refused by validation: it can never reach the barrier
    with pytest.raises(ValidationError, match="frame_id"):
        HumanState.model_validate({**human_state(np.zeros(8), person(0.2)[1]).model_dump(), "frame_id": "camera"})


def test_between_frames_q_nom_is_extrapolated_one_frame_and_its_rate_fed_forward(service: SafetyService) -> None:
    """q_nom(t) = q + q̇ (t − t_received) for one frame period (the stamps' interval),
    u_ref = q̇_nom + K (q_nom − q_cbf); after that frame, when stale, or with feedforward off: no q̇_nom.
    With the paper's retargeting (q̇_nom = S θ̇; the directions' rate is tested on its own)."""
    full = load_config(environ={}, overrides={"retargeting": {"method": "linear"}}).model_dump(mode="json")
    service.on_config(ConfigUpdate(stamp=0.0, version=2, config=full))
    service.tick()
    assert isinstance(service.pipeline.retargeter, Retargeter)
    theta = arm_forward() * 0.4
    first = human_state(theta, person(2.0)[1])
    rate = np.zeros(8)
    rate[LEFT_SHOULDER_PITCH] = 2.0  # the person's left arm rising at 2 rad/s
    frame = 1 / 30
    second = first.model_copy(update={"stamp": first.stamp + frame, "seq": 1, "theta_rate": rate})
    service.human.set(first)
    service.tick(service.human.get().received + 0.001)
    service.human.set(second)
    received = service.human.get().received
    r = service.pipeline.retargeter
    dq = r.scale * rate
    assert dq[2] == -2.0  # G1 shoulder pitch is negative forward
    gain = service.conf.safety.gain
    for tau, fed in ((0.01, True), (0.02, True), (0.2, False)):
        q_before = service.pipeline.filter.q_cbf.copy()
        result = service.tick(received + tau)
        q_nom = service._q_nom + dq * min(tau, frame)  # never more than one frame ahead
        np.testing.assert_allclose(result.u_ref, gain * (q_nom - q_before) + (dq if fed else 0.0), atol=1e-9)
    # feedforward off: the paper's eq. 7 on the same extrapolated target
    service.conf = service.conf.model_copy(update={"safety": service.conf.safety.model_copy(update={"feedforward": False})})
    q_before = service.pipeline.filter.q_cbf.copy()
    result = service.tick(received + 0.2)
    np.testing.assert_allclose(result.u_ref, gain * (service._q_nom + dq * frame - q_before), atol=1e-9)
    u_before = result.u
    result = service.tick(received + service.conf.safety.human_timeout_s + 0.1)  # stale: hold q_cbf
    assert service._human_stale
    assert_brakes_to_rest(service, u_before, result.u)


def test_a_continuous_target_path_applies_in_place_and_never_jumps_at_a_new_frame(service: SafetyService) -> None:
    """``safety.target_path: continuous`` (a hot field: the same pipeline): at a new frame q_nom starts
    where it was and moves straight to the new state extrapolated one frame ahead, and that path's
    velocity v is fed forward, u_ref = v + K (q_nom − q_cbf)."""
    pipeline = service.pipeline
    full = load_config(environ={}, overrides={"retargeting": {"method": "linear"},  # the path, not the speed cap
                                              "safety": {"target_path": "continuous", "human_speed_mps": 0.0}}
                       ).model_dump(mode="json")
    service.on_config(ConfigUpdate(stamp=0.0, version=2, config=full))
    service.tick()
    assert service.pipeline is pipeline and service.conf.safety.target_path is TargetPath.CONTINUOUS
    first = human_state(arm_forward() * 0.4, person(2.0)[1])
    rate = np.zeros(8)
    rate[LEFT_SHOULDER_PITCH] = 2.0
    frame = 1 / 30
    second = human_state(arm_forward() * 0.6, person(2.0)[1]).model_copy(
        update={"stamp": first.stamp + frame, "seq": 1, "theta_rate": rate})
    service.human.set(first)
    service.tick(service.human.get().received + 0.001)
    start = service._q_nom.copy()  # the first state: held, no path to it
    service.human.set(second)
    received = service.human.get().received
    r = service.pipeline.retargeter
    service.tick(received)  # applies the second state
    end = np.clip(service._q_nom + r.scale * rate * frame, r.q_min, r.q_max)
    assert np.abs(end - start).max() > 0.05  # the new frame is elsewhere: a jumping q_nom would jump there
    v = (end - start) / frame
    gain = service.conf.safety.gain
    for tau in (0.0005, 0.01, 0.02):
        q_before = service.pipeline.filter.q_cbf.copy()
        result = service.tick(received + tau)
        np.testing.assert_allclose(result.u_ref, v + gain * (start + v * tau - q_before), atol=1e-9)
    q_before = service.pipeline.filter.q_cbf.copy()
    result = service.tick(received + 0.2)  # after the frame: at its end, at rest
    np.testing.assert_allclose(result.u_ref, gain * (end - q_before), atol=1e-9)


def test_vanished_person_is_held_and_stops_imitating_until_forgotten(service: SafetyService) -> None:
    full = load_config(environ={}).model_dump(mode="json")
    full["safety"]["lost_human_hold_s"] = hold = 0.05
    service.on_config(ConfigUpdate(stamp=0.0, version=2, config=full))  # a hot field: same pipeline
    pipeline = service.pipeline
    seen = human_state(arm_forward(), person(1.0)[1])
    service.human.set(seen)
    result = service.tick(service.human.get().received + 0.01)
    assert service.pipeline is pipeline and service.conf.safety.lost_human_hold_s == hold
    assert np.abs(result.u).max() > 0.1 and not service._memory.lost  # imitating
    gone = seen.model_copy(update={"seq": 1, "capsule_valid": np.zeros(7, bool), "theta_valid": np.zeros(8, bool)})
    service.human.set(gone)  # fresh, but the whole person is invalid
    u_before = result.u
    result = service.tick(service.human.get().received + 0.01)
    assert service._memory.lost and not service._human_stale
    assert result.rows.min_h(False) is not None  # the remembered capsules are still avoided
    assert_brakes_to_rest(service, u_before, result.u)  # q_nom = q_cbf: no longer imitating
    assert service.watchdogs.trips["human_lost"] == 1
    service._publish_status(0.0, result, result.mode, result.q_cbf)  # SafetyStatus.human_lost is reported
    time.sleep(hold + 0.01)
    service.human.set(gone.model_copy(update={"seq": 2}))  # past the hold: forgotten
    result = service.tick(service.human.get().received + 0.01)
    assert not service._memory.lost and result.rows.min_h(False) is None  # rows disabled
    assert service.watchdogs.trips["human_lost"] == 1


def test_an_older_config_version_is_refused_not_rolled_back_to(service: SafetyService) -> None:
    """After v5 is applied, a delayed v4 or a second writer's v1 is refused and counted; v5 again (a
    config API restarted, republishing) and v6 are taken."""
    full = load_config(environ={}, overrides={"retargeting": {"method": "linear"}}).model_dump(mode="json")
    full["safety"]["phi"] = 0.03
    service.on_config(ConfigUpdate(stamp=0.0, version=5, config=full))
    service.tick()
    assert service.config_version == 5
    stale = {**full, "safety": {**full["safety"], "phi": 0.05}}
    for version in (4, 1):
        service.on_config(ConfigUpdate(stamp=0.0, version=version, config=stale))
        service.tick()
    assert service.config_version == 5 and service.pipeline.filter.params.phi == 0.03
    assert service.refusals.own("config") == 2
    service.on_config(ConfigUpdate(stamp=0.0, version=5, config=full))
    service.on_config(ConfigUpdate(stamp=0.0, version=6, config=stale))
    service.tick()
    assert service.config_version == 6 and service.pipeline.filter.params.phi == 0.05
    assert service.refusals.own("config") == 2


def test_config_update_swaps_pipeline_and_rate(service: SafetyService) -> None:
    # the paper's retargeting: a person standing neutral maps onto home exactly, so q_cbf stays there
    full = load_config(environ={}, overrides={"retargeting": {"method": "linear"}}).model_dump(mode="json")
    # a parameter-only change is applied in place: same pipeline, new FilterParams (a margin home
    # keeps: every self pair is >= 3.9 cm apart there, so q_cbf stays at home below)
    pipeline = service.pipeline
    full["safety"].update(phi=0.03, intrusion_backout_mps=0.02)
    service.on_config(ConfigUpdate(stamp=0.0, version=2, config=full))
    service.tick()
    assert service.pipeline is pipeline and service.pipeline.filter.params.phi == 0.03
    assert service.pipeline.filter.params.intrusion_backout_mps == 0.02
    assert service.config_version == 2
    # a structural one (pair preset) and a retargeting change: new pipeline at the next step
    full["safety"].update(pairs="paper72", rate_hz=250.0, gamma=3.0)
    full["retargeting"]["mirror"] = True
    q_before = service.pipeline.filter.q_cbf.copy()
    service.on_config(ConfigUpdate(stamp=0.0, version=3, config=full))
    assert service.config_version == 2  # applied at the next step, not in the callback
    service.tick()
    assert service.config_version == 3 and len(service.pipeline.pairs) == 72
    # one person fills 7 of the preset's 14 external slots; the second person's rows stay disabled
    service.human.set(human_state(np.zeros(8), person(1.0)[1]))
    result = service.tick()
    assert result.rows.min_h(False) is not None and int(result.rows.enabled.sum()) == N_SELF_PAIRS + 49
    assert service.period == pytest.approx(1 / 250) and service.pipeline.filter.params.gamma == 3.0
    assert service.pipeline.retargeter.mirror
    np.testing.assert_allclose(service.pipeline.filter.q_cbf, q_before, atol=1e-9)  # q_cbf carried over
    assert service.conf.robot_id == service.bus.robot_id  # the session's identity is not replaced
    full["robot"]["spec"] = "robots/does_not_exist.yaml"
    service.on_config(ConfigUpdate(stamp=0.0, version=4, config=full))
    service.tick()
    assert service.config_version == 3 and service.dropped()["config"] == 1


def test_realtime_scheduling_is_entered_or_refused_cleanly() -> None:
    import os

    seen: dict[str, object] = {}

    def worker() -> None:
        seen["description"] = enter_realtime(5)
        seen["during"] = os.sched_getscheduler(0)
        leave_realtime()
        seen["after"] = os.sched_getscheduler(0)

    thread = threading.Thread(target=worker)
    thread.start()
    thread.join(5)
    expected = os.SCHED_FIFO if str(seen["description"]).startswith("SCHED_FIFO") else os.SCHED_OTHER
    assert seen["during"] == expected and seen["after"] == os.SCHED_OTHER
    assert os.sched_getscheduler(0) == os.SCHED_OTHER  # only the calling thread was affected
    assert enter_realtime(0) == "normal scheduling"


def test_the_retargeting_by_directions_follows_the_persons_skeleton(service: SafetyService) -> None:
    """Switched on by a config update: q_nom comes from the state's keypoints (the arm raised
    forward points the robot's left arm forward), and a later change of φ reaches its clearance."""
    from services.safety.direction_retarget import DirectionRetargeter

    full = load_config(environ={}, overrides={"retargeting": {"method": "directions"}}).model_dump(mode="json")
    service.on_config(ConfigUpdate(stamp=0.0, version=2, config=full))
    service.tick()
    assert isinstance(service.pipeline.retargeter, DirectionRetargeter)
    state = human_state(arm_forward(), person(2.0)[1])
    for k in range(30):  # a second of the same pose: the target converges at 2 iterations a state
        service.human.set(state.model_copy(update={"stamp": state.stamp + k / 30, "seq": k}))
        service.tick(service.human.get().received + 0.001)
    assert service._q_nom[2] < -1.2  # G1 shoulder pitch is negative forward
    full["safety"]["phi"] = 0.03
    service.on_config(ConfigUpdate(stamp=0.0, version=3, config=full))
    service.tick()
    assert service.pipeline.retargeter.clearance == 0.03 and service.pipeline.retargeter.phi == 0.03
