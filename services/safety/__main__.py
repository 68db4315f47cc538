from services.safety.service import cli

cli()
