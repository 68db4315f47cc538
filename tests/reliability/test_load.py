"""Load checks: a flood of human states at the safety service, 200 requests/s at the config API.

``human_state_flood``
    ``safemimic safety`` at 500 Hz in its own process (Zenoh peer on loopback); another process
    publishes valid :class:`~shared.messages.HumanState` messages at 10× perception's 30 Hz
    (300 Hz) plus bursts of 1,000 back-to-back messages every 2 s. Budget: ≥ 99 % of the control
    deadlines kept over the flood (the service's own ``deadline_misses`` in
    :class:`~shared.messages.SafetyStatus`, against its ticks counted by the commands' ``seq``),
    beside the machine's own wake-up latency measured just before (``machine_wake``:
    :func:`tests.support.machine.wake_latency`), and the newest state used within
    :data:`NEWEST_MAX_PERIODS` control periods of wall time (``newest_within_ms``). Behaviour: the
    service lives through it and uses the newest state: after each burst, one of the first
    :data:`NEWEST_MAX_PERIODS` :class:`~shared.messages.JointCommand` s the service publishes after
    the burst's last message was sent carries its ``human_seq`` (or a newer one): counted in ticks
    that ran, so a machine that wakes the loop late misses the budget, not the behaviour; and the
    commands' ``human_seq`` never goes back.

``config_api_load``
    ``safemimic config-api`` (uvicorn) and a real ``safemimic safety`` (which acknowledges
    changes) as processes on loopback; an open-loop client schedules 200 requests/s (latency is
    counted from the scheduled time, so a server falling behind shows up) on :data:`API_MIX`:
    reads of the configuration, status and health, and 1 in 20 a PATCH of the safety service's γ
    that waits until the safety service reports it applied. Behaviour: no error (exception,
    non-2xx, or a change not acknowledged as applied). Budgets: answers at 200/s (within
    :data:`API_RATE_TOLERANCE`), p99 < 50 ms.

Each result carries the machine's load average before and after and the host's steal time during
the load (``steal_pct_during``): the checks run on shared 2-core machines, where timing figures move
with what else runs.
"""

from __future__ import annotations

import json
import multiprocessing
import os
import queue
import re
import secrets
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest

from safemimic.launch import Child, free_port, launch, stop_all
from shared.bus import Bus
from shared.config import BusConfig
from tests.reliability.check import Check, CheckResult
from tests.support.bus import BusRecorder
from tests.support.machine import cpu_times, host_kept_cpu, steal_pct, wake_latency
from tests.support.messages import human_state

#: The safety service's control rate under test (Hz).
SAFETY_RATE_HZ = 500.0
#: Perception's normal HumanState rate (a 30 Hz camera) and the flood's multiple of it.
NORMAL_HUMAN_HZ = 30.0
FLOOD_FACTOR = 10
#: Back-to-back messages per burst, and the time between bursts (s).
BURST_SIZE = 1000
BURST_EVERY_S = 2.0
#: The first burst, after the flood starts (s): the quick variant sees two bursts too.
FIRST_BURST_S = 0.5
#: Flood duration (s): full run and the quick variant ``make test`` runs.
FLOOD_S, FLOOD_QUICK_S = 10.0, 3.0
#: Pass: fraction of control deadlines kept during the flood.
MIN_DEADLINES_KEPT = 0.99
#: Pass: time (in control periods) from a burst's last message being sent until a command uses it
#: (or a newer state): 10 periods = 20 ms, less than one frame of a 30 Hz camera, so the state used
#: is never a frame behind what perception sent. Decoding every message of a burst in the
#: subscriber's callback lags by 50–500 ms on a loaded 2-core machine; the zero-order hold alone by
#: one period. Counted in time, not in ticks run: a stalled loop runs fewer ticks meanwhile.
NEWEST_MAX_PERIODS = 10

#: Config API request rate (1/s) and duration (s): full and quick.
API_RATE_HZ = 200.0
API_S, API_QUICK_S = 10.0, 3.0
#: Pass: 99th percentile latency from the scheduled send time (ms).
API_P99_MS = 50.0
#: The answered rate (answers over the span from first to last answer) may fall this far below the
#: target: the first and last answers' own latency jitter moves the span by a few milliseconds.
API_RATE_TOLERANCE = 0.01
#: Client threads (one keep-alive connection each) and their process's GIL switch interval (s).
API_WORKERS = 16
CLIENT_SWITCH_INTERVAL_S = 0.0005
#: One cycle of the request mix, repeated: mostly reads, one change of γ in 20 requests (10/s).
API_MIX: tuple[str, ...] = ("config", "status") * 9 + ("health", "patch")
#: The two γ values PATCHes alternate between (each one a real change: a new version).
API_GAMMAS = (4.0, 6.0)

