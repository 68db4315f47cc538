"""The CBF-QP filter (paper eqs. 7–9): rows hold, nominal when free, safe on crossing arms and an
approaching person, finite and honest about infeasibility. Real Pinocchio, real DAQP and OSQP."""

from __future__ import annotations

import numpy as np
import pytest

from services.safety.filter import movable_rows
from services.safety.qp import QPProblem, make_backend
from services.safety.qp.box import braking_box, reach_box
from shared.messages import SafetyMode
from tests.support.pipelines import DT, alone_at, pipeline_for




def cross_arm_reach(neutral: np.ndarray, seconds: float = 3.0) -> np.ndarray:
    """q_nom (T, 8) from ``neutral``: both arms reach forward and across the chest."""
    crossed = np.array([0.0, 0.1, -1.3, -1.2, 0.4, -1.3, 1.2, 0.4])
    s = np.clip(np.linspace(-0.2, 1.6, int(seconds / DT)), 0, 1)[:, None]
    ramp = np.sin(np.pi / 2 * np.minimum(s, 1.0)) ** 2
    return neutral + ramp * (crossed - neutral)


@pytest.mark.parametrize("backend", ["daqp", "osqp"])
def test_cross_arm_reach_keeps_self_clearance(backend: str) -> None:
    p = pipeline_for(backend)
    kin = p.kinematics
    p.barrier.set_external(None)
    trajectory = cross_arm_reach(kin.q_home)
    unfiltered = min(p.filter.rows_at(q).min_h(self_rows=True) for q in trajectory[::25])
    assert unfiltered < -0.05, "the scenario must collide without the CBF"
    p.filter.reset(trajectory[0])
    worst, modes = np.inf, set()
    for q_nom in trajectory:
        result = p.filter.step(q_nom, DT)
        modes.add(result.mode)
        worst = min(worst, p.filter.rows_at(result.q_cbf).min_h(self_rows=True))
        assert np.isfinite(result.q_cbf).all()
        assert (result.q_cbf >= kin.q_min - 1e-12).all() and (result.q_cbf <= kin.q_max + 1e-12).all()
    assert worst >= -1e-3
    assert SafetyMode.ACTIVE in modes and SafetyMode.HOLD not in modes


def test_solution_satisfies_rows_and_is_nominal_when_free() -> None:
    p = pipeline_for()
    rng = np.random.default_rng(2)
    kin = p.kinematics
    for _ in range(200):
        p.barrier.set_external(np.array([[0.6, 0.0, 1.0]]) + rng.normal(scale=0.2, size=(7, 2, 3)), np.full(7, 0.05))
        p.filter.reset(kin.q_home + rng.normal(scale=0.2, size=8))
        q_nom = rng.uniform(kin.q_min, kin.q_max)
        rows = p.filter.rows_at(p.filter.q_cbf)
        result = p.filter.step(q_nom, DT)
        if result.mode in (SafetyMode.NOMINAL, SafetyMode.ACTIVE):
            # every row some velocity can change (a person touching a locked thigh cannot be undone:
            # that row is left out of the QP and reported as an intrusion)
            assert (rows.A @ result.u - rows.b)[movable_rows(rows.A)].min(initial=0.0) >= -1e-4
        if result.mode is SafetyMode.NOMINAL:
            lower = np.maximum(-p.filter.params.u_max, (kin.q_min - (result.q_cbf - DT * result.u)) / DT)
            upper = np.minimum(p.filter.params.u_max, (kin.q_max - (result.q_cbf - DT * result.u)) / DT)
            np.testing.assert_allclose(result.u, np.clip(result.u_ref, lower, upper), atol=1e-6)


def test_free_space_tracks_u_ref_exactly() -> None:
    p = pipeline_for()
    alone_at(p, p.kinematics.q_home)
    q_nom = p.kinematics.q_home + 0.01
    result = p.filter.step(q_nom, DT)
    assert result.mode is SafetyMode.NOMINAL and result.active_rows == 0
    np.testing.assert_allclose(result.u, result.u_ref, atol=1e-9)


def test_person_walking_into_the_robot_is_kept_out_or_reported() -> None:
    """A human forearm capsule sweeps from 1 m in front of the robot through its chest."""
    p = pipeline_for(human_velocity_term=True)
    kin = p.kinematics
    reach_forward = np.array([0.0, 0.0, -1.4, 0.1, 1.2, -1.4, -0.1, 1.2])
    p.filter.reset(kin.q_home)
    radii = np.full(7, 0.05)
    far = np.array([[3.0, 0.0, 0.2], [3.0, 0.0, 0.3]])
    modes = []
    for k in range(1500):
        x = 1.0 - 0.6 * k * DT  # 0.6 m/s towards the robot
        velocity = np.zeros((7, 2, 3))
        velocity[2] = [[-0.6, 0, 0], [-0.6, 0, 0]]
        capsules = np.repeat(far[None], 7, axis=0)
        capsules[2] = [[x, -0.3, 1.05], [x, 0.3, 1.05]]  # a forearm held across, at chest height
        p.barrier.set_external(capsules, radii, velocities=velocity)
        result = p.filter.step(reach_forward, DT)
        modes.append(result.mode)
        h_human = p.filter.rows_at(result.q_cbf).min_h(self_rows=False)
        assert np.isfinite(result.q_cbf).all()
        assert h_human >= -1e-3 or result.mode in (SafetyMode.RELAXED, SafetyMode.HOLD)
    assert SafetyMode.ACTIVE in modes
    assert SafetyMode.RELAXED in modes  # the forearm finally passes through the torso: infeasible


