"""The collision-geometry interface of the CBF: colliders fitted to the capsules, rows of every pair.

Every backend (capsules, sphere decomposition, oriented boxes; paper §IV-B, Table I) turns the
same inputs into the same output:

* in: the 7 robot capsules from forward kinematics, endpoints (7, 2, 3) and their point Jacobians
  (7, 2, 3, n), and the external (human) capsules of :meth:`CollisionGeometry.set_external`;
* out: :class:`BarrierRows`, one row per pair of *colliders* of every monitored capsule pair of
  the :class:`~services.safety.pairs.PairSet`,

      h = d(p_A, p_B) − (ρ_A + ρ_B + φ),   A = ∂h/∂q = nᵀ (J_pA − J_pB),   b = −γ (h − T a) + a,

  with p_A, p_B the witness points (closest points) of the two colliders, n = (p_A − p_B)/‖·‖ the
  unit normal, ρ the colliders' sphere-swept radii (0 for a box) and a = max(nᵀ v_pB, 0) the
  approach speed of an external collider (see :mod:`services.safety.barriers.capsules`). By the envelope
  theorem the witness points are held fixed in their bodies when differentiating, so a witness
  point's Jacobian is that of a body-fixed point. Every backend builds its rows with the same
  compiled kernel (:func:`services.safety.barriers.kernel.pair_rows`) over a stack of *segments*
  whose endpoints carry point Jacobians: a capsule's own segment, a sphere's centre or a box's
  witness point as a zero-length segment.

A row whose external capsule is missing (invalid) stays in the matrix with A = 0, b = −1e9 and
h = NaN, so the QP keeps a fixed size.
"""

from __future__ import annotations

import math
from abc import abstractmethod
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from services.safety.barriers.base import Barrier, RowBlock
from services.safety.barriers.kernel import (
    DISABLED_B, finish_segment_rows, masked_min, measured_rows, pair_rows, segment_pairs, write_segment_block,
)
from services.safety.compiled import BoundKernel
from services.safety.pairs import N_ROBOT, PairSet
from shared.geometry import EPS_NORMAL, safe_normal, segment_closest_points


@dataclass
class BarrierRows(RowBlock):
    """Pair rows for one step: ``A`` (m, n), ``b`` (m,), barrier values ``h`` (m,, NaN if disabled),
    ``soft`` = the robot–person rows (self rows are hard)."""

    distance: np.ndarray
    enabled: np.ndarray
    is_self: np.ndarray
    min_h_all: float = float("inf")  # min h over enabled rows (inf: none)
    #: (m,) m per row: h against the person capsule *as measured*, not swept ahead, where a swept
    #: person row is inside its margin (h < 0: :meth:`CollisionGeometry.measured_h`), h elsewhere
    #: (at most the measured one there, which lies inside the swept capsule); None: h (nothing swept)
    h_measured: np.ndarray | None = None

    def person_inside(self, below: float) -> np.ndarray:
        """(m,) bool: the enabled robot–person rows whose person capsule *as measured* is inside,
        h_measured < ``below`` (m, ≤ 0: a row with h ≥ 0 has its measured capsule outside too)."""
        h = self.h if self.h_measured is None else self.h_measured
        return self.soft & self.enabled & (h < below)  # a disabled row's h is NaN: never below

    def min_h(self, self_rows: bool) -> float | None:
        """Minimum h over enabled self (or robot–human) rows; None if there is none."""
        count, low = masked_min(self.h, self.enabled, self.is_self, self_rows)
        return float(low) if count else None

    def minima(self) -> tuple[float, float]:
        low_self = self.min_h(True)
        return self.min_h_all, float("inf") if low_self is None else low_self


def swept_witness_points(segments: np.ndarray, radii: np.ndarray, first: np.ndarray, second: np.ndarray) -> np.ndarray:
    """(m, 2, 3) closest surface points p_A − r_A n, p_B + r_B n of sphere-swept segment pairs
    (``first[i]``, ``second[i]``) of ``segments`` (S, 2, 3) with ``radii`` (S,)."""
    a, b = segments[first], segments[second]
    closest = segment_closest_points(a[:, 0], a[:, 1], b[:, 0], b[:, 1])
    normal = safe_normal(closest.p, closest.q, (a[:, 0], a[:, 1], b[:, 0], b[:, 1]))
    return np.stack([closest.p - radii[first, None] * normal, closest.q + radii[second, None] * normal], axis=1)


