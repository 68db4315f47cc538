"""The paper's Fig. 4 for this robot: the four collision models with one line per CBF constraint.

Spheres (k = 0), spheres (k = 1), boxes and capsules (:mod:`services.safety.barriers`) fitted to
the G1 and to the person of the side-by-side arm raise, at the moment ``T_SHOW`` s into the
scenario, the robot where the capsule CBF put it (:func:`bench.geometry.track`). The robot is the
executor's MuJoCo model; robot colliders are drawn translucent blue, the person's orange, and
every row of the default pair set (the robot's self pairs + robot × person) as a yellow line
between the closest points of its two colliders. A box is drawn as its bounding box (MuJoCo has
no rounded box): its faces are exact, its edges and corners stand up to (√3 − 1) r/2 outside the
collider, where a witness point then lies just inside the drawn box. Rendered offscreen
(``MUJOCO_GL=egl``).

    python -m bench.geometry_figure [--out docs/figures/collision_geometries.png]
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

import matplotlib  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import mujoco  # noqa: E402
import numpy as np  # noqa: E402

from bench.geometry import GEOMETRIES, configured, scenario_human, title, track  # noqa: E402
from services.executor.mujoco.model import PDGains  # noqa: E402
from services.executor.mujoco.sim import SimRobot  # noqa: E402
from services.safety.assembly import build_pipeline  # noqa: E402
from services.safety.barriers.pairs import CollisionGeometry  # noqa: E402
from services.safety.barriers.boxes import BoxBarrier  # noqa: E402
from services.safety.barriers.spheres import SphereBarrier  # noqa: E402
from services.safety.kinematics import RobotKinematics  # noqa: E402
from services.safety.pairs import N_ROBOT  # noqa: E402
from services.safety.human_memory import external_capsules  # noqa: E402
from shared.config import StackConfig, load_config  # noqa: E402
from shared.robot_spec import configured_robot_spec  # noqa: E402

OUT = Path(__file__).resolve().parent.parent / "docs" / "figures" / "collision_geometries.png"
SCENARIO, T_SHOW = "side-by-side-arm-raise", 3.3  # s: the near arm sweeps forward in front of the robot
WIDTH, HEIGHT = 480, 600
ROBOT_RGBA, HUMAN_RGBA = (0.15, 0.45, 0.95, 0.35), (0.95, 0.55, 0.2, 0.35)
LINE_RGBA, LINE_WIDTH = (1.0, 0.85, 0.0, 0.45), 0.0008  # m
CAMERA = {"azimuth": 155.0, "elevation": -14.0, "distance": 3.2}
HEADLIGHT_AMBIENT, HEADLIGHT_DIFFUSE = (0.45, 0.45, 0.45), (0.6, 0.6, 0.6)
MAX_GEOM = 15000


def _add(scene: mujoco.MjvScene, kind: mujoco.mjtGeom, size, pos, mat, rgba) -> None:
    if scene.ngeom < scene.maxgeom:
        mujoco.mjv_initGeom(scene.geoms[scene.ngeom], kind, np.asarray(size, float), np.asarray(pos, float),
                            np.asarray(mat, float).ravel(), np.asarray(rgba, np.float32))
        scene.ngeom += 1


def _colour(is_robot: bool) -> tuple[float, ...]:
    return ROBOT_RGBA if is_robot else HUMAN_RGBA


def add_colliders(scene: mujoco.MjvScene, barrier: CollisionGeometry, capsules: np.ndarray, radii: np.ndarray) -> None:
    """The backend's colliders: its spheres, its boxes, or the capsules (robot first, then the person)."""
    if isinstance(barrier, SphereBarrier):
        centres, rho = barrier.spheres
        for s, (c, r) in enumerate(zip(centres, rho)):
            _add(scene, mujoco.mjtGeom.mjGEOM_SPHERE, [r, 0, 0], c, np.eye(3), _colour(s < barrier.n_robot_spheres))
    elif isinstance(barrier, BoxBarrier):
        for b, (c, R, half) in enumerate(zip(barrier.centres, barrier.rotations, barrier.half_extents)):
            _add(scene, mujoco.mjtGeom.mjGEOM_BOX, half, c, R, _colour(b < N_ROBOT))
    else:
        for i, ((a, b), r) in enumerate(zip(capsules, radii)):
            _add(scene, mujoco.mjtGeom.mjGEOM_CAPSULE, [r, 0, 0], np.zeros(3), np.eye(3), _colour(i < N_ROBOT))
            mujoco.mjv_connector(scene.geoms[scene.ngeom - 1], mujoco.mjtGeom.mjGEOM_CAPSULE, r, a, b)


