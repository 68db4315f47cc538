"""``safemimic health``: which services are alive on the bus (their Zenoh liveliness tokens).

Prints one JSON line ``{"alive": [...], "missing": [...]}`` and exits 0 when every service named
on the command line holds its token ``safemimic/{robot_id}/alive/{service}`` (with no name: when
the bus is reachable at all), 1 when one is missing, 2 when the bus cannot be opened or the
command line names no service (:data:`~shared.names.SERVICE_NAMES`; a command's spelling,
``config-api``, names its token ``config_api``) or a timeout that is not > 0. Docker compose uses it
as the services' health check; on a robot it answers "is the safety layer up?".
"""

from __future__ import annotations

import argparse
import json
import sys

from shared.bus import Bus
from shared.cli_args import add_bus_arguments, config_from_args
from shared.names import SERVICE_NAMES

SERVICE_NAME = "health"


def build_parser(parser: argparse.ArgumentParser | None = None) -> argparse.ArgumentParser:
    parser = parser or argparse.ArgumentParser(prog="safemimic health")
    parser.description = (
        "Query the liveliness tokens on the bus; exit 0 if every named service is alive (e.g. "
        "'safemimic health safety perception --mode client --connect tcp/ROBOT:7447')."
    )
    parser.add_argument("services", nargs="*", metavar="SERVICE",
                        help=f"a service: {', '.join(SERVICE_NAMES)} (config-api, its command's name, works too)")
    parser.add_argument("--timeout", type=float, default=2.0, metavar="SECONDS", help="how long to collect replies (default 2)")
    add_bus_arguments(parser)
    return parser


def token_names(services: list[str]) -> list[str]:
    """The liveliness token names of the ``services`` named on the command line, ``-`` read as ``_``
    (``config-api``: ``config_api``); ValueError naming those that are no service."""
    tokens = [name.replace("-", "_") for name in services]
    unknown = [name for name, token in zip(services, tokens) if token not in SERVICE_NAMES]
    if unknown:
        raise ValueError(f"SERVICE {', '.join(map(repr, unknown))}: not a service; the services are "
                         f"{', '.join(SERVICE_NAMES)}")
    return tokens


def run(args: argparse.Namespace) -> int:
    try:
        tokens = token_names(args.services)
        if not args.timeout > 0:
            raise ValueError(f"--timeout must be > 0 seconds, got {args.timeout:g}")
    except ValueError as exc:
        print(f"safemimic health: {exc}", file=sys.stderr)
        return 2
    conf = config_from_args(args)  # a ConfigError: shared.entrypoint says it, exit 2
    try:
        with Bus(conf.bus, conf.robot_id, SERVICE_NAME) as bus:
            alive = bus.alive_services(args.timeout)
    except Exception as exc:  # zenoh.ZError: the router or peers cannot be reached
        print(json.dumps({"error": f"cannot open the bus: {exc}"}), flush=True)
        return 2
    missing = sorted(set(tokens) - alive)
    print(json.dumps({"alive": sorted(alive), "missing": missing}), flush=True)
    return 1 if missing else 0
