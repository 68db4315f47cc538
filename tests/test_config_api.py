"""Config API over real HTTP (uvicorn in its own process) and real Zenoh on loopback.

Each endpoint; 401 without the token; 422 naming the field with the store file unchanged; an
accepted change reaches a Zenoh subscriber with the next version and is acknowledged by a
SafetyStatus; a restart keeps it; the token file; the body limit; reads from a non-loopback
address. The helpers here (:class:`ApiServer`, :class:`FakeSafety`) are
reused by the other ``test_config_api_*`` modules.
"""

from __future__ import annotations

import json
import socket
import stat
import sys
import threading
import time
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import httpx
import numpy as np
import pytest

from shared.bus import Bus
from shared.config import BusConfig, load_config
from shared.messages import ConfigUpdate, HumanState, SafetyMode, SafetyStatus
from shared.names import CAPSULE_NAMES
from tests.support.bus import BusRecorder
from tests.support.processes import Proc, free_port

pytestmark = pytest.mark.integration

#: How long a test waits for a ConfigUpdate on the bus (s).
UPDATE_TIMEOUT_S = 5.0
TOKEN = "test-token-for-the-config-api-0123"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
#: Short acknowledgement timeout of the API under test (s): tests without a safety service wait this long.
ACK_TIMEOUT_S = 0.6


# --------------------------------------------------------------------------------------------
# helpers (also used by test_config_api_browser/_fuzz/_safety)


class ApiServer:
    """``safemimic config-api`` as a real process on a free port, peer of the test's Zenoh session."""

    def __init__(self, store: Path, zenoh_endpoint: str, env: dict[str, str] | None = None, *extra: str) -> None:
        self.store = store
        self.proc = Proc(
            [
                sys.executable, "-m", "safemimic.cli", "config-api", "--port", "0", "--store", str(store),
                "--mode", "peer", "--connect", zenoh_endpoint, "--no-multicast", *extra,
            ],
            env={
                "SAFEMIMIC_API_TOKEN": TOKEN,
                "SAFEMIMIC__API__ACK_TIMEOUT_S": str(ACK_TIMEOUT_S),
                "XDG_STATE_HOME": str(store.parent / "state"),
                **(env or {}),
            },
        )
        try:
            self.ready = self.proc.wait_json("ready", timeout=20)
        except BaseException:
            self.proc.stop()
            raise
        self.url: str = self.ready["url"]
        self.http = httpx.Client(base_url=self.url, timeout=10)

    def stop(self) -> None:
        self.http.close()
        self.proc.stop()

    def __enter__(self) -> ApiServer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


class FakeSafety:
    """Plays the safety service on the bus: applies every ConfigUpdate (if ``ack``) and reports
    the applied version in a SafetyStatus at 50 Hz, with the given live values (``intrusion``: every
    status reports a person inside a margin; ``backing_out``: and the stop backing out of them;
    ``lateness_ms``: the person's states that late; ``refuse``: it refuses every update, counting
    it in ``dropped["config"]`` as the safety service does)."""

    def __init__(self, bus: Bus, ack: bool = True, report_version: int | None = None, mode: SafetyMode = SafetyMode.ACTIVE,
                 h_self: float = 0.031, h_human: float | None = 0.142, robot_id: str | None = None,
                 intrusion: bool = False, backing_out: bool = False, lateness_ms: float = 0.0,
                 refuse: bool = False) -> None:
        self.version = report_version or 0
        self.ack = ack and report_version is None and not refuse
        self.refuse, self.refused = refuse, 0
        self.mode, self.h_self, self.h_human, self.intrusion = mode, h_self, h_human, intrusion
        self.backing_out, self.lateness_ms = backing_out, lateness_ms
        self.published = 0
        self._publisher = bus.publisher("safety/status", robot_id=robot_id)
        bus.subscribe("config", self._on_config, robot_id=robot_id)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _on_config(self, update: ConfigUpdate) -> None:
        if self.ack:
            self.version = max(self.version, update.version)
        elif self.refuse and update.version > self.version:
            self.refused += 1

    def _run(self) -> None:
        while not self._stop.wait(0.02):
            self._publisher.put(
                SafetyStatus(
                    stamp=time.monotonic(), mode=self.mode, min_h_self=self.h_self, min_h_human=self.h_human,
                    active_constraints=3, total_constraints=63, qp_solve_time_ms=0.012 + 0.001 * (self.published % 5),
                    step_time_ms=0.2, config_version=self.version, backend="daqp", executor_holding=True,
                    watchdog_trips={"executor_command": 2}, person_intrusion=self.intrusion,
                    backing_out=self.backing_out, human_lateness_ms=self.lateness_ms,
                    dropped={"config": self.refused} if self.refused else {},
                )
            )
            self.published += 1

    def __enter__(self) -> FakeSafety:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(2)


