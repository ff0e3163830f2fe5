"""`python -m liedfl_cli <command> ...`: the same as the `liedfl` command."""

from .cli import main

main()
