"""The robot drawn from its description's MJCF: one triangle mesh per body, posed by MuJoCo's FK.

:class:`RobotMesh` reads the MJCF named by the robot description (mesh geoms: their vertices and
faces; primitives — box, sphere, capsule, cylinder, ellipsoid — tessellated here) and merges the
visible geoms of each body into one mesh in that body's frame (metres). :meth:`RobotMesh.pose`
puts the 8 imitation joints at ``q`` (rad, the description's order), every other joint at its
home value and the base body at ``(0, 0, base_height)`` with identity orientation — the robot
frame of every message (z up) — and returns each body's world pose and the 7 CBF capsules'
endpoints (7, 2, 3) m, computed from the same body poses and the description's capsule segments.

Needs only ``mujoco`` (no Pinocchio, no executor): the viewer stays independent of the other
services.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np

from services.viewer.errors import ViewerError
from shared.robot_spec import RobotSpec

#: Geom groups drawn (MuJoCo's viewer shows 0–2 by default; our model's visual class is group 2).
VISIBLE_GROUPS = (0, 1, 2)
_SEGMENTS = 16  # tessellation around an axis


class RobotMeshError(ViewerError, ValueError):
    """The MJCF cannot be loaded or does not match the robot description (message says why)."""


@dataclass(frozen=True)
class BodyMesh:
    """One body's visible geoms merged: ``vertices`` (V, 3) m and ``faces`` (F, 3) in the body frame,
    per-vertex ``normals`` (V, 3) and one RGBA ``color`` (the first geom's, 0–255)."""

    body: str
    vertices: np.ndarray
    faces: np.ndarray
    normals: np.ndarray
    color: tuple[int, int, int, int]


@dataclass(frozen=True)
class RobotPose:
    """World poses of :attr:`RobotMesh.bodies`: ``translations`` (B, 3) m, ``quaternions`` (B, 4)
    xyzw (Rerun's order); ``capsules`` (7, 2, 3) m, the CBF capsules' segment endpoints."""

    translations: np.ndarray
    quaternions: np.ndarray
    capsules: np.ndarray


def _sphere(radius: np.ndarray, n: int = _SEGMENTS) -> tuple[np.ndarray, np.ndarray]:
    """A UV sphere (ellipsoid with per-axis ``radius`` (3,)): vertices, faces."""
    theta = np.linspace(0.0, np.pi, n // 2 + 1)
    phi = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    t, p = np.meshgrid(theta, phi, indexing="ij")
    unit = np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], axis=-1).reshape(-1, 3)
    return unit * radius, _grid_faces(len(theta), n)


def _grid_faces(rows: int, cols: int) -> np.ndarray:
    """Two triangles per cell of a rows × cols vertex grid that wraps around in columns."""
    r, c = np.meshgrid(np.arange(rows - 1), np.arange(cols), indexing="ij")
    a = r * cols + c
    b = r * cols + (c + 1) % cols
    d, e = a + cols, b + cols
    return np.concatenate([np.stack([a, d, b], -1).reshape(-1, 3), np.stack([b, d, e], -1).reshape(-1, 3)])


def _capsule(radius: float, half: float, n: int = _SEGMENTS) -> tuple[np.ndarray, np.ndarray]:
    """A capsule along z (segment ±``half``) of ``radius``: a sphere split at its equator."""
    vertices, faces = _sphere(np.full(3, radius), n)
    vertices = vertices.copy()
    vertices[:, 2] += np.where(vertices[:, 2] >= 0.0, half, -half)
    return vertices, faces


def _cylinder(radius: float, half: float, n: int = _SEGMENTS) -> tuple[np.ndarray, np.ndarray]:
    """A closed cylinder along z: two rings and two cap centres."""
    phi = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    ring = np.stack([radius * np.cos(phi), radius * np.sin(phi)], -1)
    vertices = np.concatenate([np.c_[ring, np.full(n, -half)], np.c_[ring, np.full(n, half)],
                               [[0, 0, -half], [0, 0, half]]])
    i = np.arange(n)
    j = (i + 1) % n
    side = np.concatenate([np.stack([i, j, i + n], -1), np.stack([j, j + n, i + n], -1)])
    caps = np.concatenate([np.stack([np.full(n, 2 * n), j, i], -1), np.stack([np.full(n, 2 * n + 1), i + n, j + n], -1)])
    return vertices, np.concatenate([side, caps])


def _box(half: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float) * half
    faces = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                      [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])
    return corners, faces


def geom_triangles(model: mujoco.MjModel, geom: int) -> tuple[np.ndarray, np.ndarray] | None:
    """Geom ``geom``'s triangles in its own frame (vertices (V, 3) m, faces (F, 3)); None for types
    that are not drawn (planes, height fields, lines)."""
    kind, size = int(model.geom_type[geom]), model.geom_size[geom]
    t = mujoco.mjtGeom
    if kind == t.mjGEOM_MESH:
        mesh = int(model.geom_dataid[geom])
        v0, nv = model.mesh_vertadr[mesh], model.mesh_vertnum[mesh]
        f0, nf = model.mesh_faceadr[mesh], model.mesh_facenum[mesh]
        return model.mesh_vert[v0:v0 + nv].astype(np.float64), model.mesh_face[f0:f0 + nf].astype(np.int64)
    if kind == t.mjGEOM_BOX:
        return _box(size)
    if kind == t.mjGEOM_SPHERE:
        return _sphere(np.full(3, size[0]))
    if kind == t.mjGEOM_ELLIPSOID:
        return _sphere(size.copy())
    if kind == t.mjGEOM_CAPSULE:
        return _capsule(size[0], size[1])
    if kind == t.mjGEOM_CYLINDER:
        return _cylinder(size[0], size[1])
    return None


