"""``safemimic demo``: run what exists end to end on this machine and print what happened.

Today: a real ``safemimic router`` process on loopback, a publisher and a subscriber session
connected through it as clients, HumanState messages at 30 Hz for a few seconds, liveliness
of the publisher, and the measured one-way latency. Later issues extend it to the full stack.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import threading
import time

import numpy as np

from bench.codec import human_state
from shared.bus import Bus
from shared.config import BusConfig
from shared.messages import Message


def _free_port() -> int:
    import socket

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def build_parser(parser: argparse.ArgumentParser | None = None) -> argparse.ArgumentParser:
    parser = parser or argparse.ArgumentParser(prog="safemimic demo")
    parser.description = "Run the stack end to end on loopback and print what happens."
    parser.add_argument("--seconds", type=float, default=3.0, help="how long to stream (default 3)")
    return parser


def run(args: argparse.Namespace) -> int:
    endpoint = f"tcp/127.0.0.1:{_free_port()}"
    router = subprocess.Popen(
        [sys.executable, "-m", "safemimic.cli", "router", "--listen", endpoint, "--no-multicast"],
        stdout=subprocess.PIPE, text=True,
    )
    try:
        assert router.stdout is not None
        print(router.stdout.readline().strip())
        client = BusConfig(mode="client", connect=[endpoint], multicast_scouting=False)
        latencies: list[float] = []
        alive: list[str] = []
        done = threading.Event()

        def on_state(message: Message) -> None:
            latencies.append(time.monotonic() - message.stamp)

        with Bus(client, "demo", "viewer") as viewer, Bus(client, "demo", "perception") as perception:
            viewer.subscribe("human/state", on_state)
            viewer.watch_alive(lambda service, up: alive.append(f"{service} {'up' if up else 'down'}"))
            perception.declare_alive()
            publisher = perception.publisher("human/state")
            time.sleep(0.5)
            message = human_state()
            end = time.monotonic() + args.seconds
            sent = 0
            while time.monotonic() < end and not done.is_set():
                message.stamp = time.monotonic()
                publisher.put(message)
                sent += 1
                time.sleep(1 / 30)
            time.sleep(0.2)
        lat_ms = np.array(latencies) * 1e3
        print(f"liveliness seen by the viewer: {', '.join(alive) or 'none'}")
        print(f"HumanState: sent {sent}, received {len(lat_ms)} through the router "
              f"(dropped as invalid: {viewer.dropped.total()})")
        if len(lat_ms):
            print(f"one-way latency through the router: p50 {np.percentile(lat_ms, 50):.3f} ms, "
                  f"p99 {np.percentile(lat_ms, 99):.3f} ms")
        return 0 if len(lat_ms) >= 0.9 * sent else 1
    finally:
        router.terminate()
        router.wait(5)
