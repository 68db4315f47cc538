"""The MuJoCo simulation's contact computations on a compiled model and its data (architecture §7, §10).

The contact *types* are the executor interface's (:mod:`services.executor.contacts`); this module
computes them from MuJoCo:

- **robot–robot**: body pairs from MuJoCo's contact list; pairs already touching at home
  (:func:`robot_pairs_in_contact`, excluded from the physics by the model) are measured with
  ``mj_geomDistance`` instead and reported once they press more than :data:`HOME_PRESS_TOLERANCE`
  deeper than at home;
- **robot–human**: ``mj_geomDistance`` between every placed human capsule and every *surface* geom
  of the robot (:func:`surface_geoms`), with the robot's own closing speed at the deepest point;
  :func:`body_contacts` merges them per (robot body, capsule).

The robot's *surface* (what a person could touch) is every collision geom of the robot plus every
visual geom that no collision geom of its body duplicates (same shape, size and pose): the real
G1 model's rubber hands are visual-only meshes, so without them no hand contact would ever be
counted. Distances to surfaces need no contact forces, and they also cover the architecture §10 trap
(MuJoCo reports no contact between a mocap capsule and the welded, DOF-less pelvis).
Units SI: metres, seconds.
"""

from __future__ import annotations

import mujoco
import numpy as np

from services.executor.contacts import BodyContact, SurfaceContact
from shared.names import CAPSULE_NAMES

__all__ = ["HOME_PRESS_TOLERANCE", "ContactMeter", "body_contacts", "robot_pairs_in_contact", "surface_geoms"]

#: A pair touching at home is a contact once it presses this much deeper than at home (m).
HOME_PRESS_TOLERANCE = 1e-3

#: One body pair touching at home: its names, its collision geom pairs and its penetration at home (m).
_HomePair = tuple[tuple[str, str], list[tuple[int, int]], float]


def surface_geoms(model: mujoco.MjModel, robot_geom: np.ndarray, collides: np.ndarray) -> np.ndarray:
    """Robot geoms a person could touch: every collision geom, and every visual geom that no
    collision geom of the same body duplicates (same type, mesh, size and pose)."""
    surface = []
    for g in np.flatnonzero(robot_geom):
        if not collides[g]:
            twins = np.flatnonzero(robot_geom & collides & (model.geom_bodyid == model.geom_bodyid[g]))
            if any(
                model.geom_type[c] == model.geom_type[g] and model.geom_dataid[c] == model.geom_dataid[g]
                and np.allclose(model.geom_size[c], model.geom_size[g]) and np.allclose(model.geom_pos[c], model.geom_pos[g])
                and np.allclose(model.geom_quat[c], model.geom_quat[g])
                for c in twins
            ):
                continue
        surface.append(g)
    return np.array(surface, dtype=np.int64)


def robot_pairs_in_contact(model: mujoco.MjModel, qpos: np.ndarray, robot_body: np.ndarray) -> list[tuple[str, str]]:
    """Robot–robot body pairs in contact at ``qpos`` (names, each pair sorted)."""
    data = mujoco.MjData(model)
    data.qpos[:] = qpos
    mujoco.mj_forward(model, data)
    pairs = set()
    for g1, g2 in data.contact.geom[: data.ncon]:
        b1, b2 = model.geom_bodyid[g1], model.geom_bodyid[g2]
        if robot_body[b1] and robot_body[b2]:
            pairs.add(tuple(sorted((model.body(b1).name, model.body(b2).name))))
    return sorted(pairs)


def body_contacts(surface: tuple[SurfaceContact, ...]) -> tuple[BodyContact, ...]:
    """Surface contacts merged per (robot body, capsule), deepest first kept; sorted by names."""
    deepest: dict[tuple[str, str], float] = {}
    for c in surface:
        deepest[(c.robot_body, c.capsule)] = max(deepest.get((c.robot_body, c.capsule), 0.0), c.depth)
    return tuple(sorted(BodyContact(a, b, depth) for (a, b), depth in deepest.items()))


