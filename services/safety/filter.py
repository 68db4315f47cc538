"""The CBF-QP safety filter: one control step (paper eqs. 7–9; architecture §4).

    u_ref = q̇_nom + K (q_nom − q_cbf)      (q̇_nom: the target's own velocity; none: the paper's eq. 7)
    u* = argmin ½ ‖u − u_ref‖²_W  s.t.  A(q_cbf) u ≥ b,  u_lo ≤ u ≤ u_hi
    q_cbf⁺ = q_cbf + Δt u*

A and b stack the rows of every barrier the filter holds (:mod:`services.safety.barriers`: the
pair barrier of the configured geometry, the robot description's joint barriers, any other such
as the static capsules of :mod:`~services.safety.barriers.static`), each row hard or soft.
u_lo/u_hi are the velocity bounds intersected with the joint limits reachable in one step; u* is
clipped to them whatever the solver returns, so |q_cbf⁺ − q_cbf| ≤ u_max Δt holds exactly (twice
that on the steps that first bring q_cbf to the robot, below).

**Self margin.** The hard distance rows (self pairs, static pairs: every hard row of a barrier that
:attr:`~services.safety.barriers.base.Barrier.measures_distance`) aim ε = ``self_margin`` beyond φ:
their b is −γ (h − ε) instead of −γ h. The rows are linearised once a step: a robot sliding along
a curved boundary (h ≈ 0, A_i u ≈ 0) gains ½ κ v² Δt² of depth a step that the next step's row
only corrects at the rate γ, a steady depth of ≈ κ v² Δt / (2γ) (κ the boundary's curvature, v the
sliding speed): 2 mm at 1 m/s along the thinnest robot capsule (κ = 1/0.05 m) at Δt = 2 ms and
γ = 10; the default ε = 2 mm keeps h ≥ 0 there. A row inside the margin (0 ≤ h < ε) has b > 0 and
is treated as the relaxation treats a violated one (below): it pushes out when it can, and may be
softened at cost ``relax_penalty``, never below its floor. h itself (reported, monitored) stays
measured against φ.

**Acceleration bound.** With ``accel_max`` a (rad/s²) the box is narrowed so that every joint
can still stop at its limit decelerating at a, and intersected with [u_prev − aΔt, u_prev + aΔt]
(u_prev: the previous step's u*), so the command changes speed no
faster than the motors can follow and the robot stays on the path the barriers were computed for
(a command that jumps between velocity bounds leaves the servos 0.1–0.3 rad behind, and the
barriers hold at q_cbf but not at the robot). The bound is the lowest priority: when no u within
it satisfies the rows (or their least violation), it is widened ×2, ×4, ×8, ×16 and finally
dropped, the first box that works is used, and ``accel_max`` is reported among the rows that
gave way. It is widened for a person's floor (below) only up to ×2, the motors' full torque
(:data:`MOTOR_WIDENING`): beyond, the floor brakes no harder than the robot can without turning
into its own body, and wider boxes serve the hard rows alone. Before, a person who reached the
robot's arm while it slid along its own body widened the bound until the floor held: a command
jump of 14 rad/s in one step (traced with a noisy camera on a broad person punching) that the
servos trailed by 0.19 rad, 11 mm deeper into the robot's own margin at its joints than at the
command. A protective stop decided from the rows brakes within the bound ×2 (the motors' full
torque), its relaxed solve too (its boxes from ×2 on), and only brakes: each joint's velocity
stays between rest and u_prev (:mod:`services.safety.protective_stop`; a relaxed step that is no
stop, or a stop backing out of a still person, tries the boxes from ×1). ``ddq`` = (u* − u_prev)/Δt is the command's
acceleration (the executor's inertial feed-forward). After :meth:`SafetyFilter.reset` there is no
u_prev and no bound for one step.

**Prioritised relaxation.** When the rows are infeasible together (a person moving into the robot
faster than it can retreat), every row i gets a slack σ_i ∈ [0, max(b_i, 0)] (A_i u + σ_i ≥ b_i,
so A_i u ≥ min(b_i, 0): a soft robot–person row may give way but the robot never closes in on
that capsule; a hard row whose b_i ≤ 0 keeps σ_i = 0 and stays exactly as it was), and two QPs
are solved in order (a lexicographic solve, :mod:`services.safety.relaxation`). Inside an
acceleration bound (below) a robot moving toward a person may be unable to stop within one step:
there a soft row's floor is the hardest braking the box allows, A_i u ≥ min(b_i, 0, A_i ū) with ū
the box's point nearest rest (0 when the box holds 0): the robot closes in no faster than braking
as hard as the bound lets it, the most a real robot can do (commanding more only leaves its servos
behind). Where no u within the bound ×2 keeps the hard rows with those floors (braking every joint
at once would turn an arm sliding along its own body into it), ū is the nearest point to rest of
the ×2 box (then of each wider one) that keeps the hard rows that hold
(:meth:`~services.safety.relaxation.LexicographicSolver.braking`). An already violated
hard row (b_i > 0) gets the same floor: a self pair that sampling has carried a hair past its
boundary (h ≈ −0.03 mm after a long slide along it) would otherwise demand A_i u ≥ 0 at once, no
acceleration-bounded box could give it while the arm still moves along, and the bound would be
widened up to ×16: a command jump the servos trail by ≈ 0.01 rad, millimetres deeper at the
robot than the hair at q_cbf:

1. least violation: min Σ c_i σ_i (+ ½ε‖u − u_ref‖²_W + ½ε‖σ‖² to make it strictly convex),
   c_i = 1 for a soft row and ``relax_penalty`` for a hard row that is already violated;
2. best tracking among the least-violating: min ½‖u − u_ref‖²_W (+ ½ε‖σ‖²) with σ_i ≤ σ_i* of
   stage 1 (plus a solver tolerance): stage 1's solution is feasible here, so its total
   violation cannot grow. **Protective stop while a person row gives way**: when a soft
   (robot–person) row gives way in stage 1 (σ_i* > 0: the person moves into the robot faster than
   it can retreat), stage 2 aims at ū, the box's point nearest rest, instead of u_ref: the robot
   does not go on imitating; it retreats as far as stage 1 requires. This is ISO/TS 15066 speed
   and separation monitoring: once the separation cannot be kept, the robot initiates a
   protective stop instead of continuing its task. Why: the imitation target is then typically
   radians away (the person blocks it), so u_ref asks for the velocity bounds, and the freedom the
   rows leave (directions tangential to the perceived capsules, the other arm) swept the robot's
   links at full speed past a person known only as they were a camera latency earlier (docs/safety-measurements.md
   "How the evaluator found its way to no robot-caused step on the development set"). With ``on_intrusion =
   "stop_on_give_way"`` (opt-in) it does not retreat either: both stages are solved again with
   every robot–person row at its floor, b_i ← min(b_i, 0), aiming at ū, so the robot brakes to
   rest within the acceleration bound and closes on no perceived capsule (the slacks reported are
   the first solve's, the person rows that could not be honoured). With the default ``"stop"``
   the same holds on a step right after a protective stop: a stop goes on while person rows give
   way (:mod:`services.safety.protective_stop`, "Protective stop while a person is inside a
   margin"). A retreat the rows cannot fully
   give is a fast motion along normals of capsules seen a camera latency ago that moves the
   robot's other surfaces with it; a robot that never retreats is instead walked and swung into,
   and with a noisy camera its servos creep into the person, so it is not the default (measured:
   docs/safety-measurements.md "The intrusion stop"). Only stage 2's objective changes, so the feasibility argument
   below is unchanged.

**Protective stops** (:mod:`services.safety.protective_stop`, ISO/TS 15066 speed and separation
monitoring): a step aims at rest (u_ref = 0) and every robot–person row keeps only its floor,
b_i ← min(b_i, 0), while a person is inside the margin of a robot capsule no joint moves (or will
be within the look-ahead) or, with ``on_intrusion`` "stop" (the default), inside any robot
capsule's margin; a person who has stood still inside the arms' margins only is backed out of
(b_i ← min(b_i, ``intrusion_backout_mps``)). On a stop's first step and once its command is at
rest, q_cbf is first brought to the robot's measured joints ``q_robot``, and after that, while the
steps aim at rest, each joint its servo would push along its motion (at most [u_min, u_max]·Δt per
joint, within the joint limits; :attr:`StepResult.settled`), so the servos neither close their
tracking lag into the person nor pull an overshooting joint back into them: they only brake. The
rows are evaluated there. Stops only lower soft rows' b, so the
argument below holds as it is.

**Speed and separation** (:mod:`services.safety.separation`, ``human_speed_mps``): outside a stop, near a
person u_ref is clipped per joint to a speed that joint can brake from (at ``accel_max``) before a person
approaching at v_h arrives. Only u_ref (and the QP's linear term) changes, so the argument below holds as it is.

*Feasible by construction.* u = 0, σ_i = max(b_i, 0) satisfies every constraint of both stages
whenever 0 lies in the box, which holds in the last box tried (the velocity box alone, the
acceleration bound dropped; ū = 0 there) because q_cbf stays within the joint limits and
u_min ≤ 0 < u_max: row i reads 0 + max(b_i, 0) ≥ b_i, and σ_i's bounds contain max(b_i, 0).
In an acceleration-bounded box u = ū satisfies every soft and every violated row by the choice of
its floor, and with ū keeping the hard rows that hold every row, so such a box is infeasible only
when no u in it keeps the hard rows that hold (then the next, wider one is tried).
In particular the hard rows (self pairs, joint barriers) whose b_i ≤ 0 at the step's start
(they hold: h ≥ 0 ⇔ b = −γ h ≤ 0) are never relaxed; a violated one (b_i > 0, which the hard
rows prevent from happening) is softened the same way at cost ``relax_penalty``.

Both stages are solved by DAQP whatever ``safety.backend`` is (why:
:mod:`services.safety.relaxation`, whose docstring states the floors and the stages exactly). If both
stages fail numerically the filter holds (u* = 0, mode HOLD: q_cbf does not move, no jump);
if only stage 2 fails, stage 1's u is commanded. The mode says which happened; the output is
always finite. A state already inside a barrier (h < −1 mm) is reported as RELAXED too.

With ``enforce`` off the rows are still evaluated (h is monitored) but left out of the QP, so
u* = clip(u_ref) within the bounds: the same integrator without the safety layer (the offline
evaluator's no-CBF run).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import numpy as np

from services.safety.barriers.base import Barrier, RowBlock
from services.safety.barriers.joints import BRAKE_SHARE, JointBarrier
from services.safety.barriers.kernel import movable_mask
from services.safety.compiled import BoundKernel
from services.safety.barriers.pairs import BarrierRows, CollisionGeometry
from services.safety.qp import QPBackend, QPProblem, QPStatus, make_backend
from services.safety.qp.base import INF_BOUND
from services.safety.qp.box import (
    HIGH, LOW, LOWER, U_MAX, U_MIN, UPPER, bounded_box, braking_box, integrate, limits_table, prepare_qp, reach_box,
    velocity_box,
)
from services.safety.relaxation import RELAXED_TOL, LexicographicSolver
from services.safety.protective_stop import VIOLATION_TOL, ProtectiveStop, pushed_joints
from services.safety.separation import cap_reference
from services.safety.standoff import apply_standoff
from shared.config import IntrusionResponse
from shared.messages import SafetyMode

#: the ``FilterParams.on_intrusion`` value that also stops when person rows give way (module docstring)
_STOP_ON_GIVE_WAY = IntrusionResponse.STOP_ON_GIVE_WAY.value
#: the default: a stop also goes on while person rows give way (module docstring)
_STOP = IntrusionResponse.STOP.value
#: a row whose largest |A_ij| is below this does not depend on u (a static link's pair)
_STATIC_ROW = 1e-12
#: the acceleration bound's factors, tried in order when no u within it satisfies the rows
ACCEL_WIDENING = (1.0, 2.0, 4.0, 8.0, 16.0)
#: the name :attr:`StepResult.gave_way` gives the acceleration bound when it was widened or dropped
ACCEL_BOUND = "accel_max"
#: the widest acceleration bound (a factor of :data:`ACCEL_WIDENING`) a person's floor may widen it to:
#: ``safety.accel_max`` is about half each motor's torque, so ×2 is all of it (module docstring)
MOTOR_WIDENING = 2.0


def movable_rows(A: np.ndarray) -> np.ndarray:
    """(m,) bool: the rows of A (m, n) some velocity can change; the others (a pair of a static link
    such as a locked thigh, a disabled row) hold or fail whatever u is and stay out of the QP."""
    out = np.empty(A.shape[0], bool)
    movable_mask(A, _STATIC_ROW, out)
    return out


def binding_rows(rows: BarrierRows, u: np.ndarray) -> np.ndarray:
    """(m,) bool: the pair rows that bind at ``u`` (n,): enabled, in the QP (:func:`movable_rows`) and
    at their bound, A_i u − b_i ≤ the QP's active tolerance (a row given way is below it)."""
    return rows.enabled & movable_rows(rows.A) & (rows.A @ u - rows.b <= QPBackend.active_tol)


