"""Issue 9's load checks, quick variant (``make test``; ``make reliability`` runs the full one).

Real processes on loopback: the safety service at 500 Hz under a flood of HumanState messages
(300 Hz plus bursts of 1,000), and the config API under 200 requests/s with a safety service
acknowledging its changes. See :mod:`bench.reliability.load` for what each check measures.
"""

from __future__ import annotations

import pytest

from bench.reliability import load


@pytest.mark.integration
def test_quick_load_checks_pass() -> None:
    results = load.run(quick=True)
    for result in results:
        print(result)
    assert [r.name for r in results] == ["human_state_flood", "config_api_load"]
    failed = [str(r) for r in results if not r.passed]
    assert not failed, "\n".join(failed)
