"""The offline evaluator: the paper's two scenarios meet their numbers with our
model and the real G1, the output is deterministic, and any architecture §6 recording evaluates (keys in
any order, extra keys, real motion capture). Real perception, Pinocchio, DAQP and MuJoCo."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from safemimic.evaluate.evaluation import evaluate, evaluation_config
from safemimic.evaluate.goals import goal_report, goals_markdown
from safemimic.evaluate.metrics import RUN_KEYS, TIMING_KEYS, deterministic_part
from safemimic.evaluate.variants import broadened, read_recording
from services.perception.placement import Placement
from services.perception.scenarios import get_scenario, scenario_recording
from shared.config import RetargetMethod, TargetPath, load_config
from shared.names import KEYPOINT_NAMES
from tests.support.team import G1_MJCF, MOCAP_DIR, REPO

SCENARIOS = ("cross-arm-reach", "side-by-side-arm-raise")


def robot_model(which: str) -> str | None:
    if which == "ours":
        return None
    if not G1_MJCF.is_file():
        print(f"skipping: real G1 model not found at {G1_MJCF}")
        pytest.skip(f"real G1 model not found at {G1_MJCF} (set SAFEMIMIC_TEAM_SHARED to the team folder)")
    return str(G1_MJCF)


@pytest.mark.parametrize("model", ["ours", "real_g1"])
@pytest.mark.parametrize("scenario", SCENARIOS)
def test_paper_scenarios_violate_without_and_are_safe_with_the_cbf(scenario: str, model: str) -> None:
    conf = evaluation_config(None, scenario, "side-by-side", robot_model(model))
    metrics = evaluate(conf).metrics()
    cbf, nominal = metrics["cbf"], metrics["nominal"]
    assert tuple(cbf) == RUN_KEYS and tuple(nominal) == RUN_KEYS
    # without the CBF layer the robot violates: a barrier below zero and MuJoCo contacts
    assert min(nominal["min_h_self"], nominal["min_h_human"]) < 0, nominal
    assert nominal["contacts_robot_robot"] + nominal["contacts_robot_human"] > 0, nominal
    assert nominal["frames_h_negative"] > 0
    # with it: every barrier ≥ −1 mm, not one contact, and nothing lost while no constraint binds
    assert cbf["min_h_self"] >= -1e-3 and cbf["min_h_human"] >= -1e-3, cbf
    assert cbf["contacts_robot_robot"] == 0 and cbf["contacts_robot_human"] == 0, cbf
    # and so against the truth: at the simulated joints, with the true (undelayed) person
    assert cbf["true_min_h_self"] >= -1e-3 and cbf["true_contacts_robot_human"] == 0, cbf
    assert cbf["rms_tracking"] > nominal["rms_tracking"]  # the layer did bend the motion
    assert cbf["nan_count"] == 0 and nominal["nan_count"] == 0
    assert cbf["hold_steps"] == 0
    assert nominal["protective_stop_steps"] == nominal["backing_out_steps"] == 0  # no filter, no stop
    assert cbf["person_lost_steps"] == nominal["person_lost_steps"] == 0  # seen throughout
    assert metrics["input"]["free_steps"] < metrics["input"]["control_steps"]
    assert metrics["input"]["robot_model"] == ("g1.xml" if model == "real_g1" else "default")


@pytest.mark.parametrize("model", ["ours", "real_g1"])
@pytest.mark.parametrize("scenario", SCENARIOS)
def test_the_paper_rows_lose_nothing_while_no_constraint_binds(scenario: str, model: str) -> None:
    """The paper's claim for its rows (no standoff: ``safety.human_standoff_m`` 0): while no constraint
    binds, the CBF run tracks its target as the run without the layer does (RMS within 0.01 rad). With
    the default standoff (0.1 m) the cross-arm reach has fewer free steps and on some of them the CBF
    run is still catching up after a binding one, 0.022 against 0.010 rad, and the side-by-side arm
    raise has none (the raised arm is held off the person's throughout; measured)."""
    conf = evaluation_config(None, scenario, "side-by-side", robot_model(model))
    conf = conf.model_copy(update={"safety": conf.safety.model_copy(update={"human_standoff_m": 0.0})})
    metrics = evaluate(conf).metrics()
    cbf, nominal = metrics["cbf"], metrics["nominal"]
    assert 0 < metrics["input"]["free_steps"] < metrics["input"]["control_steps"]
    assert abs(cbf["rms_tracking_free"] - nominal["rms_tracking_free"]) <= 0.01, (cbf, nominal)


def _scripted_fidelity(method: str = "linear", scenario: str = "reach-forward", **safety: object) -> dict:
    """The CBF run's metrics of a scripted ``scenario`` with these retargeting ``method`` and ``safety`` settings."""
    conf = evaluation_config(None, scenario, "auto", None)
    conf = conf.model_copy(update={"safety": conf.safety.model_copy(update=safety),
                                   "retargeting": conf.retargeting.model_copy(update={"method": RetargetMethod(method)})})
    return evaluate(conf).metrics()["cbf"]


def test_fidelity_of_a_scripted_reach_with_feed_forward_and_targets_between_frames() -> None:
    """The scripted reach toward a person facing the robot at the default 60 ms camera latency, judged
    against the true person at the simulated joints; deterministic, not timed. The imitation's own
    fidelity is measured without the standoff (``safety.human_standoff_m`` 0), where no constraint
    binds after the first second.

    Met: rms_true_free ≤ 0.05 rad; lag ≤ latency + 20 ms (measured 80 ms: the target 82 ms behind
    the truth, 60 latency + ≈ 22 of point filter and θ̇ estimate, the command 2 ms ahead of it once
    the reach slows); the controller and servos add < 2° to the arm-direction error the
    retargeting itself leaves (the robot exactly at q_true); safe against the truth. Without the
    velocity feed-forward (the paper's eq. 7) or without the targets between frames the robot
    trails by more than 1/K more. With the default standoff (0.1 m) the hands reaching toward the
    person's are held off them: lag 110 ms (the command 26 ms behind q_nom; measured), as safe."""
    free = _scripted_fidelity(human_standoff_m=0.0)
    fidelity = free["fidelity"]
    assert fidelity["rms_true_free"] <= 0.05, fidelity
    assert fidelity["lag_ms"] <= 60.0 + 20.0, fidelity
    assert fidelity["direction_error_deg_p95"] <= fidelity["direction_error_deg_p95_at_target"] + 2.0, fidelity
    for paper_like in (_scripted_fidelity(feedforward=False, human_standoff_m=0.0),
                       _scripted_fidelity(extrapolate_max_s=0.0, human_standoff_m=0.0)):
        assert paper_like["fidelity"]["lag_ms"] >= fidelity["lag_ms"] + 80.0, paper_like["fidelity"]
        assert paper_like["fidelity"]["rms_true_free"] >= 1.5 * fidelity["rms_true_free"], paper_like["fidelity"]
    default = _scripted_fidelity()
    assert fidelity["lag_ms"] + 20.0 <= default["fidelity"]["lag_ms"] <= fidelity["lag_ms"] + 40.0, default["fidelity"]
    for run in (free, default):
        assert run["true_min_h_self"] >= -1e-3 and run["true_contacts_robot_human"] == 0, run
        assert run["robot_approach_steps"] == 0 and run["nan_count"] == 0, run


def test_a_continuous_target_path_follows_each_frame_within_that_frame() -> None:
    """The scripted wave (the hand's roll and elbow change direction every few frames): q_nom jumping
    to each frame leaves the command 42 ms behind it (K closes each jump in ≈ 1/K); on the continuous
    path (``safety.target_path: continuous``) the command follows q_nom within 4 ms and the whole lag
    falls 142 → 108 ms (measured), as safe against the truth."""
    jump = _scripted_fidelity(scenario="wave", target_path=TargetPath.JUMP)
    continuous = _scripted_fidelity(scenario="wave", target_path=TargetPath.CONTINUOUS)
    assert continuous["fidelity"]["lag_ms_command"] <= jump["fidelity"]["lag_ms_command"] - 25.0, continuous["fidelity"]
    assert continuous["fidelity"]["lag_ms"] <= jump["fidelity"]["lag_ms"] - 20.0, continuous["fidelity"]
    assert continuous["fidelity"]["rms_true_free"] <= jump["fidelity"]["rms_true_free"], continuous["fidelity"]
    assert continuous["true_min_h_self"] >= -1e-3 and continuous["true_contacts_robot_human"] == 0, continuous
    assert continuous["robot_approach_steps"] == 0 and continuous["nan_count"] == 0, continuous


def test_the_retargeting_by_directions_points_the_arms_where_the_person_does() -> None:
    """The scripted reach retargeted by directions: the retargeting's own direction error (robot at
    q_true) p50 / p95 15.1 / 24.1° with the paper's map, 4.9 / 16.6° by directions (measured); the
    controller adds < 2° to it, it tracks as well (rms_true_free ≤ 0.05 rad) and stays safe against
    the truth."""
    linear, directions = _scripted_fidelity("linear")["fidelity"], _scripted_fidelity("directions")
    fidelity = directions["fidelity"]
    assert fidelity["direction_error_deg_p50_at_target"] <= 0.5 * linear["direction_error_deg_p50_at_target"], fidelity
    assert fidelity["direction_error_deg_p95_at_target"] <= 0.75 * linear["direction_error_deg_p95_at_target"], fidelity
    assert fidelity["direction_error_deg_p95"] <= fidelity["direction_error_deg_p95_at_target"] + 2.0, fidelity
    assert fidelity["rms_true_free"] <= 0.05, fidelity
    assert directions["true_min_h_self"] >= -1e-3 and directions["true_contacts_robot_human"] == 0, directions
    assert directions["robot_approach_steps"] == 0 and directions["nan_count"] == 0, directions


def run_cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "safemimic.cli", "evaluate", *args],
                          cwd=REPO, capture_output=True, text=True, timeout=300)