@dataclass(frozen=True)
class FilterParams:
    """The tunable parameters of one step (subset of shared.config.SafetyConfig); frozen: a change
    replaces them (``dataclasses.replace``), which the filter's per-joint constants follow."""

    gamma: float
    phi: float
    gain: float
    weights: np.ndarray
    u_max: np.ndarray
    relax_penalty: float  # stage-1 cost of an already-violated hard row's slack (a soft row's: 1)
    u_min: np.ndarray | None = None  # lower velocity bound (n,); None: −u_max
    human_lookahead_s: float = 0.0  # T of the human velocity term (s; see barrier.py)
    accel_max: np.ndarray | None = None  # |u − u_prev|/Δt bound (n,) rad/s²; None: none
    self_margin: float = 0.0  # m the hard distance rows aim beyond φ (module docstring)
    on_intrusion: str = "stop"  # "stop" | "retreat" | "stop_on_give_way" (module docstring)
    intrusion_backout_mps: float = 0.0  # m/s an arm backs out of a still person in a stop (services.safety.protective_stop)
    human_standoff_m: float = 0.0  # m within which the robot closes on no person capsule (services.safety.standoff)
    human_speed_mps: float = 0.0  # m/s of a person the tracking can stop for (services.safety.separation); 0: off

    def __post_init__(self) -> None:
        """Scalars as float, arrays as contiguous float64 (the compiled step's bound argument types)."""
        for name in ("gamma", "phi", "gain", "relax_penalty", "human_lookahead_s", "self_margin",
                     "intrusion_backout_mps", "human_standoff_m", "human_speed_mps"):
            object.__setattr__(self, name, float(getattr(self, name)))
        for name in ("weights", "u_max", "u_min", "accel_max"):
            value = getattr(self, name)
            if value is not None:
                object.__setattr__(self, name, np.ascontiguousarray(value, dtype=np.float64))

    @classmethod
    def from_config(cls, safety) -> FilterParams:  # shared.config.SafetyConfig
        return cls(
            gamma=safety.gamma,
            phi=safety.phi,
            gain=safety.gain,
            weights=np.asarray(safety.weights, dtype=np.float64),
            u_max=np.asarray(safety.u_max, dtype=np.float64),
            relax_penalty=safety.relax_penalty,
            u_min=None if safety.u_min is None else np.asarray(safety.u_min, dtype=np.float64),
            human_lookahead_s=safety.human_lookahead_s,
            accel_max=None if safety.accel_max is None else np.asarray(safety.accel_max, dtype=np.float64),
            self_margin=safety.self_margin,
            on_intrusion=IntrusionResponse(safety.on_intrusion).value,
            intrusion_backout_mps=safety.intrusion_backout_mps,
            human_standoff_m=safety.human_standoff_m,
            human_speed_mps=safety.human_speed_mps,
        )


