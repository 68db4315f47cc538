"""`make demo` runs the whole simulated stack as real processes and reports truthfully."""

from __future__ import annotations

import re

import pytest

pytestmark = pytest.mark.integration


def test_demo_runs_end_to_end(spawn) -> None:
    proc = spawn("-m", "safemimic.cli", "demo", "--seconds", "4")
    assert proc.popen.wait(90) == 0, "".join(proc.output)
    out = "".join(proc.output)
    assert "services seen alive: executor, perception, safety" in out
    commands = int(re.search(r"JointCommands received: (\d+)", out).group(1))
    states = int(re.search(r"JointStates: (\d+)", out).group(1))
    assert commands > 1500 and states > 500  # 500 Hz commands, 200 Hz states for several seconds
    assert "result: OK" in out
