"""The real robot's link meshes as point clouds, for tests that hold our primitives to them."""

from __future__ import annotations

from collections.abc import Collection

import mujoco
import numpy as np


def mesh_points(m: mujoco.MjModel, d: mujoco.MjData, bodies: Collection[str], frame: str,
                skip_meshes: Collection[str] = ()) -> np.ndarray:
    """Every vertex (n, 3) of the visual meshes (geom group 2) on ``bodies``, in the coordinates of
    body ``frame`` (m), at the pose of ``d`` (after ``mj_kinematics``); meshes named in
    ``skip_meshes`` are left out."""
    fb = m.body(frame).id
    rotation, origin = d.xmat[fb].reshape(3, 3), d.xpos[fb]
    points = []
    for g in range(m.ngeom):
        if m.geom_type[g] != mujoco.mjtGeom.mjGEOM_MESH or m.geom_group[g] != 2:
            continue
        if m.body(m.geom_bodyid[g]).name not in bodies or m.mesh(m.geom_dataid[g]).name in skip_meshes:
            continue
        mid = m.geom_dataid[g]
        v = m.mesh_vert[m.mesh_vertadr[mid]: m.mesh_vertadr[mid] + m.mesh_vertnum[mid]]
        world = v @ d.geom_xmat[g].reshape(3, 3).T + d.geom_xpos[g]
        points.append((world - origin) @ rotation)
    return np.vstack(points)
