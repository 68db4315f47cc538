"""Nobody else drives the robot or switches its safety off.

Real Zenoh on loopback through a real ``safemimic router`` process with mutual TLS and the access
control generated from the service table: sessions without a certificate of the deployment's CA
cannot join; an identity can put only its own keys (perception's ``config`` and ``robot/command``
never arrive), declare only its own liveliness token; observers only look; and the real safety
and executor services ignore a forged configuration and forged commands while obeying the same
messages from the identities allowed to send them.
"""

from __future__ import annotations

import json
import os
import stat
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import zenoh
from cryptography import x509
from cryptography.x509.oid import NameOID

from safemimic.acl import ROUTER_IDENTITY, access_control, identities
from safemimic.certs import init_ca, issue, make_stack
from safemimic.stack import SERVICES, TOOLS, Site, command, router_command
from shared.bus import Bus
from shared.config import BusConfig, ConfigError, TlsConfig, load_config
from shared.messages import ConfigUpdate, JointCommand, JointState, SafetyMode, SafetyStatus
from shared.tls import tls_files, zenoh_tls
from tests.support.bus import BusRecorder
from tests.support.messages import one_of_every_message
from tests.support.processes import free_port
from tests.support.team import REPO

#: How long a message that is going to arrive takes at most here (loopback, a loaded 2-core machine).
SETTLE_S = 1.0


def _cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "safemimic.cli", *args], capture_output=True, text=True,
                          timeout=60, cwd=REPO)


def _common_name(path: Path) -> str:
    cert = x509.load_pem_x509_certificate(path.read_bytes())
    return cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)[0].value


# certificates ------------------------------------------------------------------------------------
def test_certs_init_and_issue_write_the_files_of_the_contract(tmp_path: Path) -> None:
    ca_dir = tmp_path / "ca"
    result = _cli("certs", "init", str(ca_dir))
    assert result.returncode == 0, result.stderr
    assert (ca_dir / "ca.pem").exists() and stat.S_IMODE((ca_dir / "ca.key").stat().st_mode) == 0o600
    ca = x509.load_pem_x509_certificate((ca_dir / "ca.pem").read_bytes())
    assert ca.extensions.get_extension_for_class(x509.BasicConstraints).value.ca is True

    result = _cli("certs", "issue", "perception", "--dir", str(ca_dir))
    assert result.returncode == 0, result.stderr
    assert _common_name(ca_dir / "perception.pem") == "perception"
    assert stat.S_IMODE((ca_dir / "perception.key").stat().st_mode) == 0o600
    x509.load_pem_x509_certificate((ca_dir / "perception.pem").read_bytes()).verify_directly_issued_by(ca)

    again = _cli("certs", "init", str(ca_dir))  # would invalidate every certificate already issued
    assert again.returncode == 2 and "already exists" in again.stderr
    orphan = _cli("certs", "issue", "safety", "--dir", str(tmp_path / "empty"))
    assert orphan.returncode == 2 and "certs init" in orphan.stderr
    bad = _cli("certs", "issue", "../evil", "--dir", str(ca_dir))
    assert bad.returncode == 2 and "bad identity name" in bad.stderr


def test_certs_stack_makes_every_identity_once_and_splits_them(tmp_path: Path) -> None:
    names = make_stack(tmp_path, router_hosts=["127.0.0.1", "robot.local"], do_split=True)
    assert names == [ROUTER_IDENTITY, "executor", "safety", "perception", "config_api", *TOOLS]
    router = x509.load_pem_x509_certificate((tmp_path / "router.pem").read_bytes())
    san = router.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert set(map(str, san.get_values_for_type(x509.IPAddress))) == {"127.0.0.1"}
    assert set(san.get_values_for_type(x509.DNSName)) == {"router", "robot.local"}
    for name in names:  # each identity's folder: the CA certificate and its own pair, nothing else
        assert sorted(p.name for p in (tmp_path / name).iterdir() if p.suffix != ".json5") == \
            sorted(["ca.pem", f"{name}.pem", f"{name}.key"])
    key_before = (tmp_path / "safety.key").read_bytes()
    make_stack(tmp_path)  # idempotent: a restarted one-shot container changes no key
    assert (tmp_path / "safety.key").read_bytes() == key_before


