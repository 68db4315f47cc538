"""One evaluation: an input read once, perceived once, run with and without the CBF layer.

:func:`evaluate` composes the services' public pieces in one process (the perception pipeline,
the safety pipeline, the MuJoCo executor); :func:`write_outputs` writes ``metrics.json``,
``contacts.json`` and the figures of one run pair into a folder.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np

from safemimic.evaluate.episode import Episode, run_episode
from safemimic.evaluate.metrics import (free_steps, input_metrics, limits_floor_joints, run_metrics, target_directions,
                                        write_metrics)
from safemimic.evaluate.person import CameraModel, HumanTrack, TruePerson, perceive, true_person
from safemimic.evaluate.source import EvaluationInput, open_input
from services.safety.assembly import make_retargeter
from services.safety.kinematics import RobotKinematics
from shared.config import StackConfig, load_config
from shared.robot_spec import configured_robot_spec


@dataclass
class Evaluation:
    """Both runs of one input, with what they were computed from."""

    conf: StackConfig
    source: EvaluationInput
    camera: CameraModel
    human: HumanTrack
    person: TruePerson
    kinematics: RobotKinematics
    cbf: Episode
    nominal: Episode
    placement: str

    @cached_property
    def limits_floor(self) -> np.ndarray:
        """(N, 8) rad: the lag's limits floor (:func:`limits_floor_joints`), computed once."""
        return limits_floor_joints(self.person, self.conf.safety, self.camera.latency_s)

    def metrics(self) -> dict[str, Any]:
        """The content of ``metrics.json``."""
        free = free_steps(self.cbf)
        phi, mirror = self.conf.safety.phi, self.conf.retargeting.mirror
        latency = self.camera.latency_s
        at_target = target_directions(self.person, mirror, latency)
        limits_floor = self.limits_floor
        return {
            "cbf": run_metrics(self.cbf, free, self.person, phi, mirror, at_target, latency,
                               self.human.in_view(self.cbf.human), limits_floor),
            "nominal": run_metrics(self.nominal, free, self.person, phi, mirror, at_target, latency,
                                   self.human.in_view(self.nominal.human), limits_floor),
            "input": input_metrics(self.conf, self.source, self.human, self.cbf, self.placement, self.camera,
                                   float(self.person.capsule_valid.all(axis=1).mean())),
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


def true_person_of(conf: StackConfig, source: EvaluationInput, kinematics: RobotKinematics) -> TruePerson:
    """The true person of ``source`` at every control step of its duration (``q_true`` through the
    configured retargeting of ``kinematics``' robot)."""
    dt = 1.0 / conf.safety.rate_hz
    t = np.arange(max(1, round(source.seconds / dt))) * dt
    return true_person(conf, source, t, make_retargeter(conf, kinematics.spec, RobotKinematics(kinematics.spec)), kinematics)


#: Progress callback: (steps done, steps in all) over both runs.
Progress = Callable[[int, int], None]


def evaluate(conf: StackConfig, seconds: float | None = None, camera: CameraModel = CameraModel(),
             progress: Progress | None = None) -> Evaluation:
    """Read the input, perceive it once through ``camera``, run it with and without the CBF layer.

    Raises SourceUnavailable, RobotSpecError, KinematicsError, SimModelError or ValueError for
    unusable input.
    """
    source = open_input(conf, seconds)
    human = perceive(conf, source, camera)
    kinematics = RobotKinematics(configured_robot_spec(conf))
    person = true_person_of(conf, source, kinematics)
    t = person.t
    runs = {}
    for i, enforce in enumerate((True, False)):
        report = None if progress is None else (lambda done, i=i: progress(i * len(t) + done, 2 * len(t)))
        runs[enforce] = run_episode(conf, human, person, enforce, kinematics, report)
    return Evaluation(conf, source, camera, human, person, kinematics, runs[True], runs[False],
                      conf.perception.placement)


def write_outputs(evaluation: Evaluation, out: Path, rrd: Path | None = None) -> dict[str, Any]:
    """Write metrics.json, contacts.json and the three figures into ``out`` (and with ``rrd`` both
    runs as a Rerun recording there: :mod:`safemimic.evaluate.recording`); the metrics."""
    from safemimic.evaluate.figures import plot_barriers, plot_joints  # matplotlib: only when writing
    from safemimic.evaluate.snapshot import render_snapshot

    out.mkdir(parents=True, exist_ok=True)
    metrics = evaluation.metrics()
    write_metrics(out / "metrics.json", metrics)
    e = evaluation
    contacts = {
        run: {**ep.tally.summary(), "true_robot_human": ep.true_tally.robot_human.summary()}
        for run, ep in (("cbf", e.cbf), ("nominal", e.nominal))
    }
    (out / "contacts.json").write_text(json.dumps(contacts, indent=2) + "\n")
    title = f"{e.source.name}, placement {e.placement}, robot model {metrics['input']['robot_model']}"
    plot_joints(e.cbf, e.nominal, e.person, e.limits_floor, e.kinematics.joint_names, out / "joints.png", title)
    plot_barriers(e.cbf, e.nominal, e.conf.safety.phi, out / "barriers.png", title, e.conf.safety.human_standoff_m)
    render_snapshot(e.conf, e.kinematics, e.human, e.person, e.cbf, e.nominal, out / "snapshot.png")
    if rrd is not None:
        from safemimic.evaluate.recording import write_rrd  # rerun-sdk (the viz extra): only when asked

        write_rrd(e, rrd)
    return metrics
