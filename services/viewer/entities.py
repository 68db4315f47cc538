"""Entity paths, colours and the default layout of every safemimic Rerun recording.

One naming for the live viewer and the evaluator's ``--rrd`` files (frames: the robot frame,
metres, z up; time on the ``time`` timeline, seconds):

- ``robot/{run}/mesh/{body}``: the robot's body meshes (static) and their world poses;
  ``robot/{run}/capsules``: its 7 CBF capsules; ``robot/{run}/status/{mode,qp_ms,contacts}``.
  ``run`` is ``cbf`` (with the safety layer: the live robot) or ``nominal`` (the evaluator's run
  without it).
- ``person/{who}/{keypoints,bones,capsules}``: ``who`` is ``perceived`` (what the safety layer
  holds) or ``true`` (the evaluator's recording as recorded).
- ``barriers/{run}/binding``: closest-point segments of the binding pairs (yellow);
  ``barriers/{run}/min_h/{self,human}``: min h per pair group (m); ``barriers/{run}/h/{pair}``:
  every monitored pair (evaluator).
- ``joints/{joint}/{q_nom,q_cbf,q,...}``: per imitation joint (rad).
- ``viewer/...``: the live viewer's own counters (messages per topic, dropped, services alive).
"""

from __future__ import annotations

from collections.abc import Sequence

#: The runs of a recording: with the CBF layer (the live robot) and without it.
RUNS = ("cbf", "nominal")
#: The people: the perceived one (the safety layer's input) and the true one (evaluator).
PEOPLE = ("perceived", "true")
TIMELINE = "time"
#: Closest-point segments of binding pairs (the paper's figures).
YELLOW = (255, 220, 0, 255)
ROBOT_COLORS = {"cbf": None, "nominal": (230, 110, 60, 110)}  # None: the MJCF's own colours
CAPSULE_COLORS = {"cbf": (60, 140, 255, 70), "nominal": (255, 120, 60, 50)}
PERSON_COLORS = {"perceived": (190, 90, 230, 90), "true": (40, 190, 90, 110)}
KEYPOINT_COLORS = {"perceived": (190, 90, 230, 255), "true": (40, 170, 80, 255)}
#: Pair groups of the min-h series.
GROUPS = ("self", "human")


def robot(run: str, *parts: str) -> str:
    return "/".join(("robot", run, *parts))


def person(who: str, *parts: str) -> str:
    return "/".join(("person", who, *parts))


def barriers(run: str, *parts: str) -> str:
    return "/".join(("barriers", run, *parts))


def joint(name: str, series: str) -> str:
    return f"joints/{name}/{series}"


def safe_part(name: str) -> str:
    """A pair or joint name as one entity path part (``|`` and ``.`` kept readable, ``/`` not allowed)."""
    return name.replace("/", "_").replace("|", "--").replace(" ", "_")


def blueprint(joint_names: Sequence[str]):  # -> rerun.blueprint.Blueprint
    """The layout: the 3D scene left; min h, mode/QP time and one tab per joint right."""
    import rerun.blueprint as rrb

    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial3DView(name="robot, person, barriers", origin="/",
                              contents=["+ robot/**", "+ person/**", "+ barriers/**"]),
            rrb.Vertical(
                rrb.TimeSeriesView(name="min h per pair group (m)", origin="/", contents=["+ barriers/*/min_h/**"]),
                rrb.TimeSeriesView(name="mode, QP time (ms), contacts", origin="/", contents=["+ robot/*/status/**"]),
                rrb.Tabs(*[rrb.TimeSeriesView(name=name, origin=f"joints/{name}") for name in joint_names]),
            ),
            column_shares=[3, 2],
        ),
        collapse_panels=True,
    )
