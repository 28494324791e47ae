"""`python -m jaxdyn`: the same as the `jaxdyn` command."""

import sys

from ._cli import main

sys.exit(main())
