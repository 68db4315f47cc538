"""The standoff from a person (services.safety.standoff, ``safety.human_standoff_m``): a person row
only tightens and never demands a retreat (random rows), and the real filter closes on no person
capsule within the standoff while it closes at γ h without one (random states of the default robot)."""

from __future__ import annotations

import subprocess
import sys

import numpy as np

from services.safety.standoff import CREEP, apply_standoff
from shared.names import CAPSULE_NAMES
from tests.support.pipelines import DT, pipeline_for, random_safe_state
from tests.support.team import REPO

FOREARM = CAPSULE_NAMES.index("left_forearm")
GAMMA = 10.0


def test_a_row_only_tightens_never_demands_a_retreat_and_leaves_hard_and_disabled_rows_on_random_rows() -> None:
    rng = np.random.default_rng(7)
    for _ in range(500):
        m = int(rng.integers(1, 40))
        b = rng.normal(scale=0.5, size=m)
        h = rng.uniform(-0.1, 0.4, size=m)
        h[rng.random(m) < 0.1] = np.nan  # disabled rows (a missing capsule)
        soft = rng.random(m) < 0.6
        standoff = float(rng.uniform(0.0, 0.2))
        out = b.copy()
        apply_standoff(out, h, soft, GAMMA, standoff)
        assert (out >= b).all()  # only tightens: every u the new rows allow, the old ones did
        assert ((out > 0.0) == (b > 0.0)).all()  # a retreat is demanded exactly where it was: u = 0 meets min(b, 0)
        untouched = ~soft | np.isnan(h)
        assert (out[untouched] == b[untouched]).all()
        near = soft & (h <= standoff)
        assert (out[near] >= -CREEP).all()  # within the standoff: no closing beyond the creep
        far = soft & (h > standoff)
        assert (out[far] >= -GAMMA * (h[far] - standoff) - CREEP - 1e-15).all()
    b = rng.normal(size=20)
    out = b.copy()
    apply_standoff(out, rng.uniform(0, 0.1, 20), np.ones(20, bool), GAMMA, 0.0)
    assert (out == b).all()  # 0: the paper's rows


def still_person_near_the_forearm(pipelines, rng: np.random.Generator, q: np.ndarray) -> None:
    """One person capsule (the others missing), standing still a few centimetres off the side of the
    left forearm at ``q``."""
    endpoints, _ = pipelines[0].kinematics.compute(q)
    forearm = endpoints[FOREARM]
    along = forearm[1] - forearm[0]
    normal = rng.normal(size=3)
    normal -= normal @ along / (along @ along) * along
    normal /= np.linalg.norm(normal)
    centre = forearm.mean(axis=0) + float(rng.uniform(0.13, 0.2)) * normal  # radii 0.06 + the forearm's, φ, margin
    capsules = np.repeat(np.stack([centre - 0.3 * along, centre + 0.3 * along])[None], 7, axis=0)
    valid = np.arange(7) == 0
    for p in pipelines:
        p.barrier.set_external(capsules, np.full(7, 0.06), valid, np.zeros((7, 2, 3)))


def test_the_filter_closes_on_no_person_capsule_within_the_standoff_on_random_states() -> None:
    """From rest (no acceleration bound on a first step) the plain QP holds every row: a person row
    whose h is within D = 0.05 m allows no closing (but the 0.1 mm/s creep), one beyond it closing at
    γ (h − D) at most; the same
    targets without the standoff close on the person within D (so the rows are what stops them)."""
    with_standoff, without = pipeline_for(human_standoff_m=0.05), pipeline_for(human_standoff_m=0.0)
    kin = with_standoff.kinematics
    rng = np.random.default_rng(3)
    gamma = with_standoff.filter.params.gamma
    checked = closed_without = 0
    for i in range(120):
        q = random_safe_state(with_standoff, rng)
        q_nom = np.clip(q + rng.normal(scale=0.6, size=q.shape), kin.q_min, kin.q_max)
        still_person_near_the_forearm((with_standoff, without), np.random.default_rng(i), q)
        rows = with_standoff.filter.rows_at(q)
        person = rows.soft & np.isfinite(rows.h) & (rows.h > 0.0)
        near, far = person & (rows.h <= 0.05), person & (rows.h > 0.05)
        if not near.any():
            continue
        for p in (with_standoff, without):
            p.filter.reset(q)
        result = with_standoff.filter.step(q_nom, DT)
        if result.protective_stop or result.relaxed.any():
            continue
        rate = rows.A @ result.u
        assert (rate[near] >= -CREEP - 1e-6).all(), rate[near]
        assert (rate[far] >= -gamma * (rows.h[far] - 0.05) - CREEP - 1e-6).all()
        checked += 1
        free = without.filter.step(q_nom, DT)
        closed_without += bool((rows.A[near] @ free.u < -1e-3).any())
    assert checked >= 30, checked
    assert closed_without >= 10, closed_without  # without it the same targets close in within D


def test_the_warm_up_compiles_the_standoff_kernel_for_a_standoff_set_later_in_place() -> None:
    """A pipeline without a standoff never calls its compiled kernel; the standoff is set in place
    (no new pipeline), so its first call would compile inside a control tick unless the warm-up did
    it first. In a fresh process: after the warm-up the kernel has its compiled signature."""
    code = ("from services.safety.barriers.kernel import raise_to_standoff\n"
            "from tests.support.pipelines import DT, pipeline_for\n"
            "pipeline_for(human_standoff_m=0.0).warm_up(DT)\n"
            "print(len(raise_to_standoff.signatures))\n")
    done = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert int(done.stdout.split()[-1]) >= 1, done.stdout
