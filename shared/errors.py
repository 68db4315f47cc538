"""The root of safemimic's own errors: ``except SafemimicError`` catches every refusal the code
raises on purpose (bad input, a model that does not fit, a source that cannot open, ...).

Each package has its own base under it (:class:`shared.codec.CodecError`,
:class:`services.safety.errors.SafetyError`, :class:`services.executor.errors.ExecutorError`,
:class:`services.perception.errors.PerceptionError`,
:class:`services.config_api.errors.ConfigApiError`, :class:`services.viewer.errors.ViewerError`,
:class:`safemimic.certs.CertError`); an error that is also a plain ``ValueError`` or
``RuntimeError`` in Python's sense keeps that class as a second base, so callers that catch the
built-in type still do.
"""

from __future__ import annotations

__all__ = ["SafemimicError"]


class SafemimicError(Exception):
    """Base class of every error safemimic raises on purpose."""
