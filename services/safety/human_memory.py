"""The barrier's external capsules from the HumanState stream: a person who vanishes is remembered.

Perception marks a capsule invalid when it no longer sees that body part (occlusion, zero
confidence, the whole person gone beyond its point filter's hold). Absence of evidence is not
absence of the person, so per capsule slot :class:`HumanMemory` keeps the last valid capsule
(endpoints, radius) and when it was last valid, and applies this rule at each fresh HumanState
received at time ``now``:

- a slot valid in the message is used as it is (with its measured velocity when asked for), or
  swept along that velocity for ``safety.human_predict_s`` (the message shows the person a camera
  latency and a held frame ago: :func:`swept_capsules`), and further by the message's lateness
  (:class:`FrameLateness`: how much longer than usual it took from its capture to its publication,
  an inference or a camera stalling; the person moved on meanwhile);
- a slot the message marks invalid that was valid within ``hold_s`` (``safety.lost_human_hold_s``)
  is *lost*: its remembered capsule stays in the barrier, without a velocity term (the person may
  still be there), and while any slot is lost the robot stops imitating (q_nom = q_cbf);
- a lost slot last valid more than ``hold_s`` ago is forgotten (its rows are disabled) and
  imitation may resume with the remaining valid capsules; a slot never seen valid (legs outside
  the camera's view) is never lost and never blocks imitation.

How fast the capsules were *seen* to move over the last second of frames
(:class:`~services.safety.seen_motion.SeenMotion`) is what tells a person standing still from one
moving (the intrusion stop backs out of the first only).

Time is the caller's clock (the safety service: local receive time; the evaluator: source time).
Ages are taken at each fresh message only: between messages nothing changes, and a stale human
(no message for ``safety.human_timeout_s``) keeps every capsule the barrier holds. Updating again
with the same message and time gives the same result.
"""

from __future__ import annotations

import math
from collections import deque
from typing import NamedTuple

import numpy as np

from services.safety.nominal import frame_stamp
from services.safety.seen_motion import SeenMotion
from shared.messages import HumanState
from shared.names import CAPSULE_NAMES


class ExternalCapsules(NamedTuple):
    """The barrier's external capsule arrays, as ``set_external`` takes them (E external slots):
    endpoints (E,2,3) m, radii (E,) m, valid (E,) bool, velocities (E,2,3) m/s or None, sweep (E,) m
    how much each radius grew to enclose the capsule swept ahead (None: none swept), held (E,) bool
    the slots remembered rather than measured in the newest message, whose velocity (0) is unknown
    (None: none), seen_speed m/s how fast the person was seen to move
    (:class:`~services.safety.seen_motion.SeenMotion`; inf: unknown), measured (E,2,3) m the
    endpoints as measured, before the sweep (None: none swept)."""

    endpoints: np.ndarray
    radii: np.ndarray
    valid: np.ndarray
    velocities: np.ndarray | None
    sweep: np.ndarray | None = None
    held: np.ndarray | None = None
    seen_speed: float = math.inf
    measured: np.ndarray | None = None


def padded(
    n_external: int, endpoints: np.ndarray, radii: np.ndarray, valid: np.ndarray, velocities: np.ndarray | None,
    sweep: np.ndarray | None = None, held: np.ndarray | None = None, moved: float = math.inf,
    measured: np.ndarray | None = None,
) -> ExternalCapsules:
    """One person's capsules in the pair set's ``n_external`` slots (7 per person; the ``paper72``
    preset has a second person): this person fills the first 7, the other slots stay invalid
    (disabled rows); ``moved`` (m/s): their :attr:`ExternalCapsules.seen_speed` (inf: unknown);
    ``measured``: with a ``sweep``, the endpoints before it."""
    n = min(n_external, endpoints.shape[0])
    out = ExternalCapsules(np.zeros((n_external, 2, 3)), np.zeros(n_external), np.zeros(n_external, bool),
                           None if velocities is None else np.zeros((n_external, 2, 3)),
                           None if sweep is None else np.zeros(n_external),
                           None if held is None else np.zeros(n_external, bool), moved,
                           None if measured is None else np.zeros((n_external, 2, 3)))
    out.endpoints[:n], out.radii[:n], out.valid[:n] = endpoints[:n], radii[:n], valid[:n]
    if out.measured is not None:
        out.measured[:n] = measured[:n]
    if out.velocities is not None:
        out.velocities[:n] = velocities[:n]
    if out.sweep is not None:
        out.sweep[:n] = sweep[:n]
    if out.held is not None:
        out.held[:n] = held[:n]
    return out


