"""The ``safemimic`` command: one entry point, one subcommand per service or tool.

A subcommand's module is imported only when it runs, so a perception-only install
(``pip install safemimic[perception]``) never imports MuJoCo or Pinocchio.
Each module provides ``build_parser(parser)`` and ``run(args) -> int``.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from shared.entrypoint import ParagraphHelpFormatter, run_command
from shared.version import VERSION

#: subcommand → (module, one-line help). Later issues add perception, safety, executor, ...
SUBCOMMANDS: dict[str, tuple[str, str]] = {
    "router": ("services.router.main", "run a Zenoh router (zenoh's own, router mode) for clients on several hosts"),
    "safety": ("services.safety.service", "run the CBF safety service: HumanState → retarget → CBF-QP → JointCommand at 500 Hz"),
    "perception": ("services.perception.service", "run the perception service: skeleton source → filter → θ + human capsules → HumanState"),
    "pose-model": ("services.perception.camera.model", "install or check the BlazePose weights of the camera source (from the mediapipe 0.10.21 wheel, SHA-256 pinned)"),
    "record-scenario": ("services.perception.record", "write a scripted synthetic scenario (known angles) as a .npz skeleton recording"),
    "config-api": ("services.config_api.main", "serve the config API and web console: validated, persisted, published parameter changes"),
    "executor": ("services.executor.service", "run the robot executor: MuJoCo simulation (or hardware) following JointCommand, publishing JointState"),
    "evaluate": ("safemimic.evaluate.main", "offline evaluation against the true person (camera latency, noise): with and without the CBF layer in MuJoCo → metrics.json + figures; --suite for a folder"),
    "compare": ("safemimic.evaluate.compare", "two evaluation suites side by side, before → after a change: sums, goals met and the runs that changed"),
    "variants": ("safemimic.evaluate.variants", "test variants of recordings (turned, stepping in or sideways, scaled, broadened, mirrored) to evaluate with --suite"),
    "demo": ("safemimic.demo", "run the stack end to end on this machine and print what happens"),
    "viewer": ("services.viewer.service", "live 3D view in Rerun of robot, person and barriers (subscribes only; web viewer, --save FILE.rrd)"),
    "config": ("safemimic.show_config", "print the configuration a service would run with (file, SAFEMIMIC__ variables, flags), validated"),
    "health": ("safemimic.health", "which services are alive on the bus (liveliness tokens); exit 0 if the named ones are"),
    "certs": ("safemimic.certs", "the deployment's CA and one certificate per service (mutual TLS; the router's access control)"),
}


def _top_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="safemimic",
        description="Safe human-to-humanoid motion imitation: perception → CBF-QP safety layer → robot, over Zenoh.",
        epilog="Run 'safemimic COMMAND --help' for the options of a command. The benchmarks and the reliability "
               "checks run from a checkout of the repository, not from the package: make bench, make reliability.",
        formatter_class=ParagraphHelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"safemimic {VERSION}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", title="commands")
    for name, (_, help_text) in SUBCOMMANDS.items():
        sub.add_parser(name, help=help_text, add_help=False)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if not argv or argv[0] not in SUBCOMMANDS:
        parser = _top_parser()
        parser.parse_args(argv)  # handles --help, --version and unknown commands
        parser.print_help()
        return 2
    name, rest = argv[0], argv[1:]
    module = importlib.import_module(SUBCOMMANDS[name][0])
    return run_command(name, module.build_parser, module.run, rest)


if __name__ == "__main__":
    sys.exit(main())