def segment_rows(
    segments: np.ndarray,
    radii: np.ndarray,
    jacobians: np.ndarray,
    velocities: np.ndarray,
    first: np.ndarray,
    second: np.ndarray,
    n_robot: int,
    gamma: float,
    phi: float,
    lookahead: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, float]:
    """Rows (A (m, n), b (m,), h (m,), distance (m,), min h (inf: no row)) of the sphere-swept segments ``segments``
    (S, 2, 3) with ``radii`` (S,): closest points, h and normals, then A and b, in one compiled call
    (:func:`~services.safety.barriers.kernel.segment_pairs`). The first ``n_robot`` segments are the
    robot's, with endpoint Jacobians ``jacobians`` (n_robot, 2, 3, n); the others are external
    (zero Jacobian), with endpoint ``velocities`` (S, 2, 3). Row i pairs segment ``first[i]``
    (robot) with ``second[i]``. A zero-length segment is a sphere."""
    m = len(first)
    distance, h, s, t = np.empty((4, m))  # one allocation; each a contiguous row
    normal = np.empty((m, 3))
    A, b = np.empty((m, jacobians.shape[3])), np.empty(m)
    need, min_h = segment_pairs(segments, radii, jacobians, velocities, first, second, n_robot, gamma, phi, lookahead,
                         EPS_NORMAL, distance, h, s, t, normal, A, b)
    if need:  # segments touching or crossing: the documented deterministic fallback normal, then the rows
        fallback_normals(segments, first, second, distance, normal)
        pair_rows(normal, s, t, h, jacobians, velocities, first, second, n_robot, gamma, lookahead, A, b)
    return A, b, h, distance, float(min_h)


def fallback_normals(segments: np.ndarray, first: np.ndarray, second: np.ndarray, distance: np.ndarray,
                     normal: np.ndarray) -> None:
    """Rows whose segments touch or cross (``distance`` < EPS_NORMAL) get the documented deterministic
    fallback normal (:func:`shared.geometry.safe_normal`) in ``normal`` (m, 3)."""
    rows = np.flatnonzero(distance < EPS_NORMAL)
    ea, eb = segments[first[rows]], segments[second[rows]]
    normal[rows] = safe_normal(np.zeros((len(rows), 3)), np.zeros((len(rows), 3)), (ea[:, 0], ea[:, 1], eb[:, 0], eb[:, 1]))


class SegmentRowWriter:
    """The compiled fast path of the rows of sphere-swept segment pairs (:func:`segment_rows`'s values)
    written in place (:meth:`Barrier.write_rows`): ``motion`` (2, S, 2, 3) C-contiguous = (segments,
    their endpoint velocities), the first R segments the robot's (copied from the forward kinematics
    at every write), ``radii`` (S,), row i pairing ``first[i]`` with ``second[i]``, with per-row
    ``flags`` (3, m) = (enabled, self-collision row, soft). The arrays are the owner's, read at every
    write (the owner updates them in place, e.g. through views of ``motion``; :attr:`flags` may be
    replaced)."""

    def __init__(self, motion: np.ndarray, radii: np.ndarray, first: np.ndarray, second: np.ndarray,
                 flags: np.ndarray) -> None:
        self.motion, self.radii, self.flags = motion, radii, flags
        self.pairs = np.ascontiguousarray(np.stack([first, second]), dtype=np.int64)
        m = self.pairs.shape[1]
        # the kernel's scratch: s and t of every row, then its normal (views for the fallback path)
        self._scratch = np.empty(5 * m)
        self._st, self._normal = self._scratch[:2 * m].reshape(2, m), self._scratch[2 * m:].reshape(m, 3)
        self._write = BoundKernel(write_segment_block)
        # numba compiles on first use: the kernel of touching segments, which only such a rare step
        # calls, is compiled now for the types of write's arguments (no row written), not in a control tick
        finish_segment_rows(self._normal, self._st, np.zeros((0, 2, 3, 0)), motion[1], self.pairs[:, :0], flags, 0, 0.0,
                            0.0, 0, np.zeros((0, 0)), np.zeros(0), np.zeros(0, bool), np.zeros(0))

    def write(self, endpoints: np.ndarray, jacobians: np.ndarray, gamma: float, phi: float, lookahead: float,
              start: int, A: np.ndarray, b: np.ndarray, soft: np.ndarray, h: np.ndarray,
              distance: np.ndarray) -> tuple[float, float]:
        """Rows at the robot's ``endpoints`` (R, 2, 3) and ``jacobians`` (R, 2, 3, n) into rows ``start`` …
        of ``A``, ``b``, ``soft``, ``h`` and their distances into ``distance`` (m,); returns
        :meth:`RowBlock.minima`."""
        pairs, flags, motion = self.pairs, self.flags, self.motion
        need, low, low_self = self._write.call(endpoints, motion, self.radii, jacobians, pairs, flags, gamma, phi,
                                               lookahead, distance, self._scratch, start, A, b, soft, h)
        if need:  # segments touching or crossing: the fallback normals, then the rows
            fallback_normals(motion[0], pairs[0], pairs[1], distance, self._normal)
            low, low_self = finish_segment_rows(self._normal, self._st, jacobians, motion[1], pairs, flags,
                                                endpoints.shape[0], gamma, lookahead, start, A, b, soft, h)
        return low, low_self