#: Longest wait for a service to come up (the safety service builds and warms its pipeline).
STARTUP_TIMEOUT_S = 60.0
_SUMMARY = re.compile(r"safety: (\d+) ticks .*?, (\d+) deadline misses")
_SCHEDULING = re.compile(r"safety service started: \S+ Hz \(([^)]*)\)")


def load_avg() -> list[float]:
    """The 1/5/15-minute load averages, rounded."""
    return [round(x, 2) for x in os.getloadavg()]


def _endpoint() -> str:
    return f"tcp/127.0.0.1:{free_port()}"


def _safety_command(listen: str, robot_id: str) -> list[str]:
    """``safemimic safety`` at :data:`SAFETY_RATE_HZ` as a Zenoh peer listening on ``listen``."""
    return ["safemimic", "safety", "--mode", "peer", "--listen", listen, "--no-multicast", "--robot-id", robot_id,
            "--rate", str(SAFETY_RATE_HZ)]


def _peer(endpoint: str) -> BusConfig:
    return BusConfig(mode="peer", connect=[endpoint], multicast_scouting=False)


def _wait(condition: Callable[[], bool], what: str, children: list[Child], timeout_s: float = STARTUP_TIMEOUT_S) -> None:
    """Poll ``condition()`` until true; a child that exits or the timeout raises with the logs."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline or any(not child.running() for child in children):
            logs = "\n".join(f"--- {c.name}\n{c.log_tail()}" for c in children)
            raise RuntimeError(f"{what} did not happen within {timeout_s:.0f} s:\n{logs}")
        time.sleep(0.05)


@contextmanager
def _services(argvs: dict[str, list[str]], env: dict[str, str] | None = None) -> Iterator[list[Child]]:
    """Launch the named command lines (logs in a fresh folder); stop them all on exit."""
    with tempfile.TemporaryDirectory(prefix="safemimic-load-") as run_dir:
        children: list[Child] = []
        try:
            for name, argv in argvs.items():
                children.append(launch(name, argv, Path(run_dir), env))
            yield children
        finally:
            stop_all(children)


def _open_bus(endpoint: str, robot_id: str, service: str, children: list[Child]) -> Bus:
    """A peer session connected to ``endpoint``, retried while the listening service starts."""
    buses: list[Bus] = []

    def opened() -> bool:
        try:
            buses.append(Bus(_peer(endpoint), robot_id, service))
        except Exception:  # zenoh.ZError: nobody listening yet
            return False
        return True

    _wait(opened, f"a Zenoh session to {endpoint}", children)
    return buses[0]


def _in_process(target: Callable[..., None], *args: Any, timeout_s: float) -> Any:
    """Run ``target(*args, conn)`` in a fresh process; what it sends on ``conn`` (its one result)."""
    context = multiprocessing.get_context("spawn")
    receiving, sending = context.Pipe(duplex=False)
    process = context.Process(target=target, args=(*args, sending), daemon=True)
    process.start()
    deadline = time.monotonic() + timeout_s
    try:
        while not receiving.poll(0.1):
            if not process.is_alive() or time.monotonic() > deadline:
                raise RuntimeError(f"{target.__name__} sent no result (exit code {process.exitcode})")
        return receiving.recv()
    finally:
        process.join(5)
        if process.is_alive():
            process.kill()
            process.join()


def _safety_summary(child: Child) -> dict[str, Any]:
    """The stopped safety service's own summary (ticks, misses) and its loop's scheduling."""
    text = child.log_path.read_text(errors="replace")
    summary, scheduling = _SUMMARY.search(text), _SCHEDULING.search(text)
    out: dict[str, Any] = {"service_scheduling": scheduling.group(1) if scheduling else None}
    if summary:
        ticks, misses = int(summary.group(1)), int(summary.group(2))
        out.update(service_ticks_total=ticks, service_misses_total=misses)
    return out


# --------------------------------------------------------------------------------------------
# human_state_flood


@dataclass(frozen=True)
class FloodPlan:
    """What the publisher process sends: a steady rate plus periodic bursts, for ``seconds``."""

    rate_hz: float
    seconds: float
    burst_size: int
    burst_every_s: float


@dataclass
class FloodSent:
    """What the publisher process did (monotonic times: one clock for every process on this host)."""

    start: float
    end: float
    sent: int
    #: (seq of a burst's last message, time it was handed to Zenoh) per burst.
    bursts: list[tuple[int, float]]


def publish_flood(endpoint: str, robot_id: str, plan: FloodPlan, conn: Connection) -> None:
    """The publisher process: HumanState at ``plan.rate_hz`` plus bursts; sends a :class:`FloodSent` back.

    Waits until the safety service's liveliness token is visible (the session is up and the
    subscriber declared) before the first message.
    """
    message = human_state()
    with Bus(_peer(endpoint), robot_id, "load_publisher") as bus:
        publisher = bus.publisher("human/state")
        while "safety" not in bus.alive_services(timeout_s=1.0):
            time.sleep(0.1)

        def put() -> None:
            message.stamp = time.monotonic()
            publisher.put(message)

        bursts: list[tuple[int, float]] = []
        start = time.monotonic()
        next_burst = start + FIRST_BURST_S
        k = 0
        while (now := time.monotonic()) < start + plan.seconds:
            if now >= next_burst:
                for _ in range(plan.burst_size):
                    put()
                bursts.append((message.seq, time.monotonic()))
                next_burst += plan.burst_every_s
            put()
            k += 1
            time.sleep(max(0.0, start + k / plan.rate_hz - time.monotonic()))
        conn.send(FloodSent(start, time.monotonic(), message.seq + 1, bursts))


def flood_record(recorder: BusRecorder) -> tuple[np.ndarray, np.ndarray]:
    """The commands as an (n, 3) array ``(stamp, seq, human_seq)`` (human_seq −1 when none) and the
    statuses as (m, 2) ``(stamp, deadline_misses)``, in stamp order."""
    commands = np.array([(c.stamp, c.seq, -1 if c.human_seq is None else c.human_seq)
                         for c in recorder.between("robot/command")], dtype=float)
    statuses = np.array([(s.stamp, s.deadline_misses) for s in recorder.between("safety/status")], dtype=float)
    return commands[np.argsort(commands[:, 0])], statuses[np.argsort(statuses[:, 0])]


def deadlines_kept(commands: np.ndarray, statuses: np.ndarray, start: float, end: float) -> dict[str, Any]:
    """Deadline figures over [start, end]: from the last status at or before ``start`` to the first at
    or after ``end``; ticks from the commands' seq (the tick index), misses from the statuses."""
    before, after = statuses[statuses[:, 0] <= start], statuses[statuses[:, 0] >= end]
    if not len(before) or not len(after):
        raise RuntimeError("no SafetyStatus around the flood window")
    (t0, missed0), (t1, missed1) = before[-1], after[0]
    seq0 = commands[commands[:, 0] <= t0][-1, 1]
    seq1 = commands[commands[:, 0] <= t1][-1, 1]
    ticks, misses = int(seq1 - seq0), int(missed1 - missed0)
    return {"ticks": ticks, "deadline_misses": misses, "deadlines_kept": round(1 - misses / (ticks + misses), 5),
            "window_s": round(t1 - t0, 2)}


