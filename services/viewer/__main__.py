"""``python -m services.viewer``: the viewer service (same as ``safemimic viewer``)."""
import sys

from services.viewer.service import build_parser, run
from shared.entrypoint import run_command

sys.exit(run_command("viewer", build_parser, run, sys.argv[1:]))