def test_same_input_gives_identical_metrics_and_the_figures(tmp_path: Path) -> None:
    """Two runs of the CLI: metrics.json equal byte for byte except the two wall-clock QP timings."""
    texts = []
    for name in ("a", "b"):
        done = run_cli("--scenario", "cross-arm-reach", "--seconds", "4", "--out", str(tmp_path / name))
        assert done.returncode == 0, done.stderr
        assert "min_h_self" in done.stdout and "evaluate (with and without CBF)" in done.stderr  # table and progress
        texts.append((tmp_path / name / "metrics.json").read_text())
    first, second = (json.loads(text) for text in texts)
    assert set(first) == {"cbf", "nominal", "input"}
    assert deterministic_part(first) == deterministic_part(second)

    def without_timings(text: str) -> str:
        return "\n".join(line for line in text.splitlines() if not any(f'"{k}"' in line for k in TIMING_KEYS))

    assert without_timings(texts[0]) == without_timings(texts[1])
    assert all(first[run][k] > 0 for run in ("cbf", "nominal") for k in TIMING_KEYS)
    assert first["input"]["control_steps"] == 2000 and first["input"]["seconds"] == 4.0
    for figure in ("joints.png", "barriers.png", "snapshot.png"):
        data = (tmp_path / "a" / figure).read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 20_000, figure
    contacts = json.loads((tmp_path / "a" / "contacts.json").read_text())
    assert contacts["nominal"]["robot_robot"]["steps"] == first["nominal"]["contacts_robot_robot"] > 0


