"""``python -m services.executor``: the executor service (same as ``safemimic executor``)."""
import sys

from safemimic.cli import main

sys.exit(main(["executor", *sys.argv[1:]]))
