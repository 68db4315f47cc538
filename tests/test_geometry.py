"""Tests for shared.geometry: exact segment/segment distance, capsules, normals.

The reference for the distance is an independent brute force: for a fixed
``s`` the distance from ``P(s)`` to segment 2 is exact (clamped projection),
``f(s) = dist(P(s), S2)`` is convex on [0, 1], so a dense scan over ``s``
brackets the minimiser and golden-section search refines it to ~1e-14 in
``s`` (~1e-14 m in ``f`` for segments of length O(1 m)).
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from shared.geometry import (
    Capsule,
    CapsuleDistance,
    SegmentClosestPoints,
    capsule_distance,
    safe_normal,
    segment_closest_points,
)

# Any numpy floating-point warning (overflow, 0/0, ...) is a failure.
pytestmark = pytest.mark.filterwarnings("error")

TOL_D = 1e-9  # distance vs reference (m)
TOL_PT = 1e-12  # closest points on their segments (m)

# ----------------------------------------------------------------------------
# Brute-force reference
# ----------------------------------------------------------------------------

_INV_PHI = (np.sqrt(5.0) - 1.0) / 2.0


def _point_segment_distance(x: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Exact distance from points x (M, K, 3) to segments [a, b] (M, 3)."""
    d = (b - a)[:, None, :]
    dd = np.einsum("mkj,mkj->mk", d, d)
    w = x - a[:, None, :]
    t = np.einsum("mkj,mkj->mk", w, d) / np.where(dd > 0.0, dd, 1.0)
    t = np.clip(np.where(dd > 0.0, t, 0.0), 0.0, 1.0)
    diff = w - t[..., None] * d
    return np.sqrt(np.einsum("mkj,mkj->mk", diff, diff))


def reference_distance(a1, b1, a2, b2, n_scan: int = 65, n_golden: int = 64) -> np.ndarray:
    """min_s dist(a1 + s (b1 - a1), [a2, b2]) by dense scan + golden section."""
    a1, b1, a2, b2 = (np.asarray(x, dtype=np.float64) for x in (a1, b1, a2, b2))
    d1 = b1 - a1

    def f(s: np.ndarray) -> np.ndarray:  # s: (M, K)
        return _point_segment_distance(a1[:, None, :] + s[..., None] * d1[:, None, :], a2, b2)

    m = a1.shape[0]
    grid = np.broadcast_to(np.linspace(0.0, 1.0, n_scan), (m, n_scan))
    f_grid = f(grid)
    k = np.argmin(f_grid, axis=1)
    h = 1.0 / (n_scan - 1)
    lo = np.clip((k - 1) * h, 0.0, 1.0)
    hi = np.clip((k + 1) * h, 0.0, 1.0)
    x1 = hi - _INV_PHI * (hi - lo)
    x2 = lo + _INV_PHI * (hi - lo)
    f1 = f(x1[:, None])[:, 0]
    f2 = f(x2[:, None])[:, 0]
    for _ in range(n_golden):
        left = f1 <= f2  # convex f: a minimiser lies in [lo, x2] if left, else [x1, hi]
        hi = np.where(left, x2, hi)
        lo = np.where(left, lo, x1)
        x_new = np.where(left, hi - _INV_PHI * (hi - lo), lo + _INV_PHI * (hi - lo))
        f_new = f(x_new[:, None])[:, 0]
        x1, x2 = np.where(left, x_new, x2), np.where(left, x1, x_new)
        f1, f2 = np.where(left, f_new, f2), np.where(left, f1, f_new)
    f_mid = f(0.5 * (lo + hi)[:, None])[:, 0]
    return np.minimum.reduce([f_grid.min(axis=1), f1, f2, f_mid])


# ----------------------------------------------------------------------------
# Deterministic random families of segment pairs
# ----------------------------------------------------------------------------


