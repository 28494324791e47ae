"""Subcommands of `jaxdyn`: one module each, with `HELP`, `add_arguments(parser)`, `run(args)`
and, where its programs call LAPACK, `LAPACK = True` (see `jaxdyn._cli`)."""
