"""`safemimic executor` as a real process over real Zenoh on 127.0.0.1 (peer mode, explicit
endpoints, multicast off). This test process plays the safety service (JointCommand) and
perception (HumanState) and listens to JointState; the service's final counters come as one JSON
line when it is stopped with SIGTERM."""

from __future__ import annotations

import threading
import time

import msgpack
import numpy as np
import pytest

from shared.bus import Bus
from shared.codec import encode
from shared.config import BusConfig
from shared.messages import HumanState, JointCommand
from shared.names import CAPSULE_NAMES
from shared.robot_spec import default_robot_spec_path, load_robot_spec
from tests.support.bus import BusRecorder
from tests.support.processes import free_port
from tests.support.team import G1_MJCF

pytestmark = pytest.mark.integration

SPEC = load_robot_spec(default_robot_spec_path())
Q_HOME = np.array([SPEC.home.get(j, 0.0) for j in SPEC.imitation_joints])
STEP = np.array([0.2, 0.2, -0.4, 0.3, -0.4, -0.4, -0.3, -0.4])  # arms out and forward: collision-free
TORSO = CAPSULE_NAMES.index("torso")
STOPS = 5  # protective-stop commands sent


class Commander:
    """Publishes JointCommand(q, dq=0) at 200 Hz from a thread until stopped."""

    def __init__(self, bus: Bus, q: np.ndarray) -> None:
        self._publisher = bus.publisher("robot/command")
        self._q = q
        self._stop = threading.Event()
        self.first_put = self.last_put = 0.0
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(0.005):
            self._publisher.put(JointCommand(stamp=time.monotonic(), q=self._q, dq=np.zeros(8)))
            self.last_put = time.monotonic()
            self.first_put = self.first_put or self.last_put

    def stop(self) -> float:
        self._stop.set()
        self._thread.join(2)
        return self.last_put


def human_in_pelvis() -> HumanState:
    """Only the torso capsule valid, 4 cm long, inside the robot's welded pelvis."""
    capsules = np.zeros((7, 2, 3))
    capsules[TORSO] = [[0.0, -0.02, 0.72], [0.0, 0.02, 0.72]]
    valid = np.zeros(7, bool)
    valid[TORSO] = True
    return HumanState(
        stamp=time.monotonic(), keypoints=np.zeros((15, 3)), keypoint_valid=np.zeros(15, bool),
        theta=np.zeros(8), theta_valid=np.zeros(8, bool), capsules=capsules,
        capsule_radii=np.full(7, 0.03), capsule_valid=valid,
    )