def _unit(rng: np.random.Generator, n: int) -> np.ndarray:
    v = rng.normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def _perp(rng: np.random.Generator, d: np.ndarray) -> np.ndarray:
    """Random unit vectors orthogonal to the rows of d."""
    v = rng.normal(size=d.shape)
    v -= (np.einsum("ij,ij->i", v, d) / np.einsum("ij,ij->i", d, d))[:, None] * d
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def family_general(rng, n):
    return tuple(rng.uniform(-1.0, 1.0, size=(n, 3)) for _ in range(4))


def family_parallel(rng, n):
    a1 = rng.uniform(-1, 1, (n, 3))
    d1 = rng.uniform(-1, 1, (n, 3))
    k = rng.uniform(-2, 2, n)  # includes anti-parallel
    off = _perp(rng, d1) * rng.uniform(0.0, 1.0, n)[:, None] + d1 * rng.uniform(-2, 2, n)[:, None]
    a2 = a1 + off
    b2 = a2 + k[:, None] * d1
    return a1, a1 + d1, a2, b2


def family_parallel_axis(rng, n):
    """Exactly parallel in floating point (axis-aligned, dyadic coordinates)."""
    a1 = np.round(rng.uniform(-1, 1, (n, 3)) * 64) / 64
    a2 = np.round(rng.uniform(-1, 1, (n, 3)) * 64) / 64
    axis = rng.integers(0, 3, n)
    l1 = np.round(rng.uniform(-1, 1, n) * 64) / 64
    l2 = np.round(rng.uniform(-1, 1, n) * 64) / 64
    b1 = a1.copy()
    b2 = a2.copy()
    b1[np.arange(n), axis] += l1
    b2[np.arange(n), axis] += l2
    return a1, b1, a2, b2


def family_collinear(rng, n, overlapping: bool):
    a1 = rng.uniform(-1, 1, (n, 3))
    d1 = rng.uniform(-1, 1, (n, 3))
    if overlapping:
        u = rng.uniform(-0.5, 1.5, n)
        v = rng.uniform(-0.5, 1.5, n)
        # force overlap of [min(u,v), max(u,v)] with [0, 1]
        v = np.where(np.maximum(u, v) < 0.0, rng.uniform(0, 1, n), v)
        v = np.where(np.minimum(u, v) > 1.0, rng.uniform(0, 1, n), v)
    else:
        side = rng.random(n) < 0.5
        u = np.where(side, rng.uniform(1.05, 2.0, n), rng.uniform(-2.0, -0.05, n))
        v = np.where(side, rng.uniform(1.05, 2.0, n), rng.uniform(-2.0, -0.05, n))
    a2 = a1 + u[:, None] * d1
    b2 = a1 + v[:, None] * d1
    return a1, a1 + d1, a2, b2


def family_crossing(rng, n):
    """Segments through a common point X (interior or endpoint): d = 0."""
    x = rng.uniform(-1, 1, (n, 3))
    e1 = _unit(rng, n)
    e2 = _unit(rng, n)
    # endpoint touches (T-junctions, V shapes) in about a third of the cases
    al = np.where(rng.random(n) < 0.15, 0.0, rng.uniform(0.05, 1.0, n))
    be = rng.uniform(0.05, 1.0, n)
    ga = np.where(rng.random(n) < 0.15, 0.0, rng.uniform(0.05, 1.0, n))
    de = rng.uniform(0.05, 1.0, n)
    return (
        x - al[:, None] * e1,
        x + be[:, None] * e1,
        x - ga[:, None] * e2,
        x + de[:, None] * e2,
    )


def family_degenerate(rng, n):
    a1, b1, a2, b2 = family_general(rng, n)
    which = rng.integers(0, 3, n)  # 0: seg1 point, 1: seg2 point, 2: both
    b1 = np.where((which == 0)[:, None] | (which == 2)[:, None], a1, b1)
    b2 = np.where((which == 1)[:, None] | (which == 2)[:, None], a2, b2)
    return a1, b1, a2, b2


