"""``safemimic config``: the configuration a service would run with, validated and printed.

The same loading as every service (:func:`shared.cli_args.config_from_args`: the file, then the
``SAFEMIMIC__…`` variables, then the command line's bus flags), so what it prints is what
``safemimic safety`` with the same file, environment and flags would use, and a value it refuses
is refused there too (exit 2, each bad field named with where its value came from). ``KEY`` picks
one section or value by its dotted name (``safety``, ``safety.gain``, ``bus.connect``). Secrets
(:data:`SECRETS`: the API's bearer token) are printed as :data:`HIDDEN` when set.
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

import yaml

from shared.cli_args import add_bus_arguments, config_from_args

#: The dotted names of the values never printed.
SECRETS = ("api.token",)
HIDDEN = "<set, hidden>"


def printable(tree: dict[str, Any]) -> dict[str, Any]:
    """``tree`` (a configuration dumped as JSON, changed in place) with each set :data:`SECRETS` value
    replaced by :data:`HIDDEN`."""
    for name in SECRETS:
        *path, leaf = name.split(".")
        node = select(tree, ".".join(path))
        if node.get(leaf) is not None:
            node[leaf] = HIDDEN
    return tree


def select(tree: dict[str, Any], key: str | None) -> Any:
    """The value at the dotted ``key`` of the configuration ``tree`` (all of it for None); KeyError
    naming the first part that is not there and what is."""
    node: Any = tree
    for depth, part in enumerate(key.split(".") if key else ()):
        if not isinstance(node, dict) or part not in node:
            where = ".".join(key.split(".")[:depth]) or "the configuration"
            known = ", ".join(node) if isinstance(node, dict) else "nothing: it is a value"
            raise KeyError(f"{key}: {where} has no {part!r} (it has {known})")
        node = node[part]
    return node


def build_parser(parser: argparse.ArgumentParser | None = None) -> argparse.ArgumentParser:
    parser = parser or argparse.ArgumentParser(prog="safemimic config")
    parser.description = (
        "Print the configuration a service would run with: the file (--config, $SAFEMIMIC_CONFIG or the shipped "
        "default), the SAFEMIMIC__SECTION__FIELD variables and the bus flags, merged and validated. Exit 0 if "
        "it is valid, 2 with every bad field (and where its value came from) if not. "
        "E.g. 'safemimic config safety.gain', 'SAFEMIMIC__SAFETY__GAMMA=5 safemimic config safety'."
    )
    parser.add_argument("key", nargs="?", metavar="KEY", help="a section or value by its dotted name (default: all)")
    parser.add_argument("--json", action="store_true", help="JSON instead of YAML")
    add_bus_arguments(parser)
    return parser


def run(args: argparse.Namespace) -> int:
    conf = config_from_args(args)  # a ConfigError: shared.entrypoint says it, exit 2
    try:
        value = select(printable(conf.model_dump(mode="json")), args.key)
    except KeyError as exc:
        print(f"safemimic config: {exc.args[0]}", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps(value, indent=2, ensure_ascii=False))
    elif isinstance(value, (dict, list)):
        print(yaml.safe_dump(value, sort_keys=False, width=120, allow_unicode=True), end="")
    else:  # one value: a text as it is, a number, true/false or null as YAML and JSON write them
        print(value if isinstance(value, str) else json.dumps(value))
    return 0