class ContactMeter:
    """The contacts of one compiled scene, measured on its data after a step.

    Args:
        model: the compiled scene (:func:`~services.executor.mujoco.model.build_model`).
        data: its data at the home pose (the home pairs' penetration at home is taken from it).
        robot_body: per body, whether it is the robot's.
        human_geoms: per person and capsule (CAPSULE_NAMES order), the capsule's geom id.
        home_contacts: robot–robot body pairs touching at home (excluded from the physics).
    """

    def __init__(self, model: mujoco.MjModel, data: mujoco.MjData, robot_body: np.ndarray, human_geoms: np.ndarray,
                 home_contacts: tuple[tuple[str, str], ...]) -> None:
        self.model = model
        self._body_names = [model.body(b).name for b in range(model.nbody)]
        collides = (model.geom_contype != 0) | (model.geom_conaffinity != 0)
        robot_geom = robot_body[model.geom_bodyid]
        self._robot_collider = robot_geom & collides
        #: Robot geoms a person could touch (collision geoms + visual-only surfaces such as hands).
        self.surface_geoms = surface_geoms(model, robot_geom, collides)
        self._human_geoms = human_geoms
        self._capsule_of_geom = {int(g): c for row in human_geoms for g, c in zip(row, CAPSULE_NAMES)}
        self._jacp = np.zeros((3, model.nv))
        self._home_pairs = [self._home_pair(data, a, b) for a, b in home_contacts]

    def _home_pair(self, data: mujoco.MjData, a: str, b: str) -> _HomePair:
        m = self.model
        geoms_a = [int(g) for g in np.flatnonzero((m.geom_bodyid == m.body(a).id) & self._robot_collider)]
        geoms_b = [int(g) for g in np.flatnonzero((m.geom_bodyid == m.body(b).id) & self._robot_collider)]
        geom_pairs = [(ga, gb) for ga in geoms_a for gb in geoms_b]
        depth = max((-mujoco.mj_geomDistance(m, data, ga, gb, 0.0, None) for ga, gb in geom_pairs), default=0.0)
        return (a, b), geom_pairs, depth

    def robot_robot(self, data: mujoco.MjData) -> tuple[BodyContact, ...]:
        """Robot–robot body pairs in contact: from MuJoCo's contact list, and the pairs touching at
        home once they press :data:`HOME_PRESS_TOLERANCE` deeper than at home; sorted by names."""
        m, d = self.model, data
        robot_robot: dict[tuple[str, str], float] = {}
        names = self._body_names
        for (g1, g2), dist in zip(d.contact.geom[: d.ncon], d.contact.dist[: d.ncon]):
            if dist < 0.0 and self._robot_collider[g1] and self._robot_collider[g2]:
                pair = tuple(sorted((names[m.geom_bodyid[g1]], names[m.geom_bodyid[g2]])))
                robot_robot[pair] = max(robot_robot.get(pair, 0.0), -float(dist))
        for pair, geom_pairs, home_depth in self._home_pairs:
            depth = max(-mujoco.mj_geomDistance(m, d, ga, gb, 0.0, None) for ga, gb in geom_pairs)
            if depth > home_depth + HOME_PRESS_TOLERANCE:
                robot_robot[pair] = depth - home_depth  # pressed beyond the home contact
        return tuple(sorted(BodyContact(a, b, depth) for (a, b), depth in robot_robot.items()))

    def robot_human(self, data: mujoco.MjData, person: int, placed: np.ndarray, segments: np.ndarray,
                    radii: np.ndarray) -> tuple[SurfaceContact, ...]:
        """Every (robot surface geom, placed capsule of ``person``) pair that penetrates:
        ``mj_geomDistance`` (no contact forces), with the robot's own velocity at its deepest point
        along the normal, −nᵀ J_p q̇ (n from the person toward the robot). ``placed``, ``segments``
        (endpoints, m) and ``radii`` (m) are the person's, per capsule.

        A broad phase comes first (``mj_geomDistance`` has none of its own): a surface geom is
        examined only if its bounding sphere comes within the capsule's radius of its segment.
        """
        if not placed.any() or not len(self.surface_geoms):
            return ()
        m, d = self.model, data
        humans = self._human_geoms[person][placed]
        surface = self.surface_geoms
        a, b = segments[placed, 0], segments[placed, 1]  # (H, 3)
        axis = b - a
        centres = d.geom_xpos[surface]  # (S, 3)
        along = np.einsum("hsk,hk->hs", centres[None] - a[:, None], axis) / np.maximum((axis * axis).sum(1), 1e-12)[:, None]
        closest = a[:, None] + np.clip(along, 0.0, 1.0)[..., None] * axis[:, None]
        gap = np.linalg.norm(centres[None] - closest, axis=2)
        near = gap <= radii[placed, None] + m.geom_rbound[None, surface]
        found = []
        fromto = np.zeros(6)
        for hi, si in zip(*np.nonzero(near)):
            h, s = int(humans[hi]), int(surface[si])
            dist = mujoco.mj_geomDistance(m, d, s, h, 0.0, fromto)
            if dist >= 0.0:
                continue
            point = fromto[:3].copy()
            toward_person = fromto[3:] - point
            length = float(np.linalg.norm(toward_person))
            if length > 1e-9:  # fromto runs from the robot's surface to the person's, signed by dist
                normal = -toward_person / (length * np.sign(dist))
            else:  # touching at one point: fall back to the geom centres
                normal = d.geom_xpos[s] - d.geom_xpos[h]
                normal = normal / max(float(np.linalg.norm(normal)), 1e-12)
            body = int(m.geom_bodyid[s])
            found.append(SurfaceContact(self._body_names[body], self._capsule_of_geom[h], -float(dist), point,
                                        normal, self._closing(d, body, point, normal, d.qvel)))
        return tuple(found)

    def closing_speed(self, data: mujoco.MjData, contact: SurfaceContact, qvel: np.ndarray) -> float:
        """The speed (m/s) at which ``contact``'s robot point would move into the person if the
        robot's joints moved at ``qvel`` (nv,) from its current pose: −nᵀ J_p(point) q̇, J_p the
        translational Jacobian of the contact's point on its robot body (positive: closing). With
        the simulated q̇ this is :attr:`SurfaceContact.closing_speed`."""
        body = self._body_names.index(contact.robot_body)
        return self._closing(data, body, contact.point, contact.normal, qvel)

    def _closing(self, data: mujoco.MjData, body: int, point: np.ndarray, normal: np.ndarray, qvel: np.ndarray) -> float:
        mujoco.mj_jac(self.model, data, self._jacp, None, point, body)
        return -float(normal @ (self._jacp @ qvel))
