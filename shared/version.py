"""The installed distribution's version (``importlib.metadata``), for ``--version`` and the API."""

from __future__ import annotations

from importlib.metadata import PackageNotFoundError, version

try:
    VERSION = version("safemimic")
except PackageNotFoundError:  # running from a source tree that is not installed
    VERSION = "0.0.0+source"
