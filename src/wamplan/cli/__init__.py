"""The command line, ``wamplan``: one module per command family, registered lazily (see :mod:`wamplan.cli.main`)."""

from wamplan.cli.main import build_parser, main

__all__ = ["build_parser", "main"]
