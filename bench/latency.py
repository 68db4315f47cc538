"""Benchmark: skeleton published → command published, end to end over loopback (architecture §8: p99 ≤ 5 ms).

Real processes, the command lines of :mod:`safemimic.stack`: ``executor``, ``safety`` and
``perception`` (the paper's two scenarios, 30 fps, in a loop), three times:

* ``router_tls``: every service a Zenoh client of ``safemimic router`` over mutual TLS, the router
  enforcing the access control generated from the service table (the deployed, secure topology;
  a throwaway CA from ``safemimic certs stack``; the probe has the ``viewer`` certificate);
* ``router``: the same over plain tcp without access control (``--insecure``);
* ``direct``: the same services as peers connected straight to the safety service (no router, open);
* ``router_tls_viewer``: ``router_tls`` with the live Rerun viewer (``safemimic viewer``, its own
  certificate, serving its web viewer) subscribed to every topic: ``viewer_cost_p99_ms`` and the
  safety loop's ``deadline_misses`` (from ``SafetyStatus``, over the sampled window) with and
  without it show whether watching changes the loop's deadlines (skipped without rerun-sdk).
  On a shared machine the background load drifts between two runs more than the viewer could
  matter, so ``router_tls`` and ``router_tls_viewer`` run in ``rounds`` alternating rounds of
  ``seconds / rounds`` each, their samples pooled: both see the same drift.

Each topology also reports ``cpu_cores``: the CPU time each process (router, services, viewer)
used over the sampled window, divided by its length (Linux ``/proc``; absent elsewhere).

``tls_cost_p50_ms`` / ``tls_cost_p99_ms`` are ``router_tls`` minus ``router``: what authentication,
encryption and the access-control checks add per skeleton.

For each skeleton, the first JointCommand computed from it (``human_stamp``/``human_seq`` name the
HumanState used) gives ``command.stamp − human.stamp``: from the skeleton's publication to the
control tick that published the command (both ``time.monotonic()`` on this host). It includes the
zero-order-hold wait for the next 2 ms tick (uniform on [0, 2) ms: ≈ 1 ms on average): the safety
service samples the newest human state at a fixed rate instead of reacting to each one. Also
reported: ``human_hop`` (HumanState publication → arrival at this probe, one more client of the
same router: the transport share) and ``received`` (→ the command's arrival here, one hop more).
"""

from __future__ import annotations

import os
import socket
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from safemimic.certs import make_stack
from safemimic.launch import Child, free_port, launch, stop_all
from safemimic.stack import (
    Site,
    client_flags,
    command,
    router_command,
    router_endpoint,
    viewer_command,
    write_paper_scenarios,
)
from shared.bus import Bus
from shared.config import BusConfig, TlsConfig, load_config
from shared.messages import HumanState, JointCommand, SafetyStatus

BUDGET_P99_MS = 5.0
SERVICES = ("executor", "safety", "perception")
STARTUP_TIMEOUT_S = 90.0
SETTLE_S = 2.0