def human_state(theta: list[float], valid: bool = True) -> HumanState:
    return HumanState(
        stamp=time.monotonic(), keypoints=np.zeros((15, 3)), keypoint_valid=np.ones(15, bool),
        theta=np.asarray(theta), theta_valid=np.full(8, valid), capsules=np.zeros((7, 2, 3)),
        capsule_radii=np.full(7, 0.06), capsule_valid=np.ones(7, bool),
    )


@pytest.fixture(scope="module")
def zenoh_endpoint() -> str:
    return f"tcp/127.0.0.1:{free_port()}"


@pytest.fixture(scope="module")
def bus(zenoh_endpoint: str) -> Iterator[Bus]:
    """The test's Zenoh session (peer, listening on loopback): the API processes connect to it."""
    with Bus(BusConfig(mode="peer", listen=[zenoh_endpoint], multicast_scouting=False), "g1", "test") as test_bus:
        yield test_bus


@pytest.fixture(scope="module")
def api(tmp_path_factory: pytest.TempPathFactory, zenoh_endpoint: str, bus: Bus) -> Iterator[ApiServer]:
    with ApiServer(tmp_path_factory.mktemp("api") / "config.json", zenoh_endpoint) as server:
        yield server


def store_bytes(server: ApiServer) -> bytes | None:
    return server.store.read_bytes() if server.store.exists() else None


def wait_until(predicate: Callable[[], bool], timeout: float = 5.0) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        assert time.monotonic() < deadline, "condition not met in time"
        time.sleep(0.02)


# --------------------------------------------------------------------------------------------
# reads


def test_health_and_config_read(api: ApiServer) -> None:
    health = api.http.get("/api/health").json()
    assert health["status"] == "ok" and health["store"] == str(api.store)
    assert "config_api" in health["services_alive"]

    body = api.http.get("/api/config").json()
    defaults = load_config(environ={})
    assert body["version"] == health["config_version"]
    assert body["joint_names"][0] == "waist_roll_joint" and len(body["capsule_names"]) == 7
    safety = body["safety"]
    # the names, mapped onto the configuration explicitly
    assert set(safety) == {"gamma", "phi", "k", "w", "u_min", "u_max", "accel_max", "self_margin", "human_margin", "human_predict_s",
                           "human_standoff_m", "human_speed_mps", "dt", "enabled_pair_groups", "capsule_radii", "human_velocity_term",
                           "geometry", "sphere_k", "on_intrusion", "intrusion_backout_mps", "feedforward", "target_path"}
    assert safety["dt"] == pytest.approx(1.0 / body["config"]["safety"]["rate_hz"])
    assert safety["k"] == body["config"]["safety"]["gain"] and safety["w"] == body["config"]["safety"]["weights"]
    assert set(body["retarget"]) == {"S", "b", "q_home", "theta_home", "mirror", "method"}
    assert body["config"]["robot_id"] == defaults.robot_id
    assert body["config"]["api"]["token"] is None
    for path in ("/api/config", "/api/config/history", "/api/status", "/api/health", "/openapi.json"):
        assert TOKEN not in api.http.get(path).text, path


def test_openapi_documents_the_contract(api: ApiServer) -> None:
    schema = api.http.get("/openapi.json").json()
    paths = schema["paths"]
    for path, method in [("/api/config", "get"), ("/api/config/safety", "patch"), ("/api/config/retarget", "patch"),
                         ("/api/calibrate", "post"), ("/api/status", "get"), ("/api/health", "get"),
                         ("/api/config/history", "get"), ("/api/status/stream", "get")]:
        assert method in paths[path], (path, method)
    patch = schema["components"]["schemas"]["SafetyPatch"]["properties"]
    assert patch["gamma"]["exclusiveMinimum"] == 0 and patch["phi"]["maximum"] == 0.5
    assert patch["w"]["minItems"] == patch["w"]["maxItems"] == 8
    # the velocity bounds as the writer takes them: within the G1's joint_velocity_limits, joint by joint
    assert [item["maximum"] for item in patch["u_max"]["prefixItems"]] == [37.0] * 8
    u_min = next(variant for variant in patch["u_min"]["anyOf"] if variant.get("type") == "array")
    assert [item["minimum"] for item in u_min["prefixItems"]] == [-37.0] * 8 and u_min["items"] is False
    assert "401" in paths["/api/config/safety"]["patch"]["responses"]
    assert "409" in paths["/api/calibrate"]["post"]["responses"]
    assert schema["components"]["securitySchemes"]["bearer"]["scheme"] == "bearer"
    assert paths["/api/config/safety"]["patch"]["security"] == [{"bearer": []}]
    assert paths["/api/config"]["get"]["security"] == [{"bearer": []}, {}]  # loopback reads need no token


# --------------------------------------------------------------------------------------------
# writes: token, validation


