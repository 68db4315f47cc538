"""``python -m services.safety``: the safety service (same as ``safemimic safety``)."""
import sys

from safemimic.cli import main

sys.exit(main(["safety", *sys.argv[1:]]))
