"""``snapshot.png``: MuJoCo's offscreen picture of the worst moment (the paper's Fig. 2a/3a).

The worst moment is the control step with the smallest h of the run without the CBF layer (where
the unsafe robot is deepest inside a barrier; if it never goes below 0, the CBF run's smallest h).
At that step the safe robot (the CBF run's simulated pose) is drawn solid, the unsafe one (the
run without CBF) as a translucent red ghost wherever it differs, the person's 7 capsules in skin
colour (the perceived, delayed ones translucent blue), and the closest-point segments of the pairs binding in the CBF-QP in yellow (if none
binds at that step: the three pairs closest to their boundary). Two views: front and top.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import mujoco  # noqa: E402
import numpy as np  # noqa: E402

from safemimic.evaluate.episode import PERCEIVED_PERSON, TRUE_PERSON, Episode, make_executor  # noqa: E402
from safemimic.evaluate.person import HumanTrack, TruePerson  # noqa: E402
from services.executor.mujoco.model import HUMAN_GEOM_GROUP  # noqa: E402
from services.executor.mujoco.sim import SimRobot  # noqa: E402
from services.safety.kinematics import RobotKinematics  # noqa: E402
from services.safety.pairs import N_ROBOT  # noqa: E402
from shared.config import StackConfig  # noqa: E402
from shared.geometry import segment_closest_points  # noqa: E402

WIDTH, HEIGHT = 640, 560
GHOST_RGBA = (0.9, 0.15, 0.1, 0.35)
SEGMENT_RGBA = (1.0, 0.85, 0.0, 1.0)
SEGMENT_WIDTH = 0.006  # m
SCENE_EXTENT = 3.0  # m
FLOOR_RGBA = (0.55, 0.58, 0.62, 1.0)
HEADLIGHT_AMBIENT = (0.45, 0.45, 0.45)
HEADLIGHT_DIFFUSE = (0.6, 0.6, 0.6)
#: Pairs drawn when none binds at the worst step.
_FALLBACK_PAIRS = 3
#: (azimuth, elevation) in degrees of the two views; MuJoCo's azimuth 180 looks along −x (from the front).
VIEWS = {"front": (155.0, -15.0), "top": (180.0, -70.0)}
CAMERA_DISTANCE = 2.3  # m


def worst_step(cbf: Episode, nominal: Episode) -> int:
    """The step shown: the no-CBF run's smallest h, or the CBF run's if the former stays ≥ 0."""
    def lowest(ep: Episode) -> tuple[float, int]:
        per_step = np.nan_to_num(ep.h, nan=np.inf).min(axis=1)
        k = int(np.argmin(per_step))
        return float(per_step[k]), k

    h_unsafe, k_unsafe = lowest(nominal)
    return k_unsafe if h_unsafe < 0 else lowest(cbf)[1]


def shown_pairs(cbf: Episode, k: int) -> np.ndarray:
    """Row indices whose closest-point segments are drawn at step ``k``."""
    binding = np.flatnonzero(cbf.active[k])
    if binding.size:
        return binding
    h = np.nan_to_num(cbf.h[k], nan=np.inf)
    return np.argsort(h, kind="stable")[:_FALLBACK_PAIRS][np.isfinite(np.sort(h)[:_FALLBACK_PAIRS])]


def closest_segments(kinematics: RobotKinematics, q: np.ndarray, capsules: np.ndarray, cbf: Episode,
                     rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Closest points (p on the robot capsule, q on the other) of pair ``rows`` at joint angles ``q``."""
    robot, _ = kinematics.compute(q)
    stacked = np.concatenate([robot, capsules])  # the first person fills the first external slots
    first, second = cbf.pairs.first[rows], cbf.pairs.second[rows]
    keep = second < N_ROBOT + len(capsules)
    first, second = first[keep], second[keep]
    points = segment_closest_points(stacked[first, 0], stacked[first, 1], stacked[second, 0], stacked[second, 1])
    return points.p, points.q


def _add_ghost(sim: SimRobot, unsafe: mujoco.MjData, option: mujoco.MjvOption, scene: mujoco.MjvScene) -> None:
    """Add the unsafe robot's moving geoms as a translucent ghost where they differ from the safe pose."""
    first = scene.ngeom
    mujoco.mjv_addGeoms(sim.model, unsafe, option, mujoco.MjvPerturb(), mujoco.mjtCatBit.mjCAT_DYNAMIC, scene)
    for i in range(first, scene.ngeom):
        geom = scene.geoms[i]
        robot_geom = geom.objtype == mujoco.mjtObj.mjOBJ_GEOM and sim.model.geom_group[geom.objid] != HUMAN_GEOM_GROUP
        moved = robot_geom and np.linalg.norm(sim.data.geom_xpos[geom.objid] - unsafe.geom_xpos[geom.objid]) > 1e-3
        geom.rgba = GHOST_RGBA if moved else (0.0, 0.0, 0.0, 0.0)