def _rotation(quat_wxyz: np.ndarray) -> np.ndarray:
    out = np.empty(9)
    mujoco.mju_quat2Mat(out, quat_wxyz)
    return out.reshape(3, 3)


def _vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    tri = vertices[faces]
    face_n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normals = np.zeros_like(vertices)
    for k in range(3):
        np.add.at(normals, faces[:, k], face_n)
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    return np.divide(normals, length, out=np.zeros_like(normals), where=length > 0)


class RobotMesh:
    """The robot description's MJCF as drawable body meshes, posed by joint angles (module docstring).

    Raises :class:`RobotMeshError` when the model cannot be loaded or lacks a joint or capsule
    frame the description names.
    """

    def __init__(self, spec: RobotSpec, model_path: str | Path | None = None) -> None:
        path = Path(model_path or spec.model)
        try:
            self.model = mujoco.MjModel.from_xml_path(str(path))
        except Exception as exc:  # ValueError from MuJoCo's parser, with its own message
            raise RobotMeshError(f"cannot load robot model {path}: {exc}") from None
        self.spec = spec
        self.data = mujoco.MjData(self.model)
        self.joint_qpos = np.array([self._qpos_address(j) for j in spec.imitation_joints], dtype=np.intp)
        self.home_qpos = self._home_qpos()
        self.meshes = self._body_meshes()
        self.bodies = tuple(mesh.body for mesh in self.meshes)
        self._body_ids = np.array([self.model.body(name).id for name in self.bodies], dtype=np.intp)
        self._capsule_body, self._capsule_ab = self._capsule_frames()

    def _qpos_address(self, joint: str) -> int:
        try:
            return int(self.model.joint(joint).qposadr[0])
        except KeyError:
            raise RobotMeshError(f"robot model has no joint {joint!r} (robot description {self.spec.name})") from None

    def _home_qpos(self) -> np.ndarray:
        qpos = self.model.qpos0.copy()
        for j in range(self.model.njnt):
            if self.model.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE:  # the base: at base_height, upright
                adr = self.model.jnt_qposadr[j]
                qpos[adr:adr + 7] = [0.0, 0.0, self.spec.base_height, 1.0, 0.0, 0.0, 0.0]
        for name, value in self.spec.home.items():
            qpos[self._qpos_address(name)] = value
        return qpos

    def _body_meshes(self) -> tuple[BodyMesh, ...]:
        m = self.model
        parts: dict[int, list[tuple[np.ndarray, np.ndarray]]] = {}
        colors: dict[int, tuple[int, int, int, int]] = {}
        for g in range(m.ngeom):
            if m.geom_group[g] not in VISIBLE_GROUPS or m.geom_rgba[g, 3] <= 0.0 or m.geom_bodyid[g] == 0:
                continue
            triangles = geom_triangles(m, g)
            if triangles is None:
                continue
            vertices, faces = triangles
            world = vertices @ _rotation(m.geom_quat[g]).T + m.geom_pos[g]  # geom frame → body frame
            body = int(m.geom_bodyid[g])
            parts.setdefault(body, []).append((world, faces))
            colors.setdefault(body, tuple(int(round(255 * c)) for c in m.geom_rgba[g]))  # type: ignore[arg-type]
        meshes = []
        for body, items in parts.items():
            offsets = np.cumsum([0] + [len(v) for v, _ in items[:-1]])
            vertices = np.concatenate([v for v, _ in items])
            faces = np.concatenate([f + o for (_, f), o in zip(items, offsets)])
            meshes.append(BodyMesh(m.body(body).name, vertices, faces, _vertex_normals(vertices, faces), colors[body]))
        if not meshes:
            raise RobotMeshError(f"robot model {self.spec.model} has no visible geometry in groups {VISIBLE_GROUPS}")
        return tuple(meshes)

    def _capsule_frames(self) -> tuple[np.ndarray, np.ndarray]:
        from shared.names import CAPSULE_NAMES

        bodies, ab = [], []
        for name in CAPSULE_NAMES:
            capsule = self.spec.capsules[name]
            try:
                bodies.append(self.model.body(capsule.frame).id)
            except KeyError:
                raise RobotMeshError(f"capsule {name}: robot model has no body {capsule.frame!r}") from None
            ab.append([capsule.a, capsule.b])
        return np.array(bodies, dtype=np.intp), np.array(ab, dtype=np.float64)

    @property
    def capsule_radii(self) -> np.ndarray:
        """The description's capsule radii (7,) m, in CAPSULE_NAMES order."""
        from shared.names import CAPSULE_NAMES

        return np.array([self.spec.capsules[name].radius for name in CAPSULE_NAMES])

    def pose(self, q: np.ndarray) -> RobotPose:
        """Body poses and CBF capsules with the imitation joints at ``q`` (8,) rad."""
        q = np.asarray(q, dtype=np.float64)
        if q.shape != (len(self.joint_qpos),) or not np.isfinite(q).all():
            raise ValueError(f"q must be {len(self.joint_qpos)} finite joint angles, got shape {q.shape}")
        self.data.qpos[:] = self.home_qpos
        self.data.qpos[self.joint_qpos] = q
        mujoco.mj_kinematics(self.model, self.data)
        xpos, xquat, xmat = self.data.xpos, self.data.xquat, self.data.xmat
        ids = self._body_ids
        quats = xquat[ids][:, [1, 2, 3, 0]].copy()  # MuJoCo wxyz → xyzw
        rot = xmat[self._capsule_body].reshape(-1, 3, 3)
        capsules = np.einsum("cij,ckj->cki", rot, self._capsule_ab) + xpos[self._capsule_body][:, None, :]
        return RobotPose(xpos[ids].copy(), quats, capsules)
