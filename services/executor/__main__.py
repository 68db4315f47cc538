"""``python -m services.executor``: the executor service (same as ``safemimic executor``)."""
import sys

from services.executor.service import build_parser, run
from shared.entrypoint import run_command

sys.exit(run_command("executor", build_parser, run, sys.argv[1:]))