class LatencyProbe:
    """Bus callbacks collecting the latency samples (ms)."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.recording = False
        self.published: list[float] = []
        self.received: list[float] = []
        self.human_hop: list[float] = []
        self.alive: set[str] = set()
        self._last_human_stamp: float | None = None
        self.misses: list[int] = []  # the safety loop's deadline_misses while recording

    def on_status(self, message: SafetyStatus) -> None:
        with self.lock:
            if self.recording:
                self.misses.append(message.deadline_misses)

    def on_human(self, message: HumanState) -> None:
        now = time.monotonic()
        with self.lock:
            if self.recording:
                self.human_hop.append((now - message.stamp) * 1e3)

    def on_command(self, message: JointCommand) -> None:
        now = time.monotonic()
        with self.lock:
            if message.human_stamp is None or message.human_stamp == self._last_human_stamp:
                return
            self._last_human_stamp = message.human_stamp
            if self.recording:
                self.published.append((message.stamp - message.human_stamp) * 1e3)
                self.received.append((now - message.human_stamp) * 1e3)

    def on_alive(self, service: str, up: bool) -> None:
        with self.lock:
            (self.alive.add if up else self.alive.discard)(service)


def _stats(samples: list[float]) -> dict[str, float]:
    values = np.asarray(samples)
    if not values.size:
        raise RuntimeError("no latency samples: did the services start?")
    return {"p50": float(np.percentile(values, 50)), "p90": float(np.percentile(values, 90)),
            "p99": float(np.percentile(values, 99)), "max": float(values.max()), "mean": float(values.mean()),
            "n": int(values.size)}


def _free_endpoint(secure: bool = False) -> str:
    return router_endpoint("127.0.0.1", free_port(), secure)


def measure(topology: str, seconds: float, run_dir: Path) -> dict[str, Any]:
    """Start the services in ``topology`` (``router_tls``, ``router``, ``direct`` or
    ``router_tls_viewer``), sample ``seconds``, stop them: :func:`summary` of one :class:`Window`."""
    return summary([record(topology, seconds, run_dir)])


def record(topology: str, seconds: float, run_dir: Path) -> Window:
    """One sampled window of ``topology`` (:func:`measure`), unsummarised."""
    secure = topology.startswith("router_tls")
    endpoint = _free_endpoint(secure)
    certs = run_dir / "certs"
    if secure:
        make_stack(certs, router_hosts=["127.0.0.1"])
    site = Site(router=endpoint, api_store=str(run_dir / "unused.json"), skeleton=str(run_dir / "paper-scenarios.npz"),
                certs=str(certs) if secure else None)
    children: list[Child] = []
    try:
        if topology in ("router", "router_tls", "router_tls_viewer"):
            children.append(launch(topology, router_command(endpoint, site.certs), run_dir))
            _wait_listening(endpoint, children[-1])  # a client that finds no router at start-up gives up
            flags = {name: client_flags(endpoint, site.certs) for name in SERVICES}
            tls = TlsConfig(dir=str(certs), identity="viewer") if secure else None
            probe_conf = BusConfig(mode="client", connect=[endpoint], multicast_scouting=False, tls=tls)
        else:  # a full mesh of peers: each listens and connects to the ones started before it
            endpoints = {name: _free_endpoint() for name in SERVICES}
            flags = {}
            for i, name in enumerate(SERVICES):
                connects = [arg for earlier in SERVICES[:i] for arg in ("--connect", endpoints[earlier])]
                flags[name] = ["--mode", "peer", "--no-multicast", "--insecure", "--listen", endpoints[name], *connects]
            probe_conf = BusConfig(mode="peer", connect=list(endpoints.values()), multicast_scouting=False)
        for name in SERVICES:
            children.append(launch(f"{topology}-{name}", command(name, site, flags[name]), run_dir))
        if topology == "router_tls_viewer":
            children.append(launch(f"{topology}-viewer", viewer_command(site, free_port(), free_port()), run_dir))
        return _sample(probe_conf, children, seconds)
    finally:
        stop_all(children)


class Window:
    """What one sampled window of a topology gave: the probe's samples, the safety loop's deadline
    misses over it (None: fewer than two statuses) and each process's CPU use (cores)."""

    def __init__(self, probe: LatencyProbe, cpu_cores: dict[str, float]) -> None:
        self.probe = probe
        self.misses = probe.misses[-1] - probe.misses[0] if len(probe.misses) > 1 else None
        self.cpu_cores = cpu_cores


def summary(windows: list[Window]) -> dict[str, Any]:
    """Latency statistics over the pooled samples of ``windows`` (rounds of one topology), the
    deadline misses summed, and the mean CPU use per process."""
    misses = [w.misses for w in windows]
    cpu: dict[str, list[float]] = {}
    for w in windows:
        for name, cores in w.cpu_cores.items():
            cpu.setdefault(name, []).append(cores)
    return {"published": _stats([x for w in windows for x in w.probe.published]),
            "received": _stats([x for w in windows for x in w.probe.received]),
            "human_hop": _stats([x for w in windows for x in w.probe.human_hop]),
            "deadline_misses": None if None in misses else sum(misses),  # type: ignore[arg-type]
            "cpu_cores": {name: round(float(np.mean(v)), 3) for name, v in cpu.items()},
            "rounds": len(windows)}


def _wait_listening(endpoint: str, child: Child) -> None:
    """Until ``endpoint`` (``tls/HOST:PORT``) accepts TCP connections; RuntimeError if ``child`` exits
    or :data:`STARTUP_TIMEOUT_S` passes."""
    host, port = endpoint.split("/", 1)[1].rsplit(":", 1)
    deadline = time.monotonic() + STARTUP_TIMEOUT_S
    while True:
        try:
            socket.create_connection((host, int(port)), timeout=1.0).close()
            return
        except OSError:
            if time.monotonic() > deadline or not child.running():
                raise RuntimeError(f"the router did not listen on {endpoint}:\n{child.log_tail()}") from None
            time.sleep(0.05)


def _cpu_seconds(pid: int) -> float | None:
    """User + system CPU time (s) of process ``pid`` so far (its threads included); None without /proc."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return None
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _role(child: Child) -> str:
    """``router``, ``safety``, ``viewer``, ...: a child's name after its topology."""
    return child.name.rsplit("-", 1)[1] if "-" in child.name else "router"


