"""The listening options ``wam serve`` and ``serve`` share: address, port, shared secret, log level."""

from __future__ import annotations

import argparse
import os

LOG_LEVELS = ["critical", "error", "warning", "info", "debug"]


def add_listen_options(p: argparse.ArgumentParser, port: int, secret_help: str) -> None:
    """``--host``, ``--port`` (default ``port``), ``--secret`` (``secret_help``) and ``--log-level``."""
    p.add_argument("--host", default="127.0.0.1",
                   help="address to listen on (default: 127.0.0.1, this machine only; 0.0.0.0: every interface)")
    p.add_argument("--port", type=int, default=port, help=f"port to listen on (default: {port})")
    p.add_argument("--secret", default=None, help=secret_help)
    p.add_argument("--log-level", default="info", choices=LOG_LEVELS, help="uvicorn log level (default: info)")


def listen_secret(args: argparse.Namespace) -> str | None:
    """The shared secret after checking ``--port``: ``--secret``, else ``$WAMPLAN_ACT_SECRET``, else None."""
    from wamplan.errors import UserError
    from wamplan.serving import SECRET_ENV

    if not 0 < args.port < 65536:
        raise UserError(f"--port must be in 1..65535, got {args.port}")
    return args.secret if args.secret is not None else os.environ.get(SECRET_ENV) or None
