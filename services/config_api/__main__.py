"""``python -m services.config_api``: the config API (same as ``safemimic config-api``)."""
import sys

from services.config_api.main import build_parser, run
from shared.entrypoint import run_command

sys.exit(run_command("config-api", build_parser, run, sys.argv[1:]))
