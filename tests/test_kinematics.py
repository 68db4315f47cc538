"""Robot model (config/robots/safemimic_g1.xml), robot spec (g1.yaml) and RobotKinematics.

The reference is the real Unitree G1 model (MuJoCo Menagerie g1.xml, BSD-3) in the team
folder beside the checkout; tests that need it skip with a printed reason when it is absent.
Independent cross-checks: MuJoCo's own forward kinematics, central finite differences for
the Jacobians, Pinocchio's getFrameJacobian for the fast path.
"""

from __future__ import annotations

import itertools
from pathlib import Path

import mujoco
import numpy as np
import pinocchio as pin
import pytest
import yaml

from services.safety.errors import KinematicsError
from services.safety.kinematics import RobotKinematics
from shared.names import CAPSULE_NAMES, IMITATION_JOINT_NAMES
from shared.robot_spec import (
    DEFAULT_SELF_PAIRS,
    RobotSpec,
    RobotSpecError,
    default_robot_spec_path,
    load_robot_spec,
)
from tests.support.meshes import mesh_points
from tests.support.team import G1_MJCF, REPO

SPEC_PATH = REPO / "config" / "robots" / "g1.yaml"
OUR_MJCF = REPO / "config" / "robots" / "safemimic_g1.xml"


def _segment_distance_local(a1, b1, a2, b2):
    """Tiny fallback: segment/segment distance by dense sampling + golden refinement."""
    a1, b1, a2, b2 = (np.asarray(x, float) for x in (a1, b1, a2, b2))

    def point_seg(p):
        d = b2 - a2
        t = np.clip((p - a2) @ d / max(d @ d, 1e-300), 0.0, 1.0)
        return np.linalg.norm(p - (a2 + t * d))

    s = np.linspace(0, 1, 2001)
    f = [point_seg(a1 + si * (b1 - a1)) for si in s]
    return float(min(f))


def segment_distance(a1, b1, a2, b2) -> float:
    try:
        from shared.geometry import segment_closest_points
    except ImportError:  # pragma: no cover - geometry module written in parallel
        return _segment_distance_local(a1, b1, a2, b2)
    return float(segment_closest_points(a1, b1, a2, b2).distance[0])


def need_real_g1() -> Path:
    if not G1_MJCF.is_file():
        print(f"real G1 model not found at {G1_MJCF}: skipping the comparison")
        pytest.skip(f"real G1 model not found at {G1_MJCF}")
    return G1_MJCF


@pytest.fixture(scope="module")
def spec() -> RobotSpec:
    return load_robot_spec(SPEC_PATH)


@pytest.fixture(scope="module")
def kin(spec: RobotSpec) -> RobotKinematics:
    return RobotKinematics(spec)


@pytest.fixture(scope="module")
def real_kin(spec: RobotSpec) -> RobotKinematics:
    return RobotKinematics(spec.with_model(need_real_g1()))


def random_configs(kin: RobotKinematics, n: int, seed: int) -> np.ndarray:
    return np.random.default_rng(seed).uniform(kin.q_min, kin.q_max, size=(n, kin.nq))


def joint_names(m: mujoco.MjModel) -> list[str]:
    return [m.joint(i).name for i in range(m.njnt)]


def body_names(m: mujoco.MjModel) -> list[str]:
    return [m.body(i).name for i in range(m.nbody)]


