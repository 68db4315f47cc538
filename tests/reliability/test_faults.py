"""Faults: kill -9 each service, the Zenoh router, and the config API mid-write (a test per check;
the stack's checks share one run of the stack).

Stack checks run the simulated stack the way ``safemimic demo`` does (:mod:`safemimic.stack`'s
command lines, :mod:`safemimic.launch`'s children: router, executor, safety, perception looping
the paper's scenarios, config API, all Zenoh clients of the router on loopback, over mutual TLS
with the router's access control, certificates from a throwaway CA) while this process records
the bus as one more client (the ``viewer`` certificate: it can only look):

- ``kill9_<service>``: SIGKILL the service's process group, leave it down :data:`OUTAGE_S` (the
  others' processes must live on and their topics keep flowing; with perception down the safety
  service must report the human stale), restart it with the same command line and measure until
  it is back — its liveliness token reappears *and* its data flows (commands for safety, joint
  states for the executor, human states for perception, HTTP 200 for the config API); the
  budget: at most :data:`RESUME_BOUND_S` after the restart command (the start-up's CPU time is
  reported beside it: on a slow or busy machine that is what the budget measures). While the
  config API is killed, PATCH requests hammer it; the restarted API must load its store at a
  version ≥ the last acknowledged.
- ``router_restart``: SIGKILL the router, restart it on the same port; every service's token and
  data (commands, joint states, human states) return (budget: within :data:`ROUTER_RESUME_BOUND_S`);
  no service process died.
- ``command_limits``: over the whole run every recorded JointCommand is finite and moves each
  joint by at most u_max·Δt per control step (``safety.u_max`` / ``u_min``, Δt = 1/``safety.rate_hz``;
  a gap of n sequence numbers allows n steps, a command that says it was ``settled`` onto the
  measured robot one more), also across the safety service's own restart (its first command
  against its predecessor's last, counted as one step).

``config_write_kill`` needs no stack: a process forked from a preloaded fork server commits
versions of the configuration through the config API's own store code
(:meth:`~services.config_api.store.ConfigStore.commit`) as fast as it can and is SIGKILLed at a
random moment; the store file must then load and validate and equal the last acknowledged
version or the one in flight (never anything else), and the next open must leave no temporary file.
"""

from __future__ import annotations

import multiprocessing
import os
import random
import secrets
import shutil
import signal
import socket
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest

from safemimic.certs import make_stack
from safemimic.launch import Child, free_port, kill, launch, stop_all
from safemimic.stack import SERVICE_BY_NAME, SERVICES, Site, command, router_command, write_paper_scenarios
from services.config_api.store import ConfigStore, stale_temporaries
from services.config_api.token import TOKEN_ENV
from shared.bus import Bus
from shared.config import BusMode, StackConfig, TlsConfig, load_config
from shared.messages import JointCommand, Message
from tests.reliability.check import Check, CheckResult
from tests.support.bus import BusRecorder

#: A restarted service must be back (token and data) this long after its restart command (s).
RESUME_BOUND_S = 2.0
#: After a router restart every service must be back this long after the restart command (s).
ROUTER_RESUME_BOUND_S = 5.0
#: How long a killed service or router stays down before its restart (s): longer than the Zenoh
#: lease (0.5 s), so its token is seen gone and the others run without it for a while.
OUTAGE_S = 1.0
#: During an outage, a surviving service's topic counts as flowing if no gap exceeds this (s).
FLOW_GAP_S = 0.5
#: Give up waiting for a restarted service (or the first start of the stack) after this long (s).
GIVE_UP_S = 20.0
#: Every service must be up this long after the stack's first start (s; as ``safemimic demo``).
STARTUP_TIMEOUT_S = 90.0
#: Relative and absolute tolerance of the rate limit |Δq| ≤ u_max·Δt (float rounding).
RATE_RTOL, RATE_ATOL = 1e-6, 1e-9
#: What shows that each service is back: its topic (seen by the recorder), or None: HTTP 200.
DATA_TOPIC: dict[str, str | None] = {
    "executor": "robot/joint_state", "safety": "robot/command", "perception": "human/state", "config-api": None,
}
#: The topics the recorder watches (what every running service produces).
WATCHED_TOPICS = ("robot/command", "robot/joint_state", "human/state", "safety/status")
#: Random delay after the writer's first acknowledged commit before SIGKILL (s).
WRITE_KILL_DELAY_S = (0.0, 0.05)
#: The two values of safety.gamma the writers alternate between (version parity picks one).
GAMMAS = (10.0, 12.5)
#: Rate-limit violations described in the report (the count covers all).
_VIOLATIONS_KEPT = 10


