"""HumanMemory: a capsule that turns invalid is held for ``hold_s``, then forgotten."""

from __future__ import annotations

import numpy as np
import pytest

from services.safety.assembly import build_pipeline
from services.safety.human_memory import FrameLateness, HumanMemory, external_capsules
from services.safety.protective_stop import STILL_SPEED
from shared.config import load_config
from shared.messages import HumanState
from shared.geometry import segment_closest_points
from shared.names import CAPSULE_NAMES

HOLD_S = 2.0
LEGS = [CAPSULE_NAMES.index("left_thigh"), CAPSULE_NAMES.index("right_thigh")]
RIGHT_FOREARM = CAPSULE_NAMES.index("right_forearm")


def state(x: float, valid: np.ndarray) -> HumanState:
    """A person whose capsules are offset by ``x`` (m), valid where ``valid``, moving at 1 m/s in x."""
    n = len(CAPSULE_NAMES)
    capsules = np.zeros((n, 2, 3))
    capsules[:, :, 0] = x
    capsules[:, 1, 2] = 0.3
    return HumanState(
        stamp=0.0, keypoints=np.zeros((15, 3)), keypoint_valid=np.ones(15, bool), theta=np.zeros(8),
        theta_valid=np.ones(8, bool), capsules=capsules, capsule_radii=np.full(n, 0.05 + x / 100),
        capsule_valid=valid, capsule_velocities=np.tile([1.0, 0.0, 0.0], (n, 2, 1)),
    )


def all_but(*slots: int) -> np.ndarray:
    valid = np.ones(len(CAPSULE_NAMES), bool)
    valid[list(slots)] = False
    return valid


def test_nothing_yet_and_valid_capsules_pass_through_padded() -> None:
    memory = HumanMemory()
    empty = memory.capsules(7, True)
    assert not empty.valid.any() and empty.velocities is None and not memory.lost
    message = state(1.0, np.ones(7, bool))
    memory.update(message, 0.0, HOLD_S)
    held, plain = memory.capsules(14, True), external_capsules(message, 14, True)
    for a, b in zip(held, plain, strict=True):
        np.testing.assert_array_equal(a, b)
    assert held.valid[:7].all() and not held.valid[7:].any()  # a second person's slots stay disabled
    assert memory.capsules(14, False).velocities is None


def test_a_stale_person_is_held_as_last_measured_without_velocity_or_sweep() -> None:
    """``stale`` (the newest message older than ``safety.human_timeout_s``): the capsules as last
    measured, whatever the velocity term and the sweep ask for; fresh, the same call sweeps them."""
    memory = HumanMemory()
    message = state(1.0, np.ones(7, bool))
    memory.update(message, 0.0, HOLD_S)
    stale, measured = memory.capsules(7, True, 0.093, stale=True), memory.capsules(7, False)
    for a, b in zip(stale, measured, strict=True):
        np.testing.assert_array_equal(a, b)
    assert stale.velocities is None and stale.sweep is None
    fresh = memory.capsules(7, True, 0.093)
    assert fresh.velocities is not None and (fresh.sweep > 0).all()
    assert not np.array_equal(fresh.endpoints, measured.endpoints)


def test_an_invalid_slot_is_held_without_velocity_then_forgotten_after_the_hold() -> None:
    memory = HumanMemory()
    memory.update(state(1.0, np.ones(7, bool)), 10.0, HOLD_S)
    memory.update(state(2.0, all_but(RIGHT_FOREARM)), 11.0, HOLD_S)  # the forearm vanished, the rest moved
    out = memory.capsules(7, True)
    assert out.valid.all() and memory.lost and memory.lost_capsules == ("right_forearm",)
    np.testing.assert_array_equal(out.endpoints[RIGHT_FOREARM], state(1.0, np.ones(7, bool)).capsules[RIGHT_FOREARM])
    np.testing.assert_allclose(out.radii[[RIGHT_FOREARM, 0]], [0.06, 0.07])  # remembered radius, current ones
    assert not out.velocities[RIGHT_FOREARM].any() and out.velocities[0].any()  # no velocity term when held
    np.testing.assert_array_equal(out.held, np.arange(7) == RIGHT_FOREARM)  # its velocity is unknown, not 0
    memory.update(state(2.0, all_but(RIGHT_FOREARM)), 10.0 + HOLD_S, HOLD_S)  # at the hold: still held
    assert memory.lost
    memory.update(state(2.0, all_but(RIGHT_FOREARM)), 10.0 + HOLD_S + 0.01, HOLD_S)  # past it: forgotten
    out = memory.capsules(7, True)
    assert not memory.lost and not out.valid[RIGHT_FOREARM] and out.valid.sum() == 6 and out.held is None
    memory.update(state(3.0, np.ones(7, bool)), 13.0, HOLD_S)  # seen again: valid, nothing lost
    assert not memory.lost and memory.capsules(7, True).endpoints[RIGHT_FOREARM, 0, 0] == 3.0