def family_near_parallel(rng, n):
    """Small angle (1e-12 .. 1e-3 rad), often nearly intersecting."""
    a1, b1, a2, _ = family_parallel(rng, n)
    d1 = b1 - a1
    ang = 10.0 ** rng.uniform(-12, -3, n)
    k = rng.uniform(-2, 2, n)
    d2 = k[:, None] * (d1 + ang[:, None] * np.linalg.norm(d1, axis=1)[:, None] * _perp(rng, d1))
    near = rng.random(n) < 0.5
    # nearly intersecting: put a2 on the line of segment 1
    a2 = np.where(near[:, None], a1 + rng.uniform(-0.5, 1.5, n)[:, None] * d1, a2)
    return a1, b1, a2, a2 + d2


def family_tiny(rng, n):
    """Segments of length 1e-300 .. 1e-6 (one or both), no special casing expected."""
    a1, b1, a2, b2 = family_general(rng, n)
    lens = 10.0 ** rng.uniform(-300, -6, n)
    which = rng.integers(0, 3, n)
    t1 = a1 + lens[:, None] * _unit(rng, n)
    t2 = a2 + lens[:, None] * _unit(rng, n)
    b1 = np.where((which != 1)[:, None], t1, b1)
    b2 = np.where((which != 0)[:, None], t2, b2)
    return a1, b1, a2, b2


FAMILIES = {
    "general": lambda rng: family_general(rng, 3000),
    "parallel": lambda rng: family_parallel(rng, 1200),
    "parallel_axis": lambda rng: family_parallel_axis(rng, 800),
    "collinear_overlap": lambda rng: family_collinear(rng, 1000, overlapping=True),
    "collinear_disjoint": lambda rng: family_collinear(rng, 1000, overlapping=False),
    "crossing": lambda rng: family_crossing(rng, 1200),
    "degenerate": lambda rng: family_degenerate(rng, 1200),
    "near_parallel": lambda rng: family_near_parallel(rng, 1200),
    "tiny": lambda rng: family_tiny(rng, 600),
}


def _check_result_invariants(res: SegmentClosestPoints, a1, b1, a2, b2) -> None:
    n = a1.shape[0]
    assert res.distance.shape == (n,) and res.s.shape == (n,) and res.t.shape == (n,)
    assert res.p.shape == (n, 3) and res.q.shape == (n, 3)
    for arr in res:
        assert np.all(np.isfinite(arr))
    assert np.all((res.s >= 0.0) & (res.s <= 1.0))
    assert np.all((res.t >= 0.0) & (res.t <= 1.0))
    np.testing.assert_allclose(res.p, a1 + res.s[:, None] * (b1 - a1), rtol=0, atol=TOL_PT)
    np.testing.assert_allclose(res.q, a2 + res.t[:, None] * (b2 - a2), rtol=0, atol=TOL_PT)
    np.testing.assert_allclose(
        res.distance, np.linalg.norm(res.p - res.q, axis=1), rtol=0, atol=TOL_PT
    )


@pytest.fixture(scope="module")
def random_pairs():
    rng = np.random.default_rng(20240611)
    out = {}
    for name, make in FAMILIES.items():
        out[name] = tuple(np.ascontiguousarray(x) for x in make(rng))
    return out


def test_enough_random_pairs(random_pairs):
    assert sum(v[0].shape[0] for v in random_pairs.values()) >= 10_000


@pytest.mark.parametrize("family", list(FAMILIES))
def test_against_brute_force(random_pairs, family):
    a1, b1, a2, b2 = random_pairs[family]
    res = segment_closest_points(a1, b1, a2, b2)
    _check_result_invariants(res, a1, b1, a2, b2)
    d_ref = reference_distance(a1, b1, a2, b2)
    err = np.abs(res.distance - d_ref)
    worst = int(np.argmax(err))
    assert err[worst] <= TOL_D, (
        f"{family}: |d - d_ref| = {err[worst]:.3e} at pair {worst}: "
        f"{a1[worst]}, {b1[worst]}, {a2[worst]}, {b2[worst]}"
    )
    # The reference is an upper bound on the true minimum up to rounding, and
    # the result is realised by points on the segments, so it too is >= the
    # true minimum: a much too large result would show as d > d_ref.
    assert np.all(res.distance <= d_ref + TOL_D)