def newest_lag(commands: np.ndarray, bursts: list[tuple[int, float]], period: float) -> dict[str, Any]:
    """Per burst: ms and ticks run from its last message's send time to the first command using it (or newer)."""
    ticks, ms = [], []
    for last_seq, sent in bursts:
        after = commands[commands[:, 0] >= sent]
        using = np.flatnonzero(after[:, 2] >= last_seq)
        if not len(using):
            raise RuntimeError(f"no command used human state {last_seq} (or a newer one)")
        first = after[using[0]]
        ticks.append(int(first[1] - after[0, 1]) + 1)  # commands published since the send, this one included
        ms.append(float(first[0] - sent) * 1e3)
    seqs = commands[commands[:, 2] >= 0, 2]
    return {"bursts": len(bursts), "newest_lag_ticks_max": max(ticks), "newest_lag_ms_max": round(max(ms), 2),
            "newest_lag_ms": [round(x, 2) for x in ms], "human_seq_went_back": int(np.sum(np.diff(seqs) < 0)),
            "period_ms": period * 1e3}


def human_state_flood(seconds: float, wake: dict[str, Any]) -> CheckResult:
    """The safety service under a flood of human states: deadlines kept, newest state used
    (``wake``: :func:`~tests.support.machine.wake_latency` just before, reported beside them)."""
    load_before = load_avg()
    plan = FloodPlan(NORMAL_HUMAN_HZ * FLOOD_FACTOR, seconds, BURST_SIZE, BURST_EVERY_S)
    endpoint, robot_id = _endpoint(), f"load{free_port()}"
    with _services({"safety": _safety_command(endpoint, robot_id)}) as children:
        with _open_bus(endpoint, robot_id, "load_probe", children) as bus:
            recorder = BusRecorder(bus, ("robot/command", "safety/status"))
            _wait(lambda: recorder.count("robot/command") > SAFETY_RATE_HZ, "1 s of commands from the safety service", children)
            cpu_before = cpu_times()
            sent: FloodSent = _in_process(publish_flood, endpoint, robot_id, plan, timeout_s=STARTUP_TIMEOUT_S + seconds)
            flood_steal = steal_pct(cpu_before)
            time.sleep(0.2)  # the statuses after the flood's end
            commands, statuses = flood_record(recorder)
        exit_codes = stop_all(children)
        summary = _safety_summary(children[0])
    kept = deadlines_kept(commands, statuses, sent.start, sent.end)
    period = 1.0 / SAFETY_RATE_HZ
    lag = newest_lag(commands, sent.bursts, period)
    figures = {
        **kept, "min_deadlines_kept": MIN_DEADLINES_KEPT, **lag, "newest_max_ms": NEWEST_MAX_PERIODS * period * 1e3,
        "human_sent": sent.sent, "human_rate_hz": plan.rate_hz, "burst_size": plan.burst_size,
        "flood_s": round(sent.end - sent.start, 2), **summary, "service_exit": exit_codes["safety"],
        "load_avg_before": load_before, "load_avg_after": load_avg(), "steal_pct_during": flood_steal,
        "machine_wake": wake,
    }
    behaved = (lag["newest_lag_ticks_max"] <= NEWEST_MAX_PERIODS and lag["human_seq_went_back"] == 0
               and len(sent.bursts) >= 1 and exit_codes["safety"] == 0)
    return CheckResult("human_state_flood", behaved, figures,
                       {"deadlines_kept": kept["deadlines_kept"] >= MIN_DEADLINES_KEPT,
                        "newest_within_ms": lag["newest_lag_ms_max"] <= figures["newest_max_ms"]})