def test_tls_settings_give_clear_errors(tmp_path: Path) -> None:
    make_stack(tmp_path / "ours")
    init_ca(tmp_path / "theirs")
    issue("safety", tmp_path / "theirs")
    with pytest.raises(ConfigError, match="not issued by the CA"):
        tls_files(TlsConfig(ca=str(tmp_path / "ours/ca.pem"), certificate=str(tmp_path / "theirs/safety.pem"),
                            private_key=str(tmp_path / "theirs/safety.key")), "safety")
    with pytest.raises(ConfigError, match=r"certs issue nobody --dir"):
        tls_files(TlsConfig(dir=str(tmp_path / "ours")), "nobody")
    with pytest.raises(ConfigError, match="mode client"):
        load_config(overrides={"bus": {"tls": {"dir": str(tmp_path)}, "mode": "peer"}}, environ={})
    with pytest.raises(ConfigError, match="tls/HOST:PORT"):
        load_config(overrides={"bus": {"tls": {"dir": str(tmp_path)}, "mode": "client",
                                       "connect": ["tcp/127.0.0.1:7447"]}}, environ={})
    with pytest.raises(ConfigError, match="needs dir"):
        load_config(overrides={"bus": {"tls": {"identity": "safety"}}}, environ={})
    assert load_config(overrides={"bus": {"tls": None}}, environ={}).bus.tls is None  # --insecure
    (tmp_path / "ours" / "access_control.json5").unlink()
    router = _cli("router", "--listen", f"tls/127.0.0.1:{free_port()}", "--no-multicast", "--certs", str(tmp_path / "ours"))
    assert router.returncode == 2 and "access-control file" in router.stderr and "certs stack" in router.stderr
    peer = _cli("health", "--certs", str(tmp_path / "ours"))  # default.yaml's peer mode
    assert peer.returncode == 2 and "mode client" in peer.stderr


# the access control is the table ------------------------------------------------------------------
def _allowed(identity: str, message: str, flow: str) -> set[str]:
    acl = access_control()
    rules = {rule["id"]: rule for rule in acl["rules"]}
    policy = next(p for p in acl["policies"] if p["subjects"] == [identity])
    return {key for rule_id in policy["rules"] for key in rules[rule_id]["key_exprs"]
            if message in rules[rule_id]["messages"] and flow in rules[rule_id]["flows"]}


def test_access_control_lets_each_identity_put_only_its_own_keys() -> None:
    acl = access_control()
    assert acl["enabled"] is True and acl["default_permission"] == "deny"
    assert {s["id"]: s["cert_common_names"] for s in acl["subjects"]} == {i.name: [i.name] for i in identities()}
    owner = {"human/state": "perception", "robot/command": "safety", "safety/status": "safety",
             "robot/joint_state": "executor", "config": "config_api"}
    for identity in identities():
        puts = _allowed(identity.name, "put", "ingress")
        assert puts == {f"safemimic/*/{topic}" for topic, who in owner.items() if who == identity.name}
        tokens = _allowed(identity.name, "liveliness_token", "ingress")
        assert tokens == ({f"safemimic/*/alive/{identity.name}"} if identity.name in {s.token for s in SERVICES} else set())
        for message in ("delete", "declare_queryable", "query", "reply"):
            assert not _allowed(identity.name, message, "ingress") and not _allowed(identity.name, message, "egress")
    # the subscriptions are the ones the services make, nothing more
    assert _allowed("perception", "declare_subscriber", "ingress") == {"safemimic/*/config"}
    assert _allowed("executor", "declare_subscriber", "ingress") == {"safemimic/*/robot/command", "safemimic/*/human/state"}
    assert _allowed("health", "declare_subscriber", "ingress") == set()


# real sessions through a secure router -------------------------------------------------------------
@dataclass
class SecureRouter:
    certs: Path
    endpoint: str

    def bus(self, identity: str, service: str | None = None) -> Bus:
        conf = BusConfig(mode="client", connect=[self.endpoint], multicast_scouting=False,
                         tls=TlsConfig(dir=str(self.certs), identity=identity))
        return Bus(conf, "g1", service or identity)

    def site(self, tmp_path: Path) -> Site:
        return Site(router=self.endpoint, api_store=str(tmp_path / "config.json"), skeleton="", certs=str(self.certs))


