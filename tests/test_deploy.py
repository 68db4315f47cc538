"""docker compose and the local launcher come from one table (safemimic/stack.py) and agree."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

import numpy as np
import pytest
import yaml

from safemimic.acl import ROUTER_IDENTITY, access_control, identities
from safemimic.stack import (
    API_PORT,
    COMPOSE_PATH,
    COMPOSE_SITE,
    IMAGE_UID,
    PAPER_SCENARIOS,
    ROUTER_CONFIG_PATH,
    ROUTER_PORT,
    SERVICES,
    Site,
    command,
    compose_text,
    main,
    router_config_text,
)
from services.perception.scenarios import get_scenario
from shared.bus import Bus
from shared.config import BusConfig
from shared.skeleton import read_recording
from tests.support.processes import free_port
from tests.support.team import REPO

DOCKERFILE = REPO / "deploy" / "Dockerfile"
LOCAL = Site(router="tls/127.0.0.1:17447", api_store="/tmp/x/config.json", skeleton="/tmp/x/p.npz", api_port=18080,
             certs="/tmp/x/certs")


def _compose() -> dict:
    return yaml.safe_load(COMPOSE_PATH.read_text())


def _generic(argv: list[str], site: Site) -> list[str]:
    """A command line with the site's own values replaced by their names."""
    values = {site.router: "<router>", site.api_store: "<store>", site.skeleton: "<skeleton>",
              site.api_host: "<api_host>", str(site.api_port): "<api_port>", site.certs: "<certs>"}
    return [values.get(arg, arg) for arg in argv]


def test_committed_compose_file_is_what_the_table_generates() -> None:
    assert COMPOSE_PATH.read_text() == compose_text(), "run `python -m safemimic.stack compose` and commit the result"
    assert ROUTER_CONFIG_PATH.read_text() == router_config_text(), "run `python -m safemimic.stack compose` and commit"


def test_compose_router_is_secure_with_the_generated_access_control() -> None:
    """zenohd listens on tls only, with mutual TLS, the services' lease and the table's access control."""
    text = ROUTER_CONFIG_PATH.read_text()
    conf = json.loads(text[text.index("{"):])  # after the two comment lines
    assert conf["listen"]["endpoints"] == [f"tls/0.0.0.0:{ROUTER_PORT}"]
    link = conf["transport"]["link"]
    assert link["protocols"] == ["tls"] and link["tls"]["enable_mtls"] is True
    assert link["tx"]["lease"] == 500
    assert link["tls"]["listen_certificate"] == f"/certs/{ROUTER_IDENTITY}.pem"
    assert conf["access_control"] == access_control() and conf["access_control"]["default_permission"] == "deny"


def test_each_compose_service_mounts_only_its_own_certificates() -> None:
    compose = _compose()
    services = compose["services"]
    certs = services["certs"]
    names = {ROUTER_IDENTITY, *(identity.name for identity in identities())}
    assert certs["restart"] == "no" and certs["command"][:4] == ["safemimic", "certs", "stack", "/certs"]
    assert f"{IMAGE_UID}:{IMAGE_UID}" in certs["command"] and "--split" in certs["command"]
    assert set(certs["volumes"]) == {"certs-ca:/certs", *(f"certs-{name}:/certs/{name}" for name in names)}
    assert {f"certs-{name}" for name in names} | {"certs-ca"} <= set(compose["volumes"])
    for name, service in services.items():
        if name == "certs":
            continue
        identity = ROUTER_IDENTITY if name == "router" else next(s.token for s in SERVICES if s.name == name)
        mounted = [volume for volume in service["volumes"] if volume.startswith("certs-")]
        assert mounted == [f"certs-{identity}:/certs:ro"], name  # never the CA key, never another service's key
        assert service["depends_on"]["certs"]["condition"] == "service_completed_successfully"
        if name != "router":
            assert service["environment"]["SAFEMIMIC__BUS__TLS__IDENTITY"] == identity
            assert service["healthcheck"]["test"][-2:] == ["--certs", "/certs"]
    assert f"--uid {IMAGE_UID}" in DOCKERFILE.read_text()


def test_table_names_the_services_as_they_name_themselves() -> None:
    """Subcommands exist; liveliness tokens are the ones the services declare."""
    from safemimic.cli import SUBCOMMANDS
    from services.config_api.link import SERVICE_NAME as API
    from services.executor.service import SERVICE_NAME as EXECUTOR
    from services.perception.service import SERVICE_NAME as PERCEPTION
    from services.safety.service import HUMAN_SOURCE_SERVICE
    from services.safety.service import SERVICE_NAME as SAFETY

    assert all(spec.name in SUBCOMMANDS for spec in SERVICES) and "health" in SUBCOMMANDS
    assert [spec.token for spec in SERVICES] == [EXECUTOR, SAFETY, PERCEPTION, API]
    assert HUMAN_SOURCE_SERVICE == PERCEPTION  # the token whose loss makes the human stale


def test_compose_and_local_launcher_run_the_same_command_lines() -> None:
    services = _compose()["services"]
    assert set(services) == {"certs", "router", *(spec.name for spec in SERVICES)}
    for spec in SERVICES:
        compose_argv = services[spec.name]["command"]
        assert compose_argv[:2] == ["safemimic", spec.name]
        assert compose_argv[2:6] == ["--mode", "client", "--connect", f"tls/router:{ROUTER_PORT}"]
        assert compose_argv[7:9] == ["--certs", "/certs"]
        assert _generic(compose_argv, COMPOSE_SITE) == _generic(command(spec.name, LOCAL), LOCAL)