def _gamma(version: int) -> float:
    return GAMMAS[version % 2]


# --------------------------------------------------------------------------------------------
# the recorder: this process's own Zenoh client of the router


@dataclass
class _CommandLimits:
    """Finiteness and the rate limit of the command stream, checked as commands arrive."""

    step_hi: np.ndarray  # u_max·Δt per joint (> 0)
    step_lo: np.ndarray  # u_min·Δt per joint (< 0)
    commands: int = 0
    non_finite: int = 0
    violations: int = 0
    max_ratio: float = 0.0
    restarts: list[tuple[float, float]] = field(default_factory=list)  # (time, |Δq| ratio) at each safety restart
    ratios: list[tuple[float, float]] = field(default_factory=list)  # (time, ratio) of every step
    worst: list[dict[str, Any]] = field(default_factory=list)  # the first violations: time, seq, steps, ratio
    _last: tuple[int, np.ndarray] | None = None

    def add(self, t: float, message: JointCommand) -> None:
        self.commands += 1
        q = np.asarray(message.q, dtype=np.float64)
        if not (np.isfinite(q).all() and np.isfinite(message.dq).all()):
            self.non_finite += 1
            return
        if self._last is not None:
            last_seq, last_q = self._last
            restarted = message.seq <= last_seq  # a new safety process numbers from 0 again
            steps = (1 if restarted else message.seq - last_seq) + message.settled  # a settle: one step more
            ratio = self.ratio(q - last_q, steps)
            self.ratios.append((t, ratio))
            self.max_ratio = max(self.max_ratio, ratio)
            if ratio > self.threshold:
                self.violations += 1
                if len(self.worst) < _VIOLATIONS_KEPT:
                    self.worst.append({"t": t, "seq": message.seq, "steps": steps, "ratio": round(ratio, 3),
                                       "safety_restart": restarted})
            if restarted:
                self.restarts.append((t, ratio))
        self._last = (message.seq, q)

    @property
    def threshold(self) -> float:
        """The largest ratio still within the limit: 1 + RATE_RTOL, plus RATE_ATOL on the smallest step."""
        return 1.0 + RATE_RTOL + RATE_ATOL / float(min(self.step_hi.min(), -self.step_lo.max()))

    def ratio(self, dq: np.ndarray, steps: int) -> float:
        """max over joints of Δq / (steps · bound), the bound on Δq's side (1.0: at the limit)."""
        return max(0.0, float(np.max(np.maximum(dq / (steps * self.step_hi), dq / (steps * self.step_lo)))))

    def between(self, t0: float, t1: float) -> dict[str, Any]:
        """The largest ratio and the violations among the commands that arrived in [t0, t1]."""
        ratios = [ratio for t, ratio in self.ratios if t0 <= t <= t1]
        return {"max_rate_ratio": round(max(ratios, default=0.0), 4),
                "rate_violations": sum(ratio > self.threshold for ratio in ratios)}


