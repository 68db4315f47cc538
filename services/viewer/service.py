"""``safemimic viewer``: a live 3D view of robot, person and barriers in Rerun (only subscribes).

    safemimic viewer --mode client --connect tls/ROBOT:7447 --certs DIR   # serves Rerun's web viewer
    safemimic viewer ... --save run.rrd                                   # records to a file instead
    safemimic viewer ... --rerun-connect rerun+http://HOST:9876/proxy      # streams to a native viewer

Subscribes to ``HumanState``, ``JointCommand``, ``JointState`` and ``SafetyStatus`` with the
``viewer`` identity (its certificate may only subscribe: ``safemimic.stack.TOOLS``) and draws,
at most ``--rate`` (≤ 30) frames a second, what :class:`~services.viewer.live.LiveScene` says.
What it costs a host shared with the 500 Hz safety loop is bounded twice: Zenoh lets at most
``--rate`` samples a second of the control-rate topics (:data:`~services.viewer.live.DECIMATED`)
into its session, dropping the rest before Python sees them, and the process runs in the
background (:func:`shared.realtime.enter_background`: SCHED_IDLE; ``--foreground`` keeps normal
priority).
The bus flag ``--connect`` is Zenoh's; the Rerun viewer to stream to is ``--rerun-connect``.
By default it serves the web viewer shipped in the rerun-sdk wheel (``--web-port``, gRPC on
``--grpc-port``; no internet needed) and prints one JSON line ``{"event": "ready", "url": ...}``;
once a second a ``{"event": "stats", ...}`` line (messages drawn per topic, dropped, errors,
stale topics). Exit 0 on Ctrl-C/SIGTERM, 2 for unusable options or robot model.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import sys
import time
import urllib.parse
from pathlib import Path

from shared.bus import Bus, close_bounded
from shared.cli_args import add_bus_arguments, config_from_args
from shared.realtime import enter_background
from shared.robot_spec import configured_robot_spec
from shared.stop_signals import stop_on_signals

SERVICE_NAME = "viewer"
MAX_RATE_HZ = 30.0
WEB_PORT, GRPC_PORT = 9090, 9876


def _rate(text: str) -> float:
    value = float(text)
    if not 0.0 < value <= MAX_RATE_HZ:
        raise argparse.ArgumentTypeError(f"must be in (0, {MAX_RATE_HZ:g}] frames a second, got {text}")
    return value


def build_parser(parser: argparse.ArgumentParser | None = None) -> argparse.ArgumentParser:
    parser = parser or argparse.ArgumentParser(prog="safemimic viewer")
    parser.description = (
        "Live 3D view in Rerun: the robot (meshes from the robot description's MJCF, CBF capsules), the "
        "perceived person, the closest-point segments of the pairs the safety service reports binding (yellow), "
        "and time series of min h per pair group, mode, QP time, q_nom, q_cbf and measured q per joint. Only subscribes; ≤ 30 frames/s. "
        "Serves Rerun's web viewer unless --save or --rerun-connect."
    )
    sink = parser.add_mutually_exclusive_group()
    sink.add_argument("--save", metavar="FILE.rrd", help="record to FILE.rrd instead of serving (open it: rerun FILE.rrd)")
    sink.add_argument("--rerun-connect", metavar="URL",
                      help="stream to a running native Rerun viewer, e.g. rerun+http://127.0.0.1:9876/proxy "
                      "(the bus's own --connect is Zenoh's)")
    parser.add_argument("--web-port", type=int, default=WEB_PORT, metavar="PORT", help=f"web viewer port (default {WEB_PORT})")
    parser.add_argument("--grpc-port", type=int, default=GRPC_PORT, metavar="PORT", help=f"Rerun gRPC port the page reads (default {GRPC_PORT})")
    parser.add_argument("--host", default="127.0.0.1", help="host name printed in the URL (default 127.0.0.1)")
    parser.add_argument("--rate", type=_rate, default=MAX_RATE_HZ, metavar="HZ", help="frames a second, ≤ 30 (default 30)")
    parser.add_argument("--memory-limit", default="512MiB", help="what the gRPC server keeps for late viewers (default 512MiB)")
    parser.add_argument("--duration", type=float, metavar="S", help="stop after S seconds (default: until Ctrl-C)")
    parser.add_argument("--foreground", action="store_true",
                        help="run at normal CPU priority; by default the viewer runs in the background (Linux "
                        "SCHED_IDLE, elsewhere nice 19) so that on a host shared with the 500 Hz safety loop it "
                        "never delays it")
    add_bus_arguments(parser)
    return parser


def _open_sink(rec, args: argparse.Namespace) -> dict:
    """Point ``rec`` at its sink; the ready line's fields."""
    import rerun as rr

    if args.save:
        path = Path(args.save).expanduser()
        path.parent.mkdir(parents=True, exist_ok=True)
        rec.save(path)
        return {"save": str(path)}
    if args.rerun_connect:
        rec.connect_grpc(args.rerun_connect)
        return {"connect": args.rerun_connect}
    uri = rec.serve_grpc(grpc_port=args.grpc_port, server_memory_limit=args.memory_limit)
    rr.serve_web_viewer(web_port=args.web_port, open_browser=False, connect_to=uri)
    uri = uri.replace("127.0.0.1", args.host).replace("0.0.0.0", args.host)
    return {"url": f"http://{args.host}:{args.web_port}/?url={urllib.parse.quote(uri, safe='')}", "grpc": uri}


