"""`make demo` runs the whole simulated stack as real processes, reports truthfully and stops cleanly."""

from __future__ import annotations

import importlib.util
import json
import os
import re
import signal
import time
import urllib.request
from pathlib import Path

import pytest

from safemimic.stack import SERVICES
from tests.support.team import MOCAP_DIR

pytestmark = pytest.mark.integration

SUMMARY_KEYS = {"commands_published", "min_h_self", "min_h_human", "modes", "latency_ms_p99", "nan_count"}
#: the live Rerun viewer too where rerun-sdk (the viz extra, in dev) is installed
CHILDREN = ("router", *(spec.name for spec in SERVICES),
            *(("viewer",) if importlib.util.find_spec("rerun") is not None else ()))


def _pids(output: str) -> dict[str, int]:
    """Child pids from the demo's ``$ safemimic NAME ... (pid N)`` lines."""
    return {m.group(1): int(m.group(2)) for m in re.finditer(r"^\$ safemimic (\S+) .*\(pid (\d+)\)$", output, re.M)}


def _running_in_groups(pgids: set[int]) -> list[str]:
    """Live (non-zombie) processes whose process group is one of ``pgids``."""
    found = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:  # exited meanwhile
            continue
        state, pgrp = fields[0], int(fields[2])
        if pgrp in pgids and state != "Z":
            found.append(f"{stat.parent.name} ({state})")
    return found


def test_demo_runs_for_a_duration_and_writes_the_summary(spawn, tmp_path: Path) -> None:
    summary_path = tmp_path / "summary.json"
    proc = spawn("-m", "safemimic.cli", "demo", "--duration", "5", "--summary-json", str(summary_path), "--api-port", "0")
    console = proc.wait_for(lambda line: line.startswith("console: "), 90)
    url = re.search(r"(http://\S+)/", console).group(1)
    with urllib.request.urlopen(f"{url}/api/health", timeout=10) as response:  # the printed console is real
        assert json.load(response)["status"] == "ok"
    assert proc.popen.wait(90) == 0, "".join(proc.output)
    out = "".join(proc.output)
    assert set(_pids(out)) == set(CHILDREN)
    assert "health (liveliness): router up" in out and "config_api up" in out
    assert "result: OK" in out
    # secure by default: every session over mutual TLS with a throwaway CA made in the run folder
    assert re.search(r"^router: tls/127\.0\.0\.1:\d+$", out, re.M), out
    certs = Path(re.search(r"^certs: (\S+)", out, re.M).group(1))
    assert {"ca.pem", "router.pem", "safety.key", "access_control.json5"} <= {p.name for p in certs.iterdir()}
    assert "--connect tls/127.0.0.1:" in out and f"--certs {certs}" in out
    assert "INSECURE" not in out
    summary = json.loads(summary_path.read_text())
    assert SUMMARY_KEYS <= set(summary) and summary["ok"] is True
    assert summary["commands_published"] > 1500  # 500 Hz for 5 s
    assert summary["commands_received"] <= summary["commands_published"]
    assert sum(summary["modes"].values()) == summary["commands_received"]
    assert set(summary["modes"]) <= {"nominal", "active", "relaxed", "hold"}
    assert summary["nan_count"] == 0
    # the CBF keeps every barrier non-negative (to solver tolerance) through the paper's scenarios
    assert summary["min_h_self"] is not None and summary["min_h_self"] >= -2e-3
    assert summary["min_h_human"] is not None and summary["min_h_human"] >= -2e-3
    assert summary["latency_ms_p99"] > 0 and summary["latency_samples"] > 50  # 30 fps skeletons
    assert summary["exit_codes"].keys() == set(CHILDREN)


def test_demo_replays_demo_skeleton(spawn, tmp_path: Path) -> None:
    clips = sorted(MOCAP_DIR.glob("*.npz"))
    if not clips:
        pytest.skip(f"no motion-capture clip in {MOCAP_DIR} (the team's shared data folder is missing)")
    proc = spawn("-m", "safemimic.cli", "demo", "--duration", "3", "--api-port", "0", env={"DEMO_SKELETON": str(clips[0])})
    assert proc.popen.wait(90) == 0, "".join(proc.output)
    out = "".join(proc.output)
    assert f"person: {clips[0]}" in out and "result: OK" in out
    logs = Path(re.search(r"logs: (\S+)$", out, re.M).group(1))
    ready = next(json.loads(line) for line in (logs / "perception.log").read_text().splitlines()
                 if line.startswith('{"event": "ready"'))
    assert ready["source"] == f"replay {clips[0].name}"


def test_demo_insecure_runs_the_open_bus_with_a_warning(spawn) -> None:
    proc = spawn("-m", "safemimic.cli", "demo", "--insecure", "--duration", "2", "--api-port", "0")
    assert proc.popen.wait(90) == 0, "".join(proc.output)
    out = "".join(proc.output)
    assert re.search(r"^router: tcp/127\.0\.0\.1:\d+$", out, re.M) and "WARNING: --insecure" in out
    assert "certs: " not in out and "--insecure" in out.split("$ safemimic safety", 1)[1].splitlines()[0]
    assert "result: OK" in out


def test_demo_refuses_a_bad_demo_skeleton(spawn, tmp_path: Path) -> None:
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"not a recording")
    proc = spawn("-m", "safemimic.cli", "demo", "--duration", "3", env={"DEMO_SKELETON": str(bad)})
    assert proc.popen.wait(30) == 2
    assert "DEMO_SKELETON" in "".join(proc.output)


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGKILL], ids=["ctrl-c", "killed"])
def test_demo_leaves_no_process_behind(spawn, sig: signal.Signals) -> None:
    """Ctrl-C stops every child group cleanly; even a SIGKILLed demo orphans nothing (PDEATHSIG)."""
    proc = spawn("-m", "safemimic.cli", "demo", "--api-port", "0")
    # the first status row (t ≈ 1 s; later on a loaded machine): the stack runs
    proc.wait_for(lambda line: re.match(r"\s+\d+\.\d +(nominal|active|relaxed|hold) ", line) is not None, 90)
    pids = _pids("".join(proc.output))
    assert set(pids) == set(CHILDREN) and not any(p == proc.popen.pid for p in pids.values())
    assert len(_running_in_groups(set(pids.values()))) >= len(CHILDREN)
    os.kill(proc.popen.pid, sig)
    code = proc.popen.wait(30)
    deadline = time.monotonic() + 15
    while _running_in_groups(set(pids.values())) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert _running_in_groups(set(pids.values())) == [], "".join(proc.output)
    if sig == signal.SIGINT:
        out = "".join(proc.output)
        assert code == 0 and "stopping (Ctrl-C)" in out and "result: OK" in out, out
