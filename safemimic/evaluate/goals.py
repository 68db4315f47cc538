"""The project's safety and imitation goals, checked on every run of a suite (``summary.md``'s
"Goals", ``summary.json``'s ``"goals"``).

Each goal is a test of one CBF run's metrics (:mod:`safemimic.evaluate.metrics`); where the
evaluator measures a floor that no controller of the imitation joints can go below, a failing run
whose floor alone already misses the goal is counted apart (``beyond_floor``): the goal cannot be
met there by any command, so the run says nothing about the controller.

Safety (a person faster than the robot), with the CBF, in every run: no robot–robot contact, the
self barrier ≥ −1 mm at the simulated joints (``true_min_h_self``: the robot as it moved, not the
filter's own q_cbf), no robot-caused contact step, no approach step, true contacts at most 10 % of
the run without the CBF (0 where that run has none; floor: the steps with the person inside a
body no imitation joint moves), no NaN. Imitation: lag ≤ latency + 20 ms (floor: the lag of a
robot following the target seen one latency late as fast as its speed and acceleration bounds
allow), ``rms_true_free`` ≤ 0.05 rad (floor: the latency floor), arm direction p95 ≤ 15° (floor:
the same at the target, the retargeting's own error, or at the target seen one latency late: that
error and the latency's).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

__all__ = ["GOALS", "Goal", "goal_report", "goals_markdown"]

#: A run's metrics (a ``summary.json`` run: ``cbf``, ``nominal``, ``input``) → whether the goal holds
#: (None: the metric is missing, e.g. no free step to judge the fidelity on).
Check = Callable[[dict[str, Any]], bool | None]


@dataclass(frozen=True)
class Goal:
    """One goal: ``name`` (what it asks, as the report shows it), ``holds`` (the check) and ``floor``
    (whether the run's measured floor alone already misses the goal; None: no floor)."""

    name: str
    holds: Check
    floor: Check | None = None


def _fidelity(run: dict[str, Any], key: str) -> float | None:
    return run["cbf"]["fidelity"].get(key)


def _at_most(value: float | None, bound: float) -> bool | None:
    return None if value is None else value <= bound


def _contact_share(run: dict[str, Any], steps: int) -> bool:
    """``steps`` at most 10 % of the no-CBF run's true contacts (0 where that run has none)."""
    return steps <= 0.1 * run["nominal"]["true_contacts_robot_human"]


#: How many failing runs a row of the markdown table names (summary.json has them all).
FAILING_SHOWN = 10
#: The goals, in the order the report lists them.
GOALS: tuple[Goal, ...] = (
    Goal("robot–robot contacts 0", lambda r: r["cbf"]["contacts_robot_robot"] == 0),
    Goal("min self h ≥ −1 mm", lambda r: r["cbf"]["true_min_h_self"] is None or r["cbf"]["true_min_h_self"] >= -1e-3),
    Goal("robot-caused contact steps 0", lambda r: r["cbf"]["robot_caused_contact_steps"] == 0),
    Goal("robot approach steps 0", lambda r: r["cbf"]["robot_approach_steps"] == 0),
    Goal("true contacts ≤ 10 % of the run without the CBF",
         lambda r: _contact_share(r, r["cbf"]["true_contacts_robot_human"]),
         lambda r: not _contact_share(r, r["cbf"]["true_contacts_fixed_bodies"])),
    Goal("no NaN", lambda r: r["cbf"]["nan_count"] == 0),
    Goal("lag ≤ latency + 20 ms", lambda r: _at_most(_fidelity(r, "lag_ms"), r["input"]["latency_ms"] + 20.0),
         lambda r: _at_most(_fidelity(r, "lag_ms_limits_floor"), r["input"]["latency_ms"] + 20.0) is False),
    Goal("rms_true_free ≤ 0.05 rad", lambda r: _at_most(_fidelity(r, "rms_true_free"), 0.05),
         lambda r: _at_most(_fidelity(r, "rms_true_free_latency_floor"), 0.05) is False),
    Goal("arm direction p95 ≤ 15°", lambda r: _at_most(_fidelity(r, "direction_error_deg_p95"), 15.0),
         lambda r: any(_at_most(_fidelity(r, f"direction_error_deg_p95_{floor}"), 15.0) is False
                       for floor in ("at_target", "latency_floor"))),
)


def goal_report(runs: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per goal of :data:`GOALS`, over the evaluated ``runs`` (``summary.json`` rows; rows with an
    ``error`` are left out): ``{"goal", "met", "failed", "beyond_floor", "not_judged", "failing"}``
    — run counts, and the failing runs as ``"clip (placement)"``, those beyond the floor marked
    ``" [floor]"``."""
    evaluated = [r for r in runs if r is not None and "error" not in r]
    report = []
    for goal in GOALS:
        met = failed = beyond = unjudged = 0
        failing: list[str] = []
        for run in evaluated:
            holds = goal.holds(run)
            if holds is None:
                unjudged += 1
            elif holds:
                met += 1
            else:
                failed += 1
                floored = goal.floor is not None and bool(goal.floor(run))
                beyond += floored
                failing.append(f"{run['clip']} ({run['placement']})" + (" [floor]" if floored else ""))
        report.append({"goal": goal.name, "met": met, "failed": failed, "beyond_floor": beyond,
                       "not_judged": unjudged, "failing": failing})
    return report


def goals_markdown(report: list[dict[str, Any]]) -> list[str]:
    """``summary.md``'s "Goals" section (lines) for :func:`goal_report`'s ``report``."""
    lines = [
        "## Goals", "",
        "With the CBF, in every run. *at a floor*: failing runs where the evaluator's own floor already misses "
        "the goal (the person inside the pelvis or legs; the target seen one latency late; the robot's speed and "
        "acceleration bounds; the retargeting's error at the target), so that no command to the imitation joints "
        "can meet it there; marked [floor] in the list.", "",
        "| goal | runs met | failed | of them at a floor (no command meets it) | not judged | failing runs |",
        "|---|---|---|---|---|---|",
    ]
    for row in report:
        shown, more = row["failing"][:FAILING_SHOWN], len(row["failing"]) - FAILING_SHOWN
        failing = ", ".join(shown) + (f" and {more} more (summary.json)" if more > 0 else "") or "—"
        lines.append(f"| {row['goal']} | {row['met']} | {row['failed']} | {row['beyond_floor']} | {row['not_judged']} "
                     f"| {failing} |")
    return lines