@dataclass
class StepResult:
    """Outcome of one step: the new q_cbf (n,), u* (n,), mode, the pair barrier's rows and solver
    facts; ``relaxed`` (m,) the pair rows that gave way (their slack > 0; all False unless RELAXED,
    then a shared read-only array);
    ``intrusion``: a person capsule, as measured, is inside the margin (h < 0 on a soft pair row;
    :attr:`BarrierRows.h_measured` < 0 where the person is swept ahead) while the robot retreats from
    or holds against it (A_i u* ≥ 0); ``gave_way`` the names of every row of
    any barrier that gave way (:meth:`Barrier.row_names`, each once); ``min_h_self`` (m) the
    smallest h over the self-collision distance rows of every barrier (pair and static; None: none);
    ``ddq`` (n,) rad/s² the command's acceleration (u* − u_prev)/Δt (zero after a reset);
    ``protective_stop``: a person row of a capsule no joint moves asked for a positive rate (the
    person inside its margin or reaching it within the look-ahead), or with ``on_intrusion``
    "stop" a person capsule is inside any robot capsule's margin (with "stop_on_give_way" also: a
    person row gave way), so the step aimed at rest (``u_ref`` 0) and no person row asked for more
    than holding its distance or backing out of a still person; ``settled``: q_cbf was first
    brought to the robot's joints this step, so |q_cbf − the previous q_cbf| ≤ 2 u_max Δt instead
    of u_max Δt (both: :mod:`services.safety.protective_stop`); ``backing_out``: the stop backed out
    of a person who stands still inside the arms' margins (some arm's person rows kept b_i ←
    min(b_i, ``intrusion_backout_mps``) instead of 0); ``speed_capped``: the speed and separation cap
    slowed u_ref on some joint (:mod:`services.safety.separation`)."""

    q_cbf: np.ndarray
    u: np.ndarray
    u_ref: np.ndarray
    mode: SafetyMode
    rows: BarrierRows
    active_rows: int
    qp_time_s: float
    qp_status: QPStatus
    relaxed: np.ndarray
    intrusion: bool = False
    protective_stop: bool = False
    gave_way: tuple[str, ...] = ()
    min_h_self: float | None = None
    ddq: np.ndarray | None = None
    settled: bool = False
    backing_out: bool = False
    speed_capped: bool = False


