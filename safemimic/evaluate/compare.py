"""``safemimic compare BEFORE AFTER``: two evaluation suites side by side, before → after a change.

    safemimic evaluate --suite clips/ --out results/before
    SAFEMIMIC__SAFETY__HUMAN_PREDICT_S=0 safemimic evaluate --suite clips/ --out results/after
    safemimic compare results/before results/after --out results/compare.md

BEFORE and AFTER are ``safemimic evaluate --suite`` output folders or their ``summary.json``
(:mod:`safemimic.evaluate.suite`). Runs are matched by (clip, placement); a run evaluated on one
side only, or failed on either, is listed and left out of the figures. The report (markdown, on
standard output; ``--out`` also writes it):

- the settings of both suites, with a warning where they differ (latency, noise, dropout, seed,
  robot model): a change is only measured on the same inputs; and the stack parameters each run
  records (its ``input``: γ, φ, K, the look-ahead, the sweep, the margins, feed-forward, the
  target path, the intrusion policy, the retargeting method, the point filter) that differ;
- the figures over the CBF runs both evaluated (:data:`METRICS`: true contacts, robot-caused and
  approach steps with their commanded share, robot–robot contacts, the worst min self h at the
  simulated joints, NaN, hold and motor-saturated steps, the median lag, ``rms_true_free`` summed),
  before → after;
- the goals (:func:`~safemimic.evaluate.goals.goal_report`): runs that meet each, before → after;
- one row per run whose figures changed (every run with ``--all``), a safety figure that got worse
  in **bold**.

A safety figure is worse when it grows (contacts, robot-caused or approach steps, robot–robot
contacts, NaN, hold steps, steps with a motor at its torque limit) or, for min self h, falls; the
fidelity figures (lag, RMS) are shown, never judged. Exit status 0; 1 with ``--fail-on-worse``
when some run's safety figure got worse (a CI gate on a change); 2 for unusable input.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from safemimic.evaluate.goals import goal_report
from shared.cli_args import check_output_path
from shared.entrypoint import ParagraphHelpFormatter
from shared.errors import SafemimicError

#: The settings whose difference makes two suites measure different inputs.
SETTINGS = ("latency_ms", "latency_jitter_ms", "depth_noise_m", "dropout", "dropout_frames", "seed", "robot_model",
            "seconds")
#: What a run's ``input`` records about the run itself (or the suite's inputs, :data:`SETTINGS`) rather
#: than the stack's parameters.
_PER_RUN = frozenset({"source", "placement", "frames", "fps", "control_steps", "free_steps", "true_person_complete",
                      *SETTINGS})


class CompareError(SafemimicError, ValueError):
    """A suite that cannot be compared (missing, not a suite, unreadable): its path and why."""


@dataclass(frozen=True)
class Metric:
    """One figure of a CBF run: ``get`` reads it from a ``summary.json`` run (None: not measured),
    ``total`` combines the runs' values (``over`` says how), ``worse`` says which way is worse (+1:
    higher, −1: lower, 0: not judged), ``scale`` and ``fmt`` how it is printed. Values are compared
    as printed: a difference below the printed precision is no change."""

    name: str
    get: Callable[[dict[str, Any]], float | None]
    total: Callable[[list[float]], float]
    over: str  # how ``total`` combines the runs, for the report
    worse: int
    fmt: str = ".0f"
    scale: float = 1.0

    def text(self, value: float | None) -> str:
        return "—" if value is None else format(value * self.scale, self.fmt)

    def printed(self, value: float | None) -> float | None:
        """``value`` as :meth:`text` shows it."""
        return None if value is None else float(self.text(value))


def _cbf(key: str) -> Callable[[dict[str, Any]], float | None]:
    return lambda run: run["cbf"].get(key)


def _fidelity(key: str) -> Callable[[dict[str, Any]], float | None]:
    return lambda run: run["cbf"].get("fidelity", {}).get(key)


#: What the report compares, in its column order.
METRICS: tuple[Metric, ...] = (
    Metric("true contacts", _cbf("true_contacts_robot_human"), sum, "sum", +1),
    Metric("robot-caused", _cbf("robot_caused_contact_steps"), sum, "sum", +1),
    Metric("robot-caused, commanded", _cbf("robot_caused_contact_steps_commanded"), sum, "sum", +1),
    Metric("approaches", _cbf("robot_approach_steps"), sum, "sum", +1),
    Metric("approaches, commanded", _cbf("robot_approach_steps_commanded"), sum, "sum", +1),
    Metric("robot–robot contacts", _cbf("contacts_robot_robot"), sum, "sum", +1),
    Metric("min self h (mm)", _cbf("true_min_h_self"), min, "worst", -1, ".1f", 1e3),
    Metric("NaN", _cbf("nan_count"), sum, "sum", +1),
    Metric("hold steps", _cbf("hold_steps"), sum, "sum", +1),
    Metric("motor-saturated steps", _cbf("torque_saturated_steps"), sum, "sum", +1),
    Metric("lag (ms)", _fidelity("lag_ms"), statistics.median, "median", 0, ".1f"),
    Metric("rms_true_free (rad)", _fidelity("rms_true_free"), sum, "sum", 0, ".3f"),
)


def load_summary(path: Path) -> dict[str, Any]:
    """A suite's ``summary.json`` from its folder or the file itself (:class:`CompareError` if unusable)."""
    file = path / "summary.json" if path.is_dir() else path
    if not file.is_file():
        raise CompareError(f"{path}: no summary.json (a 'safemimic evaluate --suite' output folder or its summary.json)")
    try:
        summary = json.loads(file.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise CompareError(f"{file}: unreadable: {exc}") from exc
    if not isinstance(summary, dict) or not isinstance(summary.get("runs"), list):
        raise CompareError(f"{file}: not a suite summary (no 'runs' list)")
    return summary


def _key(run: dict[str, Any]) -> tuple[str, str]:
    return str(run.get("clip")), str(run.get("placement"))


def _evaluated(summary: dict[str, Any]) -> dict[tuple[str, str], dict[str, Any]]:
    return {_key(run): run for run in summary["runs"] if isinstance(run, dict) and "error" not in run and "cbf" in run}


def worse(metric: Metric, before: float | None, after: float | None) -> bool:
    """Whether ``after`` is worse than ``before`` as printed, for a judged ``metric`` (an unmeasured
    value never is)."""
    b, a = metric.printed(before), metric.printed(after)
    if metric.worse == 0 or b is None or a is None:
        return False
    return (a - b) * metric.worse > 0


def _change(metric: Metric, before: float | None, after: float | None) -> str:
    if metric.text(before) == metric.text(after):
        return metric.text(after)
    text = f"{metric.text(before)} → {metric.text(after)}"
    return f"**{text}**" if worse(metric, before, after) else text


def _total(metric: Metric, runs: list[dict[str, Any]]) -> float | None:
    values = [v for v in (metric.get(run) for run in runs) if v is not None]
    return float(metric.total(values)) if values else None


@dataclass
class Comparison:
    """Two suites matched run by run: ``common`` (clip, placement) keys evaluated on both sides,
    the ``only_before`` / ``only_after`` ones, and the runs that got worse."""

    before: dict[str, Any]
    after: dict[str, Any]

    def __post_init__(self) -> None:
        self.runs_before, self.runs_after = _evaluated(self.before), _evaluated(self.after)
        self.common = sorted(self.runs_before.keys() & self.runs_after.keys())
        self.only_before = sorted(self.runs_before.keys() - self.runs_after.keys())
        self.only_after = sorted(self.runs_after.keys() - self.runs_before.keys())
        if not self.common:
            raise CompareError("the two suites have no evaluated run in common (matched by clip and placement)")

    def worse_runs(self) -> list[tuple[str, str]]:
        """The common runs in which some safety figure got worse."""
        return [k for k in self.common
                if any(worse(m, m.get(self.runs_before[k]), m.get(self.runs_after[k])) for m in METRICS)]

    def markdown(self, every_run: bool = False) -> str:
        """The report (module docstring); ``every_run``: a row for every common run, not only the changed."""
        lines = ["# Comparison of two evaluation suites", "", *self._settings_lines(), *self._totals_lines(),
                 *self._goals_lines(), *self._runs_lines(every_run)]
        for label, keys in (("before", self.only_before), ("after", self.only_after)):
            if keys:
                lines += ["", f"Evaluated only {label} (left out): " + ", ".join(f"{c} ({p})" for c, p in keys) + "."]
        return "\n".join(lines) + "\n"

    def _sides(self) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
        return [self.runs_before[k] for k in self.common], [self.runs_after[k] for k in self.common]

    def _totals_lines(self) -> list[str]:
        before, after = self._sides()
        lines = [f"{len(self.common)} runs evaluated in both (matched by clip and placement). Their CBF runs together, "
                 "before → after (a safety figure that got worse in **bold**):", "",
                 "| figure | over the runs | before | after |", "|---|---|---|---|"]
        for m in METRICS:
            b, a = _total(m, before), _total(m, after)
            mark = "**" if worse(m, b, a) else ""
            lines.append(f"| {m.name} | {m.over} | {m.text(b)} | {mark}{m.text(a)}{mark} |")
        return lines

    def _goals_lines(self) -> list[str]:
        before, after = self._sides()
        lines = ["", "## Goals", ""]
        try:
            reports = goal_report(before), goal_report(after)
        except (KeyError, TypeError) as exc:  # a summary written by an evaluator without that figure
            return lines + [f"Not compared: a run of these summaries has no figure {exc} (an older evaluator's?)."]
        lines += ["Runs that meet each goal of the project (`safemimic.evaluate.goals`), before → after (fewer in "
                  "**bold**):", "", "| goal | before | after |", "|---|---|---|"]
        for b, a in zip(*reports):
            mark = "**" if a["met"] < b["met"] else ""
            lines.append(f"| {b['goal']} | {b['met']} of {len(before)} | {mark}{a['met']} of {len(after)}{mark} |")
        return lines

    def _runs_lines(self, every_run: bool) -> list[str]:
        pairs = [(k, self.runs_before[k], self.runs_after[k]) for k in self.common]
        rows = [(k, b, a) for k, b, a in pairs
                if every_run or any(m.printed(m.get(b)) != m.printed(m.get(a)) for m in METRICS)]
        lines = ["", "## Runs" + ("" if every_run else " that changed"), ""]
        if not rows:
            return lines + ["None: every figure of every run is the same."]
        lines += ["| clip | placement | " + " | ".join(m.name for m in METRICS) + " |",
                  "|---|---|" + "---|" * len(METRICS)]
        for (clip, placement), b, a in rows:
            lines.append(f"| {clip} | {placement} | " + " | ".join(_change(m, m.get(b), m.get(a)) for m in METRICS) + " |")
        return lines

    def _settings_lines(self) -> list[str]:
        sb, sa = self.before.get("settings", {}), self.after.get("settings", {})
        differ = [name for name in SETTINGS if sb.get(name) != sa.get(name)]
        if differ:
            lines = ["**The two suites were evaluated on different inputs**, so their difference is not only the "
                     "change: " + "; ".join(f"{n} {sb.get(n)} → {sa.get(n)}" for n in differ) + "."]
        else:
            lines = ["Inputs (both): " + ", ".join(f"{n} {sb.get(n)}" for n in SETTINGS if n in sb) + "."]
        changed = self.changed_parameters()
        if changed:
            lines.append("Stack parameters recorded with the runs that differ: "
                         + "; ".join(f"{n} {b} → {a}" for n, (b, a) in changed.items()) + ".")
        return lines + [""]

    def changed_parameters(self) -> dict[str, tuple[Any, Any]]:
        """The stack's parameters each run records (``input``, :func:`~safemimic.evaluate.metrics.input_metrics`)
        whose value differs between the suites, on the first common run."""
        first = self.common[0]
        b, a = self.runs_before[first].get("input", {}), self.runs_after[first].get("input", {})
        return {n: (b.get(n), a.get(n)) for n in sorted(b.keys() | a.keys())
                if n not in _PER_RUN and b.get(n) != a.get(n) and not isinstance(b.get(n, a.get(n)), (dict, list))}


def build_parser(parser: argparse.ArgumentParser | None = None) -> argparse.ArgumentParser:
    parser = parser or argparse.ArgumentParser(prog="safemimic compare")
    parser.formatter_class = ParagraphHelpFormatter
    parser.description = (
        "Two evaluation suites side by side, before → after a change: their CBF runs together (true "
        "contacts, robot-caused and approach steps, robot–robot contacts, min self h, NaN, hold steps, steps with a "
        "motor at its torque limit, lag, "
        "rms_true_free), the project's goals met, and the runs whose figures changed. Runs are matched by clip "
        "and placement; evaluate both on the same inputs (the report warns where their settings differ).\n\n"
        "  safemimic evaluate --suite clips/ --out before\n"
        "  SAFEMIMIC__SAFETY__GAMMA=5 safemimic evaluate --suite clips/ --out after\n"
        "  safemimic compare before after"
    )
    parser.add_argument("before", type=Path, help="a 'safemimic evaluate --suite' output folder (or its summary.json)")
    parser.add_argument("after", type=Path, help="the same for the changed stack")
    parser.add_argument("--out", type=Path, metavar="FILE.md", help="also write the report to this file")
    parser.add_argument("--all", action="store_true", help="a row for every run, not only the ones that changed")
    parser.add_argument("--fail-on-worse", action="store_true",
                        help="exit 1 when a safety figure of some run got worse (a gate for a change)")
    return parser


def run(args: argparse.Namespace) -> int:
    try:
        if args.out is not None:
            check_output_path(args.out, "--out", folder=False)
        comparison = Comparison(load_summary(args.before), load_summary(args.after))
    except ValueError as exc:  # a CompareError, or an --out that cannot be written
        print(f"safemimic compare: {exc}", file=sys.stderr)
        return 2
    report = comparison.markdown(every_run=args.all)
    print(report, end="", flush=True)
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(report, encoding="utf-8")
    worse_runs = comparison.worse_runs()
    if worse_runs:
        print(f"{len(worse_runs)} run(s) with a safety figure worse: "
              + ", ".join(f"{c} ({p})" for c, p in worse_runs), file=sys.stderr)
    return 1 if args.fail_on_worse and worse_runs else 0

