"""Typed errors of the config API."""

from __future__ import annotations

from shared.errors import SafemimicError

__all__ = ["ConfigApiError"]


class ConfigApiError(SafemimicError):
    """Base class of the config API's own errors (an unusable store or token)."""
