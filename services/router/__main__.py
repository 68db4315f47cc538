"""``python -m services.router``: the Zenoh router (same as ``safemimic router``)."""
import sys

from safemimic.cli import main

sys.exit(main(["router", *sys.argv[1:]]))
