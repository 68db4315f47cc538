"""``safemimic evaluate``: the offline evaluator (architecture §7; paper §IV-A, Figs. 2–3).

One process runs the services' own code in lockstep, without Zenoh: the perception pipeline
(filter → angles → capsules) on every skeleton frame, the safety pipeline (retarget → CBF-QP) at
its control rate with the newest human state held in between, and the MuJoCo executor following
q_cbf. Each input is run twice — with the CBF layer and without it (the same integrator with no
CBF rows, u* = clip(u_ref)) — and the difference is what the safety layer does.

Modules: :mod:`~safemimic.evaluate.episode` (the input and the lockstep loop),
:mod:`~safemimic.evaluate.metrics` (``metrics.json``), :mod:`~safemimic.evaluate.figures` (joint
trajectories, barrier values), :mod:`~safemimic.evaluate.snapshot` (MuJoCo offscreen picture of
the worst moment), :mod:`~safemimic.evaluate.main` (the command).
"""

from __future__ import annotations

import os
import sys

# Offscreen rendering (snapshot.png) without a display: MuJoCo picks its OpenGL backend when it is
# first imported, so choose EGL (software rendering works, architecture §10) before any submodule
# imports it. An explicit MUJOCO_GL wins.
if sys.platform.startswith("linux") and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
    os.environ.setdefault("MUJOCO_GL", "egl")
