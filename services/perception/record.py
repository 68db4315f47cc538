"""``safemimic record-scenario NAME OUT.npz``: write a scripted scenario as a recording (architecture §6).

The file is in the robot frame with the chosen placement applied (``source`` says which);
``safemimic perception --recording OUT.npz --placement recorded`` streams it back unchanged, and
any other placement re-places it (replays are normalised first).
"""

from __future__ import annotations

import argparse
import sys

from services.perception.placement import parse_placement
from services.perception.scenarios import SCENARIOS, get_scenario, scenario_recording
from shared.body import Body
from shared.cli_args import check_output_path
from shared.config import ConfigError, load_config
from shared.skeleton import write_recording


def build_parser(parser: argparse.ArgumentParser | None = None) -> argparse.ArgumentParser:
    parser = parser or argparse.ArgumentParser(prog="safemimic record-scenario")
    parser.description = "Write a scripted synthetic scenario as a .npz skeleton recording (robot frame)."
    parser.add_argument("name", choices=list(SCENARIOS), metavar="NAME", help=f"one of: {', '.join(SCENARIOS)}")
    parser.add_argument("out", metavar="OUT.npz", help="file to write")
    parser.add_argument("--seconds", type=float, help="length (default: one period of the scenario)")
    parser.add_argument("--fps", type=float, default=30.0, help="frame rate (default 30)")
    parser.add_argument("--placement", default="auto", help="auto | side-by-side | facing | recorded | x,y,yaw (m, m, rad)")
    parser.add_argument("--shoulder-width", type=float, help="synthetic person's shoulder width (m; default from config)")
    parser.add_argument("--config", "-c", metavar="FILE", help="stack configuration (placement distances, body)")
    return parser


def run(args: argparse.Namespace) -> int:
    try:
        check_output_path(args.out, "OUT.npz", folder=False)
        conf = load_config(args.config).perception
        scenario = get_scenario(args.name)
        placement = parse_placement(args.placement, conf, auto=scenario.placement)
        body = Body(shoulder_width=args.shoulder_width or conf.scenario_shoulder_width)
        recording = scenario_recording(scenario, args.seconds or scenario.period, args.fps, placement, body)
    except (ConfigError, ValueError) as exc:
        print(f"record-scenario: {exc}", file=sys.stderr)
        return 2
    path = write_recording(args.out, recording)
    print(f"wrote {path}: {scenario.name}, {len(recording)} frames at {recording.fps:g} fps "
          f"({recording.t[-1] + 1 / recording.fps:.2f} s), placement x={placement.x:.2f} m "
          f"y={placement.y:.2f} m yaw={placement.yaw:.3f} rad")
    return 0
