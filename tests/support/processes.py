"""Real child processes for tests: a process whose output is collected, and a free loopback port
(:func:`safemimic.launch.free_port`, the launcher's own)."""

from __future__ import annotations

import json
import os
import queue
import subprocess
import threading
import time

from safemimic.launch import free_port
from tests.support.team import REPO

__all__ = ["Proc", "free_port"]


class Proc:
    """A child process whose stdout lines are collected by a reader thread."""

    def __init__(self, args: list[str], env: dict[str, str] | None = None) -> None:
        self.args = args
        self.popen = subprocess.Popen(
            args,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            cwd=REPO,
            env={**os.environ, "PYTHONUNBUFFERED": "1", **(env or {})},
        )
        self.lines: queue.Queue[str] = queue.Queue()
        self.output: list[str] = []
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        assert self.popen.stdout is not None
        for line in self.popen.stdout:
            self.output.append(line)
            self.lines.put(line)

    def wait_for(self, predicate, timeout: float = 15.0) -> str:
        """The first new stdout line satisfying ``predicate``; fails with the output so far."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            try:
                line = self.lines.get(timeout=max(0.01, deadline - time.monotonic()))
            except queue.Empty:
                break
            if predicate(line):
                return line
        raise AssertionError(f"timed out waiting on {self.args}; output:\n{''.join(self.output)[-3000:]}")

    def wait_json(self, event: str, timeout: float = 15.0) -> dict:
        def is_event(line: str) -> bool:
            return line.startswith("{") and json.loads(line).get("event") == event

        return json.loads(self.wait_for(is_event, timeout))

    def stop(self) -> None:
        if self.popen.poll() is None:
            self.popen.terminate()
            try:
                self.popen.wait(5)
            except subprocess.TimeoutExpired:
                self.popen.kill()
                self.popen.wait(5)
