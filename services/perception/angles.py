"""The reduced human pose θ ∈ R^8 from a skeleton (paper §II-A).

Frames
------
Points are in the robot frame (x forward, y left, z up; ``k = (0, 0, 1)`` is the global up of the
paper's F_Z). The torso frame F_T (paper): origin at the pelvis,

    e_z = unit(c − pelvis),                 c = shoulder centre,
    e_x = unit(l − (l·e_z) e_z),            l = right_shoulder − left_shoulder  (the person's RIGHT),
    e_y = e_z × e_x                         (the person's FORWARD; right-handed).

This is the axis convention the paper's formulas imply: with it, arm forward gives +π/2 shoulder
pitch and an arm out sideways +π/2 shoulder roll on both sides (see the tests).

Angles (radians), in :data:`shared.names.POSE_ANGLE_NAMES` order
------------------------------------------------------------------
With ``k_T = (k·e_x, k·e_y, k·e_z)`` the global up in torso coordinates,

    torso roll  = atan2(−e_yᵀ(k × e_z), kᵀe_z) = atan2(k·e_x, k·e_z)   (+: leaning to the person's left)
    torso pitch = atan2(−e_xᵀ(k × e_z), kᵀe_z) = atan2(−k·e_y, k·e_z)  (+: leaning forward)

(the identities follow from e_z × e_y = −e_x and e_z × e_x = e_y). For an arm with upper-arm
vector u (shoulder → elbow) and forearm f (elbow → wrist), write u in torso coordinates as
(o, f', d) = (σ u_x, u_y, −u_z)/‖u‖ — outward, forward, downward — with σ = −1 on the left and
+1 on the right. The paper's estimator (``paper``) is

    pitch = atan2(u_y, −u_z) = atan2(f', d),     roll = atan2(∓u_x, −u_z) = atan2(o, d),
    elbow = arccos(u·f / (‖u‖ ‖f‖))              (0 = straight).

Its pitch and roll are the angles of the arm's projections onto the sagittal and frontal planes.
They are well conditioned while the arm points down (d > 0) but wrap at ±π overhead: an arm
swept sideways past shoulder height flips pitch from 0 to π in one frame.

The continuous estimator (default)
----------------------------------
It follows the robot's shoulder joint order — pitch about the lateral axis first, then roll — so
that the robot, driven by these angles, points its arm where the person does. That chain maps
(pitch p, roll r) to the direction (o, f', d) = (sin r, cos r sin p, cos r cos p). Per frame:

1. pitch: the sagittal angle p̂ = atan2(f', d). In the paper zone (d ≥ ``paper_zone``, the arm
   clearly below the shoulder) p = p̂ exactly. Elsewhere p = p_prev + κ·wrap_π(p̂ − p_prev): the
   change is taken modulo π (the chain reaches every direction twice, (p, r) and (p ± π, ±π − r);
   the branch nearest the previous frame wins) and scaled by κ = min(1, s/``pitch_observability``)
   with s = √(f'² + d²) = |cos r|: near the arm's lateral axis pitch barely moves the arm, so its
   noisy measurement is followed only in proportion to how observable it is. Without history
   (first frame) p = p̂, the branch with |roll| ≤ π/2 (the G1's roll range is the narrow one),
   except where pitch is unobservable (s < ``pitch_observability``): there the untwisted branch
   |p| ≤ π/2 is taken, so an arm held out sideways reads pitch 0, roll π/2. Then p is wrapped
   into [S − 2π, S) with S = ``seam`` (default 5π/4: the wrap is 45° behind straight overhead,
   a direction arms seldom take; S ∈ (π, 3π/2] keeps overhead = π and the whole region below
   the horizontal inside, so every p below is the same representative the paper zone uses).
2. roll: r = atan2(o, w) with w = f' sin(λp) + d cos(λp), λ = smoothstep((zone − d)/zone) in [0, 1].
   λ = 0 (paper zone) gives the paper's roll atan2(o, d); λ = 1 (arm at or above the shoulder)
   gives the roll that best reproduces the arm direction after pitch p (it maximises the dot
   product between the chain's direction and u), which on the tracked branch is the exact
   inverse of the chain. Outside the paper zone r is wrapped into [S − 2π, S) too.
3. output (branch switches spread): steps 1–2 give the *tracked* angles x (pitch and roll, each
   on its own). Continuous motion changes x by little per frame; a change |x − x_prev| ≥ π/2 in
   one frame (:data:`BRANCH_JUMP`: 47 rad/s at 30 Hz, no arm moves so) is a branch switch — x
   wrapping at S when the arm circles on (a "windmill": forward, overhead, down behind), or
   snapping onto the paper's branch on entering the paper zone after the arm went overhead on the
   roll branch, or the roll's w changing sign. The output is θ = x + e with an offset e:

       e ← e − (x − x_prev)                    if |x − x_prev| ≥ π/2 (θ does not follow the jump),
       e ← e − clamp(e, ±δ),                   δ = min(``branch_switch_rate``·Δt, π/4),
       e ← clamp(e, S − 2π − x, S − x)          (so θ ∈ [S − 2π, S]),

   e = 0 on a fresh start. So θ is bounded in [S − 2π, S], never changes by π or more between
   frames (|Δθ| < π/2 + π/4: the clamp projects onto an interval holding θ_prev, so it never
   adds to a step), and after a switch returns to the tracked angles at ``branch_switch_rate``
   rad/s (default 4 rad/s, the robot's default joint speed bound u_max: the target moves no
   faster than the robot may). While e ≠ 0 θ is not the tracked angle: a windmilling arm's
   pitch swings back from S through the front (a shoulder pitch joint cannot turn round; the
   only other way, through the lateral axis, would swing the arm out sideways into a person
   beside the robot), taking 2π/rate ≈ 1.6 s at the default. ``t`` (s) of each frame gives Δt;
   without it frames are 1/30 s apart.

So the two estimators agree exactly wherever the paper's is well conditioned (while no switch
is being spread) — the default ``paper_zone`` = 0.5 is an upper arm at least 30° below
horizontal, where the paper's angles move at most 1/d = 2× as fast as the arm — and the
continuous one stays continuous through overhead motion. Between d = 0.5 and the horizontal the
roll blends smoothly from the paper's to the chain's. Known limits: an arm passing close to its
own lateral axis (gimbal lock of the pitch-roll chain) must turn pitch by up to π there, which κ
spreads over several frames; an arm that went overhead on the roll branch and comes down in
front switches back to the paper's values on entering the paper zone (spread by step 3); an arm
jittering across the seam stays near S (each crossing is absorbed as it happens). A frame where an arm is invalid forgets its history (the next valid frame
starts afresh, e = 0).

Validity: torso angles need the pelvis and both shoulders with a torso and a shoulder line of at
least ``min_segment``; shoulder angles also need the elbow and an upper arm ≥ ``min_segment``;
the elbow needs shoulder, elbow, wrist and both segments ≥ ``min_segment``. An invalid angle holds
its last valid value (0 before the first); no output is ever NaN.
"""

