"""Command-line flags shared by every service (zenoh-python examples style), and checks of the
commands' arguments.

``--config FILE``, ``--mode``, ``--connect``, ``--listen``, ``--no-multicast``, ``--robot-id``,
``--certs DIR`` (mutual TLS with this service's certificate from DIR: ``bus.tls.dir``) or
``--insecure`` (``bus.tls: null``, the open development bus); the parsed flags become overrides
on top of the YAML file and the environment. :func:`check_output_path`: an output argument that
can be written, checked before a command does any work.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from shared.config import StackConfig, deep_merge, load_config


def add_bus_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the common configuration and Zenoh flags to ``parser``."""
    group = parser.add_argument_group("configuration and bus")
    group.add_argument("--config", "-c", metavar="FILE", help="stack configuration YAML (default: shipped config/default.yaml or $SAFEMIMIC_CONFIG)")
    group.add_argument("--mode", "-m", choices=["peer", "client", "router"], help="Zenoh session mode")
    group.add_argument("--connect", "-e", action="append", metavar="ENDPOINT", help="Zenoh endpoint to connect to, e.g. tcp/10.0.0.2:7447 (repeatable)")
    group.add_argument("--listen", "-l", action="append", metavar="ENDPOINT", help="Zenoh endpoint to listen on, e.g. tcp/0.0.0.0:7447 (repeatable)")
    group.add_argument("--no-multicast", action="store_true", help="disable Zenoh multicast scouting (use explicit endpoints)")
    group.add_argument("--robot-id", metavar="ID", help="robot id in the key expressions safemimic/{robot_id}/...")
    security = group.add_mutually_exclusive_group()
    security.add_argument("--certs", metavar="DIR", help="mutual TLS: DIR holds ca.pem and this service's NAME.pem/NAME.key "
                          "(safemimic certs; bus.tls.dir); needs --mode client and tls/HOST:PORT endpoints (the secure bus "
                          "goes through the router, which enforces access control)")
    security.add_argument("--insecure", action="store_true", help="open tcp bus without authentication or access control "
                          "(bus.tls: null): anyone on the network can command the robot; development only")


def bus_overrides(args: argparse.Namespace) -> dict[str, Any]:
    """The overrides implied by the common flags (only those given)."""
    bus: dict[str, Any] = {}
    if args.mode:
        bus["mode"] = args.mode
    if args.connect:
        bus["connect"] = list(args.connect)
    if args.listen:
        bus["listen"] = list(args.listen)
    if args.no_multicast:
        bus["multicast_scouting"] = False
    if getattr(args, "certs", None):
        bus["tls"] = {"dir": args.certs}
    if getattr(args, "insecure", False):
        bus["tls"] = None
    overrides: dict[str, Any] = {"bus": bus} if bus else {}
    if args.robot_id:
        overrides["robot_id"] = args.robot_id
    return overrides


def config_from_args(args: argparse.Namespace, extra: dict[str, Any] | None = None) -> StackConfig:
    """Load the configuration: file, environment, then the flags, then ``extra``."""
    return load_config(args.config, overrides=deep_merge(bus_overrides(args), extra or {}))


def check_output_path(path: str | Path, argument: str, *, folder: bool) -> None:
    """Raise ValueError naming ``argument`` when ``path`` cannot be written as asked, before any work:
    a folder (``folder``) that exists as something else, a file that exists as a folder, or a path
    below an existing file. Creates nothing; a path that does not exist yet is fine."""
    path = Path(path).expanduser()
    if folder and path.exists() and not path.is_dir():
        raise ValueError(f"{argument} {path}: exists and is not a folder")
    if not folder and path.is_dir():
        raise ValueError(f"{argument} {path}: is a folder, not a file name")
    for parent in path.parents:
        if parent.exists():
            if not parent.is_dir():
                raise ValueError(f"{argument} {path}: {parent} is a file, not a folder")
            break
