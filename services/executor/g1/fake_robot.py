"""A stand-in for a Unitree G1 on DDS, to rehearse and test the G1 executor without the robot.

It speaks the robot's side of unitree_sdk2's topics with real CycloneDDS: publishes ``rt/lowstate``
(``unitree_hg`` LowState_, 500 Hz, the configured ``mode_machine``), obeys ``rt/arm_sdk`` and
``rt/lowcmd``, and records every command frame it receives (receive time, every field, whether its
CRC is right) into an ``.npz`` file at exit. It is not a model of the robot's dynamics: each motor
moves towards its effective target with a first-order lag of ``--lag`` seconds, where the effective
target is

* ``rt/arm_sdk`` (slots 12–28 with ``mode`` 1): ``(1 − w)·balance pose + w·q``, ``w`` =
  ``motor_cmd[29].q`` clipped to [0, 1] (the robot's blend of our command over its balance controller);
* ``rt/lowcmd``: ``q`` where ``kp > 0``; a motor with ``kp = 0`` stays where it is (damping);
* otherwise the balance pose (:data:`BALANCE_POSE`), which the robot holds by itself.

``tau_est`` is the PD torque ``kp (q − q_meas) + kd (dq − dq_meas)`` of the commanded motors. Motors
the variant lacks (e.g. waist roll/pitch with ``mode_machine`` 6) report zeros and never move.
Frames whose CRC is wrong are recorded and otherwise ignored, as the robot ignores them.

``SIGUSR1`` pauses/resumes ``rt/lowstate`` (a lost state stream); ``SIGTERM``/``SIGINT`` write the
record, print a JSON summary line and exit. Run: ``python -m services.executor.g1.fake_robot
--interface lo --record /tmp/g1.npz`` next to ``safemimic executor --backend g1 --interface lo``.
"""

from __future__ import annotations

import argparse
import json
import math
import signal
import sys
import threading
import time
from pathlib import Path

import numpy as np

from services.executor.g1.dds import (
    DdsLink,
    IMUState_,
    LowCmd_,
    LowState_,
    MotorState_,
    lowcmd_to_frame,
)
from services.executor.g1.frames import LOWCMD_DTYPE, lowcmd_crc
from services.executor.g1.layout import (
    ARM_SDK_SLOTS,
    NUM_BODY_MOTORS,
    NUM_MOTOR_SLOTS,
    TOPIC_ARM_SDK,
    TOPIC_LOWCMD,
    TOPIC_LOWSTATE,
    WEIGHT_SLOT,
    joint_slot,
    variant_of,
)
from shared.stop_signals import stop_on_signals

__all__ = ["BALANCE_POSE", "FakeG1", "main"]

#: The pose the stand-in's "balance controller" holds (rad, slot order): standing, arms hanging a
#: little forward and out, elbows bent; deliberately not the robot description's home.
BALANCE_POSE = np.zeros(NUM_BODY_MOTORS)
for _name, _angle in {
    "left_hip_pitch_joint": -0.1, "right_hip_pitch_joint": -0.1, "left_knee_joint": 0.3, "right_knee_joint": 0.3,
    "left_ankle_pitch_joint": -0.2, "right_ankle_pitch_joint": -0.2,
    "left_shoulder_pitch_joint": 0.3, "left_shoulder_roll_joint": 0.25, "left_elbow_joint": 0.9,
    "right_shoulder_pitch_joint": 0.3, "right_shoulder_roll_joint": -0.25, "right_elbow_joint": 0.9,
}.items():
    BALANCE_POSE[joint_slot(_name)] = _angle

_ARM_SDK = np.zeros(NUM_BODY_MOTORS, bool)
_ARM_SDK[list(ARM_SDK_SLOTS)] = True
_TOPIC_IDS = {TOPIC_ARM_SDK: 0, TOPIC_LOWCMD: 1}
_RECORD_FIELDS = ("mode", "q", "dq", "tau", "kp", "kd")


