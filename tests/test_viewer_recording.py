"""The evaluator's Rerun recordings and the viewer's drawing code, read back with Rerun's own tools.

``rerun rrd print FILE`` lists every chunk with its row count and entity path: the recording must
hold the entity roots of the issue (robot/cbf, robot/nominal, person/true, person/perceived,
barriers/, joints/) with one row per scene frame or per control step.
"""

from __future__ import annotations

import re
import subprocess
import sys
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rerun", reason="the viz extra (rerun-sdk) is not installed")

from services.safety.kinematics import RobotKinematics  # noqa: E402
from services.viewer.draw import binding_segments  # noqa: E402
from services.viewer.robot_mesh import RobotMesh, RobotMeshError  # noqa: E402
from shared.config import load_config  # noqa: E402
from shared.robot_spec import configured_robot_spec  # noqa: E402
from tests.support.team import G1_MJCF, REPO  # noqa: E402

RERUN = Path(sys.executable).parent / "rerun"
_CHUNK = re.compile(r"with (\d+) rows .* - (/\S+) - data columns: \[(.*)\]")


def rrd_rows(path: Path) -> Counter[str]:
    """Rows per entity path (summed over chunks) of a recording, from ``rerun rrd print``."""
    out = subprocess.run([str(RERUN), "rrd", "print", str(path)], capture_output=True, text=True, check=True).stdout
    rows: Counter[str] = Counter()
    for rows_text, entity, _ in _CHUNK.findall(out):
        rows[entity] += int(rows_text)
    return rows


def test_evaluate_rrd_holds_both_runs_people_barriers_and_joints(tmp_path: Path) -> None:
    out = tmp_path / "out"
    result = subprocess.run([sys.executable, "-m", "safemimic.cli", "evaluate", "--scenario", "cross-arm-reach",
                             "--seconds", "1", "--quiet", "--out", str(out), "--rrd"],
                            capture_output=True, text=True, cwd=REPO, timeout=300)
    assert result.returncode == 0, result.stderr[-3000:]
    rrd = out / "recording.rrd"
    assert f"recording {rrd}" in result.stdout
    rows = rrd_rows(rrd)
    steps = 500  # 1 s at the 500 Hz safety rate
    frames = len(range(0, steps, round(500 / 30)))  # the 3D scene at ≤ 30 Hz
    for root in ("robot/cbf", "robot/nominal", "person/true", "person/perceived", "barriers/", "joints/"):
        assert any(entity.startswith("/" + root) for entity in rows), root
    for run in ("cbf", "nominal"):
        assert rows[f"/robot/{run}/mesh/pelvis"] == frames + 1  # the static mesh + one pose per frame
        assert rows[f"/robot/{run}/capsules"] == frames
        assert rows[f"/robot/{run}/status/mode"] == steps
        assert rows[f"/barriers/{run}/min_h/self"] == steps
    assert rows["/person/true/capsules"] == frames
    assert 0 < rows["/person/perceived/capsules"] <= frames  # from the first perceived state on (60 ms latency)
    assert rows["/barriers/cbf/binding"] == frames
    pairs = [e for e in rows if e.startswith("/barriers/cbf/h/")]
    assert len(pairs) == 14 + 49 and all(rows[e] == steps for e in pairs if "human" not in e)
    for series in ("q_true", "q_nom", "q_cbf", "q", "q_without_cbf"):
        assert rows[f"/joints/left_elbow_joint/{series}"] == steps


def test_evaluate_rrd_refuses_a_name_that_is_not_rrd(tmp_path: Path) -> None:
    result = subprocess.run([sys.executable, "-m", "safemimic.cli", "evaluate", "--scenario", "cross-arm-reach",
                             "--out", str(tmp_path), "--rrd", "x.txt"], capture_output=True, text=True, cwd=REPO)
    assert result.returncode == 2 and "ends in .rrd" in result.stderr


@pytest.mark.parametrize("model", ["shipped", "menagerie"])
def test_robot_mesh_capsules_match_the_safety_kinematics(model: str) -> None:
    spec = configured_robot_spec(load_config())
    if model == "menagerie":
        if not G1_MJCF.exists():
            pytest.skip(f"the real G1 model is missing: {G1_MJCF}")
        spec = spec.with_model(G1_MJCF)
    mesh, kinematics = RobotMesh(spec), RobotKinematics(spec)
    q = np.random.default_rng(1).uniform(-0.6, 0.6, 8)
    pose = mesh.pose(q)
    endpoints, _ = kinematics.compute(q)
    assert np.abs(pose.capsules - endpoints).max() < 1e-9
    assert np.allclose(np.linalg.norm(pose.quaternions, axis=1), 1.0)
    assert "pelvis" in mesh.bodies and all(len(m.faces) > 0 for m in mesh.meshes)
    assert pose.translations[mesh.bodies.index("pelvis")][2] == pytest.approx(spec.base_height)
    with pytest.raises(ValueError, match="8 finite"):
        mesh.pose(np.full(8, np.nan))


def test_robot_mesh_refuses_a_missing_model(tmp_path: Path) -> None:
    spec = configured_robot_spec(load_config()).with_model(tmp_path / "none.xml")
    with pytest.raises(RobotMeshError, match="cannot load robot model"):
        RobotMesh(spec)


def test_binding_segments_are_the_closest_points_of_the_named_pairs() -> None:
    robot = np.zeros((7, 2, 3))
    robot[:, 1, 2] = 1.0  # every robot capsule: the z axis from 0 to 1
    people = np.zeros((7, 2, 3))
    people[:, :, 0] = 0.5  # every human capsule: x = 0.5, from y = -1 to 1 at z = 0.25
    people[:, 0, 1], people[:, 1, 1], people[:, :, 2] = -1.0, 1.0, 0.25
    segments = binding_segments(["torso|human.left_forearm", "torso|left_thigh", "bogus|human.x", "torso|human3.torso"],
                                robot, people)
    assert segments.shape == (2, 2, 3)  # the unresolvable names are skipped
    assert np.allclose(segments[0], [[0, 0, 0.25], [0.5, 0, 0.25]])
