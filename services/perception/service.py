"""``safemimic perception``: skeleton source → filter → θ + human capsules → HumanState on Zenoh.

Publishes one :class:`~shared.messages.HumanState` per source frame on
``safemimic/{robot_id}/human/state`` (robot frame; ``stamp`` = ``time.monotonic()`` at
publication, ``capture_stamp`` = when the source took the frame), holds the liveliness token
``alive/perception``, and prints JSON lines on stdout: ``ready`` (streaming starts), ``stats``
every ``perception.stats_interval_s`` and ``done`` (the final counters: frames, published, rejected
jumps, invalid frames, errors, ...). A frame that fails to process is counted and skipped; it
never stops the service.

Configuration updates (``config`` topic, from the config API) are validated when they arrive and
applied before the next frame: point filter, angle estimator and human capsule parameters change
live; the bus, robot id and source settings need a restart (logged, otherwise ignored).

Light by design (architecture §1): this module's imports reach numpy, pydantic, PyYAML, msgpack and
zenoh only — never MuJoCo, Pinocchio, a QP solver or FastAPI (a test proves it).
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import threading
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

from services.perception.pipeline import PerceptionPipeline
from services.perception.sources import open_source
from services.perception.base import SkeletonFrame, SkeletonSource
from shared.bus import Bus, topic_key
from shared.cli_args import add_bus_arguments, config_from_args
from shared.config import PerceptionConfig, SkeletonSourceName, StackConfig
from shared.messages import ConfigUpdate
from shared.service import BusService, Pending, Refusals, StepErrors, validated_update
from shared.stop_signals import stop_on_signals

log = logging.getLogger("safemimic.perception")

SERVICE_NAME = "perception"
TOPIC = "human/state"
#: perception.* settings a configuration update changes live (the rest need a restart).
_LIVE_SETTINGS = frozenset({"point_filter", "angles", "stats_interval_s"})
#: Consecutive failing frames after which the service gives up (a bug, not bad input).
_MAX_CONSECUTIVE_ERRORS = 1000


def _emit(event: str, **fields: Any) -> None:
    print(json.dumps({"event": event, **fields}), flush=True)


class PerceptionService(BusService):
    """Streams one source through the pipeline onto the bus; :meth:`run` until exhausted or stopped."""

    def __init__(self, conf: StackConfig, source: SkeletonSource, bus: Bus | None = None) -> None:
        self.conf = conf
        self.source = source
        self.pipeline = PerceptionPipeline(conf.perception, conf.human)
        self.open_bus(conf, SERVICE_NAME, bus)
        self.published = 0
        self.frame_errors = StepErrors(log, "frame", _MAX_CONSECUTIVE_ERRORS)
        self.config_version = 0
        self.refusals = Refusals()
        self._pending: Pending[tuple[int, StackConfig]] = Pending()
        try:
            self._publisher = self.bus.publisher(TOPIC)
            self.bus.subscribe("config", self.on_config)
            self.bus.declare_alive(SERVICE_NAME)
        except Exception:
            self.close()
            raise

    def on_config(self, update: ConfigUpdate) -> None:
        """Validate an accepted change (Zenoh thread); it is applied before the next frame."""
        new = validated_update(update, self.refusals, log)
        if new is None:
            return
        self._pending.put((update.version, new))

    def _apply_pending_config(self) -> None:
        pending = self._pending.take()
        if pending is None:
            return
        version, new = pending
        running = _source_settings(self.conf.perception)
        # bus and robot_id are this process's own deployment settings: never taken from an update
        if _source_settings(new.perception) != running:
            log.info("config v%d: perception source settings not applied (they take effect at a restart)", version)
        perception = new.perception.model_copy(update=running)  # the source keeps running as it is
        self.pipeline.apply(perception, new.human)
        self.conf = self.conf.model_copy(update={"perception": perception, "human": new.human})
        self.config_version = version
        log.info("applied config v%d", version)

    def wait_for_subscriber(self, timeout_s: float, stop: threading.Event) -> bool:
        """Wait up to ``timeout_s`` until some subscriber matches ``human/state``; True if one does."""
        probe = self.bus.session.declare_publisher(topic_key(self.conf.robot_id, TOPIC))
        try:
            deadline = time.monotonic() + timeout_s
            while not probe.matching_status.matching:
                if time.monotonic() >= deadline or stop.wait(0.02):
                    return False
            return True
        finally:
            probe.undeclare()

    @property
    def rejected_configs(self) -> int:
        """Configuration updates refused (they did not validate)."""
        return self.refusals.own("config")

    @property
    def errors(self) -> int:
        """Frames that failed (an unexpected exception; counted, logged, skipped)."""
        return self.frame_errors.total

    def _publish(self, frame: SkeletonFrame) -> None:
        """One frame: pending configuration → pipeline → HumanState published."""
        self._apply_pending_config()
        result = self.pipeline.step(frame)
        self._publisher.put(result.to_message(stamp=time.monotonic(), capture_stamp=frame.captured))
        self.published += 1

    def counters(self) -> dict[str, Any]:
        counters = {**asdict(self.pipeline.counters), "published": self.published, "errors": self.errors,
                    "config_version": self.config_version, "rejected_configs": self.rejected_configs,
                    "dropped_by_bus": dict(self.bus.dropped)}
        source_counters = getattr(self.source, "counters", None)  # live sources count their own failures
        if callable(source_counters):
            counters["source"] = source_counters()
        return counters

    def run(self, stop: threading.Event, duration: float | None = None) -> dict[str, Any]:
        """Stream until the source ends, ``stop`` is set or ``duration`` seconds passed; final counters."""
        perception = self.conf.perception
        if perception.wait_subscriber_s > 0 and not self.wait_for_subscriber(perception.wait_subscriber_s, stop):
            log.warning("no subscriber on %s after %.1f s: streaming anyway", TOPIC, perception.wait_subscriber_s)
        _emit("ready", source=self.source.name, fps=self.source.fps, robot_id=self.conf.robot_id)
        began = time.monotonic()
        end = began + duration if duration is not None else float("inf")
        next_stats = began + perception.stats_interval_s
        for frame in self.source.frames(stop):
            self.frame_errors.run(lambda: self._publish(frame))
            now = time.monotonic()
            if now >= next_stats:
                _emit("stats", **self.counters())
                next_stats = now + self.conf.perception.stats_interval_s
            if now >= end:
                break
        counters = {**self.counters(), "elapsed_s": time.monotonic() - began}
        _emit("done", **counters)
        return counters


def _source_settings(perception: PerceptionConfig) -> dict[str, Any]:
    """The perception settings that only take effect when the source is reopened (field → value)."""
    return {name: getattr(perception, name) for name in type(perception).model_fields if name not in _LIVE_SETTINGS}


def main(conf: StackConfig, stop: threading.Event, duration: float | None = None) -> dict[str, Any]:
    """Open the configured source and stream it (:class:`SourceUnavailable` if it cannot be opened)."""
    source = open_source(conf.perception)
    with PerceptionService(conf, source) as service:
        return service.run(stop, duration)


def build_parser(parser: argparse.ArgumentParser | None = None) -> argparse.ArgumentParser:
    parser = parser or argparse.ArgumentParser(prog="safemimic perception")
    parser.description = (
        "Run the perception service: a skeleton source (a .npz replay, a scripted scenario, a camera or a ZED) → point "
        "filter (One Euro by default or the paper's EMA, with jump rejection) → 8 pose angles + 7 human capsules in "
        "the robot frame → HumanState on safemimic/{robot_id}/human/state at the source rate."
    )
    add_bus_arguments(parser)
    group = parser.add_argument_group("perception (overrides perception.* of the configuration)")
    group.add_argument("--source", choices=[name.value for name in SkeletonSourceName], help="skeleton source")
    group.add_argument("--recording", metavar="FILE.npz", help="replay this recording (implies --source replay)")
    group.add_argument("--scenario", metavar="NAME", help="scripted scenario (implies --source scenario)")
    group.add_argument("--device", metavar="DEVICE", help="camera index or video file (implies --source camera unless --source zed)")
    group.add_argument("--placement", metavar="WHERE", help="auto | side-by-side | facing | recorded | x,y,yaw (m, m, rad)")
    group.add_argument("--estimator", choices=["continuous", "paper"], help="shoulder-angle estimator")
    group.add_argument("--loop", action="store_true", help="start over at the end of the source")
    group.add_argument("--fast", action="store_true", help="as fast as possible instead of real time")
    group.add_argument("--wait-subscriber", type=float, metavar="SECONDS", help="wait this long for a subscriber first")
    group.add_argument("--duration", type=float, metavar="SECONDS", help="stop after this many seconds")
    return parser


def _device(text: str) -> int | str:
    """``--device``: a camera index, a stream URL, or a video file (made absolute)."""
    if text.isdigit():
        return int(text)
    return text if "://" in text else str(Path(text).expanduser().resolve())


def perception_overrides(args: argparse.Namespace) -> dict[str, Any]:
    """``perception.*`` overrides implied by the flags given."""
    perception: dict[str, Any] = {}
    if args.recording:
        perception.update(source="replay", recording=str(Path(args.recording).expanduser().resolve()))
    if args.scenario:
        perception.update(source="scenario", scenario=args.scenario)
    if args.device:
        perception.update(source="camera", camera={"device": _device(args.device)})
    if args.source:
        perception["source"] = args.source
    if args.placement:
        perception["placement"] = args.placement
    if args.estimator:
        perception["angles"] = {"estimator": args.estimator}
    if args.loop:
        perception["loop"] = True
    if args.fast:
        perception["realtime"] = False
    if args.wait_subscriber is not None:
        perception["wait_subscriber_s"] = args.wait_subscriber
    return {"perception": perception} if perception else {}


def run(args: argparse.Namespace) -> int:
    if args.duration is not None and not args.duration > 0:
        print("--duration must be > 0", file=sys.stderr)
        return 2
    conf = config_from_args(args, perception_overrides(args))
    with stop_on_signals() as stop:  # a ConfigError or SourceUnavailable: shared.entrypoint says it, exit 2
        main(conf, stop, args.duration)
    return 0

