"""`python -m dlocli`: the `dlo` command."""

from dlocli.cli import main

main()
