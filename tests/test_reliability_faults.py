"""Faults, quick variant: kill -9 each service and the router of a running stack, and the
config store's writer mid-write (``bench.reliability.faults``; the full run is ``make reliability``).

Held to the behaviour (each service comes back, nothing else dies or stalls, nothing unsafe is
commanded, no acknowledged change is lost); the restart budgets (2 s, the router 5 s) are printed
and reported by ``make reliability``: a restart is mostly the interpreter's start-up CPU time
(``start_cpu_s``), which measures the machine (architecture §8).
"""

from __future__ import annotations

import pytest

from bench.reliability import faults


@pytest.mark.integration
def test_faults_quick() -> None:
    results = faults.run(quick=True)
    for result in results:
        print(result)
    names = {result.name for result in results}
    assert {"config_write_kill", "router_restart", "command_limits"} <= names
    assert {f"kill9_{spec.name}" for spec in faults.SERVICES} <= names
    misbehaved = [str(result) for result in results if not result.behaved]
    assert not misbehaved, "\n".join(misbehaved)