def _sample(conf: BusConfig, children: list[Child], seconds: float) -> Window:
    probe = LatencyProbe()
    bus = _open(conf, children)
    with bus:
        bus.subscribe("human/state", probe.on_human)
        bus.subscribe("robot/command", probe.on_command)
        bus.subscribe("safety/status", probe.on_status)
        bus.watch_alive(probe.on_alive)
        deadline = time.monotonic() + STARTUP_TIMEOUT_S
        while not set(SERVICES) <= probe.alive:
            if time.monotonic() > deadline or any(not child.running() for child in children):
                logs = "\n".join(f"--- {c.name}\n{c.log_tail()}" for c in children)
                raise RuntimeError(f"services did not come up (alive: {sorted(probe.alive)}):\n{logs}")
            time.sleep(0.1)
        time.sleep(SETTLE_S)
        cpu0 = {_role(c): _cpu_seconds(c.pid) for c in children}
        with probe.lock:
            probe.recording = True
        time.sleep(seconds)
        with probe.lock:
            probe.recording = False
        cpu1 = {_role(c): _cpu_seconds(c.pid) for c in children}
    cpu = {role: (cpu1[role] - start) / seconds for role, start in cpu0.items()
           if start is not None and cpu1[role] is not None}
    return Window(probe, cpu)


def _open(conf: BusConfig, children: list[Child]) -> Bus:
    """The probe's session, retried while the router or the listening peer starts."""
    deadline = time.monotonic() + STARTUP_TIMEOUT_S
    while True:
        try:
            return Bus(conf, load_config().robot_id, "latency_probe")
        except Exception:  # zenoh.ZError: nobody listening yet
            if time.monotonic() > deadline:
                raise
            time.sleep(0.1)


def run(seconds: float = 30.0, rounds: int = 3) -> dict[str, Any]:
    """Every topology for ``seconds``; ``router_tls`` and ``router_tls_viewer`` in ``rounds``
    alternating rounds (module docstring)."""
    import importlib.util

    with tempfile.TemporaryDirectory(prefix="safemimic-latency-") as tmp:
        run_dir = Path(tmp)
        write_paper_scenarios(run_dir / "paper-scenarios.npz")
        with_viewer = importlib.util.find_spec("rerun") is not None
        secure_rounds, viewed_rounds = [], []
        for _ in range(rounds if with_viewer else 1):
            secure_rounds.append(record("router_tls", seconds / rounds if with_viewer else seconds, run_dir))
            if with_viewer:
                viewed_rounds.append(record("router_tls_viewer", seconds / rounds, run_dir))
        secure = summary(secure_rounds)
        viewed = summary(viewed_rounds) if with_viewer else None
        routed = measure("router", seconds, run_dir)
        direct = measure("direct", seconds, run_dir)
    p50, p99 = routed["published"]["p50"], routed["published"]["p99"]
    tls_p50, tls_p99 = secure["published"]["p50"], secure["published"]["p99"]
    return {
        "name": "latency",
        "what": "skeleton published → command published (first command computed from each HumanState; "
                "includes the zero-order-hold wait for the next 2 ms safety tick), executor + safety + "
                "perception (30 fps) as processes on loopback",
        "unit": "ms",
        "p50": p50,
        "p99": p99,
        "p50_ms": p50,
        "p99_ms": p99,
        "direct_p50_ms": direct["published"]["p50"],
        "direct_p99_ms": direct["published"]["p99"],
        # the secure, deployed topology (mutual TLS + access control) and what it costs over plain tcp
        "tls_p50_ms": tls_p50,
        "tls_p99_ms": tls_p99,
        "tls_cost_p50_ms": tls_p50 - p50,
        "tls_cost_p99_ms": tls_p99 - p99,
        "tls_human_hop_p50_ms": secure["human_hop"]["p50"],
        "budget_p99": BUDGET_P99_MS,
        "within_budget": max(p99, tls_p99) <= BUDGET_P99_MS,
        # the same secure topology with the live Rerun viewer subscribed (None: rerun-sdk not installed)
        "viewer_p99_ms": viewed and viewed["published"]["p99"],
        "viewer_cost_p99_ms": viewed and viewed["published"]["p99"] - tls_p99,
        "deadline_misses": secure["deadline_misses"],
        "viewer_deadline_misses": viewed and viewed["deadline_misses"],
        "viewer_cpu_cores": viewed and viewed["cpu_cores"].get("viewer"),
        "router_tls_viewer": viewed,
        "router_tls": secure,
        "router": routed,
        "direct": direct,
        "seconds_per_topology": seconds,
        "zero_order_hold_note": "the safety loop samples the newest HumanState every 2 ms: a uniform wait of "
                                "0–2 ms (≈ 1 ms mean) before the tick that uses it",
    }
