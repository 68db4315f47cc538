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
