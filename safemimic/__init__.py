"""safemimic: safe human-to-humanoid motion imitation (the ``safemimic`` command)."""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("safemimic")
except PackageNotFoundError:  # running from a source tree that is not installed
    __version__ = "0.0.0+source"
