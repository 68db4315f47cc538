"""The load checks, quick variant (``make test``; ``make reliability`` runs the full one).

Real processes on loopback: the safety service at 500 Hz under a flood of HumanState messages
(300 Hz plus bursts of 1,000), and the config API under 200 requests/s with a safety service
acknowledging its changes. See :mod:`bench.reliability.load` for what each check measures.

Both are held to their behaviour always, and to their timing budgets (≥ 99 % of the deadlines,
200 requests/s at p99 < 50 ms) when the machine wakes a control thread on time
(``machine_wake``, measured just before the flood): on a VM whose idle vCPUs halt, a FIFO thread
doing nothing but sleep is woken up to 3 ms late, and a deadline budget then measures the host
(architecture §8: budgets belong to reports, ``make reliability`` reports them whatever the machine).
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
    misbehaved = [str(r) for r in results if not r.behaved]
    assert not misbehaved, "\n".join(misbehaved)
    wake = results[0].figures["machine_wake"]
    print(f"machine wake-up latency: {wake}")
    if wake["keeps_time"]:
        missed = [str(r) for r in results if not r.passed]
        assert not missed, "\n".join(missed)