def test_crossing_family_has_zero_distance(random_pairs):
    a1, b1, a2, b2 = random_pairs["crossing"]
    res = segment_closest_points(a1, b1, a2, b2)
    assert np.max(res.distance) < 1e-12
    np.testing.assert_allclose(res.p, res.q, rtol=0, atol=1e-12)


def test_collinear_overlap_zero_and_disjoint_gap(random_pairs):
    a1, b1, a2, b2 = random_pairs["collinear_overlap"]
    res = segment_closest_points(a1, b1, a2, b2)
    assert np.max(res.distance) < 1e-12
    a1, b1, a2, b2 = random_pairs["collinear_disjoint"]
    res = segment_closest_points(a1, b1, a2, b2)
    # gap = distance between nearest endpoints of the two collinear segments
    ends1 = np.stack([a1, b1], axis=1)
    ends2 = np.stack([a2, b2], axis=1)
    gap = np.linalg.norm(ends1[:, :, None, :] - ends2[:, None, :, :], axis=-1).min(axis=(1, 2))
    np.testing.assert_allclose(res.distance, gap, rtol=0, atol=1e-12)


def test_symmetry_and_orientation_invariance(random_pairs):
    a1, b1, a2, b2 = (np.concatenate(x) for x in zip(*random_pairs.values(), strict=True))
    d = segment_closest_points(a1, b1, a2, b2).distance
    swapped = segment_closest_points(a2, b2, a1, b1)
    reversed_ = segment_closest_points(b1, a1, b2, a2)
    np.testing.assert_allclose(swapped.distance, d, rtol=0, atol=TOL_D)
    np.testing.assert_allclose(reversed_.distance, d, rtol=0, atol=TOL_D)


def test_batch_matches_single_pairs(random_pairs):
    a1, b1, a2, b2 = (np.concatenate(x) for x in zip(*random_pairs.values(), strict=True))
    rng = np.random.default_rng(1)
    idx = rng.choice(a1.shape[0], size=200, replace=False)
    batch = segment_closest_points(a1, b1, a2, b2)
    for i in idx:
        one = segment_closest_points(a1[i], b1[i], a2[i], b2[i])
        assert one.distance.shape == (1,)
        # equal up to summation order inside numpy's reductions (the closest
        # points themselves are not unique for parallel pairs)
        np.testing.assert_allclose(one.distance[0], batch.distance[i], rtol=0, atol=1e-12)


def test_reference_itself_on_known_answers():
    """Guard the brute force: it must reproduce hand-computed distances."""
    a1 = np.array([[-1.0, 0, 0], [0, 0, 0], [0, 0, 0], [0, 0, 0]])
    b1 = np.array([[1.0, 0, 0], [1, 0, 0], [1, 0, 0], [1, 0, 0]])
    a2 = np.array([[0.0, -1, 1], [0.5, 2, 0], [3, 0, 0], [0.3, -1, 0]])
    b2 = np.array([[0.0, 1, 1], [1.5, 2, 0], [5, 0, 0], [0.3, 1, 0]])
    d_ref = reference_distance(a1, b1, a2, b2)
    np.testing.assert_allclose(d_ref, [1.0, 2.0, 2.0, 0.0], rtol=0, atol=1e-13)


# ----------------------------------------------------------------------------
# Hypothesis: invariants and reference on arbitrary inputs
# ----------------------------------------------------------------------------

coord = st.floats(min_value=-2.0, max_value=2.0, allow_nan=False, allow_infinity=False)
point = arrays(np.float64, (3,), elements=coord)


