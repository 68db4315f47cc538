"""The safety-step benchmark's code paths (a short run; no timing is asserted), its report, the
budget check of ``make bench``, and DAQP's warm start (the flags as DAQP defines them)."""

from __future__ import annotations

import numpy as np
import pytest

from bench import safety_step
from tests.support.machine import machine
from bench.report import render, verdicts
from services.safety.qp import QPProblem
from services.safety.qp.daqp_backend import DAQP_ACTIVE, DAQP_LOWER, DaqpBackend, warm_sense


def test_warm_sense_flags_follow_daqp_sign_convention() -> None:
    # DAQP (include/constants.h, daqp_dual_init_active): λ > 0 upper bound active, λ < 0 lower bound active
    assert (DAQP_ACTIVE, DAQP_LOWER) == (1, 2)
    sense = warm_sense(np.array([0.0, 2.0, -3.0, 1e-14, -1e-14]))
    assert sense.dtype == np.intc
    assert sense.tolist() == [0, DAQP_ACTIVE, DAQP_ACTIVE | DAQP_LOWER, 0, 0]


def _problem(rng: np.random.Generator, m: int = 72) -> QPProblem:
    A = rng.normal(size=(m, 8))
    b = A @ (0.1 * rng.normal(size=8)) - rng.uniform(0, 0.3, m)
    return QPProblem(w=rng.uniform(0.5, 2, 8), u_ref=3 * rng.normal(size=8), A=A, b=b,
                     lower=-np.full(8, 2.0), upper=np.full(8, 2.0))


def test_warm_resolve_of_perturbed_problem_takes_fewer_iterations() -> None:
    rng = np.random.default_rng(3)
    warm_total = cold_total = 0
    for _ in range(20):
        p0 = _problem(rng)
        p1 = QPProblem(w=p0.w, u_ref=p0.u_ref + 1e-3 * rng.normal(size=8), A=p0.A + 1e-4 * rng.normal(size=p0.A.shape),
                       b=p0.b + 1e-4 * rng.normal(size=p0.m), lower=p0.lower, upper=p0.upper)
        warm, cold = DaqpBackend(), DaqpBackend(warm_start=False)
        first = warm.solve(p0)
        assert first.u is not None and first.active_rows + int(np.count_nonzero(np.isclose(np.abs(first.u), 2.0))) >= 2
        w, c = warm.solve(p1), cold.solve(p1)
        assert w.u is not None and c.u is not None
        np.testing.assert_allclose(w.u, c.u, atol=1e-8)  # the warm start changes the path, never the answer
        assert w.iterations < c.iterations
        warm_total += w.iterations
        cold_total += c.iterations
    assert warm_total <= 0.5 * cold_total


def test_warm_start_with_upper_bounds_active() -> None:
    # u_ref far above the box: the simple upper bounds are active (λ > 0 → flag 1 only)
    problem = QPProblem(w=np.ones(8), u_ref=np.full(8, 10.0), A=np.zeros((0, 8)), b=np.zeros(0),
                        lower=-np.ones(8), upper=np.ones(8))
    backend = DaqpBackend()
    first = backend.solve(problem)
    np.testing.assert_allclose(first.u, 1.0)
    assert backend._sense.tolist() == [DAQP_ACTIVE] * 8
    again = backend.solve(problem)
    np.testing.assert_allclose(again.u, 1.0)
    assert again.iterations < first.iterations


def test_budget_check_reads_the_key_the_benchmark_writes() -> None:
    over = {"name": "safety_step", "unit": "ms", "p50": 0.1, "p99": 2.0, "budget_p50_ms": 0.25, "budget_p99_ms": 1.0}
    assert verdicts(over) == [("p50", 0.1, 0.25, True), ("p99", 2.0, 1.0, False)]
    assert verdicts({"name": "codec", "unit": "us", "p50": 60.0, "p99": 70.0, "budget_p50": 50.0}) == [("p50", 60.0, 50.0, False)]


@pytest.fixture(scope="module")
def quick() -> dict:
    return safety_step.run(steps=240)


def test_safety_step_benchmark_quick_run(quick: dict) -> None:
    r = quick
    mk = r["mink"]
    # mink-8 sees our 8 DoF, mink-29 the full model, both with exactly our 72 pairs
    assert mk["mink8"]["nv"] == 8 and mk["mink29"]["nv"] == 29
    assert mk["same_pair_count"] and mk["verification"]["mink8"]["same_pair_set"] and mk["verification"]["mink29"]["same_pair_set"]
    assert mk["mink8"]["pairs_dropped_by_mink"] > 0  # the static-link trap is real and was undone
    assert mk["mink8"]["rows_evaluated_min"] == r["constraints"] == 72
    assert mk["mink8"]["solver_failures"] == 0
    assert mk["verification"]["mink8"]["max_distance_diff_m"] < 1e-9
    assert mk["solver_settings"] == safety_step.DAQP_SETTINGS
    assert DaqpBackend()._settings == safety_step.DAQP_SETTINGS
    fl = r["floor"]
    assert fl["ratio_step_over_floor"] == pytest.approx(fl["step_p50_ms"] / (fl["fk_p50_ms"] + fl["qp_p50_ms"]))
    assert fl["rows"] > 0 and fl["fk_p50_ms"] > 0 and fl["qp_p50_ms"] > 0
    it = r["daqp_iterations"]
    assert it["warm"]["solves"] == it["cold"]["solves"] == 240
    assert it["warm"]["mean"] < it["cold"]["mean"] < it["old_flags"]["mean"]  # on the benchmark's own problems
    assert r["oscbf_external"]["measured_here"] is False and "external" in r["oscbf_external"]["source"]
    assert "budget_p99_ms" in r and len(verdicts(r)) == 2


def test_report_renders_the_run(quick: dict) -> None:
    text = render([quick], machine(), "2026-01-01 00:00:00 +0000")
    assert "mink-8" in text and "mink-29" in text and "step / (FK + QP)" in text and "**external**" in text
    assert machine()["cpu"] in text and "load average" in text
