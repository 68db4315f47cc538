"""Typed errors of the G1 backend: :class:`G1StartError`, its refusal to start."""

from __future__ import annotations

from services.executor.errors import ExecutorStartError

__all__ = ["G1StartError"]


class G1StartError(ExecutorStartError, RuntimeError):
    """The G1 executor will not start (no robot state, unknown or unfit variant); the message says
    what to check or configure."""
