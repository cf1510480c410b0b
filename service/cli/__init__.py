"""The `symgs` command line: ``main`` parses the arguments; each command group lives in a module of its own."""

from .parser import CliError, main

__all__ = ["CliError", "main"]