@pytest.mark.parametrize(
    ("method", "path", "body"),
    [("PATCH", "/api/config/safety", {"gamma": 3.0}), ("PATCH", "/api/config/retarget", {"mirror": True}),
     ("POST", "/api/calibrate", None)],
)
@pytest.mark.parametrize("headers", [{}, {"Authorization": "Bearer wrong-token-wrong-token"}, {"Authorization": TOKEN}])
def test_writes_need_the_token(api: ApiServer, method: str, path: str, body: dict | None, headers: dict) -> None:
    before_file, before = store_bytes(api), api.http.get("/api/config").json()
    response = api.http.request(method, path, json=body, headers=headers)
    assert response.status_code == 401
    assert response.headers["www-authenticate"] == "Bearer"
    assert store_bytes(api) == before_file and api.http.get("/api/config").json() == before


@pytest.mark.parametrize(
    ("content", "headers"),
    [(b"{gamma", {}), (b'{"gamma": 3.0}', {"X-Operator": "a/b"}), (b'{"gamma": 3.0}', {"Authorization": "Basic " + TOKEN}),
     (b"x" * 70_000, {}), (b'{"gamma": 3.0}', {"Authorization": "Bearer " + TOKEN[:-1]})],
)
def test_a_write_without_the_token_is_401_before_its_body_or_headers_are_looked_at(
        api: ApiServer, content: bytes, headers: dict) -> None:
    """Malformed JSON, a bad X-Operator header or an oversized body: without the token, 401 (not the
    422 or 413 a writer would get), so a client that may not write learns nothing of the validators."""
    response = api.http.patch("/api/config/safety", content=content,
                              headers={"Content-Type": "application/json", **headers})
    assert response.status_code == 401, response.text
    assert response.headers["www-authenticate"] == "Bearer"
    with_token = api.http.patch("/api/config/safety", content=content,
                                headers={"Content-Type": "application/json", **headers, **AUTH})
    assert with_token.status_code != 401, with_token.text  # the same request from a writer gets past the token


@pytest.mark.parametrize(
    ("path", "body", "field"),
    [
        ("/api/config/safety", {"gamma": -1.0}, "gamma"),
        ("/api/config/safety", {"gamma": "fast"}, "gamma"),
        ("/api/config/safety", {"gamma": None}, "gamma"),
        ("/api/config/safety", {"gamma": True}, "gamma"),  # strict: a boolean is not a number
        ("/api/config/safety", {"gamma": "3.0"}, "gamma"),
        ("/api/config/safety", {"phi": 0.9}, "phi"),
        ("/api/config/safety", {"k": 0}, "k"),
        ("/api/config/safety", {"w": [1.0] * 7}, "w"),
        ("/api/config/safety", {"w": [1.0] * 7 + [0.0]}, "w"),
        ("/api/config/safety", {"u_min": [0.5] * 8}, "u_min"),
        ("/api/config/safety", {"u_max": [-1.0] * 8}, "u_max"),
        # within the API's range but beyond the G1's joint_velocity_limits (37 rad/s), which the safety
        # service would refuse: not saved, or it would ride along with every later change
        ("/api/config/safety", {"u_max": [3.0, 3.0, 40.0, 10.0, 10.0, 10.0, 10.0, 10.0]}, "u_max"),
        ("/api/config/safety", {"u_min": [-3.0, -3.0, -10.0, -10.0, -40.0, -10.0, -10.0, -10.0]}, "u_min"),
        ("/api/config/safety", {"accel_max": [0.0] * 8}, "accel_max"),
        ("/api/config/safety", {"self_margin": -0.001}, "self_margin"),
        ("/api/config/safety", {"self_margin": 0.5}, "self_margin"),
        ("/api/config/safety", {"human_margin": -0.01}, "human_margin"),
        ("/api/config/safety", {"human_margin": 1.0}, "human_margin"),
        ("/api/config/safety", {"human_predict_s": -0.1}, "human_predict_s"),
        ("/api/config/safety", {"human_predict_s": 2.0}, "human_predict_s"),
        ("/api/config/safety", {"human_standoff_m": -0.01}, "human_standoff_m"),
        ("/api/config/safety", {"human_standoff_m": 0.5}, "human_standoff_m"),
        ("/api/config/safety", {"human_speed_mps": -0.5}, "human_speed_mps"),
        ("/api/config/safety", {"human_speed_mps": 9.0}, "human_speed_mps"),
        ("/api/config/safety", {"dt": 0}, "dt"),
        ("/api/config/safety", {"dt": 2.0}, "dt"),
        ("/api/config/safety", {"enabled_pair_groups": ["elbows"]}, "enabled_pair_groups"),
        ("/api/config/safety", {"enabled_pair_groups": ["human", "self_arms", "human"]}, "enabled_pair_groups"),
        ("/api/config/safety", {"capsule_radii": {"robot": {"nose": 0.1}}}, "capsule_radii"),
        ("/api/config/safety", {"capsule_radii": {"human": {"torso": 3.0}}}, "capsule_radii"),
        ("/api/config/safety", {"human_velocity_term": "maybe"}, "human_velocity_term"),
        ("/api/config/safety", {"on_intrusion": "flee"}, "on_intrusion"),
        ("/api/config/safety", {"intrusion_backout_mps": 0.5}, "intrusion_backout_mps"),
        ("/api/config/safety", {"intrusion_backout_mps": -0.01}, "intrusion_backout_mps"),
        ("/api/config/safety", {"feedforward": "yes"}, "feedforward"),
        ("/api/config/safety", {"target_path": "smooth"}, "target_path"),
        ("/api/config/safety", {"rate_hz": 100.0}, "rate_hz"),
        ("/api/config/retarget", {"S": [1.0] * 8 + [1.0]}, "S"),
        ("/api/config/retarget", {"b": [9.0] * 8}, "b"),
        ("/api/config/retarget", {"q_home": [0.0] * 3}, "q_home"),
        ("/api/config/retarget", {"mirror": [True]}, "mirror"),
        ("/api/config/retarget", {"mirror": 1}, "mirror"),
        ("/api/config/retarget", {"method": "cubic"}, "method"),
        ("/api/config/retarget", {"S": [True] * 8}, "S"),
    ],
)
def test_bad_value_is_422_naming_the_field_and_nothing_applied(api: ApiServer, path: str, body: dict, field: str) -> None:
    before_file, before = store_bytes(api), api.http.get("/api/config").json()
    # a valid field next to the bad one: nothing partial may be applied
    valid = {"phi": 0.031} if path.endswith("safety") else {"S": [0.9] * 8}
    response = api.http.patch(path, json={**valid, **body}, headers=AUTH)
    assert response.status_code == 422, response.text
    locations = [error["loc"] for error in response.json()["detail"]]
    assert any(loc[:2] == ["body", field] for loc in locations), locations
    assert store_bytes(api) == before_file
    assert api.http.get("/api/config").json() == before