@st.composite
def segment_pairs(draw):
    a1 = draw(point)
    b1 = draw(st.one_of(point, st.just(a1)))
    a2 = draw(st.one_of(point, st.just(a1), st.just(b1)))
    kind = draw(st.sampled_from(["free", "parallel", "collinear", "point"]))
    if kind == "free":
        b2 = draw(point)
    elif kind == "parallel":
        b2 = a2 + draw(st.floats(-2.0, 2.0)) * (b1 - a1)
    elif kind == "collinear":
        u, v = draw(st.floats(-2.0, 3.0)), draw(st.floats(-2.0, 3.0))
        a2 = a1 + u * (b1 - a1)
        b2 = a1 + v * (b1 - a1)
    else:
        b2 = a2.copy()
    return a1, b1, a2, b2


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(segment_pairs())
def test_hypothesis_against_reference(pair):
    a1, b1, a2, b2 = (np.asarray(x, dtype=np.float64)[None, :] for x in pair)
    res = segment_closest_points(a1, b1, a2, b2)
    _check_result_invariants(res, a1, b1, a2, b2)
    d_ref = reference_distance(a1, b1, a2, b2)
    assert abs(res.distance[0] - d_ref[0]) <= TOL_D
    # no endpoint of either segment is closer to the other segment than d
    for x, a, b in ((a1, a2, b2), (b1, a2, b2), (a2, a1, b1), (b2, a1, b1)):
        assert res.distance[0] <= _point_segment_distance(x[:, None, :], a, b)[0, 0] + 1e-12


# ----------------------------------------------------------------------------
# Hand cases with known answers
# ----------------------------------------------------------------------------


def _one(a1, b1, a2, b2) -> SegmentClosestPoints:
    return segment_closest_points(*(np.asarray(x, dtype=np.float64) for x in (a1, b1, a2, b2)))


def test_perpendicular_skew_interior():
    r = _one([-1, 0, 0], [1, 0, 0], [0, -1, 1], [0, 1, 1])
    assert r.distance[0] == pytest.approx(1.0, abs=1e-15)
    np.testing.assert_allclose(r.p[0], [0, 0, 0], atol=1e-15)
    np.testing.assert_allclose(r.q[0], [0, 0, 1], atol=1e-15)
    assert r.s[0] == pytest.approx(0.5) and r.t[0] == pytest.approx(0.5)


def test_perpendicular_skew_clamped():
    # the lines' closest points are off segment 1; answer uses its endpoint b1
    r = _one([-1, 0, 0], [1, 0, 0], [3, -1, 1], [3, 1, 1])
    assert r.distance[0] == pytest.approx(np.sqrt(5.0), abs=1e-15)
    np.testing.assert_allclose(r.p[0], [1, 0, 0], atol=1e-15)
    np.testing.assert_allclose(r.q[0], [3, 0, 1], atol=1e-15)
    assert r.s[0] == 1.0 and r.t[0] == pytest.approx(0.5)


def test_skew_both_clamped():
    # closest line points beyond both segments -> endpoint/endpoint
    r = _one([0, 0, 0], [1, 0, 0], [2, 1, 1], [2, 3, 1])
    assert r.distance[0] == pytest.approx(np.sqrt(1 + 1 + 1), abs=1e-15)
    assert (r.s[0], r.t[0]) == (1.0, 0.0)


def test_parallel_offset():
    r = _one([0, 0, 0], [1, 0, 0], [0.5, 2, 0], [1.5, 2, 0])
    assert r.distance[0] == pytest.approx(2.0, abs=1e-15)
    np.testing.assert_allclose(r.q[0] - r.p[0], [0, 2, 0], atol=1e-15)
    assert 0.5 <= r.s[0] <= 1.0  # any point of the overlap
    # anti-parallel, same answer
    r2 = _one([0, 0, 0], [1, 0, 0], [1.5, 2, 0], [0.5, 2, 0])
    assert r2.distance[0] == pytest.approx(2.0, abs=1e-15)
    np.testing.assert_allclose(r2.q[0] - r2.p[0], [0, 2, 0], atol=1e-15)


def test_parallel_no_overlap():
    r = _one([0, 0, 0], [1, 0, 0], [2, 1, 0], [3, 1, 0])
    assert r.distance[0] == pytest.approx(np.sqrt(2.0), abs=1e-15)
    np.testing.assert_allclose(r.p[0], [1, 0, 0], atol=1e-15)
    np.testing.assert_allclose(r.q[0], [2, 1, 0], atol=1e-15)


