"""`python -m jaxdyn`: the same as the `jaxdyn` command."""

from ._cli import console

console()