@pytest.mark.parametrize("raw", [b'{"gamma": NaN}', b'{"gamma": Infinity}', b"[1, 2]", b"{not json", b'"gamma"'])
def test_malformed_bodies_are_422(api: ApiServer, raw: bytes) -> None:
    before_file = store_bytes(api)
    response = api.http.patch("/api/config/safety", content=raw, headers={**AUTH, "Content-Type": "application/json"})
    assert response.status_code == 422, response.text
    assert store_bytes(api) == before_file


def test_oversized_body_is_413(api: ApiServer) -> None:
    before_file = store_bytes(api)
    big = {"gamma": 3.0, "padding": "x" * 70_000}
    response = api.http.patch("/api/config/safety", json=big, headers=AUTH)
    assert response.status_code == 413 and "larger than 65536" in response.json()["detail"]

    def chunks() -> Iterator[bytes]:  # no Content-Length: refused while streaming
        yield b'{"gamma": 3.0, "padding": "'
        for _ in range(40):
            yield b"x" * 4096
        yield b'"}'

    response = api.http.patch("/api/config/safety", content=chunks(), headers={**AUTH, "Content-Type": "application/json"})
    assert response.status_code == 413
    assert store_bytes(api) == before_file


# --------------------------------------------------------------------------------------------
# writes: persistence, publication, acknowledgement


def test_change_is_persisted_published_and_acknowledged(api: ApiServer, bus: Bus) -> None:
    updates = BusRecorder(bus, ("config",))
    version = api.http.get("/api/config").json()["version"]
    with FakeSafety(bus):
        response = api.http.patch(
            "/api/config/safety", json={"gamma": 4.5, "k": 6.0, "dt": 0.004},
            headers={**AUTH, "X-Operator": "ada"},
        )
    assert response.status_code == 200, response.text
    result = response.json()
    assert result["version"] == version + 1
    assert result["applied"] is True and result["acknowledged_version"] >= version + 1
    assert sorted(result["changed"]) == ["safety.gain", "safety.gamma", "safety.rate_hz"]

    update = updates.wait("config", lambda u: u.version == version + 1, UPDATE_TIMEOUT_S, since=0.0)
    assert sorted(update.changed) == ["safety.gain", "safety.gamma", "safety.rate_hz"]
    assert update.config["safety"]["gamma"] == 4.5 and update.config["safety"]["gain"] == 6.0
    assert update.config["safety"]["rate_hz"] == pytest.approx(250.0)
    assert update.config["api"]["token"] is None

    stored = json.loads(api.store.read_text())
    assert stored["version"] == version + 1 and stored["config"]["safety"]["gamma"] == 4.5
    assert TOKEN not in api.store.read_text()
    assert stat.S_IMODE(api.store.stat().st_mode) == 0o600
    assert not list(api.store.parent.glob(".config.json.*.tmp"))

    history = api.http.get("/api/config/history", params={"limit": 1}).json()
    entry = history["entries"][0]
    assert history["version"] == version + 1
    assert entry["version"] == version + 1 and entry["who"] == "ada" and entry["client"] == "127.0.0.1"
    assert entry["action"] == "patch safety"
    assert {c["path"]: (c["old"], c["new"]) for c in entry["diff"]}["safety.gamma"][1] == 4.5

    body = api.http.get("/api/config").json()
    assert body["version"] == version + 1 and body["safety"]["gamma"] == 4.5 and body["safety"]["dt"] == pytest.approx(0.004)


