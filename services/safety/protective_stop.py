"""The safety filter's protective stops (ISO/TS 15066 speed and separation monitoring): when a step
stops imitating and aims at rest, what the person rows ask for then, and how a stop holds the
robot where it is.

:class:`~services.safety.filter.SafetyFilter` asks its :class:`ProtectiveStop` at every step
(:meth:`ProtectiveStop.decide`, :meth:`ProtectiveStop.floor_person_rows`,
:meth:`ProtectiveStop.settles`, :meth:`ProtectiveStop.stepped`). The third stop, when person rows
give way in the relaxed solve, belongs to the relaxation and is described with it in
:mod:`services.safety.filter`. Every stop only lowers soft (robot–person) rows' b, never below
the floor min(b_i, 0) the relaxation gives them anyway, so the filter's feasibility argument holds
as it is.

**Protective stop at the robot's fixed body.** A robot–person row of a robot capsule that no
joint moves (a thigh: A_i = 0) cannot be honoured by any u once it asks for a positive rate,
b_i = −γ (h_i − T a_i) + a_i > 0: the person is inside the legs' margin, or approaching it at a_i
will be within the look-ahead, i.e. h_i < a_i (T + 1/γ). Such a person is walking into a robot that
cannot get out of the way, known only as they were a camera latency earlier. Then every
robot–person row keeps only its floor, b_i ← min(b_i, 0) (never closer to any perceived capsule,
no retreat demanded), and the target is rest (u_ref = 0): the robot brakes with the motors' full
torque (below) — starting as the person approaches, so that it has stopped by the time they
arrive — and stands still until no such row fails. Retreating instead — the CBF's b_i = −γ h_i > 0, arms and
waist at their velocity bounds away from a person 60 ms old — swept other surfaces of the rotating
links into the person: on the development set's two walk-throughs 543 of 586 robot-caused contact
steps came while the person stood inside the pelvis or legs. Only soft rows change and only
downward, so the feasibility argument of :mod:`services.safety.filter` holds as it is (u = 0
satisfies a row A_i u ≥ min(b_i, 0)).

**Protective stop while a person is inside a margin** (``on_intrusion`` "stop", the default, or
"stop_on_give_way"): the same stop — every robot–person row keeps only its floor,
b_i ← min(b_i, 0), the target is rest — whenever some enabled robot–person row of the pair
barrier has h_i < −``VIOLATION_TOL``: a person capsule is inside a robot capsule's margin (φ plus
the person margin), which the rows never let the robot do, so the person moved in, faster than
the robot could leave or while the camera still showed them elsewhere. Retreating from them
(``"retreat"``: the violated rows demand A_i u ≥ −γ h_i > 0, the least total violation first)
moves the robot along normals of capsules seen a camera latency ago, at up to γ|h| (0.9 m/s at
h = −90 mm): on the test variants of the development clips (a full turn in place, a step of 1 m
toward the robot) that swung hands into true thighs at 1 m/s and leaned the torso into a true
forearm while the perceived pairs opened. The stop ends once no person row is inside (h ≥ −1 mm)
*and* the rows can be kept: a step right after a stop whose person rows give way in the relaxed
solve (the person, just outside a margin as measured, closing faster than the robot could
retreat) is the stop again, solved as ``stop_on_give_way`` solves every such step
(:meth:`~services.safety.filter.SafetyFilter._relax`: every person row at its floor, aiming at
rest, braking only), and so on while they give way; then imitation resumes under the ordinary
rows. Traced with a noisy camera (the mirrored punches beside the robot): a fist jittered out of
the margin for one frame, the stop ended, and the relaxed solve's retreat from the swept fist, the
elbow at up to 2.3 rad/s, drove the left forearm deeper into the true fist 18 mm inside it. With the person
swept ahead (``safety.human_predict_s``: each person capsule
widened by ``sweep`` to enclose where its velocity carries it) a row counts as inside only when
the capsule as measured is (:attr:`~services.safety.barriers.pairs.BarrierRows.h_measured`, its h
computed on the capsule as the camera showed it, for the rows the swept one puts inside): a person
only expected to come in is kept out by the (swept) rows, not met by a robot standing still. (The
bound h_swept + 2·sweep this test once used read a forearm measured 6 cm inside as outside while
it punched at metres per second, and the relaxed step retreated along the rows of a person a
latency old, into where they were: docs/safety-measurements.md "A stop brakes with the motors' full torque, on the
person as measured".) Like the stop above it
only lowers soft rows' b, so the feasibility argument is unchanged. Measured (docs/safety-measurements.md "The
intrusion stop"): the distance the robot closed into the true person 2.4–5× smaller in contact and
1.7–3.5× within φ, at 11–30 % more contact steps, which are the person's.

**A stop brakes with the motors' full torque.** A stop decided from the rows (either of the above)
brakes within twice the acceleration bound
(:data:`~services.safety.filter.MOTOR_WIDENING`: ``safety.accel_max`` is about half each motor's
torque, a bound kept while imitating so that the servos stay on the path the barriers were
computed for), as the relaxed step already may for a person's floor: an arm moving at 3 rad/s stops
in half the time and half the angle. The stop is there because the person is closer than the rows
allow, and they are where the camera showed them a latency ago: every millisecond of braking is
the arm moving on into where they may already be (traced on the test variants: a fist punching
across a forearm still braking from 3 rad/s, a waist braking from 0.9 rad/s over 90 ms). Where the
rows are infeasible together, so does the relaxed solve: its boxes from ×2 on (a relaxed step
that is no stop starts at ×1, and so does a stop backing out, below: braking every relaxed step
that hard left the servos trailing their command). Only the box widens, within what the motors
give; the rows and their floors are those of the step, so the feasibility argument holds as it
is. Measured (docs/safety-measurements.md "A stop brakes with the motors' full torque, on the
person as measured"): on the test variants, with the measured intrusion above, robot-caused
contact steps 192 (158 commanded) → 155 (111), on the noisy camera 51 (27) → 44 (9), at 1–15 %
more contacts (the person meeting a robot that stands still sooner).

**A stop only brakes.** In a stop decided from the rows (unless it backs out, below) every box the
step solves in, the plain QP's and each of the relaxed solve's, is narrowed per joint to the
velocities between rest and the last command, [min(u_prev, 0), max(u_prev, 0)]
(:func:`~services.safety.qp.box.braking_box`): a joint may slow down, never speed up or turn back.
Traced on the side-stepping punches: with the rows infeasible within the braking box, the relaxed
solve's least-violation stage manoeuvred, the waist rolling faster again (0.57 → 0.69 rad/s) and a
shoulder turning back, to keep the distances to capsules seen a latency ago, and swung the torso
into the true forearm at up to 160 mm/s. The narrowed box keeps its point nearest rest (the
braking point ū, and 0 in the widest box), so every relaxed box's floors and the feasibility
argument hold as they are; the stop solved when person rows give way (``stop_on_give_way``)
only brakes the same way. Measured (docs/safety-measurements.md "A stop only brakes", with the
relaxed solve from ×2 above): the 56 test variants' robot-caused steps 73 (66 commanded) → 53
(26), with the noisy camera 338 (141) → 278 (62).

**Backing out from a person who stands inside.** The intrusion stop holds the robot while a person
is inside a margin; a person who *stays* there (standing beside the robot with a hand hanging into
its forearm's margin: a broad person where a narrow one fits) would freeze it for as long as they
stand. So the stop backs out of them when

- the person stands still: their capsules seen to move slower than :data:`STILL_SPEED` (0.15 m/s:
  a standing person sways by a few cm/s, a walking one carries the torso at ≥ 0.5 m/s) over up to
  the last second (:class:`~services.safety.seen_motion.SeenMotion`: the uniform speed that would
  spread a capsule endpoint as far as those frames show, so a camera's frame-to-frame noise
  averages out while steady or back-and-forth motion counts), seen for at least 0.5 s (longer than
  a keypoint glitch or the turning point of a swing); unknown motion (a stale person, a capsule
  held from memory, one seen in under half the frames) counts as moving, and
- they are inside the margins of the robot's arms only (not the torso's, not the fixed body's).

Then each pair row whose person capsule as measured is inside (``person_inside``, as the stop
decides) keeps b_i ← min(b_i, c) instead of its floor, c = ``safety.intrusion_backout_mps``
(0.05 m/s): the arm backs out along the pair's normal at up to c,
the least motion that does so (the target is still rest), until no row is inside and imitation
resumes under the ordinary rows. A still person is where the camera showed them a latency ago, so
backing out of their capsules moves no surface toward where they really are, and every other
person row keeps at least its floor. Otherwise the stop stays as it is: backing out of a moving
person's capsules, a camera latency old, is what ``retreat`` does; a person inside the fixed body
is walking into the robot (on the test variants a person stepping slowly in was backed out of into
1,198 robot-caused contact steps); backing out of a person inside the torso's margin leans the
torso, whose mesh meets them where its capsule's closest point is not closing (the same person
stepping in: 284). The back-out rows are lowered, never raised (min(b_i, c) ≤ b_i), and their
relaxation floor stays min(b_i, 0) = 0, so the feasibility argument holds as it is. Measured
(docs/safety-measurements.md "Backing out from a person who stands inside"): a broad person
(shoulders 0.37 m) dancing beside the robot, 4,113 contact steps → 138, none robot-caused.

**The stop holds the robot where it is.** A servo tracks q_cbf with a lag: braking within the
acceleration bound leaves the joints 1–20 mrad behind the command, and once the command is at rest
they close that gap, the robot moving on into a person after the filter stopped it (traced with a
noisy camera: most robot-caused contact steps were u* = 0 with a joint still converging onto
q_cbf). A step *aims at rest* when it is a protective stop (any of the above) or a relaxed step
whose person rows gave way (stage 2 aimed at ū). q_cbf is first brought to the robot's joints
``q_robot`` (measured, extrapolated to the step by their velocity; the caller's) on the first step
of a protective stop decided from its rows, and on the first step after one that aimed at rest and
commanded it (|u*| ≤ :data:`AT_REST`: the braking is over, the lag it left is not).

**The servos only brake.** Braked with the motors' full torque, a joint still moves when its
command is at rest (a shoulder at 0.8 rad/s, the waist at 0.3 rad/s, traced on the sword
walk-through with a noisy camera); it passes the pose it was brought to, its servo (ζ ≈ 0.55 at
the shoulder pitch) pulls it back, and that return, for a few hundred milliseconds at up to 10 mm/s,
carried the robot into the person the stop was for. So after that settle, while the steps go on
aiming at rest, a joint j is brought to the robot again on every step at which its servo would
push it along the way it moves: it moves (|v_j| > :data:`STILL_JOINT_SPEED`, v_j = its
``q_robot`` change since the last step / Δt) and the command lies ahead of it,
(q_cbf,j − q_robot,j) v_j > 0 — the lag of a joint still closing on its command, or the return
after an overshoot. There the servo's spring is zeroed and its damping brakes the joint; where
the spring opposes the motion (an overshooting joint, a joint sagging away from its command under
gravity it does not compensate, a measurement drifting away) the command holds, so the spring
brakes it. Following never adds motion: it moves a joint's command only onto where the joint
already is, behind the way it is going, and so it cannot run away (a sagging joint or a drifting
measurement is never followed, whatever the time). Never while imitating (a command at rest
during imitation, a still person, settling onto a servo stuck within its friction would start a
slow cycle). Nor into the robot itself: a follow that would put the command where some
self-collision row's h is negative and lower than it is (the servo's overshoot carried an arm into
the torso's φ) is not made, so the stop keeps the robot out of itself as its rows do.

Each settle moves q_cbf by at most [u_min, u_max]·Δt per joint and keeps it within the joint
limits; the rows are evaluated there and the step runs from there, its u* still braking from
u_prev within the stop's box. The command moves to where the robot already is, so the robot does
not jump; |q_cbf⁺ − q_cbf| ≤ 2 u_max Δt on those steps (:attr:`~services.safety.filter.StepResult.settled`
says which; the service's command carries it). A missing or non-finite ``q_robot`` settles
nothing. Measured (docs/safety-measurements.md "The stop holds the robot where it is"): with a
noisy camera robot-caused contact steps 289 → 51 and approach steps 298 → 78 over three seeds with
the two settles; with the servos only braking, on the 56 test variants with a noisy camera 762 → 338
and 759 → 353. Every row is
evaluated at the settled pose, so the feasibility argument holds there as it is (a hard row the
few mrad carried past its boundary, which the self margin makes unlikely, is a violated one and
softened as such).
"""

