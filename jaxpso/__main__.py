"""`python -m jaxpso`: the `jaxpso` command (`jaxpso.cli`)."""

import sys

from jaxpso import cli

if __name__ == "__main__":
  sys.exit(cli.main())
