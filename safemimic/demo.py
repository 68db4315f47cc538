"""``safemimic demo``: the whole simulated stack on this machine, and what it did.

Starts real processes on loopback, exactly the command lines a user would type on several
hosts: ``safemimic router``, ``safemimic executor`` (MuJoCo), ``safemimic safety`` (CBF-QP at
500 Hz) and ``safemimic perception`` (a scripted person, by default the paper's
side-by-side arm raise), all as Zenoh clients of the router. This process watches the bus like
any other client and prints, once a second, what the safety layer is doing; at the end a summary
with the measured skeleton → command latency.
"""

from __future__ import annotations

import argparse
import socket
import subprocess
import sys
import threading
import time
from collections import Counter
from dataclasses import dataclass, field

import numpy as np

from shared.bus import Bus
from shared.config import BusConfig
from shared.messages import JointCommand, JointState, SafetyStatus

SCENARIOS = ("side-by-side-arm-raise", "cross-arm-reach", "wave", "reach-forward", "neutral")


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


@dataclass
class Watch:
    """What the demo observes on the bus (updated from Zenoh callbacks)."""

    lock: threading.Lock = field(default_factory=threading.Lock)
    commands: int = 0
    states: int = 0
    latency_ms: list[float] = field(default_factory=list)
    modes: Counter = field(default_factory=Counter)
    status: SafetyStatus | None = None
    min_h_self: float = float("inf")
    min_h_human: float = float("inf")
    non_finite: int = 0
    alive: dict[str, bool] = field(default_factory=dict)
    seen_alive: set[str] = field(default_factory=set)
    last_human_seq: int | None = None

    def on_command(self, message: JointCommand) -> None:
        now = time.monotonic()
        with self.lock:
            self.commands += 1
            self.modes[message.mode.value] += 1
            if not (np.isfinite(message.q).all() and np.isfinite(message.dq).all()):
                self.non_finite += 1
            # latency of the first command computed from each new skeleton (later ones reuse it: ZOH)
            if message.human_stamp is not None and message.human_seq != self.last_human_seq:
                self.last_human_seq = message.human_seq
                self.latency_ms.append((now - message.human_stamp) * 1e3)

    def on_state(self, message: JointState) -> None:
        with self.lock:
            self.states += 1

    def on_status(self, message: SafetyStatus) -> None:
        with self.lock:
            self.status = message
            if message.min_h_self is not None:
                self.min_h_self = min(self.min_h_self, message.min_h_self)
            if message.min_h_human is not None:
                self.min_h_human = min(self.min_h_human, message.min_h_human)

    def on_alive(self, service: str, up: bool) -> None:
        with self.lock:
            self.alive[service] = up
            if up:
                self.seen_alive.add(service)


def build_parser(parser: argparse.ArgumentParser | None = None) -> argparse.ArgumentParser:
    parser = parser or argparse.ArgumentParser(prog="safemimic demo")
    parser.description = (
        "Run router + executor (MuJoCo) + safety (CBF-QP, 500 Hz) + perception (a scripted person) as "
        "separate processes on loopback and print what the safety layer does."
    )
    parser.add_argument("--scenario", choices=SCENARIOS, default="side-by-side-arm-raise", help="scripted person (default: the paper's side-by-side arm raise)")
    parser.add_argument("--seconds", type=float, default=12.0, help="how long the person moves (default 12)")
    parser.add_argument("--viewer", action="store_true", help="open MuJoCo's viewer (needs a display)")
    return parser


def _start(name: str, args: list[str], endpoint: str, duration: float) -> subprocess.Popen:
    command = [sys.executable, "-m", "safemimic.cli", name, "--mode", "client", "--connect", endpoint,
               "--no-multicast", "--duration", f"{duration:.1f}", *args]
    print(f"$ safemimic {' '.join(command[3:])}", flush=True)
    return subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)


def run(args: argparse.Namespace) -> int:
    endpoint = f"tcp/127.0.0.1:{_free_port()}"
    print(f"$ safemimic router --listen {endpoint} --no-multicast", flush=True)
    router = subprocess.Popen([sys.executable, "-m", "safemimic.cli", "router", "--listen", endpoint, "--no-multicast"],
                              stdout=subprocess.PIPE, text=True)
    procs: dict[str, subprocess.Popen] = {}
    watch = Watch()
    try:
        assert router.stdout is not None
        print("  " + router.stdout.readline().strip())
        client = BusConfig(mode="client", connect=[endpoint], multicast_scouting=False)
        with Bus(client, "g1", "demo") as bus:
            bus.subscribe("robot/command", watch.on_command)
            bus.subscribe("robot/joint_state", watch.on_state)
            bus.subscribe("safety/status", watch.on_status)
            bus.watch_alive(watch.on_alive)
            total = args.seconds + 6.0  # services start before the person and outlive them
            procs["executor"] = _start("executor", ["--viewer"] if args.viewer else [], endpoint, total)
            procs["safety"] = _start("safety", [], endpoint, total)
            time.sleep(2.5)  # let the safety service warm up (compiled kernels) and sync to the robot
            procs["perception"] = _start("perception", ["--scenario", args.scenario, "--loop"], endpoint, args.seconds)
            print(f"\n{'t (s)':>6} {'mode':>9} {'min h self':>11} {'min h human':>12} {'active':>7} {'step ms':>8} {'cmds/s':>7}")
            start, last_commands = time.monotonic(), 0
            while time.monotonic() - start < args.seconds + 1.0:
                time.sleep(1.0)
                with watch.lock:
                    s, commands = watch.status, watch.commands
                if s is not None:
                    fmt = lambda v: "—" if v is None else f"{v * 1000:+.1f} mm"  # noqa: E731
                    print(f"{time.monotonic() - start:6.1f} {s.mode.value:>9} {fmt(s.min_h_self):>11} {fmt(s.min_h_human):>12} "
                          f"{s.active_constraints:>3}/{s.total_constraints:<3} {s.step_time_ms:8.3f} {commands - last_commands:7d}", flush=True)
                last_commands = commands
        return _summary(watch, procs)
    finally:
        for proc in [*procs.values(), router]:
            if proc.poll() is None:
                proc.terminate()
        for proc in [*procs.values(), router]:
            try:
                proc.wait(10)
            except subprocess.TimeoutExpired:
                proc.kill()


def _summary(watch: Watch, procs: dict[str, subprocess.Popen]) -> int:
    lat = np.array(watch.latency_ms)
    print("\nsummary")
    print(f"  services seen alive: {', '.join(sorted(watch.seen_alive)) or 'none'}")
    print(f"  JointCommands received: {watch.commands} ({dict(watch.modes)}), JointStates: {watch.states}")
    print(f"  lowest min h reported: self {watch.min_h_self * 1000:+.1f} mm, robot–human {watch.min_h_human * 1000:+.1f} mm")
    if lat.size:
        print(f"  skeleton published → command received here: p50 {np.percentile(lat, 50):.2f} ms, "
              f"p99 {np.percentile(lat, 99):.2f} ms (first command from each new skeleton; includes waiting for the next 2 ms control tick)")
    failed = [name for name, proc in procs.items() if proc.poll() not in (0, None)]
    for name in failed:
        err = procs[name].stderr.read() if procs[name].stderr else ""
        print(f"  {name} exited with {procs[name].returncode}:\n{err[-2000:]}")
    ok = watch.commands > 0 and watch.states > 0 and watch.non_finite == 0 and not failed
    print(f"  result: {'OK' if ok else 'FAILED'}{'' if watch.non_finite == 0 else f', {watch.non_finite} non-finite commands'}")
    return 0 if ok else 1
