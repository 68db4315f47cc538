"""Typed errors of the perception service."""

from __future__ import annotations

from shared.errors import SafemimicError

__all__ = ["PerceptionError"]


class PerceptionError(SafemimicError):
    """Base class of the perception service's own errors (a source that cannot open, pose weights
    that are missing or corrupt)."""
