"""The live viewer's loop body: newest bus messages → Rerun, at most once per frame.

:class:`LiveScene` reads the newest valid message of each topic (:meth:`shared.bus.Bus.newest`:
samples wait in Zenoh's queue and only the newest is decoded, so a 500 Hz topic costs this
process one decode per frame) and logs what changed since the last frame:

- ``JointState`` → the robot's body poses and CBF capsules at the measured q (``robot/cbf``),
  ``joints/{joint}/q`` (rad); before the first one, the newest command's q poses the robot;
- ``JointCommand`` → ``joints/{joint}/q_cbf`` (rad, the safe target) and the mode;
- ``SafetyStatus`` → ``barriers/cbf/min_h/{self,human}`` (m, the safety service's own min h per
  pair group), ``robot/cbf/status/{mode,qp_ms,step_ms,deadline_misses}``;
- ``HumanState`` → ``person/perceived`` (keypoints, bones, capsules where valid).

Binding pairs: the safety service does not publish which rows bind, so the viewer evaluates
every monitored pair (the description's self pairs and every robot × person capsule pair) on the
capsules it draws, h = d − (r_A + r_B + φ), and draws the closest-point segments of the pairs with
h ≤ ``near_m`` in yellow (``barriers/cbf/binding``): those the CBF keeps from closing, or about to.

A message that fails to decode is dropped and counted by the bus; one that fails to draw is
counted in :attr:`LiveScene.errors` and skipped; a topic silent for :data:`STALE_S` is reported
stale (logged once to ``viewer/log``, the last picture stays). Nothing here raises into the loop.
"""

from __future__ import annotations

import logging
import time
from collections import Counter

import numpy as np
import rerun as rr

from services.viewer import draw
from services.viewer import entities as E
from services.viewer.robot_mesh import RobotMesh
from shared.bus import Bus
from shared.messages import SafetyMode
from shared.names import CAPSULE_NAMES

log = logging.getLogger(__name__)
TOPICS = ("robot/joint_state", "robot/command", "safety/status", "human/state")
#: A topic silent this long (s) is reported stale.
STALE_S = 1.0
_MODES = tuple(SafetyMode)


def monitored_pairs(self_pairs: list[tuple[str, str]]) -> tuple[str, ...]:
    """The monitored pair names (PairSet naming): self pairs, then every robot × person capsule."""
    return tuple(f"{a}|{b}" for a, b in self_pairs) + tuple(
        f"{robot}|human.{human}" for human in CAPSULE_NAMES for robot in CAPSULE_NAMES)


