"""The stack's service command lines: the one table the local launcher and docker compose share.

:data:`SERVICES` lists the four services (executor, safety, perception, config API) with the pip
extra each needs and its role arguments; :func:`command` turns one into the exact ``safemimic``
command line for a :class:`Site` (where the router is, where the console listens, which skeleton
perception plays). ``safemimic demo`` runs these command lines as local processes;
``deploy/docker-compose.yml`` is generated from the same table (``python -m safemimic.stack
compose``) and a test checks that the committed file is what the table generates.

The router is not in the table's command lines: locally it is ``safemimic router`` (zenoh-python in
router mode), in compose the official ``eclipse/zenoh`` image (architecture §1); both listen on
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
from shared.body import Body
from shared.config import DEFAULT_CONFIG_PATH, PerceptionConfig, load_config
from shared.realtime import DEFAULT_RT_PRIORITY
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
#: zenohd's configuration in compose (mutual TLS + the generated access control), beside the compose file.
ROUTER_CONFIG_PATH = COMPOSE_PATH.parent / "zenoh-router.json5"
#: Where a container finds its own certificates (its own volume, read-only).
CERTS_MOUNT = "/certs"
#: The image's unprivileged user (deploy/Dockerfile): owner of the certificates the one-shot service writes.
IMAGE_UID = 10001


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
    #: folder of the certificates (``safemimic certs``): every command line gets ``--certs`` and the
    #: router endpoint is ``tls/...``; None: the open development bus (``--insecure``)
    certs: str | None = None


@dataclass(frozen=True)
class BusRights:
    """What one identity may do on the bus: the router's access control is generated from these
    (:mod:`safemimic.acl`, default deny), so a session can do nothing its row does not name.

    ``puts``: topics it publishes; ``subscribes``: topics it receives; ``token``: it declares its own
    liveliness token ``alive/<identity>`` (no other); ``watches_alive``: it follows everyone's
    tokens; ``queries_alive``: it asks which tokens exist (``safemimic health``).
    """

    puts: tuple[str, ...] = ()
    subscribes: tuple[str, ...] = ()
    token: bool = False
    watches_alive: bool = False
    queries_alive: bool = False


@dataclass(frozen=True)
class ServiceSpec:
    """One service: its ``safemimic`` subcommand, liveliness token (= certificate name), pip extra,
    role arguments and what it may do on the bus."""

    name: str
    token: str
    extra: str
    role_args: Callable[[Site], list[str]]
    rights: BusRights


#: Every service may also ask which liveliness tokens exist (read-only): its container's health
#: check (``safemimic health``) runs with the service's own certificate.
SERVICES: tuple[ServiceSpec, ...] = (
    # MuJoCo simulation of the G1 following JointCommand, publishing JointState
    ServiceSpec("executor", "executor", "sim", lambda site: ["--viewer"] if site.viewer else [],
                BusRights(puts=("robot/joint_state",), subscribes=("robot/command", "human/state"), token=True,
                          queries_alive=True)),
    # the CBF-QP safety layer at 500 Hz: HumanState → JointCommand
    ServiceSpec("safety", "safety", "safety", lambda site: [],
                BusRights(puts=("robot/command", "safety/status"),
                          subscribes=("human/state", "robot/joint_state", "config"), token=True, watches_alive=True,
                          queries_alive=True)),
    # a recorded person, looped: skeleton → filter → θ + human capsules → HumanState
    ServiceSpec("perception", "perception", "perception",
                lambda site: ["--recording", site.skeleton, "--placement", site.placement, "--loop"],
                BusRights(puts=("human/state",), subscribes=("config",), token=True, queries_alive=True)),
    # REST config API and web console
    ServiceSpec("config-api", "config_api", "api",
                lambda site: ["--host", site.api_host, "--port", str(site.api_port), "--store", site.api_store],
                BusRights(puts=("config",), subscribes=("human/state", "safety/status"), token=True, watches_alive=True,
                          queries_alive=True)),
)
SERVICE_BY_NAME: dict[str, ServiceSpec] = {spec.name: spec for spec in SERVICES}
#: Topics an observer may read: everything but nothing to write.
_OBSERVED = ("human/state", "robot/joint_state", "robot/command", "safety/status", "config")
#: The other identities that hold a certificate: tools that only look (certificate name → rights).
#: ``demo`` is the launcher's own watching session, ``health`` the liveliness check (compose health
#: checks, ``safemimic health``), ``viewer`` any observer (a visualiser, the tests' and benchmarks' probes).
TOOLS: dict[str, BusRights] = {
    "demo": BusRights(subscribes=_OBSERVED, watches_alive=True),
    "health": BusRights(queries_alive=True),
    "viewer": BusRights(subscribes=_OBSERVED, watches_alive=True),
}


def security_flags(certs: str | None) -> list[str]:
    """``--certs DIR`` (mutual TLS with the identity's own certificate from DIR), or ``--insecure``."""
    return ["--certs", certs] if certs is not None else ["--insecure"]


def client_flags(router: str, certs: str | None = None) -> list[str]:
    """The bus flags of a Zenoh client of ``router`` (explicit endpoint, no multicast scouting)."""
    return ["--mode", "client", "--connect", router, "--no-multicast", *security_flags(certs)]


def command(name: str, site: Site, bus_flags: list[str] | None = None) -> list[str]:
    """The command line of service ``name`` at ``site`` (starts with ``safemimic``).

    ``bus_flags`` replaces the default client-of-the-router flags (e.g. peers connected directly).
    """
    spec = SERVICE_BY_NAME[name]
    flags = client_flags(site.router, site.certs) if bus_flags is None else bus_flags
    return ["safemimic", spec.name, *flags, *spec.role_args(site)]


def viewer_command(site: Site, web_port: int, grpc_port: int) -> list[str]:
    """The live viewer (``safemimic viewer``, the ``viewer`` identity: subscriptions only), serving
    Rerun's web viewer on ``web_port`` (its data on ``grpc_port``). Not in :data:`SERVICES`: it
    holds no liveliness token and nothing depends on it."""
    return ["safemimic", "viewer", *client_flags(site.router, site.certs), "--host", site.api_host,
            "--web-port", str(web_port), "--grpc-port", str(grpc_port)]


def health_command(name: str, router: str, certs: str | None = None) -> list[str]:
    """The command that exits 0 while service ``name``'s liveliness token is present."""
    return ["safemimic", "health", SERVICE_BY_NAME[name].token, *client_flags(router, certs)]


def router_command(listen: str, certs: str | None = None) -> list[str]:
    """The local router (zenoh-python in router mode) listening on ``listen``; with ``certs`` it
    authenticates every session and enforces ``certs/access_control.json5`` (:mod:`safemimic.acl`)."""
    return ["safemimic", "router", "--listen", listen, "--no-multicast", *security_flags(certs)]


def router_endpoint(host: str, port: int, secure: bool) -> str:
    """``tls/HOST:PORT`` on a secure bus, else ``tcp/HOST:PORT``."""
    return f"{'tls' if secure else 'tcp'}/{host}:{port}"


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
    router=f"tls/router:{ROUTER_PORT}", api_store="/state/config.json", skeleton=IMAGE_SKELETON, api_host="0.0.0.0",
    certs=CERTS_MOUNT,
)
#: The router's certificate names ``router`` (its name on the compose network) and this host's name or
#: address, ``$SAFEMIMIC_ROUTER_HOST`` (default localhost), for boxes that connect from elsewhere.
ROUTER_HOST_ENV = "SAFEMIMIC_ROUTER_HOST"
_HEADER = """\
# safemimic on docker compose: the official Zenoh router and the four services (architecture §1).
# GENERATED by `python -m safemimic.stack compose` from safemimic/stack.py, the table the local
# launcher (`safemimic demo`) uses too: edit the table, not this file (a test compares them).
#
#   docker compose -f deploy/docker-compose.yml up --build
#   console: http://localhost:8080/  (reads and writes need $SAFEMIMIC_API_TOKEN through the published
#   port, which is not loopback for the container, else the token the
#   config-api prints once in its log); a perception box elsewhere connects to tls/THIS_HOST:7447
#   with its own certificate (README "Security"; SAFEMIMIC_ROUTER_HOST=THIS_HOST names the router).
# The one-shot `certs` service makes the CA and one certificate per identity once, into the
# `certs-ca` volume; each service mounts only its own `certs-<identity>` volume (CA certificate, its
# certificate and key) at /certs. zenohd reads deploy/zenoh-router.json5 (TLS + access control).
"""