def test_unacknowledged_change_is_saved_and_reported(api: ApiServer, bus: Bus) -> None:
    updates = BusRecorder(bus, ("config",))
    version = api.http.get("/api/config").json()["version"]
    started = time.monotonic()
    response = api.http.patch("/api/config/safety", json={"phi": 0.045}, headers=AUTH)
    waited = time.monotonic() - started
    result = response.json()
    assert response.status_code == 200 and result["applied"] is False
    assert result["version"] == version + 1 and "no safety service is reporting" in result["detail"]
    assert ACK_TIMEOUT_S * 0.9 <= waited < ACK_TIMEOUT_S + 2.0
    update = updates.wait("config", lambda u: u.version == version + 1, UPDATE_TIMEOUT_S, since=0.0)
    assert update.config["safety"]["phi"] == 0.045
    assert api.http.get("/api/config").json()["safety"]["phi"] == 0.045


def test_a_change_the_safety_service_refuses_is_reported_as_refused(api: ApiServer, bus: Bus) -> None:
    version = api.http.get("/api/config").json()["version"]
    with FakeSafety(bus, refuse=True) as safety:
        wait_until(lambda: api.http.get("/api/status").json()["status_age_s"] is not None)
        result = api.http.patch("/api/config/safety", json={"phi": 0.044}, headers=AUTH).json()
    assert safety.refused >= 1 and result["applied"] is False and result["version"] == version + 1
    assert "the safety service refused it" in result["detail"] and "its log says why" in result["detail"], result


def test_unchanged_values_make_no_new_version(api: ApiServer) -> None:
    body = api.http.get("/api/config").json()
    before_file = store_bytes(api)
    response = api.http.patch("/api/config/safety", json={"gamma": body["safety"]["gamma"]}, headers=AUTH)
    assert response.status_code == 200
    assert response.json()["version"] == body["version"] and response.json()["changed"] == []
    assert api.http.patch("/api/config/retarget", json={}, headers=AUTH).json()["changed"] == []
    assert store_bytes(api) == before_file


def test_every_safety_field_maps_onto_the_config(api: ApiServer) -> None:
    patch = {
        "w": [2.0, 2.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0],
        "u_min": [-1.0, -1.0, -3.0, -3.0, -3.0, -3.0, -3.0, -3.0],
        "u_max": [1.5, 1.5, 3.5, 3.5, 3.5, 3.5, 3.5, 3.5],
        "accel_max": [5.0, 5.0, 40.0, 40.0, 100.0, 40.0, 40.0, 100.0],
        "self_margin": 0.004,
        "human_margin": 0.03,
        "human_predict_s": 0.0,
        "human_standoff_m": 0.07,
        "human_speed_mps": 2.0,
        "enabled_pair_groups": ["human", "self_arms"],
        "capsule_radii": {"robot": {"left_forearm": 0.061, "torso": 0.12}, "human": {"torso": 0.16, "forearm": 0.055}},
        "human_velocity_term": False,
        "on_intrusion": "retreat",
        "intrusion_backout_mps": 0.1,
        "feedforward": False,
        "target_path": "continuous",
    }
    assert api.http.patch("/api/config/safety", json=patch, headers=AUTH).status_code == 200
    conf = api.http.get("/api/config").json()["config"]
    assert conf["safety"]["weights"] == patch["w"] and conf["safety"]["u_min"] == patch["u_min"]
    assert conf["safety"]["u_max"] == patch["u_max"] and conf["safety"]["accel_max"] == patch["accel_max"]
    assert conf["safety"]["self_margin"] == 0.004 and conf["safety"]["human_margin"] == 0.03
    assert conf["safety"]["human_predict_s"] == 0.0 and conf["safety"]["human_standoff_m"] == 0.07
    assert conf["safety"]["human_speed_mps"] == 2.0
    assert conf["safety"]["enabled_pair_groups"] == ["self_arms", "human"]
    assert conf["safety"]["capsule_radii"] == {"left_forearm": 0.061, "torso": 0.12}
    assert conf["human"]["torso_radius"] == 0.16 and conf["human"]["forearm_radius"] == 0.055
    assert conf["human"]["thigh_radius"] == load_config(environ={}).human.thigh_radius
    assert conf["safety"]["human_velocity_term"] is False and conf["safety"]["intrusion_backout_mps"] == 0.1
    assert conf["safety"]["feedforward"] is False and conf["safety"]["target_path"] == "continuous"
    assert api.http.get("/api/config").json()["safety"]["target_path"] == "continuous"
    assert conf["safety"]["on_intrusion"] == "retreat" and api.http.get("/api/config").json()["safety"]["on_intrusion"] == "retreat"
    assert api.http.patch("/api/config/safety", json={"on_intrusion": "stop_on_give_way"}, headers=AUTH).status_code == 200
    assert api.http.get("/api/config").json()["safety"]["on_intrusion"] == "stop_on_give_way"

    # null: back to the default (symmetric bounds, the robot description's radius)
    reset = {"u_min": None, "capsule_radii": {"robot": {"torso": None}}}
    result = api.http.patch("/api/config/safety", json=reset, headers=AUTH).json()
    assert sorted(result["changed"]) == ["safety.capsule_radii.torso", "safety.u_min"]
    safety = api.http.get("/api/config").json()["safety"]
    assert safety["u_min"] is None and safety["capsule_radii"]["robot"] == {"left_forearm": 0.061}


