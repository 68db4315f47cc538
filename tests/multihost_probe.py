"""A bus observer for the multi-host test, run as its own process on one of the test's hosts.

Prints JSON lines with ``time.monotonic()`` stamps (one clock for every network namespace of the
machine): ``ready``; ``alive`` on each liveliness change; ``status`` for each SafetyStatus, with the
commands and joint states received so far, the ``human_seq`` of the newest command and how many
commands were non-finite.
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
import time

import numpy as np

from shared.bus import Bus
from shared.cli_args import add_bus_arguments, config_from_args
from shared.messages import JointCommand, JointState, SafetyStatus


def main() -> None:
    parser = argparse.ArgumentParser()
    add_bus_arguments(parser)
    conf = config_from_args(parser.parse_args())
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    lock = threading.Lock()
    commands = {"count": 0, "nonfinite": 0, "human_seq": None, "joint_states": 0}

    def emit(event: str, **fields: object) -> None:
        with lock:
            print(json.dumps({"event": event, "t": time.monotonic(), **fields}), flush=True)

    def on_command(message: JointCommand) -> None:
        with lock:
            commands["count"] += 1
            commands["nonfinite"] += int(not (np.isfinite(message.q).all() and np.isfinite(message.dq).all()))
            commands["human_seq"] = message.human_seq

    def on_joint_state(message: JointState) -> None:
        with lock:
            commands["joint_states"] += 1

    def on_status(message: SafetyStatus) -> None:
        with lock:
            counts = dict(commands)
        emit("status", mode=message.mode.value, human_stale=message.human_stale, min_h_self=message.min_h_self,
             min_h_human=message.min_h_human, commands=counts["count"], nonfinite=counts["nonfinite"],
             human_seq=counts["human_seq"], joint_states=counts["joint_states"])

    with Bus(conf.bus, conf.robot_id, "probe") as bus:
        bus.subscribe("robot/command", on_command)
        bus.subscribe("robot/joint_state", on_joint_state)
        bus.subscribe("safety/status", on_status)
        bus.watch_alive(lambda service, up: emit("alive", service=service, up=up))
        emit("ready")
        while not stop.wait(0.2):  # timed: SIGTERM may land on a zenoh thread (see services/router/main.py)
            pass


if __name__ == "__main__":
    sys.exit(main())
