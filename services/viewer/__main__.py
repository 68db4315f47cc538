"""``python -m services.viewer``: the viewer service (same as ``safemimic viewer``)."""
import sys

from safemimic.cli import main

sys.exit(main(["viewer", *sys.argv[1:]]))