@pytest.mark.parametrize("flip", [False, True])
def test_collinear_disjoint_gap(flip):
    a2, b2 = ([3, 0, 0], [5, 0, 0]) if not flip else ([5, 0, 0], [3, 0, 0])
    r = _one([0, 0, 0], [1, 0, 0], a2, b2)
    assert r.distance[0] == pytest.approx(2.0, abs=1e-15)
    np.testing.assert_allclose(r.p[0], [1, 0, 0], atol=1e-15)
    np.testing.assert_allclose(r.q[0], [3, 0, 0], atol=1e-15)
    assert r.t[0] == (1.0 if flip else 0.0)


def test_collinear_overlapping():
    r = _one([0, 0, 0], [2, 0, 0], [1, 0, 0], [3, 0, 0])
    assert r.distance[0] == 0.0
    assert 1.0 <= r.p[0][0] <= 2.0


def test_point_point():
    r = _one([1, 2, 3], [1, 2, 3], [4, 6, 3], [4, 6, 3])
    assert r.distance[0] == pytest.approx(5.0, abs=1e-15)
    assert (r.s[0], r.t[0]) == (0.0, 0.0)
    np.testing.assert_array_equal(r.p[0], [1, 2, 3])
    np.testing.assert_array_equal(r.q[0], [4, 6, 3])


@pytest.mark.parametrize(
    "pt, d, t",
    [([0.5, 1, 0], 1.0, 0.5), ([2, 1, 0], np.sqrt(2), 1.0), ([-3, 0, 4], 5.0, 0.0)],
)
def test_point_segment_both_orders(pt, d, t):
    seg = ([0, 0, 0], [1, 0, 0])
    r = _one(pt, pt, *seg)
    assert r.distance[0] == pytest.approx(d, abs=1e-15)
    assert r.s[0] == 0.0 and r.t[0] == pytest.approx(t)
    r2 = _one(*seg, pt, pt)
    assert r2.distance[0] == pytest.approx(d, abs=1e-15)
    assert r2.t[0] == 0.0 and r2.s[0] == pytest.approx(t)
    np.testing.assert_allclose(r2.q[0], pt, atol=0)


def test_x_crossing():
    r = _one([-1, 0, 0], [1, 0, 0], [0, -1, 0], [0, 1, 0])
    assert r.distance[0] == 0.0
    np.testing.assert_allclose(r.p[0], [0, 0, 0], atol=1e-15)
    np.testing.assert_allclose(r.q[0], [0, 0, 0], atol=1e-15)
    assert r.s[0] == pytest.approx(0.5) and r.t[0] == pytest.approx(0.5)


def test_t_junction_touching():
    r = _one([-1, 0, 0], [1, 0, 0], [0.25, 0, 0], [0.25, 2, 0])
    assert r.distance[0] == 0.0
    assert r.s[0] == pytest.approx(0.625) and r.t[0] == 0.0


def test_tiny_segments_are_finite_and_exact():
    r = _one([0, 0, 0], [1e-300, 0, 0], [0, 1e-200, 1], [0, 0, 1])
    assert np.all(np.isfinite(r.distance)) and r.distance[0] == pytest.approx(1.0, abs=1e-15)


def test_broadcasting_one_against_many():
    rng = np.random.default_rng(3)
    a2 = rng.uniform(-1, 1, (7, 3))
    b2 = rng.uniform(-1, 1, (7, 3))
    a1, b1 = np.array([0.0, 0, 0]), np.array([1.0, 0, 0])
    r = segment_closest_points(a1, b1, a2, b2)
    assert r.distance.shape == (7,) and r.p.shape == (7, 3)
    full = segment_closest_points(np.tile(a1, (7, 1)), np.tile(b1, (7, 1)), a2, b2)
    np.testing.assert_allclose(r.distance, full.distance, rtol=0, atol=0)


