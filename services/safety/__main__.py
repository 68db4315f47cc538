"""``python -m services.safety``: the safety service (same as ``safemimic safety``)."""
import sys

from services.safety.service import build_parser, run
from shared.entrypoint import run_command

sys.exit(run_command("safety", build_parser, run, sys.argv[1:]))