def test_compose_file_has_router_health_checks_restart_policy_config_and_console() -> None:
    compose = _compose()
    services = compose["services"]
    router = services["router"]
    assert router["image"].startswith("eclipse/zenoh:1.")  # the official router, never a home-made broker
    assert f"{ROUTER_PORT}:{ROUTER_PORT}/tcp" in router["ports"]  # hosts elsewhere (an edge box) connect here
    assert router["command"] == ["--config", "/etc/zenoh/router.json5"]
    assert f"./{ROUTER_CONFIG_PATH.name}:/etc/zenoh/router.json5:ro" in router["volumes"]
    pyproject = tomllib.loads((REPO / "pyproject.toml").read_text())
    extras = pyproject["project"]["optional-dependencies"]
    for name, service in services.items():
        if name == "certs":  # the one-shot service that makes the certificates
            continue
        assert service["restart"] == "unless-stopped"
        assert service["healthcheck"]["test"][0] in ("CMD", "CMD-SHELL")
        if name == "router":
            continue
        spec = next(spec for spec in SERVICES if spec.name == name)
        assert service["build"]["args"]["EXTRAS"] == spec.extra and spec.extra in extras
        assert service["healthcheck"]["test"][1:4] == ["safemimic", "health", spec.token]
        assert "../config:/opt/safemimic/config:ro" in service["volumes"]
        assert (COMPOSE_PATH.parent / "../config/default.yaml").resolve() == REPO / "config" / "default.yaml"
    assert f"{API_PORT}:{API_PORT}/tcp" in services["config-api"]["ports"]
    assert "api-state:/state" in services["config-api"]["volumes"] and "api-state" in compose["volumes"]


def test_dockerfile_installs_the_role_extra_and_bakes_the_scenarios() -> None:
    text = DOCKERFILE.read_text()
    assert "ARG EXTRAS" in text and 'pip install -e ".[${EXTRAS}]"' in text
    assert "python -m safemimic.stack paper-scenarios skeletons/paper-scenarios.npz" in text
    assert COMPOSE_SITE.skeleton == "/opt/safemimic/skeletons/paper-scenarios.npz" and "WORKDIR /opt/safemimic" in text
    for folder in ("safemimic", "shared", "services", "config"):
        assert f"COPY {folder} {folder}" in text
    assert "USER safemimic" in text


def _docker_compose() -> list[str] | None:
    """The docker compose command line here, or None."""
    docker, standalone = shutil.which("docker"), shutil.which("docker-compose")
    if docker and subprocess.run([docker, "compose", "version"], capture_output=True).returncode == 0:
        return [docker, "compose"]
    return [standalone] if standalone else None


def test_docker_compose_config_validates() -> None:
    compose = _docker_compose()
    if compose is None:
        reason = ("the docker client is installed but not its compose plugin" if shutil.which("docker")
                  else "no docker client on this machine")
        pytest.skip(f"{reason}: `docker compose config` cannot run here (the file is checked against the table above)")
    result = subprocess.run([*compose, "-f", str(COMPOSE_PATH), "config", "--format", "json"],
                            capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    resolved = json.loads(result.stdout)["services"]
    for spec in SERVICES:
        assert resolved[spec.name]["command"] == command(spec.name, COMPOSE_SITE)


def test_paper_scenarios_recording_loops_seamlessly(tmp_path: Path) -> None:
    assert main(["paper-scenarios", str(tmp_path / "p.npz")]) == 0
    recording = read_recording(tmp_path / "p.npz")
    assert recording.fps == 30.0
    assert len(recording) == round(sum(get_scenario(name).period for name in PAPER_SCENARIOS) * 30)
    # the end flows into the start: the last frame is one frame from the first, not a jump
    assert np.abs(recording.xyz[-1] - recording.xyz[0]).max() < 0.01
    assert np.isfinite(recording.xyz).all() and recording.valid.all()


@pytest.mark.integration
def test_health_command_reports_liveliness(spawn) -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    spawn("-m", "safemimic.cli", "router", "--listen", endpoint, "--no-multicast").wait_for(lambda line: "listening" in line)
    flags = ["--mode", "client", "--connect", endpoint, "--no-multicast"]

    def health(*names: str) -> tuple[int, dict]:
        result = subprocess.run([sys.executable, "-m", "safemimic.cli", "health", *names, *flags],
                                capture_output=True, text=True, timeout=30, cwd=REPO)
        return result.returncode, json.loads(result.stdout)

    bus_conf = BusConfig(mode="client", connect=[endpoint], multicast_scouting=False)
    with Bus(bus_conf, "g1", "safety") as bus, Bus(bus_conf, "g1", "config_api") as api:
        bus.declare_alive()
        api.declare_alive()
        assert health("safety") == (0, {"alive": ["config_api", "safety"], "missing": []})
        assert health("safety", "executor") == (1, {"alive": ["config_api", "safety"], "missing": ["executor"]})
        assert health("config-api") == health("config_api") == (0, {"alive": ["config_api", "safety"], "missing": []})
    assert health("safety")[0] == 1  # the token went with the session
    unreachable = subprocess.run(
        [sys.executable, "-m", "safemimic.cli", "health", "--mode", "client", "--connect", f"tcp/127.0.0.1:{free_port()}"],
        capture_output=True, text=True, timeout=30, cwd=REPO,
    )
    assert unreachable.returncode == 2 and "cannot open the bus" in unreachable.stdout
