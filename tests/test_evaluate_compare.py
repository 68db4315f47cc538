"""``safemimic compare``: two evaluation suites before → after (safemimic.evaluate.compare).

Two real suites of the evaluator (one clip, the stack's default and the person not swept ahead),
then the report's rules on suites written here: runs matched by clip and placement, a safety
figure worse in bold (as printed), the goals met, different inputs warned about, unusable input
a clear error (exit 2), ``--fail-on-worse`` a gate (exit 1).
"""

from __future__ import annotations

import copy
import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from safemimic.evaluate.compare import METRICS, Comparison, CompareError, load_summary, worse
from safemimic.evaluate.metrics import RUN_KEYS
from tests.support.team import MOCAP_DIR, REPO

CLIP = MOCAP_DIR / "bandai2_raise_up_both_hands.npz"


def safemimic(*args: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "safemimic.cli", *args], cwd=REPO, capture_output=True, text=True,
                          timeout=300, env={**os.environ, **(env or {})})


def test_two_real_suites_compare_with_the_parameter_that_changed(tmp_path: Path) -> None:
    """The evaluator's own summaries: a suite against itself has no change; against the same clip
    evaluated with another look-ahead and without the person's sweep, the report names both."""
    if not CLIP.is_file():
        pytest.skip(f"motion capture clip not found: {CLIP}")
    clips = tmp_path / "clips"
    clips.mkdir()
    (clips / CLIP.name).symlink_to(CLIP)
    after = {"SAFEMIMIC__SAFETY__HUMAN_PREDICT_S": "0", "SAFEMIMIC__SAFETY__HUMAN_LOOKAHEAD_S": "0.2"}
    for name, env in (("before", {}), ("after", after)):
        done = safemimic("evaluate", "--suite", str(clips), "--seconds", "2", "--jobs", "2", "--quiet",
                         "--out", str(tmp_path / name), env=env)
        assert done.returncode == 0, done.stderr

    same = safemimic("compare", str(tmp_path / "before"), str(tmp_path / "before"), "--fail-on-worse")
    assert same.returncode == 0, same.stderr
    assert "2 runs evaluated in both" in same.stdout and "None: every figure of every run is the same." in same.stdout
    assert "Stack parameters" not in same.stdout

    report = tmp_path / "report" / "compare.md"
    done = safemimic("compare", str(tmp_path / "before"), str(tmp_path / "after" / "summary.json"), "--all",
                     "--out", str(report))
    assert done.returncode == 0, done.stderr
    assert report.read_text() == done.stdout
    assert "human_lookahead_s 0.11 → 0.2; human_predict_s 0.093 → 0.0." in done.stdout  # what differs between the stacks
    assert "The two suites were evaluated on different inputs" not in done.stdout
    rows = [line for line in done.stdout.splitlines() if line.startswith(f"| {CLIP.stem} |")]
    assert len(rows) == 2  # --all: both placements
    assert "| robot-caused contact steps 0 |" in done.stdout  # the goals, before and after


def _run(clip: str, placement: str, **cbf: Any) -> dict[str, Any]:
    """A run as ``summary.json`` holds it: every key of a run's metrics (0 unless given), a safe one."""
    metrics: dict[str, Any] = dict.fromkeys(RUN_KEYS, 0)
    metrics.update(true_contacts_robot_human=10, true_min_h_self=0.005, min_h_self=0.005,
                   fidelity={"lag_ms": 100.0, "rms_true_free": 0.1, "rms_true_free_latency_floor": 0.03,
                             "direction_error_deg_p95": 30.0, "direction_error_deg_p95_at_target": 20.0})
    metrics.update(cbf)
    return {"clip": clip, "placement": placement, "cbf": metrics, "nominal": {"true_contacts_robot_human": 100},
            "input": {"latency_ms": 60.0, "gamma": 10.0, "source": f"replay {clip}.npz", "frames": 300}}


def _suite(*runs: dict[str, Any], **settings: Any) -> dict[str, Any]:
    return {"settings": {"latency_ms": 60.0, "depth_noise_m": 0.0, "dropout": 0.0, "seed": 0, **settings},
            "runs": list(runs)}


def test_a_safety_figure_is_worse_in_its_own_direction_as_printed() -> None:
    by_name = {m.name: m for m in METRICS}
    contacts, self_h, lag = by_name["robot-caused"], by_name["min self h (mm)"], by_name["lag (ms)"]
    assert worse(contacts, 0, 3) and not worse(contacts, 3, 0)
    assert worse(self_h, 0.002, 0.001) and not worse(self_h, 0.001, 0.002)
    assert not worse(self_h, 0.00104, 0.00101)  # 1.0 mm both as printed: no change
    assert not worse(lag, 100.0, 300.0)  # fidelity is shown, never judged
    assert not worse(contacts, None, 3)