class Recorder(BusRecorder):
    """This process's own client of the router (the viewer's certificate: it can only look): every
    command, joint state, human state, status and liveliness change on the bus, timed, and the
    command stream's limits followed as it comes."""

    def __init__(self, conf: StackConfig, router: str, certs: Path) -> None:
        safety = conf.safety
        dt = 1.0 / safety.rate_hz
        u_max = np.asarray(safety.u_max, dtype=np.float64)
        u_min = -u_max if safety.u_min is None else np.asarray(safety.u_min, dtype=np.float64)
        self.limits = _CommandLimits(step_hi=u_max * dt, step_lo=u_min * dt)
        bus_conf = conf.bus.model_copy(update={"mode": BusMode.CLIENT, "connect": [router], "listen": [],
                                              "multicast_scouting": False,
                                              "tls": TlsConfig(dir=str(certs), identity="viewer")})
        super().__init__(Bus(bus_conf, conf.robot_id, "faults"), WATCHED_TOPICS, alive=True, on_message=self._follow)

    def close(self) -> None:
        self.bus.close()

    def _follow(self, topic: str, now: float, message: Message) -> None:
        if isinstance(message, JointCommand):
            self.limits.add(now, message)

    def stale_between(self, t0: float, t1: float) -> bool:
        """Whether a status arrived in (t0, t1) showing the human state stale."""
        at = self.first_after("safety/status", t0, lambda status: status.human_stale)
        return at is not None and at < t1

    def invalid_commands(self) -> int:
        """Command payloads that failed to decode or validate (e.g. a NaN the codec refused); the
        bus's drop count less the valid messages it refused as replayed or out of order."""
        return int(self.bus.dropped["robot/command"] - self.bus.out_of_order["robot/command"])


# --------------------------------------------------------------------------------------------
# the stack


