"""The live viewer's loop body: newest bus messages → Rerun, at most once per frame.

:class:`LiveScene` reads the newest valid message of each topic (:meth:`shared.bus.Bus.newest`:
samples wait in Zenoh's queue and only the newest is decoded; the viewer's session lets in at
most one sample per frame of the control-rate topics, :data:`DECIMATED`) and logs what changed
since the last frame:

- ``JointState`` → the robot's body poses and CBF capsules at the measured q (``robot/cbf``),
  ``joints/{joint}/q`` (rad); before the first one, the newest command's q poses the robot. A
  frame logs only the bodies that moved more than :data:`POSE_TOLERANCE` since they were last
  logged (legs never, a resting arm not); every body once every :data:`FULL_POSE_S`, so a viewer
  that joins late or a server that dropped old data still has them all;
- ``JointCommand`` → ``joints/{joint}/q_cbf`` (rad, the safe target);
- ``SafetyStatus`` → ``joints/{joint}/q_nom`` (rad, the target the filter tracked),
  ``barriers/cbf/min_h/{self,human}`` (m, the safety service's own min h per pair group),
  ``robot/cbf/status/{mode,qp_ms,step_ms,deadline_misses}``, what the stop does
  (``robot/cbf/status/{person_intrusion,backing_out}``, 1 or 0), how late the camera is
  (``robot/cbf/status/human_lateness_ms``) and its binding pairs;
- ``HumanState`` → ``person/perceived`` (keypoints, bones, capsules where valid).

The time series are sent in batches every :data:`SERIES_BATCH_S` (:class:`draw.SeriesBatch`; each
sample keeps its own time), so the plots trail the 3D view by at most that much.

Binding pairs (``barriers/cbf/binding``, yellow as in the paper's figures): the closest-point
segments, on the capsules drawn, of the pairs the newest ``SafetyStatus`` names in
``binding_pairs`` — those whose CBF row was at its bound in the safety service's QP.

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

log = logging.getLogger(__name__)
TOPICS = ("robot/joint_state", "robot/command", "safety/status", "human/state")
#: The control-rate topics (500 Hz commands, the executor's states, 50 Hz status): the viewer's
#: session lets in at most one sample per frame of each (``Bus(max_hz=...)``). ``human/state``
#: comes at the camera's rate (30 fps), one per frame already; a rule at that rate would drop
#: every frame that arrives a little early.
DECIMATED = ("robot/joint_state", "robot/command", "safety/status")
#: A topic silent this long (s) is reported stale.
STALE_S = 1.0
#: Every body's pose is logged at least this often (s); in between only the bodies that moved.
FULL_POSE_S = 1.0
#: A body moved when its position (m) or a quaternion component changed by more than this
#: (0.2 mm; ≈ 0.02° of rotation): less is not visible.
POSE_TOLERANCE = 2e-4
#: The time series gathered are sent this often (s).
SERIES_BATCH_S = 0.5
_MODES = tuple(SafetyMode)


class LiveScene:
    """What the viewer draws each frame (module docstring); ``rec`` is the Rerun stream, ``radii``
    the robot's CBF capsule radii (7,) m."""

    def __init__(self, bus: Bus, rec: rr.RecordingStream, mesh: RobotMesh, radii: np.ndarray) -> None:
        self.bus, self.rec, self.mesh, self.radii = bus, rec, mesh, np.asarray(radii, float)
        self.joints = tuple(mesh.spec.imitation_joints)
        self.newest = {topic: bus.newest(topic) for topic in TOPICS}
        self.received: Counter[str] = Counter()  # new messages drawn, per topic
        self.logged: Counter[str] = Counter()  # frames logged per entity group
        self.errors: Counter[str] = Counter()
        self.stale: set[str] = set()
        self._seen: dict[str, tuple[str, int, float]] = {}  # topic → (source, seq, stamp) last drawn
        self._heard: dict[str, float] = {}
        self._robot_caps: np.ndarray | None = None
        self._human: np.ndarray | None = None  # the person's capsules (7, 2, 3) m, NaN where invalid
        self._binding: list[str] = []
        self._next_full_pose = -np.inf
        self._logged_pose: tuple[np.ndarray, np.ndarray] | None = None  # per body: last logged position, quaternion
        self.series = draw.SeriesBatch(rec)
        self._next_series = -np.inf
        self._t = 0.0  # the frame's time on the timeline (s)
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
        self._t = now - self.start
        self.rec.set_time(E.TIMELINE, duration=self._t)
        changed = False  # the binding segments need drawing again
        for topic in TOPICS:
            try:
                message = self._new(topic, now)
                if message is not None:
                    changed |= getattr(self, "_draw_" + topic.replace("/", "_"))(message, now)
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
            self.series.add(f"viewer/dropped/{E.safe_part(topic)}", self._t, count)
        if now >= self._next_series:
            self.flush()
            self._next_series = now + SERIES_BATCH_S

    def flush(self) -> None:
        """Send the time series gathered so far (:data:`SERIES_BATCH_S`; call once more at the end)."""
        try:
            self.series.send()
        except Exception:
            self.errors["series"] += 1
            log.exception("sending the time series failed")

    def _pose_robot(self, q: np.ndarray, now: float) -> None:
        pose = self.mesh.pose(q)
        moved = np.ones(len(self.mesh.bodies), bool)
        if now < self._next_full_pose and self._logged_pose is not None:
            position, quaternion = self._logged_pose
            moved = (np.abs(pose.translations - position).max(axis=1) > POSE_TOLERANCE) | \
                (np.abs(pose.quaternions - quaternion).max(axis=1) > POSE_TOLERANCE)
        else:
            self._next_full_pose = now + FULL_POSE_S
            self._logged_pose = (pose.translations.copy(), pose.quaternions.copy())
        draw.log_robot_pose(self.rec, self.mesh, "cbf", pose, self.radii, moved)
        self._logged_pose[0][moved], self._logged_pose[1][moved] = pose.translations[moved], pose.quaternions[moved]
        self._robot_caps = pose.capsules
        self.logged["robot"] += 1

    def _log_joints(self, series: str, q: np.ndarray) -> None:
        for name, value in zip(self.joints, q):
            self.series.add(E.joint(name, series), self._t, value)

    def _draw_robot_joint_state(self, m, now: float) -> bool:
        self._pose_robot(m.q, now)
        self._log_joints("q", m.q)
        return True

    def _draw_robot_command(self, m, now: float) -> bool:
        posed = "robot/joint_state" not in self._seen  # no measured state yet: show the commanded pose
        if posed:
            self._pose_robot(m.q, now)
        self._log_joints("q_cbf", m.q)
        self.logged["joints"] += 1
        return posed

    def _draw_safety_status(self, m, now: float) -> bool:
        if m.q_nom is not None:
            self._log_joints("q_nom", m.q_nom)
        self.series.add(E.barriers("cbf", "min_h", "self"), self._t, m.min_h_self)
        self.series.add(E.barriers("cbf", "min_h", "human"), self._t, m.min_h_human)
        self.series.add(E.robot("cbf", "status", "mode"), self._t, _MODES.index(m.mode))
        self.series.add(E.robot("cbf", "status", "qp_ms"), self._t, m.qp_solve_time_ms)
        self.series.add(E.robot("cbf", "status", "step_ms"), self._t, m.step_time_ms)
        self.series.add(E.robot("cbf", "status", "deadline_misses"), self._t, m.deadline_misses)
        self.series.add(E.robot("cbf", "status", "person_intrusion"), self._t, float(m.person_intrusion))
        self.series.add(E.robot("cbf", "status", "backing_out"), self._t, float(m.backing_out))
        self.series.add(E.robot("cbf", "status", "human_lateness_ms"), self._t, m.human_lateness_ms)
        self.logged["status"] += 1
        changed = m.binding_pairs != self._binding
        self._binding = list(m.binding_pairs)
        return changed

    def _draw_human_state(self, m, now: float) -> bool:
        draw.log_person(self.rec, "perceived", m.keypoints, m.keypoint_valid, m.capsules, m.capsule_radii,
                        m.capsule_valid)
        self._human = np.where(m.capsule_valid[:, None, None], m.capsules, np.nan)
        self.logged["person"] += 1
        return True

    def _draw_binding(self) -> None:
        """The binding pairs' closest-point segments on the capsules drawn now (a pair whose capsule is
        not drawn, e.g. an invalid person capsule, is left out)."""
        segments = np.empty((0, 2, 3))
        if self._binding and self._robot_caps is not None:
            people = np.zeros((0, 2, 3)) if self._human is None else self._human
            segments = draw.binding_segments(self._binding, self._robot_caps, people)
            segments = segments[np.isfinite(segments).all(axis=(1, 2))]
        draw.log_binding(self.rec, "cbf", segments)
        self.logged["binding"] += 1

    def stats(self) -> dict:
        """Counters for the stats line: messages drawn per topic, entity frames, drop/error counts."""
        return {"received": dict(self.received), "logged": dict(self.logged), "dropped": dict(self.bus.dropped),
                "superseded": dict(self.bus.superseded), "errors": dict(self.errors), "stale": sorted(self.stale)}