@pytest.fixture
def secure_router(spawn, tmp_path: Path) -> Iterator[SecureRouter]:
    certs = tmp_path / "certs"
    make_stack(certs, router_hosts=["127.0.0.1"])
    endpoint = f"tls/127.0.0.1:{free_port()}"
    router = spawn("-m", "safemimic.cli", *router_command(endpoint, str(certs))[1:])
    line = router.wait_for(lambda line: "listening" in line, 30)
    assert "mutual TLS + access control" in line
    yield SecureRouter(certs, endpoint)


def _raw_client(endpoint: str, tls: dict) -> zenoh.Session:
    """A client session built by hand (no checks of ours): what an intruder would configure."""
    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("transport/link/tls", json.dumps(tls))
    return zenoh.open(conf)


@pytest.mark.integration
def test_a_session_without_a_certificate_of_our_ca_cannot_join(secure_router: SecureRouter, tmp_path: Path) -> None:
    ours = tls_files(TlsConfig(dir=str(secure_router.certs)), "perception")
    with _raw_client(secure_router.endpoint, zenoh_tls(ours, router=False)):  # the control: our own certificate joins
        pass
    with pytest.raises(zenoh.ZError):  # trusts the router, shows no certificate
        _raw_client(secure_router.endpoint, {"root_ca_certificate": str(ours.ca)})
    init_ca(tmp_path / "theirs")
    issue("perception", tmp_path / "theirs")  # the right name, the wrong CA
    theirs = {**zenoh_tls(ours, router=False), "connect_private_key": str(tmp_path / "theirs/perception.key"),
              "connect_certificate": str(tmp_path / "theirs/perception.pem")}
    with pytest.raises(zenoh.ZError):
        _raw_client(secure_router.endpoint, theirs)
    with pytest.raises(zenoh.ZError):  # plain tcp to the router's port
        _raw_client(secure_router.endpoint.replace("tls/", "tcp/"), {})
    with pytest.raises(ConfigError, match="not issued by the CA"):  # ours refuses before even trying
        Bus(BusConfig(mode="client", connect=[secure_router.endpoint], multicast_scouting=False,
                      tls=TlsConfig(ca=str(ours.ca), certificate=theirs["connect_certificate"],
                                    private_key=theirs["connect_private_key"])), "g1", "perception")


@pytest.mark.integration
def test_each_identity_puts_only_its_own_keys_and_declares_only_its_own_token(secure_router: SecureRouter) -> None:
    messages = one_of_every_message()
    with secure_router.bus("viewer") as viewer, secure_router.bus("perception") as perception, \
            secure_router.bus("health") as health, secure_router.bus("viewer", service="viewer2") as viewer2:
        inbox = BusRecorder(viewer, messages, alive=True)
        health_inbox = BusRecorder(health, ("human/state",))  # health may only ask for tokens
        publishers = {topic: perception.publisher(topic) for topic in messages}
        viewer_config = viewer2.publisher("config")  # another session: no local delivery
        perception.declare_alive("perception")
        perception.declare_alive("safety")  # a forged token
        time.sleep(SETTLE_S)
        for _ in range(5):
            for topic, message in messages.items():
                publishers[topic].put(message.model_copy())
            viewer_config.put(messages["config"].model_copy())
            time.sleep(0.02)
        deadline = time.monotonic() + SETTLE_S * 3
        while inbox.count("human/state") < 5 and time.monotonic() < deadline:
            time.sleep(0.05)
        time.sleep(SETTLE_S)  # anything forbidden would have arrived by now too
        assert inbox.count("human/state") == 5  # perception's own key passes
        for topic in ("config", "robot/command", "robot/joint_state", "safety/status"):
            assert inbox.count(topic) == 0, topic  # dropped at the router
        assert inbox.alive_tokens() == {"perception"}  # its own token, not the forged one
        assert health_inbox.count("human/state") == 0
        assert health.alive_services(1.0) == {"perception"}
        flags = ["--mode", "client", "--connect", secure_router.endpoint, "--no-multicast", "--certs", str(secure_router.certs)]
        result = _cli("health", "perception", *flags)  # the health certificate
        assert result.returncode == 0 and json.loads(result.stdout) == {"alive": ["perception"], "missing": []}, result
        as_service = subprocess.run(  # a compose health check: inside a service's container, its own certificate
            [sys.executable, "-m", "safemimic.cli", "health", "perception", "safety", *flags], capture_output=True,
            text=True, timeout=60, cwd=REPO, env={**os.environ, "SAFEMIMIC__BUS__TLS__IDENTITY": "executor"})
        assert as_service.returncode == 1 and json.loads(as_service.stdout)["missing"] == ["safety"], as_service


