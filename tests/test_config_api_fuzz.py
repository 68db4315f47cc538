"""Schemathesis against the served /openapi.json: generated requests (valid and invalid, with and
without the token) never get a 5xx, and responses conform to the documented schema."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
import schemathesis
from hypothesis import HealthCheck, given, settings
from schemathesis import GenerationMode

from services.config_api.store import ConfigStore
from shared.bus import Bus
from shared.config import load_config
from tests.test_config_api import AUTH, ApiServer, FakeSafety, bus, zenoh_endpoint  # noqa: F401 (fixtures)

pytestmark = pytest.mark.integration


@pytest.fixture(scope="module")
def fuzzed(tmp_path_factory: pytest.TempPathFactory, zenoh_endpoint: str, bus: Bus) -> Iterator[ApiServer]:  # noqa: F811
    """An API whose changes a fake safety service acknowledges at once (no waiting for timeouts)."""
    with ApiServer(tmp_path_factory.mktemp("fuzz") / "config.json", zenoh_endpoint) as server, FakeSafety(bus):
        yield server


#: The live stream never ends: test_config_api reads it.
STREAM = "/api/status/stream"


def _check(case: schemathesis.Case) -> None:
    case.call_and_validate(headers=AUTH)
    anonymous = case.call()
    assert anonymous.status_code < 500, anonymous.text
    if case.method != "GET":  # refused: no token (401), or a body that cannot even be read (400/413/422)
        assert anonymous.status_code in (400, 401, 413, 422), anonymous.text


def test_generated_requests_never_get_a_server_error(fuzzed: ApiServer) -> None:
    """Every operation of the served schema, with valid and with invalid generated data."""
    schema = schemathesis.openapi.from_url(f"{fuzzed.url}/openapi.json").exclude(path=STREAM)
    operations = [result.ok() for result in schema.get_all_operations()]
    names = {f"{op.method.upper()} {op.path}" for op in operations}
    assert {"GET /api/config", "PATCH /api/config/safety", "PATCH /api/config/retarget", "POST /api/calibrate",
            "GET /api/config/history", "GET /api/status", "GET /api/health"} <= names
    for operation in operations:
        has_inputs = bool(operation.body or operation.query or operation.headers)
        for mode in (GenerationMode.POSITIVE, GenerationMode.NEGATIVE) if has_inputs else (GenerationMode.POSITIVE,):
            fuzz = settings(max_examples=30, deadline=None, database=None, suppress_health_check=list(HealthCheck))(
                given(case=operation.as_strategy(generation_mode=mode))(_check)
            )
            fuzz()


def test_fuzzing_left_a_valid_loadable_store(fuzzed: ApiServer) -> None:
    """Generated valid changes were accepted, and the persisted store reloads into a valid configuration."""
    body = fuzzed.http.get("/api/config").json()
    assert body["version"] > 0
    reloaded = ConfigStore.open(Path(fuzzed.store), load_config(environ={}))
    assert reloaded.snapshot.version == body["version"]
    assert reloaded.snapshot.config.safety.model_dump(mode="json") == body["config"]["safety"]