def test_recording_with_shuffled_keys_and_an_extra_key_evaluates(tmp_path: Path) -> None:
    """The same scenario as a recording: keypoints in another order plus an unknown key give the
    very same numbers as the canonical file."""
    recording = scenario_recording(get_scenario("side-by-side-arm-raise"), 3.0, 30.0, Placement(y=0.7))
    canonical = tmp_path / "canonical.npz"
    order = np.random.default_rng(3).permutation(len(KEYPOINT_NAMES))
    np.savez(canonical, names=np.array(KEYPOINT_NAMES), t=recording.t, xyz=recording.xyz,
             fps=np.float64(recording.fps), conf=recording.conf)
    shuffled = tmp_path / "shuffled.npz"
    np.savez(shuffled, xyz=recording.xyz[:, order], camera_serial=np.array("ZED-12345"), fps=np.float64(recording.fps),
             conf=recording.conf[:, order], t=recording.t, names=np.array(KEYPOINT_NAMES)[order])
    results = [
        deterministic_part(evaluate(evaluation_config(str(path), None, "recorded", None)).metrics())
        for path in (canonical, shuffled)
    ]
    assert results[0]["input"].pop("source") == "replay canonical.npz"
    assert results[1]["input"].pop("source") == "replay shuffled.npz"
    assert results[0] == results[1]
    assert results[0]["input"]["frames"] == 90 and results[0]["cbf"]["nan_count"] == 0