def _healthcheck(test: list[str], start_period: str) -> dict[str, Any]:
    return {"test": test, "interval": "10s", "timeout": "5s", "retries": 3, "start_period": start_period}


def compose_spec() -> dict[str, Any]:
    """The docker compose file as a mapping (router + four services from :data:`SERVICES`)."""
    from safemimic.acl import ROUTER_IDENTITY, identities

    names = [ROUTER_IDENTITY, *(identity.name for identity in identities())]
    certs = {
        "build": {"context": "..", "dockerfile": "deploy/Dockerfile", "args": {"EXTRAS": "perception"}},
        "image": "safemimic:perception",
        # once: existing certificates are kept, so a restart never changes a key
        "command": ["safemimic", "certs", "stack", CERTS_MOUNT, "--split", "--owner", f"{IMAGE_UID}:{IMAGE_UID}",
                    "--host", "router", "--host", f"${{{ROUTER_HOST_ENV}:-localhost}}"],
        "user": "root",
        "volumes": [f"certs-ca:{CERTS_MOUNT}", *(f"certs-{name}:{CERTS_MOUNT}/{name}" for name in names)],
        "restart": "no",
    }
    router = {
        "image": ZENOH_IMAGE,
        # TLS, the access control and the services' lease (bus.lease_ms) are in zenoh-router.json5
        "command": ["--config", "/etc/zenoh/router.json5"],
        "volumes": [f"./{ROUTER_CONFIG_PATH.name}:/etc/zenoh/router.json5:ro", f"certs-{ROUTER_IDENTITY}:{CERTS_MOUNT}:ro"],
        "ports": [f"{ROUTER_PORT}:{ROUTER_PORT}/tcp"],
        "depends_on": {"certs": {"condition": "service_completed_successfully"}},
        "restart": "unless-stopped",
        # the image is Alpine: busybox nc checks that zenohd accepts connections
        "healthcheck": _healthcheck(["CMD-SHELL", f"nc -z 127.0.0.1 {ROUTER_PORT} || exit 1"], "5s"),
    }
    services: dict[str, Any] = {"certs": certs, "router": router}
    for spec in SERVICES:
        service: dict[str, Any] = {
            "build": {"context": "..", "dockerfile": "deploy/Dockerfile", "args": {"EXTRAS": spec.extra}},
            "image": f"safemimic:{spec.extra}",
            "command": command(spec.name, COMPOSE_SITE),
            # the health check runs in this container, with this service's own certificate
            "environment": {"SAFEMIMIC_CONFIG": f"{IMAGE_ROOT}/config/default.yaml",
                            "SAFEMIMIC__BUS__TLS__IDENTITY": spec.token},
            "volumes": [f"../config:{IMAGE_ROOT}/config:ro", f"certs-{spec.token}:{CERTS_MOUNT}:ro"],
            # started, not healthy: a client that cannot reach the router exits and is restarted, so a
            # router health check that misjudges never blocks the stack
            "depends_on": {"router": {"condition": "service_started"},
                           "certs": {"condition": "service_completed_successfully"}},
            "restart": "unless-stopped",
            "healthcheck": _healthcheck(["CMD", *health_command(spec.name, COMPOSE_SITE.router, COMPOSE_SITE.certs)],
                                        "60s"),
        }
        if spec.name == "safety":
            # SCHED_FIFO for the 500 Hz loop (falls back without it): the image's user is not root, and
            # Docker gives capabilities to root only (moby #50083), so the RLIMIT_RTPRIO that lets any
            # user take real-time priorities up to it is what makes it work; cap_add for a root user
            service["cap_add"] = ["SYS_NICE"]
            service["ulimits"] = {"rtprio": DEFAULT_RT_PRIORITY}
        if spec.name == "config-api":
            service["environment"]["SAFEMIMIC_API_TOKEN"] = "${SAFEMIMIC_API_TOKEN:-}"
            service["ports"] = [f"{API_PORT}:{COMPOSE_SITE.api_port}/tcp"]
            service["volumes"].append("api-state:/state")
        services[spec.name] = service
    volumes = {"api-state": {}, "certs-ca": {}, **{f"certs-{name}": {} for name in names}}
    return {"name": "safemimic", "services": services, "volumes": volumes}


