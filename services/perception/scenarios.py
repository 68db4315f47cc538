"""Scripted synthetic motions with known pose angles (the paper's scenarios and a few more).

A scenario is a periodic θ(t) (:data:`shared.names.POSE_ANGLE_NAMES` order, radians, the
convention of :mod:`services.perception.angles`): keyframes joined by cosine easing (zero
velocity at every keyframe, C¹), plus optional oscillations. :func:`scenario_frames` turns it
into keypoints of a :class:`~shared.body.Body` placed in the robot frame, so a
scenario can be streamed, written as a recording and compared against the angles it was made of.

Poses name angles per arm as ``left_*``/``right_*``, or ``near_*``/``far_*`` for the arm on the
robot's side and the other one (:attr:`Placement.near_arm`).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from services.perception.placement import Placement
from services.perception.synthetic import DEFAULT_PAPER_ZONE, skeleton
from shared.body import Body
from shared.names import KEYPOINT_NAMES
from shared.skeleton import Recording

_ANGLE_INDEX = {"torso_roll": 0, "torso_pitch": 1}
for _side, _first in (("left", 2), ("right", 5)):
    for _offset, _joint in enumerate(("pitch", "roll", "elbow")):
        _ANGLE_INDEX[f"{_side}_{_joint}"] = _first + _offset

#: Standing relaxed: arms hanging slightly forward and out, elbows a little bent.
NEUTRAL: dict[str, float] = {
    "torso_roll": 0.0, "torso_pitch": 0.0,
    "left_pitch": 0.05, "left_roll": 0.08, "left_elbow": 0.2,
    "right_pitch": 0.05, "right_roll": 0.08, "right_elbow": 0.2,
}


def _resolve(pose: dict[str, float], near_arm: str) -> np.ndarray:
    """θ (8,) from a pose dict on top of :data:`NEUTRAL`; near/far resolved to left/right."""
    far_arm = "left" if near_arm == "right" else "right"
    theta = np.array([NEUTRAL[name] for name in sorted(_ANGLE_INDEX, key=_ANGLE_INDEX.get)])
    for name, value in pose.items():
        side, _, joint = name.partition("_")
        side = {"near": near_arm, "far": far_arm}.get(side, side)
        theta[_ANGLE_INDEX[f"{side}_{joint}"]] = value
    return theta


@dataclass(frozen=True)
class Scenario:
    """A periodic scripted motion: keyframes (time s, pose) over one ``period``, plus ``wobble``.

    ``wobble(t)`` returns offsets to add to θ (a dict of angle name → rad). ``placement`` is the
    named placement used when the configuration says ``auto``.
    """

    name: str
    description: str
    period: float
    placement: str
    keyframes: tuple[tuple[float, dict[str, float]], ...]
    wobble: Callable[[float], dict[str, float]] = field(default=lambda t: {})

    def theta(self, t: float, near_arm: str = "right") -> np.ndarray:
        """θ (8,) at time ``t`` (s; periodic)."""
        t = t % self.period
        times = [k[0] for k in self.keyframes]
        i = max(0, min(len(times) - 2, int(np.searchsorted(times, t, side="right")) - 1))
        (t0, pose0), (t1, pose1) = self.keyframes[i], self.keyframes[i + 1]
        s = min(1.0, max(0.0, (t - t0) / (t1 - t0)))
        ease = 0.5 * (1.0 - math.cos(math.pi * s))
        theta = (1.0 - ease) * _resolve(pose0, near_arm) + ease * _resolve(pose1, near_arm)
        return theta + _resolve_offsets(self.wobble(t), near_arm)


def _resolve_offsets(offsets: dict[str, float], near_arm: str) -> np.ndarray:
    return _resolve(offsets, near_arm) - _resolve({}, near_arm) if offsets else np.zeros(len(_ANGLE_INDEX))


def _window(t: float, start: float, end: float, ramp: float) -> float:
    """Smooth 0→1→0 envelope: 1 on [start + ramp, end − ramp], 0 outside [start, end]."""
    rise = min(1.0, max(0.0, (t - start) / ramp))
    fall = min(1.0, max(0.0, (end - t) / ramp))
    return 0.5 * (1.0 - math.cos(math.pi * min(rise, fall)))


def _sway(t: float) -> dict[str, float]:
    """Breathing and weight shifts while standing (periods dividing 12 s)."""
    return {
        "torso_pitch": 0.03 * math.sin(2 * math.pi * t / 4.0),
        "torso_roll": 0.02 * math.sin(2 * math.pi * t / 6.0),
        "left_pitch": 0.05 * math.sin(2 * math.pi * t / 3.0),
        "right_pitch": -0.05 * math.sin(2 * math.pi * t / 3.0),
    }


def _wave(t: float) -> dict[str, float]:
    """The hand waving (1.5 Hz) while the arm is up."""
    envelope = _window(t, 1.5, 4.5, 0.4)
    phase = 2 * math.pi * 1.5 * t
    return {"right_elbow": 0.4 * envelope * math.sin(phase), "right_roll": 0.2 * envelope * math.sin(phase)}


_CROSS = {"left_pitch": 1.25, "left_roll": -0.8, "left_elbow": 1.2,
          "right_pitch": 1.1, "right_roll": -0.8, "right_elbow": 1.2}
# Side by side: the far arm rises sideways (far pitch stays neutral), so the robot, imitating it
# with its arm on the person's side, swings that arm into the person; the near arm rises sideways
# over into the robot's workspace, sweeps forward and back.
_ARMS_OUT = {"near_pitch": 0.2, "near_roll": 1.2, "near_elbow": 0.4, "far_roll": 1.2, "far_elbow": 0.2}
_NEAR_FORWARD = {**_ARMS_OUT, "near_pitch": 1.0, "near_roll": 0.6, "near_elbow": 0.5}
_REACH = {"left_pitch": 1.4, "left_roll": 0.05, "left_elbow": 0.15,
          "right_pitch": 1.4, "right_roll": 0.05, "right_elbow": 0.15}
_WAVE_UP = {"right_pitch": 2.3, "right_roll": 0.35, "right_elbow": 1.0}

SCENARIOS: dict[str, Scenario] = {
    s.name: s
    for s in (
        Scenario(
            "cross-arm-reach",
            "both arms reach forward and across the chest (a retargeted robot would hit itself)",
            6.0, "side-by-side",
            ((0.0, {}), (1.0, {}), (2.5, _CROSS), (3.5, _CROSS), (5.0, {}), (6.0, {})),
        ),
        Scenario(
            "side-by-side-arm-raise",
            "beside the robot both arms rise sideways: the near one into the robot's workspace (then it sweeps "
            "forward and back), the far one so that the imitating robot swings its arm into the person; both lower",
            8.0, "side-by-side",
            ((0.0, {}), (1.0, {}), (2.5, _ARMS_OUT), (3.5, _NEAR_FORWARD), (4.5, _ARMS_OUT), (6.0, {}), (8.0, {})),
        ),
        Scenario("neutral", "standing relaxed, breathing and shifting weight", 12.0, "side-by-side",
                 ((0.0, {}), (12.0, {})), _sway),
        Scenario(
            "wave",
            "the right hand is raised above the shoulder and waves, then lowered",
            6.0, "facing",
            ((0.0, {}), (0.5, {}), (1.5, _WAVE_UP), (4.5, _WAVE_UP), (5.5, {}), (6.0, {})),
            _wave,
        ),
        Scenario(
            "reach-forward",
            "both arms reach straight forward towards the robot, then come back",
            6.0, "facing",
            ((0.0, {}), (0.5, {}), (2.0, _REACH), (3.5, _REACH), (5.0, {}), (6.0, {})),
        ),
    )
}


def get_scenario(name: str) -> Scenario:
    """The scenario called ``name``; ValueError listing the known ones otherwise."""
    try:
        return SCENARIOS[name]
    except KeyError:
        raise ValueError(f"unknown scenario {name!r}; known: {', '.join(SCENARIOS)}") from None


def scenario_frames(
    scenario: Scenario,
    times: np.ndarray,
    placement: Placement,
    body: Body = Body(),
    paper_zone: float = DEFAULT_PAPER_ZONE,
) -> tuple[np.ndarray, np.ndarray]:
    """(θ (T, 8), keypoints (T, 15, 3) in the robot frame) at ``times`` (s)."""
    theta = np.array([scenario.theta(float(t), placement.near_arm) for t in times])
    xyz = np.array([placement.apply(skeleton(th, body, paper_zone)) for th in theta])
    return theta, xyz


def scenario_recording(
    scenario: Scenario, seconds: float, fps: float, placement: Placement, body: Body = Body()
) -> Recording:
    """The scenario as a recording (architecture §6) of ``seconds`` at ``fps``, in the robot frame."""
    if not (seconds > 0 and fps > 0):
        raise ValueError("seconds and fps must be > 0")
    times = np.arange(max(1, round(seconds * fps))) / fps
    _, xyz = scenario_frames(scenario, times, placement, body)
    source = (
        f"safemimic scenario {scenario.name!r} ({scenario.description}); synthetic person "
        f"shoulder_width={body.shoulder_width} m; placement x={placement.x:.3f} y={placement.y:.3f} "
        f"yaw={placement.yaw:.4f} rad (robot frame: x forward, y left, z up, floor z = 0)"
    )
    return Recording(t=times, xyz=xyz, conf=np.ones((len(times), len(KEYPOINT_NAMES))), fps=float(fps), source=source)
