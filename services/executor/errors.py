"""Typed errors of the executor service."""

from __future__ import annotations

from shared.errors import SafemimicError

__all__ = ["ExecutorError", "ExecutorStartError"]


class ExecutorError(SafemimicError):
    """Base class of the executor's own errors."""


class ExecutorStartError(ExecutorError):
    """A backend refuses to start (a model that does not load or fit, no robot state, an unfit
    variant): the service reports it in one line and exits with code 2."""
