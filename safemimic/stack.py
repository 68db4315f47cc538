"""The stack's service command lines: the one table the local launcher and docker compose share.

:data:`SERVICES` lists the four services (executor, safety, perception, config API) with the pip
extra each needs and its role arguments; :func:`command` turns one into the exact ``safemimic``
command line for a :class:`Site` (where the router is, where the console listens, which skeleton
perception plays). ``safemimic demo`` runs these command lines as local processes;
``deploy/docker-compose.yml`` is generated from the same table (``python -m safemimic.stack
compose``) and a test checks that the committed file is what the table generates.

The router is not in the table's command lines: locally it is ``safemimic router`` (zenoh-python in
router mode), in compose the official ``eclipse/zenoh`` image (DESIGN §1); both listen on
:data:`ROUTER_PORT` and every service is a Zenoh client of it.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from services.perception.placement import parse_placement
from services.perception.scenarios import get_scenario, scenario_recording
from services.perception.synthetic import Body
from shared.config import DEFAULT_CONFIG_PATH, PerceptionConfig, load_config
from shared.skeleton import Recording, write_recording

#: The Zenoh router's TCP port (zenoh's default).
ROUTER_PORT = 7447
#: The config API / web console port.
API_PORT = 8080
#: The paper's two scenarios (Cai et al. §IV): a self-collision case and a human–robot one.
PAPER_SCENARIOS = ("cross-arm-reach", "side-by-side-arm-raise")
#: The official Zenoh router image (same 1.x protocol as the eclipse-zenoh Python package).
ZENOH_IMAGE = "eclipse/zenoh:1.10.1"
#: Where the repository's files live inside the image (an editable install: ``config/`` is mounted here).
IMAGE_ROOT = "/opt/safemimic"
#: The paper scenarios' recording baked into the image at build time.
IMAGE_SKELETON = f"{IMAGE_ROOT}/skeletons/paper-scenarios.npz"
COMPOSE_PATH = Path(__file__).resolve().parent.parent / "deploy" / "docker-compose.yml"


@dataclass(frozen=True)
class Site:
    """What differs between deployments of the same command lines."""

    router: str  #: Zenoh endpoint every service connects to, e.g. ``tcp/10.0.0.2:7447``
    api_store: str  #: the config API's store file
    skeleton: str  #: the .npz recording perception replays in a loop
    placement: str = "side-by-side"  #: where that person stands relative to the robot
    api_host: str = "127.0.0.1"  #: address the config API binds
    api_port: int = API_PORT
    viewer: bool = False  #: the executor opens MuJoCo's viewer


@dataclass(frozen=True)
class ServiceSpec:
    """One service: its ``safemimic`` subcommand, liveliness token, pip extra and role arguments."""

    name: str
    token: str
    extra: str
    role_args: Callable[[Site], list[str]]


SERVICES: tuple[ServiceSpec, ...] = (
    # MuJoCo simulation of the G1 following JointCommand, publishing JointState
    ServiceSpec("executor", "executor", "sim", lambda site: ["--viewer"] if site.viewer else []),
    # the CBF-QP safety layer at 500 Hz: HumanState → JointCommand
    ServiceSpec("safety", "safety", "safety", lambda site: []),
    # a recorded person, looped: skeleton → filter → θ + human capsules → HumanState
    ServiceSpec("perception", "perception", "perception",
                lambda site: ["--recording", site.skeleton, "--placement", site.placement, "--loop"]),
    # REST config API and web console
    ServiceSpec("config-api", "config_api", "api",
                lambda site: ["--host", site.api_host, "--port", str(site.api_port), "--store", site.api_store]),
)
SERVICE_BY_NAME: dict[str, ServiceSpec] = {spec.name: spec for spec in SERVICES}


def client_flags(router: str) -> list[str]:
    """The bus flags of a Zenoh client of ``router`` (explicit endpoint, no multicast scouting)."""
    return ["--mode", "client", "--connect", router, "--no-multicast"]


def command(name: str, site: Site, bus_flags: list[str] | None = None) -> list[str]:
    """The command line of service ``name`` at ``site`` (starts with ``safemimic``).

    ``bus_flags`` replaces the default client-of-the-router flags (e.g. peers connected directly).
    """
    spec = SERVICE_BY_NAME[name]
    flags = client_flags(site.router) if bus_flags is None else bus_flags
    return ["safemimic", spec.name, *flags, *spec.role_args(site)]


def health_command(name: str, router: str) -> list[str]:
    """The command that exits 0 while service ``name``'s liveliness token is present."""
    return ["safemimic", "health", SERVICE_BY_NAME[name].token, *client_flags(router)]


def router_command(listen: str) -> list[str]:
    """The local router (zenoh-python in router mode) listening on ``listen``."""
    return ["safemimic", "router", "--listen", listen, "--no-multicast"]


