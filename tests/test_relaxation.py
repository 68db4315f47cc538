"""Prioritised relaxation: when a person moves into the robot faster than it can
retreat, the self rows and joint barriers hold, every person row keeps at least A_i u ≥ min(b_i, 0)
(the robot never closes in), the total violation is the least possible, and the problem is feasible
by construction (u = 0, σ = max(b, 0)); the relaxation's own tests run with
``safety.on_intrusion: retreat``, where a person inside a margin is retreated from. With the default
``stop`` that person stops the robot instead, never closer, no retreat; with ``stop_on_give_way``
so does one moving in faster than the robot can retreat. Random states on the real robot model,
real Pinocchio, DAQP and OSQP; the least violation is checked against SciPy's LP solver."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from scipy.optimize import linprog

from services.safety.barriers.joints import JointBarrier
from services.safety.barriers.static import StaticCapsuleBarrier
from services.safety.filter import ACCEL_BOUND, MOTOR_WIDENING, movable_rows
from services.safety.protective_stop import STILL_JOINT_SPEED
from services.safety.human_memory import padded, swept_capsules
from services.safety.qp import QPProblem
from services.safety.relaxation import RELAXED_TOL, LexicographicSolver
from services.safety.standoff import apply_standoff
from shared.messages import SafetyMode
from shared.names import CAPSULE_NAMES
from tests.support.pipelines import DT, alone_at, pipeline_for, random_safe_state

TOL = 1e-6
FOREARM = CAPSULE_NAMES.index("left_forearm")



def stacked(p, q):
    """(A, b, soft) of the rows the filter stacks at ``q``: every barrier's, the person rows' b raised by
    the standoff (services.safety.standoff), without the self margin's shift of the hard rows."""
    blocks = p.filter.blocks_at(q)
    b, soft = np.concatenate([block.b for block in blocks]), np.concatenate([block.soft for block in blocks])
    params = p.filter.params
    apply_standoff(b, np.concatenate([block.h for block in blocks]), soft, params.gamma, params.human_standoff_m)
    return np.vstack([block.A for block in blocks]), b, soft


def random_intrusion(p, rng: np.random.Generator, *others, speeds: tuple[float, float] = (1.0, 3.0),
                     q: np.ndarray | None = None):
    """A random joint state whose self rows and joint barriers hold (or ``q``), and a person's capsules
    pushed into the margin of the robot's left forearm at ``speeds`` (m/s, uniform; 1–3 by default)
    toward it, as measured and as seen (in ``others``' barriers too)."""
    kin = p.kinematics
    q = random_safe_state(p, rng) if q is None else q
    endpoints, _ = kin.compute(q)
    forearm = endpoints[FOREARM]
    centre = forearm.mean(axis=0) + rng.normal(scale=0.03, size=3)
    direction = rng.normal(size=3)
    direction /= np.linalg.norm(direction)
    capsules = np.repeat(np.stack([centre - 0.1 * direction, centre + 0.1 * direction])[None], 7, axis=0)
    capsules += rng.normal(scale=0.05, size=(7, 1, 3))
    toward = forearm.mean(axis=0) - capsules.mean(axis=1)
    speed = rng.uniform(*speeds)
    velocities = np.repeat((speed * toward / np.linalg.norm(toward, axis=1, keepdims=True))[:, None], 2, axis=1)
    for pipeline in (p, *others):
        pipeline.barrier.set_external(capsules, np.full(7, 0.06), np.ones(7, bool), velocities, seen_speed=speed)
    return q


def least_violation(A, b, soft, lower, upper, relax_penalty: float) -> float:
    """min Σ c_i σ_i s.t. A u + σ ≥ b, 0 ≤ σ ≤ max(b, 0), lower ≤ u ≤ upper (SciPy's HiGHS LP)."""
    m, n = A.shape
    cost = np.concatenate([np.zeros(n), np.where(soft, 1.0, relax_penalty)])
    result = linprog(cost, A_ub=-np.hstack([A, np.eye(m)]), b_ub=-b,
                     bounds=[*zip(lower, upper), *((0.0, max(v, 0.0)) for v in b)], method="highs")
    assert result.status == 0, result.message
    return float(result.fun)


def test_the_lexicographic_solve_is_feasible_and_least_violating_on_random_row_sets() -> None:
    """:class:`LexicographicSolver` alone, on random rows no u satisfies together (hard rows that
    hold at 0, soft rows demanding more than the velocity box gives): the feasibility argument of
    its docstring (the box holds 0, so u = 0 with σ = max(b, 0) is a solution) means it always
    returns a finite u within the box; the hard rows hold, no soft row falls below min(b_i, 0), the
    slacks cover exactly what u leaves, and their sum is SciPy's least violation (the tracking stage
    never trades violation for tracking)."""
    rng = np.random.default_rng(35)
    solver, penalty = LexicographicSolver(), 100.0
    gave = 0
    for _ in range(60):
        n, m = 8, int(rng.integers(4, 20))
        A = rng.normal(size=(m, n))
        soft = rng.random(m) < 0.5
        b = np.where(soft, rng.uniform(-1.0, 40.0, m), -rng.uniform(0.0, 2.0, m))  # hard rows hold at u = 0
        upper = rng.uniform(0.5, 3.0, n)
        lower = -rng.uniform(0.5, 3.0, n)
        problem = QPProblem(w=np.ones(n), u_ref=rng.uniform(-5.0, 5.0, n), A=A, b=b, lower=lower, upper=upper)
        result = solver.solve(problem, soft, np.zeros(m), penalty)
        assert result.u is not None and np.isfinite(result.u).all()
        u = result.u
        assert (lower - TOL <= u).all() and (u <= upper + TOL).all()
        lhs = A @ u
        assert (lhs[~soft] >= b[~soft] - TOL).all(), "a hard row gave way"
        assert (lhs[soft] >= np.minimum(b[soft], 0.0) - TOL).all(), "a soft row fell below its floor"
        assert np.allclose(result.slack, np.maximum(b - lhs, 0.0), atol=1e-5)
        least = least_violation(A, b, soft, lower, upper, penalty)
        assert result.slack[soft].sum() == pytest.approx(least, abs=1e-4 * max(1.0, least))
        gave += result.gave
    assert gave >= 30, "the random rows must mostly be infeasible together"


def test_in_an_acceleration_bound_the_braking_point_keeps_the_hard_rows_on_random_row_sets() -> None:
    """:class:`LexicographicSolver` in a box around a moving command u_prev that excludes rest (an
    acceleration bound), with hard rows that hold (b ≤ 0) and that some u of the box keeps, and soft
    rows demanding a retreat: where the box's point nearest rest, clip(0), breaks a hard row (an arm
    sliding along its own body, braked joint by joint, would turn into it), the braking point ū is
    instead the box's point nearest rest that keeps them, so the solve still succeeds in that box
    (the filter widens the bound only when it fails): u within the box, the hard rows held, no soft
    row below min(b_i, 0, A_i ū). A box no u of which keeps a hard row fails at once."""
    rng = np.random.default_rng(77)
    solver = LexicographicSolver()
    turned = 0
    for _ in range(80):
        n, m = 8, int(rng.integers(6, 20))
        u_prev = rng.uniform(-3.0, 3.0, n)
        reach = rng.uniform(0.05, 0.5, n)
        lower, upper = u_prev - reach, u_prev + reach
        keeps = rng.uniform(lower, upper)  # a point of the box every hard row holds at
        A = rng.normal(size=(m, n))
        soft = rng.random(m) < 0.5
        b = np.where(soft, rng.uniform(-1.0, 10.0, m), np.minimum(A @ keeps - rng.uniform(0.0, 0.3, m), 0.0))
        problem = QPProblem(w=rng.uniform(0.5, 2.0, n), u_ref=rng.uniform(-5.0, 5.0, n), A=A, b=b, lower=lower, upper=upper)
        brake, _ = solver.braking(problem, b, ~soft)
        assert brake is not None
        assert (lower - TOL <= brake).all() and (brake <= upper + TOL).all()
        assert (A[~soft] @ brake >= b[~soft] - TOL).all()
        nearest = np.clip(0.0, lower, upper)
        if (A[~soft] @ nearest < b[~soft] - TOL).any():
            turned += 1
            assert problem.w @ brake**2 <= problem.w @ keeps**2 + TOL  # nearer rest than any other point keeping them
        else:
            np.testing.assert_array_equal(brake, nearest)
        result = solver.solve(problem, soft, np.zeros(m), 100.0)
        assert result.u is not None and np.isfinite(result.u).all()
        assert (lower - TOL <= result.u).all() and (result.u <= upper + TOL).all()
        lhs = A @ result.u
        assert (lhs[~soft] >= b[~soft] - TOL).all(), "a hard row gave way"
        assert (lhs[soft] >= np.minimum(np.minimum(b[soft], 0.0), A[soft] @ brake) - TOL).all()
    assert turned >= 20, "clip(0) must often break a hard row for this test to mean anything"
    beyond = QPProblem(w=np.ones(2), u_ref=np.zeros(2), A=np.array([[1.0, 0.0], [0.0, 1.0]]), b=np.array([-0.1, 5.0]),
                       lower=np.array([-3.0, -1.0]), upper=np.array([-2.0, 1.0]))
    hard = np.array([True, False])
    assert solver.braking(beyond, beyond.b, hard)[0] is None  # u_0 ≥ −0.1 nowhere in [−3, −2]
    assert solver.solve(beyond, ~hard, np.zeros(2), 100.0).u is None


