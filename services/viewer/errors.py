"""Typed errors of the viewer service."""

from __future__ import annotations

from shared.errors import SafemimicError

__all__ = ["ViewerError"]


class ViewerError(SafemimicError):
    """Base class of the viewer's own errors (a robot model it cannot draw)."""
