"""safemimic: safe human-to-humanoid motion imitation (the ``safemimic`` command)."""

from shared.version import VERSION as __version__

__all__ = ["__version__"]