from __future__ import annotations

import math

import numpy as np

from shared.config import PoseAnglesConfig, PoseEstimatorName
from shared.lowpass import angle_rate_filter, angle_rate_parameters
from shared.names import KEYPOINT_INDEX, POSE_ANGLE_NAMES
from shared.torso_frame import Vec, dot as _dot, norm as _norm, sub as _sub, torso_axes

_PELVIS = KEYPOINT_INDEX["pelvis"]
_L_SHOULDER = KEYPOINT_INDEX["left_shoulder"]
_R_SHOULDER = KEYPOINT_INDEX["right_shoulder"]
#: (side sign σ, shoulder, elbow, wrist, index of the arm's pitch in θ); pitch, roll, elbow follow.
_ARMS = (
    (-1.0, _L_SHOULDER, KEYPOINT_INDEX["left_elbow"], KEYPOINT_INDEX["left_wrist"], 2),
    (1.0, _R_SHOULDER, KEYPOINT_INDEX["right_elbow"], KEYPOINT_INDEX["right_wrist"], 5),
)
N_ANGLES = len(POSE_ANGLE_NAMES)
_TWO_PI = 2.0 * math.pi
#: A tracked shoulder angle changing this much (rad) in one frame switched branch: it is spread.
BRANCH_JUMP = 0.5 * math.pi
#: At most this much (rad) of a spread switch is released per frame, whatever the frame gap.
MAX_DECAY_STEP = 0.25 * math.pi
#: Frame period assumed when the estimator is called without times (s).
NOMINAL_FRAME_S = 1.0 / 30.0
def wrap_pi(angle: float) -> float:
    """``angle`` wrapped into [−π/2, π/2): the difference modulo a half turn."""
    return angle - math.pi * math.floor(angle / math.pi + 0.5)


