"""``safemimic demo``: the whole simulated stack on this machine, and what it did.

Starts real processes on loopback with the command lines of :mod:`safemimic.stack` (the same
table docker compose is generated from): ``safemimic router`` (Zenoh's router), then
``executor`` (MuJoCo), ``safety`` (CBF-QP at 500 Hz), ``perception`` (the paper's two scenarios
back to back in a loop, or the recording named by ``$DEMO_SKELETON``) and ``config-api`` (REST
and the web console), all Zenoh clients of the router. Secure by default: a throwaway CA and one
certificate per identity are made in the run folder (``safemimic certs stack``), every session
connects over mutual TLS (``tls/127.0.0.1:PORT``) and the router enforces the access control
generated from the service table; ``--insecure`` runs today's open tcp bus instead, with a warning. This process watches the bus like any
other client: it prints the console URL, each service's health (its liveliness token), once a
second what the safety layer is doing, and at the end a one-screen summary (optionally as JSON).

It runs until ``--duration`` seconds have passed once every service is up, or until Ctrl-C /
SIGTERM; then it stops every child's process group (SIGTERM, then SIGKILL after a grace period).
Children also get SIGTERM from the kernel if this process dies abruptly, so none is orphaned.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import math
import os
import secrets
import sys
import tempfile
import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from safemimic.certs import make_stack
from safemimic.launch import Child, free_port, launch, stop_all
from safemimic.stack import (
    API_PORT,
    PAPER_SCENARIOS,
    SERVICES,
    Site,
    command,
    router_command,
    router_endpoint,
    viewer_command,
    write_paper_scenarios,
)
from services.config_api.token import TOKEN_ENV
from services.perception.placement import check_placement
from shared.bus import Bus
from shared.config import BusMode, TlsConfig, load_config
from shared.messages import HumanState, JointCommand, JointState, SafetyStatus
from shared.skeleton import RecordingError, read_recording
from shared.stop_signals import stop_on_signals

#: Environment variable naming a .npz recording to replay instead of the paper's scenarios.
SKELETON_ENV = "DEMO_SKELETON"
#: Every service must hold its liveliness token within this long after the start (s).
STARTUP_TIMEOUT_S = 90.0
#: Liveliness tokens the demo expects (the router is checked through this process's own session).
EXPECTED_TOKENS = tuple(spec.token for spec in SERVICES)


def _mm(value: float | None) -> str:
    return "—" if value is None or not math.isfinite(value) else f"{value * 1000:+.1f} mm"


@dataclass
class Watch:
    """What the demo observes on the bus (updated from Zenoh callbacks, read under ``lock``)."""

    lock: threading.Lock = field(default_factory=threading.Lock)
    commands: int = 0
    non_finite: int = 0
    dropped_commands: int = 0  # invalid commands the codec refused (e.g. non-finite values)
    joint_states: int = 0
    human_states: int = 0
    statuses: int = 0
    stale_statuses: int = 0
    modes: Counter = field(default_factory=Counter)
    latency_ms: list[float] = field(default_factory=list)
    status: SafetyStatus | None = None
    min_h_self: float = math.inf
    min_h_human: float = math.inf
    alive: dict[str, bool] = field(default_factory=dict)
    seen_alive: set[str] = field(default_factory=set)
    health_events: list[tuple[float, str, bool]] = field(default_factory=list)
    _published_closed: int = 0  # commands published in earlier runs of the safety service
    _seq_first: int | None = None
    _seq_last: int | None = None
    _last_human_stamp: float | None = None

    def on_command(self, message: JointCommand) -> None:
        with self.lock:
            self.commands += 1
            self.modes[message.mode.value] += 1
            if not (np.isfinite(message.q).all() and np.isfinite(message.dq).all()):
                self.non_finite += 1
            if self._seq_last is None or message.seq < self._seq_last:  # first command, or safety restarted
                self._published_closed += self._span()
                self._seq_first = message.seq
            self._seq_last = message.seq
            # the first command computed from each new skeleton: its tick's stamp minus the skeleton's
            # publication stamp (both monotonic on this host); later commands reuse it (zero-order hold)
            if message.human_stamp is not None and message.human_stamp != self._last_human_stamp:
                self._last_human_stamp = message.human_stamp
                self.latency_ms.append((message.stamp - message.human_stamp) * 1e3)

    def _span(self) -> int:
        return 0 if self._seq_first is None or self._seq_last is None else self._seq_last - self._seq_first + 1

    @property
    def commands_published(self) -> int:
        """Commands the safety service published while watched (from their sequence numbers)."""
        return self._published_closed + self._span()

    def on_joint_state(self, message: JointState) -> None:
        with self.lock:
            self.joint_states += 1

    def on_human(self, message: HumanState) -> None:
        with self.lock:
            self.human_states += 1

    def on_status(self, message: SafetyStatus) -> None:
        with self.lock:
            self.status = message
            self.statuses += 1
            self.stale_statuses += int(message.human_stale)
            if message.min_h_self is not None:
                self.min_h_self = min(self.min_h_self, message.min_h_self)
            if message.min_h_human is not None:
                self.min_h_human = min(self.min_h_human, message.min_h_human)

    def on_alive(self, service: str, up: bool) -> None:
        with self.lock:
            if self.alive.get(service) != up:
                self.health_events.append((time.monotonic(), service, up))
            self.alive[service] = up
            if up:
                self.seen_alive.add(service)

    def all_up(self) -> bool:
        """Every service holds its token and the safety loop runs (a SafetyStatus arrived)."""
        with self.lock:
            return self.status is not None and all(self.alive.get(token) for token in EXPECTED_TOKENS)

    def take_health_events(self) -> list[tuple[float, str, bool]]:
        with self.lock:
            events, self.health_events = self.health_events, []
            return events

    def health_column(self) -> str:
        with self.lock:
            down = [token for token in EXPECTED_TOKENS if not self.alive.get(token)]
        return "all up" if not down else "down: " + ",".join(down)


def build_parser(parser: argparse.ArgumentParser | None = None) -> argparse.ArgumentParser:
    parser = parser or argparse.ArgumentParser(prog="safemimic demo")
    parser.description = (
        "Run the Zenoh router, executor (MuJoCo), safety (CBF-QP, 500 Hz), perception and the config API "
        "as separate processes on loopback; print the console URL, each service's health, what the safety "
        f"layer does, and a summary. Perception loops the paper's scenarios ({', '.join(PAPER_SCENARIOS)}) "
        f"or replays ${SKELETON_ENV}=FILE.npz. Stop with Ctrl-C."
    )
    parser.add_argument("--duration", type=float, metavar="S", help="run S seconds once every service is up, then exit (default: until Ctrl-C)")
    parser.add_argument("--summary-json", type=Path, metavar="FILE", help="also write the summary as JSON")
    parser.add_argument("--viewer", action="store_true", help="open MuJoCo's viewer (needs a display)")
    parser.add_argument("--placement", default="side-by-side", metavar="WHERE",
                        help="where the person stands: side-by-side (default) | facing | recorded | x,y,yaw")
    parser.add_argument("--api-port", type=int, default=API_PORT, metavar="PORT", help=f"web console port (default {API_PORT}; 0: any free port)")
    parser.add_argument("--no-rerun", action="store_true",
                        help="do not start the live Rerun viewer (started by default when rerun-sdk is installed)")
    parser.add_argument("--insecure", action="store_true",
                        help="the open tcp bus: no TLS, no access control (anyone on this machine can command the robot)")
    return parser


def _skeleton(run_dir: Path) -> Path:
    """``$DEMO_SKELETON`` (checked), else the paper's scenarios written into ``run_dir``."""
    named = os.environ.get(SKELETON_ENV)
    if named:
        path = Path(named).expanduser().resolve()
        read_recording(path)  # RecordingError now, not a perception crash later
        return path
    return write_paper_scenarios(run_dir / "paper-scenarios.npz")