def test_the_whole_person_vanishing_is_held_and_the_same_update_twice_changes_nothing() -> None:
    memory = HumanMemory()
    memory.update(state(1.0, np.ones(7, bool)), 0.0, HOLD_S)
    gone = state(0.0, np.zeros(7, bool))
    memory.update(gone, 0.5, HOLD_S)
    first = memory.capsules(7, True)
    memory.update(gone, 0.5, HOLD_S)
    again = memory.capsules(7, True)
    assert memory.lost and first.valid.all() and (first.endpoints[:, :, 0] == 1.0).all()
    for a, b in zip(first, again, strict=True):
        np.testing.assert_array_equal(a, b)


def test_slots_never_seen_valid_do_not_block() -> None:
    memory = HumanMemory()
    for t in np.arange(0.0, 1.0, 1 / 30):  # legs outside the camera's view throughout
        memory.update(state(1.0, all_but(*LEGS)), float(t), HOLD_S)
        assert not memory.lost
    assert not memory.capsules(7, False).valid[LEGS].any()


def test_the_swept_capsule_encloses_the_seen_and_the_predicted_capsule_on_random_states() -> None:
    """human_predict_s: every point of the measured capsule and of the one its velocities carry τ
    ahead lies inside the capsule the rows get; a lost slot is not moved; τ = 0 changes nothing."""
    rng = np.random.default_rng(3)
    n = len(CAPSULE_NAMES)
    for trial in range(50):
        valid = rng.random(n) < 0.8
        message = HumanState(
            stamp=0.0, keypoints=np.zeros((15, 3)), keypoint_valid=np.ones(15, bool), theta=np.zeros(8),
            theta_valid=np.ones(8, bool), capsules=rng.uniform(-1, 1, (n, 2, 3)), capsule_radii=rng.uniform(0.04, 0.2, n),
            capsule_valid=valid, capsule_velocities=rng.normal(0.0, 2.0, (n, 2, 3)),
        )
        memory = HumanMemory()
        memory.update(state(0.0, np.ones(n, bool)), 0.0, HOLD_S)
        memory.update(message, 0.1, HOLD_S)  # slots invalid now are lost: held at x = 0
        tau = float(rng.uniform(0.01, 0.3))
        swept = memory.capsules(n, True, tau)
        seen = memory.capsules(n, True)
        for a, b in zip(memory.capsules(n, True, 0.0), seen, strict=True):
            np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(swept.velocities, seen.velocities)
        np.testing.assert_allclose(swept.radii, seen.radii + swept.sweep)  # the widening, reported per slot
        assert seen.sweep is None and (swept.sweep[~valid] == 0).all() and (swept.sweep[valid] > 0).all()
        np.testing.assert_array_equal(swept.endpoints[~valid], seen.endpoints[~valid])
        np.testing.assert_array_equal(swept.radii[~valid], seen.radii[~valid])
        for i in np.flatnonzero(valid):
            ends = message.capsules[i]
            for start in (ends, ends + tau * message.capsule_velocities[i]):
                for s in np.linspace(0.0, 1.0, 11):
                    point = start[0] + s * (start[1] - start[0])
                    gap = segment_closest_points(swept.endpoints[i, 0], swept.endpoints[i, 1], point, point).distance[0]
                    assert gap + message.capsule_radii[i] <= swept.radii[i] + 1e-12, (trial, i, s)