def compose_text() -> str:
    """The text of ``deploy/docker-compose.yml``."""
    return _HEADER + yaml.safe_dump(compose_spec(), sort_keys=False, width=120)


def router_config_text() -> str:
    """zenohd's configuration in compose (``deploy/zenoh-router.json5``): listen on tls only, mutual
    TLS with the router's certificate from its volume, the services' lease, the access control."""
    import json

    from safemimic.acl import ROUTER_IDENTITY, access_control

    lease_ms = load_config(DEFAULT_CONFIG_PATH, environ={}).bus.lease_ms  # zenohd's own default is 10 s
    own = f"{CERTS_MOUNT}/{ROUTER_IDENTITY}"
    conf = {
        "mode": "router",
        "listen": {"endpoints": [f"tls/0.0.0.0:{ROUTER_PORT}"]},
        "scouting": {"multicast": {"enabled": False}},
        "transport": {"link": {
            "protocols": ["tls"],
            "tx": {"lease": lease_ms},
            "tls": {"root_ca_certificate": f"{CERTS_MOUNT}/ca.pem", "enable_mtls": True,
                    "listen_private_key": f"{own}.key", "listen_certificate": f"{own}.pem",
                    "connect_private_key": f"{own}.key", "connect_certificate": f"{own}.pem"},
        }},
        "access_control": access_control(),
    }
    return ("// zenohd in docker compose. GENERATED by `python -m safemimic.stack compose` from safemimic/stack.py\n"
            "// (the access control: safemimic.acl from the service table): edit the table, not this file.\n"
            + json.dumps(conf, indent=2) + "\n")


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
        router_config = args.out.parent / ROUTER_CONFIG_PATH.name
        router_config.write_text(router_config_text())
        print(f"wrote {router_config}")
    else:
        write_paper_scenarios(args.out)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
