"""``safemimic perception`` as a real process over real Zenoh on loopback.

The service runs with an import hook that refuses MuJoCo, Pinocchio, the QP solvers, numba,
FastAPI and the other non-perception packages (as if they were not installed), so the same run
proves the perception role needs none of them.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys

import numpy as np
import pytest

from services.perception.placement import Placement
from services.perception.scenarios import get_scenario, scenario_recording
from shared.bus import Bus
from shared.config import BusConfig, HumanConfig, load_config
from shared.messages import ConfigUpdate, HumanState
from shared.names import KEYPOINT_INDEX as K
from shared.skeleton import write_recording
from tests.support.bus import BusRecorder
from tests.support.processes import free_port
from tests.support.team import REPO

pytestmark = pytest.mark.integration

#: Everything outside ``pip install .[perception]`` (base deps + OpenCV) that the stack uses elsewhere.
HEAVY = ("mujoco", "pinocchio", "pin", "osqp", "daqp", "numba", "llvmlite", "fastapi", "uvicorn", "starlette",
         "mink", "matplotlib", "scipy", "httpx", "playwright")
#: ``python -c`` program: block the heavy packages, run the safemimic CLI, report import attempts.
LIGHT_RUNNER = f"""
import importlib.abc, json, sys
HEAVY = {set(HEAVY)!r}
attempts = []
class Refuse(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in HEAVY:
            attempts.append(name)
            raise ImportError(name + " is not installed here (perception must not need it)")
        return None
sys.meta_path.insert(0, Refuse())
from safemimic.cli import main
code = main(sys.argv[1:])
loaded = sorted(m for m in sys.modules if m.split(".")[0] in HEAVY)
print(json.dumps({{"event": "imports", "attempted": attempts, "loaded": loaded}}), flush=True)
sys.exit(code)
"""
FPS = 30.0
SECONDS = 3.0


def test_service_streams_a_30fps_replay_in_order_without_heavy_imports(spawn, tmp_path) -> None:
    recording = scenario_recording(get_scenario("side-by-side-arm-raise"), SECONDS, FPS, Placement(y=0.7))
    recording.xyz[40, K["right_wrist"]] += (0.0, 0.0, 0.8)  # a detection glitch: rejected, counted
    recording.conf[50:55, K["left_wrist"]] = 0.0  # a short dropout: held
    path = write_recording(tmp_path / "raise.npz", recording)

    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    robot_id = f"perception_test_{port}"
    conf = BusConfig(mode="peer", listen=[endpoint], multicast_scouting=False)
    with Bus(conf, robot_id, "test") as bus:
        seen = BusRecorder(bus, ("human/state",), alive=True)
        service = spawn(
            "-c", LIGHT_RUNNER, "perception", "--recording", str(path), "--robot-id", robot_id,
            "--mode", "peer", "--connect", endpoint, "--no-multicast", "--wait-subscriber", "10",
        )
        ready = service.wait_json("ready", timeout=20)
        assert ready["fps"] == FPS and "raise.npz" in ready["source"]
        done = service.wait_json("done", timeout=SECONDS + 15)
        imports = service.wait_json("imports", timeout=10)
        assert service.popen.wait(10) == 0
        gone = seen.wait_token("perception", False, timeout_s=5)
        assert seen.wait_token("perception", True, timeout_s=0) < gone
    received: list[HumanState] = seen.between("human/state")

    frames = len(recording)
    assert imports == {"event": "imports", "attempted": [], "loaded": []}
    assert done["frames"] == done["published"] == frames and done["errors"] == 0
    assert done["rejected_jumps"] >= 1 and done["filter_resets"] == 0
    assert len(received) >= 0.95 * frames, f"received {len(received)} of {frames}"
    seqs = [m.seq for m in received]
    assert seqs == sorted(set(seqs)) and seqs[-1] <= frames - 1  # in order, no duplicates

    radii = np.array([HumanConfig().torso_radius, 0.06, 0.05, 0.06, 0.05, 0.08, 0.08])
    for message in received:
        assert message.frame_id == "robot" and message.source.startswith("perception@")  # service@zid
        assert message.capture_stamp is not None and message.capture_stamp <= message.stamp
        np.testing.assert_allclose(message.capsule_radii, radii)
        assert message.theta_valid.all() and message.capsule_valid.all() and message.keypoint_valid.all()
    # Keypoints are in the robot frame: the person stands 0.7 m to the robot's left.
    pelvis = np.array([m.keypoints[K["pelvis"]] for m in received])
    np.testing.assert_allclose(pelvis[:, 1], 0.7, atol=0.02)
    # The near (right) arm rises sideways: its shoulder roll reaches the scripted 1.2 rad.
    assert max(m.theta[6] for m in received) == pytest.approx(1.2, abs=0.05)
    stamps = np.array([m.capture_stamp for m in received])
    assert np.median(np.diff(stamps)) == pytest.approx(1 / FPS, rel=0.2)  # published at the source rate


def test_a_camera_that_cannot_open_is_a_clear_error_not_a_traceback() -> None:
    done = subprocess.run(
        [sys.executable, "-m", "safemimic.cli", "perception", "--device", "63", "--no-multicast"],
        cwd=REPO, capture_output=True, text=True, timeout=60,
    )
    assert done.returncode == 2
    assert ("cannot open camera 63" in done.stderr or "pose-model install" in done.stderr), done.stderr
    assert "Traceback" not in done.stderr


def test_bad_recording_and_bad_flags_exit_with_a_message(tmp_path) -> None:
    (tmp_path / "junk.npz").write_bytes(b"not a zip file")
    for args, expected in (
        (["--recording", str(tmp_path / "junk.npz")], "cannot read"),
        (["--placement", "somewhere"], "placement"),
        (["--scenario", "juggling"], "unknown scenario"),
    ):
        done = subprocess.run(
            [sys.executable, "-m", "safemimic.cli", "perception", "--no-multicast", "--fast", *args],
            cwd=REPO, capture_output=True, text=True, timeout=60,
        )
        assert done.returncode == 2, (args, done.stderr)
        assert expected in done.stderr and "Traceback" not in done.stderr, done.stderr


def test_service_keeps_running_through_a_recording_full_of_garbage(spawn, tmp_path) -> None:
    """NaN frames, infinite points, teleports: every frame is still published, finite."""
    rng = np.random.default_rng(2)
    recording = scenario_recording(get_scenario("wave"), 2.0, FPS, Placement(x=0.95, yaw=math.pi))
    xyz = recording.xyz
    xyz[5:16] = np.nan  # the person lost for longer than the hold time
    xyz[20, :, 0] = 50.0  # everything 50 m away for one frame
    xyz[30:50, K["left_elbow"]] = rng.normal(size=(20, 3))  # elbow noise of a metre
    path = write_recording(tmp_path / "garbage.npz", recording)
    port = free_port()
    robot_id = f"perception_garbage_{port}"
    conf = BusConfig(mode="peer", listen=[f"tcp/127.0.0.1:{port}"], multicast_scouting=False)
    with Bus(conf, robot_id, "test") as bus:
        seen = BusRecorder(bus, ("human/state",))
        service = spawn(
            "-m", "safemimic.cli", "perception", "--recording", str(path), "--robot-id", robot_id, "--fast",
            "--mode", "peer", "--connect", f"tcp/127.0.0.1:{port}", "--no-multicast", "--wait-subscriber", "10",
        )
        done = service.wait_json("done", timeout=20)
        assert service.popen.wait(10) == 0
    assert done["errors"] == 0 and done["published"] == len(recording)
    assert done["rejected_jumps"] > 0 and done["invalid_frames"] > 0
    assert bus.dropped.total() == 0
    received = seen.between("human/state")
    assert received and all(np.isfinite(m.theta).all() and np.isfinite(m.capsules).all() for m in received)
    print(json.dumps({k: done[k] for k in ("rejected_jumps", "reacquired", "invalid_frames", "missing_points")}))


def test_config_updates_apply_at_the_next_frame(spawn) -> None:
    """A ConfigUpdate (as the config API publishes it) changes the human radii live; a bad one is refused."""
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    robot_id = f"perception_config_{port}"
    stack = load_config().model_dump(mode="json")
    with Bus(BusConfig(mode="peer", listen=[endpoint], multicast_scouting=False), robot_id, "test") as bus:
        seen = BusRecorder(bus, ("human/state",))
        service = spawn(
            "-m", "safemimic.cli", "perception", "--scenario", "neutral", "--loop", "--robot-id", robot_id,
            "--mode", "peer", "--connect", endpoint, "--no-multicast", "--wait-subscriber", "10", "--duration", "20",
        )
        service.wait_json("ready", timeout=20)
        seen.wait_count("human/state", 3, timeout_s=5)
        assert seen.last("human/state").capsule_radii[0] == pytest.approx(0.15)
        publisher = bus.publisher("config")
        bad = json.loads(json.dumps(stack))
        bad["human"]["torso_radius"] = 5.0  # beyond the model's bound: refused
        publisher.put(ConfigUpdate(stamp=0.0, version=1, changed=["human.torso_radius"], config=bad))
        good = json.loads(json.dumps(stack))
        good["human"]["torso_radius"] = 0.2
        good["perception"]["angles"]["estimator"] = "paper"
        publisher.put(ConfigUpdate(stamp=0.0, version=2, changed=["human.torso_radius"], config=good))
        seen.wait("human/state", lambda m: m.capsule_radii[0] == pytest.approx(0.2), timeout_s=5)
        service.popen.terminate()
        done = service.wait_json("done", timeout=10)
    assert done["config_version"] == 2 and done["rejected_configs"] == 1 and done["errors"] == 0
