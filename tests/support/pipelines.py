"""Safety pipelines for the filter's tests: the default configuration with a few safety fields
changed, and the robot alone (no person) at rest."""

from __future__ import annotations

import numpy as np

from services.safety.assembly import SafetyPipeline, build_pipeline
from shared.config import load_config

#: The control period of the filter tests (s): the default 500 Hz.
DT = 0.002


def pipeline_for(backend: str = "daqp", **safety) -> SafetyPipeline:
    """The default pipeline with ``safety.backend`` and any other ``safety`` fields overridden."""
    return build_pipeline(load_config(environ={}, overrides={"safety": {"backend": backend, **safety}}))


def alone_at(p: SafetyPipeline, q: np.ndarray) -> None:
    """No person in the scene; the filter restarts at ``q`` (no previous command: no acceleration bound)."""
    p.barrier.set_external(None)
    p.filter.reset(q)


def random_safe_state(p: SafetyPipeline, rng: np.random.Generator) -> np.ndarray:
    """A random joint state whose self rows and joint barriers hold (no person in the scene)."""
    kin = p.kinematics
    while True:
        q = rng.uniform(kin.q_min, kin.q_max)
        p.barrier.set_external(None)
        blocks = p.filter.blocks_at(q)
        if all((block.b[~block.soft] <= 0.0).all() for block in blocks):
            return q