class FakeG1:
    """The stand-in robot: one loop at ``rate_hz`` taking commands, moving, publishing its state."""

    def __init__(self, link: DdsLink, mode_machine: int, rate_hz: float, lag_s: float) -> None:
        variant = variant_of(mode_machine)
        self.absent = variant.absent_slots if variant else frozenset()
        self.present = np.array([i not in self.absent for i in range(NUM_BODY_MOTORS)])
        self.mode_machine = mode_machine
        self.period = 1.0 / rate_hz
        self.alpha = 1.0 - math.exp(-self.period / lag_s)
        self.q = np.where(self.present, BALANCE_POSE, 0.0)
        self.dq = np.zeros(NUM_BODY_MOTORS)
        self.tau = np.zeros(NUM_BODY_MOTORS)
        self.target = self.q.copy()
        self.publishing = True
        self.tick = 0
        self.frames: list[tuple[float, int, bool, np.ndarray]] = []
        self.states: list[tuple[float, np.ndarray]] = []
        self.link = link  # the participant lives as long as this object
        self._writer = link.writer(TOPIC_LOWSTATE, LowState_)
        self._readers = {topic: link.reader(topic, LowCmd_, depth=64) for topic in _TOPIC_IDS}

    def toggle_state(self, *_: object) -> None:
        self.publishing = not self.publishing

    def run(self, stop: threading.Event) -> None:
        due = time.monotonic()
        while not stop.is_set():
            now = time.monotonic()
            for topic, reader in self._readers.items():
                for message in reader.take(N=64):
                    if isinstance(message, LowCmd_):
                        self._obey(topic, lowcmd_to_frame(message), now)
            previous = self.q.copy()
            self.q = np.where(self.present, self.q + self.alpha * (self.target - self.q), 0.0)
            self.dq = (self.q - previous) / self.period
            self.tick += 1
            if self.publishing:
                self._writer.write(self._lowstate())
                self.states.append((now, self.q.astype(np.float32)))
            due += self.period
            stop.wait(max(0.0, due - time.monotonic()))

    def _obey(self, topic: str, frame: np.ndarray, now: float) -> None:
        crc_ok = int(frame["crc"]) == lowcmd_crc(frame)
        self.frames.append((now, _TOPIC_IDS[topic], crc_ok, frame.copy()))
        if not crc_ok:
            return
        m = frame["motor_cmd"][:NUM_BODY_MOTORS]
        on = (m["mode"] == 1) & self.present
        q_cmd, kp, kd = m["q"].astype(float), m["kp"].astype(float), m["kd"].astype(float)
        if topic == TOPIC_ARM_SDK:
            w = float(np.clip(frame["motor_cmd"]["q"][WEIGHT_SLOT], 0.0, 1.0))
            on &= _ARM_SDK
            self.target = np.where(on, (1.0 - w) * BALANCE_POSE + w * q_cmd, BALANCE_POSE)
            gain = w
        else:
            stiff = on & (kp > 0)
            self.target = np.where(stiff, q_cmd, np.where(on, self.q, BALANCE_POSE))
            gain = 1.0
        pd = kp * (q_cmd - self.q) + kd * (m["dq"].astype(float) - self.dq)
        self.tau = np.where(on, gain * pd, 0.0)

    def _lowstate(self) -> LowState_:
        motors = []
        for i in range(NUM_MOTOR_SLOTS):
            live = i < NUM_BODY_MOTORS and bool(self.present[i])
            motors.append(MotorState_(
                mode=int(live), q=float(self.q[i]) if live else 0.0, dq=float(self.dq[i]) if live else 0.0,
                ddq=0.0, tau_est=float(self.tau[i]) if live else 0.0, temperature=[30, 30] if live else [0, 0],
                vol=48.0 if live else 0.0, sensor=[0, 0], motorstate=0, reserve=[0, 0, 0, 0],
            ))
        imu = IMUState_(quaternion=[1.0, 0.0, 0.0, 0.0], gyroscope=[0.0] * 3, accelerometer=[0.0, 0.0, 9.81],
                        rpy=[0.0] * 3, temperature=30)
        return LowState_(version=[1, 0], mode_pr=0, mode_machine=self.mode_machine, tick=self.tick & 0xFFFFFFFF,
                         imu_state=imu, motor_state=motors, wireless_remote=[0] * 40, reserve=[0] * 4, crc=0)

    def save(self, path: Path) -> None:
        """Every received frame (``t``, ``topic`` 0 arm_sdk / 1 lowcmd, ``crc_ok``, ``mode_pr``,
        ``mode_machine``, per-slot ``mode``/``q``/``dq``/``tau``/``kp``/``kd`` (N × 35)) and every
        published state (``state_t``, ``state_q`` (M × 29))."""
        frames = np.array([f for *_, f in self.frames], dtype=LOWCMD_DTYPE).reshape(-1)
        motors = frames["motor_cmd"]
        np.savez(
            path,
            t=np.array([t for t, *_ in self.frames]), topic=np.array([k for _, k, *_ in self.frames], int),
            crc_ok=np.array([ok for _, _, ok, _ in self.frames], bool), mode_pr=frames["mode_pr"],
            mode_machine=frames["mode_machine"], **{f: motors[f] for f in _RECORD_FIELDS},
            state_t=np.array([t for t, _ in self.states]),
            state_q=np.array([q for _, q in self.states]).reshape(-1, NUM_BODY_MOTORS),
        )

    def summary(self) -> dict[str, int]:
        return {"frames": len(self.frames), "arm_sdk": sum(k == 0 for _, k, *_ in self.frames),
                "lowcmd": sum(k == 1 for _, k, *_ in self.frames), "bad_crc": sum(not ok for _, _, ok, _ in self.frames),
                "states": self.tick}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m services.executor.g1.fake_robot", description=__doc__.split("\n\n")[0])
    parser.add_argument("--interface", default="lo", help="network interface for DDS (default: lo)")
    parser.add_argument("--domain", type=int, default=0, help="DDS domain id (default: 0, the robot's)")
    parser.add_argument("--mode-machine", type=int, default=5, help="LowState_.mode_machine: 5 = 29-DoF, 6 = waist locked")
    parser.add_argument("--rate", type=float, default=500.0, help="rt/lowstate rate (Hz)")
    parser.add_argument("--lag", type=float, default=0.03, help="motor time constant (s)")
    parser.add_argument("--record", type=Path, help="write every received frame and published state here (.npz)")
    parser.add_argument("--duration", type=float, help="stop after this many seconds")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    robot = FakeG1(DdsLink(args.domain, args.interface), args.mode_machine, args.rate, args.lag)
    signal.signal(signal.SIGUSR1, robot.toggle_state)
    with stop_on_signals() as stop:
        if args.duration:
            threading.Timer(args.duration, stop.set).start()
        print(json.dumps({"event": "ready", "mode_machine": args.mode_machine, "domain": args.domain}), flush=True)
        robot.run(stop)
    if args.record:
        robot.save(args.record)
    print(json.dumps({"event": "stopped", **robot.summary()}), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