class SafetyFilter:
    """Holds q_cbf and filters nominal targets through the CBF-QP of its barriers.

    ``barrier`` is the pair barrier (its rows are reported in :class:`StepResult`); the robot
    description's joint barriers are added after it, then ``extra`` (e.g. the static capsules);
    ``barriers`` lists everything stacked.
    """

    def __init__(self, kinematics, barrier: CollisionGeometry, params: FilterParams, backend: str = "daqp",
                 extra: Sequence[Barrier] = ()) -> None:
        self.kinematics = kinematics
        #: Whether the CBF rows constrain the QP (False: rows only monitored, u* = clip(u_ref)).
        self.enforce = True
        self.barrier = barrier
        self.barriers: list[Barrier] = [
            barrier, JointBarrier(kinematics.spec.joint_barriers, kinematics.joint_names), *extra,
        ]
        #: The name of every stacked row, in stacking order (fixed for a pair set).
        self.row_names: tuple[str, ...] = tuple(name for b in self.barriers for name in b.row_names())
        self._starts: list[tuple[Barrier, int]] = []  # every barrier and its first stacked row
        start = 0
        for b in self.barriers:
            self._starts.append((b, start))
            start += len(b.row_names())
        n, self._m_all = len(kinematics.joint_names), start
        # buffers of one step (every result gets fresh arrays): the stacked priorities, the QP's rows
        # (the movable ones) and their stacked indices, the QP in DAQP's layout (prepare_qp's ``stacked``; the rows' upper
        # bounds infinite) and its views for k rows (:meth:`_qp_views`)
        self._soft_all = np.empty(start, bool)
        self._A_qp = np.empty((start, n))
        self._kept = np.empty(start, np.intp)
        self._stacked = np.empty((3, n + start))
        self._stacked[2, n:] = INF_BOUND
        self._views: dict[int, tuple] = {}
        self._caps = np.empty(n)  # the speed and separation caps of a step (services.safety.separation)
        self._prepare, self._integrate = BoundKernel(prepare_qp), BoundKernel(integrate)
        # StepResult.relaxed of a step whose QP was feasible: no pair row gave way (shared, read-only)
        self._none_relaxed = np.zeros(barrier.n_rows, bool)
        self._none_relaxed.flags.writeable = False
        self.q_min = np.asarray(kinematics.q_min, dtype=np.float64)
        self.q_max = np.asarray(kinematics.q_max, dtype=np.float64)
        self.q_cbf = np.clip(np.asarray(kinematics.q_home, dtype=np.float64), self.q_min, self.q_max)
        self._params = params  # blocks_at reads them; the setter below derives the rest
        #: (M,) bool: the stacked hard distance rows (self and static pairs), which aim self_margin beyond φ
        self._self_rows = np.concatenate([
            ~block.soft.astype(bool) if barrier.measures_distance else np.zeros(block.b.shape[0], bool)
            for barrier, block in zip(self.barriers, self.blocks_at(self.q_cbf))])
        #: the protective stops (:mod:`services.safety.protective_stop`)
        self.stops = ProtectiveStop(barrier, self.kinematics.compute(self.q_cbf)[1])
        self._rest = np.zeros(len(kinematics.joint_names))
        self.params = params
        self.backend_name = backend
        self._qp: QPBackend = make_backend(backend)
        self._relaxation = LexicographicSolver()  # DAQP whatever the backend (services.safety.relaxation)
        self._u_prev: np.ndarray | None = None  # the last step's u* (None: no acceleration bound this step)
        self._q_robot_prev: np.ndarray | None = None  # the last step's q_robot (None: unknown)

    @property
    def params(self) -> FilterParams:
        """The step's parameters (frozen; their arrays are never written): setting them rebuilds the
        per-joint table of :func:`~services.safety.qp.box.prepare_qp` (its constants and the boxes it
        writes) and the self margin's shift of b."""
        return self._params

    @params.setter
    def params(self, params: FilterParams) -> None:
        self._params = params
        self._limits = limits = limits_table(self.q_min, self.q_max, params.u_min, params.u_max, params.accel_max,
                                             params.weights)
        #: the box a step uses, views of the table's box rows: [not bounded] (LOWER, UPPER), [bounded] (LOW, HIGH)
        self._box_views = ((limits[LOWER], limits[UPPER]), (limits[LOW], limits[HIGH]))
        #: (M,) γ ε on the stacked hard distance rows, 0 elsewhere: their b shift (module docstring)
        self._shift = self._self_rows * (params.gamma * params.self_margin)

    def _qp_views(self, k: int) -> tuple[np.ndarray, np.ndarray, tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """(A, b, (f, bounds lower, bounds upper)) of the QP with k rows: views of the buffers
        :func:`~services.safety.qp.box.prepare_qp` writes (made once per k)."""
        views = self._views.get(k)
        if views is None:
            n, stacked = self._limits.shape[1], self._stacked
            views = self._views[k] = (self._A_qp[:k], stacked[1, n:n + k],
                                      (stacked[0, :n], stacked[1, :n + k], stacked[2, :n + k]))
        return views

    def reset(self, q: np.ndarray) -> None:
        """Restart integration from configuration ``q`` (e.g. the measured joint state)."""
        q = np.asarray(q, dtype=np.float64)
        if q.shape == self.q_cbf.shape and np.isfinite(q).all():
            self.q_cbf = np.clip(q, self.q_min, self.q_max)
            self._u_prev = self._q_robot_prev = None
            self.stops.reset()

    def blocks_at(self, q: np.ndarray) -> list[RowBlock]:
        """Every barrier's rows at configuration ``q`` (no QP, no state change); the pair rows first."""
        endpoints, jacobians = self.kinematics.compute(q)
        p = self.params
        return [b.constraint_rows(q, endpoints, jacobians, p.gamma, p.phi, p.human_lookahead_s, p.accel_max)
                for b in self.barriers]

    def rows_at(self, q: np.ndarray) -> BarrierRows:
        """The pair barrier's rows at configuration ``q`` (no QP, no state change)."""
        endpoints, jacobians = self.kinematics.compute(q)
        p = self.params
        return self.barrier.evaluate(endpoints, jacobians, p.gamma, p.phi, p.human_lookahead_s)

    def _write_rows(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, float, float, BarrierRows]:
        """Every barrier's rows at ``q`` written into fresh stacked arrays (and ``soft_all``): (A (M, n),
        b (M,), the smallest h over the distance rows, over the self-collision ones (m; inf:
        none), the pair barrier's rows). The hard distance rows aim ``self_margin`` beyond φ (module
        docstring): their b shift is added to the stacked b by prepare_qp in :meth:`step` and here to the
        reported pair rows unless they view the stacked b (a barrier that stacked copies:
        :meth:`Barrier.write_rows`' default)."""
        p = self.params
        endpoints, jacobians = self.kinematics.compute(q)
        m_all, n = self._m_all, q.shape[0]
        A_all, b_all, h_all = np.empty((m_all, n)), np.empty(m_all), np.empty(m_all)
        gamma, phi, lookahead, accel = p.gamma, p.phi, p.human_lookahead_s, p.accel_max
        inside = low_self = math.inf
        for barrier, start in self._starts:
            low, low_own = barrier.write_rows(q, endpoints, jacobians, gamma, phi, lookahead, accel, start, A_all, b_all,
                                              self._soft_all, h_all)
            if low < inside:  # min(inside, low) without the call (a NaN never replaces a value, as in min)
                inside = low
            if low_own < low_self:
                low_self = low_own
        apply_standoff(b_all, h_all, self._soft_all, gamma, p.human_standoff_m)
        rows: BarrierRows = self.barrier.last_rows  # type: ignore[assignment]
        if p.self_margin > 0.0 and rows.b.base is not b_all:
            rows.b += self._shift[: rows.b.shape[0]]
        return A_all, b_all, inside, low_self, rows

    def _settle_pose(self, q: np.ndarray, q_robot: np.ndarray, dt: float,
                     joints: np.ndarray | None = None) -> np.ndarray | None:
        """q_cbf brought to the robot on a settling step (:meth:`ProtectiveStop.settles`; only the
        ``joints`` mask, when given: :attr:`ProtectiveStop.follows`): ``q_robot`` (n,) clipped to
        q ± [u_min, u_max]·Δt and to the joint limits; None when ``q_robot`` is not a finite (n,)
        array (the stop then holds q_cbf)."""
        q_robot = np.asarray(q_robot, dtype=np.float64)
        if q_robot.shape != q.shape or not np.isfinite(q_robot).all():
            return None
        limits = self._limits  # its velocity rows: u_min (None: −u_max) and u_max
        settled = np.clip(np.clip(q_robot, q + limits[U_MIN] * dt, q + limits[U_MAX] * dt), self.q_min, self.q_max)
        return settled if joints is None else np.where(joints, settled, q)

    def step(self, q_nom: np.ndarray, dt: float, dq_nom: np.ndarray | None = None,
             q_robot: np.ndarray | None = None) -> StepResult:
        """One control step towards ``q_nom`` (n,) over ``dt`` seconds; ``dq_nom`` (n,) rad/s, the
        target's velocity, is fed forward (u_ref = dq_nom + K (q_nom − q_cbf); None: K only).
        ``q_robot`` (n,) rad: the robot's joints at this step (measured, extrapolated to now; None:
        unknown), to which q_cbf is brought as a protective stop begins and once a command aiming
        at rest is at rest, and after that joint by joint where the servo would push the joint
        along its motion (:mod:`services.safety.protective_stop`).

        Every barrier writes its rows into the stacked A, b, soft, h (:meth:`Barrier.write_rows`);
        u_ref, the first velocity box and the rows a velocity can move, in the QP solver's layout, come
        from one compiled call (:func:`~services.safety.qp.box.prepare_qp`) and the clip, integration
        and ddq from another: the feasible step allocates only what it returns."""
        p = self.params
        q = self.q_cbf
        n = q.shape[0]
        A_all, b_all, inside, low_self, rows = self._write_rows(q)
        soft_all, accel, shift, shifted = self._soft_all, p.accel_max, self._shift, p.self_margin > 0.0
        stop, fixed_stop = self.stops.decide(b_all, rows, p.on_intrusion) if self.enforce else (False, False)
        settled, backing_out = None, False
        last, self._q_robot_prev = self._q_robot_prev, None if q_robot is None else np.array(q_robot, dtype=np.float64)
        if self.stops.settles(stop, self._u_prev) and q_robot is not None:  # q_cbf brought to the robot
            settled = self._settle_pose(q, q_robot, dt)
            if settled is not None:
                q = self.q_cbf = settled
                A_all, b_all, inside, low_self, rows = self._write_rows(q)
        elif self.stops.follows and (joints := pushed_joints(q, self._q_robot_prev, last, dt)) is not None:
            followed = self._settle_pose(q, q_robot, dt, joints)  # the servos only brake ...
            written = None if followed is None else self._write_rows(followed)
            if written is not None and written[3] >= min(low_self, 0.0):  # ... never into a self row
                settled = q = self.q_cbf = followed
                A_all, b_all, inside, low_self, rows = written
            elif written is not None:
                A_all, b_all, inside, low_self, rows = self._write_rows(q)
        if stop:  # the protective stop (services.safety.protective_stop): rest is the target, person rows their floor
            q_nom, dq_nom = q, self._rest
            backing_out = self.stops.floor_person_rows(b_all, soft_all, rows, not fixed_stop, p.intrusion_backout_mps)
        q_nom = np.ascontiguousarray(q_nom, dtype=np.float64)  # the bound kernel's types (BoundKernel)
        dq_nom = q_nom if dq_nom is None else np.ascontiguousarray(dq_nom, dtype=np.float64)
        if q_nom.shape != q.shape or dq_nom.shape != q.shape:
            raise ValueError(f"q_nom and dq_nom must have shape {q.shape}")
        u_ref, u_prev = np.empty(n), self._u_prev
        bounded = accel is not None and u_prev is not None
        dt = float(dt)
        # With enforce, rows no velocity can change (a pair of a static link such as a locked thigh, a
        # missing capsule's disabled row) hold or fail whatever u is: they are left out of the QP,
        # where a failing one would only make it infeasible (a person touching a static link is an
        # intrusion, reported below, not a row the robot could honour).
        k, honours = self._prepare.call(q_nom, dq_nom, dq_nom is not q_nom, p.gain, q, self._limits, BRAKE_SHARE,
                                        u_prev if bounded else q, bounded, dt, u_ref, A_all, b_all,
                                        shift, shifted, _STATIC_ROW, bool(self.enforce), self._A_qp, self._kept,
                                        self._stacked)
        lower, upper = self._box_views[bounded]
        A, b, stacked = self._qp_views(k)
        capped = 0
        if p.human_speed_mps > 0.0 and accel is not None and not stop and self.enforce:
            # near a person, no tracking speed the joint could not stop from in time (module docstring)
            capped = cap_reference(rows.A, rows.h, rows.soft, rows.enabled, accel, p.human_speed_mps, p.weights,
                                   u_ref, stacked[0], self._caps)
        braking = u_prev if stop and bounded and not backing_out else None  # a stop only brakes (module docstring)
        if stop and bounded:  # a protective stop brakes with the motors' full torque (module docstring)
            lower, upper, honours = reach_box(u_prev, accel, MOTOR_WIDENING, dt, self._limits[LOWER],
                                              self._limits[UPPER])
            if braking is not None:
                lower, upper = braking_box(lower, upper, braking)
            stacked[1][:n], stacked[2][:n] = lower, upper
        problem = QPProblem(p.weights, u_ref, A, b, lower, upper, stacked)
        solution = self._qp.solve(problem)
        qp_time = solution.solve_time_s
        u = solution.u
        relaxed = self._none_relaxed
        gave_rest = False
        gave_way: tuple[str, ...] = ()
        if u is not None:
            active = solution.active_rows
            mode = SafetyMode.ACTIVE if active else SafetyMode.NOMINAL
            if self.enforce and inside < -VIOLATION_TOL:
                mode = SafetyMode.RELAXED
        else:
            u, mode, active, relaxed, gave_way, seconds, lower, upper, honours, gave_stop = self._relaxed_step(
                problem, q, dt, soft_all[self._kept[: b.shape[0]]], self._kept[: b.shape[0]], rows.b.shape[0], braking,
                in_stop=stop)
            qp_time += seconds
            gave_rest = bool((relaxed & soft_all[: relaxed.shape[0]]).any())  # stage 2 aimed at rest
            if gave_stop:  # the protective stop when person rows give way (module docstring): it tracked rest
                stop, u_ref = True, np.zeros(n)
        if not honours:
            gave_way += (ACCEL_BOUND,)
        # u within [lower, upper] (an iterative solver's tolerance never exceeds u_max), q + Δt u within
        # the limits, a copy of it and ddq: the rows of one fresh array (the solver's u as the kernel's type)
        u, out = np.ascontiguousarray(u, dtype=np.float64), np.empty((4, n))
        if self._integrate.call(u, lower, upper, q, dt, self._limits, u if u_prev is None else u_prev,
                              u_prev is not None, out):
            u, q_next, q_result, ddq = out[0], out[1], out[2], out[3]  # (indexing: half an iteration's cost)
        else:  # not finite
            u, q_next, mode = np.zeros(n), q.copy(), SafetyMode.HOLD
            q_result = q_next.copy()
            ddq = np.zeros(n) if u_prev is None else (u - u_prev) / dt
        self.q_cbf = q_next
        self._u_prev = u
        self.stops.stepped(stop or gave_rest, stop)  # the steps aiming at rest (services.safety.protective_stop)
        intrusion = False
        if self.enforce and rows.min_h_all < 0.0:  # min over enabled rows: no row inside its margin, no intrusion
            person = rows.person_inside(0.0)
            intrusion = bool(person.any() and (rows.A[person] @ u >= -RELAXED_TOL).all())
        return StepResult(q_result, u, u_ref, mode, rows, active, qp_time, solution.status, relaxed, intrusion,
                          stop, gave_way, None if low_self == math.inf else low_self, ddq, settled is not None,
                          backing_out, capped > 0)

    def _relaxed_step(self, problem: QPProblem, q: np.ndarray, dt: float, soft: np.ndarray, kept: np.ndarray,
                      n_pair: int, braking: np.ndarray | None = None, in_stop: bool = False) -> tuple:
        """The step when the plain QP has no solution: the relaxed solve (:meth:`_relax`) in every box
        of :meth:`_relaxed_boxes` in turn until one works (``braking``: a protective stop's u_prev,
        as there; ``in_stop``: the step is a protective stop decided from its rows). Returns (u,
        mode, active rows, the pair rows that gave way (``n_pair``,), the names of every row that
        gave way, QP seconds, the box used (lower, upper), whether it honours the acceleration
        bound, whether it was the protective stop of :meth:`_relax`); u None and mode HOLD when no
        box works.
        ``soft`` and ``kept`` (their indices among all the stacked rows) of ``problem``'s rows."""
        A, b = problem.A, problem.b
        margin = self._shift[kept]  # each row's b shift
        seconds = 0.0
        for lower, upper, honours, keep_hard in self._relaxed_boxes(q, dt, braking):
            problem = QPProblem(w=problem.w, u_ref=problem.u_ref, A=A, b=b, lower=lower, upper=upper)
            u, slack, spent, stopped = self._relax(problem, soft, margin, keep_hard, in_stop)
            seconds += spent
            if u is not None:
                gave = np.zeros(len(self.row_names), bool)
                gave[kept] = slack > RELAXED_TOL + margin  # within the self margin is no giving way
                names = tuple(dict.fromkeys(self.row_names[i] for i in np.flatnonzero(gave)))
                active = int(np.count_nonzero(A @ u - b <= 1e-6))
                return u, SafetyMode.RELAXED, active, gave[:n_pair], names, seconds, lower, upper, honours, stopped
        return (np.zeros(problem.n), SafetyMode.HOLD, 0, np.zeros(n_pair, bool), (), seconds, lower, upper, honours,
                False)

    def compile_boxes(self, dt: float) -> None:
        """Compute every velocity box the step may try (:meth:`_boxes`) once, so that numba compiles
        the kernels of the widened boxes now: a step asks for them only when its QP is infeasible,
        and a control tick would otherwise pay their compilation the first time a person walks in.
        No state changes."""
        u_prev = self._u_prev
        self._u_prev = np.zeros_like(self.q_cbf) if u_prev is None else u_prev
        try:
            for _ in self._boxes(self.q_cbf, dt):
                pass
        finally:
            self._u_prev = u_prev

    def _relaxed_boxes(self, q: np.ndarray, dt: float,
                       braking: np.ndarray | None = None) -> Iterator[tuple[np.ndarray, np.ndarray, bool, bool]]:
        """The boxes the relaxed step tries, each (lower, upper, honours the acceleration bound,
        ``keep_hard``: the braking point keeps the hard rows, :meth:`LexicographicSolver.solve`): the
        boxes of :meth:`_boxes` up to the bound ×:data:`MOTOR_WIDENING` braking at their point
        nearest rest (the person's floors as hard as the motors can), then that box again and every
        wider one braking at the nearest point to rest that keeps the hard rows (module docstring).
        Without a bound, :meth:`_boxes` gives the velocity box alone, paired here with the first
        factor: its point nearest rest, 0, keeps every hard row that holds, so it is the same ū.
        ``braking`` (u_prev of a protective stop decided from the rows, in an acceleration bound,
        unless it backs out): the boxes from the motors' full torque (×:data:`MOTOR_WIDENING`, the
        stop's own bound, honoured there) on, each narrowed to braking from u_prev
        (:func:`~services.safety.qp.box.braking_box`: the same points nearest rest)."""
        widest_honoured = 1.0 if braking is None else MOTOR_WIDENING
        for factor, (lower, upper, within) in zip((*ACCEL_WIDENING, math.inf), self._boxes(q, dt)):
            honours = within and factor <= widest_honoured
            if braking is not None:  # a stop brakes with the motors' full torque, and only brakes
                if factor < MOTOR_WIDENING:
                    continue
                lower, upper = braking_box(lower, upper, braking)
            if factor <= MOTOR_WIDENING:
                yield lower, upper, honours, False
            if factor >= MOTOR_WIDENING:
                yield lower, upper, honours, True

    def _boxes(self, q: np.ndarray, dt: float) -> Iterator[tuple[np.ndarray, np.ndarray, bool]]:
        """The velocity boxes to try in order, each (lower, upper, within: the box is the bound's
        reach ×f, not clipped wholly beyond the velocity box; the first one's is whether it honours
        the acceleration bound), computed when asked for (the first suffices unless the QP is infeasible).

        Without a bound (none configured, or the first step after a reset): the velocity box
        (:func:`~services.safety.qp.box.velocity_box`) alone. With one (a, rad/s²): the velocity box
        narrowed so that a joint can still stop at its limit decelerating at a' = β a (β =
        BRAKE_SHARE; d the distance left: |u| ≤ √(2a'd + (a'Δt/2)²) − a'Δt/2, the speed from which
        steps of a'Δt brake to rest within d; 0 stays inside), then intersected with
        [u_prev − f aΔt, u_prev + f aΔt] for f in :data:`ACCEL_WIDENING`, then that narrowed box alone. A bound clipped into the box is non-empty but no longer honoured where
        the box lies wholly beyond it (a velocity bound lowered at run time)."""
        p, u_prev = self.params, self._u_prev
        a = p.accel_max
        if a is None or u_prev is None:
            yield (*velocity_box(q, self.q_min, self.q_max, p.u_min, p.u_max, dt), True)
            return
        lower, upper, low, high, within = bounded_box(q, self.q_min, self.q_max, p.u_min, p.u_max, a, BRAKE_SHARE,
                                                      u_prev, ACCEL_WIDENING[0], dt)
        for factor in ACCEL_WIDENING:
            if factor != ACCEL_WIDENING[0]:
                low, high, within = reach_box(u_prev, a, factor, dt, lower, upper)
            yield low, high, within
        yield lower, upper, False

    def _relax(self, problem: QPProblem, soft: np.ndarray, margin: np.ndarray,
               keep_hard: bool, in_stop: bool = False) -> tuple[np.ndarray | None, np.ndarray, float, bool]:
        """The relaxed solve (module docstring): (u or None, slacks (m,), seconds, whether it is the
        protective stop).

        :class:`~services.safety.relaxation.LexicographicSolver` on ``problem`` (``keep_hard``: its
        braking point keeps the hard rows); when a soft
        (robot–person) row gives way there and ``on_intrusion`` is "stop_on_give_way", or "stop"
        and the last step was a protective stop and this one is none yet (``in_stop``: a stop decided
        from the rows, whose person rows are at their floors or backing out: a stop goes on while
        person rows give way), the
        protective stop: the same solve again with every soft row at its floor, b_i ← min(b_i, 0)
        (never closer, no retreat demanded), aiming at ū, the box's point nearest rest, in the box
        narrowed to braking from u_prev (:func:`~services.safety.qp.box.braking_box`, which keeps ū). The slacks
        are the first solve's: the person rows that could not be honoured as asked (reported as
        given way). Only soft rows' b is lowered, so the feasibility argument holds unchanged; if
        the stop's solve fails numerically the first solve's u is used.
        """
        penalty = self.params.relax_penalty
        first = self._relaxation.solve(problem, soft, margin, penalty, keep_hard=keep_hard)
        on = self.params.on_intrusion
        stops = on == _STOP_ON_GIVE_WAY or (on == _STOP and self.stops.stopped and not in_stop)
        if first.u is None or not first.gave or not stops:
            return first.u, first.slack, first.seconds, False
        floored = problem.b.copy()
        np.minimum(floored, 0.0, out=floored, where=soft)
        lower, upper = problem.lower, problem.upper
        if self._u_prev is not None and self.params.accel_max is not None:  # a stop only brakes
            lower, upper = braking_box(lower, upper, self._u_prev)
        stop = self._relaxation.solve(dataclasses.replace(problem, b=floored, lower=lower, upper=upper), soft, margin,
                                      penalty, rest=True, keep_hard=keep_hard)
        u = first.u if stop.u is None else np.clip(stop.u, lower, upper)  # (within the solver's tolerance)
        return u, first.slack, first.seconds + stop.seconds, stop.u is not None
