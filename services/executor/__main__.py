from services.executor.service import cli

cli()