def _wait_for_log(child: Child, marker: str, stop: threading.Event, timeout_s: float = 60.0) -> str | None:
    """The first line of ``child``'s log containing ``marker`` (None if it exits, the demo stops or time runs out)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and child.running() and not stop.is_set():
        for line in child.log_tail(1_000_000).splitlines():
            if marker in line:
                return line
        stop.wait(0.05)
    return None


def run(args: argparse.Namespace) -> int:
    if args.duration is not None and not args.duration > 0:
        print("safemimic demo: --duration must be > 0", file=sys.stderr)
        return 2
    try:
        check_placement(args.placement, "--placement")
    except ValueError as exc:
        print(f"safemimic demo: {exc}", file=sys.stderr)
        return 2
    run_dir = Path(tempfile.mkdtemp(prefix="safemimic-demo-"))
    try:
        skeleton = _skeleton(run_dir)
    except RecordingError as exc:
        print(f"safemimic demo: ${SKELETON_ENV}: {exc}", file=sys.stderr)
        return 2
    token = os.environ.get(TOKEN_ENV) or secrets.token_urlsafe(24)
    endpoint = router_endpoint("127.0.0.1", free_port(), secure=not args.insecure)
    certs = None if args.insecure else run_dir / "certs"
    if certs is not None:
        make_stack(certs, router_hosts=["127.0.0.1"])  # a throwaway CA: this run's sessions only
    api_port = args.api_port or free_port()
    site = Site(router=endpoint, api_store=str(run_dir / "config.json"), skeleton=str(skeleton),
                placement=args.placement, api_port=api_port, viewer=args.viewer,
                certs=None if certs is None else str(certs))
    print(f"router: {endpoint}", flush=True)
    if certs is not None:
        print(f"certs: {certs}  (mutual TLS; the router's access control: {certs / 'access_control.json5'})", flush=True)
    else:
        print("WARNING: --insecure: open tcp bus, no TLS, no access control: anyone on this machine can command "
              "the robot and switch its safety layer off", flush=True)
    print(f"person: {'the paper scenarios ' + ' + '.join(PAPER_SCENARIOS) if SKELETON_ENV not in os.environ else skeleton}"
          f" ({args.placement}), looping; logs in {run_dir}", flush=True)
    if args.viewer and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        print("--viewer: no display here, the executor will run headless (see its log)", flush=True)
    children: list[Child] = []
    watch = Watch()
    with stop_on_signals() as stop:
        try:
            children.append(_start("router", router_command(endpoint, site.certs), run_dir))
            if not _wait_for_log(children[0], "listening", stop):
                print(f"the router did not start:\n{children[0].log_tail()}", flush=True)
                return 1
            for spec in SERVICES:
                children.append(_start(spec.name, command(spec.name, site), run_dir, {TOKEN_ENV: token}))
            if _rerun_wanted(args):
                children.append(_start("viewer", viewer_command(site, free_port(), free_port()), run_dir))
            elapsed = _watch_stack(args, site, children, watch, stop, token)
        finally:  # the services first, then the router they are connected through
            exit_codes = {**stop_all(children[1:]), **stop_all(children[:1])}
    summary = _summary(watch, exit_codes, elapsed, site, run_dir)
    if args.summary_json:
        args.summary_json.write_text(json.dumps(summary, indent=2) + "\n")
        print(f"  summary written to {args.summary_json}")
    return 0 if summary["ok"] else 1


def _rerun_wanted(args: argparse.Namespace) -> bool:
    """The live viewer runs unless --no-rerun, where rerun-sdk is installed (the viz extra)."""
    if args.no_rerun:
        return False
    if importlib.util.find_spec("rerun") is None:
        print("viewer: not started (rerun-sdk missing: pip install 'safemimic[viz]')", flush=True)
        return False
    return True


def _start(name: str, argv: list[str], run_dir: Path, env: dict[str, str] | None = None) -> Child:
    child = launch(name, argv, run_dir, env)
    print(f"$ {' '.join(argv)}    (pid {child.pid})", flush=True)
    return child


def _watch_stack(args: argparse.Namespace, site: Site, children: list[Child], watch: Watch,
                 stop: threading.Event, token: str) -> float:
    """Watch the bus until the duration is over, Ctrl-C or a child exits; the seconds watched."""
    conf = load_config()  # the services' robot id (file or $SAFEMIMIC__ROBOT_ID), this session a client too
    tls = None if site.certs is None else TlsConfig(dir=site.certs)  # this session: the demo identity
    bus_conf = conf.bus.model_copy(update={"mode": BusMode.CLIENT, "connect": [site.router], "listen": [],
                                          "multicast_scouting": False, "tls": tls})
    by_name = {child.name: child for child in children}
    with Bus(bus_conf, conf.robot_id, "demo") as bus:
        bus.subscribe("robot/command", watch.on_command)
        bus.subscribe("robot/joint_state", watch.on_joint_state)
        bus.subscribe("human/state", watch.on_human)
        bus.subscribe("safety/status", watch.on_status)
        bus.watch_alive(watch.on_alive)
        ready = _wait_for_log(by_name["config-api"], '{"event": "ready"', stop)
        if ready:
            url = json.loads(ready)["url"]
            origin = f"${TOKEN_ENV}" if os.environ.get(TOKEN_ENV) else token
            print(f"\nconsole: {url}/   (writes: Authorization: Bearer {origin})", flush=True)
        if "viewer" in by_name:
            shown = _wait_for_log(by_name["viewer"], '{"event": "ready"', stop)
            if shown:
                print(f"viewer: {json.loads(shown)['url']}   (Rerun web viewer: robot, person, barriers)", flush=True)
        deadline = time.monotonic() + STARTUP_TIMEOUT_S
        while not watch.all_up() and time.monotonic() < deadline and not stop.is_set() and not _exited(children):
            _print_health(watch)
            stop.wait(0.2)
        _print_health(watch)
        if not watch.all_up():
            print(f"not every service came up: {watch.health_column()}", flush=True)
            return 0.0
        print("health (liveliness): router up (this session is connected through it), "
              + ", ".join(f"{token} up" for token in EXPECTED_TOKENS), flush=True)
        print(f"\n{'t (s)':>6} {'mode':>9} {'min h self':>11} {'min h human':>12} {'active':>7} {'step ms':>8} "
              f"{'cmds/s':>7} {'lat p99':>8}  health", flush=True)
        with watch.lock:
            watch.latency_ms.clear()  # measured in steady state, not while the processes start
        start, last_commands = time.monotonic(), 0
        end = math.inf if args.duration is None else start + args.duration
        while not stop.is_set() and time.monotonic() < end and not _exited(children):
            stop.wait(max(0.0, min(1.0, end - time.monotonic())))
            _print_health(watch, start)
            with watch.lock:
                status, commands = watch.status, watch.commands
                lat = f"{np.percentile(watch.latency_ms, 99):6.2f}ms" if watch.latency_ms else "—"
            if status is not None:
                print(f"{time.monotonic() - start:6.1f} {status.mode.value:>9} {_mm(status.min_h_self):>11} "
                      f"{_mm(status.min_h_human):>12} {status.active_constraints:>3}/{status.total_constraints:<3} "
                      f"{status.step_time_ms:8.3f} {commands - last_commands:7d} {lat:>8}  "
                      f"{watch.health_column()}{_watchdog_column(status)}", flush=True)
            last_commands = commands
        if stop.is_set():
            print("\nstopping (Ctrl-C) ...", flush=True)
        with watch.lock:
            watch.dropped_commands = bus.dropped["robot/command"]
        return time.monotonic() - start


def _exited(children: list[Child]) -> bool:
    exited = [child for child in children if not child.running()]
    for child in exited:
        print(f"\n{child.name} exited with {child.popen.returncode}; its log ends:\n{child.log_tail()}", flush=True)
    return bool(exited)


def _watchdog_column(status: SafetyStatus) -> str:
    """The safety service's tripped watchdogs and what its stop does, e.g. "  human stale, backing
    out, camera 80 ms late" ('' when none)."""
    flags = {"human stale": status.human_stale, "perception lost": status.human_source_lost,
             "person lost (held)": status.human_lost,
             "joint state stale": status.joint_state_stale, "executor holding": status.executor_holding,
             "resyncing": status.resyncing, "person intrusion": status.person_intrusion,
             "backing out": status.backing_out}
    tripped = [name for name, on in flags.items() if on]
    if status.human_lateness_ms >= 1.0:
        tripped.append(f"camera {status.human_lateness_ms:.0f} ms late")
    if status.relaxed_pairs:
        tripped.append(f"gave way: {', '.join(status.relaxed_pairs[:3])}{' …' if len(status.relaxed_pairs) > 3 else ''}")
    return f"  {', '.join(tripped)}" if tripped else ""