def test_real_motion_capture_with_walking_and_turning_evaluates() -> None:
    clip = MOCAP_DIR / "bandai1_stand_then_dance.npz"
    if not clip.is_file():
        print(f"skipping: motion capture clip not found at {clip}")
        pytest.skip(f"motion capture clip not found at {clip}")
    conf = evaluation_config(str(clip), None, "facing", None)
    metrics = evaluate(conf, seconds=4.0).metrics()
    assert metrics["input"]["control_steps"] == 2000
    for run in ("cbf", "nominal"):
        assert metrics[run]["nan_count"] == 0
    assert metrics["cbf"]["min_h_self"] >= -1e-3  # self pairs: the robot alone decides, always kept


def test_a_broad_person_standing_in_an_arms_margin_is_backed_out_of(tmp_path: Path) -> None:
    """The development dance by a person whose shoulders are 0.37 m apart (the broadened variant),
    beside the robot: for its first seconds they stand with the right forearm inside the margin of
    the robot's left forearm at home. With backing out (the default) the robot leaves that margin
    once they have been seen still for 0.5 s (their capsules spread no further than a slow sway
    would), touching them only while it does (their forearm sways onto its hand at 0.54 s); with it
    off the intrusion stop holds the robot where it is, in contact most of the time. Neither is
    robot-caused."""
    clip = MOCAP_DIR / "bandai1_stand_then_dance.npz"
    if not clip.is_file():
        pytest.skip(f"motion capture clip not found at {clip}")
    fields, names = read_recording(clip)
    broad = tmp_path / "broad.npz"
    np.savez(broad, **{**fields, "xyz": broadened(fields["xyz"], names, 0.37)})
    runs = {}
    for backout in (0.05, 0.0):
        conf = evaluation_config(str(broad), None, "side-by-side", None)
        conf = conf.model_copy(update={"safety": conf.safety.model_copy(update={"intrusion_backout_mps": backout})})
        metrics = evaluate(conf, seconds=4.0).metrics()
        assert metrics["input"]["intrusion_backout_mps"] == backout and metrics["input"]["on_intrusion"] == "stop"
        runs[backout] = metrics["cbf"]
    assert evaluation_config(str(broad), None, "side-by-side", None).safety.intrusion_backout_mps == 0.05  # default
    assert runs[0.0]["true_contacts_robot_human"] > 1000 and runs[0.0]["min_h_human"] < -0.05  # frozen inside
    assert runs[0.05]["true_contacts_robot_human"] <= 0.1 * runs[0.0]["true_contacts_robot_human"]  # the goal's 10 %
    assert runs[0.05]["min_h_human"] > runs[0.0]["min_h_human"]
    assert runs[0.0]["backing_out_steps"] == 0 < runs[0.05]["backing_out_steps"] <= runs[0.05]["protective_stop_steps"]
    assert runs[0.05]["protective_stop_steps"] < runs[0.0]["protective_stop_steps"]  # it stood less
    for run in runs.values():
        assert run["robot_caused_contact_steps"] == 0 and run["nan_count"] == 0 and run["min_h_self"] >= -1e-3


def test_unusable_input_exits_2_with_the_reason(tmp_path: Path) -> None:
    done = run_cli("--skeleton", str(tmp_path / "missing.npz"), "--out", str(tmp_path / "out"))
    assert done.returncode == 2 and "missing.npz" in done.stderr
    done = run_cli("--scenario", "cross-arm-reach", "--seconds", "-1", "--out", str(tmp_path / "out"))
    assert done.returncode == 2 and "seconds" in done.stderr


