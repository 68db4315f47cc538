"""``safemimic router``: a Zenoh session in router mode that clients connect through (architecture §1)."""

from __future__ import annotations

import argparse
import logging
import threading

from shared.bus import close_bounded, open_session
from shared.cli_args import add_bus_arguments, config_from_args
from shared.config import StackConfig, deep_merge
from shared.stop_signals import stop_on_signals

log = logging.getLogger("safemimic.router")
DEFAULT_LISTEN = "tcp/0.0.0.0:7447"
DEFAULT_SECURE_LISTEN = "tls/0.0.0.0:7447"
#: The common name of the router's certificate (``safemimic certs``).
ROUTER_IDENTITY = "router"



def main(conf: StackConfig, stop: threading.Event) -> bool:
    """Run zenoh's router until ``stop`` is set; True if the session closed within the timeout."""
    session = open_session(conf.bus, identity=ROUTER_IDENTITY)
    try:
        endpoints = ", ".join(conf.bus.listen) or "zenoh defaults"
        security = "mutual TLS + access control" if conf.bus.tls is not None else "INSECURE: no TLS, no access control"
        print(f"zenoh router {session.zid()} listening on {endpoints} ({security})", flush=True)
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
        "--mode client --connect tls/HOST:7447 --certs DIR exchange messages and liveliness through it. "
        f"Default listen endpoint: {DEFAULT_SECURE_LISTEN} with --certs (DIR/router.pem, DIR/access_control.json5), "
        f"{DEFAULT_LISTEN} without."
    )
    parser.add_argument("--acl", metavar="FILE", help="Zenoh access_control JSON5 (default: CERTS/access_control.json5)")
    add_bus_arguments(parser)
    return parser


def run(args: argparse.Namespace) -> int:
    args.mode = "router"
    extra = {"bus": {"tls": {"access_control": args.acl}}} if args.acl else {}
    # a ConfigError (here, or from main: an unusable certificate or access-control file) is
    # shared.entrypoint's to say, exit 2
    conf = config_from_args(args, extra)
    if not args.listen:
        listen = DEFAULT_SECURE_LISTEN if conf.bus.tls is not None else DEFAULT_LISTEN
        conf = config_from_args(args, deep_merge(extra, {"bus": {"listen": [listen]}}))
    with stop_on_signals() as stop:
        main(conf, stop)
    return 0  # a hung close: safemimic.cli leaves without it

