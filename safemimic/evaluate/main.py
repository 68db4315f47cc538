"""``safemimic evaluate``: run an input with and without the CBF layer against the true person.

    safemimic evaluate --scenario cross-arm-reach --out results/cross
    safemimic evaluate --skeleton clip.npz --placement facing --robot-model g1.xml --out results/clip
    safemimic evaluate --suite clips/ --placements side-by-side,facing --jobs 2 --out results/suite

Writes into ``--out``: ``metrics.json`` (:mod:`safemimic.evaluate.metrics`), ``contacts.json``
(per run: which body pairs touched, for how many steps, how deep), ``joints.png`` (the 8 joints:
true, perceived, without and with the CBF), ``barriers.png`` (every monitored h over time) and
``snapshot.png`` (MuJoCo at the worst moment). With ``--suite``: one such folder per clip and
placement plus ``summary.json``, ``summary.md`` and ``summary.png`` (:mod:`safemimic.evaluate.suite`).
``--rrd [FILE.rrd]`` adds both runs as one Rerun recording (:mod:`safemimic.evaluate.recording`;
in a suite one ``recording.rrd``, or FILE's name, in each run's folder).
Exit status 0, 1 when some run of a suite failed, 2 for unusable input.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from safemimic.evaluate.evaluation import evaluate, evaluation_config, write_outputs
from safemimic.evaluate.metrics import COMPLETE_WARNING, RUN_KEYS
from safemimic.evaluate.person import DEFAULT_LATENCY_S, CameraModel, latency_text
from safemimic.evaluate.progress import ProgressBar
from services.executor.mujoco.model import SimModelError
from services.perception.placement import check_placement
from services.perception.scenarios import SCENARIOS
from services.perception.sources import SourceUnavailable
from services.safety.kinematics import KinematicsError
from shared.cli_args import check_output_path
from shared.entrypoint import ParagraphHelpFormatter
from shared.config import ConfigError
from shared.robot_spec import RobotSpecError

#: The recording's file name when --rrd is given without one (and in each run folder of a suite).
RRD_NAME = "recording.rrd"
#: What makes an input unusable (exit 2 for a single run, a failed row in a suite).
INPUT_ERRORS = (ConfigError, SourceUnavailable, RobotSpecError, KinematicsError, SimModelError, ValueError)


def summary_table(metrics: dict[str, Any]) -> str:
    """The two runs side by side, one metric a line (the fidelity object flattened)."""
    lines = [f"{'metric':<40}{'with CBF':>14}{'without CBF':>14}"]

    def cell(value: Any) -> str:
        return f"{'—' if value is None else f'{value:g}':>14}"

    for key in RUN_KEYS:
        if key == "fidelity":
            for sub in metrics["cbf"]["fidelity"]:
                lines.append(f"{'fidelity.' + sub:<40}" + "".join(cell(metrics[r]["fidelity"][sub]) for r in ("cbf", "nominal")))
        else:
            lines.append(f"{key:<40}" + "".join(cell(metrics[r][key]) for r in ("cbf", "nominal")))
    return "\n".join(lines)


def camera_model(args: argparse.Namespace) -> CameraModel:
    """The perceived person's corruption from the command line (ValueError out of range)."""
    return CameraModel(latency_s=args.latency_ms / 1e3, depth_noise_m=args.depth_noise_m, dropout=args.dropout,
                       seed=args.seed, jitter_s=args.latency_jitter_ms / 1e3, dropout_frames=args.dropout_frames)