def test_concurrent_patches_of_the_robot_radii_all_land(api: ApiServer) -> None:
    """Each request's change is computed from the configuration it replaces, inside the writer's
    lock: seven operators each enlarging one capsule at once leave seven overrides, none undone by
    another's stale copy of the mapping."""
    names = list(CAPSULE_NAMES)
    clear = {"capsule_radii": {"robot": dict.fromkeys(names)}}
    assert api.http.patch("/api/config/safety", json=clear, headers=AUTH).status_code == 200
    start = threading.Barrier(len(names))

    def enlarge(name: str) -> int:
        with httpx.Client(base_url=api.url, timeout=10) as client:
            start.wait()
            body = {"capsule_radii": {"robot": {name: 0.12}}}
            return client.patch("/api/config/safety", json=body, headers=AUTH).status_code

    with ThreadPoolExecutor(len(names)) as pool:
        assert list(pool.map(enlarge, names)) == [200] * len(names)
    assert api.http.get("/api/config").json()["safety"]["capsule_radii"]["robot"] == dict.fromkeys(names, 0.12)
    assert api.http.patch("/api/config/safety", json=clear, headers=AUTH).status_code == 200


def test_retarget_fields_map_onto_the_config(api: ApiServer) -> None:
    patch = {"S": [1.0, 1.0, 0.8, 0.8, 1.0, 0.8, 0.8, 1.0], "b": [0.0, 0.05, 0, 0, 0, 0, 0, 0],
             "q_home": [0.0, 0.0, 0.2, 0.3, 1.2, 0.2, -0.3, 1.2], "mirror": True, "method": "directions"}
    result = api.http.patch("/api/config/retarget", json=patch, headers=AUTH).json()
    assert sorted(result["changed"]) == ["retargeting.method", "retargeting.mirror", "retargeting.offset", "retargeting.q_home",
                                         "retargeting.scale"]
    body = api.http.get("/api/config").json()
    retargeting = body["config"]["retargeting"]
    assert retargeting["scale"] == patch["S"] and retargeting["offset"] == patch["b"]
    assert retargeting["q_home"] == patch["q_home"] and retargeting["mirror"] is True
    assert body["retarget"] == {**patch, "theta_home": retargeting["theta_home"]}


def test_store_failure_is_503_and_nothing_applied(tmp_path: Path, zenoh_endpoint: str, bus: Bus) -> None:
    folder = tmp_path / "state"
    folder.mkdir()
    with ApiServer(folder / "config.json", zenoh_endpoint) as server:
        updates = BusRecorder(bus, ("config",))
        before = server.http.get("/api/config").json()
        folder.rmdir()
        folder.write_text("a file where the store's folder was")  # even root cannot write below a file
        response = server.http.patch("/api/config/safety", json={"gamma": 7.5}, headers=AUTH)
        assert response.status_code == 503 and "not applied" in response.json()["detail"]
        assert server.http.get("/api/config").json() == before
        time.sleep(0.3)
        assert not [u for u in updates.between("config") if u.config["safety"]["gamma"] == 7.5]


# --------------------------------------------------------------------------------------------
# calibrate, status, stream


