"""The ``gpmpc`` command line: argument parsing and one module per command."""

from torch_gpmpc.cli.parser import main

__all__ = ["main"]