def build_parser(parser: argparse.ArgumentParser | None = None) -> argparse.ArgumentParser:
    parser = parser or argparse.ArgumentParser(prog="safemimic evaluate")
    parser.formatter_class = ParagraphHelpFormatter
    parser.description = (
        "Offline evaluation against the true person: the services' own code (point filter → angles → capsules "
        "→ retargeting → CBF-QP → MuJoCo) in lockstep at the safety rate, without Zenoh, once with the CBF layer "
        "and once without it (u* = clip(u_ref)).\n\n"
        "The TRUE person is the recording as recorded (no filter), interpolated to the control rate: MuJoCo's "
        "person follows it and every true_* metric is measured against it, at the simulated joints, on every "
        "robot surface. The PERCEIVED person is what the safety layer gets: the same skeleton delayed by "
        "--latency-ms (--latency-jitter-ms: late now and then), optionally noisy (--depth-noise-m, --dropout "
        "with --dropout-frames for keypoints hidden in runs, --seed), then filtered as the perception service does.\n\n"
        "Writes metrics.json, contacts.json, joints.png, barriers.png and snapshot.png into --out; with --suite "
        "one such folder per clip and placement plus summary.json, summary.md and summary.png; summary.md ends "
        "with the goals: how many runs meet each safety and imitation goal, which fail, and which of those "
        "fail only because the evaluator's own floor (the person inside the pelvis or legs, the target seen one "
        "latency late, the retargeting's error) already misses it."
    )
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--skeleton", metavar="FILE.npz", help="a skeleton recording (architecture §6)")
    source.add_argument("--scenario", choices=list(SCENARIOS), metavar="NAME",
                        help=f"a scripted scenario: {', '.join(SCENARIOS)}")
    source.add_argument("--suite", metavar="DIR", help="evaluate every .npz recording in DIR at each of --placements")
    parser.add_argument("--placement", default="auto",
                        help="side-by-side | facing | recorded | x,y,yaw (m, m, rad) | auto (a scenario's own; "
                        "a recording: side-by-side); default auto")
    parser.add_argument("--placements", default="side-by-side,facing", metavar="LIST",
                        help="with --suite: comma-separated placements, as --placement (x,y,yaw: three numbers in a row; "
                        "default side-by-side,facing)")
    parser.add_argument("--jobs", type=int, default=None, metavar="N",
                        help="with --suite: parallel processes (default: the CPU count)")
    parser.add_argument("--robot-model", metavar="PATH",
                        help="MJCF to use instead of the robot description's (e.g. Menagerie's unitree_g1/g1.xml)")
    parser.add_argument("--latency-ms", type=float, default=1e3 * DEFAULT_LATENCY_S, metavar="MS",
                        help="camera latency of the perceived person (default 60: one 30 Hz frame of exposure and "
                        "readout ≈ 33 ms + pose inference ≈ 20–30 ms on this CPU + transport); 0 without noise "
                        "gives the stack's perceived inputs with no delay")
    parser.add_argument("--latency-jitter-ms", type=float, default=0.0, metavar="MS",
                        help="a camera late now and then: each frame arrives later by an exponentially distributed "
                        "extra delay of this mean, never before the frame before it (default 0: every frame "
                        "--latency-ms late)")
    parser.add_argument("--depth-noise-m", type=float, default=0.0, metavar="SIGMA",
                        help="Gaussian depth noise per frame along the camera's viewing rays "
                        "(perception.camera.extrinsics): a common shift of the skeleton (σ) plus a per-keypoint "
                        "part (σ/2); default 0")
    parser.add_argument("--dropout", type=float, default=0.0, metavar="P",
                        help="each keypoint missing in a frame with probability P (default 0)")
    parser.add_argument("--dropout-frames", type=float, default=0.0, metavar="L",
                        help="with --dropout: each keypoint is hidden in runs of L frames on average (an arm "
                        "behind the body, a limb out of view), still a fraction P of the frames; runs longer "
                        "than the point filter's hold make a capsule lost, which stops the imitation "
                        "(safety.lost_human_hold_s). Default 0: independent from frame to frame")
    parser.add_argument("--seed", type=int, default=0, help="random seed of noise, dropout and jitter (default 0)")
    parser.add_argument("--seconds", type=float, metavar="S",
                        help="evaluate this long (default: the whole recording / one period of the scenario; "
                        "longer loops it)")
    parser.add_argument("--out", required=True, metavar="DIR", help="folder for the results")
    parser.add_argument("--rrd", nargs="?", const=RRD_NAME, metavar="FILE.rrd",
                        help="also write both runs as a Rerun recording (needs the viz extra; open it with "
                        f"'rerun FILE.rrd'); without a value {RRD_NAME} in --out; with --suite one file of that "
                        "name in each run's folder")
    parser.add_argument("--config", "-c", metavar="FILE", help="stack configuration YAML (default: shipped)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    return parser


def rrd_path(rrd: str | None, out: Path, suite: bool) -> Path | None:
    """Where a run's recording goes: None without --rrd; in a suite the name inside ``out`` (a run's
    folder); a bare file name inside ``out``; else the path as given."""
    if rrd is None:
        return None
    path = Path(rrd).expanduser()
    if path.suffix != ".rrd":
        raise ValueError(f"--rrd {rrd}: a Rerun recording's name ends in .rrd")
    return out / path.name if suite or path.parent == Path(".") else path


def _check_rerun(args: argparse.Namespace) -> None:
    if getattr(args, "rrd", None) is not None:
        import importlib.util

        if importlib.util.find_spec("rerun") is None:
            raise ValueError("--rrd needs rerun-sdk: pip install 'safemimic[viz]'")


def run(args: argparse.Namespace) -> int:
    try:
        camera = camera_model(args)
        check_output_path(args.out, "--out", folder=True)
        check_placement(args.placement, "--placement")
        rrd = rrd_path(args.rrd, Path(args.out), args.suite is not None)
        if rrd is not None:
            check_output_path(rrd, "--rrd", folder=False)
        _check_rerun(args)
    except ValueError as exc:
        print(f"safemimic evaluate: {exc}", file=sys.stderr)
        return 2
    if args.suite is not None:
        from safemimic.evaluate.suite import run_suite

        return run_suite(args, camera)
    try:
        conf = evaluation_config(args.skeleton, args.scenario, args.placement, args.robot_model, args.config)
        bar = None if args.quiet else ProgressBar(1, "evaluate (with and without CBF)")
        evaluation = evaluate(conf, args.seconds, camera, None if bar is None else bar.update_of)
        if bar is not None:
            bar.close()
    except INPUT_ERRORS as exc:
        print(f"safemimic evaluate: {exc}", file=sys.stderr)
        return 2
    rrd = rrd_path(args.rrd, Path(args.out), suite=False)
    metrics = write_outputs(evaluation, Path(args.out), rrd)
    print(f"{evaluation.source.name}: {metrics['input']['seconds']:g} s, "
          f"{metrics['input']['control_steps']} control steps, robot model {metrics['input']['robot_model']}, "
          f"camera latency {latency_text(metrics['input'])}")
    print(summary_table(metrics))
    complete = metrics["input"]["true_person_complete"]
    if complete < COMPLETE_WARNING:
        print(f"safemimic evaluate: warning: the recording has the whole person in only {100 * complete:.0f} % of the "
              "steps (a body part missing from its frames): contacts with what it does not show are not counted",
              file=sys.stderr)
    print(f"wrote {args.out}/metrics.json, contacts.json, joints.png, barriers.png, snapshot.png"
          + (f"; recording {rrd} (open: rerun {rrd})" if rrd is not None else ""))
    return 0