# --------------------------------------------------------------------------- the MJCF
def test_our_model_loads_in_mujoco_mesh_free() -> None:
    m = mujoco.MjModel.from_xml_path(str(OUR_MJCF))
    assert m.nq == 36 and m.nv == 35 and m.njnt == 30 and m.nu == 29
    assert m.nmesh == 0, "the shipped model must not need mesh files"
    assert m.jnt_type[0] == mujoco.mjtJoint.mjJNT_FREE and m.body(m.jnt_bodyid[0]).name == "pelvis"
    names = joint_names(m)
    for j in IMITATION_JOINT_NAMES:
        assert j in names
    # Collision geoms: group 3, contact bit 1; visual geoms: group 2, no contact.
    collision = [g for g in range(m.ngeom) if m.geom_group[g] == 3]
    visual = [g for g in range(m.ngeom) if m.geom_group[g] == 2]
    assert len(collision) > 30 and len(visual) > 30
    assert all(m.geom_contype[g] == 1 and m.geom_conaffinity[g] == 1 for g in collision)
    assert all(m.geom_contype[g] == 0 and m.geom_conaffinity[g] == 0 for g in visual)
    bodies_with_collision = {m.body(m.geom_bodyid[g]).name for g in collision}
    for b in ("pelvis", "torso_link", "left_shoulder_yaw_link", "left_elbow_link", "left_wrist_yaw_link",
              "right_wrist_yaw_link", "left_hip_yaw_link", "right_knee_link", "left_ankle_roll_link"):
        assert b in bodies_with_collision, b


@pytest.mark.parametrize("key", ["home", "stand"])
def test_no_robot_self_contact_at_keyframes(key: str) -> None:
    m = mujoco.MjModel.from_xml_path(str(OUR_MJCF))
    d = mujoco.MjData(m)
    mujoco.mj_resetDataKeyframe(m, d, m.key(key).id)
    mujoco.mj_forward(m, d)
    pairs = [(m.body(m.geom_bodyid[c.geom1]).name, m.body(m.geom_bodyid[c.geom2]).name) for c in d.contact[: d.ncon]]
    assert d.ncon == 0, pairs


def test_mujoco_reports_real_self_collisions() -> None:
    """The collision geoms are live: folding the left forearm into the chest touches the torso."""
    m = mujoco.MjModel.from_xml_path(str(OUR_MJCF))
    d = mujoco.MjData(m)
    mujoco.mj_resetDataKeyframe(m, d, m.key("home").id)
    for name, value in {"left_shoulder_pitch_joint": -0.3, "left_shoulder_roll_joint": -0.6,
                        "left_elbow_joint": 0.0}.items():
        d.qpos[m.jnt_qposadr[m.joint(name).id]] = value
    mujoco.mj_forward(m, d)
    touched = {frozenset((m.body(m.geom_bodyid[c.geom1]).name, m.body(m.geom_bodyid[c.geom2]).name))
               for c in d.contact[: d.ncon]}
    assert any("torso_link" in p and any(b.startswith("left_") for b in p) for p in touched), touched


def test_home_keyframe_matches_spec(spec: RobotSpec) -> None:
    m = mujoco.MjModel.from_xml_path(str(OUR_MJCF))
    key = m.key("home")
    assert key.qpos[:3] == pytest.approx([0.0, 0.0, spec.base_height])
    assert key.qpos[3:7] == pytest.approx([1.0, 0.0, 0.0, 0.0])
    for j in range(1, m.njnt):
        name = m.joint(j).name
        assert key.qpos[m.jnt_qposadr[j]] == pytest.approx(spec.home.get(name, 0.0)), name
        assert key.ctrl[m.actuator(name).id] == pytest.approx(spec.home.get(name, 0.0)), name


def test_our_model_loads_in_pinocchio() -> None:
    model = pin.buildModelFromMJCF(str(OUR_MJCF))
    assert model.nq == 36 and model.nv == 35
    assert model.joints[1].shortname() == "JointModelFreeFlyer"
    for j in IMITATION_JOINT_NAMES:
        assert model.existJointName(j)