def _print_health(watch: Watch, start: float | None = None) -> None:
    for when, service, up in watch.take_health_events():
        at = f"{when - start:6.1f} s" if start is not None else "startup"
        print(f"  [{at}] {service}: {'up' if up else 'DOWN (liveliness token gone)'}", flush=True)


def _summary(watch: Watch, exit_codes: dict[str, int], elapsed: float, site: Site, run_dir: Path) -> dict[str, Any]:
    """Print the one-screen summary and return it as a JSON-ready dict."""
    with watch.lock:
        lat = np.array(watch.latency_ms)
        nan_count = watch.non_finite + watch.dropped_commands
        failed = {name: code for name, code in exit_codes.items() if code not in (0, -15)}
        summary: dict[str, Any] = {
            "duration_s": round(elapsed, 3),
            "commands_published": watch.commands_published,
            "commands_received": watch.commands,
            "joint_states": watch.joint_states,
            "human_states": watch.human_states,
            "statuses": watch.statuses,
            "stale_statuses": watch.stale_statuses,
            "min_h_self": watch.min_h_self if math.isfinite(watch.min_h_self) else None,
            "min_h_human": watch.min_h_human if math.isfinite(watch.min_h_human) else None,
            "modes": dict(watch.modes),
            "latency_ms_p50": float(np.percentile(lat, 50)) if lat.size else None,
            "latency_ms_p99": float(np.percentile(lat, 99)) if lat.size else None,
            "latency_samples": int(lat.size),
            "nan_count": nan_count,
            "services_seen_alive": sorted(watch.seen_alive),
            "exit_codes": exit_codes,
            "console_port": site.api_port,
            "logs": str(run_dir),
        }
    ok = (watch.commands > 0 and watch.joint_states > 0 and nan_count == 0 and not failed
          and set(EXPECTED_TOKENS) <= watch.seen_alive and elapsed > 0)
    summary["ok"] = ok
    print("\nsummary")
    print(f"  ran {elapsed:.1f} s; services seen alive: {', '.join(summary['services_seen_alive']) or 'none'}")
    print(f"  JointCommands published {summary['commands_published']} (received here {watch.commands}), "
          f"JointStates {watch.joint_states}, HumanStates {watch.human_states}, SafetyStatus {watch.statuses}")
    print(f"  modes: {', '.join(f'{mode} {count}' for mode, count in watch.modes.most_common()) or 'none'}")
    print(f"  lowest min h reported: self {_mm(summary['min_h_self'])}, robot–human {_mm(summary['min_h_human'])}")
    if lat.size:
        print(f"  skeleton published → command published: p50 {summary['latency_ms_p50']:.2f} ms, p99 "
              f"{summary['latency_ms_p99']:.2f} ms over {lat.size} skeletons (includes waiting for the next 2 ms tick)")
    for name, code in failed.items():
        print(f"  {name} exited with {code}")
    print(f"  non-finite commands: {nan_count}; logs: {run_dir}")
    print(f"  result: {'OK' if ok else 'FAILED'}", flush=True)
    return summary
