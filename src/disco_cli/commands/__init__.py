"""One module per `disco` subcommand; see disco_cli.cli for the registration."""