def test_the_report_matches_runs_marks_what_got_worse_and_counts_the_goals() -> None:
    before = _suite(_run("walk", "facing"), _run("raise", "facing"), _run("old", "facing"),
                    {"clip": "broken", "placement": "facing", "error": "not a zip file"})
    after = _suite(_run("walk", "facing", robot_caused_contact_steps=4, robot_caused_contact_steps_commanded=1),
                   _run("raise", "facing"), _run("new", "facing"))
    comparison = Comparison(before, after)
    assert comparison.common == [("raise", "facing"), ("walk", "facing")]
    assert comparison.only_before == [("old", "facing")] and comparison.only_after == [("new", "facing")]
    assert comparison.worse_runs() == [("walk", "facing")]
    text = comparison.markdown()
    assert "| robot-caused | sum | 0 | **4** |" in text and "| robot-caused, commanded | sum | 0 | **1** |" in text
    assert "| robot-caused contact steps 0 | 2 of 2 | **1 of 2** |" in text
    assert "| walk | facing | 10 | **0 → 4** | **0 → 1** |" in text
    assert "Evaluated only before (left out): old (facing)." in text and "Evaluated only after (left out): new (facing)." in text
    assert "broken" not in text  # a failed run is in neither side's figures


def test_a_small_fall_in_self_clearance_counts_once_it_shows() -> None:
    """min self h 5.0 → 4.9 mm is worse (it prints so); 5.00 → 4.96 mm prints 5.0 both: unchanged."""
    shows = Comparison(_suite(_run("raise", "facing")), _suite(_run("raise", "facing", true_min_h_self=0.0049)))
    assert shows.worse_runs() == [("raise", "facing")] and "**5.0 → 4.9**" in shows.markdown()
    hidden = Comparison(_suite(_run("raise", "facing")), _suite(_run("raise", "facing", true_min_h_self=0.00496)))
    assert hidden.worse_runs() == [] and "None: every figure of every run is the same." in hidden.markdown()


def test_different_inputs_and_parameters_are_named() -> None:
    before = _suite(_run("walk", "facing"))
    after = copy.deepcopy(_suite(_run("walk", "facing"), latency_ms=120.0))
    after["runs"][0]["input"]["gamma"] = 5.0
    text = Comparison(before, after).markdown()
    assert "**The two suites were evaluated on different inputs**" in text and "latency_ms 60.0 → 120.0" in text
    assert "Stack parameters recorded with the runs that differ: gamma 10.0 → 5.0." in text


def test_a_summary_without_a_goal_s_figure_is_compared_without_the_goals() -> None:
    """An older evaluator's summary may lack a figure a goal reads: the figures still compare."""
    old = _suite(_run("walk", "facing"))
    del old["runs"][0]["cbf"]["true_min_h_self"]
    text = Comparison(old, _suite(_run("walk", "facing"))).markdown()
    assert "Not compared: a run of these summaries has no figure 'true_min_h_self'" in text
    assert "| true contacts | sum | 10 | 10 |" in text


def test_unusable_input_is_a_clear_error(tmp_path: Path) -> None:
    with pytest.raises(CompareError, match="no summary.json"):
        load_summary(tmp_path)
    (tmp_path / "summary.json").write_text("{not json")
    with pytest.raises(CompareError, match="unreadable"):
        load_summary(tmp_path)
    (tmp_path / "summary.json").write_text(json.dumps({"settings": {}}))
    with pytest.raises(CompareError, match="no 'runs' list"):
        load_summary(tmp_path)
    with pytest.raises(CompareError, match="no evaluated run in common"):
        Comparison(_suite(_run("walk", "facing")), _suite(_run("walk", "side-by-side")))
    done = safemimic("compare", str(tmp_path), str(tmp_path / "missing"))
    assert done.returncode == 2 and "safemimic compare:" in done.stderr and "no 'runs' list" in done.stderr


def test_fail_on_worse_gates_a_change(tmp_path: Path) -> None:
    for name, steps in (("before", 0), ("after", 2)):
        (tmp_path / name).mkdir()
        (tmp_path / name / "summary.json").write_text(json.dumps(_suite(_run("walk", "facing", robot_approach_steps=steps))))
    gated = safemimic("compare", str(tmp_path / "before"), str(tmp_path / "after"), "--fail-on-worse")
    assert gated.returncode == 1 and "1 run(s) with a safety figure worse: walk (facing)" in gated.stderr
    assert safemimic("compare", str(tmp_path / "before"), str(tmp_path / "after")).returncode == 0
    assert safemimic("compare", str(tmp_path / "after"), str(tmp_path / "before"), "--fail-on-worse").returncode == 0