@pytest.mark.parametrize(("backend", "standoff"), [("daqp", 0.0), ("osqp", 0.0), ("daqp", 0.1)])
def test_random_intrusions_keep_self_rows_and_never_close_in_on_the_person(backend: str, standoff: float) -> None:
    """Random intrusions, rows infeasible together: never the numerical-failure hold, the self rows and
    joint barriers kept, no person row below min(b_i, 0). With the standoff (``safety.human_standoff_m``)
    its rows through rest once made DAQP report the relaxed problem infeasible (services.safety.standoff,
    the creep)."""
    p = pipeline_for(backend, on_intrusion="retreat", human_standoff_m=standoff)
    rng = np.random.default_rng(16)
    relaxed = 0
    for _ in range(40):
        q = random_intrusion(p, rng)
        A, b, soft = stacked(p, q)
        p.filter.reset(q)
        q_nom = rng.uniform(p.kinematics.q_min, p.kinematics.q_max)  # imitation pulling anywhere
        result = p.filter.step(q_nom, DT)
        u = result.u
        assert np.isfinite(u).all() and np.isfinite(result.q_cbf).all()
        assert result.mode is not SafetyMode.HOLD
        tol = 1e-6 if backend == "daqp" else 2e-3
        lhs = A @ u
        assert (lhs[~soft] >= b[~soft] - tol).all(), "a self row or joint barrier gave way"
        assert (lhs[soft] >= np.minimum(b[soft], 0.0) - tol).all(), "the robot closed in on a person capsule"
        if result.mode is SafetyMode.RELAXED and result.relaxed.any():
            relaxed += 1
            assert result.rows.soft[result.relaxed].all(), "only person rows give way"
    assert relaxed >= 10, "the intrusions must make the rows infeasible often"


def test_the_relaxed_problem_is_feasible_by_construction_and_least_violating() -> None:
    """On random states: u = 0, σ = max(b, 0) satisfies every constraint; the filter's total
    violation equals the LP's minimum (without the self margin, which only shifts some rows' b:
    :func:`test_self_rows_aim_the_margin_beyond_phi`)."""
    p = pipeline_for(self_margin=0.0, on_intrusion="retreat")
    rng = np.random.default_rng(61)
    params = p.filter.params
    checked = 0
    for _ in range(40):
        q = random_intrusion(p, rng)
        A, b, soft = stacked(p, q)
        upper = np.minimum(params.u_max, (p.kinematics.q_max - q) / DT)
        lower = np.minimum(np.maximum(-params.u_max, (p.kinematics.q_min - q) / DT), upper)
        assert (lower <= 0.0).all() and (upper >= 0.0).all()
        sigma0 = np.maximum(b, 0.0)
        assert (A @ np.zeros(A.shape[1]) + sigma0 >= b).all()  # the feasibility argument
        p.filter.reset(q)
        result = p.filter.step(rng.uniform(p.kinematics.q_min, p.kinematics.q_max), DT)
        if result.mode is not SafetyMode.RELAXED or not result.relaxed.any():
            continue
        violation = np.maximum(b - A @ result.u, 0.0)
        cost = np.where(soft, 1.0, params.relax_penalty)
        best = least_violation(A, b, soft, lower, upper, params.relax_penalty)
        assert float(cost @ violation) <= best + 1e-3 * max(1.0, best), (cost @ violation, best)  # ε-regularised
        checked += 1
    assert checked >= 10


def test_a_person_giving_way_stops_the_imitation_the_retreat_does_not_need() -> None:
    """Protective stop: while a person row gives way (the person moves into the left forearm faster
    than it can retreat), the freedom the rows leave is not spent imitating: the right arm, which
    the imitation pulls anywhere and no binding row needs, brakes to rest (after a reset the box
    holds 0, so u = 0 there) instead of following u_ref. Without the self margin, which lets a hard
    row inside it push out (:func:`test_self_rows_aim_the_margin_beyond_phi`), so that the rows at
    their bound are those of ``stacked``."""
    p = pipeline_for(self_margin=0.0, on_intrusion="retreat")
    rng = np.random.default_rng(17)
    names = p.kinematics.joint_names
    right = [names.index(f"right_{j}_joint") for j in ("shoulder_pitch", "shoulder_roll", "elbow")]
    checked = 0
    for _ in range(60):
        q = random_intrusion(p, rng)
        A, b, soft = stacked(p, q)
        p.filter.reset(q)
        q_nom = q.copy()
        q_nom[right] = rng.uniform(p.kinematics.q_min, p.kinematics.q_max)[right]
        result = p.filter.step(q_nom, DT)
        if result.mode is not SafetyMode.RELAXED or not result.relaxed.any():
            continue
        binding = A @ result.u - b <= 1e-6  # at their bound or given way
        if np.abs(A[binding][:, right]).max() > 1e-9 or np.abs(result.u_ref[right]).max() < 0.1:
            continue  # a row needs the right arm, or the imitation does not ask it to move
        lhs = A @ result.u
        assert (lhs[~soft] >= b[~soft] - 1e-6).all() and (lhs[soft] >= np.minimum(b[soft], 0.0) - 1e-6).all()
        np.testing.assert_allclose(result.u[right], 0.0, atol=1e-6)
        checked += 1
    assert checked >= 5


THIGH = CAPSULE_NAMES.index("left_thigh")


def person_in_the_legs(p, rng: np.random.Generator, q: np.ndarray, inside: bool = True, walking: float = 0.0) -> None:
    """The person's capsules at ``q``: their torso through the robot's left thigh and the other six
    around the left forearm closing at 1–3 m/s (``inside``), or only their torso, 0.3 m in front of
    the thigh's surface, walking toward it at ``walking`` m/s."""
    endpoints, _ = p.kinematics.compute(q)
    thigh = endpoints[THIGH].mean(axis=0) + ([0.0, 0.0, 0.0] if inside else [0.3 + 0.06 + 0.05, 0.0, 0.0])
    forearm = endpoints[FOREARM].mean(axis=0)
    capsules = forearm + rng.normal(scale=0.08, size=(7, 2, 3))
    capsules[0] = thigh + [0.0, 0.0, -0.3], thigh + [0.0, 0.0, 0.3]
    toward = forearm - capsules.mean(axis=1)
    velocities = np.repeat((rng.uniform(1.0, 3.0) * toward / np.linalg.norm(toward, axis=1, keepdims=True))[:, None], 2, axis=1)
    velocities[0] = [-walking, 0.0, 0.0]
    p.barrier.set_external(capsules, np.full(7, 0.05), np.arange(7) == 0 if not inside else np.ones(7, bool), velocities)