@pytest.mark.parametrize("which", ["ours", "real_g1"])
def test_executor_follows_holds_and_counts_over_zenoh(spawn, which: str) -> None:
    model_flags: list[str] = []
    if which == "real_g1":
        if not G1_MJCF.is_file():
            pytest.skip(f"real G1 model not found at {G1_MJCF} (set SAFEMIMIC_TEAM_SHARED to the team folder)")
        model_flags = ["--robot-model", str(G1_MJCF)]
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    service = spawn(
        "-m", "safemimic.cli", "executor", "--mode", "peer", "--listen", endpoint, "--no-multicast",
        "--viewer", *model_flags, env={"DISPLAY": "", "WAYLAND_DISPLAY": ""},
    )
    with Bus(BusConfig(mode="peer", connect=[endpoint], multicast_scouting=False), "g1", "test") as bus:
        states = BusRecorder(bus, ("robot/joint_state",), alive=True)
        states.wait_token("executor", True, timeout_s=20)
        first = states.wait("robot/joint_state", lambda m: True, timeout_s=10, since=0.0)
        np.testing.assert_allclose(first.q, Q_HOME, atol=1e-3)  # no command yet: home

        # A step on all 8 joints is followed to within 0.02 rad in 0.5 s.
        target = Q_HOME + STEP
        commander = Commander(bus, target)
        while not commander.first_put:
            time.sleep(0.001)
        reached, _ = states.wait_timed("robot/joint_state", lambda m: np.abs(m.q - target).max() < 0.02, timeout_s=2,
                                       since=commander.first_put)
        print(f"{which}: step followed to within 0.02 rad after {reached - commander.first_put:.3f} s")
        assert reached - commander.first_put <= 0.5, f"reached after {reached - commander.first_put:.3f} s"

        # Commands stop once the robot has settled (still moving at "within 0.02 rad", it may pass
        # 0.02 again on its way in): after the timeout it keeps holding the last commanded position.
        states.wait("robot/joint_state", lambda m: np.abs(m.q - target).max() < 0.01, timeout_s=2, since=reached)
        stopped = commander.stop()
        time.sleep(0.7)
        held = [m.q for m in states.between("robot/joint_state", stopped)]
        assert len(held) > 50, "JointState must keep coming while commands are stale"
        assert np.abs(np.array(held) - target).max() < 0.02

        # Malformed payloads and a human state in the wrong frame are dropped; the service goes on.
        bus.put_raw("robot/command", b"\xc1 not msgpack")
        bus.put_raw("robot/command", msgpack.packb({"schema": {"name": "JointCommand", "version": JointCommand.SCHEMA_VERSION},
                                                    "stamp": 0.0, "q": [1.0] * 3, "dq": [0.0] * 8}))
        bus.put_raw("human/state", b"\x00" * 64)
        wrong_frame = human_in_pelvis()
        wrong_frame.frame_id = "camera"  # type: ignore[assignment]  (encode does not re-validate)
        bus.put_raw("human/state", encode(wrong_frame))
        # A protective stop's commands are applied (with the servos damped harder) and counted.
        commands = bus.publisher("robot/command")
        for _ in range(STOPS):
            commands.put(JointCommand(stamp=time.monotonic(), q=target, dq=np.zeros(8), protective_stop=True))
            time.sleep(0.02)
        # The person's torso capsule inside the welded pelvis: counted as a robot–human contact.
        humans = bus.publisher("human/state")
        for _ in range(5):
            humans.put(human_in_pelvis())
            time.sleep(0.02)
        after = time.monotonic()
        time.sleep(0.2)
        assert len(states.between("robot/joint_state", after)) > 10, "the service stopped publishing after bad input"

    service.popen.terminate()
    counters = service.wait_json("stopped", timeout=15)
    output = "".join(service.output)
    assert "needs a display" in output, "--viewer without a display must say why it runs headless"
    assert counters["tick_errors"] == 0
    assert counters["commands_applied"] >= 20  # 200 Hz until the step was reached
    assert 1 <= counters["stop_commands"] <= STOPS, counters["stop_commands"]  # the Commander's are no stops
    assert counters["command_timeouts"] >= 1
    assert counters["stale_ticks"] >= 0.4 * counters["rate_hz"]  # ≥ 0.4 s of the 0.5 s held after the timeout
    assert counters["dropped"].get("robot/command", 0) >= 2
    assert counters["dropped"].get("human/state", 0) >= 2
    assert counters["human_updates"] >= 1
    contacts = counters["contacts"]
    assert "pelvis|torso" in contacts["robot_human"]["pairs"], contacts
    assert contacts["robot_robot"]["steps"] == 0, contacts
    assert counters["achieved_hz"] > 0.9 * counters["rate_hz"]


def test_bad_robot_model_is_a_clear_error(spawn, tmp_path) -> None:
    missing = tmp_path / "nope.xml"
    service = spawn("-m", "services.executor", "--robot-model", str(missing), "--no-multicast", "--duration", "1")
    assert service.popen.wait(30) == 2
    time.sleep(0.1)  # let the reader thread drain stdout
    assert f"robot model {missing} does not exist" in "".join(service.output)


def test_the_executor_follows_one_safety_service_at_a_time(spawn) -> None:
    """Two sessions command at once (an old safety service left running beside a new one): the
    executor follows the first and refuses the other's commands instead of interleaving both; once
    the first falls silent past the command timeout, the other is followed."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    service = spawn("-m", "safemimic.cli", "executor", "--mode", "peer", "--listen", endpoint, "--no-multicast")
    config = BusConfig(mode="peer", connect=[endpoint], multicast_scouting=False)
    with Bus(config, "g1", "test") as bus, Bus(config, "g1", "second") as other:
        states = BusRecorder(bus, ("robot/joint_state",), alive=True)
        states.wait_token("executor", True, timeout_s=20)
        first_target, second_target = Q_HOME + STEP, Q_HOME - 0.5 * STEP
        first = Commander(bus, first_target)
        while not first.first_put:
            time.sleep(0.001)
        time.sleep(0.1)
        second = Commander(other, second_target)
        time.sleep(1.0)
        both = [m.q for m in states.between("robot/joint_state", time.monotonic() - 0.5)]
        assert np.abs(np.array(both) - first_target).max() < 0.02, "only the first is followed"
        stopped = first.stop()
        reached, _ = states.wait_timed("robot/joint_state", lambda m: np.abs(m.q - second_target).max() < 0.02,
                                       timeout_s=3, since=stopped)
        second.stop()
    service.popen.terminate()
    counters = service.wait_json("stopped", timeout=15)
    assert counters["commander_switches"] == 1
    assert counters["dropped"].get("robot/command", 0) >= 100  # the second's 200 Hz while the first commanded
    assert counters["tick_errors"] == 0
