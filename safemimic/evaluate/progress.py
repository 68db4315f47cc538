"""A dependency-free progress bar on stderr for long evaluation runs."""

from __future__ import annotations

import sys
from typing import TextIO

#: Characters of the bar itself.
_WIDTH = 30


class ProgressBar:
    """``label [#####.....]  42 %`` redrawn in place on a terminal; on a pipe or file (CI logs)
    one line per quarter, so logs stay short. ``update(done)`` with 0 ≤ done ≤ total."""

    def __init__(self, total: int, label: str, stream: TextIO | None = None) -> None:
        self.total = max(1, total)
        self.label = label
        self.stream = stream if stream is not None else sys.stderr
        self._interactive = self.stream.isatty()
        self._shown = -1  # last percentage (terminal) or quarter (log) written

    def update(self, done: int) -> None:
        percent = min(100, 100 * done // self.total)
        if self._interactive:
            if percent != self._shown:
                filled = _WIDTH * percent // 100
                self.stream.write(f"\r{self.label} [{'#' * filled}{'.' * (_WIDTH - filled)}] {percent:3d} %")
                self.stream.flush()
                self._shown = percent
        elif percent // 25 != self._shown:
            self._shown = percent // 25
            self.stream.write(f"{self.label}: {percent} %\n")
            self.stream.flush()

    def update_of(self, done: int, total: int) -> None:
        """``update(done)`` with the total (re)stated: a caller that learns it as it goes."""
        self.total = max(1, total)
        self.update(done)

    def close(self) -> None:
        """Finish the line (the bar at 100 %)."""
        self.update(self.total)
        if self._interactive:
            self.stream.write("\n")
            self.stream.flush()