def stop_rows(p, full_torque: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(A, b, soft, brake) of ``p``'s next step, a protective stop, from its q_cbf and previous
    command: the stacked rows as the barriers write them and the hardest braking the stop's box
    allows: a stop decided from the rows, the acceleration bound ×2 (the motors' full torque); not
    ``full_torque`` (a stop when person rows give way, decided in the relaxed solve, or one backing
    out, whose relaxed solve starts at ×1), the bound."""
    q = p.filter.q_cbf.copy()
    A, b, soft = stacked(p, q)
    boxes = p.filter._boxes(q, DT)  # noqa: SLF001
    lower, upper, _ = next(boxes)
    if full_torque:
        lower, upper, _ = next(boxes)
    return A, b, soft, np.clip(0.0, lower, upper)


def assert_a_stop_that_never_closes_in(result, A: np.ndarray, b: np.ndarray, soft: np.ndarray,
                                       brake: np.ndarray) -> None:
    """``result`` (a step from the rows of :func:`stop_rows`) is a protective stop aiming at rest
    (u_ref = 0), finite, not HOLD; the hard rows hold and no person row is approached faster than
    braking as hard as the motors allow (its floor min(b_i, 0, A_i ū), ū the point nearest rest of
    the bound ×2, retreat demands b_i > 0 included; a stop's plain step keeps min(b_i, 0) itself)."""
    assert result.protective_stop and np.isfinite(result.u).all() and result.mode is not SafetyMode.HOLD
    np.testing.assert_array_equal(result.u_ref, 0.0)
    lhs = A @ result.u
    assert (lhs[~soft] >= b[~soft] - TOL).all(), "a self row or joint barrier gave way"
    if "accel_max" not in result.gave_way:
        floor = np.minimum(np.minimum(b[soft], 0.0), A[soft] @ brake)
        assert (lhs[soft] >= floor - TOL).all(), "the robot closed in on a person capsule"


def assert_stops_without_retreat(p, q: np.ndarray, q_nom: np.ndarray, u_prev: np.ndarray,
                                 give_way: bool = False) -> None:
    """From ``q`` moving at ``u_prev`` with the imitation pulling to ``q_nom`` and the person the
    barrier holds: the step is a protective stop aiming at rest (u_ref = 0), finite, not HOLD; the
    hard rows hold and no person row is approached faster than braking as hard as the acceleration
    bound allows (its floor min(b_i, 0), retreat demands b_i > 0 included: none is demanded); every
    step only brakes, each joint's velocity between rest and the step before's, never faster and
    never turned back (where the relaxed solve takes over too); the robot is at rest within 0.5 s.
    ``give_way``: the stop is the one when person rows give way (:func:`stop_rows`)."""
    p.filter.reset(q)
    p.filter._u_prev = u_prev.copy()  # noqa: SLF001 (moving)
    rows = stop_rows(p, full_torque=not give_way)
    result = p.filter.step(q_nom, DT, np.zeros_like(q_nom))
    assert_a_stop_that_never_closes_in(result, *rows)
    for _ in range(round(0.5 / DT)):
        assert_only_brakes(result, u_prev)
        u_prev = result.u
        result = p.filter.step(q_nom, DT, np.zeros_like(q_nom))
        if not np.abs(result.u).max() > 1e-6:
            break
    np.testing.assert_allclose(result.u, 0.0, atol=1e-6)  # at rest within 0.5 s


def assert_only_brakes(result, u_prev: np.ndarray) -> None:
    """A protective stop's step (not backing out) only brakes: each u_j between 0 and u_prev,j."""
    assert result.protective_stop and not result.backing_out
    assert (result.u >= np.minimum(u_prev, 0.0) - 1e-9).all() and (result.u <= np.maximum(u_prev, 0.0) + 1e-9).all()


def test_a_person_at_the_legs_stops_the_robot_without_a_retreat_on_random_states() -> None:
    """Protective stop at the fixed body: on random states (the hard rows holding) with the robot
    moving and the imitation pulling anywhere, a person inside the margin of a thigh (which no
    joint moves) makes the step aim at rest: u_ref = 0, the hard rows hold, no person row is
    approached (A_i u ≥ min(b_i, 0) against the rows as the barrier wrote them, b_i = −γ h_i > 0
    included: no retreat is demanded, none is forbidden; closing no faster than braking within the
    acceleration bound), the output is finite and once the bound has braked it the robot stands
    still. The same person 0.3 m in front of the thigh does not stop it standing or walking toward
    it at 0.5 m/s, but does at 2 m/s: the row anticipates them within the look-ahead
    (h < a (T + 1/γ)), so the robot brakes before they arrive. With the shipped self margin (its
    push-out of a row inside the band keeps no joint moving: at rest within 0.5 s all the same),
    and ``on_intrusion: retreat``, so that only this rule stops the robot (at a random state the
    person's torso in front of the legs may be inside an arm's margin, which the default intrusion
    stop answers too)."""
    p = pipeline_for(on_intrusion="retreat")
    rng = np.random.default_rng(26)
    kin = p.kinematics
    for _ in range(25):
        q = random_safe_state(p, rng)
        person_in_the_legs(p, rng, q)
        q_nom = rng.uniform(kin.q_min, kin.q_max)
        assert_stops_without_retreat(p, q, q_nom, 0.5 * rng.uniform(-p.filter.params.u_max, p.filter.params.u_max))
        for walking, stops in ((0.0, False), (0.5, False), (2.0, True)):  # within the look-ahead at 2 m/s
            person_in_the_legs(p, rng, p.filter.q_cbf, inside=False, walking=walking)
            assert p.filter.step(q_nom, DT, np.zeros_like(q_nom)).protective_stop is stops, walking


def test_a_protective_stop_brakes_with_the_motors_full_torque_on_random_states() -> None:
    """A stop decided from the rows (here a person walking into the legs at 2 m/s, who reaches the
    thigh's margin within the look-ahead), where its rows are feasible, brakes within twice the
    acceleration bound, the motors' full torque (``safety.accel_max`` is about half of it): from a
    robot moving at up to a quarter of its velocity bounds the command changes by at most 2·a·Δt per
    joint and by more than a·Δt on some joint (the bound alone would take twice as long to stop, the
    arm moving on into where the person, seen a camera latency ago, already is), and only brakes
    (each joint between rest and its velocity before). Where the rows are infeasible the relaxed
    solve brakes from the bound ×2 on too: unless it names the bound as given way, no joint's
    command changes by more than 2·a·Δt there either, and some by more than a·Δt."""
    p = pipeline_for(on_intrusion="retreat")
    rng = np.random.default_rng(41)
    a, harder, relaxed_harder = p.filter.params.accel_max, 0, 0
    for _ in range(40):
        q = random_safe_state(p, rng)
        person_in_the_legs(p, rng, q, inside=False, walking=2.0)
        p.filter.reset(q)
        u_prev = 0.25 * rng.uniform(-p.filter.params.u_max, p.filter.params.u_max)
        p.filter._u_prev = u_prev.copy()  # noqa: SLF001 (moving)
        result = p.filter.step(rng.uniform(p.kinematics.q_min, p.kinematics.q_max), DT, np.zeros(8))
        assert_only_brakes(result, u_prev)
        if ACCEL_BOUND in result.gave_way:  # a wider relaxed box, or a joint's reach wholly beyond its
            continue  # velocity box (braking for a joint limit)
        change = np.abs(result.u - u_prev)
        assert (change <= MOTOR_WIDENING * a * DT + 1e-9).all()
        if result.mode is SafetyMode.RELAXED:  # the rows infeasible together: the relaxed solve at ×2
            relaxed_harder += bool((change > 1.01 * a * DT).any())
            continue
        assert (change > 1.01 * a * DT).any()
        harder += 1
    assert harder >= 10 and relaxed_harder >= 10


def test_a_person_inside_a_margin_stops_the_robot_without_a_retreat_on_random_states() -> None:
    """The intrusion stop (``safety.on_intrusion: stop``, the default): a person pushed into the
    left forearm's margin at 1–3 m/s, on random states with the robot moving and the imitation
    pulling anywhere: the step is a protective stop aiming at rest (u_ref = 0), the hard rows hold,
    no person row is approached faster than braking within the acceleration bound (its floor
    min(b_i, 0) against the rows as the barrier wrote them, retreat demands b_i > 0 included: none
    is demanded), the output is finite and the robot is at rest within 0.5 s. The same states with
    ``retreat`` are no stop, and some violated row is retreated from; the person outside every
    margin stops nothing. (With ``retreat`` the person may still reach a thigh's margin, which
    stops the robot whatever ``on_intrusion`` says: those states are not counted.)"""
    stop, retreat = pipeline_for(), pipeline_for(on_intrusion="retreat")
    rng = np.random.default_rng(28)
    retreated = 0
    for _ in range(25):
        q = random_intrusion(stop, rng, retreat)
        A, b, soft = stacked(stop, q)
        assert stop.barrier.last_rows.min_h(self_rows=False) < -1e-3  # inside the forearm's margin
        q_nom = rng.uniform(stop.kinematics.q_min, stop.kinematics.q_max)
        assert_stops_without_retreat(stop, q, q_nom, 0.5 * rng.uniform(-stop.filter.params.u_max, stop.filter.params.u_max))
        retreat.filter.reset(q)
        result = retreat.filter.step(q_nom, DT, np.zeros_like(q_nom))
        if result.protective_stop:  # the person also reaches a thigh, which no joint moves: the other stop
            continue
        violated = soft & (b > 1e-6)
        retreated += bool((A[violated] @ result.u > 1e-6).any())
    assert retreated >= 10, "with retreat, violated rows must be retreated from"
    alone = pipeline_for()
    alone_at(alone, alone.kinematics.q_home)
    endpoints, _ = alone.kinematics.compute(alone.kinematics.q_home)
    far = endpoints[FOREARM].mean(axis=0) + [0.5, 0.0, 0.0]  # 0.5 m in front of the forearm
    alone.barrier.set_external(np.repeat(np.stack([far, far + [0.0, 0.0, 0.3]])[None], 7, axis=0), np.full(7, 0.05))
    assert not alone.filter.step(alone.kinematics.q_home, DT).protective_stop


@pytest.mark.parametrize("standoff", [0.0, 0.1])
def test_a_person_standing_inside_a_margin_is_backed_out_of_on_random_states(standoff: float) -> None:
    """Backing out (``safety.intrusion_backout_mps``, default 0.05 m/s): a person standing still
    with capsules inside the left forearm's margin, on random states with the robot moving and the
    imitation pulling anywhere. Every step until no person row is inside is a protective stop
    aiming at rest whose hard rows hold and whose person rows keep their floor, finite; the rows
    the person is inside are opened (their h grows), and
    on most states the stop ends within 3 s, the robot out of the margin. The same person walking in
    at 0.2 m/s, or with backing out off, stops the robot where it is and it stays inside; so does a
    still person inside the torso's margin. A capsule held from memory makes the person's speed
    unknown. The same with a standoff (``safety.human_standoff_m``; with its rows exactly at b = 0
    within D, before its creep, nothing was backed out of)."""
    p = pipeline_for(human_standoff_m=standoff)
    off = pipeline_for(intrusion_backout_mps=0.0, human_standoff_m=standoff)
    walking = pipeline_for(human_standoff_m=standoff)
    rng = np.random.default_rng(41)
    ended = 0
    for _ in range(15):
        q = random_intrusion(p, rng, off, speeds=(0.0, 0.0))
        assert p.barrier.person_speed == 0.0
        stacked(p, q)  # the rows at q
        h0 = p.barrier.last_rows.h.copy()
        inside = p.barrier.last_rows.person_inside(-1e-3)
        assert inside.any()
        q_nom = rng.uniform(p.kinematics.q_min, p.kinematics.q_max)
        u_prev = 0.5 * rng.uniform(-p.filter.params.u_max, p.filter.params.u_max)
        for pipeline in (p, off):
            pipeline.filter.reset(q)
            pipeline.filter._u_prev = u_prev.copy()  # noqa: SLF001 (moving)
        for step in range(round(3.0 / DT)):
            rows, backing_rows = stop_rows(p), stop_rows(p, full_torque=False)
            result = p.filter.step(q_nom, DT, np.zeros_like(q_nom))
            if not result.protective_stop:
                ended += 1
                assert not p.barrier.last_rows.person_inside(-1e-3).any()
                break
            assert_a_stop_that_never_closes_in(result, *(backing_rows if result.backing_out else rows))
        assert (p.barrier.last_rows.h[inside] > h0[inside] + 1e-3).any(), "nothing was backed out of"
        for _ in range(round(1.0 / DT)):
            result = off.filter.step(q_nom, DT, np.zeros_like(q_nom))
        assert result.protective_stop and off.barrier.last_rows.person_inside(-1e-3).any()
        np.testing.assert_allclose(result.u, 0.0, atol=1e-6)  # stood still where it was
    assert ended >= 10, f"the stop ended on {ended} of 15 states"
    q = random_intrusion(walking, rng, speeds=(0.2, 0.2))
    assert walking.barrier.person_speed == pytest.approx(0.2)
    assert_stops_without_retreat(walking, q, q, np.zeros_like(q))
    home = p.kinematics.q_home
    torso = p.kinematics.compute(home)[0][CAPSULE_NAMES.index("torso")].mean(axis=0)
    p.barrier.set_external(np.repeat(np.stack([torso, torso + [0.3, 0.0, 0.0]])[None], 7, axis=0), np.full(7, 0.05),
                           velocities=np.zeros((7, 2, 3)), seen_speed=0.0)
    assert p.barrier.person_speed == 0.0
    assert_stops_without_retreat(p, home, home, np.zeros_like(home))
    held = np.arange(7) == 3
    p.barrier.set_external(np.repeat(np.stack([torso, torso + [0.3, 0.0, 0.0]])[None], 7, axis=0), np.full(7, 0.05),
                           velocities=np.zeros((7, 2, 3)), held=held, seen_speed=0.0)
    assert p.barrier.person_speed == np.inf


def test_a_protective_stop_brings_the_command_to_the_robot_twice_on_random_states() -> None:
    """A protective stop brings q_cbf to the robot's measured joints (the servos' lag, a few mrad,
    would otherwise carry the robot on into the person after the command stopped) on its first step
    and on its first step after a command at rest, by at most [u_min, u_max]·Δt per joint and within
    the joint limits, and on no other step; the step runs from there: its hard rows hold at the
    settled pose and |Δq_cbf| ≤ 2 u_max Δt. A non-finite robot pose settles nothing; without a stop
    the robot pose is ignored. Random intrusions on the real model, the robot moving, a robot that
    trails the command by up to 4 mrad (20 mrad on some joints: beyond u_max Δt)."""
    p = pipeline_for()
    params, kin = p.filter.params, p.kinematics
    lower = -params.u_max if params.u_min is None else params.u_min
    rng = np.random.default_rng(36)
    rested = 0
    for _ in range(20):
        q = random_intrusion(p, rng)
        q_nom = rng.uniform(kin.q_min, kin.q_max)
        lag = rng.uniform(-4e-3, 4e-3, q.shape) * np.where(rng.random(q.shape) < 0.2, 5.0, 1.0)
        p.filter.reset(q)
        p.filter._u_prev = 0.5 * rng.uniform(-params.u_max, params.u_max)  # noqa: SLF001 (moving)
        settled_at, rest_at, u_before = [], None, None
        for k in range(round(0.5 / DT)):
            q_robot = q + lag
            start = np.clip(np.clip(q_robot, q + lower * DT, q + params.u_max * DT), kin.q_min, kin.q_max)
            result = p.filter.step(q_nom, DT, np.zeros_like(q_nom), q_robot)
            if not result.protective_stop:  # the robot braked out of the person's margin: the stop is over
                break
            assert result.mode is not SafetyMode.HOLD and (np.abs(result.q_cbf - q) <= 2 * params.u_max * DT + 1e-12).all()
            if rest_at is None and u_before is not None and np.abs(u_before).max() <= 1e-9:
                rest_at = k
            moved = not np.allclose(result.q_cbf, np.clip(q + DT * result.u, kin.q_min, kin.q_max), rtol=0.0, atol=1e-12)
            assert result.settled is moved, k  # the step says it was brought to the robot
            if moved:
                settled_at.append(k)
                np.testing.assert_allclose(result.q_cbf, np.clip(start + DT * result.u, kin.q_min, kin.q_max), atol=1e-12)
                A, b, soft = stacked(p, start)
                assert (A[~soft] @ result.u >= b[~soft] - TOL).all(), "a hard row at the settled pose gave way"
            q, u_before = result.q_cbf, result.u
        assert settled_at == [0] + ([] if rest_at is None else [rest_at]), (settled_at, rest_at)
        rested += rest_at is not None
        p.filter.reset(q)
        unknown = p.filter.step(q_nom, DT, np.zeros_like(q_nom), np.full_like(q, np.nan))
        assert unknown.protective_stop and not unknown.settled
        np.testing.assert_allclose(unknown.q_cbf, np.clip(q + DT * unknown.u, kin.q_min, kin.q_max), atol=1e-12)
    assert rested >= 10, "the stops must come to rest"
    alone = pipeline_for()
    alone_at(alone, kin.q_home)
    free = alone.filter.step(kin.q_home, DT, None, kin.q_home + 3e-3)
    assert not free.protective_stop
    np.testing.assert_allclose(free.q_cbf, kin.q_home + DT * free.u, atol=1e-12)


def stop_at_rest(p, rng: np.random.Generator, q: np.ndarray, q_nom: np.ndarray):
    """Step a protective stop (the robot still, at q_cbf) until its command is at rest and its settle at
    rest is done; the last result, or None if the stop ended first."""
    for _ in range(round(0.5 / DT)):
        result = p.filter.step(q_nom, DT, np.zeros_like(q_nom), p.filter.q_cbf.copy())
        if not result.protective_stop:
            return None
        if p.filter.stops.follows:
            return result
    return None


def test_in_a_stop_at_rest_the_servos_only_brake_on_random_states() -> None:
    """Once a stop's command is at rest (and its settle at rest done), a joint is brought to the
    robot exactly where its servo would push it along its motion — it moves faster than
    STILL_JOINT_SPEED and the command lies ahead of it, (q_cbf − q_robot) v > 0 — by at most
    [u_min, u_max]·Δt, and no other joint is, nor is any where a self row's h would be negative and
    below where it is; the step runs from there (its hard rows hold). A joint
    sagging or a measurement drifting away from the command is never followed, however long: the
    command does not run away; a non-finite pose follows nothing. Random intrusions on the real
    model, random joint velocities and offsets."""
    p = pipeline_for()
    params, kin = p.filter.params, p.kinematics
    lower = -params.u_max if params.u_min is None else params.u_min
    rng = np.random.default_rng(38)
    checked = followed = 0
    for _ in range(30):
        q = random_intrusion(p, rng)
        q_nom = rng.uniform(kin.q_min, kin.q_max)
        p.filter.reset(q)
        if stop_at_rest(p, rng, q, q_nom) is None:
            continue
        q = p.filter.q_cbf.copy()
        velocity = rng.uniform(-0.5, 0.5, q.shape) * np.where(rng.random(q.shape) < 0.3, 0.005, 1.0)
        q_robot = q + rng.uniform(-0.01, 0.01, q.shape)
        p.filter._q_robot_prev = q_robot - velocity * DT  # noqa: SLF001 (the robot moved at `velocity`)
        expected = (np.abs(velocity) > STILL_JOINT_SPEED) & ((q - q_robot) * velocity > 0.0)
        start = np.where(expected, np.clip(np.clip(q_robot, q + lower * DT, q + params.u_max * DT), kin.q_min, kin.q_max), q)
        lowest_self = p.filter._write_rows(q)[3]  # noqa: SLF001 (the smallest self h, here and where it would follow)
        if p.filter._write_rows(start)[3] < min(lowest_self, 0.0):  # noqa: SLF001
            expected[:], start = False, q  # never followed into a self row
        result = p.filter.step(q_nom, DT, np.zeros_like(q_nom), q_robot)
        if not result.protective_stop:
            continue
        assert result.settled is bool(expected.any())
        np.testing.assert_allclose(result.q_cbf, np.clip(start + DT * result.u, kin.q_min, kin.q_max), atol=1e-12)
        A, b, soft = stacked(p, start)
        assert (A[~soft] @ result.u >= b[~soft] - TOL).all(), "a hard row at the followed pose gave way"
        checked += 1
        followed += int(expected.any())
        # a non-finite robot pose follows nothing, nor does the first pose after it (no velocity)
        lost = p.filter.step(q_nom, DT, np.zeros_like(q_nom), np.full_like(q, np.nan))
        back = p.filter.step(q_nom, DT, np.zeros_like(q_nom), result.q_cbf + 0.01)
        assert not (lost.settled or back.settled)
        # sagging away from the command (and a measurement drifting away) for a second: never followed
        held, away = result.q_cbf.copy(), rng.choice([-1.0, 1.0], q.shape) * rng.uniform(0.01, 0.5, q.shape)
        p.filter._q_robot_prev = held.copy()  # noqa: SLF001 (the robot at the command, then sagging)
        for k in range(1, round(1.0 / DT)):
            result = p.filter.step(q_nom, DT, np.zeros_like(q_nom), held + away * k * DT)
            if not result.protective_stop:
                break
            assert not result.settled, k
    assert checked >= 10 and followed >= 5, (checked, followed)


def person_rushing_in(p, rng: np.random.Generator, q: np.ndarray, *others) -> bool:
    """At ``q``: one person capsule (the torso's slot) 1–6 cm outside the left forearm's margin, rushing
    at it at 4–8 m/s (faster than any retreat: its row asks for more than the velocity box gives),
    the others far away. False when the capsule lands inside some other robot capsule's margin."""
    endpoints, _ = p.kinematics.compute(q)
    a, b = endpoints[FOREARM]
    direction = rng.normal(size=3)
    direction -= (direction @ (b - a)) / ((b - a) @ (b - a)) * (b - a)  # across the forearm's axis
    direction /= np.linalg.norm(direction)
    radius, gap = 0.06, rng.uniform(0.01, 0.06)
    reach = p.barrier.robot_radii[FOREARM] + p.filter.params.phi + radius + p.barrier.person_margin + gap
    centre = 0.5 * (a + b) + reach * direction
    capsules = np.repeat(np.stack([centre, centre])[None], 7, axis=0)
    capsules[1:] += [5.0, 5.0, 5.0]  # far away
    velocities = np.zeros((7, 2, 3))
    velocities[0] = -rng.uniform(4.0, 8.0) * direction
    for pipeline in (p, *others):
        pipeline.barrier.set_external(capsules, np.full(7, radius), np.ones(7, bool), velocities)
    low = p.filter.rows_at(q).min_h(self_rows=False)
    return low is not None and low > 0.0


def test_a_command_at_rest_after_person_rows_gave_way_is_brought_to_the_robot_once() -> None:
    """A step whose person rows gave way aims at rest (here ``stop_on_give_way``: a person rushing
    in faster than any retreat, the robot at rest after a reset); once such a step commanded rest,
    the next one first brings q_cbf to the robot's measured joints (clipped to u_max·Δt), and the
    one after does not again while the steps go on aiming at rest. Random states on the real model."""
    p = pipeline_for(on_intrusion="stop_on_give_way")
    params, kin = p.filter.params, p.kinematics
    rng = np.random.default_rng(37)
    checked = 0
    for _ in range(40):
        q = random_safe_state(p, rng)
        if not person_rushing_in(p, rng, q):
            continue
        q_nom = rng.uniform(kin.q_min, kin.q_max)
        lag = rng.uniform(-4e-3, 4e-3, q.shape)
        p.filter.reset(q)
        first = p.filter.step(q_nom, DT, np.zeros_like(q_nom), q + lag)
        if first.settled or not first.relaxed.any() or np.abs(first.u).max() > 1e-9:
            continue  # a stop decided from the rows (the person reaches a thigh), or not at rest
        q = first.q_cbf
        second = p.filter.step(q_nom, DT, np.zeros_like(q_nom), q + lag)
        assert second.settled
        start = np.clip(np.clip(q + lag, q - params.u_max * DT, q + params.u_max * DT), kin.q_min, kin.q_max)
        np.testing.assert_allclose(second.q_cbf, np.clip(start + DT * second.u, kin.q_min, kin.q_max), atol=1e-12)
        third = p.filter.step(q_nom, DT, np.zeros_like(q_nom), second.q_cbf + lag)
        assert third.relaxed.any() and not third.settled
        checked += 1
    assert checked >= 5


def test_a_person_rushing_in_faster_than_any_retreat_stops_the_robot_on_random_states() -> None:
    """The protective stop when person rows give way (``on_intrusion: stop_on_give_way``): a person
    capsule outside every margin but rushing at the left forearm faster than it could retreat, on
    random states with the robot moving and the imitation pulling anywhere: the rows are
    infeasible, and instead of the retreat they cannot give the step is a protective stop aiming at
    rest (u_ref = 0), the hard rows hold, no person row is approached faster than braking within the
    acceleration bound (its floor min(b_i, 0): no retreat demanded), the output is finite, the rows
    that gave way are reported and the robot is at rest within 0.5 s. With the default ``stop`` (nobody is inside a margin) the
    same states retreat from the rushing capsule (A_i u > 0 on its rows) and are no stop."""
    stop, retreat = pipeline_for(on_intrusion="stop_on_give_way"), pipeline_for()
    rng = np.random.default_rng(29)
    kin = stop.kinematics
    stopped = retreated = 0
    for _ in range(40):
        q = random_safe_state(stop, rng)
        if not person_rushing_in(stop, rng, q, retreat):
            continue
        q_nom = rng.uniform(kin.q_min, kin.q_max)
        u_prev = 0.5 * rng.uniform(-stop.filter.params.u_max, stop.filter.params.u_max)
        A, b, soft = stacked(stop, q)
        retreat.filter.reset(q)
        result = retreat.filter.step(q_nom, DT, np.zeros_like(q_nom))
        if result.protective_stop:  # the capsule also reaches a thigh within the look-ahead: the other stop
            continue
        rushing = soft & (b > 1e-6)
        retreated += bool((A[rushing] @ result.u > 1e-6).any())
        stop.filter.reset(q)
        stop.filter._u_prev = u_prev.copy()  # noqa: SLF001 (moving)
        first = stop.filter.step(q_nom, DT, np.zeros_like(q_nom))
        assert first.mode is SafetyMode.RELAXED and first.relaxed.any(), "the rushing person's rows must give way"
        assert any("human.torso" in name for name in first.gave_way)
        assert_stops_without_retreat(stop, q, q_nom, u_prev, give_way=True)
        stopped += 1
    assert stopped >= 15 and retreated >= stopped // 2


def test_a_stop_goes_on_while_person_rows_give_way_on_random_states() -> None:
    """With the default ``stop`` the intrusion stop ends only once nobody is inside a margin as
    measured *and* the person rows can be kept: after a stop's step, a person just outside every
    margin but rushing at the left forearm faster than it can retreat (rows that give way) keeps
    the next step a protective stop aiming at rest (u_ref = 0), braking only, the hard rows held and
    no person row approached faster than braking within the acceleration bound, where the same step
    after one that was no stop retreats and goes on (no stop). Random states on the real model."""
    p, fresh = pipeline_for(), pipeline_for()
    rng = np.random.default_rng(41)
    kin, u_max = p.kinematics, p.filter.params.u_max
    went_on = 0
    for _ in range(80):
        q = random_safe_state(p, rng)
        q_nom = rng.uniform(kin.q_min, kin.q_max)
        random_intrusion(p, rng, q=q)
        p.filter.reset(q)
        p.filter._u_prev = 0.5 * rng.uniform(-u_max, u_max)  # noqa: SLF001 (moving)
        first = p.filter.step(q_nom, DT, np.zeros_like(q_nom))
        if not first.protective_stop:
            continue
        q = first.q_cbf
        if not person_rushing_in(p, rng, q, fresh):
            continue
        fresh.filter.reset(q)
        fresh.filter._u_prev = first.u.copy()  # noqa: SLF001 (the same motion, after no stop)
        after_no_stop = fresh.filter.step(q_nom, DT, np.zeros_like(q_nom))
        if after_no_stop.protective_stop or not after_no_stop.relaxed.any():
            continue  # the person reaches a thigh within the look-ahead, or the rows can be kept
        rows = stop_rows(p, full_torque=False)
        second = p.filter.step(q_nom, DT, np.zeros_like(q_nom))
        assert_a_stop_that_never_closes_in(second, *rows)
        assert_only_brakes(second, first.u)
        assert second.relaxed.any(), "the rows that gave way are reported"
        went_on += 1
    assert went_on >= 10, went_on


def _slide_into_the_torso(margin: float) -> tuple[float, set[str]]:
    """The left arm driven through the torso (imitation pulling across the body) for 2 s from home,
    no person: the smallest self h the filter held (m) and every name that gave way."""
    p = pipeline_for(self_margin=margin)
    alone_at(p, p.kinematics.q_home)
    q_nom = p.kinematics.q_home.copy()
    names = p.kinematics.joint_names
    q_nom[names.index("left_shoulder_roll_joint")] = -1.2
    q_nom[names.index("left_shoulder_pitch_joint")] = -0.6
    q_nom[names.index("left_elbow_joint")] = 0.0
    lowest, gave = np.inf, set()
    for _ in range(1000):
        result = p.filter.step(q_nom, DT)
        lowest = min(lowest, result.min_h_self)
        gave |= set(result.gave_way)
    return lowest, gave


def test_self_rows_aim_the_margin_beyond_phi() -> None:
    """``safety.self_margin`` ε: an arm pressed into the torso stops with its self rows about ε
    beyond φ (h reported against φ stays ≥ 0, a sampled slide along the boundary no longer dips
    below it); rows inside the band are pushed out but not reported as giving way."""
    with_margin, gave = _slide_into_the_torso(0.002)
    without, _ = _slide_into_the_torso(0.0)
    assert with_margin >= 0.002 and abs((with_margin - without) - 0.002) < 5e-4, (with_margin, without)
    assert not {name for name in gave if "|" in name and "human" not in name}, gave


def test_an_already_violated_self_row_is_softened_not_dropped() -> None:
    """Arms crossed through each other (it must not happen): the output is finite and the violated
    self rows do not get worse (A u ≥ min(b, 0) = 0 for them)."""
    p = pipeline_for()
    p.barrier.set_external(None)
    q = np.array([0.0, 0.1, -1.3, -1.4, 0.5, -1.3, 1.4, 0.5])
    A, b, soft = stacked(p, q)
    violated = ~soft & (b > 1e-6)
    assert violated.any(), "the test state must violate a self row"
    p.filter.reset(q)
    result = p.filter.step(p.kinematics.q_home, DT)
    assert np.isfinite(result.u).all() and result.mode is SafetyMode.RELAXED
    assert (A[violated] @ result.u >= -1e-6).all()


def test_an_already_violated_static_row_is_named_and_never_deepened() -> None:
    """An arm inside the static pelvis capsule's margin (it must not happen; random states find
    it) with the velocity box too small to leave it in one step: the step is RELAXED, names that
    row in ``gave_way``, counts its h in ``min_h_self`` and never moves the arm deeper (A u ≥ 0)."""
    p = pipeline_for()
    p.barrier.set_external(None)
    p.filter.params = dataclasses.replace(p.filter.params, u_max=np.full(8, 1e-3))  # rad/s: no retreat can cancel b = −γ h in one step
    static = next(b for b in p.filter.barriers if isinstance(b, StaticCapsuleBarrier))
    rng = np.random.default_rng(5)
    checked = 0
    while checked < 5:
        q = rng.uniform(p.kinematics.q_min, p.kinematics.q_max)
        blocks = p.filter.blocks_at(q)
        block = blocks[-1]
        if not -0.05 < block.h.min() < -0.002:
            continue
        p.filter.reset(q)
        result = p.filter.step(rng.uniform(p.kinematics.q_min, p.kinematics.q_max), DT)
        violated = block.b > RELAXED_TOL
        assert result.mode is SafetyMode.RELAXED and np.isfinite(result.u).all()
        assert result.min_h_self == pytest.approx(min(block.h.min(), blocks[0].min_h(True)))
        assert (block.A[violated] @ result.u >= -1e-6).all()
        assert {static.row_names()[i] for i in np.flatnonzero(violated)} <= set(result.gave_way)
        checked += 1


def test_a_self_row_a_hair_past_its_boundary_brakes_within_the_acceleration_bound() -> None:
    """An arm moving into a self pair that sampling has carried a hair (0.03–0.3 mm) past its
    boundary: the violated row may not demand A_i u ≥ 0 at once (no bounded box could give it while
    the arm still moves in; the bound would be widened, a jump the servos trail): it brakes as hard
    as the bound allows, A_i u ≥ min(b_i, 0, A_i ū), ū the bounded box's point nearest rest, and
    the bound holds."""
    p = pipeline_for()
    p.barrier.set_external(None)
    kin, a = p.kinematics, p.filter.params.accel_max
    joint_rows = np.concatenate([np.full(len(b.row_names()), isinstance(b, JointBarrier)) for b in p.filter.barriers])
    rng = np.random.default_rng(11)
    checked = 0
    while checked < 5:
        q0 = rng.uniform(kin.q_min, kin.q_max)
        A, b, soft = stacked(p, q0)
        if not (b[~soft] <= 0.0).all():
            continue
        direction = rng.normal(size=8)
        direction /= np.linalg.norm(direction)
        low, high = 0.0, 1.0  # bisect along the direction for a self row 0.03–0.3 mm past its boundary
        if (stacked(p, np.clip(q0 + high * direction, kin.q_min, kin.q_max))[1][~soft] <= 0.0).all():
            continue
        for _ in range(60):
            mid = 0.5 * (low + high)
            _, b_mid, _ = stacked(p, np.clip(q0 + mid * direction, kin.q_min, kin.q_max))
            low, high = (mid, high) if (b_mid[~soft] <= 0.0).all() else (low, mid)
            if 3e-4 * p.filter.params.gamma < b_mid[~soft].max() < 3e-3 * p.filter.params.gamma:
                break
        else:
            continue
        q = np.clip(q0 + mid * direction, kin.q_min, kin.q_max)
        A, b, soft = stacked(p, q)
        violated = ~soft & (b > 0.0)
        if (violated & joint_rows).any():
            continue  # a joint barrier, not a self pair
        p.filter.reset(q)
        p.filter._u_prev = 1.0 * direction  # noqa: SLF001 (moving in at 1 rad/s: the state a previous step leaves)
        lower, upper, honours = next(p.filter._boxes(q, DT))  # noqa: SLF001
        brake = np.clip(0.0, lower, upper)
        if not honours or (A[~soft & ~violated] @ brake < b[~soft & ~violated] - 1e-9).any():
            continue  # a joint limit or another hard row needs more than the bound: not this test's case
        result = p.filter.step(q + direction, DT)  # imitation pulling further in
        assert result.mode is SafetyMode.RELAXED and "accel_max" not in result.gave_way, result.gave_way
        assert (np.abs(result.u - 1.0 * direction) <= a * DT + 1e-9).all()
        assert (A[violated] @ result.u >= np.minimum(0.0, A[violated] @ brake) - 1e-6).all()
        assert (A[~soft & ~violated] @ result.u >= b[~soft & ~violated] - 1e-6).all()
        checked += 1


def test_joint_barrier_rows_are_a_barrier_kind() -> None:
    p = pipeline_for()
    joints = [b for b in p.filter.barriers if isinstance(b, JointBarrier)]
    assert len(joints) == 1 and len(joints[0].index) > 0
    block = joints[0].constraint_rows(p.kinematics.q_home, *p.kinematics.compute(p.kinematics.q_home),
                                      gamma=10.0, phi=0.02, lookahead=0.0)
    assert not block.soft.any() and (block.h > 0).all()  # home lies inside every joint barrier
    np.testing.assert_allclose(block.b, -10.0 * block.h)


def test_the_acceleration_bound_holds_wherever_the_rows_allow_and_gives_way_only_to_keep_them() -> None:
    """Tracking targets drawn anywhere in the joint range, no person: every step's u* changes by at
    most accel_max·Δt unless ``accel_max`` is reported among what gave way; the self rows and
    joint barriers hold at every step either way (the last box tried is the plain velocity box,
    where u = 0 keeps them); ``ddq`` is (u* − u_prev)/Δt."""
    p = pipeline_for()
    p.barrier.set_external(None)
    a = p.filter.params.accel_max
    assert a is not None, "the default configuration bounds the acceleration"
    rng = np.random.default_rng(7)
    p.filter.reset(p.kinematics.q_home)
    u_prev, bounded, gave = np.zeros(8), 0, 0
    for step in range(3000):
        if step % 150 == 0:
            q_nom = rng.uniform(p.kinematics.q_min, p.kinematics.q_max)
        q = p.filter.q_cbf.copy()
        A, b, soft = stacked(p, q)
        result = p.filter.step(q_nom, DT)
        assert (A[~soft] @ result.u >= b[~soft] - 1e-6).all(), "a self row or joint barrier gave way"
        if step:
            np.testing.assert_allclose(result.ddq, (result.u - u_prev) / DT, atol=1e-9)
            if "accel_max" in result.gave_way:
                gave += 1
            else:
                assert (np.abs(result.u - u_prev) <= a * DT + 1e-9).all()
                bounded += 1
        u_prev = result.u
    assert bounded > 0.95 * 3000, (bounded, gave)


def test_after_a_reset_the_first_step_is_unbounded_and_its_acceleration_zero() -> None:
    p = pipeline_for()
    alone_at(p, p.kinematics.q_home)
    q_nom = p.kinematics.q_home + 0.05
    first = p.filter.step(q_nom, DT)
    assert (np.abs(first.u) > p.filter.params.accel_max * DT).any()  # the velocity box alone
    np.testing.assert_array_equal(first.ddq, np.zeros(8))
    second = p.filter.step(q_nom, DT)
    assert "accel_max" not in second.gave_way
    assert (np.abs(second.u - first.u) <= p.filter.params.accel_max * DT + 1e-9).all()


def test_a_joint_approaching_its_limit_brakes_in_time() -> None:
    """The waist pitch driven at its limit: the bounded command slows down before it (never faster
    than √(2 β a d) with d the distance left) and comes to rest at the limit without a jump."""
    p = pipeline_for()
    p.barrier.set_external(None)
    a = p.filter.params.accel_max
    waist = p.kinematics.joint_names.index("waist_pitch_joint")
    p.filter.reset(p.kinematics.q_home)
    previous = p.filter.step(p.kinematics.q_home, DT).u[waist]  # at rest: the bound applies from here
    q_nom = p.kinematics.q_home.copy()
    q_nom[waist] = p.kinematics.q_max[waist] + 1.0  # beyond the limit: imitation pulls through it
    for _ in range(1500):
        result = p.filter.step(q_nom, DT)
        assert "accel_max" not in result.gave_way
        assert abs(result.u[waist] - previous) <= a[waist] * DT + 1e-9
        previous = result.u[waist]
    assert p.filter.q_cbf[waist] == pytest.approx(p.kinematics.q_max[waist], abs=1e-3) and abs(previous) < 1e-3


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_random_intrusions_with_a_moving_robot_keep_the_hard_rows(seed: int) -> None:
    """The random intrusions above, but with the robot already moving at random speeds (u_prev):
    the acceleration bound cannot always reach a retreat; the self rows and joint barriers still
    hold; within the bound no person row closes faster than braking as hard as the bound allows
    (A_i u ≥ min(b_i, 0, A_i ū), ū the bounded box's point nearest rest; a protective stop's, the
    bound ×2's, the motors' full torque); when the bound gave way
    it is named, and beyond twice the bound (the motors' full torque) only where no u within that
    keeps the hard rows (SciPy's LP), never for a person's floor alone."""
    p = pipeline_for(on_intrusion="retreat")
    rng = np.random.default_rng(seed)
    gave = 0
    for _ in range(30):
        q = random_intrusion(p, rng)
        A, b, soft = stacked(p, q)
        p.filter.reset(q)
        u_prev = rng.uniform(-p.filter.params.u_max, p.filter.params.u_max)
        p.filter._u_prev = u_prev.copy()  # noqa: SLF001 (the state a previous step leaves)
        boxes = p.filter._boxes(q, DT)  # noqa: SLF001
        bounded_lower, bounded_upper, _ = next(boxes)
        twice_lower, twice_upper, _ = next(boxes)  # the bound ×2
        result = p.filter.step(rng.uniform(p.kinematics.q_min, p.kinematics.q_max), DT)
        if result.protective_stop:  # (a person reaching a thigh) it brakes at the motors' full torque
            brake = np.clip(0.0, twice_lower, twice_upper)
        else:
            brake = np.clip(0.0, bounded_lower, bounded_upper)
        lhs = A @ result.u
        assert result.mode is not SafetyMode.HOLD and np.isfinite(result.u).all()
        assert (lhs[~soft] >= b[~soft] - 1e-6).all()
        if ((result.u < twice_lower - 1e-9) | (result.u > twice_upper + 1e-9)).any():  # beyond the motors' torque
            holding = ~soft & (b <= 0.0)  # the hard rows that hold (b without the self margin)
            keep = linprog(np.zeros(len(u_prev)), A_ub=-A[holding], b_ub=-b[holding],
                           bounds=list(zip(twice_lower, twice_upper)), method="highs")
            assert keep.status == 2, "the bound was widened beyond ×2 for a person's floor"
        if "accel_max" in result.gave_way:
            gave += 1
        else:
            assert (lhs[soft] >= np.minimum(np.minimum(b[soft], 0.0), A[soft] @ brake) - 1e-6).all()
    assert gave > 0, "some intrusion must need more than the acceleration bound"


def test_an_arm_sliding_along_its_own_body_brakes_for_a_person_within_the_motors_torque() -> None:
    """Random states 0–2 mm outside a self pair's margin, the robot moving along that boundary (its
    row's A_i u = 0) at up to half its speed bounds, and a person rushing into the left forearm's
    margin: braking every joint at once for the person would turn the arm into its own body. The
    hard rows hold and the command stays within twice the acceleration bound (the motors' full
    torque) wherever some u there keeps the hard rows (SciPy's LP): the bound is not widened into a
    jump the servos cannot follow for the person's sake (it was, by up to 14 rad/s in one step)."""
    p = pipeline_for()
    kin, gamma = p.kinematics, p.filter.params.gamma
    self_rows = np.concatenate([np.full(len(b.row_names()), not isinstance(b, JointBarrier)) for b in p.filter.barriers])
    rng = np.random.default_rng(29)
    checked = 0
    for _ in range(400):
        q0 = random_safe_state(p, rng)
        direction = rng.normal(size=8)
        direction /= np.linalg.norm(direction)
        low, high = 0.0, 1.0  # bisect along the direction to 0–2 mm outside a self pair's margin
        _, b_far, soft = stacked(p, np.clip(q0 + high * direction, kin.q_min, kin.q_max))
        if (b_far[~soft & self_rows] <= 0.0).all():
            continue
        for _ in range(40):
            mid = 0.5 * (low + high)
            _, b_mid, _ = stacked(p, np.clip(q0 + mid * direction, kin.q_min, kin.q_max))
            low, high = (mid, high) if (b_mid[~soft] <= 0.0).all() else (low, mid)
        q = np.clip(q0 + low * direction, kin.q_min, kin.q_max)
        random_intrusion(p, rng, q=q)
        A, b, soft = stacked(p, q)
        holding = ~soft & (b <= 0.0)
        near = np.flatnonzero(holding & self_rows & (b > -gamma * 2e-3))
        if len(near) == 0 or (b[~soft] > 0.0).any():
            continue
        row = A[near[0]]
        u_prev = rng.uniform(-0.5, 0.5) * p.filter.params.u_max
        u_prev -= (row @ u_prev) / (row @ row) * row  # sliding along the boundary
        p.filter.reset(q)
        p.filter._u_prev = u_prev.copy()  # noqa: SLF001 (the state a previous step leaves)
        boxes = p.filter._boxes(q, DT)  # noqa: SLF001
        next(boxes)
        twice_lower, twice_upper, _ = next(boxes)
        result = p.filter.step(rng.uniform(kin.q_min, kin.q_max), DT)
        assert (A[holding] @ result.u >= b[holding] - 1e-6).all(), "a self row or joint barrier gave way"
        if ((result.u < twice_lower - 1e-9) | (result.u > twice_upper + 1e-9)).any():
            keep = linprog(np.zeros(8), A_ub=-A[holding], b_ub=-b[holding], bounds=list(zip(twice_lower, twice_upper)),
                           method="highs")
            assert keep.status == 2, "the bound was widened beyond ×2 for a person's floor"
        checked += 1
        if checked == 40:
            break
    assert checked == 40


def test_warm_up_compiles_the_kernels_only_an_infeasible_step_uses() -> None:
    """After the pipeline's warm-up the kernel of the widened acceleration boxes (``_reach``, which
    only an infeasible step calls) is compiled like the first box's (numba compiles on first use: a
    control tick must not pay it the first time a person walks in), and the filter is back at q."""
    from services.safety.qp import box

    p = pipeline_for()
    q = p.kinematics.q_home.copy()
    p.warm_up(DT, q)
    assert box._bounded.signatures and box._reach.signatures  # noqa: SLF001 (numba dispatchers)
    np.testing.assert_array_equal(p.filter.q_cbf, q)


def test_warm_up_compiles_the_step_kernels() -> None:
    """After the pipeline's warm-up every kernel of the step is compiled (numba compiles on first use:
    no control tick may pay it): the barriers' in-place row writers, the kernel of touching segments
    (only such a rare step calls it), the QP's inputs (u_ref, the first box, the movable rows), the
    integration and the DAQP backend's flags and slack."""
    from services.safety.barriers import kernel
    from services.safety.qp import box, daqp_backend

    p = pipeline_for()
    p.warm_up(DT)
    for dispatcher in (kernel.write_segment_block, kernel.write_joint_block, kernel.finish_segment_rows,
                       box.prepare_qp, box.integrate, daqp_backend._settle):  # noqa: SLF001
        assert dispatcher.signatures, dispatcher.__name__
    # the kernels the step calls through their entry points are bound to them (no binding in a tick)
    filt = p.filter
    writers = [b._writer for b in filt.barriers if hasattr(b, "_writer")]  # noqa: SLF001
    joints = [b._write for b in filt.barriers if isinstance(b, JointBarrier)]  # noqa: SLF001
    bound = [filt._prepare, filt._integrate, filt._qp._settle_stacked, *joints, *(w._write for w in writers)]  # noqa: SLF001
    assert len(writers) == 2 and len(joints) == 1  # the capsule and static pairs' writers, the joint rows
    for kernel_call in bound:
        assert kernel_call.call != kernel_call._bind, kernel_call.dispatcher.__name__  # noqa: SLF001


def test_a_bound_kernel_gives_the_dispatchers_values() -> None:
    """BoundKernel calls the compiled entry point of its first call's argument types: the same values
    as numba's dispatcher, call after call."""
    from services.safety.barriers.kernel import joint_rows
    from services.safety.compiled import BoundKernel

    bound = BoundKernel(joint_rows)
    q, index = np.linspace(-1.0, 1.0, 8), np.array([0, 3, 7], dtype=np.intp)
    sign, limit, accel = np.array([1.0, -1.0, 1.0]), np.array([-0.5, 0.2, 0.9]), np.full(8, 3.0)
    for gamma in (5.0, 0.5):
        h, b, h_ref, b_ref = np.empty(3), np.empty(3), np.empty(3), np.empty(3)
        bound.call(q, index, sign, limit, gamma, accel, 0.5, True, h, b)
        joint_rows(q, index, sign, limit, gamma, accel, 0.5, True, h_ref, b_ref)
        np.testing.assert_array_equal(h, h_ref)
        np.testing.assert_array_equal(b, b_ref)
    assert bound.call is not joint_rows


@pytest.mark.parametrize("geometry", ["capsule", "spheres"])
def test_the_self_margin_shifts_the_reported_and_the_solved_rows_once(geometry: str) -> None:
    """The self margin's b shift (γ ε on the hard distance rows) is in the pair rows a step reports,
    once, whether the barrier's rows view the stacked b (the capsule writer) or are its own copies
    (a geometry through :meth:`Barrier.write_rows`' default), and the QP the step solved saw it."""
    margin = 0.003
    shifted, plain = pipeline_for(geometry=geometry, self_margin=margin), pipeline_for(geometry=geometry, self_margin=0.0)
    q = np.array([0.0, 0.1, -0.9, 0.3, 0.9, -0.9, -0.3, 0.9])  # arms near the torso
    for p in (shifted, plain):
        alone_at(p, q)
    with_margin, without = shifted.filter.step(q, DT), plain.filter.step(q, DT)
    self_rows = ~with_margin.rows.soft
    expected = np.where(self_rows, shifted.filter.params.gamma * margin, 0.0)
    np.testing.assert_allclose(with_margin.rows.b - without.rows.b, expected, rtol=0.0, atol=1e-12)
    k = int(movable_rows(np.vstack([block.A for block in shifted.filter.blocks_at(q)])).sum())  # the QP's rows
    solved = shifted.filter._qp_views(k)[1]  # noqa: SLF001 (the b the step's QP was given)
    kept = shifted.filter._kept[: solved.shape[0]]  # noqa: SLF001
    pair = kept < with_margin.rows.b.shape[0]
    np.testing.assert_array_equal(solved[pair], with_margin.rows.b[kept[pair]])


def test_a_swept_person_stops_the_robot_only_once_the_measured_capsule_is_inside_on_random_states() -> None:
    """``safety.human_predict_s``: one person capsule outside every margin, 1–6 cm from the left
    forearm's, approaching it across its axis at 1–3 m/s and swept 0.093 s ahead
    (:func:`swept_capsules`), so that the swept capsule is inside the margin and the
    measured one is not. On random states with the imitation pulling anywhere: no protective stop
    (the rows keep the person out), where the same rows without the sweep reported would stop the
    robot; once the measured capsule is itself 3–6 cm inside, the swept one stops the robot too at
    every speed: at 1–3 m/s the sweep carries it up to 14 cm, past the forearm's axis, where the
    bound h + 2·sweep the stop once took read it as outside (``BarrierRows.h_measured`` is exact)."""
    p = pipeline_for()
    rng = np.random.default_rng(31)
    kin = p.kinematics
    kept_out = 0

    def step(capsules, velocities, radius, sweep_reported, q, q_nom):
        ends, radii, sweep = swept_capsules(capsules, np.full(7, radius), velocities, 0.093)
        p.barrier.set_external(*padded(7, ends, radii, np.ones(7, bool), velocities,
                                       *((sweep, None, math.inf, capsules) if sweep_reported else ())))
        fixed = p.filter.stops.at_fixed_body(np.concatenate([blk.b for blk in p.filter.blocks_at(q)]))
        p.filter.reset(q)
        return fixed, p.filter.step(q_nom, DT, np.zeros_like(q_nom)).protective_stop

    for _ in range(60):
        q = random_safe_state(p, rng)
        endpoints, _ = kin.compute(q)
        a, b = endpoints[FOREARM]
        direction = rng.normal(size=3)
        direction -= (direction @ (b - a)) / ((b - a) @ (b - a)) * (b - a)  # across the forearm's axis
        direction /= np.linalg.norm(direction)
        radius = 0.06
        reach = p.barrier.robot_radii[FOREARM] + p.filter.params.phi + radius + p.barrier.person_margin
        velocities = np.zeros((7, 2, 3))
        velocities[0] = -rng.uniform(1.0, 3.0) * direction
        q_nom = rng.uniform(kin.q_min, kin.q_max)

        def person(gap: float) -> np.ndarray:
            centre = 0.5 * (a + b) + (reach + gap) * direction
            capsules = np.repeat(np.stack([centre, centre])[None], 7, axis=0)
            capsules[1:] += [5.0, 5.0, 5.0]  # far away
            return capsules

        outside = person(rng.uniform(0.01, 0.06))
        p.barrier.set_external(outside, np.full(7, radius), np.ones(7, bool), velocities)
        low = p.filter.rows_at(q).min_h(self_rows=False)
        fixed, stop = step(outside, velocities, radius, True, q, q_nom)
        if fixed or low is None or low < 0.0:  # near another robot capsule too, or reaching a thigh (no joint moves it)
            continue
        assert not stop, "a capsule only expected inside must be kept out by the rows, not stop the robot"
        assert step(outside, velocities, radius, False, q, q_nom)[1], "read as inside without the sweep: a stop"
        assert step(person(-rng.uniform(0.03, 0.06)), velocities, radius, True, q, q_nom)[1], "measured inside: a stop"
        kept_out += 1
    assert kept_out >= 15
