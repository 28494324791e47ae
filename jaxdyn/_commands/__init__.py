"""Subcommands of `jaxdyn`: one module each, with `HELP`, `add_arguments(parser)`, `run(args)`."""
