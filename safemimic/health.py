"""``safemimic health``: which services are alive on the bus (their Zenoh liveliness tokens).

Prints one JSON line ``{"alive": [...], "missing": [...]}`` and exits 0 when every service named
on the command line holds its token ``safemimic/{robot_id}/alive/{service}`` (with no name: when
the bus is reachable at all), 1 when one is missing, 2 when the bus cannot be opened. Docker
compose uses it as the services' health check; on a robot it answers "is the safety layer up?".
"""

from __future__ import annotations

import argparse
import json

from shared.bus import Bus
from shared.cli_args import add_bus_arguments, config_from_args

SERVICE_NAME = "health"


def build_parser(parser: argparse.ArgumentParser | None = None) -> argparse.ArgumentParser:
    parser = parser or argparse.ArgumentParser(prog="safemimic health")
    parser.description = (
        "Query the liveliness tokens on the bus; exit 0 if every named service is alive (e.g. "
        "'safemimic health safety perception --mode client --connect tcp/ROBOT:7447')."
    )
    parser.add_argument("services", nargs="*", metavar="SERVICE", help="liveliness token names: executor, safety, perception, config_api")
    parser.add_argument("--timeout", type=float, default=2.0, metavar="SECONDS", help="how long to collect replies (default 2)")
    add_bus_arguments(parser)
    return parser


def run(args: argparse.Namespace) -> int:
    conf = config_from_args(args)  # a ConfigError: shared.entrypoint says it, exit 2
    try:
        with Bus(conf.bus, conf.robot_id, SERVICE_NAME) as bus:
            alive = bus.alive_services(args.timeout)
    except Exception as exc:  # zenoh.ZError: the router or peers cannot be reached
        print(json.dumps({"error": f"cannot open the bus: {exc}"}), flush=True)
        return 2
    missing = sorted(set(args.services) - alive)
    print(json.dumps({"alive": sorted(alive), "missing": missing}), flush=True)
    return 1 if missing else 0
