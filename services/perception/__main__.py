"""``python -m services.perception``: the perception service (same as ``safemimic perception``)."""
import sys

from safemimic.cli import main

sys.exit(main(["perception", *sys.argv[1:]]))
