"""``safemimic evaluate``: run an input with and without the CBF layer; write metrics and figures.

    safemimic evaluate --scenario cross-arm-reach --out results/cross
    safemimic evaluate --skeleton clip.npz --placement facing --robot-model g1.xml --out results/clip

Writes into ``--out``: ``metrics.json`` (:mod:`services.evaluate.metrics`), ``contacts.json``
(per run: which body pairs touched, for how many steps, how deep), ``joints.png`` (the 8 joints,
nominal vs safe), ``barriers.png`` (every monitored h over time) and ``snapshot.png`` (MuJoCo at
the worst moment). Prints the two runs side by side. Exit status 0, or 2 for unusable input.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from services.evaluate.episode import Episode, EvaluationInput, HumanTrack, open_input, perceive, run_episode
from services.evaluate.metrics import RUN_KEYS, free_steps, input_metrics, run_metrics, write_metrics
from services.evaluate.progress import ProgressBar
from services.perception.scenarios import SCENARIOS
from services.perception.sources import SourceUnavailable
from services.safety.kinematics import KinematicsError, RobotKinematics
from shared.config import ConfigError, StackConfig, load_config
from services.executor.sim import SimModelError
from shared.robot_spec import RobotSpecError, configured_robot_spec

log = logging.getLogger("safemimic.evaluate")


@dataclass
class Evaluation:
    """Both runs of one input, with what they were computed from."""

    conf: StackConfig
    source: EvaluationInput
    human: HumanTrack
    kinematics: RobotKinematics
    cbf: Episode
    nominal: Episode
    placement: str

    def metrics(self) -> dict[str, Any]:
        """The content of ``metrics.json``."""
        free = free_steps(self.cbf)
        return {
            "cbf": run_metrics(self.cbf, free),
            "nominal": run_metrics(self.nominal, free),
            "input": input_metrics(self.conf, self.source, self.human, self.cbf, self.placement),
        }


def evaluation_config(
    skeleton: str | None, scenario: str | None, placement: str, robot_model: str | None, config: str | None = None
) -> StackConfig:
    """The stack configuration for one evaluation: the file (or shipped default) and the environment,
    with the input, the placement and the robot model of the command line."""
    perception: dict[str, Any] = {"placement": placement}
    if skeleton is not None:
        perception.update(source="replay", recording=str(Path(skeleton).expanduser().resolve()))
    if scenario is not None:
        perception.update(source="scenario", scenario=scenario)
    overrides: dict[str, Any] = {"perception": perception}
    if robot_model is not None:
        overrides["robot"] = {"model": str(Path(robot_model).expanduser().resolve())}
    return load_config(config, overrides=overrides)


def evaluate(conf: StackConfig, seconds: float | None = None, show_progress: bool = True) -> Evaluation:
    """Read the input, perceive it once, run it with and without the CBF layer.

    Raises SourceUnavailable, RobotSpecError, KinematicsError or SimModelError for unusable input.
    """
    source = open_input(conf, seconds)
    human = perceive(conf, source)
    kinematics = RobotKinematics(configured_robot_spec(conf))
    runs = {}
    for enforce in (True, False):
        label = "with CBF   " if enforce else "without CBF"
        n_steps = max(1, round(source.seconds * conf.safety.rate_hz))
        bar = ProgressBar(n_steps, f"evaluate {label}") if show_progress else None
        runs[enforce] = run_episode(conf, human, source.seconds, enforce, kinematics, bar.update if bar else None)
        if bar:
            bar.close()
    return Evaluation(conf, source, human, kinematics, runs[True], runs[False], conf.perception.placement)


def write_outputs(evaluation: Evaluation, out: Path) -> dict[str, Any]:
    """Write metrics.json, contacts.json and the three figures into ``out``; the metrics."""
    from services.evaluate.figures import plot_barriers, plot_joints  # matplotlib: only when writing
    from services.evaluate.snapshot import render_snapshot

    out.mkdir(parents=True, exist_ok=True)
    metrics = evaluation.metrics()
    write_metrics(out / "metrics.json", metrics)
    contacts = {"cbf": evaluation.cbf.tally.summary(), "nominal": evaluation.nominal.tally.summary()}
    (out / "contacts.json").write_text(json.dumps(contacts, indent=2) + "\n")
    e = evaluation
    title = f"{e.source.name}, placement {e.placement}, robot model {metrics['input']['robot_model']}"
    plot_joints(e.cbf, e.nominal, e.kinematics.joint_names, out / "joints.png", title)
    plot_barriers(e.cbf, e.nominal, e.conf.safety.phi, out / "barriers.png", title)
    render_snapshot(e.conf, e.kinematics, e.human, e.cbf, e.nominal, out / "snapshot.png")
    return metrics


def summary_table(metrics: dict[str, Any]) -> str:
    """The two runs side by side, one metric a line."""
    lines = [f"{'metric':<22}{'with CBF':>14}{'without CBF':>14}"]
    for key in RUN_KEYS:
        cells = [metrics[run][key] for run in ("cbf", "nominal")]
        lines.append(f"{key:<22}" + "".join(f"{'—' if v is None else f'{v:g}':>14}" for v in cells))
    return "\n".join(lines)


def build_parser(parser: argparse.ArgumentParser | None = None) -> argparse.ArgumentParser:
    parser = parser or argparse.ArgumentParser(prog="safemimic evaluate")
    parser.description = (
        "Offline evaluation (DESIGN §7): the services' own code (point filter → angles → capsules → "
        "retargeting → CBF-QP → MuJoCo) in lockstep at the safety rate, without Zenoh, once with the CBF "
        "layer and once without it (u* = clip(u_ref)); writes metrics.json, contacts.json, joints.png, "
        "barriers.png and snapshot.png."
    )
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--skeleton", metavar="FILE.npz", help="a skeleton recording (DESIGN §6)")
    source.add_argument("--scenario", choices=list(SCENARIOS), metavar="NAME",
                        help=f"a scripted scenario: {', '.join(SCENARIOS)}")
    parser.add_argument("--placement", default="auto",
                        help="side-by-side | facing | recorded | x,y,yaw (m, m, rad) | auto (a scenario's own; "
                        "a recording: side-by-side); default auto")
    parser.add_argument("--robot-model", metavar="PATH",
                        help="MJCF to use instead of the robot description's (e.g. Menagerie's unitree_g1/g1.xml)")
    parser.add_argument("--seconds", type=float, metavar="S",
                        help="evaluate this long (default: the whole recording / one period of the scenario; "
                        "longer loops it)")
    parser.add_argument("--out", required=True, metavar="DIR", help="folder for the results")
    parser.add_argument("--config", "-c", metavar="FILE", help="stack configuration YAML (default: shipped)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    return parser


def run(args: argparse.Namespace) -> int:
    try:
        conf = evaluation_config(args.skeleton, args.scenario, args.placement, args.robot_model, args.config)
        evaluation = evaluate(conf, args.seconds, show_progress=not args.quiet)
    except (ConfigError, SourceUnavailable, RobotSpecError, KinematicsError, SimModelError, ValueError) as exc:
        print(f"safemimic evaluate: {exc}", file=sys.stderr)
        return 2
    metrics = write_outputs(evaluation, Path(args.out))
    print(f"{evaluation.source.name}: {metrics['input']['seconds']:g} s, "
          f"{metrics['input']['control_steps']} control steps, robot model {metrics['input']['robot_model']}")
    print(summary_table(metrics))
    print(f"wrote {args.out}/metrics.json, contacts.json, joints.png, barriers.png, snapshot.png")
    return 0

