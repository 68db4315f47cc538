"""Robot forward kinematics for the CBF: capsule endpoints and their point Jacobians.

Built from a :class:`shared.robot_spec.RobotSpec`:

1. the MJCF (or URDF) becomes a Pinocchio model with a free flyer (the G1's pelvis
   free joint; a URDF gets one added);
2. a fixed-base *reduced* model keeps only the 8 imitation joints: the free flyer is
   locked with the base body at ``(0, 0, base_height)`` and identity orientation, every
   other joint at its home value (``spec.home``, unspecified joints 0);
3. one operational frame per capsule endpoint (14) is added to the reduced model, so a
   single kinematic pass yields every endpoint position and point Jacobian.

Conventions: q is ordered as ``spec.imitation_joints`` (the paper's order); positions are
in the world frame (z up, ground at z = 0 below the pelvis); Jacobians are
``LOCAL_WORLD_ALIGNED`` linear parts, i.e. ``d p / d q`` in world axes.

``compute(q)`` runs ``pin.computeJointJacobians`` + ``pin.updateFramePlacements`` and
forms the 14 point Jacobians at once from the joint Jacobian matrix (the same numbers as
``pin.getFrameJacobian(..., LOCAL_WORLD_ALIGNED)[:3]``, which the constructor checks, and
falls back to, should a Pinocchio build not expose its buffers as numpy views).
"""

from __future__ import annotations

import logging
import math
from pathlib import Path

import numpy as np
import pinocchio as pin

from services.safety.errors import KinematicsError
from shared.names import CAPSULE_NAMES
from shared.robot_spec import RobotSpec

__all__ = ["KinematicsError", "RobotKinematics"]

log = logging.getLogger(__name__)

# A joint range wider than this (rad) is treated as "no limit" (parsers use ±DBL_MAX or so).
_NO_LIMIT = 1e6
_FREE_FLYER = "JointModelFreeFlyer"


def _load_model(path: Path) -> pin.Model:
    if not path.is_file():
        raise KinematicsError(f"robot model file not found: {path}")
    ext = path.suffix.lower()
    try:
        if ext in (".xml", ".mjcf"):
            return pin.buildModelFromMJCF(str(path))
        if ext == ".urdf":
            return pin.buildModelFromUrdf(str(path), pin.JointModelFreeFlyer())
    except Exception as exc:  # Pinocchio raises RuntimeError/ValueError/... from C++
        raise KinematicsError(f"cannot build a Pinocchio model from {path}: {exc}") from exc
    raise KinematicsError(f"unsupported robot model format {ext!r} for {path} (use .xml/.mjcf or .urdf)")


