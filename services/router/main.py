"""``safemimic router``: a Zenoh session in router mode that clients connect through (DESIGN §1)."""

from __future__ import annotations

import argparse
import logging
import signal
import sys
import threading

from shared.bus import open_session
from shared.cli_args import add_bus_arguments, config_from_args
from shared.config import StackConfig

log = logging.getLogger("safemimic.router")
DEFAULT_LISTEN = "tcp/0.0.0.0:7447"


def main(conf: StackConfig, stop: threading.Event) -> None:
    """Run zenoh's router until ``stop`` is set."""
    with open_session(conf.bus) as session:
        endpoints = ", ".join(conf.bus.listen) or "zenoh defaults"
        print(f"zenoh router {session.zid()} listening on {endpoints}", flush=True)
        # Wake up now and then: SIGTERM may be delivered to one of zenoh's threads, and Python runs
        # the handler (which sets ``stop``) only when the main thread wakes; an untimed wait can hang.
        while not stop.wait(0.2):
            pass
    print("zenoh router stopped", flush=True)


def build_parser(parser: argparse.ArgumentParser | None = None) -> argparse.ArgumentParser:
    parser = parser or argparse.ArgumentParser(prog="safemimic router")
    parser.description = (
        "Run a Zenoh router (zenoh-python in router mode). Services started with "
        "--mode client --connect tcp/HOST:7447 exchange messages and liveliness through it. "
        f"Default listen endpoint: {DEFAULT_LISTEN}."
    )
    add_bus_arguments(parser)
    return parser


def run(args: argparse.Namespace) -> int:
    args.mode = "router"
    args.listen = args.listen or [DEFAULT_LISTEN]
    conf = config_from_args(args)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    main(conf, stop)
    return 0


def cli(argv: list[str] | None = None) -> None:
    logging.basicConfig(level=logging.INFO)
    sys.exit(run(build_parser().parse_args(argv)))
