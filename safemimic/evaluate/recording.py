"""``safemimic evaluate --rrd FILE``: both runs of an evaluation as one Rerun recording.

One timeline ``time`` (s from the first frame). The 3D scene is drawn at ≤ :data:`SCENE_RATE_HZ`
(every k-th control step): the robot with the CBF layer (``robot/cbf``, its simulated joints
q_sim) and without it (``robot/nominal``, a translucent ghost), their CBF capsules, the true
person (``person/true``: the recording as recorded) and the perceived one (``person/perceived``:
the delayed, filtered state the safety layer held), and the binding pairs' closest-point segments
in yellow (``barriers/cbf/binding``, between the robot at q_sim and the perceived person). The
time series are at the control rate: every monitored h and min h per group (``barriers/{run}``),
mode, QP time and true-person contacts (``robot/{run}/status``), and per joint q_true, q_nom,
q_cbf, the simulated q with and without the CBF (``joints/{joint}``). Entity names and drawing:
:mod:`services.viewer.entities`, :mod:`services.viewer.draw` (the live viewer's own code).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from safemimic.evaluate.episode import Episode
from safemimic.evaluate.evaluation import Evaluation
from services.safety.assembly import robot_radii

#: The 3D scene's rate in a recording (Hz); the series keep the control rate.
SCENE_RATE_HZ = 30.0


def _min_h(ep: Episode, self_rows: np.ndarray) -> np.ndarray:
    with np.errstate(all="ignore"):
        return np.fmin.reduce(ep.h[:, self_rows], axis=1, initial=np.inf) if self_rows.any() else np.full(len(ep.t), np.nan)


def write_rrd(evaluation: Evaluation, path: Path) -> Path:
    """Write ``evaluation``'s recording to ``path`` (a ``.rrd`` file; its folder is created)."""
    import rerun as rr

    from services.viewer import draw
    from services.viewer import entities as E
    from services.viewer.robot_mesh import RobotMesh

    e = evaluation
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    rec = rr.RecordingStream("safemimic_evaluate", recording_id=f"{e.source.name}-{e.placement}", send_properties=False)
    rec.save(path)
    joints = e.kinematics.joint_names
    mesh = RobotMesh(e.kinematics.spec)
    radii = robot_radii(e.conf, e.kinematics)
    draw.log_scene_static(rec, joints)
    runs = {"cbf": e.cbf, "nominal": e.nominal}
    for run in runs:
        draw.log_robot_meshes(rec, mesh, run)

    t = e.cbf.t
    step = max(1, round(e.conf.safety.rate_hz / SCENE_RATE_HZ))
    for k in range(0, len(t), step):
        rec.set_time(E.TIMELINE, duration=float(t[k]))
        for run, ep in runs.items():
            draw.log_robot_pose(rec, mesh, run, mesh.pose(ep.q_sim[k]), radii)
        p = e.person
        draw.log_person(rec, "true", p.keypoints[k], p.valid[k], p.capsules[k], p.radii, p.capsule_valid[k])
        index = int(e.cbf.human[k])
        people = np.empty((0, 2, 3))
        if index >= 0:
            s = e.human.states[index]
            draw.log_person(rec, "perceived", s.keypoints, s.keypoint_valid, s.capsules, s.capsule_radii, s.capsule_valid)
            people = np.where(s.capsule_valid[:, None, None], s.capsules, np.nan)
        names = [name for name, on in zip(e.cbf.pairs.names, e.cbf.active[k]) if on]
        segments = draw.binding_segments(names, e.cbf.robot_capsules[k], people)
        draw.log_binding(rec, "cbf", segments[np.isfinite(segments).all(axis=(1, 2))])

    for run, ep in runs.items():
        is_self = ep.pairs.is_self
        draw.send_series(rec, E.barriers(run, "min_h", "self"), t, _min_h(ep, is_self))
        draw.send_series(rec, E.barriers(run, "min_h", "human"), t, _min_h(ep, ~is_self))
        for i, name in enumerate(ep.pairs.names):
            draw.send_series(rec, E.barriers(run, "h", E.safe_part(name)), t, ep.h[:, i])
        draw.send_series(rec, E.robot(run, "status", "mode"), t, ep.mode.astype(float))
        draw.send_series(rec, E.robot(run, "status", "qp_ms"), t, ep.qp_ms)
        draw.send_series(rec, E.robot(run, "status", "contacts"), t, ep.contact_steps[:, 2].astype(float))
    for j, name in enumerate(joints):
        for series, values in (("q_true", e.person.q_true[:, j]), ("q_nom", e.cbf.q_nom[:, j]),
                               ("q_cbf", e.cbf.q_cbf[:, j]), ("q", e.cbf.q_sim[:, j]),
                               ("q_without_cbf", e.nominal.q_sim[:, j])):
            draw.send_series(rec, E.joint(name, series), t, values)
    rec.flush()
    rec.disconnect()
    return path