class CollisionGeometry(Barrier):
    """Colliders fitted to the robot and external capsules; the CBF rows of every monitored pair.

    Holds the capsule stack ``[robot_0 … robot_6, external_0 … external_{E−1}]`` (endpoints,
    radii, validity, endpoint velocities) that :class:`~services.safety.pairs.PairSet` indexes.
    A backend declares its rows (:meth:`_set_rows`: which monitored pair each row belongs to;
    one row per pair by default) and implements :meth:`evaluate` and :meth:`witness_points`.
    """

    #: The ``safety.geometry`` name of the backend.
    name: ClassVar[str]

    def __init__(self, pairs: PairSet, robot_radii: np.ndarray, n_joints: int) -> None:
        self.pairs = pairs
        self.robot_radii = np.asarray(robot_radii, dtype=np.float64)
        self.n_joints = n_joints
        n_stack = N_ROBOT + pairs.n_external
        #: (2, S, 2, 3) the stack's endpoints and endpoint velocities (the robot's stay zero: their
        #: motion is in J u); :attr:`_endpoints` and :attr:`_velocities` view it
        self._motion = np.zeros((2, n_stack, 2, 3))
        self._endpoints, self._velocities = self._motion[0], self._motion[1]
        self._radii = np.zeros(n_stack)
        self._sweep = np.zeros(n_stack)  # per capsule: the widening of a swept external one (m)
        self._swept = False  # some external capsule is swept (sweep > 0)
        #: the stack as measured (:meth:`measured_h`): the robot's capsules, then the external ones
        #: before their sweep (endpoints m, radii m: the person margin kept, the widening not)
        self._measured = np.zeros((n_stack, 2, 3))
        self._measured_radii = np.zeros(n_stack)
        self._measured_radii[:N_ROBOT] = self.robot_radii
        self._measured_rows = BoundKernel(measured_rows)
        self._valid = np.ones(n_stack, bool)
        self._radii[:N_ROBOT] = self.robot_radii
        #: added to every external capsule's radius at :meth:`set_external` (m; ``safety.human_margin``,
        #: the person sensor's position uncertainty): h of a robot–person row counts it
        self.person_margin = 0.0
        #: how fast the present external capsules were seen to move at :meth:`set_external` (m/s,
        #: :class:`~services.safety.seen_motion.SeenMotion`): 0 with none present, inf when unknown
        #: (not told, a present capsule held, one that just appeared)
        self.person_speed = 0.0
        self._all_enabled = True
        #: (m,) the monitored pair (index into ``pairs``) of each row; the identity for capsules.
        self.row_pair = np.arange(len(pairs))
        self._row_is_self = pairs.is_self
        self._row_capsule = np.asarray(pairs.second)  # the capsule whose validity enables the row
        self._row_constants()
        # compiled now for its argument types (no row computed), not in the control tick that first
        # finds a swept person inside a margin
        self._measured_rows.call(self._measured, self._measured_radii, self._row_first, self._row_second,
                                 self._row_swept, np.zeros(0), 0.0, np.empty(0))

    def _set_rows(self, row_pair: np.ndarray) -> None:
        """Declare the backend's rows: ``row_pair`` (m,) monitored pair of each row."""
        self.row_pair = np.asarray(row_pair, dtype=np.intp)
        self._row_is_self = self.pairs.is_self[self.row_pair]
        self._row_capsule = np.asarray(self.pairs.second)[self.row_pair]
        self._row_constants()

    def _row_constants(self) -> None:
        """Per-row arrays that are the same every step (shared by every BarrierRows, never written)."""
        self._row_soft = ~self._row_is_self
        self._row_all_enabled = np.ones(len(self._row_capsule), bool)
        self._row_enabled = self._row_all_enabled
        self._row_first = np.ascontiguousarray(np.asarray(self.pairs.first)[self.row_pair], dtype=np.int64)
        self._row_second = np.ascontiguousarray(self._row_capsule, dtype=np.int64)  # the same, for the kernel
        self._row_swept = np.zeros(len(self._row_capsule), bool)  # robot–person rows of a swept capsule
        #: (3, m) per row: enabled (updated in place by :meth:`set_external`), self-collision row, soft
        #: (the flags of :class:`SegmentRowWriter`)
        self._flags = np.stack([self._row_enabled, self._row_is_self, self._row_soft])
        #: The rows of the last evaluation (:meth:`evaluate` or :meth:`write_rows`).
        self.last_rows: BarrierRows | None = None

    def row_names(self) -> tuple[str, ...]:
        """The monitored pair of each row (a pair of several collider rows repeats its name)."""
        return tuple(self.pairs.names[i] for i in self.row_pair)

    @property
    def n_rows(self) -> int:
        """Rows (constraints) per step: fixed for a pair set."""
        return len(self.row_pair)

    def set_external(
        self,
        endpoints: np.ndarray | None,
        radii: np.ndarray | None = None,
        valid: np.ndarray | None = None,
        velocities: np.ndarray | None = None,
        sweep: np.ndarray | None = None,
        held: np.ndarray | None = None,
        seen_speed: float = math.inf,
        measured: np.ndarray | None = None,
    ) -> None:
        """Set the E external capsules ((E,2,3) m, (E,) m, (E,) bool, (E,2,3) m/s; each radius plus
        :attr:`person_margin`); None: none present. ``sweep`` (E,) m: how much each was widened to
        enclose where its velocity carries it (:func:`~services.safety.human_memory.swept_capsules`;
        None: 0), and ``measured`` (E,2,3) m, required with a sweep: their endpoints as measured,
        before it (:meth:`measured_h`, the rows' :attr:`BarrierRows.h_measured`); ``held`` (E,)
        bool: the capsules remembered rather than measured, whose velocity is unknown (None: none);
        ``seen_speed`` (m/s): how fast they were seen to move over the last states
        (:class:`~services.safety.seen_motion.SeenMotion`; inf: unknown). :attr:`person_speed` follows:
        ``seen_speed``, or inf while a present capsule is held. The measured ``velocities`` do not
        count there: a camera's noise gives a still person's capsules velocities of metres per second."""
        ext = slice(N_ROBOT, None)
        if endpoints is None:
            self._valid[ext] = False
            self._swept = False
            self.person_speed = 0.0
        else:
            self._endpoints[ext] = endpoints
            self._radii[ext] = np.add(radii, self.person_margin)
            self._valid[ext] = True if valid is None else valid
            self._velocities[ext] = 0.0 if velocities is None else velocities
            self._sweep[ext] = 0.0 if sweep is None else sweep
            self._swept = bool(self._sweep[ext].any())
            if self._swept:
                if measured is None:
                    raise ValueError("swept external capsules need their endpoints as measured (measured=)")
                self._measured[ext] = measured
                np.subtract(self._radii[ext], self._sweep[ext], out=self._measured_radii[ext])
                np.greater(self._sweep[self._row_capsule], 0.0, out=self._row_swept)
                self._row_swept &= self._row_soft
            present = self._valid[ext]
            held_present = held is not None and bool((present & held).any())
            self.person_speed = math.inf if held_present else seen_speed if present.any() else 0.0
            self._external_changed()
        self._all_enabled = bool(self._valid.all())
        self._row_enabled = self._row_all_enabled if self._all_enabled else self._valid[self._row_capsule]
        self._flags[0] = self._row_enabled

    def _external_changed(self) -> None:
        """Hook: the external capsules changed (backends fit their external colliders here)."""

    @abstractmethod
    def evaluate(
        self, robot_endpoints: np.ndarray, robot_jacobians: np.ndarray, gamma: float, phi: float, lookahead: float = 0.0
    ) -> BarrierRows:
        """Rows at the robot configuration whose FK (``RobotKinematics.compute``, just called) gave
        ``robot_endpoints`` (7,2,3) and ``robot_jacobians`` (7,2,3,n); ``lookahead`` T (s) of the
        human velocity term."""

    @abstractmethod
    def witness_points(self) -> np.ndarray:
        """(m, 2, 3) the closest points of every row's two colliders at the last evaluation: p_A on
        the robot's, p_B on the other (the constraint lines of the paper's Fig. 4)."""

    def measured_h(self, robot_endpoints: np.ndarray, h: np.ndarray, phi: float) -> np.ndarray | None:
        """(m,) h of every row against its person capsule *as measured* where that matters, or None
        when no person capsule is swept ahead (h is then measured already).

        A swept capsule (:func:`~services.safety.human_memory.swept_capsules`) encloses the capsule
        as measured, so against any robot capsule the measured one's h is at least the swept one's.
        Rows with h ≥ 0 (or disabled, NaN) keep h, a bound below their measured h that already says
        "outside". For a robot–person row inside its margin (h < 0) of a swept capsule, the exact
        value on the capsules, d(robot capsule axis, measured axis) − (r_robot + r_person + φ), with
        r_person the radius before the sweep (person margin included), at ``robot_endpoints``
        (7, 2, 3) m, the robot pose the rows were evaluated at. Whether the person is inside a margin
        (the protective stops, :mod:`services.safety.protective_stop`) is then decided on where the
        camera showed them, not on the bound h + 2·sweep, which for a limb moving at metres per
        second reads a capsule measured 6 cm inside as outside."""
        if not self._swept:
            return None
        self._measured[:N_ROBOT] = robot_endpoints
        out = np.empty(h.shape[0])
        self._measured_rows.call(self._measured, self._measured_radii, self._row_first, self._row_second,
                                 self._row_swept, h, float(phi), out)
        return out

    def _rows(self, A: np.ndarray, b: np.ndarray, h: np.ndarray, distance: np.ndarray, robot_endpoints: np.ndarray,
              phi: float, min_h: float | None = None) -> BarrierRows:
        """Package the rows at ``robot_endpoints`` (7, 2, 3) and margin ``phi``, disabling those of
        missing external capsules, with :meth:`measured_h`; ``min_h``: the smallest h of all rows
        when the caller has it (None: computed here)."""
        if not self._all_enabled:
            enabled = self._valid[self._row_capsule]
            A[~enabled] = 0.0
            b[~enabled] = DISABLED_B
            h[~enabled] = np.nan
            min_h_all = float(h[enabled].min()) if enabled.any() else float("inf")
        else:
            enabled = self._row_all_enabled
            min_h_all = min_h if min_h is not None else float(h.min()) if len(h) else float("inf")
        h_measured = self.measured_h(robot_endpoints, h, phi) if min_h_all < 0.0 else None
        self.last_rows = BarrierRows(A=A, b=b, soft=self._row_soft, h=h, distance=distance, enabled=enabled,
                                     is_self=self._row_is_self, min_h_all=min_h_all, h_measured=h_measured)
        return self.last_rows

    def constraint_rows(self, q: np.ndarray, endpoints: np.ndarray, jacobians: np.ndarray, gamma: float, phi: float,
                        lookahead: float, accel: np.ndarray | None = None) -> BarrierRows:
        return self.evaluate(endpoints, jacobians, gamma, phi, lookahead)
