"""Speed and separation (services.safety.separation, ``safety.human_speed_mps``): the reference is capped
so that each joint brakes before a person approaching at v_h arrives (random rows, against the closed
form), and in the real filter only the reference changes: the rows hold as they do without it, on random
states of the default robot with a person beside the forearm."""

from __future__ import annotations

import numpy as np

from services.safety.separation import STATIC_LEVER, cap_reference, speed_caps
from shared.messages import SafetyMode
from tests.support.pipelines import DT, pipeline_for, random_safe_state
from tests.test_standoff import still_person_near_the_forearm

V_H = 1.6


def stops_in_time(u: np.ndarray, lever: np.ndarray, h: np.ndarray, accel: np.ndarray) -> np.ndarray:
    """(m, n) bool: joint j at |u_j| brakes (at a_j) within row i's h_i while a person closes at v_h."""
    speed = np.abs(u)[None, :]
    return V_H * speed / accel + lever * speed**2 / (2.0 * accel) <= h[:, None] + 1e-12


def random_rows(rng: np.random.Generator, n: int = 8) -> tuple[np.ndarray, ...]:
    m = int(rng.integers(1, 30))
    A = rng.normal(scale=0.3, size=(m, n))
    A[rng.random((m, n)) < 0.3] = 0.0  # joints that do not move a pair
    h = rng.uniform(-0.05, 0.5, size=m)
    enabled = rng.random(m) > 0.1
    h[~enabled] = np.nan
    soft = rng.random(m) < 0.7
    accel = rng.uniform(5.0, 300.0, size=n)
    return A, h, soft, enabled, accel


def test_the_capped_reference_brakes_in_time_for_every_person_row_and_is_left_alone_elsewhere() -> None:
    rng = np.random.default_rng(11)
    n = 8
    for _ in range(400):
        A, h, soft, enabled, accel = random_rows(rng, n)
        u_ref = rng.normal(scale=5.0, size=n)
        weights = rng.uniform(0.5, 2.0, size=n)
        f = np.full(n + 3, 7.0)  # the QP's linear term (and rows' bounds beyond n: untouched)
        caps = np.empty(n)
        out = u_ref.copy()
        capped = cap_reference(A, h, soft, enabled, accel, V_H, weights, out, f, caps)
        person = soft & enabled
        lever = np.abs(A[person])
        moved = lever > STATIC_LEVER
        ok = stops_in_time(out, lever, np.maximum(h[person], 0.0), accel)
        assert (ok | ~moved).all()  # every row a joint moves: it brakes before the person arrives
        inside = (h[person] <= 0.0)[:, None] & moved
        assert (out[inside.any(axis=0)] == 0.0).all()  # a person inside a row's margin: that joint stops
        changed = out != u_ref
        assert capped == changed.sum()
        assert (np.abs(out) <= np.abs(u_ref)).all() and (np.sign(out[changed]) * np.sign(u_ref[changed]) >= 0).all()
        assert np.allclose(np.abs(out[changed]), caps[changed])  # clipped exactly at the cap: no slower
        assert (f[:n][changed] == -weights[changed] * out[changed]).all() and (f[:n][~changed] == 7.0).all()
        assert (f[n:] == 7.0).all()
        free = ~(moved.any(axis=0))
        assert np.isinf(caps[free]).all() and (out[free] == u_ref[free]).all()  # no person row moved: no cap


def test_the_cap_is_the_closed_form_and_shrinks_as_the_person_nears() -> None:
    """One row, one joint: the cap solves v_h c/a + ℓ c²/(2a) = h, and falls with h (to 0 at h = 0)."""
    accel = np.array([60.0])
    caps = np.empty(1)
    previous = np.inf
    for h in (0.5, 0.2, 0.1, 0.02, 0.0):
        speed_caps(np.array([[-0.4]]), np.array([h]), np.array([True]), np.array([True]), accel, V_H, caps)
        c = caps[0]
        assert np.isclose(V_H * c / 60.0 + 0.4 * c * c / 120.0, h, atol=1e-12)
        assert c < previous
        previous = c
    assert caps[0] == 0.0
    for soft, enabled, h in ((False, True, 0.1), (True, False, 0.1), (True, True, np.nan)):
        speed_caps(np.array([[-0.4]]), np.array([h]), np.array([soft]), np.array([enabled]), accel, V_H, caps)
        assert np.isinf(caps[0])  # hard rows (self pairs), disabled rows and a missing capsule cap nothing


def test_in_the_filter_only_the_reference_changes_and_every_row_holds_on_random_states() -> None:
    """A person standing beside the left forearm, a random target: with v_h the step's u_ref brakes in time
    for every person row, the hard rows hold and no person row is relaxed more than without it (v_h = 0)."""
    capped, free = pipeline_for(human_speed_mps=V_H), pipeline_for(human_speed_mps=0.0)
    kin = capped.kinematics
    accel = capped.filter.params.accel_max
    rng = np.random.default_rng(5)
    checked = slowed = 0
    for i in range(100):
        q = random_safe_state(capped, rng)
        q_nom = np.clip(q + rng.normal(scale=0.8, size=q.shape), kin.q_min, kin.q_max)
        still_person_near_the_forearm((capped, free), np.random.default_rng(i), q)
        for p in (capped, free):
            p.filter.reset(q)
        result, plain = (p.filter.step(q_nom, DT) for p in (capped, free))
        assert result.mode != SafetyMode.HOLD and np.isfinite(result.u).all()
        if result.protective_stop:
            continue
        rows = capped.filter.rows_at(q)
        person = rows.soft & rows.enabled
        lever = np.abs(rows.A[person])
        ok = stops_in_time(result.u_ref, lever, np.maximum(rows.h[person], 0.0), accel)
        assert (ok | (lever <= STATIC_LEVER)).all()
        for block in capped.filter.blocks_at(q):  # the hard rows hold as the plain step's do
            hard = ~block.soft & (block.b <= 0.0)
            assert (block.A[hard] @ result.u >= block.b[hard] - 1e-6).all()
        assert result.relaxed.sum() <= plain.relaxed.sum()
        checked += 1
        slowed += bool((np.abs(result.u_ref) < np.abs(plain.u_ref) - 1e-9).any())
    assert checked >= 40, checked
    assert slowed >= 20, slowed  # the cap is what slows the reference (the same targets without it are faster)
