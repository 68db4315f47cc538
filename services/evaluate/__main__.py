from services.evaluate.main import cli

cli()