def _wait_until(predicate: Callable[[], bool], timeout_s: float, poll_s: float = 0.01) -> float | None:
    """The monotonic time ``predicate`` first held (polled), None if not within ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while True:
        if predicate():
            return time.monotonic()
        if time.monotonic() > deadline:
            return None
        time.sleep(poll_s)


def _port_open(port: int) -> bool:
    with socket.socket() as sock:
        sock.settimeout(0.2)
        return sock.connect_ex(("127.0.0.1", port)) == 0


def _cpu_seconds(pid: int) -> float | None:
    """CPU time (user + system, s) process ``pid`` has used so far (Linux ``/proc``; None elsewhere)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return None
    return round((int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK"), 2)  # utime, stime


class StackStartError(RuntimeError):
    """The stack did not come up (the message holds the end of every log)."""


class Stack:
    """The router and the four services as local processes, restartable one by one."""

    def __init__(self, run_dir: Path) -> None:
        self.run_dir = run_dir
        self.router_port = free_port()
        self.router = f"tls/127.0.0.1:{self.router_port}"
        self.certs = run_dir / "certs"
        make_stack(self.certs, router_hosts=["127.0.0.1"])
        self.api_port = free_port()
        self.api_token = secrets.token_urlsafe(24)
        site = Site(router=self.router, api_store=str(run_dir / "config.json"), skeleton=str(write_paper_scenarios(run_dir / "person.npz")),
                    api_port=self.api_port, certs=str(self.certs))
        self.argv: dict[str, list[str]] = {"router": router_command(self.router, site.certs)}
        self.argv.update({spec.name: command(spec.name, site) for spec in SERVICES})
        self.children: dict[str, Child] = {}
        self.http = httpx.Client(base_url=f"http://127.0.0.1:{self.api_port}", timeout=2.0)

    def start(self, name: str) -> float:
        """Start (or restart) ``name`` with its command line; the monotonic time of the start."""
        started = time.monotonic()
        self.children[name] = launch(name, self.argv[name], self.run_dir, {TOKEN_ENV: self.api_token})
        return started

    def kill(self, name: str) -> float:
        """kill -9 ``name``; the monotonic time of the kill."""
        killed = time.monotonic()
        kill(self.children[name])
        return killed

    def running(self, names: list[str]) -> dict[str, bool]:
        return {name: self.children[name].running() for name in names}

    def http_ok(self) -> bool:
        try:
            return self.http.get("/api/health").status_code == 200
        except httpx.HTTPError:
            return False

    def stop(self) -> dict[str, int]:
        """Stop the services, then the router (SIGTERM, SIGKILL after a grace period); exit codes."""
        self.http.close()
        services = [child for name, child in self.children.items() if name != "router"]
        router = [self.children["router"]] if "router" in self.children else []
        return {**stop_all(services), **stop_all(router)}


@contextmanager
def running_stack(conf: StackConfig) -> Iterator[tuple[Stack, Recorder]]:
    """The stack up (every token present, every topic flowing, the API answering) and its recorder."""
    run_dir = Path(tempfile.mkdtemp(prefix="safemimic-faults-"))
    stack = Stack(run_dir)
    recorder: Recorder | None = None
    try:
        stack.start("router")
        if _wait_until(lambda: _port_open(stack.router_port), 10.0) is None:
            raise StackStartError(f"the router did not start:\n{stack.children['router'].log_tail()}")
        recorder = Recorder(conf, stack.router, stack.certs)
        for spec in SERVICES:
            stack.start(spec.name)
        started = time.monotonic()
        up = _wait_until(
            lambda: all(recorder.is_alive(spec.token) for spec in SERVICES)
            and all(recorder.first_after(topic, started) for topic in WATCHED_TOPICS) and stack.http_ok(),
            STARTUP_TIMEOUT_S, poll_s=0.1,
        )
        if up is None:
            logs = "\n".join(f"--- {c.name}:\n{c.log_tail(800)}" for c in stack.children.values())
            raise StackStartError(f"the stack did not come up within {STARTUP_TIMEOUT_S:.0f} s:\n{logs}")
        yield stack, recorder
    finally:
        if recorder is not None:
            recorder.close()
        stack.stop()


# --------------------------------------------------------------------------------------------
# kill -9 a service, restart it


class _PatchHammer:
    """A thread sending PATCH /api/config/safety (γ alternating) until stopped; the last version acknowledged."""

    def __init__(self, stack: Stack) -> None:
        self._stack = stack
        self._stop = threading.Event()
        self.acknowledged = 0
        self.sent = 0
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        headers = {"Authorization": f"Bearer {self._stack.api_token}"}
        with httpx.Client(base_url=str(self._stack.http.base_url), timeout=3.0, headers=headers) as http:
            while not self._stop.is_set():
                self.sent += 1
                try:
                    reply = http.patch("/api/config/safety", json={"gamma": GAMMAS[self.sent % 2]})
                except httpx.HTTPError:
                    self._stop.wait(0.02)  # down: connection refused until the restart
                    continue
                if reply.status_code == 200:
                    self.acknowledged = max(self.acknowledged, reply.json()["version"])

    def stop(self) -> None:
        self._stop.set()
        self._thread.join()


def kill_and_restart(stack: Stack, recorder: Recorder, name: str) -> dict[str, Any]:
    """One kill -9 of service ``name`` and its restart: what happened, as figures."""
    token, topic = SERVICE_BY_NAME[name].token, DATA_TOPIC[name]
    others = [spec.name for spec in SERVICES if spec.name != name]
    figures: dict[str, Any] = {"load_avg_1m": round(os.getloadavg()[0], 2)}
    if name == "config-api":  # PATCH requests in flight when the kill lands
        hammer = _PatchHammer(stack)
        _wait_until(lambda: hammer.acknowledged > 0, 5.0)
        time.sleep(random.uniform(0.0, 0.2))
        killed = stack.kill(name)
        hammer.stop()
        figures["api_acknowledged_version"] = hammer.acknowledged
    else:
        killed = stack.kill(name)
    _wait_until(lambda: recorder.token_event_after(token, False, killed) is not None, OUTAGE_S)
    gone = recorder.token_event_after(token, False, killed)
    time.sleep(max(0.0, killed + OUTAGE_S - time.monotonic()))
    outage_end = time.monotonic()
    figures |= {
        "token_gone_s": None if gone is None else round(gone - killed, 3),
        "others_alive_during": all(stack.running(others).values()),
        "others_max_gap_s": {
            other: round(recorder.max_gap(other_topic, killed, outage_end), 3)
            for other in others if (other_topic := DATA_TOPIC[other]) is not None
        },
    }
    if "config-api" in others:
        figures["api_ok_during"] = stack.http_ok()
    if name == "perception":
        figures["human_stale_reported"] = recorder.stale_between(killed, outage_end)
    restarted = stack.start(name)
    if topic is None:
        back = _wait_until(lambda: recorder.token_event_after(token, True, restarted) is not None and stack.http_ok(), GIVE_UP_S)
        data_at = back
    else:
        back = _wait_until(lambda: recorder.token_event_after(token, True, restarted) is not None
                           and recorder.first_after(topic, restarted) is not None, GIVE_UP_S)
        data_at = recorder.first_after(topic, restarted)
    token_at = recorder.token_event_after(token, True, restarted)
    figures["start_cpu_s"] = _cpu_seconds(stack.children[name].pid)
    figures["token_back_s"] = None if token_at is None else round(token_at - restarted, 3)
    figures["data_back_s"] = None if data_at is None else round(data_at - restarted, 3)
    figures["resume_s"] = None if back is None else round(back - restarted, 3)
    if name == "config-api":  # the restarted API loaded the store with every acknowledged change
        figures["api_version_after"] = stack.http.get("/api/config").json()["version"] if back is not None else None
    time.sleep(0.5)  # settle: the restarted service's first commands / the executor's reaction
    figures["others_alive_after"] = all(stack.running(others).values())
    with recorder.lock:
        figures.update(recorder.limits.between(killed, time.monotonic()))
    return figures


def _service_behaved(rounds: list[dict[str, Any]]) -> bool:
    """Every round: the service came back (token and data) at all, its token went away, the others
    lived on with their topics flowing, the API answered, perception's loss was reported, no
    acknowledged change was lost and no command broke the rate limit."""
    def ok(r: dict[str, Any]) -> bool:
        return (r["resume_s"] is not None and r["token_gone_s"] is not None
                and r["others_alive_during"] and r["others_alive_after"]
                and all(gap <= FLOW_GAP_S for gap in r["others_max_gap_s"].values())
                and r.get("api_ok_during", True) and r.get("human_stale_reported", True)
                and (r.get("api_version_after") or 0) >= r.get("api_acknowledged_version", 0)
                and r["rate_violations"] == 0)

    return all(ok(r) for r in rounds)


def _resumed_within(rounds: list[dict[str, Any]], bound_s: float) -> dict[str, bool]:
    """The restart budget: every round back within ``bound_s`` (start-up CPU time on this machine
    is in each round's ``start_cpu_s``)."""
    return {f"resume_within_{bound_s:g}s": all(r["resume_s"] is not None and r["resume_s"] <= bound_s for r in rounds)}


def router_restart(stack: Stack, recorder: Recorder) -> dict[str, Any]:
    """kill -9 the router, restart it on the same port: when every token and data stream is back."""
    killed = stack.kill("router")
    time.sleep(OUTAGE_S)
    services = [spec.name for spec in SERVICES]
    alive_during = stack.running(services)
    restarted = stack.start("router")

    def back() -> bool:
        return (all(recorder.token_event_after(spec.token, True, restarted) is not None for spec in SERVICES)
                and all(recorder.first_after(topic, restarted) is not None for topic in WATCHED_TOPICS))

    resumed = _wait_until(back, GIVE_UP_S)
    figures: dict[str, Any] = {
        "load_avg_1m": round(os.getloadavg()[0], 2),
        "resume_s": None if resumed is None else round(resumed - restarted, 3),
        "tokens_back_s": {
            spec.token: None if (at := recorder.token_event_after(spec.token, True, restarted)) is None else round(at - restarted, 3)
            for spec in SERVICES
        },
        "data_back_s": {
            topic: None if (at := recorder.first_after(topic, restarted)) is None else round(at - restarted, 3)
            for topic in WATCHED_TOPICS
        },
        "services_alive_during": all(alive_during.values()),
    }
    time.sleep(0.5)
    figures["services_alive_after"] = all(stack.running(services).values())
    with recorder.lock:
        figures.update(recorder.limits.between(killed, time.monotonic()))
    return figures


def _router_behaved(rounds: list[dict[str, Any]]) -> bool:
    """Every round: everything came back at all, no service died, no command broke the rate limit."""
    return all(r["resume_s"] is not None and r["services_alive_during"] and r["services_alive_after"]
               and r["rate_violations"] == 0 for r in rounds)


def stack_checks(conf: StackConfig, rounds: int) -> list[CheckResult]:
    """Start the stack, kill every service ``rounds`` times, then the router; the checks' results."""
    per_service: dict[str, list[dict[str, Any]]] = {spec.name: [] for spec in SERVICES}
    per_router: list[dict[str, Any]] = []
    started = time.monotonic()
    phases: list[tuple[float, str]] = [(started, "startup")]  # what the run was doing from when
    with running_stack(conf) as (stack, recorder):
        for i in range(rounds):
            for spec in SERVICES:
                phases.append((time.monotonic(), f"kill9_{spec.name} #{i + 1}"))
                per_service[spec.name].append(kill_and_restart(stack, recorder, spec.name))
        for i in range(rounds):
            phases.append((time.monotonic(), f"router_restart #{i + 1}"))
            per_router.append(router_restart(stack, recorder))
        with recorder.lock:
            limits = recorder.limits
            limit_figures = {
                "commands": limits.commands, "non_finite": limits.non_finite + recorder.invalid_commands(),
                "rate_violations": limits.violations, "max_rate_ratio": round(limits.max_ratio, 4),
                "safety_restart_ratios": [round(ratio, 4) for _, ratio in limits.restarts],
                "violations": [
                    {**{k: v for k, v in worst.items() if k != "t"},
                     "during": next(label for at, label in reversed(phases) if at <= worst["t"])}
                    for worst in limits.worst
                ],
                "duration_s": round(time.monotonic() - started, 1),
            }
    results = []
    for name, rounds_figures in per_service.items():
        resumes = [r["resume_s"] for r in rounds_figures]
        figures = {"max_resume_s": None if None in resumes else max(resumes), "bound_s": RESUME_BOUND_S, "rounds": rounds_figures}
        results.append(CheckResult(f"kill9_{name}", _service_behaved(rounds_figures), figures,
                                   _resumed_within(rounds_figures, RESUME_BOUND_S)))
    router_resumes = [r["resume_s"] for r in per_router]
    results.append(CheckResult("router_restart", _router_behaved(per_router), {
        "max_resume_s": None if None in router_resumes else max(router_resumes), "bound_s": ROUTER_RESUME_BOUND_S,
        "rounds": per_router,
    }, _resumed_within(per_router, ROUTER_RESUME_BOUND_S)))
    limits_ok = limit_figures["commands"] > 0 and limit_figures["non_finite"] == 0 and limit_figures["rate_violations"] == 0
    results.append(CheckResult("command_limits", limits_ok, {**limit_figures, "logs": str(stack.run_dir)}))
    if all(result.passed for result in results):
        shutil.rmtree(stack.run_dir)  # the services' logs are kept only when a check failed
    return results


# --------------------------------------------------------------------------------------------
# config_write_kill


def hammer_store(path: str, acknowledged: Any) -> None:
    """Commit versions of the configuration to the store at ``path`` until killed (a fork-server child).

    Version v sets ``safety.gamma`` to ``_gamma(v)``; after each commit returns, ``acknowledged``
    (a shared integer) holds v.
    """
    startup = load_config(environ={})
    store = ConfigStore.open(Path(path), startup)
    while True:
        version = store.snapshot.version + 1
        new = store.snapshot.config.model_copy(
            update={"safety": store.snapshot.config.safety.model_copy(update={"gamma": _gamma(version)})})
        store.commit(new, "faults", "127.0.0.1", "write kill")
        acknowledged.value = version


def _expected(startup: StackConfig, version: int) -> dict[str, Any]:
    """The whole configuration the store holds at ``version`` (the startup one at version 0)."""
    if version == 0:
        return startup.model_dump(mode="json")
    return startup.model_copy(update={"safety": startup.safety.model_copy(update={"gamma": _gamma(version)})}).model_dump(mode="json")


def config_write_kill(kills: int) -> CheckResult:
    """SIGKILL a store writer ``kills`` times at random moments; the file is always whole."""
    started = time.monotonic()
    context = multiprocessing.get_context("forkserver")
    context.set_forkserver_preload(["__main__", __name__])  # the main module once, not per child
    startup = load_config(environ={})
    path = Path(tempfile.mkdtemp(prefix="safemimic-write-kill-")) / "config.json"
    acknowledged = context.Value("q", 0, lock=False)
    failures: list[str] = []
    temps_left = in_flight = commits = done = 0
    for i in range(kills):
        before = acknowledged.value
        writer = context.Process(target=hammer_store, args=(str(path), acknowledged), daemon=True)
        writer.start()
        if _wait_until(lambda: acknowledged.value > before or not writer.is_alive(), 10.0, poll_s=0.001) is None \
                or acknowledged.value == before:
            writer.kill()
            writer.join()
            failures.append(f"kill {i}: the writer committed nothing (exit code {writer.exitcode})")
            break
        time.sleep(random.uniform(*WRITE_KILL_DELAY_S))
        os.kill(writer.pid, signal.SIGKILL)
        writer.join()
        done += 1
        acked = acknowledged.value
        commits += acked - before
        temps_left += bool(stale_temporaries(path))
        try:
            snapshot = ConfigStore.open(path, startup).snapshot  # parses, validates; removes temporaries
        except Exception as exc:  # StoreError, or anything else a torn file could raise
            failures.append(f"kill {i}: the store does not load: {str(exc).splitlines()[0][:200]}")
            break
        if snapshot.version not in (acked, acked + 1):
            failures.append(f"kill {i}: store at v{snapshot.version}, last acknowledged v{acked}")
        elif snapshot.config.model_dump(mode="json") != _expected(startup, snapshot.version):
            failures.append(f"kill {i}: store v{snapshot.version} holds another configuration than was written")
        in_flight += snapshot.version == acked + 1
        acknowledged.value = snapshot.version
        if stale_temporaries(path):
            failures.append(f"kill {i}: temporary files remain after the next open")
    temps_at_end = len(stale_temporaries(path))
    shutil.rmtree(path.parent)
    figures = {
        "kills": done, "commits": commits, "killed_with_temp_file": temps_left, "in_flight_commit_persisted": in_flight,
        "temp_files_at_end": temps_at_end, "failures": failures[:5],
        "duration_s": round(time.monotonic() - started, 1),
    }
    return CheckResult("config_write_kill", not failures and done == kills and temps_at_end == 0, figures)


@pytest.fixture(scope="module")
def stack_results(long_run: bool) -> dict[str, CheckResult]:
    """One stack run for its checks, by name: one kill of each service and of the router (long: two).
    A stack that does not come up (:class:`StackStartError`, with the end of every log) errors each
    of its tests."""
    return {result.name: result for result in stack_checks(load_config(), 2 if long_run else 1)}


@pytest.mark.integration
def test_config_write_kill(long_run: bool, check: Check) -> None:
    check(config_write_kill(100 if long_run else 10))


@pytest.mark.integration
@pytest.mark.parametrize("service", [spec.name for spec in SERVICES])
def test_kill9(service: str, stack_results: dict[str, CheckResult], check: Check) -> None:
    """The restart budget is held in the long run only: in the quick one it is printed (a restart
    is mostly the interpreter's start-up CPU time, ``start_cpu_s``, which measures the machine)."""
    check(stack_results[f"kill9_{service}"], budgets=False)


@pytest.mark.integration
def test_router_restart(stack_results: dict[str, CheckResult], check: Check) -> None:
    check(stack_results["router_restart"], budgets=False)


@pytest.mark.integration
def test_command_limits(stack_results: dict[str, CheckResult], check: Check) -> None:
    check(stack_results["command_limits"])
