"""Several hosts: network namespaces joined by veth links to one bridge, each host with its own address.

Hosts: ``router`` (``safemimic router`` + the config API + a bus probe), ``perception`` (an edge
box: a fresh venv with only ``pip install .[perception]``), ``safety`` and ``executor``; every
service runs the command line of :mod:`safemimic.stack` as a Zenoh client of the router, over
mutual TLS: each host gets only its own folder of ``safemimic certs stack --split`` (the CA
certificate and its identity's pair; the router's folder also holds the access control). The test
shows the pipeline working across hosts, then unplugs the perception host's cable at the switch:
the safety service must report the human source lost (``SafetyStatus.human_stale``) within 1 s,
through liveliness, and keep publishing finite, safe commands; plugging it back resumes imitation.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path

import pytest

from safemimic.certs import make_stack
from safemimic.launch import python_argv
from safemimic.stack import API_PORT, ROUTER_PORT, Site, command, router_command, write_paper_scenarios
from tests.support.processes import Proc
from tests.support.team import REPO

pytestmark = pytest.mark.integration

HOSTS = ("router", "perception", "safety", "executor")
SUBNET = "10.213.77"
#: The safety service must report the human source lost this soon after the cut.
LOST_WITHIN_S = 1.0
API_TOKEN = "multihost-test-token-0123456789"


def _ip(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(["ip", *args], capture_output=True, text=True, timeout=10)


@dataclass
class Lan:
    """Namespaces ``{prefix}-{host}`` on a bridge in ``{prefix}-lan``; host i has ``SUBNET.i``."""

    prefix: str
    procs: list[Proc] = field(default_factory=list)

    def ns(self, host: str) -> str:
        return f"{self.prefix}-{host}"

    def address(self, host: str) -> str:
        return f"{SUBNET}.{HOSTS.index(host) + 1}"

    def run(self, host: str, argv: list[str], env: dict[str, str] | None = None) -> Proc:
        """Start ``argv`` (``safemimic ...`` runs with this interpreter) on ``host``."""
        proc = Proc(["ip", "netns", "exec", self.ns(host), *python_argv(argv)], env)
        self.procs.append(proc)
        return proc

    def unplug(self, host: str) -> None:
        """Take the host's port on the switch down (its cable pulled: no RST, no FIN, silence)."""
        _check(_ip("-n", self.ns("lan"), "link", "set", f"p-{host}", "down"))

    def plug(self, host: str) -> None:
        _check(_ip("-n", self.ns("lan"), "link", "set", f"p-{host}", "up"))


def _check(result: subprocess.CompletedProcess) -> None:
    assert result.returncode == 0, f"{result.args}: {result.stderr}"


def _build(lan: Lan) -> None:
    lan_ns = lan.ns("lan")
    _check(_ip("netns", "add", lan_ns))
    _check(_ip("-n", lan_ns, "link", "add", "br0", "type", "bridge"))
    _check(_ip("-n", lan_ns, "link", "set", "br0", "up"))
    for host in HOSTS:
        ns = lan.ns(host)
        _check(_ip("netns", "add", ns))
        _check(_ip("link", "add", "eth0", "netns", ns, "type", "veth", "peer", "name", f"p-{host}", "netns", lan_ns))
        _check(_ip("-n", ns, "addr", "add", f"{lan.address(host)}/24", "dev", "eth0"))
        for dev in ("lo", "eth0"):
            _check(_ip("-n", ns, "link", "set", dev, "up"))
        _check(_ip("-n", lan_ns, "link", "set", f"p-{host}", "master", "br0", "up"))