from __future__ import annotations

import math

import numpy as np

from services.safety.barriers.kernel import any_positive
from services.safety.barriers.pairs import BarrierRows, CollisionGeometry
from services.safety.compiled import BoundKernel
from shared.config import IntrusionResponse
from shared.names import CAPSULE_NAMES

#: the ``on_intrusion`` values with the intrusion stop
STOPS = (IntrusionResponse.STOP.value, IntrusionResponse.STOP_ON_GIVE_WAY.value)
#: a barrier below −VIOLATION_TOL (m) at the start of a step counts as violated
VIOLATION_TOL = 1e-3
#: a person seen to move slower than this (m/s, :attr:`CollisionGeometry.person_speed`) stands still ("Backing out")
STILL_SPEED = 0.15
#: a command whose every |u*| is at most this (rad/s) is at rest (a protective stop's braking is over)
AT_REST = 1e-9
#: a joint that moved at most this fast (rad/s) since the step before is still ("The servos only brake"):
#: above a measurement's step-to-step noise, below the servos' settling speeds
STILL_JOINT_SPEED = 0.005


def pushed_joints(q: np.ndarray, q_robot: np.ndarray | None, last: np.ndarray | None,
                  dt: float) -> np.ndarray | None:
    """The joints whose servo would push them along their motion ("The servos only brake"): moving
    (v = (``q_robot`` − ``last``)/``dt``, the robot's joints (n,) rad at this step and the last)
    faster than :data:`STILL_JOINT_SPEED`, with the command ``q`` ahead of ``q_robot``,
    (q_j − q_robot,j) v_j > 0; as a mask, None if there is none or either pose is unknown (a NaN
    compares false)."""
    if q_robot is None or last is None or q_robot.shape != q.shape or last.shape != q.shape:
        return None
    velocity = (q_robot - last) / dt
    mask = (np.abs(velocity) > STILL_JOINT_SPEED) & ((q - q_robot) * velocity > 0.0)
    return mask if mask.any() else None


