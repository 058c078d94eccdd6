"""The one command-line entry point, ``wamplan``.

Each command family registers its sub-commands from its module in ``wamplan/cli/`` (``env``, ``data``, ``wm``,
``wam``, ``eval``, ``plot``): a function ``register(subparsers)`` decorated with
``@register_command(name)`` (the ``COMMANDS`` registry below, which lists those modules);
a handler is a function ``(args) -> int``. Imports are lazy so that ``wamplan --help`` stays fast.
"""

from __future__ import annotations

import argparse
import sys

from wamplan.registry import Registry

COMMANDS = Registry("command", modules=(
    "wamplan.cli.env",
    "wamplan.cli.data",
    "wamplan.cli.wm",
    "wamplan.cli.wam",
    "wamplan.cli.eval",
    "wamplan.cli.plot",
))
register_command = COMMANDS.register  # decorator on a command module's ``register(subparsers)``


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="wamplan", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for register in COMMANDS.values():
        register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    from wamplan.errors import UserError

    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except UserError as e:
        print(f"wamplan: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("wamplan: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