def external_capsules(message: HumanState, n_external: int, use_velocity: bool) -> ExternalCapsules:
    """One message's capsules as they are (no memory) in ``n_external`` slots (see :func:`padded`);
    how they moved since a state before is unknown (``seen_speed`` inf, as for a first message)."""
    velocities = message.capsule_velocities if use_velocity else None
    return padded(n_external, message.capsules, message.capsule_radii, message.capsule_valid, velocities)


def swept_capsules(endpoints: np.ndarray, radii: np.ndarray, velocities: np.ndarray,
                   predict_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The capsules enclosing each capsule both where it is and where its velocity carries it in
    τ = ``predict_s`` (s): (endpoints (E,2,3) m, radii (E,) m, sweep (E,) m) from ``endpoints``
    (E,2,3) m, ``radii`` (E,) m and endpoint ``velocities`` (E,2,3) m/s.

    With endpoints a, b, radius r and displacements d_a = v_a τ, d_b = v_b τ, capsule i becomes
    [a + d_a/2, b + d_b/2] with radius r + sweep, sweep = max(|d_a|, |d_b|)/2: the point at parameter
    s of either segment, a + s(b − a) (+ (1 − s) d_a + s d_b when carried), lies within
    |(1 − s) d_a + s d_b|/2 ≤ sweep of the new axis at the same s. So the capsule as measured is
    always inside (a noisy velocity can only make the rows more cautious, never let the robot closer
    to where the person was seen): against any robot capsule its h is at least the swept one's
    (whether it is itself inside a margin, which the intrusion stop asks, is computed on it:
    :meth:`~services.safety.barriers.pairs.CollisionGeometry.measured_h`). A capsule with v = 0 is
    unchanged."""
    half = (0.5 * predict_s) * velocities
    sweep = np.linalg.norm(half, axis=2).max(axis=1)
    return endpoints + half, radii + sweep, sweep


#: States over which :class:`FrameLateness` finds the usual delay: ≈ 10 s of a 30 Hz camera, so a
#: perception restarted with another pace is learnt again within seconds.
LATENESS_WINDOW = 300
#: The most lateness counted (s): a state published later still is counted this late (the person
#: swept ahead by their velocity for a second already covers wherever they can be).
MAX_LATENESS_S = 1.0
#: A delay within this (s) of the usual one is on time (lateness 0): the stamps' own jitter, and the
#: rounding of times that differ by the same constant latency.
ON_TIME_S = 1e-3


class FrameLateness:
    """How much later than usual a state was published after its frame was taken (s).

    A state's delay d = ``stamp − capture_stamp`` (both the perception's clock, so the safety
    service may run on another host) is the pose inference and whatever else came between the
    camera and the publication; the lateness of the newest state is d minus the smallest d of the
    last :data:`LATENESS_WINDOW` states (0 below :data:`ON_TIME_S`), at most :data:`MAX_LATENESS_S`.
    A camera on time has lateness 0 (the delay it usually has is what ``safety.human_predict_s``
    and the look-ahead are set for); a frame published 80 ms late after an inference stall has
    0.08 s. A state without a ``capture_stamp``, or with a delay that is negative or not finite,
    has lateness 0 and is not counted. The same state again (stamp and capture stamp) is counted
    once."""

    def __init__(self, window: int = LATENESS_WINDOW) -> None:
        self._delays: deque[float] = deque(maxlen=window)
        self._last: tuple[float, float] | None = None

    def update(self, message: HumanState) -> float:
        """The lateness of ``message`` (s), counting its delay among the window's."""
        capture = message.capture_stamp
        if capture is None:
            return 0.0
        delay = message.stamp - capture
        if not (math.isfinite(delay) and delay >= 0.0):
            return 0.0
        if (message.stamp, capture) != self._last:
            self._delays.append(delay)
            self._last = (message.stamp, capture)
        late = delay - min(self._delays)
        return 0.0 if late < ON_TIME_S else min(late, MAX_LATENESS_S)