class RobotKinematics:
    """Fixed-base kinematics of the 8 imitation joints with the 7 robot capsules.

    Not thread-safe: ``compute`` writes into buffers owned by the instance and returns
    them (they are overwritten by the next call; copy them to keep them).
    """

    def __init__(self, spec: RobotSpec) -> None:
        self._spec = spec
        full = _load_model(spec.model_path)

        # ---- joints named by the spec ------------------------------------------------
        missing = [j for j in spec.imitation_joints if not full.existJointName(j)]
        if missing:
            raise KinematicsError(
                f"imitation joints missing from {spec.model_path.name}: {missing}"
            )
        for name in spec.imitation_joints:
            jm = full.joints[full.getJointId(name)]
            if jm.nq != 1 or jm.nv != 1:
                raise KinematicsError(
                    f"imitation joint {name!r} must be a 1-DoF joint, got {jm.shortname()}"
                )
        unknown_home = sorted(j for j in spec.home if not full.existJointName(j))
        if unknown_home:
            raise KinematicsError(
                f"home names joints missing from {spec.model_path.name}: {unknown_home}"
            )

        # ---- reference configuration of the full model ------------------------------
        q_ref = pin.neutral(full)
        self._set_base(full, q_ref)
        for name, value in spec.home.items():
            jid = full.getJointId(name)
            jm = full.joints[jid]
            if jm.nq != 1:
                raise KinematicsError(f"home[{name!r}]: only 1-DoF joints can be given a home angle")
            lo = float(full.lowerPositionLimit[jm.idx_q])
            hi = float(full.upperPositionLimit[jm.idx_q])
            if abs(lo) < _NO_LIMIT and abs(hi) < _NO_LIMIT and not lo - 1e-9 <= value <= hi + 1e-9:
                raise KinematicsError(f"home[{name!r}] = {value} lies outside the joint range [{lo}, {hi}]")
            q_ref[jm.idx_q] = value

        # ---- reduced (fixed-base) model ---------------------------------------------
        keep = set(spec.imitation_joints)
        lock = [jid for jid in range(1, full.njoints) if full.names[jid] not in keep]
        model = pin.buildReducedModel(full, lock, q_ref)
        nv = model.nv
        if model.nq != len(spec.imitation_joints) or nv != model.nq:
            raise KinematicsError(f"reduced model has nq={model.nq}, nv={nv}; expected 8 revolute joints")
        jids = [model.getJointId(n) for n in spec.imitation_joints]
        self._idx_q = np.array([model.joints[j].idx_q for j in jids])
        self._idx_v = np.array([model.joints[j].idx_v for j in jids])
        self._identity_order = bool(
            np.array_equal(self._idx_q, np.arange(nv)) and np.array_equal(self._idx_v, np.arange(nv))
        )
        self._joint_names = tuple(spec.imitation_joints)

        # ---- limits and home of the 8 joints ----------------------------------------
        q_min = np.array(model.lowerPositionLimit[self._idx_q], dtype=np.float64)
        q_max = np.array(model.upperPositionLimit[self._idx_q], dtype=np.float64)
        for i, name in enumerate(self._joint_names):
            model_lo, model_hi = q_min[i], q_max[i]
            if name in spec.limits:
                lo, hi = spec.limits[name]
                bounded = abs(model_lo) < _NO_LIMIT and abs(model_hi) < _NO_LIMIT
                if bounded and (lo < model_lo - 1e-9 or hi > model_hi + 1e-9):
                    raise KinematicsError(
                        f"limits[{name!r}] = [{lo}, {hi}] is wider than the model's range "
                        f"[{model_lo}, {model_hi}]; overrides may only tighten it"
                    )
                q_min[i], q_max[i] = lo, hi
            elif not (abs(model_lo) < _NO_LIMIT and abs(model_hi) < _NO_LIMIT):
                raise KinematicsError(
                    f"joint {name!r} has no finite range in {spec.model_path.name}; give one in limits"
                )
        q_home = np.array([spec.home.get(n, 0.0) for n in self._joint_names], dtype=np.float64)
        outside = [
            f"{n}={h} not in [{lo}, {hi}]"
            for n, h, lo, hi in zip(self._joint_names, q_home, q_min, q_max)
            if not lo <= h <= hi
        ]
        if outside:
            raise KinematicsError(f"home outside the joint limits: {outside}")
        for arr in (q_min, q_max, q_home):
            arr.flags.writeable = False
        self._q_min, self._q_max, self._q_home = q_min, q_max, q_home

        # ---- capsule endpoint frames ---------------------------------------------
        missing_frames = sorted(
            {spec.capsules[c].frame for c in CAPSULE_NAMES if not model.existFrame(spec.capsules[c].frame)}
        )
        if missing_frames:
            raise KinematicsError(
                f"capsule frames missing from {spec.model_path.name}: {missing_frames}"
            )
        local = np.zeros((len(CAPSULE_NAMES), 2, 3))
        frame_ids: list[int] = []
        parents: list[int] = []
        for ci, cname in enumerate(CAPSULE_NAMES):
            cap = spec.capsules[cname]
            fid = model.getFrameId(cap.frame)
            frame = model.frames[fid]
            for k, point in enumerate((cap.a, cap.b)):
                local[ci, k] = point
                placement = frame.placement * pin.SE3(np.eye(3), np.asarray(point, dtype=np.float64))
                op = pin.Frame(
                    f"capsule/{cname}/{'ab'[k]}", frame.parentJoint, fid, placement, pin.FrameType.OP_FRAME
                )
                frame_ids.append(model.addFrame(op, False))
                parents.append(frame.parentJoint)
        local.flags.writeable = False
        self._capsule_local = local
        self._frame_ids = np.array(frame_ids)
        radii = np.array([spec.capsules[c].radius for c in CAPSULE_NAMES], dtype=np.float64)
        radii.flags.writeable = False
        self._radii = radii

        self._static_endpoints = self._place_static_capsules(model, spec)

        index = {c: i for i, c in enumerate(CAPSULE_NAMES)}
        pairs = np.array([(index[a], index[b]) for a, b in spec.self_pairs], dtype=np.intp).reshape(-1, 2)
        pairs.flags.writeable = False
        self._self_pairs = pairs

        self._model = model
        self._data = model.createData()
        self._aux_data = model.createData()

        # Support mask: column v of endpoint e's Jacobian is nonzero only if joint v moves e.
        n_end = len(frame_ids)
        mask = np.zeros((n_end, 1, nv))
        for e, jid in enumerate(parents):
            for s in model.supports[jid]:
                if s > 0:
                    mask[e, 0, model.joints[s].idx_v] = 1.0
        self._mask = mask
        self._moving = mask[:, 0, :].any(axis=1).reshape(len(CAPSULE_NAMES), 2)

        # Output buffers and scratch. The point Jacobians come out of one matmul:
        #   J_p[e] = v_O − [p_e]× ω = [1, p_e] · N,   N = [v_O ; −(ε·ω)]  (4 × 3·nv)
        # with (v_O; ω) the world-frame joint Jacobian columns, masked by joint support.
        n_cap = len(CAPSULE_NAMES)
        self._endpoints = np.zeros((n_cap, 2, 3))
        self._jacobians = np.zeros((n_cap, 2, 3, nv))
        self._P = self._endpoints.reshape(n_end, 3)  # view
        self._Paug = np.ones((n_end, 4))
        self._N = np.zeros((4, 3 * nv))
        self._N_v = self._N[0].reshape(3, nv)          # view: v_O rows
        self._N_w = self._N[1:].reshape(9, nv)         # view: rows (a, c) = −Σ_b ε_cab ω_b
        eps = np.zeros((3, 3, 3))
        for c, a, b in ((0, 1, 2), (1, 2, 0), (2, 0, 1)):
            eps[c, a, b], eps[c, b, a] = 1.0, -1.0
        self._neg_eps = -np.transpose(eps, (1, 0, 2)).reshape(9, 3)  # row (a, c), column b
        self._mask_flat = np.repeat(mask, 3, axis=1).reshape(n_end, 3 * nv)
        self._Jflat = (
            self._jacobians.reshape(n_end, 3 * nv) if self._identity_order else np.zeros((n_end, 3 * nv))
        )
        self._q_red = np.zeros(model.nq)
        self._fast = self._bind_views()

    # ------------------------------------------------------------------ set-up helpers
    def _set_base(self, full: pin.Model, q_ref: np.ndarray) -> None:
        """Put the base body at (0, 0, base_height), identity orientation, in ``q_ref``."""
        spec = self._spec
        if not full.existFrame(spec.base_body):
            raise KinematicsError(f"base body {spec.base_body!r} missing from {spec.model_path.name}")
        frame = full.frames[full.getFrameId(spec.base_body)]
        jid = frame.parentJoint
        if jid == 0:
            return  # fixed-base model: the file places the base
        jm = full.joints[jid]
        if jm.shortname() != _FREE_FLYER or full.parents[jid] != 0:
            raise KinematicsError(
                f"base body {spec.base_body!r} must hang from the world by a free joint "
                f"(got {jm.shortname()} under joint {full.names[full.parents[jid]]!r})"
            )
        desired = pin.SE3(np.eye(3), np.array([0.0, 0.0, spec.base_height]))
        # oMbase = jointPlacement · M(q_ff) · frame.placement  =>  solve for M(q_ff).
        m_ff = full.jointPlacements[jid].inverse() * desired * frame.placement.inverse()
        q_ref[jm.idx_q : jm.idx_q + jm.nq] = pin.SE3ToXYZQUAT(m_ff)

    def _bind_views(self) -> bool:
        """Bind numpy views on Pinocchio's buffers; check them against getFrameJacobian."""
        data = self._data
        try:
            self._J6 = data.J  # (6, nv) view on data.J
            views = [data.oMf[int(f)].translation for f in self._frame_ids]
            addr = np.array([v.__array_interface__["data"][0] for v in views])
            strides = np.diff(addr)
            if len(views) > 1 and np.all(strides == strides[0]) and strides[0] > 0:
                # The 14 frames were appended consecutively: one strided view reads all.
                self._oMf_P = np.lib.stride_tricks.as_strided(
                    views[0], shape=(len(views), 3), strides=(int(strides[0]), views[0].strides[0]),
                    writeable=False,
                )
                self._oMf_rows = None
            else:
                self._oMf_P = None
                self._oMf_rows = views
        except Exception:  # pragma: no cover - depends on the Pinocchio build
            log.warning("Pinocchio buffers not exposed as views; using getFrameJacobian per endpoint")
            return False
        rng = np.random.default_rng(12345)
        for _ in range(3):
            q_red = self._check_q(rng.uniform(self._q_min, self._q_max)).copy()
            ends_fast, jac_fast = (a.copy() for a in self._compute_fast(q_red))
            ends_slow, jac_slow = self._compute_slow(q_red)
            if not (np.allclose(ends_fast, ends_slow, rtol=0, atol=1e-12)
                    and np.allclose(jac_fast, jac_slow, rtol=0, atol=1e-12)):
                log.warning("fast kinematics path disagrees with getFrameJacobian; using the slow path")
                return False
        return True

    def _place_static_capsules(self, model: pin.Model, spec: RobotSpec) -> dict[str, np.ndarray]:
        """World endpoints (2, 3) of each of ``spec.static_capsules``: its frame must be on a link no
        imitation joint moves (the base or a locked link beside it), so one placement holds forever."""
        data = model.createData()
        pin.framesForwardKinematics(model, data, pin.neutral(model))
        placed: dict[str, np.ndarray] = {}
        for name, cap in spec.static_capsules.items():
            if not model.existFrame(cap.frame):
                raise KinematicsError(f"static capsule {name!r}: frame {cap.frame!r} missing from {spec.model_path.name}")
            frame = model.frames[model.getFrameId(cap.frame)]
            if frame.parentJoint != 0:
                raise KinematicsError(
                    f"static capsule {name!r}: frame {cap.frame!r} moves with joint "
                    f"{model.names[frame.parentJoint]!r}; a static capsule must sit on a link no imitation joint moves"
                )
            oMf = data.oMf[model.getFrameId(cap.frame)]
            endpoints = np.array([oMf.act(np.asarray(p, dtype=np.float64)) for p in (cap.a, cap.b)])
            endpoints.flags.writeable = False
            placed[name] = endpoints
        return placed

    # ------------------------------------------------------------------ properties
    @property
    def static_endpoints(self) -> dict[str, np.ndarray]:
        """Static capsule name → its endpoints (2, 3) m in the world frame (read-only; fixed)."""
        return dict(self._static_endpoints)

    @property
    def spec(self) -> RobotSpec:
        return self._spec

    @property
    def model(self) -> pin.Model:
        """The reduced (8-joint, fixed-base) Pinocchio model, with the endpoint frames."""
        return self._model

    @property
    def joint_names(self) -> tuple[str, ...]:
        return self._joint_names

    @property
    def nq(self) -> int:
        return len(self._joint_names)

    @property
    def q_home(self) -> np.ndarray:
        """(8,) home configuration (read-only)."""
        return self._q_home

    @property
    def q_min(self) -> np.ndarray:
        """(8,) lower limits: the model's range unless overridden by ``spec.limits`` (read-only)."""
        return self._q_min

    @property
    def q_max(self) -> np.ndarray:
        """(8,) upper limits (read-only)."""
        return self._q_max

    @property
    def capsule_names(self) -> tuple[str, ...]:
        return CAPSULE_NAMES

    @property
    def radii(self) -> np.ndarray:
        """(7,) capsule radii in ``capsule_names`` order (read-only)."""
        return self._radii

    @property
    def capsule_local(self) -> np.ndarray:
        """(7, 2, 3) endpoints a, b in each capsule's own frame (read-only)."""
        return self._capsule_local

    @property
    def capsule_moving(self) -> np.ndarray:
        """(7, 2) bool: the endpoint moves with at least one imitation joint."""
        return self._moving.copy()

    @property
    def self_pairs(self) -> np.ndarray:
        """(P, 2) capsule indices of the spec's self-collision pairs (read-only)."""
        return self._self_pairs

    @property
    def uses_fast_path(self) -> bool:
        return self._fast

    # ------------------------------------------------------------------ kinematics
    def _check_q(self, q: np.ndarray) -> np.ndarray:
        q = np.asarray(q, dtype=np.float64)
        if q.shape != (self.nq,):
            raise KinematicsError(f"q must have shape ({self.nq},), got {q.shape}")
        if not math.isfinite(q.dot(q)):  # NaN/Inf (or an absurd |q| > 1e154) anywhere
            raise KinematicsError(f"q must be finite, got {q}")
        if self._identity_order:
            return q
        self._q_red[self._idx_q] = q
        return self._q_red

    def compute(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Capsule endpoints and their point Jacobians at ``q`` (8,).

        Returns:
            endpoints: (7, 2, 3) world positions of [a, b] of each capsule (capsule_names order).
            jacobians: (7, 2, 3, 8) ``d endpoint / d q`` in world axes.
            Both are internal buffers, overwritten by the next call.
        """
        q_red = self._check_q(q)
        if self._fast:
            return self._compute_fast(q_red)
        ends, jac = self._compute_slow(q_red)
        self._endpoints[...] = ends
        self._jacobians[...] = jac
        return self._endpoints, self._jacobians

    def _compute_fast(self, q_red: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        model, data = self._model, self._data
        pin.computeJointJacobians(model, data, q_red)
        pin.updateFramePlacements(model, data)
        P, Paug = self._P, self._Paug
        if self._oMf_P is not None:
            np.copyto(P, self._oMf_P)
        else:
            for i, row in enumerate(self._oMf_rows):
                P[i] = row
        Paug[:, 1:] = P
        J6 = self._J6
        np.copyto(self._N_v, J6[:3])
        np.matmul(self._neg_eps, J6[3:], out=self._N_w)
        Jflat = self._Jflat
        np.matmul(Paug, self._N, out=Jflat)
        np.multiply(Jflat, self._mask_flat, out=Jflat)
        if not self._identity_order:
            n_end, nv = len(self._frame_ids), model.nv
            self._jacobians.reshape(n_end, 3, nv)[...] = Jflat.reshape(n_end, 3, nv)[..., self._idx_v]
        return self._endpoints, self._jacobians

    def _compute_slow(self, q_red: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Reference path: one getFrameJacobian per endpoint (also used to check the fast one)."""
        model, data = self._model, self._data
        pin.computeJointJacobians(model, data, q_red)
        pin.updateFramePlacements(model, data)
        n_end = len(self._frame_ids)
        ends = np.empty((n_end, 3))
        jac = np.empty((n_end, 3, model.nv))
        for e, fid in enumerate(self._frame_ids):
            fid = int(fid)
            ends[e] = data.oMf[fid].translation
            jac[e] = pin.getFrameJacobian(model, data, fid, pin.ReferenceFrame.LOCAL_WORLD_ALIGNED)[:3]
        if not self._identity_order:
            jac = jac[..., self._idx_v]
        shape = self._endpoints.shape
        return ends.reshape(shape), jac.reshape(shape + (model.nv,))

    def capsule_frames(self) -> tuple[np.ndarray, np.ndarray]:
        """World rotations (7, 3, 3) of the capsules' bodies and their angular Jacobians (7, 3, 8)
        (``dω/dq`` in world axes), at the configuration of the last :meth:`compute` call.

        With them a point p fixed in capsule c's body has the Jacobian
        J_p = J_a − [p − a]_× J_ω  (LOCAL_WORLD_ALIGNED), a being the capsule's endpoint ``a``
        whose Jacobian :meth:`compute` returned: what a box witness point needs
        (:mod:`services.safety.barriers.boxes`). Returns new arrays.
        """
        model, data = self._model, self._data
        n_cap = len(CAPSULE_NAMES)
        rotations = np.empty((n_cap, 3, 3))
        angular = np.empty((n_cap, 3, model.nv))
        for c in range(n_cap):
            fid = int(self._frame_ids[2 * c])  # endpoint a's frame: the body's rotation
            rotations[c] = data.oMf[fid].rotation
            angular[c] = pin.getFrameJacobian(model, data, fid, pin.ReferenceFrame.LOCAL_WORLD_ALIGNED)[3:]
        if not self._identity_order:
            angular = angular[..., self._idx_v]
        return rotations, angular

    def frame_position(self, name: str, q: np.ndarray) -> np.ndarray:
        """World position (3,) of any body/joint/frame ``name`` of the reduced model at ``q``."""
        if not self._model.existFrame(name):
            raise KinematicsError(f"no frame named {name!r} in the reduced model of {self._spec.model_path.name}")
        q_red = self._check_q(q)
        pin.framesForwardKinematics(self._model, self._aux_data, q_red)
        return np.array(self._aux_data.oMf[self._model.getFrameId(name)].translation)

    def frame_placement(self, name: str, q: np.ndarray) -> pin.SE3:
        """World placement (a copy) of frame ``name`` at ``q``."""
        if not self._model.existFrame(name):
            raise KinematicsError(f"no frame named {name!r} in the reduced model of {self._spec.model_path.name}")
        q_red = self._check_q(q)
        pin.framesForwardKinematics(self._model, self._aux_data, q_red)
        return pin.SE3(self._aux_data.oMf[self._model.getFrameId(name)])

    def __repr__(self) -> str:
        return (
            f"RobotKinematics({self._spec.name!r}, model={self._spec.model_path.name!r}, "
            f"joints={len(self._joint_names)}, capsules={len(CAPSULE_NAMES)})"
        )