def test_a_state_published_late_after_its_capture_is_swept_further_by_its_lateness() -> None:
    """FrameLateness: a camera on time (the same capture → publication delay every frame) has
    lateness 0, so the sweep is human_predict_s's alone; a frame published 80 ms later than the
    fastest of the window is swept for τ + 0.08 s (1 m/s: the radius grows by 0.04 m more); the same
    state again counts once; a state without a capture stamp or with a negative delay has none, and
    the fastest delay is forgotten after the window (a perception restarted at another pace)."""
    memory, tau = HumanMemory(), 0.093
    valid = np.ones(7, bool)
    for k in range(10):  # on time: 60 ms from capture to publication every frame
        memory.update(state(1.0, valid).model_copy(update={"stamp": 1.06 + k / 30, "capture_stamp": 1.0 + k / 30}),
                      k / 30, HOLD_S)
        assert memory.lateness == 0.0
    on_time = memory.capsules(7, True, tau)
    np.testing.assert_allclose(on_time.sweep, 0.5 * tau)  # |v| τ / 2 at 1 m/s
    late = state(1.0, valid).model_copy(update={"stamp": 2.0 + 0.14, "capture_stamp": 2.0})
    for _ in range(2):  # the same state twice: counted once, the same result
        memory.update(late, 1.0, HOLD_S)
        assert memory.lateness == pytest.approx(0.08)
        np.testing.assert_allclose(memory.capsules(7, True, tau).sweep, 0.5 * (tau + 0.08))
    np.testing.assert_allclose(memory.capsules(7, True, tau, stale=True).radii, late.capsule_radii)  # stale: none
    for capture in (None, 5.0, float("nan")):  # no capture stamp, published before its capture, not finite
        memory.update(state(1.0, valid).model_copy(update={"stamp": 3.0, "capture_stamp": capture}), 1.1, HOLD_S)
        assert memory.lateness == 0.0
    window = FrameLateness(window=3)
    values = [window.update(state(1.0, valid).model_copy(update={"stamp": 10.0 + k + delay, "capture_stamp": 10.0 + k}))
              for k, delay in enumerate((0.06, 0.20, 0.20, 0.20))]
    assert values[:3] == pytest.approx([0.0, 0.14, 0.14])
    assert values[3] == pytest.approx(0.0)  # the 60 ms frame left the window: 200 ms is this perception's pace now
    first = FrameLateness().update(state(1.0, valid).model_copy(update={"stamp": 9.0, "capture_stamp": 1.0}))
    assert first == 0.0  # the first state is its own usual delay


def frames(path, n: int = 31, fps: float = 30.0, valid: np.ndarray | None = None, t0: float = 0.0) -> list[HumanState]:
    """``n`` states ``fps`` apart from ``t0`` (stamp = capture stamp) whose capsules are offset by
    ``path(t)`` (m; a float: along x, or a (7, 2, 3) array)."""
    valid = np.ones(7, bool) if valid is None else valid
    out = []
    for k in range(n):
        t = t0 + k / fps
        message = state(1.0, valid)
        out.append(message.model_copy(update={"stamp": t, "capture_stamp": t, "capsules": message.capsules + along_x(path(t))}))
    return out


def along_x(offset: float | np.ndarray) -> np.ndarray:
    return offset if isinstance(offset, np.ndarray) else np.array([offset, 0.0, 0.0])


def seen_after(states: list[HumanState], memory: HumanMemory | None = None) -> float:
    memory = HumanMemory() if memory is None else memory
    for message in states:
        memory.update(message, message.stamp, HOLD_S)
    return memory.seen_speed


