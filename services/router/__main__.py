from services.router.main import cli

cli()
