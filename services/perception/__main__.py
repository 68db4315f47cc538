"""``python -m services.perception``: the perception service (same as ``safemimic perception``)."""
from services.perception.service import cli

cli()
