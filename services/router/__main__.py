"""``python -m services.router``: the Zenoh router (same as ``safemimic router``)."""
import sys

from services.router.main import build_parser, run
from shared.entrypoint import run_command

sys.exit(run_command("router", build_parser, run, sys.argv[1:]))