class HumanMemory:
    """The last valid capsule of every slot and the rule of the module doc (:meth:`update`, :meth:`capsules`)."""

    def __init__(self) -> None:
        n = len(CAPSULE_NAMES)
        self._endpoints = np.zeros((n, 2, 3))  # last valid capsule per slot
        self._radii = np.zeros(n)
        self._last_valid = np.full(n, -np.inf)  # when each slot was last valid (-inf: never)
        self._valid = np.zeros(n, bool)  # in the barrier: valid in the newest message, or lost
        self._lost = np.zeros(n, bool)  # remembered, not valid in the newest message
        self._velocities: np.ndarray | None = None  # the newest message's; zero on lost slots
        self._lateness = FrameLateness()
        #: The newest message's lateness (s, :class:`FrameLateness`): the sweep ahead grows by it.
        self.lateness = 0.0
        self._seen = SeenMotion(n)

    @property
    def seen_speed(self) -> float:
        """How fast the capsules were seen to move over the last second of frames (m/s, inf while
        unknown; :class:`~services.safety.seen_motion.SeenMotion`, by the frames' stamps,
        :func:`~services.safety.nominal.frame_stamp`: frames published together after a stall are
        still a frame period apart)."""
        return self._seen.speed

    @property
    def lost(self) -> bool:
        """Some slot is lost (held from memory): the robot must not imitate."""
        return bool(self._lost.any())

    @property
    def lost_capsules(self) -> tuple[str, ...]:
        """The names (CAPSULE_NAMES) of the lost slots."""
        return tuple(name for name, lost in zip(CAPSULE_NAMES, self._lost, strict=True) if lost)

    def update(self, message: HumanState, now: float, hold_s: float) -> None:
        """Take a fresh ``message`` received at ``now`` (s, the caller's clock); a slot invalid in it
        stays lost while it was valid at most ``hold_s`` (s) before ``now``."""
        self.lateness = self._lateness.update(message)
        seen = message.capsule_valid
        self._seen.see(frame_stamp(message), message.capsules, seen)
        self._endpoints[seen], self._radii[seen], self._last_valid[seen] = message.capsules[seen], message.capsule_radii[seen], now
        self._lost = ~seen & (now - self._last_valid <= hold_s)
        self._valid = seen | self._lost
        self._velocities = None
        if message.capsule_velocities is not None:
            self._velocities = np.where(seen[:, None, None], message.capsule_velocities, 0.0)

    def capsules(self, n_external: int, use_velocity: bool, predict_s: float = 0.0,
                 stale: bool = False) -> ExternalCapsules:
        """The barrier's external capsules after the last :meth:`update` (none yet: all slots invalid);
        ``use_velocity``: with the measured velocities of the currently valid slots; ``predict_s``
        τ > 0 (s): each slot valid in the newest message swept ahead by :func:`swept_capsules` for τ
        plus the message's :attr:`lateness` (a lost slot, whose velocity is 0, is unchanged), with
        the endpoints as measured beside (``measured``). Lost slots are ``held`` (None while none is). ``stale``: the newest message is older than
        ``safety.human_timeout_s`` (or its source is gone): the capsules as last measured, neither
        velocity nor sweep (a velocity that old says nothing of where the person is now). The
        capsules carry :attr:`seen_speed` (inf when ``stale``: how they move now is unknown)."""
        velocities = self._velocities if use_velocity and not stale else None
        held = self._lost if self.lost else None
        if predict_s > 0.0 and not stale and self._velocities is not None:
            endpoints, radii, sweep = swept_capsules(self._endpoints, self._radii, self._velocities,
                                                     predict_s + self.lateness)
            return padded(n_external, endpoints, radii, self._valid, velocities, sweep, held, self.seen_speed,
                          self._endpoints)
        return padded(n_external, self._endpoints, self._radii, self._valid, velocities, held=held,
                      moved=math.inf if stale else self.seen_speed)
