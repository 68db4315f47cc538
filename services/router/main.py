"""``safemimic router``: a Zenoh session in router mode that clients connect through (DESIGN §1)."""

from __future__ import annotations

import argparse
import logging
import threading

from shared.bus import close_bounded, open_session
from shared.cli_args import add_bus_arguments, config_from_args
from shared.config import StackConfig
from shared.stop_signals import stop_on_signals

log = logging.getLogger("safemimic.router")
DEFAULT_LISTEN = "tcp/0.0.0.0:7447"



def main(conf: StackConfig, stop: threading.Event) -> bool:
    """Run zenoh's router until ``stop`` is set; True if the session closed within the timeout."""
    session = open_session(conf.bus)
    try:
        endpoints = ", ".join(conf.bus.listen) or "zenoh defaults"
        print(f"zenoh router {session.zid()} listening on {endpoints}", flush=True)
        # Wake up now and then: SIGTERM may be delivered to one of zenoh's threads, and Python runs
        # the handler (which sets ``stop``) only when the main thread wakes; an untimed wait can hang.
        while not stop.wait(0.2):
            pass
    finally:
        closed = close_bounded(session.close)  # clients still connected can hold it up
    print("zenoh router stopped" if closed else "zenoh router stopped (session close timed out)", flush=True)
    return closed


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
    with stop_on_signals() as stop:
        main(conf, stop)
    return 0  # a hung close: safemimic.cli leaves without it