def test_infeasible_rows_give_relaxed_finite_output() -> None:
    p = pipeline_for()
    kin = p.kinematics
    endpoints, _ = kin.compute(kin.q_home)
    torso = endpoints[0].copy()
    capsules = np.repeat(torso[None], 7, axis=0)  # the person is inside the robot's torso
    p.barrier.set_external(capsules, np.full(7, 0.1))
    p.filter.reset(kin.q_home)
    result = p.filter.step(kin.q_home, DT)
    assert result.mode is SafetyMode.RELAXED
    assert np.isfinite(result.u).all() and np.isfinite(result.q_cbf).all()
    assert (np.abs(result.u) <= p.filter.params.u_max + 1e-9).all()


def test_backends_agree_on_random_problems() -> None:
    rng = np.random.default_rng(11)
    daqp, osqp = make_backend("daqp"), make_backend("osqp")
    for _ in range(50):
        A = rng.normal(size=(72, 8))
        b = A @ (0.1 * rng.normal(size=8)) - rng.uniform(0, 1, 72)
        problem = QPProblem(w=rng.uniform(0.5, 2, 8), u_ref=3 * rng.normal(size=8), A=A, b=b, lower=-np.full(8, 4.0), upper=np.full(8, 4.0))
        x, y = daqp.solve(problem), osqp.solve(problem)
        assert x.u is not None and y.u is not None
        np.testing.assert_allclose(x.u, y.u, atol=1e-4)
        assert x.primal_residual <= 1e-8 and y.primal_residual <= 1e-4
    with pytest.raises(ValueError, match="unknown QP backend"):
        make_backend("cplex")


@pytest.mark.parametrize("feedforward", [True, False])
def test_ramp_is_tracked_without_lag_with_feedforward(feedforward: bool) -> None:
    """u_ref = q̇_nom + K (q_nom − q_cbf) tracks a ramp with zero steady-state error; the
    paper's u_ref = K (q_nom − q_cbf) trails it by v/K (a lag of 1/K)."""
    p = pipeline_for()
    kin = p.kinematics
    alone_at(p, kin.q_home)
    rate = np.zeros(8)
    rate[2] = rate[5] = -1.5  # both shoulders pitch forward at 1.5 rad/s (clear of every self pair)
    errors = []
    for k in range(int(1.2 / DT)):
        q_nom = kin.q_home + rate * k * DT
        result = p.filter.step(q_nom, DT, rate if feedforward else None)
        errors.append(q_nom[2] + rate[2] * DT - result.q_cbf[2])  # behind the next step's target
        assert result.mode is SafetyMode.NOMINAL
    steady = np.array(errors[-50:])
    gain = p.filter.params.gain
    if feedforward:
        assert np.abs(steady).max() < 1e-3 * abs(rate[2]) / gain, steady[-1]
    else:  # the K-only loop trails by v/K
        np.testing.assert_allclose(steady, rate[2] / gain, rtol=1e-3)


def test_a_braking_box_is_never_empty_and_keeps_its_point_nearest_rest_on_random_boxes() -> None:
    """:func:`braking_box` on random boxes as the filter builds them (a velocity box holding 0,
    narrowed for the joint limits; the acceleration bound's reach ×f from a random u_prev, some
    wholly beyond the box): never empty, within [min(u_prev, 0), max(u_prev, 0)], and its point
    nearest rest is the box's (the braking point, and the feasibility argument, unchanged)."""
    rng = np.random.default_rng(7)
    for _ in range(2000):
        n = 8
        lower, upper = -rng.uniform(0.0, 5.0, n), rng.uniform(0.0, 5.0, n)
        u_prev = rng.uniform(-8.0, 8.0, n)
        accel, factor = rng.uniform(1.0, 300.0, n), rng.choice([1.0, 2.0, 4.0, 16.0])
        low, high, _ = reach_box(u_prev, accel, factor, DT, lower, upper)
        narrow_low, narrow_high = braking_box(low, high, u_prev)
        assert (narrow_low <= narrow_high).all()
        assert (narrow_low >= np.minimum(u_prev, 0.0)).all() and (narrow_high <= np.maximum(u_prev, 0.0)).all()
        np.testing.assert_array_equal(np.clip(0.0, narrow_low, narrow_high), np.clip(0.0, low, high))


def test_a_person_capsule_whose_numbers_overflow_stops_the_robot_rather_than_losing_its_rows() -> None:
    """A forearm at 1e300 m (no message carries it now: shared.messages bounds them) would make its
    rows NaN, which no QP row can hold: the filter treats that capsule as inside a margin and stops,
    instead of imitating on without its protection."""
    p = pipeline_for()
    kin = p.kinematics
    far = np.array([[3.0, 0.0, 1.0], [3.0, 0.0, 1.2]])
    capsules = np.repeat(far[None], 7, axis=0)
    capsules[3] = [[0.35, -0.1, 1.1], [0.35, 1e300, 1.1]]
    p.barrier.set_external(capsules, np.full(7, 0.05))
    p.filter.reset(kin.q_home)
    forward = kin.q_home.copy()
    forward[2] = -1.4  # the left arm straight forward, into where the forearm would be
    result = p.filter.step(forward, DT)
    assert not np.isfinite(result.rows.h[result.rows.enabled & result.rows.soft]).all(), "the scenario's rows are NaN"
    assert result.protective_stop
    assert np.isfinite(result.q_cbf).all() and np.isfinite(result.u).all()
    far_only = np.repeat(far[None], 7, axis=0)  # the same person, finite: no stop
    p.barrier.set_external(far_only, np.full(7, 0.05))
    p.filter.reset(kin.q_home)
    assert not p.filter.step(forward, DT).protective_stop