def test_calibrate_captures_theta_home_from_the_newest_human_state(api: ApiServer, bus: Bus) -> None:
    response = api.http.post("/api/calibrate", headers=AUTH)
    assert response.status_code == 409 and "no human state" in response.json()["detail"]

    publisher = bus.publisher("human/state")
    publisher.put(human_state([0.0] * 8, valid=False))
    wait_until(lambda: api.http.get("/api/status").json()["human_age_s"] is not None)
    response = api.http.post("/api/calibrate", headers=AUTH)
    assert response.status_code == 409 and "invalid angles torso_roll" in response.json()["detail"]

    theta = [0.01, -0.02, 0.05, 0.1, 0.2, 0.04, -0.1, 0.25]
    updates = BusRecorder(bus, ("config",))
    publisher.put(human_state(theta))
    responses: list[httpx.Response] = []
    wait_until(lambda: responses.append(api.http.post("/api/calibrate", headers=AUTH)) or responses[-1].status_code == 200)
    result = responses[-1].json()
    assert result["theta_home"] == pytest.approx(theta) and 0 <= result["human_age_s"] < 0.5
    assert result["changed"] == ["retargeting.theta_home"]
    body = api.http.get("/api/config").json()
    assert body["version"] == result["version"]
    assert body["retarget"]["theta_home"] == pytest.approx(theta)
    entry = api.http.get("/api/config/history").json()["entries"][0]
    assert entry["action"] == "calibrate" and entry["diff"][0]["path"] == "retargeting.theta_home"
    calibrated = updates.wait("config", lambda u: "retargeting.theta_home" in u.changed, UPDATE_TIMEOUT_S, since=0.0)
    assert calibrated.config["retargeting"]["theta_home"] == pytest.approx(theta)

    # the same pose again: nothing to change, same version; a stale pose is refused
    publisher.put(human_state(theta))
    wait_until(lambda: api.http.get("/api/status").json()["human_age_s"] < 0.2)
    again = api.http.post("/api/calibrate", headers=AUTH).json()
    assert again["version"] == body["version"] and again["changed"] == [] and again["theta_home"] == pytest.approx(theta)
    time.sleep(load_config(environ={}).api.calibrate_max_age_s + 0.1)
    response = api.http.post("/api/calibrate", headers=AUTH)
    assert response.status_code == 409 and "s old" in response.json()["detail"]


def test_status_reports_the_newest_safety_status(api: ApiServer, bus: Bus) -> None:
    with FakeSafety(bus, mode=SafetyMode.RELAXED, h_self=-0.004, h_human=None, ack=False, intrusion=True,
                    backing_out=True, lateness_ms=38.5) as fake:
        wait_until(lambda: api.http.get("/api/status").json()["mode"] == "relaxed")
        status = api.http.get("/api/status").json()
    assert status["available"] is True and status["h_min_self"] == -0.004 and status["h_min_human"] is None
    assert status["active_constraints"] == 3 and status["total_constraints"] == 63 and status["backend"] == "daqp"
    assert 0.0 <= status["status_age_s"] < 1.0 and status["solve_time_ms"] >= 0.012
    assert status["applied_config_version"] == fake.version
    assert status["config_version"] == api.http.get("/api/config").json()["version"]
    assert status["watchdogs"] == {"human_stale": False, "human_source_lost": False, "human_lost": False,
                                   "joint_state_stale": False,
                                   "executor_holding": True, "resyncing": False}
    assert status["watchdog_trips"] == {"executor_command": 2}
    assert status["person_intrusion"] is True and status["backing_out"] is True and status["human_lateness_ms"] == 38.5


def test_status_stream_sends_config_and_status_events(api: ApiServer, bus: Bus) -> None:
    events: list[tuple[str, dict]] = []
    with FakeSafety(bus, h_self=0.077, ack=False):
        with api.http.stream("GET", "/api/status/stream") as response:
            assert response.headers["content-type"].startswith("text/event-stream")
            name = None
            for line in response.iter_lines():
                if line.startswith("event:"):
                    name = line.split(":", 1)[1].strip()
                elif line.startswith("data:"):
                    events.append((name, json.loads(line.split(":", 1)[1])))
                if sum(1 for n, _ in events if n == "status") >= 3:
                    break
    assert events[0][0] == "config" and events[0][1]["version"] == api.http.get("/api/config").json()["version"]
    statuses = [data for n, data in events if n == "status"]
    assert statuses[-1]["h_min_self"] == 0.077 and statuses[-1]["available"] is True


def test_versions_stay_above_what_the_safety_service_reports(tmp_path: Path, zenoh_endpoint: str, bus: Bus) -> None:
    """A lost store must not reuse versions a running safety service already applied."""
    with (  # another robot id: the module's API never sees v41
        ApiServer(tmp_path / "config.json", zenoh_endpoint, None, "--robot-id", "lost_store") as server,
        FakeSafety(bus, report_version=41, robot_id="lost_store"),
    ):
        wait_until(lambda: server.http.get("/api/status").json()["applied_config_version"] == 41)
        result = server.http.patch("/api/config/safety", json={"gamma": 9.0}, headers=AUTH).json()
    assert result["version"] == 42 and result["applied"] is False


# --------------------------------------------------------------------------------------------
# restart, token, deployment