def test_kinematic_data_equal_real_g1() -> None:
    """Same bodies, tree, body poses, joints, axes, ranges, armature, inertials as the real G1."""
    ours = mujoco.MjModel.from_xml_path(str(OUR_MJCF))
    real = mujoco.MjModel.from_xml_path(str(need_real_g1()))
    assert body_names(ours) == body_names(real)
    assert joint_names(ours) == joint_names(real)
    np.testing.assert_array_equal(ours.body_parentid, real.body_parentid)
    for field in ("body_pos", "body_quat", "body_mass", "body_ipos", "body_iquat", "body_inertia"):
        np.testing.assert_allclose(getattr(ours, field), getattr(real, field), rtol=0, atol=1e-12, err_msg=field)
    for field in ("jnt_type", "jnt_axis", "jnt_pos", "jnt_range", "jnt_limited", "dof_armature",
                  "dof_frictionloss", "actuator_gainprm", "actuator_biasprm", "actuator_ctrlrange"):
        np.testing.assert_allclose(getattr(ours, field), getattr(real, field), rtol=0, atol=1e-12, err_msg=field)
    # Pinocchio sees the same ranges.
    p_ours = pin.buildModelFromMJCF(str(OUR_MJCF))
    p_real = pin.buildModelFromMJCF(str(G1_MJCF))
    np.testing.assert_array_equal(p_ours.lowerPositionLimit, p_real.lowerPositionLimit)
    np.testing.assert_array_equal(p_ours.upperPositionLimit, p_real.upperPositionLimit)


def test_imitation_joint_ranges_equal_real_g1(kin: RobotKinematics, real_kin: RobotKinematics) -> None:
    real = mujoco.MjModel.from_xml_path(str(G1_MJCF))
    for i, name in enumerate(kin.joint_names):
        lo, hi = real.jnt_range[real.joint(name).id]
        assert (kin.q_min[i], kin.q_max[i]) == (lo, hi), name
    np.testing.assert_array_equal(kin.q_min, real_kin.q_min)
    np.testing.assert_array_equal(kin.q_max, real_kin.q_max)


def test_capsules_enclose_real_link_meshes(spec: RobotSpec) -> None:
    """Each capsule contains every vertex of the real G1 meshes of the links it stands for."""
    m = mujoco.MjModel.from_xml_path(str(need_real_g1()))
    d = mujoco.MjData(m)
    mujoco.mj_kinematics(m, d)
    arm = ["shoulder_roll_link", "shoulder_yaw_link"]
    fore = ["elbow_link", "wrist_roll_link", "wrist_pitch_link", "wrist_yaw_link"]
    links = {
        "torso": ["torso_link", "pelvis"],
        "left_upper_arm": [f"left_{n}" for n in arm],
        "right_upper_arm": [f"right_{n}" for n in arm],
        "left_forearm": [f"left_{n}" for n in fore],
        "right_forearm": [f"right_{n}" for n in fore],
        "left_thigh": ["left_hip_pitch_link", "left_hip_roll_link", "left_hip_yaw_link"],
        "right_thigh": ["right_hip_pitch_link", "right_hip_roll_link", "right_hip_yaw_link"],
    }
    skip_meshes = {"head_link", "logo_link"}  # the torso capsule runs pelvis -> neck
    for cname, bodies in links.items():
        cap = spec.capsules[cname]
        P = mesh_points(m, d, bodies, cap.frame, skip_meshes)
        a, b = np.array(cap.a), np.array(cap.b)
        s = np.clip((P - a) @ (b - a) / ((b - a) @ (b - a)), 0, 1)
        dist = np.linalg.norm(P - (a + s[:, None] * (b - a)), axis=1)
        assert dist.max() <= cap.radius, (cname, dist.max(), cap.radius)
        # ... and is tight: the radius exceeds the farthest vertex by at most 2 mm.
        assert cap.radius - dist.max() <= 0.002, (cname, dist.max(), cap.radius)


