"""CBF rows (paper eqs. 4–7) against central finite differences on the shipped G1 model."""

from __future__ import annotations

import numpy as np
import pytest

from services.safety.assembly import build_pipeline
from services.safety.barriers.capsules import DISABLED_B, CapsuleBarrier
from services.safety.barriers.static import StaticCapsuleBarrier
from services.safety.pairs import N_ROBOT, make_pair_set, preset_pair_set
from shared.config import load_config


@pytest.fixture(scope="module")
def pipeline():
    return build_pipeline(load_config(environ={}), pair_preset="paper72")


def random_q(kin, rng) -> np.ndarray:
    return rng.uniform(kin.q_min, kin.q_max)


def random_humans(rng, n_people: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """Capsules scattered around the robot's upper body (0.2–0.8 m away)."""
    centre = np.array([0.0, 0.0, 1.0]) + rng.uniform([-0.8, -0.8, -0.4], [0.8, 0.8, 0.5], size=(7 * n_people, 1, 3))
    endpoints = centre + rng.normal(scale=0.15, size=(7 * n_people, 2, 3))
    return endpoints, rng.uniform(0.03, 0.12, 7 * n_people)


def h_of(pipeline, q: np.ndarray) -> np.ndarray:
    return pipeline.filter.rows_at(q).h


def test_rows_match_central_finite_differences(pipeline) -> None:
    rng = np.random.default_rng(3)
    kin = pipeline.kinematics
    eps = 1e-6
    checked = 0
    for _ in range(150):
        pipeline.barrier.set_external(*random_humans(rng))
        q = random_q(kin, rng)
        rows = pipeline.filter.rows_at(q)
        fd = np.empty_like(rows.A)
        for k in range(len(q)):
            dq = np.zeros_like(q)
            dq[k] = eps
            fd[:, k] = (h_of(pipeline, q + dq) - h_of(pipeline, q - dq)) / (2 * eps)
        ok = rows.distance > 1e-3
        scale = np.maximum(np.linalg.norm(fd, axis=1), 1e-3)
        rel = np.linalg.norm(rows.A - fd, axis=1) / scale
        assert np.isfinite(rows.A).all() and np.isfinite(rows.b).all()
        assert rel[ok].max() <= 1e-5, f"worst pair {pipeline.pairs.names[int(np.argmax(np.where(ok, rel, 0)))]}"
        checked += int(ok.sum())
    assert checked > 150 * 60


def test_human_rows_have_zero_jacobian_for_human_and_velocity_term(pipeline) -> None:
    """b = −γ (h − T a) + a with the approach speed a = max(nᵀ v_pB, 0) = max(−∂h/∂t, 0) when the
    human capsule moves with velocity v: approaching capsules tighten the row, receding ones never relax it."""
    rng = np.random.default_rng(5)
    kin = pipeline.kinematics
    q = kin.q_home.copy()
    endpoints, radii = random_humans(rng)
    velocity = rng.normal(size=endpoints.shape)
    barrier = pipeline.barrier
    barrier.set_external(endpoints, radii, velocities=velocity)
    rows = pipeline.filter.rows_at(q)
    dt = 1e-6
    barrier.set_external(endpoints + dt * velocity, radii, velocities=velocity)
    h_plus = pipeline.filter.rows_at(q).h
    barrier.set_external(endpoints - dt * velocity, radii, velocities=velocity)
    h_minus = pipeline.filter.rows_at(q).h
    dh_dt = (h_plus - h_minus) / (2 * dt)
    human = ~rows.is_self & (rows.distance > 1e-3)
    gamma, lookahead = pipeline.filter.params.gamma, pipeline.filter.params.human_lookahead_s
    assert lookahead > 0
    approach = np.maximum(-dh_dt[human], 0.0)
    assert approach.any() and (approach == 0).any(), "the draw must hold approaching and receding capsules"
    np.testing.assert_allclose(rows.b[human], -gamma * (rows.h[human] - lookahead * approach) + approach, atol=1e-6)
    np.testing.assert_allclose(rows.b[rows.is_self], -gamma * rows.h[rows.is_self], atol=1e-12)


def test_degenerate_geometry_gives_finite_rows(pipeline) -> None:
    """Human capsules through the robot's capsule axes (d = 0), parallel to them, or zero-length."""
    kin = pipeline.kinematics
    q = kin.q_home.copy()
    robot_endpoints, _ = kin.compute(q)
    humans = np.concatenate([robot_endpoints, robot_endpoints[:, ::-1] + [0.1, 0.0, 0.0]])  # coincident and parallel
    humans[3] = robot_endpoints[3, :1].repeat(2, axis=0)  # zero-length at a robot endpoint
    pipeline.barrier.set_external(humans, np.full(14, 0.05))
    rows = pipeline.filter.rows_at(q)
    assert np.isfinite(rows.A).all() and np.isfinite(rows.b).all() and np.isfinite(rows.h).all()
    touching = rows.distance < 1e-9
    assert touching.any()
    assert (np.linalg.norm(rows.A[touching], axis=1) > 0).any()  # a usable push-apart direction


def test_missing_human_capsules_disable_their_rows(pipeline) -> None:
    rng = np.random.default_rng(9)
    endpoints, radii = random_humans(rng)
    valid = np.ones(14, bool)
    valid[2] = False
    pipeline.barrier.set_external(endpoints, radii, valid)
    rows = pipeline.filter.rows_at(pipeline.kinematics.q_home)
    disabled = pipeline.pairs.second == N_ROBOT + 2
    assert disabled.sum() == 7
    assert (rows.A[disabled] == 0).all() and (rows.b[disabled] == DISABLED_B).all() and np.isnan(rows.h[disabled]).all()
    assert rows.enabled.sum() == len(pipeline.pairs) - 7
    pipeline.barrier.set_external(None)
    rows = pipeline.filter.rows_at(pipeline.kinematics.q_home)
    assert rows.min_h(self_rows=False) is None and rows.min_h(self_rows=True) is not None


def test_pair_presets() -> None:
    spec_pairs = [("left_forearm", "torso"), ("right_forearm", "torso")]
    default = preset_pair_set("default", spec_pairs)
    assert len(default) == 2 + 49 and default.is_self.sum() == 2
    assert len(preset_pair_set("paper72", spec_pairs)) == 72
    with pytest.raises(ValueError, match="unknown pair preset"):
        preset_pair_set("nope", spec_pairs)
    with pytest.raises(ValueError, match="two different robot capsules"):
        make_pair_set([("torso", "torso")])


def test_default_pipeline_is_clear_at_home() -> None:
    pipeline = build_pipeline(load_config(environ={}))
    rows = pipeline.filter.rows_at(pipeline.kinematics.q_home)
    assert len(pipeline.pairs) == len(pipeline.spec.self_pairs) + 49
    assert rows.min_h(self_rows=True) > 0
    assert isinstance(pipeline.barrier, CapsuleBarrier)


def test_compiled_kernel_matches_vectorised_geometry() -> None:
    """The numba pair loop equals shared.geometry on random, parallel and degenerate segments."""
    from services.safety.barriers.kernel import pair_distances
    from shared.geometry import segment_closest_points

    rng = np.random.default_rng(21)
    n = 3000
    endpoints = rng.normal(size=(2 * n, 2, 3))
    endpoints[n : n + 200, 1] = endpoints[n : n + 200, 0]  # zero-length
    endpoints[n + 200 : n + 400] = endpoints[200:400] + rng.normal(size=(200, 1, 3))  # parallel
    first, second = np.arange(n, dtype=np.int64), np.arange(n, 2 * n, dtype=np.int64)
    radii = rng.uniform(0, 0.1, 2 * n)
    out = [np.empty(n) for _ in range(4)] + [np.empty((n, 3))]
    pair_distances(endpoints, radii, first, second, 0.02, 1e-9, *out)
    distance, h, s, t, normal = out
    ref = segment_closest_points(endpoints[:n, 0], endpoints[:n, 1], endpoints[n:, 0], endpoints[n:, 1])
    np.testing.assert_allclose(distance, ref.distance, atol=1e-12)
    np.testing.assert_allclose(h, ref.distance - radii[:n] - radii[n:] - 0.02, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(normal, axis=1), 1.0, atol=1e-12)
    p = endpoints[:n, 0] + s[:, None] * (endpoints[:n, 1] - endpoints[:n, 0])
    q = endpoints[n:, 0] + t[:, None] * (endpoints[n:, 1] - endpoints[n:, 0])
    np.testing.assert_allclose(np.linalg.norm(p - q, axis=1), distance, atol=1e-12)


def test_pair_groups_radii_and_home_from_config() -> None:
    """safety.enabled_pair_groups, safety.capsule_radii and retargeting.q_home (config API fields)."""
    base = build_pipeline(load_config(environ={}))
    conf = load_config(environ={}, overrides={
        "safety": {"enabled_pair_groups": ["self_torso", "human"], "capsule_radii": {"left_forearm": 0.09}},
        "retargeting": {"q_home": [0.0, 0.1, 0.0, 0.3, 1.0, 0.0, -0.3, 1.0], "method": "linear"},
    })
    p = build_pipeline(conf)
    names = set(p.pairs.names)
    assert "left_forearm|torso" in names and "left_forearm|right_forearm" not in names
    assert "left_upper_arm|left_thigh" not in names
    assert sum(not s for s in p.pairs.is_self) == 49 and p.pairs.is_self.sum() == 2
    rows, base_rows = p.filter.rows_at(base.kinematics.q_home), base.filter.rows_at(base.kinematics.q_home)
    i, j = p.pairs.names.index("left_forearm|torso"), base.pairs.names.index("left_forearm|torso")
    np.testing.assert_allclose(base_rows.h[j] - rows.h[i], 0.09 - base.kinematics.radii[2])
    np.testing.assert_allclose(p.retargeter(np.zeros(8)), [0.0, 0.1, 0.0, 0.3, 1.0, 0.0, -0.3, 1.0])


def test_static_rows_match_finite_differences_and_are_hard() -> None:
    """The arms against the static pelvis capsule: A = ∂h/∂q (central differences), hard rows,
    b = −γ h (no approach term: the pelvis does not move), named by their pair."""
    pipeline = build_pipeline(load_config(environ={}))
    static = next(b for b in pipeline.filter.barriers if isinstance(b, StaticCapsuleBarrier))
    assert static.row_names() == tuple(f"{a}|{b}" for a, b in pipeline.spec.static_pairs)
    kin, rng, eps, gamma, phi = pipeline.kinematics, np.random.default_rng(11), 1e-6, 5.0, 0.02

    def rows(q):
        endpoints, jacobians = kin.compute(q)
        return static.constraint_rows(q, endpoints, jacobians, gamma, phi, 0.3)

    waist_moves = 0
    for _ in range(100):
        q = random_q(kin, rng)
        block = rows(q)
        assert not block.soft.any() and block.is_self.all()
        np.testing.assert_allclose(block.b, -gamma * block.h)
        fd = np.stack([(rows(q + eps * e).h - rows(q - eps * e).h) / (2 * eps) for e in np.eye(len(q))], axis=1)
        np.testing.assert_allclose(block.A, fd, atol=1e-6)
        waist_moves += int(np.count_nonzero(np.abs(block.A[:, :2]).max(axis=1) > 1e-3))
    assert waist_moves > 0.9 * 100 * len(static.row_names()), "the waist moves the arms against the pelvis"


def test_static_rows_follow_the_torso_pair_group() -> None:
    off = build_pipeline(load_config(environ={}, overrides={"safety": {"enabled_pair_groups": ["human", "self_arms", "self_legs"]}}))
    static = next(b for b in off.filter.barriers if isinstance(b, StaticCapsuleBarrier))
    assert static.row_names() == ()
    block = static.constraint_rows(off.kinematics.q_home, *off.kinematics.compute(off.kinematics.q_home), 5.0, 0.02, 0.0)
    assert block.A.shape == (0, 8) and block.min_h(True) is None


@pytest.mark.parametrize("scene", ["random", "touching", "missing", "none"])
def test_rows_written_in_place_equal_the_barriers_rows(pipeline, scene: str) -> None:
    """Every barrier's compiled in-place rows (``write_rows``, the step's fast path) equal its
    ``constraint_rows`` bit for bit, with their minima; also for touching segments (the fallback
    normals) and missing person capsules (disabled rows)."""
    rng = np.random.default_rng(4)
    kin, filt = pipeline.kinematics, pipeline.filter
    endpoints, radii = random_humans(rng)
    valid = np.ones(14, bool)
    if scene == "touching":
        robot_endpoints, _ = kin.compute(kin.q_home)
        endpoints[:7] = robot_endpoints
    if scene == "missing":
        valid[[2, 9]] = False
    pipeline.barrier.set_external(None if scene == "none" else endpoints, radii, valid, rng.normal(size=endpoints.shape))
    p = filt.params
    for q in (kin.q_home, random_q(kin, rng)):
        blocks = filt.blocks_at(q)
        ends, jac = kin.compute(q)
        m = sum(len(block.b) for block in blocks)
        A, b, soft, h = np.full((m, kin.nq), 7.0), np.full(m, 7.0), np.zeros(m, bool), np.full(m, 7.0)
        start = 0
        for barrier, block in zip(filt.barriers, blocks):
            minima = barrier.write_rows(q, ends, jac, p.gamma, p.phi, p.human_lookahead_s, p.accel_max, start, A, b,
                                        soft, h)
            rows = slice(start, start + len(block.b))
            for ours, theirs in ((A[rows], block.A), (b[rows], block.b), (soft[rows], block.soft), (h[rows], block.h)):
                np.testing.assert_array_equal(ours, theirs)
            np.testing.assert_array_equal(minima, block.minima())
            start = rows.stop
        if scene == "touching":
            assert (pipeline.barrier.last_rows.distance < 1e-9).any()
    pipeline.barrier.set_external(None)


@pytest.mark.parametrize("geometry", ["capsule", "spheres", "box"])
def test_the_person_margin_thickens_every_person_capsule_and_nothing_else(geometry: str) -> None:
    """``safety.human_margin`` δ: every robot–person row's h is δ lower than without it (the person's
    capsules δ thicker: h = d − r_A − r_B − δ − φ; spheres and boxes fit their colliders around the
    thicker capsule, so theirs are at least δ·(1 − rounding) lower), the self rows are untouched."""
    rng = np.random.default_rng(20)
    kin_q, rows = None, {}
    for delta in (0.0, 0.03):
        p = build_pipeline(load_config(environ={}, overrides={"safety": {"human_margin": delta, "geometry": geometry}}))
        assert p.barrier.person_margin == delta
        endpoints, radii = random_humans(np.random.default_rng(5), n_people=1)
        p.barrier.set_external(endpoints, radii)
        kin_q = random_q(p.kinematics, rng) if kin_q is None else kin_q
        rows[delta] = p.filter.rows_at(kin_q)
    thin, thick = rows[0.0], rows[0.03]
    is_self = thin.soft == 0
    np.testing.assert_array_equal(thin.h[is_self], thick.h[is_self])
    if geometry == "capsule":
        np.testing.assert_allclose(thin.h[~is_self] - thick.h[~is_self], 0.03, atol=1e-12)
    else:
        assert (thin.h[~is_self] - thick.h[~is_self] >= 0.015 - 1e-9).all()


@pytest.mark.parametrize("geometry", ["capsule", "spheres", "box"])
def test_a_swept_person_is_judged_inside_on_the_capsules_as_measured_on_random_states(geometry: str) -> None:
    """``BarrierRows.h_measured``: with the person swept ahead (``swept_capsules``, 0.093 s at up to
    3 m/s), every robot–person row the swept capsule puts inside its margin (h < 0) carries the h of
    the person capsule *as measured* against the robot capsule, d − (r_robot + r_person + δ + φ);
    every other row keeps h, which is never above the measured h (the swept capsule encloses the
    measured one); and with the capsules themselves, ``person_inside`` is exactly that of the same
    barrier given the measured capsules unswept. Without a sweep there is nothing to measure (None)."""
    from services.safety.human_memory import padded, swept_capsules

    rng = np.random.default_rng(42)
    config = load_config(environ={}, overrides={"safety": {"geometry": geometry}})
    p, plain, capsule = build_pipeline(config), build_pipeline(config), build_pipeline(load_config(environ={}))
    kin = p.kinematics
    inside = 0
    for _ in range(40):
        q = random_q(kin, rng)
        robot, _ = kin.compute(q)
        capsules = robot[rng.integers(0, N_ROBOT, 7)] + rng.normal(scale=0.06, size=(7, 2, 3))  # about the robot's links
        radii, velocities = rng.uniform(0.03, 0.07, 7), rng.uniform(-1.7, 1.7, (7, 2, 3))
        ends, swept_radii, sweep = swept_capsules(capsules, radii, velocities, 0.093)
        p.barrier.set_external(*padded(7, ends, swept_radii, np.ones(7, bool), velocities, sweep, None, np.inf,
                                       capsules))
        for other in (plain, capsule):
            other.barrier.set_external(capsules, radii, np.ones(7, bool), velocities)
        rows, seen = p.filter.rows_at(q), plain.filter.rows_at(q)
        exact = capsule.filter.rows_at(q).h[p.barrier.row_pair]  # the measured capsules' own h, per row's pair
        if rows.min_h_all >= 0.0:
            assert rows.h_measured is None
            continue
        person = rows.soft & rows.enabled
        under = person & (rows.h < 0.0)
        np.testing.assert_allclose(rows.h_measured[under], exact[under], atol=1e-9)
        np.testing.assert_array_equal(rows.h_measured[person & ~under], rows.h[person & ~under])
        inside += int(under.sum())
        if geometry == "capsule":
            assert (exact[person] >= rows.h[person] - 1e-9).all(), "the swept capsule encloses the measured one"
            np.testing.assert_array_equal(rows.person_inside(-1e-3), seen.person_inside(-1e-3))
    assert inside >= 20
    p.barrier.set_external(capsules, radii, np.ones(7, bool), velocities)
    assert p.filter.rows_at(q).h_measured is None