def test_suite_over_the_development_clips_writes_one_row_per_clip_and_placement(tmp_path: Path) -> None:
    """``--suite``: every clip × placement evaluated in 2 processes, a folder each, the summary in
    JSON, Markdown and PNG; a bad file is reported in its row while the others run (exit 1)."""
    clips = sorted(MOCAP_DIR.glob("*.npz"))
    if not clips:
        pytest.skip(f"motion capture clips not found in {MOCAP_DIR}")
    suite = tmp_path / "clips"
    suite.mkdir()
    for clip in clips:
        (suite / clip.name).symlink_to(clip)
    (suite / "broken.npz").write_bytes(b"not a zip file")
    out = tmp_path / "out"
    done = run_cli("--suite", str(suite), "--seconds", "1.5", "--jobs", "2", "--out", str(out))
    assert done.returncode == 1, done.stderr  # one run failed, the rest were evaluated
    summary = json.loads((out / "summary.json").read_text())
    assert summary["settings"]["latency_ms"] == 60.0 and summary["settings"]["placements"] == ["side-by-side", "facing"]
    rows = {(r["clip"], r["placement"]): r for r in summary["runs"]}
    expected = {(c.stem, p) for c in [*clips, suite / "broken.npz"] for p in ("side-by-side", "facing")}
    assert set(rows) == expected and len(summary["runs"]) == len(expected)
    assert "broken.npz" in rows[("broken", "facing")]["error"]
    for clip in clips:
        for placement in ("side-by-side", "facing"):
            row = rows[(clip.stem, placement)]
            assert tuple(row["cbf"]) == RUN_KEYS and row["cbf"]["nan_count"] == 0
            folder = out / f"{clip.stem}-{placement}"
            assert json.loads((folder / "metrics.json").read_text())["cbf"] == row["cbf"]
            assert (folder / "snapshot.png").is_file()
    table = (out / "summary.md").read_text()
    assert sum(line.startswith("| bandai") for line in table.splitlines()) == 2 * len(clips)
    assert "**failed:**" in table and "robot-caused" in table
    fidelity = rows[(clips[0].stem, "side-by-side")]["cbf"]["fidelity"]
    cell = [("—" if fidelity[key] is None else f"{fidelity[key]:.0f}")
            for key in ("lag_ms", "lag_ms_target", "lag_ms_command", "lag_ms_servo", "lag_ms_limits_floor")]
    # the lag, where it comes from, and its limits floor
    assert f"| {cell[0]} ({cell[1]} / {cell[2]} / {cell[3]}) / {cell[4]} |" in table
    walk = rows[("bandai1_slash_sword", "facing")]["cbf"]  # a person walking through the robot: it stops
    step_s = 1.0 / load_config(environ={}).safety.rate_hz
    assert walk["protective_stop_steps"] > 0
    assert f"| {walk['protective_stop_steps'] * step_s:.2f} / {walk['backing_out_steps'] * step_s:.2f} / " \
        f"{walk['person_lost_steps'] * step_s:.2f} |" in table
    assert summary["goals"] == goal_report(summary["runs"])  # the evaluated runs, the broken one left out
    assert all(g["met"] + g["failed"] + g["not_judged"] == 2 * len(clips) for g in summary["goals"])
    assert "\n".join(goals_markdown(summary["goals"])) in table
    assert (out / "summary.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "broken" in done.stderr and f"{2 * len(clips)} run folders" in done.stdout


def test_the_swept_person_changes_the_rows_and_h_is_reported_against_the_measured_person() -> None:
    """``safety.human_predict_s`` (0.093 s, the default) against 0: both runs (with the CBF) are the same
    until the first human state with a measured velocity is applied; at that step (same robot
    state) the reported h, against the perceived person as measured, is the same in both, and after
    it the swept rows move the robot differently. The paper's raise stays safe either way."""
    conf = evaluation_config(None, "side-by-side-arm-raise", "side-by-side", None)
    evaluations = []
    for predict_s in (0.0, 0.093):
        swept = conf.model_copy(update={"safety": conf.safety.model_copy(update={"human_predict_s": predict_s})})
        evaluations.append(evaluate(swept, seconds=4.0))
    measured, swept = (e.cbf for e in evaluations)
    first = next(i for i, state in enumerate(evaluations[0].human.states) if state.capsule_velocities.any())
    moving = np.flatnonzero(measured.human == first)[0]  # the first state with a measured velocity
    np.testing.assert_array_equal(measured.q_sim[:moving], swept.q_sim[:moving])
    np.testing.assert_allclose(swept.h[moving], measured.h[moving], atol=1e-12)
    assert np.abs(swept.q_sim[moving:] - measured.q_sim[moving:]).max() > 1e-3
    for e, predict_s in zip(evaluations, (0.0, 0.093), strict=True):
        metrics = e.metrics()
        cbf = metrics["cbf"]
        assert cbf["min_h_human"] >= -1e-3 and cbf["true_contacts_robot_human"] == 0, cbf
        assert metrics["input"]["human_predict_s"] == predict_s  # which sweep the run had