def write_paper_scenarios(path: str | Path, fps: float = 30.0) -> Path:
    """Write the paper's two scenarios, one period each, back to back, as one recording.

    Both start and end in the same neutral pose at the same side-by-side placement, so the
    recording loops seamlessly (``safemimic perception --recording FILE --loop``).
    """
    conf = PerceptionConfig()
    body = Body(shoulder_width=conf.scenario_shoulder_width)
    parts = []
    for name in PAPER_SCENARIOS:
        scenario = get_scenario(name)
        placement = parse_placement("side-by-side", conf, auto=scenario.placement)
        parts.append(scenario_recording(scenario, scenario.period, fps, placement, body))
    xyz = np.concatenate([part.xyz for part in parts])
    recording = Recording(
        t=np.arange(len(xyz)) / fps, xyz=xyz, conf=np.concatenate([part.conf for part in parts]), fps=fps,
        source="safemimic: the paper's scenarios back to back: " + " | ".join(part.source for part in parts),
    )
    return write_recording(path, recording)


# docker compose ------------------------------------------------------------------------------
COMPOSE_SITE = Site(
    router=f"tcp/router:{ROUTER_PORT}", api_store="/state/config.json", skeleton=IMAGE_SKELETON, api_host="0.0.0.0",
)
_HEADER = """\
# safemimic on docker compose: the official Zenoh router and the four services (DESIGN §1).
# GENERATED by `python -m safemimic.stack compose` from safemimic/stack.py, the table the local
# launcher (`safemimic demo`) uses too: edit the table, not this file (a test compares them).
#
#   docker compose -f deploy/docker-compose.yml up --build
#   console: http://localhost:8080/  (writes need $SAFEMIMIC_API_TOKEN, else the token the
#   config-api prints once in its log); a perception box elsewhere connects to tcp/THIS_HOST:7447.
"""


def _healthcheck(test: list[str], start_period: str) -> dict[str, Any]:
    return {"test": test, "interval": "10s", "timeout": "5s", "retries": 3, "start_period": start_period}


def compose_spec() -> dict[str, Any]:
    """The docker compose file as a mapping (router + four services from :data:`SERVICES`)."""
    lease_ms = load_config(DEFAULT_CONFIG_PATH, environ={}).bus.lease_ms  # zenohd's own default is 10 s
    router = {
        "image": ZENOH_IMAGE,
        # the services' lease (bus.lease_ms): a silent host is noticed as fast as the local router does
        "command": ["--listen", f"tcp/0.0.0.0:{ROUTER_PORT}", "--no-multicast-scouting",
                    "--cfg", f"transport/link/tx/lease:{lease_ms}"],
        "ports": [f"{ROUTER_PORT}:{ROUTER_PORT}/tcp"],
        "restart": "unless-stopped",
        # the image is Alpine: busybox nc checks that zenohd accepts connections
        "healthcheck": _healthcheck(["CMD-SHELL", f"nc -z 127.0.0.1 {ROUTER_PORT} || exit 1"], "5s"),
    }
    services: dict[str, Any] = {"router": router}
    for spec in SERVICES:
        service: dict[str, Any] = {
            "build": {"context": "..", "dockerfile": "deploy/Dockerfile", "args": {"EXTRAS": spec.extra}},
            "image": f"safemimic:{spec.extra}",
            "command": command(spec.name, COMPOSE_SITE),
            "environment": {"SAFEMIMIC_CONFIG": f"{IMAGE_ROOT}/config/default.yaml"},
            "volumes": [f"../config:{IMAGE_ROOT}/config:ro"],
            # started, not healthy: a client that cannot reach the router exits and is restarted, so a
            # router health check that misjudges never blocks the stack
            "depends_on": {"router": {"condition": "service_started"}},
            "restart": "unless-stopped",
            "healthcheck": _healthcheck(["CMD", *health_command(spec.name, COMPOSE_SITE.router)], "60s"),
        }
        if spec.name == "safety":
            service["cap_add"] = ["SYS_NICE"]  # SCHED_FIFO for the 500 Hz loop (falls back without it)
        if spec.name == "config-api":
            service["environment"]["SAFEMIMIC_API_TOKEN"] = "${SAFEMIMIC_API_TOKEN:-}"
            service["ports"] = [f"{API_PORT}:{COMPOSE_SITE.api_port}/tcp"]
            service["volumes"].append("api-state:/state")
        services[spec.name] = service
    return {"name": "safemimic", "services": services, "volumes": {"api-state": {}}}


def compose_text() -> str:
    """The text of ``deploy/docker-compose.yml``."""
    return _HEADER + yaml.safe_dump(compose_spec(), sort_keys=False, width=120)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m safemimic.stack", description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="action", required=True)
    compose = sub.add_parser("compose", help=f"write the docker compose file (default {COMPOSE_PATH})")
    compose.add_argument("out", nargs="?", type=Path, default=COMPOSE_PATH)
    scenarios = sub.add_parser("paper-scenarios", help="write the paper's two scenarios as one looping recording")
    scenarios.add_argument("out", type=Path)
    args = parser.parse_args(argv)
    if args.action == "compose":
        args.out.write_text(compose_text())
    else:
        write_paper_scenarios(args.out)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