def _wait(predicate, timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout} s waiting for {what}")
        time.sleep(0.05)


@pytest.mark.integration
def test_forged_config_and_commands_from_perception_change_nothing(spawn, secure_router: SecureRouter,
                                                                   tmp_path: Path) -> None:
    """The issue's attack: a ConfigUpdate v999 without pair groups and direct commands, as perception."""
    site = secure_router.site(tmp_path)
    spawn("-m", "safemimic.cli", *command("executor", site)[1:])
    safety = spawn("-m", "safemimic.cli", *command("safety", site)[1:])
    with secure_router.bus("viewer") as viewer:
        inbox = BusRecorder(viewer, ("safety/status", "robot/joint_state"))
        _wait(lambda: inbox.count("safety/status") > 10 and inbox.count("robot/joint_state") > 10, 90, "the stack")
        before: SafetyStatus = inbox.last("safety/status")
        assert before.total_constraints > 0 and before.config_version == 0
        home = inbox.last("robot/joint_state").q_command
        rogue_q = home + 0.05
        whole = load_config(environ={}).model_dump(mode="json")
        whole["safety"]["enabled_pair_groups"] = []

        def attack(bus: Bus, version: int, seconds: float) -> int:
            """Forged config updates and 500 Hz commands for ``seconds``; the first index seen after."""
            config, commands = bus.publisher("config"), bus.publisher("robot/command")
            start = inbox.count("robot/joint_state")
            for _ in range(3):
                config.put(ConfigUpdate(stamp=time.monotonic(), version=version, changed=["safety.enabled_pair_groups"],
                                        config=whole))
            end = time.monotonic() + seconds
            while time.monotonic() < end:
                commands.put(JointCommand(stamp=time.monotonic(), q=rogue_q, dq=np.zeros(8), mode=SafetyMode.NOMINAL))
                time.sleep(0.002)
            time.sleep(SETTLE_S)
            return start

        def obeyed(start: int) -> int:
            states: list[JointState] = [state for _, state in inbox.timed("robot/joint_state")[start:]]
            return sum(bool(np.allclose(s.q_command, rogue_q, atol=1e-9)) for s in states)

        with secure_router.bus("perception", service="intruder") as intruder:
            start = attack(intruder, 999, 1.5)
        after: SafetyStatus = inbox.last("safety/status")
        assert after.config_version == before.config_version == 0
        assert after.total_constraints == before.total_constraints
        assert obeyed(start) == 0  # the executor never held the forged target
        assert inbox.count("robot/joint_state") - start > 50  # while it kept reporting

        # the control: the same messages from the identities allowed to send them are obeyed
        with secure_router.bus("config_api", service="intruder") as as_api:
            as_api.publisher("config").put(ConfigUpdate(stamp=time.monotonic(), version=7, changed=[], config=whole))
            _wait(lambda: inbox.last("safety/status").config_version == 7, 10, "the config API's update applied")
        assert inbox.last("safety/status").total_constraints == 0
        # commands too, once the safety service that commands is gone (the executor follows one
        # commander at a time: a second session, even with the safety certificate, waits its silence)
        safety.popen.terminate()
        safety.popen.wait(20)
        with secure_router.bus("safety", service="intruder") as as_safety:
            start = attack(as_safety, 8, 1.5)
        assert obeyed(start) > 0