def add_lines(scene: mujoco.MjvScene, witness: np.ndarray) -> None:
    """One line per CBF row between its two closest points."""
    for a, b in witness:
        if np.linalg.norm(b - a) < 1e-6:
            continue
        _add(scene, mujoco.mjtGeom.mjGEOM_CAPSULE, [LINE_WIDTH, 0, 0], np.zeros(3), np.eye(3), LINE_RGBA)
        mujoco.mjv_connector(scene.geoms[scene.ngeom - 1], mujoco.mjtGeom.mjGEOM_CAPSULE, LINE_WIDTH, a, b)


def render(conf: StackConfig, out: Path) -> Path:
    kinematics = RobotKinematics(configured_robot_spec(conf))
    human = scenario_human(conf, SCENARIO)
    q = track(configured(conf, "capsule", None), human, seconds=T_SHOW, kinematics=kinematics).q_cbf[-1]
    state = human.states[int(np.searchsorted(human.t, T_SHOW, side="right")) - 1]

    sim = SimRobot(kinematics.spec, PDGains.from_config(conf.executor))
    model, data = sim.model, sim.data
    model.vis.global_.offwidth, model.vis.global_.offheight = max(model.vis.global_.offwidth, WIDTH), max(model.vis.global_.offheight, HEIGHT)
    model.stat.extent = 3.0  # the parked person capsules would inflate the clipping range
    model.vis.headlight.ambient[:], model.vis.headlight.diffuse[:] = HEADLIGHT_AMBIENT, HEADLIGHT_DIFFUSE
    for name, value in zip(kinematics.joint_names, q):
        data.qpos[model.joint(name).qposadr[0]] = value
    mujoco.mj_forward(model, data)
    option = mujoco.MjvOption()  # the person's own capsule geoms (group 4) stay hidden: drawn as colliders
    camera = mujoco.MjvCamera()
    camera.lookat[:] = [0.0, 0.42, kinematics.spec.base_height + 0.1]
    camera.azimuth, camera.elevation, camera.distance = CAMERA["azimuth"], CAMERA["elevation"], CAMERA["distance"]

    panels = []
    with mujoco.Renderer(model, HEIGHT, WIDTH, max_geom=MAX_GEOM) as renderer:
        for geometry, k in GEOMETRIES:
            pipeline = build_pipeline(configured(conf, geometry, k), kinematics=kinematics)
            capsules = external_capsules(state, pipeline.pairs.n_external, False)
            pipeline.barrier.set_external(*capsules)
            rows = pipeline.filter.rows_at(q)
            robot, _ = kinematics.compute(q)
            stack = np.concatenate([robot, capsules[0]])
            radii = np.concatenate([pipeline.barrier.robot_radii, capsules[1]])
            renderer.update_scene(data, camera, option)
            add_colliders(renderer.scene, pipeline.barrier, stack, radii)
            add_lines(renderer.scene, pipeline.barrier.witness_points()[rows.enabled])
            panels.append((title(geometry, k), int(rows.enabled.sum()), renderer.render().copy()))

    fig, axes = plt.subplots(1, len(panels), figsize=(4 * len(panels), 5.3), constrained_layout=True)
    for ax, (name, count, image) in zip(axes, panels):
        ax.imshow(image)
        ax.set_title(f"{name}: {count} constraints", fontsize=11)
        ax.axis("off")
    fig.suptitle(f"Collision geometries on the G1 beside a person ({SCENARIO}, t = {T_SHOW} s); "
                 "blue: robot colliders, orange: the person's, yellow: one line per CBF constraint", fontsize=10)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=100)
    plt.close(fig)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(prog="python -m bench.geometry_figure", description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=OUT, help=f"PNG file (default: {OUT})")
    print(f"wrote {render(load_config(environ={}), parser.parse_args().out)}")


if __name__ == "__main__":
    main()