def _segment_distances(points: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    s = np.clip((points - a) @ (b - a) / ((b - a) @ (b - a)), 0, 1)
    return np.linalg.norm(points - (a + s[:, None] * (b - a)), axis=1)


def test_pelvis_and_torso_capsules_enclose_the_trunk_over_the_waist_range(spec: RobotSpec) -> None:
    """On a grid of waist roll × pitch over the joints' whole range, every vertex of the real G1's
    trunk meshes (pelvis, waist yaw and roll links, torso with head and logo) lies inside the
    torso capsule (carried by the waist) or the static pelvis capsule; the torso capsule alone
    leaves the pelvis out by several centimetres once the waist moves."""
    m = mujoco.MjModel.from_xml_path(str(need_real_g1()))
    d = mujoco.MjData(m)
    torso, pelvis = spec.capsules["torso"], spec.static_capsules["pelvis"]
    assert pelvis.frame == "pelvis"
    roll, pitch = (m.joint(j) for j in ("waist_roll_joint", "waist_pitch_joint"))
    worst_union, worst_torso_only = -np.inf, -np.inf
    for r, p in itertools.product(np.linspace(*roll.range, 9), np.linspace(*pitch.range, 9)):
        mujoco.mj_resetData(m, d)
        d.qpos[m.jnt_qposadr[roll.id]], d.qpos[m.jnt_qposadr[pitch.id]] = r, p
        mujoco.mj_kinematics(m, d)
        points = mesh_points(m, d, ["pelvis", "waist_yaw_link", "waist_roll_link", "torso_link"], "pelvis")
        t_id, p_id = m.body("torso_link").id, m.body("pelvis").id  # the torso capsule in pelvis coordinates
        rotation = d.xmat[p_id].reshape(3, 3).T @ d.xmat[t_id].reshape(3, 3)
        origin = d.xmat[p_id].reshape(3, 3).T @ (d.xpos[t_id] - d.xpos[p_id])
        torso_a, torso_b = (rotation @ np.array(x) + origin for x in (torso.a, torso.b))
        outside_torso = _segment_distances(points, torso_a, torso_b) - torso.radius
        outside_pelvis = _segment_distances(points, np.array(pelvis.a), np.array(pelvis.b)) - pelvis.radius
        worst_union = max(worst_union, np.minimum(outside_torso, outside_pelvis).max())
        worst_torso_only = max(worst_torso_only, outside_torso.max())
    assert worst_union <= 0.0, f"a trunk vertex lies {1e3 * worst_union:.1f} mm outside both capsules"
    assert worst_torso_only > 0.03, "the torso capsule alone was expected to leave the pelvis out"


def test_pelvis_capsule_is_tight(spec: RobotSpec) -> None:
    """The pelvis capsule holds every pelvis vertex with at most 2 mm to spare."""
    m = mujoco.MjModel.from_xml_path(str(need_real_g1()))
    d = mujoco.MjData(m)
    mujoco.mj_kinematics(m, d)
    cap = spec.static_capsules["pelvis"]
    farthest = _segment_distances(mesh_points(m, d, ["pelvis"], "pelvis"), np.array(cap.a), np.array(cap.b)).max()
    assert farthest <= cap.radius <= farthest + 0.002


def test_static_capsules_are_fixed_and_placed_in_the_world(kin: RobotKinematics, spec: RobotSpec) -> None:
    cap = spec.static_capsules["pelvis"]
    ends = kin.static_endpoints["pelvis"]
    np.testing.assert_allclose(ends, np.array([cap.a, cap.b]) + [0.0, 0.0, spec.base_height])
    with pytest.raises(ValueError):
        ends[0, 0] = 1.0  # read-only
    moving = spec.model_copy(update={"static_capsules": {"hand": spec.capsules["left_forearm"]}})
    with pytest.raises(KinematicsError, match="moves with joint 'left_elbow_joint'"):
        RobotKinematics(moving)


def test_home_static_pairs_have_clearance(kin: RobotKinematics, spec: RobotSpec) -> None:
    ends = kin.compute(kin.q_home)[0]
    for robot, static in spec.static_pairs:
        i, (a, b) = CAPSULE_NAMES.index(robot), kin.static_endpoints[static]
        clearance = segment_distance(ends[i, 0], ends[i, 1], a, b) - kin.radii[i] - spec.static_capsules[static].radius
        assert clearance > 0.03, (robot, static, clearance)


# --------------------------------------------------------------------------- the spec
def test_default_spec_fields(spec: RobotSpec) -> None:
    assert default_robot_spec_path() == SPEC_PATH.resolve()
    assert Path(spec.model) == OUR_MJCF.resolve() and Path(spec.model).is_absolute()
    assert spec.base_body == "pelvis" and spec.base_height == pytest.approx(0.793)
    assert tuple(spec.imitation_joints) == IMITATION_JOINT_NAMES
    assert set(spec.capsules) == set(CAPSULE_NAMES)
    assert [tuple(p) for p in spec.self_pairs] == [tuple(p) for p in DEFAULT_SELF_PAIRS]
    assert spec.limits == {}


def _raw_spec() -> dict:
    return yaml.safe_load(SPEC_PATH.read_text())


def _write(tmp_path: Path, raw: dict) -> Path:
    path = tmp_path / "robot.yaml"
    path.write_text(yaml.safe_dump(raw))
    return path


def test_model_path_resolved_against_yaml_folder(tmp_path: Path) -> None:
    raw = _raw_spec()
    raw["model"] = str(Path("..") / "models" / "robot.xml")
    sub = tmp_path / "specs"
    sub.mkdir()
    spec = load_robot_spec(_write(sub, raw))
    assert Path(spec.model) == (tmp_path / "models" / "robot.xml").resolve()


@pytest.mark.parametrize(
    "mutate, message",
    [
        (lambda r: r.update(extra_field=1), "extra_field"),
        (lambda r: r["capsules"].pop("torso"), "torso"),
        (lambda r: r["capsules"].update(head=r["capsules"]["torso"]), "head"),
        (lambda r: r["capsules"]["left_forearm"].update(radius=0.0), "radius"),
        (lambda r: r["capsules"]["left_forearm"].update(radius=-0.01), "radius"),
        (lambda r: r["capsules"]["left_forearm"].update(a=[0.0, 0.0]), "a"),
        (lambda r: r["capsules"]["left_forearm"].update(colour="red"), "colour"),
        (lambda r: r["self_pairs"].append(["left_forearm", "head"]), "head"),
        (lambda r: r["self_pairs"].append(["torso", "torso"]), "itself"),
        (lambda r: r["self_pairs"].append(["torso", "left_forearm"]), "twice"),
        (lambda r: r["imitation_joints"].pop(), "exactly 8"),
        (lambda r: r["imitation_joints"].reverse(), "order"),
        (lambda r: r.update(limits={"left_hip_pitch_joint": [-1, 1]}), "not imitation joints"),
        (lambda r: r.update(limits={"left_elbow_joint": [1, -1]}), "min < max"),
        (lambda r: r.update(limits={"left_elbow_joint": [0.0, 1.0]}), "outside limits"),
        (lambda r: r.update(base_height=-1.0), "base_height"),
        (lambda r: r.pop("model"), "model"),
        (lambda r: r["static_capsules"].update(torso=r["static_capsules"]["pelvis"]), "may not reuse"),
        (lambda r: r["static_pairs"].append(["left_forearm", "chest"]), "static capsule of"),
        (lambda r: r["static_pairs"].append(["pelvis", "left_forearm"]), "robot capsule of"),
        (lambda r: r["static_pairs"].append(["left_forearm", "pelvis"]), "twice"),
    ],
)
def test_invalid_specs_are_rejected_clearly(tmp_path: Path, mutate, message: str) -> None:
    raw = _raw_spec()
    mutate(raw)
    path = _write(tmp_path, raw)
    with pytest.raises(RobotSpecError) as err:
        load_robot_spec(path)
    assert message in str(err.value) and str(path) in str(err.value)


def test_spec_file_errors(tmp_path: Path) -> None:
    with pytest.raises(RobotSpecError, match="cannot read"):
        load_robot_spec(tmp_path / "missing.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("- just\n- a list\n")
    with pytest.raises(RobotSpecError, match="mapping"):
        load_robot_spec(bad)


# --------------------------------------------------------------------------- kinematics
def test_kinematics_properties(kin: RobotKinematics, spec: RobotSpec) -> None:
    assert kin.joint_names == IMITATION_JOINT_NAMES
    assert kin.capsule_names == CAPSULE_NAMES
    assert kin.q_home.shape == kin.q_min.shape == kin.q_max.shape == (8,)
    assert kin.q_home == pytest.approx([spec.home.get(j, 0.0) for j in IMITATION_JOINT_NAMES])
    assert np.all(kin.q_min < kin.q_home) and np.all(kin.q_home < kin.q_max)
    assert kin.radii == pytest.approx([spec.capsules[c].radius for c in CAPSULE_NAMES])
    assert kin.model.nq == kin.model.nv == 8
    assert kin.uses_fast_path
    # Thighs hang from the locked legs: never moved by the 8 joints; everything else is.
    assert kin.capsule_moving.tolist() == [[True, True]] * 5 + [[False, False]] * 2
    with pytest.raises(ValueError):
        kin.q_home[0] = 1.0  # read-only


def test_base_at_base_height(kin: RobotKinematics, spec: RobotSpec) -> None:
    for q in (kin.q_home, random_configs(kin, 1, 3)[0]):
        M = kin.frame_placement(spec.base_body, q)
        np.testing.assert_allclose(M.translation, [0.0, 0.0, spec.base_height], atol=1e-15)
        np.testing.assert_allclose(M.rotation, np.eye(3), atol=1e-15)


def test_compute_shapes_and_input_checks(kin: RobotKinematics) -> None:
    ends, jac = kin.compute(kin.q_home)
    assert ends.shape == (7, 2, 3) and jac.shape == (7, 2, 3, 8)
    assert np.isfinite(ends).all() and np.isfinite(jac).all()
    assert np.all(jac[5:] == 0.0)
    for bad in (np.zeros(7), np.zeros((8, 1)), np.r_[np.zeros(7), np.nan], np.r_[np.zeros(7), np.inf]):
        with pytest.raises(KinematicsError):
            kin.compute(bad)
    with pytest.raises(KinematicsError, match="no_such_frame"):
        kin.frame_position("no_such_frame", kin.q_home)


def test_endpoints_match_real_g1(kin: RobotKinematics, real_kin: RobotKinematics) -> None:
    """1,000 random configurations: our model and the real G1 give the same capsule endpoints."""
    worst = 0.0
    for q in random_configs(kin, 1000, seed=1):
        ours = kin.compute(q)[0].copy()
        real = real_kin.compute(q)[0]
        worst = max(worst, float(np.abs(ours - real).max()))
    print(f"max |endpoint(ours) - endpoint(real G1)| over 1000 configs: {worst:.3e} m")
    assert worst <= 1e-3  # the requirement
    assert worst <= 1e-12  # the kinematic chain is copied, so it is exact up to rounding


def test_jacobians_match_finite_differences(kin: RobotKinematics) -> None:
    eps = 1e-6
    worst = 0.0
    for q in random_configs(kin, 200, seed=2):
        jac = kin.compute(q)[1].copy()
        fd = np.empty_like(jac)
        for k in range(kin.nq):
            dq = np.zeros(kin.nq)
            dq[k] = eps
            plus = kin.compute(q + dq)[0].copy()
            minus = kin.compute(q - dq)[0].copy()
            fd[..., k] = (plus - minus) / (2 * eps)
        rel = np.abs(jac - fd).max() / np.abs(fd).max()
        worst = max(worst, rel)
    print(f"max relative Jacobian error vs central differences over 200 configs: {worst:.2e}")
    assert worst <= 1e-6


def test_fast_path_equals_get_frame_jacobian(kin: RobotKinematics) -> None:
    model = kin.model
    data = model.createData()
    for q in random_configs(kin, 50, seed=4):
        ends, jac = kin.compute(q)
        pin.computeJointJacobians(model, data, q)
        pin.updateFramePlacements(model, data)
        for ci, cname in enumerate(CAPSULE_NAMES):
            for k, tag in enumerate("ab"):
                fid = model.getFrameId(f"capsule/{cname}/{tag}")
                np.testing.assert_allclose(ends[ci, k], data.oMf[fid].translation, rtol=0, atol=1e-14)
                ref = pin.getFrameJacobian(model, data, fid, pin.LOCAL_WORLD_ALIGNED)[:3]
                np.testing.assert_allclose(jac[ci, k], ref, rtol=0, atol=1e-13)


def test_reordered_joints_permute_consistently(spec: RobotSpec, kin: RobotKinematics) -> None:
    """A spec listing the joints in another order gets q and Jacobian columns in that order."""
    perm = np.array([7, 2, 0, 5, 1, 6, 3, 4])
    joints = [spec.imitation_joints[i] for i in perm]
    # model_construct: the G1 order check is deliberately bypassed to reach the permuted path.
    other = RobotSpec.model_construct(**{**spec.__dict__, "imitation_joints": joints})
    kin2 = RobotKinematics(other)
    assert kin2.joint_names == tuple(joints)
    np.testing.assert_array_equal(kin2.q_min, kin.q_min[perm])
    for q in random_configs(kin, 20, seed=5):
        e1, j1 = (a.copy() for a in kin.compute(q))
        e2, j2 = kin2.compute(q[perm])
        np.testing.assert_allclose(e2, e1, atol=1e-14)
        np.testing.assert_allclose(j2, j1[..., perm], atol=1e-13)


def test_cross_check_with_mujoco(kin: RobotKinematics, spec: RobotSpec) -> None:
    """mj_kinematics (pelvis at base_height, other joints at home) gives the same bodies and capsules."""
    m = mujoco.MjModel.from_xml_path(str(OUR_MJCF))
    d = mujoco.MjData(m)
    worst = 0.0
    for q in random_configs(kin, 50, seed=6):
        d.qpos[:] = 0.0
        d.qpos[:7] = [0.0, 0.0, spec.base_height, 1.0, 0.0, 0.0, 0.0]
        for name, value in spec.home.items():
            d.qpos[m.jnt_qposadr[m.joint(name).id]] = value
        for name, value in zip(kin.joint_names, q):
            d.qpos[m.jnt_qposadr[m.joint(name).id]] = value
        mujoco.mj_kinematics(m, d)
        for b in range(1, m.nbody):
            ours = kin.frame_position(m.body(b).name, q)
            worst = max(worst, float(np.abs(ours - d.xpos[b]).max()))
            assert np.abs(ours - d.xpos[b]).max() <= 1e-9, m.body(b).name
        ends = kin.compute(q)[0]
        for ci, cname in enumerate(CAPSULE_NAMES):
            cap = spec.capsules[cname]
            b = m.body(cap.frame).id
            R = d.xmat[b].reshape(3, 3)
            for k, p in enumerate((cap.a, cap.b)):
                np.testing.assert_allclose(ends[ci, k], R @ np.array(p) + d.xpos[b], rtol=0, atol=1e-9)
    print(f"max |body position (Pinocchio) - body position (MuJoCo)|: {worst:.3e} m")


def test_home_self_pairs_have_clearance(kin: RobotKinematics) -> None:
    ends = kin.compute(kin.q_home)[0]
    assert len(kin.self_pairs) == len(DEFAULT_SELF_PAIRS)
    for i, j in kin.self_pairs:
        d = segment_distance(ends[i, 0], ends[i, 1], ends[j, 0], ends[j, 1])
        clearance = d - kin.radii[i] - kin.radii[j]
        print(f"home clearance {CAPSULE_NAMES[i]:>15s} - {CAPSULE_NAMES[j]:<15s} {clearance:+.3f} m")
        assert clearance > 0.03, (CAPSULE_NAMES[i], CAPSULE_NAMES[j], clearance)


def test_excluded_adjacent_pairs_really_overlap(kin: RobotKinematics) -> None:
    """The pairs left out of self_pairs overlap at home by construction (so they must be left out)."""
    ends = kin.compute(kin.q_home)[0]
    idx = {c: i for i, c in enumerate(CAPSULE_NAMES)}
    for a, b in [("left_upper_arm", "torso"), ("right_upper_arm", "torso"), ("left_upper_arm", "left_forearm"),
                 ("right_upper_arm", "right_forearm"), ("left_thigh", "torso"), ("right_thigh", "torso")]:
        i, j = idx[a], idx[b]
        d = segment_distance(ends[i, 0], ends[i, 1], ends[j, 0], ends[j, 1])
        assert d < kin.radii[i] + kin.radii[j], (a, b)


# --------------------------------------------------------------------------- errors
def _with(spec: RobotSpec, **update) -> RobotSpec:
    return RobotSpec.model_validate({**spec.model_dump(), **update})


def test_missing_model_file(spec: RobotSpec, tmp_path: Path) -> None:
    with pytest.raises(KinematicsError, match="not found"):
        RobotKinematics(spec.with_model(tmp_path / "nope.xml"))
    other = tmp_path / "robot.sdf"
    other.write_text("<sdf/>")
    with pytest.raises(KinematicsError, match="unsupported"):
        RobotKinematics(spec.with_model(other))


def test_missing_joint_is_named(spec: RobotSpec) -> None:
    joints = list(spec.imitation_joints)
    renamed = joints[4]
    joints[4] = "left_elbow_pitch_joint"
    limits = {("left_elbow_pitch_joint" if name == renamed else name): v for name, v in spec.joint_velocity_limits.items()}
    with pytest.raises(KinematicsError, match="left_elbow_pitch_joint"):
        RobotKinematics(_with(spec, imitation_joints=joints, joint_velocity_limits=limits))
    with pytest.raises(KinematicsError, match="left_tail_joint"):
        RobotKinematics(_with(spec, home={**spec.home, "left_tail_joint": 0.1}))


def test_missing_frame_is_named(spec: RobotSpec) -> None:
    caps = {k: v.model_dump() for k, v in spec.capsules.items()}
    caps["left_forearm"]["frame"] = "left_forearm_link"
    with pytest.raises(KinematicsError, match="left_forearm_link"):
        RobotKinematics(_with(spec, capsules=caps))
    with pytest.raises(KinematicsError, match="hips"):
        RobotKinematics(_with(spec, base_body="hips"))


def test_limits_override_only_tightens(spec: RobotSpec) -> None:
    kin = RobotKinematics(_with(spec, limits={"waist_roll_joint": (-0.3, 0.25)}))
    assert (kin.q_min[0], kin.q_max[0]) == (-0.3, 0.25)
    assert kin.q_min[1] == -0.52
    with pytest.raises(KinematicsError, match="wider"):
        RobotKinematics(_with(spec, limits={"waist_roll_joint": (-1.0, 0.25)}))


def test_home_outside_range_is_rejected(spec: RobotSpec) -> None:
    with pytest.raises(KinematicsError, match="left_knee_joint"):
        RobotKinematics(_with(spec, home={**spec.home, "left_knee_joint": -1.0}))
    with pytest.raises(KinematicsError, match="left_elbow_joint"):
        RobotKinematics(_with(spec, home={**spec.home, "left_elbow_joint": 3.0}))