@pytest.fixture
def lan() -> Iterator[Lan]:
    """The four hosts and the switch; processes stopped and namespaces deleted whatever happens."""
    if shutil.which("ip") is None:
        pytest.skip("iproute2's `ip` is not installed (apt-get install iproute2)")
    if os.geteuid() != 0:
        pytest.skip("creating network namespaces needs root (CAP_NET_ADMIN)")
    lan = Lan(prefix=f"sm{os.getpid()}")
    probe = _ip("netns", "add", lan.ns("probe"))
    if probe.returncode != 0:
        pytest.skip(f"the kernel refuses network namespaces: {probe.stderr.strip()}")
    _ip("netns", "del", lan.ns("probe"))
    try:
        _build(lan)
        yield lan
    finally:
        for proc in lan.procs:
            proc.stop()
        for name in ("lan", *HOSTS):
            _ip("netns", "del", lan.ns(name))  # deleting the namespaces removes their veth pairs too
        leftover = [ns for ns in _ip("netns", "list").stdout.split() if ns.startswith(f"{lan.prefix}-")]
        assert not leftover, f"namespaces left behind: {leftover}"


@pytest.fixture(scope="module")
def edge_venv(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A fresh venv with ``pip install .[perception]`` only: what an edge box next to the camera gets."""
    venv = tmp_path_factory.mktemp("edge") / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True, timeout=120)
    install = subprocess.run([str(venv / "bin" / "pip"), "install", "--quiet", f"{REPO}[perception]"],
                             capture_output=True, text=True, timeout=600)
    assert install.returncode == 0, install.stderr[-3000:]
    return venv


class Probe:
    """The JSON lines of tests/multihost_probe.py, parsed as they arrive."""

    def __init__(self, proc: Proc) -> None:
        self.proc = proc
        self.events: list[dict] = []
        self.alive: set[str] = set()  # services whose token is present, per the events so far

    def wait(self, predicate: Callable[[dict], bool], timeout: float, what: str) -> dict:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline and self.proc.popen.poll() is None:
            try:
                line = self.proc.lines.get(timeout=max(0.01, deadline - time.monotonic()))
            except Exception:  # queue.Empty
                break
            if line.startswith("{"):
                event = json.loads(line)
                self.events.append(event)
                if event["event"] == "alive":
                    (self.alive.add if event["up"] else self.alive.discard)(event["service"])
                if predicate(event):
                    return event
        raise AssertionError(f"timed out after {timeout} s waiting for {what}; last events: {self.events[-5:]}; "
                             f"probe output: {''.join(self.proc.output)[-2000:]}")


def _status(predicate: Callable[[dict], bool]) -> Callable[[dict], bool]:
    return lambda event: event["event"] == "status" and predicate(event)


def test_edge_install_is_light(edge_venv: Path, tmp_path: Path) -> None:
    """The perception extra brings no MuJoCo, Pinocchio, QP solver, numba or web server, and the
    wheel holds neither the benchmarks nor the tests (they run from the checkout)."""
    probe = ("import importlib.metadata as m, importlib.util as u, json; print(json.dumps({"
             "'heavy': [n for n in ('mujoco', 'pinocchio', 'osqp', 'daqp', 'numba', 'fastapi', 'uvicorn') if u.find_spec(n)], "
             "'packages': sorted({f.parts[0] for f in m.files('safemimic') if f.suffix == '.py'})}))")
    check = subprocess.run([str(edge_venv / "bin" / "python"), "-c", probe], capture_output=True, text=True,
                           cwd=tmp_path, timeout=60, env={k: v for k, v in os.environ.items() if k != "PYTHONPATH"})
    assert check.returncode == 0, check.stderr
    assert json.loads(check.stdout) == {"heavy": [], "packages": ["config", "safemimic", "services", "shared"]}
    assert (edge_venv / "bin" / "safemimic").exists()


def test_pipeline_across_hosts_survives_a_cut_perception_link(lan: Lan, edge_venv: Path, tmp_path: Path) -> None:
    router = f"tls/{lan.address('router')}:{ROUTER_PORT}"
    certs = tmp_path / "certs"  # made once; each host below gets only its own folder
    make_stack(certs, router_hosts=[lan.address("router")], do_split=True)
    skeleton = write_paper_scenarios(tmp_path / "paper-scenarios.npz")
    site = Site(router=router, api_store=str(tmp_path / "api" / "config.json"), skeleton=str(skeleton),
                api_host=lan.address("router"), api_port=API_PORT)

    def own(identity: str) -> Site:
        return replace(site, certs=str(certs / identity))

    started = lan.run("router", router_command(f"tls/0.0.0.0:{ROUTER_PORT}", str(certs / "router")))
    assert "mutual TLS + access control" in started.wait_for(lambda line: "listening" in line, 30)
    probe = Probe(lan.run("router", [sys.executable, "-m", "tests.multihost_probe", "--mode", "client", "--connect", router,
                                     "--no-multicast", "--certs", str(certs / "viewer")],
                          env={"SAFEMIMIC__BUS__TLS__IDENTITY": "viewer"}))  # an observer's certificate
    lan.run("router", command("config-api", own("config_api")), env={"SAFEMIMIC_API_TOKEN": API_TOKEN})
    lan.run("executor", command("executor", own("executor")))
    # a human timeout far beyond the test: only the liveliness token can make the human stale here
    lan.run("safety", command("safety", own("safety")), env={"SAFEMIMIC__SAFETY__HUMAN_TIMEOUT_S": "30"})
    edge = command("perception", own("perception"))
    lan.run("perception", [str(edge_venv / "bin" / "safemimic"), *edge[1:]])

    services = {"executor", "safety", "perception", "config_api"}
    probe.wait(lambda e: services <= probe.alive, 90, "every service's liveliness token")
    # the pipeline across four hosts: skeletons from the edge box reach safety, commands and joint
    # states flow between the safety and executor hosts, the human appears in the barrier
    first = probe.wait(_status(lambda e: e["human_seq"] is not None and e["min_h_human"] is not None), 30, "a human")
    before = probe.wait(_status(lambda e: e["human_seq"] >= first["human_seq"] + 30 and not e["human_stale"]), 10,
                        "30 more skeletons used")
    assert before["joint_states"] > 0 and before["commands"] > 0 and before["nonfinite"] == 0
    # the console host sees every service; a read from another address needs the token
    request = (f"import urllib.request as r; q = r.Request('http://{site.api_host}:{site.api_port}/api/health', "
               f"headers={{'Authorization': 'Bearer {API_TOKEN}'}}); print(r.urlopen(q, timeout=5).read().decode())")
    health = subprocess.run(["ip", "netns", "exec", lan.ns("router"), sys.executable, "-c", request],
                            capture_output=True, text=True, timeout=30)
    assert health.returncode == 0, health.stderr
    assert {"executor", "perception", "safety"} <= set(json.loads(health.stdout)["services_alive"])

    cut = time.monotonic()
    lan.unplug("perception")
    # with safety.human_timeout_s = 30 s only the vanished liveliness token can make the human stale now
    stale = probe.wait(_status(lambda e: e["t"] > cut and e["human_stale"]), 5, "human_stale after the cut")
    probe.wait(lambda e: "perception" not in probe.alive, 2, "the perception token gone at the probe too")
    lost = next(e for e in probe.events if e["event"] == "alive" and e["service"] == "perception" and not e["up"])
    print(f"cut → perception token gone {lost['t'] - cut:.3f} s, → SafetyStatus.human_stale {stale['t'] - cut:.3f} s")
    assert stale["t"] - cut <= LOST_WITHIN_S and lost["t"] - cut <= LOST_WITHIN_S
    # the robot is kept safe while the person is unseen: finite commands at the control rate, the
    # person's last capsules still respected
    during = probe.wait(_status(lambda e: e["t"] > stale["t"] + 1.5), 5, "statuses during the outage")
    outage = [e for e in probe.events if e["event"] == "status" and stale["t"] <= e["t"] <= during["t"]]
    assert all(e["human_stale"] for e in outage)
    assert all(e["min_h_human"] is not None and e["min_h_human"] >= -1e-3 for e in outage)
    assert during["nonfinite"] == 0
    assert (during["commands"] - stale["commands"]) / (during["t"] - stale["t"]) > 300  # 500 Hz nominal
    assert during["human_seq"] == stale["human_seq"]  # nothing new from the unplugged host

    lan.plug("perception")
    probe.wait(lambda e: "perception" in probe.alive, 15, "perception back")
    resumed = probe.wait(_status(lambda e: not e["human_stale"] and e["human_seq"] > during["human_seq"] + 10), 15,
                         "new skeletons used again")
    assert resumed["nonfinite"] == 0