def _add_floor(scene: mujoco.MjvScene) -> None:
    """A grey floor at z = 0 (drawn only: the simulated model has none)."""
    geom = scene.geoms[scene.ngeom]
    mujoco.mjv_initGeom(geom, mujoco.mjtGeom.mjGEOM_PLANE, np.array([3.0, 3.0, 0.1]), np.zeros(3),
                        np.eye(3).ravel(), np.array(FLOOR_RGBA, dtype=np.float32))
    scene.ngeom += 1


def _add_segments(scene: mujoco.MjvScene, starts: np.ndarray, ends: np.ndarray) -> None:
    for a, b in zip(starts, ends):
        if scene.ngeom >= scene.maxgeom:
            return
        geom = scene.geoms[scene.ngeom]
        mujoco.mjv_initGeom(geom, mujoco.mjtGeom.mjGEOM_CAPSULE, np.zeros(3), np.zeros(3), np.zeros(9),
                            np.array(SEGMENT_RGBA, dtype=np.float32))
        mujoco.mjv_connector(geom, mujoco.mjtGeom.mjGEOM_CAPSULE, SEGMENT_WIDTH, a, b)
        scene.ngeom += 1


def render_snapshot(conf: StackConfig, kinematics: RobotKinematics, human: HumanTrack, person: TruePerson,
                    cbf: Episode, nominal: Episode, path: Path) -> Path:
    """Render the worst moment of the two runs (front and top views) into ``path`` (PNG)."""
    k = worst_step(cbf, nominal)
    sim = make_executor(conf, kinematics).sim
    model = sim.model
    model.vis.global_.offwidth = max(model.vis.global_.offwidth, WIDTH)
    model.vis.global_.offheight = max(model.vis.global_.offheight, HEIGHT)
    # near/far clipping scale with the model's extent, which the parked human capsules (1 km below
    # the floor) inflate: give the renderer the scene's real size
    model.stat.extent = SCENE_EXTENT
    model.vis.headlight.ambient[:] = HEADLIGHT_AMBIENT
    model.vis.headlight.diffuse[:] = HEADLIGHT_DIFFUSE
    state = human.states[cbf.human[k]] if cbf.human[k] >= 0 else None
    sim.set_human(person.capsules[k], person.radii, person.capsule_valid[k], TRUE_PERSON)
    if state is not None:
        sim.set_human(state.capsules, state.capsule_radii, state.capsule_valid, PERCEIVED_PERSON)
    sim.data.qpos[:] = cbf.qpos[k]
    mujoco.mj_forward(model, sim.data)
    unsafe = mujoco.MjData(model)
    unsafe.qpos[:] = nominal.qpos[k]
    unsafe.mocap_pos[:], unsafe.mocap_quat[:] = sim.data.mocap_pos, sim.data.mocap_quat
    mujoco.mj_forward(model, unsafe)

    rows = shown_pairs(cbf, k)
    capsules = state.capsules if state is not None else np.zeros((0, 2, 3))
    starts, ends = closest_segments(kinematics, cbf.q_sim[k], capsules, cbf, rows)
    option = mujoco.MjvOption()
    option.geomgroup[HUMAN_GEOM_GROUP] = 1
    camera = mujoco.MjvCamera()
    # look at the drawn closest-point segments (where it happens), else at the robot's chest
    chest = np.array([0.0, 0.0, kinematics.spec.base_height + 0.3])
    camera.lookat[:] = 0.5 * (starts + ends).mean(axis=0) if len(starts) else chest
    camera.distance = CAMERA_DISTANCE
    images = []
    with mujoco.Renderer(model, HEIGHT, WIDTH) as renderer:
        for azimuth, elevation in VIEWS.values():
            camera.azimuth, camera.elevation = azimuth, elevation
            renderer.update_scene(sim.data, camera, option)
            _add_floor(renderer.scene)
            _add_ghost(sim, unsafe, option, renderer.scene)
            _add_segments(renderer.scene, starts, ends)
            images.append(renderer.render().copy())

    fig, axes = plt.subplots(1, len(images), figsize=(12, 5.6), constrained_layout=True)
    for ax, image, view in zip(axes, images, VIEWS):
        ax.imshow(image)
        ax.set_title(view, fontsize=10)
        ax.axis("off")
    names = ", ".join(cbf.pairs.names[r] for r in rows) or "none"
    fig.suptitle(
        f"t = {cbf.t[k]:.2f} s — solid: with CBF; red ghost: without CBF (min h {1e3 * np.nanmin(nominal.h[k]):.0f} mm); "
        f"skin: the true person; blue: the perceived one; yellow: closest points of {names}",
        fontsize=9, wrap=True,
    )
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path
