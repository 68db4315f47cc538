"""The live viewer's scene on a real Zenoh bus: it draws what arrives, survives garbage and silence."""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

import numpy as np
import pytest

rr = pytest.importorskip("rerun", reason="the viz extra (rerun-sdk) is not installed")

from services.viewer.live import DECIMATED, LiveScene  # noqa: E402
from services.viewer.robot_mesh import RobotMesh  # noqa: E402
from shared.bus import Bus  # noqa: E402
from shared.config import BusConfig, load_config  # noqa: E402
from shared.messages import JointCommand, JointState, SafetyMode, SafetyStatus  # noqa: E402
from shared.robot_spec import configured_robot_spec  # noqa: E402
from tests.support.processes import Proc, free_port  # noqa: E402
from tests.test_viewer_recording import rrd_rows  # noqa: E402


def test_scene_draws_new_messages_counts_garbage_and_reports_a_silent_publisher(tmp_path: Path) -> None:
    port = free_port()
    listen = BusConfig(mode="peer", listen=[f"tcp/127.0.0.1:{port}"], multicast_scouting=False)
    connect = BusConfig(mode="peer", connect=[f"tcp/127.0.0.1:{port}"], multicast_scouting=False)
    spec = configured_robot_spec(load_config())
    mesh = RobotMesh(spec)
    rec = rr.RecordingStream("test_viewer", send_properties=False)
    rec.save(tmp_path / "live.rrd")
    with Bus(listen, "test", "viewer") as vbus, Bus(connect, "test", "executor") as pbus:
        scene = LiveScene(vbus, rec, mesh, mesh.capsule_radii)
        joints, status = pbus.publisher("robot/joint_state"), pbus.publisher("safety/status")
        time.sleep(0.5)  # the subscription reaches the publisher
        for k in range(3):
            joints.put(JointState(stamp=time.monotonic(), q=np.full(8, 0.1 * k), dq=np.zeros(8)))
            status.put(SafetyStatus(stamp=time.monotonic(), mode=SafetyMode.ACTIVE, min_h_self=0.01, min_h_human=None,
                                    active_constraints=1, total_constraints=63, qp_solve_time_ms=0.01, step_time_ms=0.1,
                                    q_nom=np.full(8, 0.2), binding_pairs=["left_forearm|right_forearm"],
                                    person_intrusion=k > 0, backing_out=k == 2, human_lateness_ms=10.0 * k))
            pbus.put_raw("robot/joint_state", b"\x93garbage")
            time.sleep(0.1)
            scene.frame()
        assert scene.received["robot/joint_state"] == 3 and scene.received["safety/status"] == 3
        assert vbus.dropped["robot/joint_state"] >= 1  # counted, never drawn, never raised
        assert scene.errors == {} and scene.logged["robot"] == 3 and scene.logged["binding"] == 3
        scene.frame(time.monotonic() + 5.0)  # nothing new for 5 s: reported stale, the last picture stays
        assert "robot/joint_state" in scene.stats()["stale"]
    rec.flush()
    rows = rrd_rows(tmp_path / "live.rrd")
    assert rows["/robot/cbf/capsules"] == 3 and rows["/joints/left_elbow_joint/q"] == 3
    assert rows["/joints/left_elbow_joint/q_nom"] == 3 and rows["/barriers/cbf/binding"] == 3
    # a body's pose is logged when it moved: the static mesh + every frame for the arm, the first frame only
    # for the pelvis (no imitation joint moves it)
    assert rows["/robot/cbf/mesh/left_elbow_link"] == 1 + 3 and rows["/robot/cbf/mesh/pelvis"] == 1 + 1
    assert rows["/barriers/cbf/min_h/self"] == 3 and rows["/viewer/log"] >= 1
    assert rows["/robot/cbf/status/backing_out"] == rows["/robot/cbf/status/human_lateness_ms"] == 3
    assert rows["/robot/cbf/status/person_intrusion"] == 3


def test_the_viewer_session_lets_in_at_most_one_control_rate_sample_per_frame() -> None:
    """A 500 Hz JointCommand stream reaches the viewer's Python at ≤ 30 samples a second: Zenoh drops
    the rest in the session (counted here as every sample Python saw: drawn + superseded + dropped),
    although the scene is read 100 times a second; a session without the cap sees every one."""
    port = free_port()
    listen = BusConfig(mode="peer", listen=[f"tcp/127.0.0.1:{port}"], multicast_scouting=False)
    connect = BusConfig(mode="peer", connect=[f"tcp/127.0.0.1:{port}"], multicast_scouting=False)
    mesh = RobotMesh(configured_robot_spec(load_config()))
    rec = rr.RecordingStream("test_viewer_decimated", send_properties=False)
    rec.memory_recording()
    topic = "robot/command"
    with Bus(listen, "test", "safety") as pbus, Bus(connect, "test", "onlooker") as full, \
            Bus(connect, "test", "viewer", max_hz=dict.fromkeys(DECIMATED, 30.0)) as vbus:
        scene = LiveScene(vbus, rec, mesh, mesh.capsule_radii)
        everything = full.newest(topic)
        commands = pbus.publisher(topic)
        time.sleep(0.5)  # the subscriptions reach the publisher
        seen0 = scene.received[topic] + vbus.superseded[topic] + vbus.dropped[topic]
        all0 = everything.count + full.superseded[topic]
        start, sent, next_frame = time.monotonic(), 0, 0.0
        while (elapsed := time.monotonic() - start) < 3.0:
            commands.put(JointCommand(stamp=time.monotonic(), q=np.zeros(8), dq=np.zeros(8)))
            sent += 1
            if elapsed >= next_frame:
                scene.frame()
                everything.get()
                next_frame += 0.01
            time.sleep(0.002)
        time.sleep(0.1)
        scene.frame()
        everything.get()
        seen = scene.received[topic] + vbus.superseded[topic] + vbus.dropped[topic] - seen0
        total = everything.count + full.superseded[topic] - all0
    assert sent > 600 and total >= 0.9 * sent, (sent, total)  # every sample reaches an uncapped session
    assert 0.5 * 30 * elapsed <= seen <= 30 * elapsed + 2, (seen, elapsed)


@pytest.mark.skipif(not hasattr(os, "SCHED_IDLE"), reason="SCHED_IDLE is Linux's")
def test_the_viewer_process_runs_every_thread_at_idle_priority(tmp_path: Path) -> None:
    """``safemimic viewer`` (here recording to a file) says it runs under SCHED_IDLE and every thread
    of it does, Zenoh's and Rerun's included: a waking control tick preempts any of them."""
    viewer = Proc([sys.executable, "-m", "services.viewer", "--save", str(tmp_path / "v.rrd"), "--duration", "30",
                   "--insecure", "--mode", "peer", "--no-multicast"])
    try:
        ready = viewer.wait_json("ready", timeout=60)
        viewer.wait_json("stats", timeout=10)  # its loop runs: every thread it starts has started
        threads = [int(t) for t in os.listdir(f"/proc/{viewer.popen.pid}/task")]
        policies = {}
        for t in threads:
            try:
                policies[t] = os.sched_getscheduler(t)
            except ProcessLookupError:  # a thread that ended meanwhile
                pass
    finally:
        viewer.stop()
    assert ready["scheduling"] == "SCHED_IDLE"
    assert len(threads) > 3 and set(policies.values()) == {os.SCHED_IDLE}, policies