def intruded(rows: BarrierRows) -> bool:
    """Whether a person capsule is inside a robot capsule's margin: some enabled robot–person
    row of the pair barrier's ``rows`` has h < −:data:`VIOLATION_TOL` (the intrusion stop). A row
    against a capsule swept ahead (``safety.human_predict_s``) counts only when the capsule as
    measured is inside (:attr:`BarrierRows.h_measured`): a person expected to come closer is kept
    out by the rows, not met by a stop. An enabled robot–person row whose h is not finite (a
    person's numbers overflowing the distance arithmetic) counts as inside: such a row cannot
    enter the QP (``row_moves`` leaves it out), so without the stop that person capsule would
    silently have no protection at all."""
    if math.isnan(rows.min_h_all):  # NaN wins np.min: some enabled row has no distance
        return bool((rows.soft & rows.enabled & ~np.isfinite(rows.h)).any()) or bool(
            rows.person_inside(-VIOLATION_TOL).any())
    if not rows.min_h_all < -VIOLATION_TOL:  # the smallest h of all enabled rows: none is inside
        return False
    return bool(rows.person_inside(-VIOLATION_TOL).any())


class ProtectiveStop:
    """The stops of one filter: which rows they watch (fixed from the pair barrier and the robot's
    Jacobians at construction) and what they remember between steps (whether the last step aimed
    at rest, whether its settle at rest was done)."""

    def __init__(self, barrier: CollisionGeometry, jacobians: np.ndarray) -> None:
        """``barrier``: the filter's pair barrier (its rows come first in the stacked rows);
        ``jacobians`` (7, 2, 3, n): the robot capsules' endpoint Jacobians at any pose (a capsule no
        joint moves has a zero one at every pose)."""
        self._barrier = barrier
        fixed = ~jacobians.reshape(len(jacobians), -1).any(axis=1)
        row_robot = np.asarray(barrier.pairs.first)[barrier.row_pair]
        person = ~barrier.pairs.is_self[barrier.row_pair]
        #: the stacked robot–person rows of robot capsules no joint moves (zero Jacobian: a thigh),
        #: whose b > 0 starts the stop at the fixed body
        self._fixed_person_rows = np.flatnonzero(fixed[row_robot] & person)
        #: (m,) bool: the pair barrier's robot–person rows of an arm capsule (upper arm, forearm), the
        #: only ones backed out of
        self._arm_person_rows = np.array(["arm" in name for name in CAPSULE_NAMES])[row_robot] & person
        self._any_positive = BoundKernel(any_positive)
        self.reset()

    def reset(self) -> None:
        """Forget the steps before (the filter restarts)."""
        self._aimed_rest = False  # the last step aimed at rest (a protective stop, or person rows gave way)
        self._rested = False  # since the steps began to aim at rest, a settle at rest was done
        self._stopped = False  # the last step was a protective stop

    def at_fixed_body(self, b: np.ndarray) -> bool:
        """Whether a robot–person row of a capsule no joint moves asks for a positive rate (``b``
        (M,) the stacked rows' bounds; A_i = 0 there, so A_i u ≥ b_i > 0 fails whatever u is): the
        person is inside its margin or reaches it within the look-ahead."""
        return self._any_positive.call(b, self._fixed_person_rows)

    def decide(self, b: np.ndarray, rows: BarrierRows, on_intrusion: str) -> tuple[bool, bool]:
        """(whether this step is a protective stop, whether it is the one at the fixed body), from
        the stacked rows' bounds ``b`` (M,) and the pair barrier's ``rows``."""
        fixed = self.at_fixed_body(b)
        return fixed or (on_intrusion in STOPS and intruded(rows)), fixed

    def floor_person_rows(self, b: np.ndarray, soft: np.ndarray, rows: BarrierRows, backs_out: bool,
                          backout: float) -> bool:
        """A stop's rows, in place in ``b`` (M,), the stacked rows' bounds: every robot–person row
        (``soft`` (M,)) at its floor, b_i ← min(b_i, 0); if ``backs_out`` (not the stop at the
        fixed body), while the person stands still (:attr:`CollisionGeometry.person_speed` ≤
        :data:`STILL_SPEED`) and every pair row whose person capsule as
        measured is inside (:meth:`BarrierRows.person_inside`) is an arm capsule's, those rows keep
        b_i ← min(b_i, ``backout``) (m/s) instead ("Backing out from a person who stands inside").
        Returns whether they did (the step backs out)."""
        pair_b, kept = b[: self._arm_person_rows.shape[0]], None  # the pair rows come first
        if backs_out and backout > 0.0 and self._barrier.person_speed <= STILL_SPEED:
            inside = rows.person_inside(-VIOLATION_TOL)
            if not (inside & ~self._arm_person_rows).any():  # inside the torso's margin too: no back-out
                kept = np.minimum(pair_b[inside], backout)
        np.minimum(b, 0.0, out=b, where=soft)
        if kept is None:
            return False
        pair_b[inside] = kept
        return True

    def settles(self, stop: bool, u_prev: np.ndarray | None) -> bool:
        """Whether this step brings q_cbf to the robot ("The stop holds the robot where it is"):
        ``stop`` (this step is a protective stop decided from its rows) and the last step did not
        aim at rest (the stop's first step); or the last step aimed at rest and commanded it
        (``u_prev``, the last command: |u*| ≤ :data:`AT_REST`), the first such step since the steps
        began to aim at rest (marked done here; :meth:`stepped` clears the mark once a step no
        longer aims at rest)."""
        if stop and not self._aimed_rest:
            return True
        if not self._aimed_rest or self._rested or u_prev is None or float(np.abs(u_prev).max()) > AT_REST:
            return False
        self._rested = True
        return True

    @property
    def follows(self) -> bool:
        """Whether this step brings to the robot the joints its servo would push along their motion
        ("The servos only brake"): the steps aim at rest and their settle at rest was done."""
        return self._aimed_rest and self._rested

    @property
    def stopped(self) -> bool:
        """Whether the last step was a protective stop."""
        return self._stopped

    def stepped(self, aimed_rest: bool, stopped: bool) -> None:
        """Record that the step just taken aimed at rest (a protective stop, or a relaxed step whose
        person rows gave way) or did not, and whether it was a protective stop."""
        self._aimed_rest = aimed_rest
        self._stopped = stopped
        self._rested = self._rested and aimed_rest
