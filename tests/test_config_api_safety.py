"""The config API with the real safety service: a change is applied by the running service and
acknowledged through its SafetyStatus; an asymmetric u_min reaches the CBF-QP filter."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from services.safety.assembly import build_pipeline
from shared.config import load_config
from tests.support.processes import free_port
from tests.test_config_api import AUTH, ApiServer, wait_until


@pytest.mark.integration
def test_real_safety_service_applies_and_acknowledges_changes(spawn, tmp_path: Path) -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    client = ["--mode", "client", "--connect", endpoint, "--no-multicast"]
    router = spawn("-m", "safemimic.cli", "router", "--listen", endpoint, "--no-multicast")
    router.wait_for(lambda line: "listening on" in line)
    safety = spawn("-m", "safemimic.cli", "safety", *client, "--rt-priority", "0", "--duration", "60")
    safety.wait_for(lambda line: "safety service started" in line, timeout=30)
    with ApiServer(tmp_path / "config.json", endpoint, {}, "--mode", "client") as api:
        # the service reports at 50 Hz; the API subscribes through the router
        wait_until(lambda: api.http.get("/api/status").json()["available"], timeout=10)
        result = api.http.patch(
            "/api/config/safety",
            json={"gamma": 6.0, "u_min": [-1.0, -1.0, -2.0, -2.0, -2.0, -2.0, -2.0, -2.0]},
            headers=AUTH,
        ).json()
        assert result["applied"] is True, result
        assert result["version"] == 1 and result["acknowledged_version"] == 1
        assert api.http.get("/api/status").json()["applied_config_version"] == 1

        result = api.http.patch("/api/config/retarget", json={"S": [1.0, 1.0, 0.9, 0.9, 1.0, 0.9, 0.9, 1.0]}, headers=AUTH).json()
        assert result["applied"] is True and result["version"] == 2
        status = api.http.get("/api/status").json()
        assert status["applied_config_version"] == 2 and status["backend"] == "daqp"
        assert status["mode"] in ("nominal", "active") and status["h_min_self"] > 0
    assert not any("rejected config update" in line for line in safety.output), "".join(safety.output[-20:])


def test_asymmetric_u_min_bounds_the_filter() -> None:
    """safety.u_min (from the API's ``u_min``) is the lower velocity bound of the QP; null: −u_max."""
    conf = load_config(environ={}, overrides={"safety": {"u_min": [-0.5] * 8, "u_max": [3.0] * 8}})
    pipeline = build_pipeline(conf)
    filt = pipeline.filter
    q0 = filt.q_cbf.copy()
    dt = 1.0 / conf.safety.rate_hz
    down = filt.step(q0 - 0.3, dt)  # far below: K (q_nom − q) saturates at u_min
    assert down.u.min() >= -0.5 - 1e-6
    assert np.isclose(down.u, -0.5, atol=1e-4).sum() >= 4
    filt.reset(q0)
    up = filt.step(q0 + 0.3, dt)  # far above: up to u_max (or the joint limit reachable in one step)
    assert up.u.max() > 2.0

    symmetric = build_pipeline(load_config(environ={}, overrides={"safety": {"u_max": [3.0] * 8}}), kinematics=pipeline.kinematics)
    assert symmetric.filter.params.u_min is None
    assert symmetric.filter.step(q0 - 0.3, dt).u.min() < -2.0