def test_list_inputs_and_bad_shape():
    r = segment_closest_points([0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0])
    assert r.distance.shape == (1,) and r.distance[0] == pytest.approx(1.0)
    with pytest.raises(ValueError):
        segment_closest_points(
            np.zeros((4, 2)), np.zeros((4, 2)), np.zeros((4, 2)), np.zeros((4, 2))
        )


# ----------------------------------------------------------------------------
# Capsules
# ----------------------------------------------------------------------------


def test_capsule_distance_separated_and_penetrating():
    c1 = Capsule(np.array([-1.0, 0, 0]), np.array([1.0, 0, 0]), 0.1)
    c2 = Capsule(np.array([0.0, -1, 0.5]), np.array([0.0, 1, 0.5]), 0.15)
    res = capsule_distance(c1, c2)
    assert isinstance(res, CapsuleDistance)
    assert res.distance == pytest.approx(0.5)
    assert res.signed_distance == pytest.approx(0.25)
    np.testing.assert_allclose(res.p, [0, 0, 0], atol=1e-15)
    np.testing.assert_allclose(res.q, [0, 0, 0.5], atol=1e-15)
    c3 = Capsule([0.0, -1, 0.3], [0.0, 1, 0.3], 0.25)
    assert capsule_distance(c1, c3).signed_distance == pytest.approx(-0.05)
    # spheres are zero-length capsules
    s1 = Capsule([0.0, 0, 0], [0.0, 0, 0], 1.0)
    s2 = Capsule([3.0, 4, 0], [3.0, 4, 0], 2.0)
    assert capsule_distance(s1, s2).signed_distance == pytest.approx(2.0)


def test_capsule_validation_and_immutability():
    with pytest.raises(ValueError):
        Capsule([0, 0, 0], [1, 0, 0], -0.1)
    with pytest.raises(ValueError):
        Capsule([0, 0, np.nan], [1, 0, 0], 0.1)
    src = np.array([0.0, 0, 0])
    c = Capsule(src, [1, 0, 0], 0.1)
    src[0] = 5.0  # the capsule keeps its own copy
    assert c.a[0] == 0.0
    with pytest.raises(ValueError):
        c.a[0] = 1.0  # read-only
    with pytest.raises(AttributeError):
        c.radius = 1.0  # type: ignore[misc]


# ----------------------------------------------------------------------------
# safe_normal
# ----------------------------------------------------------------------------


def _assert_unit(n: np.ndarray) -> None:
    assert np.all(np.isfinite(n))
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, rtol=0, atol=1e-12)


def test_safe_normal_regular_case():
    p = np.array([[1.0, 2, 3], [0, 0, 0]])
    q = np.array([[1.0, 2, 1], [3, 4, 0]])
    n = safe_normal(p, q)
    np.testing.assert_allclose(n, [[0, 0, 1], [-0.6, -0.8, 0]], atol=1e-15)


def test_safe_normal_coincident_default_and_direction():
    p = np.zeros((3, 3))
    n = safe_normal(p, p)
    _assert_unit(n)
    np.testing.assert_array_equal(n, np.tile([0.0, 0, 1], (3, 1)))
    n = safe_normal(p, p + 1e-12, np.array([[2.0, 0, 0], [0, 0, 0], [0, 3, 4]]))
    np.testing.assert_allclose(n, [[1, 0, 0], [0, 0, 1], [0, 0.6, 0.8]], atol=1e-15)


