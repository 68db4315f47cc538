"""``python -m services.perception``: the perception service (same as ``safemimic perception``)."""
import sys

from services.perception.service import build_parser, run
from shared.entrypoint import run_command

sys.exit(run_command("perception", build_parser, run, sys.argv[1:]))