class LiveScene:
    """What the viewer draws each frame (module docstring); ``rec`` is the Rerun stream, ``radii``
    the robot's CBF capsule radii (7,) m, ``phi`` the CBF margin (m)."""

    def __init__(self, bus: Bus, rec: rr.RecordingStream, mesh: RobotMesh, radii: np.ndarray, phi: float,
                 near_m: float) -> None:
        self.bus, self.rec, self.mesh, self.radii = bus, rec, mesh, np.asarray(radii, float)
        self.phi, self.near_m = phi, near_m
        self.joints = tuple(mesh.spec.imitation_joints)
        self.pairs = monitored_pairs([tuple(p) for p in mesh.spec.self_pairs])
        self._radius_of = {name: r for name, r in zip(CAPSULE_NAMES, self.radii)}
        self.newest = {topic: bus.newest(topic) for topic in TOPICS}
        self.received: Counter[str] = Counter()  # new messages drawn, per topic
        self.logged: Counter[str] = Counter()  # frames logged per entity group
        self.errors: Counter[str] = Counter()
        self.stale: set[str] = set()
        self._seen: dict[str, tuple[str, int, float]] = {}  # topic → (source, seq, stamp) last drawn
        self._heard: dict[str, float] = {}
        self._robot_caps: np.ndarray | None = None
        self._human: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        self.start = time.monotonic()
        draw.log_scene_static(rec, self.joints)
        draw.log_robot_meshes(rec, mesh, "cbf")

    def _new(self, topic: str, now: float):
        held = self.newest[topic].get()
        if held is None:
            return None
        m = held.message
        key = (m.source, m.seq, m.stamp)
        if self._seen.get(topic) == key:
            if topic not in self.stale and now - self._heard.get(topic, now) > STALE_S:
                self.stale.add(topic)
                self.rec.log("viewer/log", rr.TextLog(f"{topic}: no message for {STALE_S:g} s (publisher gone?)",
                                                      level="WARN"))
            return None
        self._seen[topic], self._heard[topic] = key, now
        if topic in self.stale:
            self.stale.discard(topic)
            self.rec.log("viewer/log", rr.TextLog(f"{topic}: messages again", level="INFO"))
        self.received[topic] += 1
        return m

    def frame(self, now: float | None = None) -> None:
        """Draw what arrived since the last frame (never raises: failures are counted)."""
        now = time.monotonic() if now is None else now
        self.rec.set_time(E.TIMELINE, duration=now - self.start)
        changed = False
        for topic in TOPICS:
            try:
                message = self._new(topic, now)
                if message is not None:
                    changed |= getattr(self, "_draw_" + topic.replace("/", "_"))(message)
            except Exception:  # a valid message the drawing code cannot handle: count, go on
                self.errors[topic] += 1
                log.exception("drawing %s failed", topic)
        if changed:
            try:
                self._draw_binding()
            except Exception:
                self.errors["binding"] += 1
                log.exception("drawing the binding pairs failed")
        for topic, count in self.bus.dropped.items():
            draw.log_scalar(self.rec, f"viewer/dropped/{E.safe_part(topic)}", count)

    def _pose_robot(self, q: np.ndarray) -> None:
        pose = self.mesh.pose(q)
        draw.log_robot_pose(self.rec, self.mesh, "cbf", pose, self.radii)
        self._robot_caps = pose.capsules
        self.logged["robot"] += 1

    def _draw_robot_joint_state(self, m) -> bool:
        self._pose_robot(m.q)
        for name, value in zip(self.joints, m.q):
            draw.log_scalar(self.rec, E.joint(name, "q"), value)
        return True

    def _draw_robot_command(self, m) -> bool:
        if "robot/joint_state" not in self._seen:  # no measured state yet: show the commanded pose
            self._pose_robot(m.q)
        for name, value in zip(self.joints, m.q):
            draw.log_scalar(self.rec, E.joint(name, "q_cbf"), value)
        self.logged["joints"] += 1
        return "robot/joint_state" not in self._seen

    def _draw_safety_status(self, m) -> bool:
        draw.log_scalar(self.rec, E.barriers("cbf", "min_h", "self"), m.min_h_self)
        draw.log_scalar(self.rec, E.barriers("cbf", "min_h", "human"), m.min_h_human)
        draw.log_scalar(self.rec, E.robot("cbf", "status", "mode"), _MODES.index(m.mode))
        draw.log_scalar(self.rec, E.robot("cbf", "status", "qp_ms"), m.qp_solve_time_ms)
        draw.log_scalar(self.rec, E.robot("cbf", "status", "step_ms"), m.step_time_ms)
        draw.log_scalar(self.rec, E.robot("cbf", "status", "deadline_misses"), m.deadline_misses)
        self.logged["status"] += 1
        return False

    def _draw_human_state(self, m) -> bool:
        draw.log_person(self.rec, "perceived", m.keypoints, m.keypoint_valid, m.capsules, m.capsule_radii,
                        m.capsule_valid)
        self._human = (m.capsules, m.capsule_radii, m.capsule_valid)
        self.logged["person"] += 1
        return True

    def near_pairs(self) -> list[str]:
        """Monitored pairs whose h (on the drawn capsules, margin φ) is ≤ ``near_m``."""
        if self._robot_caps is None:
            return []
        people, people_r = np.full((len(CAPSULE_NAMES), 2, 3), np.nan), np.zeros(len(CAPSULE_NAMES))
        if self._human is not None:
            caps, radii, valid = self._human
            people = np.where(valid[:, None, None], caps, np.nan)
            people_r = radii
        seg = draw.binding_segments(self.pairs, self._robot_caps, people)  # every name resolves: aligned
        d = np.linalg.norm(seg[:, 0] - seg[:, 1], axis=1)
        r = np.array([self._radius_of[n.split("|")[0]] + self._pair_radius(n.split("|")[1], people_r) for n in self.pairs])
        with np.errstate(invalid="ignore"):
            near = np.isfinite(d) & (d - r - self.phi <= self.near_m)
        return [n for n, on in zip(self.pairs, near) if on]

    def _pair_radius(self, member: str, people_r: np.ndarray) -> float:
        if "." in member:
            return float(people_r[CAPSULE_NAMES.index(member.split(".", 1)[1])])
        return float(self._radius_of[member])

    def _draw_binding(self) -> None:
        names = self.near_pairs()
        people = np.zeros((0, 2, 3)) if self._human is None else self._human[0]
        segments = draw.binding_segments(names, self._robot_caps, people) if names else np.empty((0, 2, 3))
        draw.log_binding(self.rec, "cbf", segments)
        self.logged["binding"] += 1

    def stats(self) -> dict:
        """Counters for the stats line: messages drawn per topic, entity frames, drop/error counts."""
        return {"received": dict(self.received), "logged": dict(self.logged), "dropped": dict(self.bus.dropped),
                "superseded": dict(self.bus.superseded), "errors": dict(self.errors), "stale": sorted(self.stale)}