def test_how_fast_the_capsules_were_seen_to_move_over_the_last_second() -> None:
    """``seen_speed`` over the last second of frames (SeenMotion): the speed of a steady motion, unknown
    (inf) until the frames span STILL_SEEN_FOR_S, for a capsule seen in under half of them and after
    the stream starts over; a still person under a camera's noise is still although their endpoints jump
    by centimetres from frame to frame; an arm punching out and back within the window is not."""
    walking = frames(lambda t: 0.9 * t)
    memory = HumanMemory()
    assert seen_after(walking[:15], memory) == np.inf  # 0.47 s seen: not yet known
    assert seen_after(walking[15:16], memory) == pytest.approx(0.9, rel=0.07)
    assert seen_after(walking[16:], memory) == pytest.approx(0.9, rel=0.04)
    assert memory._seen.frames == 31  # noqa: SLF001 (a second of frames, and the one before it)
    assert memory.capsules(7, True).seen_speed == memory.seen_speed
    assert memory.capsules(7, True, stale=True).seen_speed == np.inf  # stale: how they move now is unknown
    before = memory.seen_speed
    memory.update(walking[-1], 2.0, HOLD_S)  # the same message again: unchanged
    assert memory.seen_speed == before
    assert seen_after(frames(lambda t: 0.9 * t, t0=1.0, n=31), memory) == pytest.approx(0.9, rel=0.04)
    assert memory._seen.frames == 31  # noqa: SLF001
    assert seen_after(frames(lambda t: 0.9 * t, t0=0.5, n=2), memory) == np.inf  # back in time: started over

    rng = np.random.default_rng(3)
    noise = rng.normal(scale=0.01, size=(31, 7, 2, 3))  # 1.7 cm RMS per endpoint
    noisy = frames(lambda t: noise[round(t * 30)])
    jumps = max(np.linalg.norm(noise[k + 1] - noise[k], axis=2).max() * 30 for k in range(30))
    assert jumps > 1.0  # a frame-to-frame speed above 1 m/s ...
    assert seen_after(noisy) < STILL_SPEED  # ... on a person standing still
    punching = frames(lambda t: 0.15 * np.sin(2 * np.pi * 2.0 * t))  # out and back twice a second
    assert seen_after(punching) > 2 * STILL_SPEED

    legs_gone = frames(lambda t: 0.0)
    legs_gone[-1] = legs_gone[-1].model_copy(update={"capsule_valid": all_but(*LEGS)})
    assert seen_after(legs_gone) == pytest.approx(0.0, abs=1e-12)  # held, not measured: the others stood still
    appeared = frames(lambda t: 0.0, valid=all_but(RIGHT_FOREARM))
    for k in range(16, 31):
        appeared[k] = appeared[k].model_copy(update={"capsule_valid": np.ones(7, bool)})
    assert seen_after(appeared) == np.inf  # the forearm seen in 15 of 31 frames: unknown
    appeared[15] = appeared[15].model_copy(update={"capsule_valid": np.ones(7, bool)})
    assert seen_after(appeared) == pytest.approx(0.0, abs=1e-12)  # in 16 of 31: enough
    half_seen = [message.model_copy(update={"capsule_valid": appeared[k].capsule_valid})
                 for k, message in enumerate(walking[:31])]
    assert seen_after(half_seen) == pytest.approx(0.9, rel=0.07)  # over the half second it was seen
    nobody = frames(lambda t: 0.0)
    nobody[-1] = nobody[-1].model_copy(update={"capsule_valid": np.zeros(7, bool)})
    assert seen_after(nobody) == 0.0
    assert external_capsules(walking[0], 7, True).seen_speed == np.inf  # one message as it is: unknown


def test_the_person_speed_is_the_seen_one_whatever_their_velocities_say() -> None:
    """The barrier's ``person_speed`` (what the back-out's stillness reads) is ``seen_speed``: the
    measured velocities (a camera's noise gives a still person metres per second; a capsule
    re-initialised after a jump has 0) do not count; unknown when not told or a capsule is held,
    0 with nobody there."""
    barrier = build_pipeline(load_config(environ={})).barrier
    message = state(1.0, np.ones(7, bool))
    zero = np.zeros((7, 2, 3))
    capsules = external_capsules(message, barrier.pairs.n_external, False)
    barrier.set_external(capsules.endpoints, capsules.radii, capsules.valid, zero + [0.0, 3.0, 0.0], seen_speed=0.04)
    assert barrier.person_speed == 0.04
    barrier.set_external(capsules.endpoints, capsules.radii, capsules.valid, zero, seen_speed=2.5)
    assert barrier.person_speed == 2.5
    barrier.set_external(capsules.endpoints, capsules.radii, capsules.valid, zero)
    assert barrier.person_speed == np.inf  # not told
    barrier.set_external(capsules.endpoints, capsules.radii, capsules.valid, zero, held=np.arange(7) == 2, seen_speed=0.0)
    assert barrier.person_speed == np.inf
    barrier.set_external(capsules.endpoints, capsules.radii, np.zeros(7, bool), zero)
    assert barrier.person_speed == 0.0
    barrier.set_external(*capsules._replace(velocities=zero))  # inf: one message as it is
    assert barrier.person_speed == np.inf


def test_the_seen_speed_is_over_the_frames_interval_when_the_states_carry_capture_stamps() -> None:
    """Frames 1/30 s apart published in bunches 2 ms apart (inference stalling): the window and the
    speed are the frames' (0.9 m/s), not the publications'."""
    bunched = [message.model_copy(update={"stamp": 5.0 + (k // 4) * 4 / 30 + (k % 4) * 0.002})
               for k, message in enumerate(frames(lambda t: 0.9 * t))]
    assert seen_after(bunched) == pytest.approx(0.9, rel=0.04)
