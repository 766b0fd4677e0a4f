"""One module per ``ti-cmax`` subcommand: ``HELP``, ``add_arguments(parser)``, ``run(args) -> int``."""