def wrap_seam(angle: float, seam: float) -> float:
    """``angle`` wrapped into [seam − 2π, seam)."""
    return angle - _TWO_PI * (math.floor((angle - seam) / _TWO_PI) + 1.0)


def smoothstep(x: float) -> float:
    """C¹ ramp: 0 for x ≤ 0, 1 for x ≥ 1, 3x² − 2x³ between."""
    x = min(1.0, max(0.0, x))
    return x * x * (3.0 - 2.0 * x)


def torso_roll_pitch(axes: tuple[Vec, Vec, Vec]) -> tuple[float, float]:
    """Torso (roll, pitch) from the torso axes (e_x, e_y, e_z): the paper's formulas."""
    e_x, e_y, e_z = axes
    k_x, k_y, k_z = e_x[2], e_y[2], e_z[2]  # the global up k = (0, 0, 1) in F_T
    return math.atan2(k_x, k_z), math.atan2(-k_y, k_z)


class PoseEstimator:
    """θ from one skeleton per call; ``paper`` or ``continuous`` shoulder angles (module docstring).

    Call with ``xyz`` (15, 3) points (any z-up frame; robot frame in the service) and ``valid``
    (15,) bool; returns (θ (8,), θ_valid (8,)). θ entries that are invalid hold their last valid
    value. The estimator keeps per-arm history (continuous mode): :meth:`reset` forgets it.
    """

    def __init__(self, conf: PoseAnglesConfig) -> None:
        self.configure(conf)
        self._theta = [0.0] * N_ANGLES  # the last valid value of each angle (held while invalid)
        self._history = [False, False]  # per arm: previous pitch/roll usable for branch tracking
        self._tracked = [(0.0, 0.0), (0.0, 0.0)]  # per arm: the chain's (pitch, roll) before spreading
        self._offset = [(0.0, 0.0), (0.0, 0.0)]  # per arm: output − tracked, decaying to 0 (step 3)
        self._t: float | None = None

    def configure(self, conf: PoseAnglesConfig) -> None:
        """Estimator and thresholds for the following frames."""
        self.conf = conf
        self.continuous = conf.estimator == PoseEstimatorName.CONTINUOUS

    def reset(self) -> None:
        """Forget the branch history (held outputs stay, for display only: they are invalid now)."""
        self._history = [False, False]
        self._t = None

    def __call__(self, xyz: np.ndarray, valid: np.ndarray, t: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        """θ, θ_valid of one frame; ``t`` (s) paces the branch-switch spreading (None: frames 1/30 s apart)."""
        theta, ok = self.estimate(xyz.tolist(), valid.tolist(), t)
        return np.array(theta), np.array(ok)

    def estimate(self, points: list[Vec], present: list[bool], t: float | None = None) -> tuple[list[float], list[bool]]:
        """:meth:`__call__` on Python lists (15 points (x, y, z), 15 flags): θ, θ_valid as new lists."""
        dt = NOMINAL_FRAME_S if t is None or self._t is None else max(0.0, t - self._t)
        self._t = t
        theta, ok = self._theta, [False] * N_ANGLES
        axes = None
        if present[_PELVIS] and present[_L_SHOULDER] and present[_R_SHOULDER]:
            axes = torso_axes(points[_PELVIS], points[_L_SHOULDER], points[_R_SHOULDER], self.conf.min_segment)
        if axes is not None:
            theta[0], theta[1] = torso_roll_pitch(axes)
            ok[0] = ok[1] = True
        for arm, (sign, shoulder, elbow, wrist, first) in enumerate(_ARMS):
            upper, elbow_angle = self._arm_geometry(points, present, axes, sign, shoulder, elbow, wrist)
            if elbow_angle is not None:
                theta[first + 2] = elbow_angle
                ok[first + 2] = True
            if upper is None:
                self._history[arm] = False
                continue
            if self.continuous:
                pitch, roll = self._spread(arm, self._continuous(arm, upper), dt)
            else:
                o, f, d = upper
                pitch, roll = math.atan2(f, d), math.atan2(o, d)
            theta[first], theta[first + 1] = pitch, roll
            ok[first] = ok[first + 1] = True
            self._history[arm] = True
        return theta[:], ok

    def _arm_geometry(
        self, points: list[Vec], present: list[bool], axes: tuple[Vec, Vec, Vec] | None,
        sign: float, shoulder: int, elbow: int, wrist: int,
    ) -> tuple[Vec | None, float | None]:
        """One arm: its unit upper arm (o, f', d) (outward, forward, down) in torso coordinates and
        its elbow angle; None where not computable (validity: module docstring)."""
        min_segment = self.conf.min_segment
        if not (present[shoulder] and present[elbow]):
            return None, None
        upper = _sub(points[elbow], points[shoulder])
        upper_len = _norm(upper)
        if not upper_len >= min_segment:
            return None, None
        elbow_angle = None
        if present[wrist]:
            fore = _sub(points[wrist], points[elbow])
            fore_len = _norm(fore)
            if fore_len >= min_segment:
                cosine = _dot(upper, fore) / (upper_len * fore_len)
                elbow_angle = math.acos(min(1.0, max(-1.0, cosine)))
        if axes is None:
            return None, elbow_angle
        e_x, e_y, e_z = axes
        direction = (sign * _dot(e_x, upper) / upper_len, _dot(e_y, upper) / upper_len, -_dot(e_z, upper) / upper_len)
        return direction, elbow_angle

    def _continuous(self, arm: int, upper: Vec) -> tuple[float, float]:
        """Steps 1–2 of the module docstring: the tracked (pitch, roll) of the unit upper arm
        ``upper`` = (o, f', d), each in [seam − 2π, seam)."""
        o, f, d = upper
        zone, seam = self.conf.paper_zone, self.conf.seam
        measured = math.atan2(f, d)
        history = self._history[arm]
        pitch_prev = self._tracked[arm][0]
        observability = self.conf.pitch_observability
        s = math.hypot(f, d)
        if d >= zone:
            pitch = measured
        elif not history:  # fresh start: the |roll| ≤ π/2 branch, untwisted where pitch is unobservable
            pitch = measured
            if s < observability and abs(measured) > 0.5 * math.pi:
                pitch -= math.copysign(math.pi, measured)
        else:
            gain = 1.0 if s >= observability else s / observability
            pitch = pitch_prev + gain * wrap_pi(measured - pitch_prev)
        pitch = wrap_seam(pitch, seam)
        blend = smoothstep((zone - d) / zone)
        if blend == 0.0:
            return pitch, math.atan2(o, d)
        q = blend * pitch
        return pitch, wrap_seam(math.atan2(o, f * math.sin(q) + d * math.cos(q)), seam)

    def _spread(self, arm: int, tracked: tuple[float, float], dt: float) -> tuple[float, float]:
        """Step 3 of the module docstring: output = tracked + offset, jumps absorbed, offset decaying."""
        previous, offset = self._tracked[arm], self._offset[arm]
        self._tracked[arm] = tracked
        if not self._history[arm]:
            self._offset[arm] = (0.0, 0.0)
            return tracked
        seam = self.conf.seam
        decay = min(self.conf.branch_switch_rate * dt, MAX_DECAY_STEP)
        spread = []
        for target, before, e in zip(tracked, previous, offset):
            step = target - before
            if abs(step) >= BRANCH_JUMP:
                e -= step  # the output does not follow the jump
            e = e - decay if e > decay else e + decay if e < -decay else 0.0  # e ← e − clamp(e, ±δ)
            high, low = seam - target, seam - _TWO_PI - target  # output in [seam − 2π, seam]
            e = high if e > high else low if e < low else e
            spread.append(e)
        self._offset[arm] = tuple(spread)
        return tracked[0] + spread[0], tracked[1] + spread[1]


def _angle_keypoints() -> np.ndarray:
    """(8, 15) bool: the keypoints each angle of θ is computed from."""
    uses = np.zeros((N_ANGLES, len(KEYPOINT_INDEX)), dtype=bool)
    torso = [_PELVIS, _L_SHOULDER, _R_SHOULDER]
    uses[0:2, torso] = True
    for _, shoulder, elbow, wrist, first in _ARMS:
        uses[first:first + 2, torso + [elbow]] = True
        uses[first + 2, [shoulder, elbow, wrist]] = True
    return uses


ANGLE_KEYPOINTS = _angle_keypoints()
#: the indices of each angle's keypoints (:data:`ANGLE_KEYPOINTS`, row by row)
_ANGLE_KEYPOINT_LISTS = [np.flatnonzero(row).tolist() for row in ANGLE_KEYPOINTS]


class AngleRates:
    """θ̇ (8,) rad/s from consecutive θ of one person (the contract of ``HumanState.theta_rate``).

    Per angle i, between frames at t_prev and t (Δt = t − t_prev > 0) where θ_i is valid (and
    finite) in both and none of its keypoints (:data:`ANGLE_KEYPOINTS`) is fresh (re-initialised by the point
    filter this frame), the difference θ_i(t) − θ_i(t_prev) wrapped into [−π, π) goes through the
    rate filter of ``conf`` (:class:`shared.lowpass.RateFilter`: the slope at the newest frame, second order
    where the previous difference was usable too, low-passed at ``rate_cutoff_hz`` plus
    ``rate_beta`` × the angle's speed). Anywhere else θ̇_i = 0 and its filter restarts; :meth:`reset`
    (a filter reset) zeroes every rate. The output is always finite.
    """

    def __init__(self, conf: PoseAnglesConfig) -> None:
        self.filter = angle_rate_filter(N_ANGLES, conf)
        self._theta = [0.0] * N_ANGLES
        self._valid = [False] * N_ANGLES
        self._t: float | None = None

    def configure(self, conf: PoseAnglesConfig) -> None:
        """New rate parameters from the next frame on (the state is kept)."""
        self.filter.configure(*angle_rate_parameters(conf))

    def reset(self) -> None:
        self.filter.reset()
        self._valid = [False] * N_ANGLES
        self._t = None

    def __call__(self, t: float, theta: np.ndarray, valid: np.ndarray, fresh: np.ndarray) -> np.ndarray:
        """θ̇ at ``t`` (s) from θ (8,), θ_valid (8,) and the filter's ``fresh`` (15,) points."""
        return self.update(t, theta.tolist(), valid.tolist(), fresh.tolist())

    def update(self, t: float, angles: list[float], valid: list[bool], fresh: list[bool]) -> np.ndarray:
        """:meth:`__call__` on Python lists (kept as the previous frame's: not to be modified after)."""
        dt = 0.0 if self._t is None else t - self._t
        steps = [now - before for now, before in zip(angles, self._theta)]
        usable = [now and before and math.isfinite(d) for now, before, d in zip(valid, self._valid, steps)]
        if True in fresh:
            usable = [use and not any(fresh[k] for k in uses) for use, uses in zip(usable, _ANGLE_KEYPOINT_LISTS)]
        if dt > 0.0 and any(usable):
            wrapped = [d - _TWO_PI * math.floor((d + math.pi) / _TWO_PI) if use else 0.0  # into [−π, π)
                       for d, use in zip(steps, usable)]
            rate = self.filter.update(dt, wrapped, usable)
        else:
            self.filter.reset([not use for use in usable])
            rate = self.filter.rate
        self._theta = angles
        self._valid = valid
        self._t = t
        return rate
