from services.config_api.main import cli

cli()