def run(args: argparse.Namespace) -> int:
    scheduling = "normal scheduling" if args.foreground else enter_background()
    if importlib.util.find_spec("rerun") is None:
        print("safemimic viewer needs rerun-sdk: pip install 'safemimic[viz]'", file=sys.stderr)
        return 2
    import rerun as rr

    from services.viewer.live import DECIMATED, LiveScene
    from services.viewer.robot_mesh import RobotMesh

    conf = config_from_args(args)  # a ConfigError, RobotSpecError, RobotMeshError: shared.entrypoint, exit 2
    spec = configured_robot_spec(conf)
    mesh = RobotMesh(spec)
    radii = mesh.capsule_radii
    for i, name in enumerate(spec.capsules):  # the safety service's overrides (safety.capsule_radii)
        radii[i] = conf.safety.capsule_radii.get(name, radii[i])
    rec = rr.RecordingStream("safemimic_viewer", send_properties=False)
    try:
        ready = _open_sink(rec, args)
    except Exception as exc:  # a port in use, an unreachable native viewer, an unwritable file
        print(f"safemimic viewer: {exc}", file=sys.stderr)
        return 2
    period = 1.0 / args.rate
    with stop_on_signals() as stop, Bus(conf.bus, conf.robot_id, SERVICE_NAME,
                                            max_hz=dict.fromkeys(DECIMATED, args.rate)) as bus:
        alive: dict[str, bool] = {}
        bus.watch_alive(lambda service, up: alive.__setitem__(service, up))
        scene = LiveScene(bus, rec, mesh, radii)
        print(json.dumps({"event": "ready", **ready, "rate_hz": args.rate, "scheduling": scheduling}), flush=True)
        end = time.monotonic() + args.duration if args.duration else float("inf")
        next_frame = next_stats = time.monotonic()
        while not stop.is_set() and time.monotonic() < end:
            scene.frame()
            now = time.monotonic()
            if now >= next_stats:
                for service, up in list(alive.items()):
                    rec.log(f"viewer/alive/{service}", rr.Scalars(1.0 if up else 0.0))
                print(json.dumps({"event": "stats", **scene.stats(), "alive": sorted(s for s, up in alive.items() if up)}),
                      flush=True)
                next_stats = now + 1.0
            next_frame = max(next_frame + period, now)
            stop.wait(max(0.0, next_frame - time.monotonic()))
        scene.flush()
    # a slow web client must not hold the exit: the flush and the server's shutdown are bounded
    close_bounded(lambda: (rec.flush(), rec.disconnect()), timeout_s=2.0)
    return 0
