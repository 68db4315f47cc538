"""Skeleton sources by configuration: ``replay`` (a .npz recording), ``scenario`` (scripted), ``camera``, ``zed``.

Every source is a :class:`~services.perception.base.SkeletonSource` yielding robot-frame frames.
The live sources, ``camera`` (OpenCV capture + BlazePose monocular 3D pose) and ``zed`` (ZED SDK
body tracking), live in :mod:`services.perception.camera` and are imported only when configured
(their runtimes are the ``camera`` extra and the ZED SDK); they yield frames already in the robot
frame (camera extrinsics applied), with ``t`` = ``captured`` = the monotonic capture time (a video
file: its own frame times).
"""

from __future__ import annotations

import numpy as np

from services.perception.errors import PerceptionError
from services.perception.placement import parse_placement, place_recording
from services.perception.scenarios import get_scenario, scenario_frames
from services.perception.base import PlayedSource, SkeletonSource
from shared.body import Body
from shared.config import PerceptionConfig, SkeletonSourceName, resolve_config_path
from shared.skeleton import RecordingError, read_recording, with_hip_centre_pelvis


class SourceUnavailable(PerceptionError, RuntimeError):
    """The configured source cannot be opened (missing file, bad recording, no camera, weights or runtime)."""


def open_source(conf: PerceptionConfig, paper_zone: float | None = None) -> SkeletonSource:
    """The source ``conf.source`` describes; :class:`SourceUnavailable` with the reason if it cannot be."""
    if conf.source == SkeletonSourceName.REPLAY:
        return open_replay(conf)
    if conf.source == SkeletonSourceName.SCENARIO:
        return open_scenario(conf, conf.angles.paper_zone if paper_zone is None else paper_zone)
    if conf.source == SkeletonSourceName.CAMERA:
        from services.perception.camera.source import open_camera

        return open_camera(conf)
    from services.perception.camera.zed import open_zed

    return open_zed(conf)


def open_replay(conf: PerceptionConfig) -> PlayedSource:
    """Replay ``conf.recording``, normalised and placed, paced and looped as configured; a missing
    pelvis is the hip centre, as the camera sources' (:func:`~shared.skeleton.with_hip_centre_pelvis`)."""
    if not conf.recording:
        raise SourceUnavailable("the replay source needs a recording (perception.recording or --recording FILE.npz)")
    path = resolve_config_path(conf.recording)  # relative: against the configuration folder
    try:
        recording = read_recording(path)
        placement = parse_placement(conf.placement, conf)
    except (RecordingError, ValueError) as exc:
        raise SourceUnavailable(str(exc)) from None
    placed = place_recording(with_hip_centre_pelvis(recording), placement)
    return PlayedSource(
        name=f"replay {path.name}",
        times=placed.t,
        pose=lambda i: (placed.xyz[i], placed.conf[i]),
        fps=placed.fps,
        realtime=conf.realtime,
        loop=conf.loop,
    )


def open_scenario(conf: PerceptionConfig, paper_zone: float) -> PlayedSource:
    """One period of ``conf.scenario`` (endless and seamless with ``loop``), placed as configured."""
    try:
        scenario = get_scenario(conf.scenario)
        placement = parse_placement(conf.placement, conf, auto=scenario.placement)
        body = Body(shoulder_width=conf.scenario_shoulder_width)
    except ValueError as exc:
        raise SourceUnavailable(str(exc)) from None
    fps = conf.scenario_fps
    times = np.arange(max(1, round(scenario.period * fps))) / fps
    _, xyz = scenario_frames(scenario, times, placement, body, paper_zone)
    confidence = np.ones(xyz.shape[:2])
    return PlayedSource(
        name=f"scenario {scenario.name}",
        times=times,
        pose=lambda i: (xyz[i], confidence[i]),
        fps=fps,
        realtime=conf.realtime,
        loop=conf.loop,
        seamless=True,
    )
