"""The ``gpmpc`` command line: the parser, the entry point, one module per command."""

from torch_gpmpc.cli.entry import main

__all__ = ["main"]