def test_restart_keeps_the_config_and_republishes_it(tmp_path: Path, zenoh_endpoint: str, bus: Bus) -> None:
    store = tmp_path / "config.json"
    with ApiServer(store, zenoh_endpoint) as first:
        first.http.patch("/api/config/safety", json={"gamma": 3.25}, headers=AUTH)
        result = first.http.patch("/api/config/retarget", json={"mirror": True}, headers=AUTH).json()
    assert result["version"] == 2
    updates = BusRecorder(bus, ("config",))
    with ApiServer(store, zenoh_endpoint) as second:
        assert second.ready["version"] == 2
        body = second.http.get("/api/config").json()
        assert body["version"] == 2 and body["safety"]["gamma"] == 3.25 and body["retarget"]["mirror"] is True
        assert [e["version"] for e in second.http.get("/api/config/history").json()["entries"]] == [2, 1]
        assert updates.wait("config", lambda u: u.version == 2, UPDATE_TIMEOUT_S, since=0.0).config["safety"]["gamma"] == 3.25  # published at start
        # a service that comes up gets the accepted configuration again
        time.sleep(0.3)
        declared = time.monotonic()
        token = bus.declare_alive("safety")
        try:
            update = updates.wait("config", lambda u: u.version == 2 and u.changed == [], UPDATE_TIMEOUT_S, since=declared)
        finally:
            token.undeclare()
        assert update.config["safety"]["gamma"] == 3.25
        assert second.http.patch("/api/config/safety", json={"gamma": 3.5}, headers=AUTH).json()["version"] == 3


def test_generated_token_is_stored_0600_and_printed_once(tmp_path: Path, zenoh_endpoint: str) -> None:
    store = tmp_path / "config.json"
    with ApiServer(store, zenoh_endpoint, {"SAFEMIMIC_API_TOKEN": ""}) as first:
        token_file = tmp_path / "api_token"
        token = token_file.read_text().strip()
        assert len(token) >= 32 and stat.S_IMODE(token_file.stat().st_mode) == 0o600
        assert sum(token in line for line in first.proc.output) == 1
        assert first.http.patch("/api/config/safety", json={"gamma": 2.0}, headers=AUTH).status_code == 401
        ok = first.http.patch("/api/config/safety", json={"gamma": 2.0}, headers={"Authorization": f"Bearer {token}"})
        assert ok.status_code == 200
    with ApiServer(store, zenoh_endpoint, {"SAFEMIMIC_API_TOKEN": ""}) as second:
        assert not any(token in line for line in second.proc.output)
        ok = second.http.patch("/api/config/safety", json={"gamma": 2.5}, headers={"Authorization": f"Bearer {token}"})
        assert ok.status_code == 200 and token_file.read_text().strip() == token


def test_corrupt_store_refuses_to_start(tmp_path: Path, zenoh_endpoint: str) -> None:
    store = tmp_path / "config.json"
    store.write_text('{"format": "safemimic.config-store/1", "version": 3, "config": {"safety": {"gamma": -1}}}')
    proc = Proc([sys.executable, "-m", "safemimic.cli", "config-api", "--port", "0", "--store", str(store),
                 "--no-multicast", "--connect", zenoh_endpoint], env={"SAFEMIMIC_API_TOKEN": TOKEN})
    assert proc.popen.wait(20) == 2
    wait_until(lambda: any("safety.gamma" in line for line in proc.output), timeout=2)
    assert any(str(store) in line for line in proc.output)


def _non_loopback_ipv4() -> str | None:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        try:
            sock.connect(("192.0.2.123", 9))  # no packet is sent: this only picks the outgoing address
        except OSError:
            return None
        address = sock.getsockname()[0]
    return None if address.startswith("127.") else address


def test_reads_from_a_non_loopback_address_need_the_token(tmp_path: Path, zenoh_endpoint: str) -> None:
    address = _non_loopback_ipv4()
    if address is None:
        pytest.skip("no non-loopback IPv4 address on this machine")
    with ApiServer(tmp_path / "config.json", zenoh_endpoint, None, "--host", "0.0.0.0") as server:
        port = server.url.rsplit(":", 1)[1]
        with httpx.Client(base_url=f"http://{address}:{port}", timeout=5) as remote:
            assert remote.get("/api/config").status_code == 401
            assert remote.get("/api/status").status_code == 401
            assert remote.get("/api/config", headers=AUTH).status_code == 200
            assert remote.get("/api/health").status_code == 401
            assert remote.patch("/api/config/safety", json={"gamma": 3.0}, headers=AUTH).json()["version"] == 1
        assert server.http.get("/api/config").status_code == 200  # loopback reads stay open


def test_bind_defaults_to_loopback(api: ApiServer) -> None:
    assert api.url.startswith("http://127.0.0.1:")
    assert load_config(environ={}).api.host == "127.0.0.1"
    # no CORS by default: a cross-origin preflight gets no allow-origin header
    preflight = api.http.options(
        "/api/config/safety", headers={"Origin": "http://evil.example", "Access-Control-Request-Method": "PATCH"}
    )
    assert "access-control-allow-origin" not in preflight.headers