# --------------------------------------------------------------------------------------------
# config_api_load


@dataclass(frozen=True)
class Outcome:
    """One request: its kind, when it was answered (monotonic s), latency from its scheduled time (ms),
    and the error if any."""

    kind: str
    done: float
    latency_ms: float
    error: str | None


def _request(client: httpx.Client, kind: str, gamma: float, scheduled: float, token: str) -> Outcome:
    """Send one request of ``kind``; an exception, a non-2xx answer or an unapplied change is an error."""
    error = None
    try:
        if kind == "patch":
            response = client.patch("/api/config/safety", json={"gamma": gamma}, headers={"Authorization": f"Bearer {token}"})
            if response.is_success and not response.json()["applied"]:
                error = "change not acknowledged as applied"
        else:
            response = client.get(f"/api/{kind}")
        if not response.is_success:
            error = f"HTTP {response.status_code}"
    except Exception as exc:
        error = type(exc).__name__
    done = time.monotonic()
    return Outcome(kind, done, (done - scheduled) * 1e3, error)


def drive_api(url: str, token: str, rate_hz: float, seconds: float, conn: Connection) -> None:
    """The client process: schedule ``rate_hz`` requests/s of :data:`API_MIX` for ``seconds`` whatever
    the answers (open loop), sent by :data:`API_WORKERS` threads with a keep-alive connection each;
    sends the list of :class:`Outcome` back.

    Threads with httpx's synchronous client: its asynchronous client costs ≈ 2 ms of CPU per
    request here, 4× as much, and would make the client the bottleneck on 2 cores.
    """
    sys.setswitchinterval(CLIENT_SWITCH_INTERVAL_S)  # a worker woken by an answer waits less for the GIL
    jobs: queue.SimpleQueue[tuple[int, float] | None] = queue.SimpleQueue()
    outcomes: list[Outcome] = []
    ready = threading.Barrier(API_WORKERS + 1)

    def work() -> None:
        with httpx.Client(base_url=url, timeout=10.0) as client:
            client.get("/api/health")  # connect before the clock starts
            ready.wait()
            while (job := jobs.get()) is not None:
                i, scheduled = job
                gamma = API_GAMMAS[(i // len(API_MIX)) % len(API_GAMMAS)]
                outcomes.append(_request(client, API_MIX[i % len(API_MIX)], gamma, scheduled, token))

    workers = [threading.Thread(target=work, daemon=True) for _ in range(API_WORKERS)]
    for worker in workers:
        worker.start()
    ready.wait()
    start = time.monotonic() + 0.05
    for i in range(int(rate_hz * seconds)):
        scheduled = start + i / rate_hz
        time.sleep(max(0.0, scheduled - time.monotonic()))
        jobs.put((i, scheduled))
    for _ in workers:
        jobs.put(None)
    for worker in workers:
        worker.join()
    conn.send(outcomes)


def _latency_figures(latencies_ms: np.ndarray) -> dict[str, float]:
    return {f"{name}_ms": round(float(np.percentile(latencies_ms, q)), 2) for name, q in
            (("p50", 50), ("p90", 90), ("p99", 99), ("max", 100))}


def config_api_load(seconds: float) -> CheckResult:
    """The config API at 200 requests/s (reads + acknowledged changes): rate, p99 latency, errors."""
    load_before = load_avg()
    endpoint, robot_id, token = _endpoint(), f"load{free_port()}", secrets.token_urlsafe(24)
    with tempfile.TemporaryDirectory(prefix="safemimic-load-api-") as store_dir:
        api = ["safemimic", "config-api", "--mode", "peer", "--connect", endpoint, "--no-multicast",
               "--robot-id", robot_id, "--port", "0", "--store", str(Path(store_dir) / "config.json")]
        env = {"SAFEMIMIC_API_TOKEN": token, "XDG_STATE_HOME": store_dir}
        with _services({"safety": _safety_command(endpoint, robot_id), "config-api": api}, env) as children:
            ready: dict[str, Any] = {}

            def api_ready() -> bool:
                for line in children[1].log_tail(100_000).splitlines():
                    if line.startswith("{") and json.loads(line).get("event") == "ready":
                        ready.update(json.loads(line))
                        return True
                return False

            def safety_reporting() -> bool:
                return httpx.get(f"{ready['url']}/api/status", timeout=2.0).json()["available"]

            _wait(api_ready, "the config API's ready line", children)
            _wait(safety_reporting, "a SafetyStatus at the config API", children)
            cpu_before = cpu_times()
            outcomes = _in_process(drive_api, ready["url"], token, API_RATE_HZ, seconds, timeout_s=seconds + 60)
            load_steal = steal_pct(cpu_before)
            version = httpx.get(f"{ready['url']}/api/config", timeout=2.0).json()["version"]
    latencies = np.array([o.latency_ms for o in outcomes])
    answered = sorted(o.done for o in outcomes if not o.error)
    achieved = (len(answered) - 1) / (answered[-1] - answered[0]) if len(answered) > 1 else 0.0
    errors = [o for o in outcomes if o.error]
    by_kind = {kind: _latency_figures(np.array([o.latency_ms for o in outcomes if o.kind == kind]))["p99_ms"]
               for kind in dict.fromkeys(API_MIX)}
    figures = {
        "requests": len(outcomes), "rate_target": API_RATE_HZ, "rate_achieved": round(achieved, 1),
        **_latency_figures(latencies), "p99_limit_ms": API_P99_MS, "p99_by_kind_ms": by_kind,
        "errors": len(errors), "error_kinds": sorted({f"{o.kind}: {o.error}" for o in errors}),
        "changes_applied": sum(1 for o in outcomes if o.kind == "patch" and not o.error), "final_version": version,
        "load_avg_before": load_before, "load_avg_after": load_avg(), "steal_pct_during": load_steal,
    }
    return CheckResult("config_api_load", not errors, figures, {
        "rate": achieved >= API_RATE_HZ * (1 - API_RATE_TOLERANCE), "p99_ms": figures["p99_ms"] < API_P99_MS,
    })


@pytest.fixture(scope="module")
def machine_wake() -> dict[str, Any]:
    """Can this machine keep a 500 Hz loop's time at all, right now (measured just before the flood)?"""
    return wake_latency()


@pytest.mark.integration
def test_human_state_flood(machine_wake: dict[str, Any], long_run: bool, check: Check) -> None:
    """The flood's deadline budget is held where the machine woke a control thread on time just before
    and its host took no CPU from it during the flood (:func:`~tests.support.machine.host_kept_cpu`)."""
    result = human_state_flood(FLOOD_S if long_run else FLOOD_QUICK_S, machine_wake)
    check(result, budgets=machine_wake["keeps_time"] and host_kept_cpu(result.figures["steal_pct_during"]))


@pytest.mark.integration
def test_config_api_load(machine_wake: dict[str, Any], long_run: bool, check: Check) -> None:
    """The API's rate and latency budgets are held as the flood's deadlines are (the machine kept time
    before, its host took no CPU during the load)."""
    result = config_api_load(API_S if long_run else API_QUICK_S)
    check(result, budgets=machine_wake["keeps_time"] and host_kept_cpu(result.figures["steal_pct_during"]))
