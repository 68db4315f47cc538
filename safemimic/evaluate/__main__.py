"""``python -m safemimic.evaluate``: the offline evaluator (same as ``safemimic evaluate``)."""
import sys

from safemimic.cli import main

sys.exit(main(["evaluate", *sys.argv[1:]]))
