"""The suite's goals (safemimic.evaluate.goals): each goal checked on a run's metrics, the runs
whose own floor already misses a goal counted apart, failed runs left out, and the section in
summary.md (the section inside a suite's summary.md: tests/test_evaluate.py)."""

from __future__ import annotations

import copy
from typing import Any

from safemimic.evaluate.goals import FAILING_SHOWN, GOALS, goal_report, goals_markdown

NAMES = [goal.name for goal in GOALS]


def run(clip: str = "clip", **cbf: Any) -> dict[str, Any]:
    """A run meeting every goal, with ``cbf`` keys replaced (``fidelity`` merged)."""
    fidelity = {"lag_ms": 75.0, "rms_true_free": 0.04, "rms_true_free_latency_floor": 0.02,
                "direction_error_deg_p95": 12.0, "direction_error_deg_p95_at_target": 8.0}
    fidelity.update(cbf.pop("fidelity", {}))
    metrics = {"contacts_robot_robot": 0, "min_h_self": 0.002, "true_min_h_self": 0.002, "robot_caused_contact_steps": 0,
               "robot_approach_steps": 0, "true_contacts_robot_human": 3, "true_contacts_fixed_bodies": 0,
               "nan_count": 0, "fidelity": fidelity, **cbf}
    return {"clip": clip, "placement": "facing", "cbf": metrics, "nominal": {"true_contacts_robot_human": 100},
            "input": {"latency_ms": 60.0}}


def row(report: list[dict[str, Any]], name: str) -> dict[str, Any]:
    return report[NAMES.index(name)]


def test_a_run_meeting_every_goal_meets_every_goal() -> None:
    report = goal_report([run()])
    assert [r["goal"] for r in report] == NAMES
    assert all((r["met"], r["failed"], r["beyond_floor"], r["not_judged"], r["failing"]) == (1, 0, 0, 0, [])
               for r in report)


def test_each_goal_fails_on_its_own_metric() -> None:
    bad = {
        "robot–robot contacts 0": {"contacts_robot_robot": 1},
        "min self h ≥ −1 mm": {"true_min_h_self": -0.0011},
        "robot-caused contact steps 0": {"robot_caused_contact_steps": 1},
        "robot approach steps 0": {"robot_approach_steps": 2},
        "true contacts ≤ 10 % of the run without the CBF": {"true_contacts_robot_human": 11},
        "no NaN": {"nan_count": 1},
        "lag ≤ latency + 20 ms": {"fidelity": {"lag_ms": 81.0}},
        "rms_true_free ≤ 0.05 rad": {"fidelity": {"rms_true_free": 0.051}},
        "arm direction p95 ≤ 15°": {"fidelity": {"direction_error_deg_p95": 15.5}},
    }
    assert set(bad) == set(NAMES)
    for name, change in bad.items():
        report = goal_report([run("bad", **copy.deepcopy(change)), run("good")])
        for other in report:
            expected = (1, 1, ["bad (facing)"]) if other["goal"] == name else (2, 0, [])
            assert (other["met"], other["failed"], other["failing"]) == expected, (name, other)


def test_the_self_barrier_goal_judges_the_simulated_joints_not_the_filters_own_view() -> None:
    """The filter's q_cbf may keep h ≥ 0 while the robot, whose servos trail it, goes inside: the
    goal is the robot's (``true_min_h_self``)."""
    inside = run("inside", min_h_self=0.001, true_min_h_self=-0.0025)
    filter_only = run("filter", min_h_self=-0.004, true_min_h_self=0.0005)
    goal = row(goal_report([inside, filter_only]), "min self h ≥ −1 mm")
    assert (goal["met"], goal["failed"], goal["failing"]) == (1, 1, ["inside (facing)"])


def test_a_run_whose_floor_misses_the_goal_is_counted_beyond_the_floor() -> None:
    inside_the_legs = run("walk", true_contacts_robot_human=40, true_contacts_fixed_bodies=15)  # floor 15 > 10
    closing_in = run("reach", true_contacts_robot_human=40, true_contacts_fixed_bodies=5)  # floor 5 ≤ 10
    late = run("late", fidelity={"rms_true_free": 0.2, "rms_true_free_latency_floor": 0.09})
    retargeted = run("far", fidelity={"direction_error_deg_p95": 40.0, "direction_error_deg_p95_at_target": 20.0})
    seen_late = run("fast", fidelity={"direction_error_deg_p95": 30.0, "direction_error_deg_p95_at_target": 10.0,
                                      "direction_error_deg_p95_latency_floor": 18.0})
    behind = run("slow", fidelity={"direction_error_deg_p95": 30.0, "direction_error_deg_p95_at_target": 10.0,
                                   "direction_error_deg_p95_latency_floor": 12.0})
    too_fast = run("punch", fidelity={"lag_ms": 130.0, "lag_ms_limits_floor": 91.0})  # the bounds alone: 91 > 80
    within_reach = run("raise", fidelity={"lag_ms": 99.0, "lag_ms_limits_floor": 58.0})
    report = goal_report([inside_the_legs, closing_in, late, retargeted, seen_late, behind, too_fast, within_reach])
    contacts = row(report, "true contacts ≤ 10 % of the run without the CBF")
    assert (contacts["failed"], contacts["beyond_floor"]) == (2, 1)
    assert contacts["failing"] == ["walk (facing) [floor]", "reach (facing)"]
    assert row(report, "rms_true_free ≤ 0.05 rad")["failing"] == ["late (facing) [floor]"]
    assert row(report, "lag ≤ latency + 20 ms")["failing"] == ["punch (facing) [floor]", "raise (facing)"]
    assert row(report, "arm direction p95 ≤ 15°")["failing"] == ["far (facing) [floor]", "fast (facing) [floor]",
                                                                  "slow (facing)"]


def test_no_contact_without_the_cbf_allows_none_with_it() -> None:
    quiet = run(true_contacts_robot_human=1)
    quiet["nominal"]["true_contacts_robot_human"] = 0
    assert row(goal_report([quiet]), "true contacts ≤ 10 % of the run without the CBF")["failed"] == 1


def test_missing_metrics_are_not_judged_and_failed_runs_are_left_out() -> None:
    unjudged = run(fidelity={"lag_ms": None, "rms_true_free": None, "direction_error_deg_p95": None})
    report = goal_report([unjudged, {"clip": "broken", "placement": "facing", "error": "no such file"}, None])
    for name in ("lag ≤ latency + 20 ms", "rms_true_free ≤ 0.05 rad", "arm direction p95 ≤ 15°"):
        assert (row(report, name)["not_judged"], row(report, name)["met"], row(report, name)["failed"]) == (1, 0, 0)
    assert row(report, "no NaN")["met"] == 1  # the failed run is not counted anywhere


def test_the_goals_section_names_the_failing_runs_and_says_how_many_more() -> None:
    runs = [run(f"walk{i}", robot_caused_contact_steps=1) for i in range(FAILING_SHOWN + 2)]
    section = goals_markdown(goal_report(runs))
    assert section[0] == "## Goals"
    line = next(line for line in section if line.startswith("| robot-caused contact steps 0 |"))
    assert line.startswith(f"| robot-caused contact steps 0 | 0 | {FAILING_SHOWN + 2} | 0 | 0 | ")
    assert line.endswith("and 2 more (summary.json) |") and f"walk{FAILING_SHOWN - 1} (facing)" in line
    assert f"walk{FAILING_SHOWN} (facing)" not in line
    assert f"| no NaN | {FAILING_SHOWN + 2} | 0 | 0 | 0 | — |" in section
