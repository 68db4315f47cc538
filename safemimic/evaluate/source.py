"""The evaluator's input: the configured skeleton source's frames, read once.

:func:`open_input` reads ``conf.perception``'s source exactly as the perception service does
(``open_source``: a architecture §6 recording, normalised and placed, or a scripted scenario), without
pacing. Frames are in the robot frame, times from the source (s).
"""

from __future__ import annotations

import itertools
import threading
from dataclasses import dataclass

from services.perception.sources import open_source
from services.perception.base import SkeletonFrame
from shared.config import StackConfig


@dataclass(frozen=True)
class EvaluationInput:
    """The skeleton frames to evaluate (robot frame, times from the source) and where they came from."""

    name: str
    frames: tuple[SkeletonFrame, ...]
    fps: float

    @property
    def seconds(self) -> float:
        """Evaluated duration (s): first frame to one frame period after the last."""
        return self.frames[-1].t - self.frames[0].t + 1.0 / self.fps


def open_input(conf: StackConfig, seconds: float | None = None) -> EvaluationInput:
    """The frames of ``conf.perception``'s source (one pass; with ``seconds``, looped or cut to it).

    Raises :class:`~services.perception.sources.SourceUnavailable` (bad file, unknown scenario)
    and ValueError for a non-positive ``seconds``.
    """
    if seconds is not None and not seconds > 0:
        raise ValueError(f"seconds must be > 0, got {seconds}")
    perception = conf.perception.model_copy(update={"realtime": False, "loop": seconds is not None})
    source = open_source(perception)
    frames = source.frames(threading.Event())
    if seconds is not None:
        first = next(frames)
        frames = itertools.chain([first], itertools.takewhile(lambda f: f.t - first.t < seconds - 1e-9, frames))
    return EvaluationInput(name=source.name, frames=tuple(frames), fps=float(source.fps))
