"""``wamplan wam ...``: serve a trained WAM over the Cosmos Policy /act protocol."""

from __future__ import annotations

import argparse

from wamplan.errors import UserError


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("wam", help="world action models: serve one over the /act protocol")
    sub = parser.add_subparsers(dest="wam_command", metavar="WAM_COMMAND")
    parser.set_defaults(func=lambda args: (parser.print_help(), 2)[1])

    serve = sub.add_parser("serve", help="serve a WAM checkpoint at http://HOST:PORT/act (Cosmos Policy protocol)")
    serve.add_argument("--ckpt", required=True, help="WAM checkpoint directory (model.safetensors + config.json)")
    serve.add_argument("--host", default="127.0.0.1", help="address to listen on (default: 127.0.0.1)")
    serve.add_argument("--port", type=int, default=8777, help="port to listen on (default: 8777)")
    serve.add_argument("--instruction", default=None,
                       help="instruction used when a request's task_description is empty "
                            "(default: the WAM's own default instruction)")
    serve.add_argument("--log-level", default="info", choices=["critical", "error", "warning", "info", "debug"],
                       help="uvicorn log level (default: info)")
    serve.set_defaults(func=_serve)


def _serve(args: argparse.Namespace) -> int:
    if not 0 < args.port < 65536:
        raise UserError(f"--port must be in 1..65535, got {args.port}")
    from wamplan.wam.base import load_wam

    wam = load_wam(args.ckpt)
    from wamplan.wam.server import serve

    print(f"serving WAM '{wam.name}' from {args.ckpt} at http://{args.host}:{args.port}/act", flush=True)
    try:
        serve(wam, host=args.host, port=args.port, instruction_default=args.instruction, log_level=args.log_level)
    finally:
        wam.close()
    return 0
