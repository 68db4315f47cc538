"""``python -m services.config_api``: the config API (same as ``safemimic config-api``)."""
import sys

from safemimic.cli import main

sys.exit(main(["config-api", *sys.argv[1:]]))
