"""Child processes of a launcher (``safemimic demo``, the latency benchmark) that never outlive it.

Each child runs in its own session (so its process group holds it and anything it starts), writes
stdout and stderr to a log file (a pipe nobody reads would fill and block it), and on Linux gets
SIGTERM from the kernel if the launcher dies without cleaning up (``PR_SET_PDEATHSIG``).
:func:`stop_all` ends the groups: SIGTERM, a grace period, then SIGKILL.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

_PR_SET_PDEATHSIG = 1


def _die_with_parent() -> None:
    """In the child before exec: ask the kernel for SIGTERM when the launcher dies (Linux)."""
    if sys.platform.startswith("linux"):
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
        libc.prctl(_PR_SET_PDEATHSIG, signal.SIGTERM)


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port free on ``host`` right now (for a child to listen on)."""
    with socket.socket() as sock:
        sock.bind((host, 0))
        return sock.getsockname()[1]


def python_argv(argv: Sequence[str]) -> list[str]:
    """A ``safemimic ...`` command line run by this interpreter (no PATH lookup, same venv)."""
    if argv and argv[0] == "safemimic":
        return [sys.executable, "-m", "safemimic.cli", *argv[1:]]
    return list(argv)


@dataclass
class Child:
    """A launched process: its name, the Popen and its log file."""

    name: str
    popen: subprocess.Popen
    log_path: Path

    @property
    def pid(self) -> int:
        return self.popen.pid

    def running(self) -> bool:
        return self.popen.poll() is None

    def log_tail(self, max_chars: int = 2000) -> str:
        """The end of the child's output."""
        try:
            return self.log_path.read_text(errors="replace")[-max_chars:]
        except OSError:
            return ""


def launch(name: str, argv: Sequence[str], log_dir: Path, env: Mapping[str, str] | None = None) -> Child:
    """Start ``argv`` (``safemimic ...`` runs with this interpreter) in a new session, output to ``log_dir/name.log``."""
    log_path = log_dir / f"{name}.log"
    with open(log_path, "ab") as log:
        popen = subprocess.Popen(
            python_argv(argv), stdin=subprocess.DEVNULL, stdout=log, stderr=subprocess.STDOUT,
            env={**os.environ, "PYTHONUNBUFFERED": "1", **(env or {})},
            start_new_session=True, preexec_fn=_die_with_parent,
        )
    return Child(name, popen, log_path)


def _signal_group(child: Child, sig: signal.Signals) -> None:
    try:
        os.killpg(child.pid, sig)  # the child leads its own session: pgid == pid
    except (ProcessLookupError, PermissionError):
        pass


def stop_all(children: Sequence[Child], grace_s: float = 5.0) -> dict[str, int]:
    """SIGTERM every child's process group, wait up to ``grace_s``, SIGKILL what is left; exit codes."""
    for child in children:
        _signal_group(child, signal.SIGTERM)
    deadline = time.monotonic() + grace_s
    for child in children:
        try:
            child.popen.wait(max(0.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            pass
    for child in children:
        _signal_group(child, signal.SIGKILL)  # stragglers, and anything the child left in its group
        child.popen.wait()
    return {child.name: child.popen.returncode for child in children}


def kill(child: Child) -> None:
    """SIGKILL ``child``'s process group at once, no grace period, and reap it (``kill -9``: fault injection)."""
    _signal_group(child, signal.SIGKILL)
    child.popen.wait()