def test_safe_normal_crossing_uses_cross_product():
    seg = (
        np.array([-1.0, 0, 0]),
        np.array([1.0, 0, 0]),
        np.array([0.0, -1, 0]),
        np.array([0.0, 1, 0]),
    )
    r = segment_closest_points(*seg)
    n = safe_normal(r.p, r.q, seg)
    _assert_unit(n)
    np.testing.assert_allclose(np.abs(n[0]), [0, 0, 1], atol=1e-15)
    # nearly crossing (0 < d < eps): the fallback points from segment 2 to 1,
    # i.e. it agrees with the (ill-conditioned) true (p - q) / d
    for dz in (-5e-10, 5e-10):
        seg_near = (seg[0], seg[1], seg[2] + [0, 0, dz], seg[3] + [0, 0, dz])
        r = segment_closest_points(*seg_near)
        assert 0 < r.distance[0] < 1e-9
        n = safe_normal(r.p, r.q, seg_near)
        np.testing.assert_allclose(n[0], [0, 0, -np.sign(dz)], atol=1e-15)
        np.testing.assert_allclose(n[0], (r.p - r.q)[0] / r.distance[0], atol=1e-6)
    # the same with single (3,) endpoints broadcast against N rows of p, q
    n = safe_normal(np.zeros((4, 3)), np.zeros((4, 3)), seg)
    assert n.shape == (4, 3)
    np.testing.assert_allclose(np.abs(n), np.tile([0, 0, 1.0], (4, 1)), atol=1e-15)
    with pytest.raises(ValueError):
        safe_normal(np.zeros((4, 3)), np.zeros((4, 3)), np.ones((3, 3)))


def test_safe_normal_collinear_and_points():
    # collinear touching segments: normal orthogonal to the segment
    seg = (
        np.array([0.0, 0, 0]),
        np.array([1.0, 1, 0]),
        np.array([1.0, 1, 0]),
        np.array([2.0, 2, 0]),
    )
    r = segment_closest_points(*seg)
    assert r.distance[0] == 0.0
    n = safe_normal(r.p, r.q, seg)
    _assert_unit(n)
    assert abs(n[0] @ np.array([1.0, 1, 0])) < 1e-12
    # parallel side by side within eps: no usable offset -> axis orthogonal to seg 1
    seg = (
        np.array([0.0, 0, 0]),
        np.array([1.0, 0, 0]),
        np.array([0.0, -1e-12, 0]),
        np.array([1.0, -1e-12, 0]),
    )
    r = segment_closest_points(*seg)
    n = safe_normal(r.p, r.q, seg)
    _assert_unit(n)
    assert abs(n[0][0]) < 1e-15
    # nearly parallel (angle 1e-7 < 1e-6) crossing, midpoints offset: the
    # component of the midpoint offset orthogonal to segment 1
    seg = (
        np.array([-1.0, 0, 0]),
        np.array([1.0, 0, 0]),
        np.array([-0.5, -0.5e-7, 0]),
        np.array([1.5, 1.5e-7, 0]),
    )
    r = segment_closest_points(*seg)
    assert r.distance[0] < 1e-15
    n = safe_normal(r.p, r.q, seg)
    _assert_unit(n)
    np.testing.assert_allclose(n[0], [0, -1, 0], atol=1e-12)
    # point on a segment
    seg = (
        np.array([0.3, 0, 0]),
        np.array([0.3, 0, 0]),
        np.array([0.0, 0, 0]),
        np.array([1.0, 0, 0]),
    )
    r = segment_closest_points(*seg)
    n = safe_normal(r.p, r.q, seg)
    _assert_unit(n)
    assert abs(n[0][0]) < 1e-12
    # two coincident points: +z
    seg = tuple(np.array([0.2, 0.2, 0.2]) for _ in range(4))
    r = segment_closest_points(*seg)
    np.testing.assert_array_equal(safe_normal(r.p, r.q, seg), [[0, 0, 1]])


@settings(max_examples=200, deadline=None)
@given(segment_pairs(), st.sampled_from([0.0, 1e-15, 1e-10]))
def test_safe_normal_hypothesis_finite_unit(pair, jitter):
    a1, b1, a2, b2 = (np.asarray(x, dtype=np.float64)[None, :] for x in pair)
    r = segment_closest_points(a1, b1, a2, b2)
    p = r.p
    q = p + jitter  # coincident or within eps -> fallback
    for fb in (None, (a1, b1, a2, b2), b1 - a1):
        n = safe_normal(p, q, fb)
        assert n.shape == (1, 3)
        _assert_unit(n)
