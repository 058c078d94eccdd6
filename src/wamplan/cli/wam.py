"""``wamplan wam ...``: train TinyWAM on episode stores; serve a trained WAM over the Cosmos Policy /act protocol."""

from __future__ import annotations

import argparse
from pathlib import Path

from wamplan.errors import UserError
from wamplan.cli.main import add_command, add_group, first_screen, register_command
from wamplan.cli.server_options import add_listen_options, listen_secret


@register_command("wam")
def register(subparsers: argparse._SubParsersAction) -> None:
    add_group(subparsers, "wam", _wam_commands,
              help="world action models: train TinyWAM, serve one over the /act protocol")


def _wam_commands(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="wam_command", metavar="WAM_COMMAND")
    add_command(sub, "serve", _serve_options,
                help="serve a WAM checkpoint at http://HOST:PORT/act (Cosmos Policy protocol)")
    add_command(sub, "viz", _viz_options, help="a WAM's predicted t+H views beside the real ones, on a stored episode")
    add_command(sub, "train", _train_options,
                help="train TinyWAM on episode stores (re-run the same command to resume)",
                description="Train TinyWAM (actions + t+H images) into the run directory --out. If --out holds an "
                            "unfinished run, it is resumed; options left out keep the saved values.")


def _serve_options(serve: argparse.ArgumentParser) -> None:
    serve.add_argument("--ckpt", required=True, help="WAM checkpoint directory (model.safetensors + config.json)")
    add_listen_options(serve, 8777, "shared secret every /act request must carry in the X-WAMplan-Secret header, as "
                                    "Authorization: Bearer (or Api-Key), or as ?token=SECRET in the URL (for clients that cannot "
                                    "send headers); default: $WAMPLAN_ACT_SECRET, none if unset. Prefer the "
                                    "variable: a command line is visible to other users of the machine")
    serve.add_argument("--max-request-mb", type=float, default=16.0,
                       help="refuse /act bodies larger than this with HTTP 413 (default: 16 MiB)")
    serve.add_argument("--instruction", default=None,
                       help="instruction used when a request's task_description is empty "
                            "(default: the WAM's own default instruction)")
    serve.add_argument("--errors", choices=["http", "upstream"], default=None,
                       help="how a failed /act request is answered: http (default, for wamplan's client) a 4xx/5xx "
                            "status and a JSON body saying what is wrong; upstream (use it with Cosmos Policy's own "
                            "clients) HTTP 200 and the JSON string \"error\", as its reference server answers, the "
                            "reason in this server's log")
    serve.add_argument("--bare-errors", action="store_true", help="the same as --errors upstream")
    serve.add_argument("--fit-proprio", action="store_true",
                       help="pad with zeros or truncate a proprio of another length than the WAM's (e.g. ALOHA's 14-D "
                            "qpos), said in each answer's wamplan field; default: refuse it (HTTP 400)")
    serve.add_argument("--device", default="auto", help="torch device for the WAM: auto, cpu, cuda, cuda:1, ... "
                                                        "(default: auto)")
    serve.set_defaults(func=_serve)


def _viz_options(viz: argparse.ArgumentParser) -> None:
    viz.add_argument("--ckpt", required=True, help="WAM checkpoint directory")
    viz.add_argument("--data", required=True, help="episode store")
    viz.add_argument("--episode", type=int, default=0, help="index in the store's sorted episode list")
    viz.add_argument("--starts", type=int, nargs="+", default=[16, 48, 80], help="chunk start steps (rows)")
    viz.add_argument("--out", type=Path, default=Path("wam_pred.png"), help="PNG to write (default: wam_pred.png)")
    viz.set_defaults(func=_viz)


def _train_options(train: argparse.ArgumentParser) -> None:
    from wamplan.config import add_arguments
    from wamplan.wam.tinywam_config import TinyWAMConfig
    from wamplan.wam.train_config import WAMTrainConfig

    train.add_argument("--data", required=True, help="episode store directory, or several separated by commas")
    train.add_argument("--out", type=Path, required=True,
                       help="run directory: checkpoint/ + metrics.jsonl (created, or resumed)")
    train.add_argument("--sources", default=None, help="train only on these sources, comma separated "
                                                       "(e.g. expert); default: every episode in the stores")
    train.add_argument("--max-steps", type=int, default=None,
                       help="stop after this many optimisation steps in all (checkpointed; re-run to continue)")
    train.add_argument("--no-progress", action="store_true", help="no progress bar (logs only)")
    add_arguments(train.add_argument_group("training", "the optimisation, loss and augmentation"), WAMTrainConfig)
    add_arguments(train.add_argument_group("model", "TinyWAM's architecture (a resumed run keeps its own)"),
                  TinyWAMConfig)
    first_screen(train, "--sources", "--max-steps", "--epochs", "--batch-size", "--lr", "--device")
    train.set_defaults(func=_train)


def _serve(args: argparse.Namespace) -> int:
    secret = listen_secret(args)
    if not args.max_request_mb > 0:
        raise UserError(f"--max-request-mb must be > 0, got {args.max_request_mb}")
    if args.bare_errors and args.errors == "http":
        raise UserError("--bare-errors is --errors upstream, which --errors http contradicts; give one of them")
    from wamplan.device import resolve_device
    from wamplan.wam.base import load_wam
    from wamplan.serving.runner import bind_socket
    from wamplan.wam.protocol import field_map, proprio_rule, resolve_maps
    from wamplan.wam.server import serve

    resolve_device(args.device)  # before loading anything

    sock = bind_socket(args.host, args.port)  # a busy port fails here, before loading or announcing anything
    try:
        wam = load_wam(args.ckpt, device=args.device)
    except BaseException:
        sock.close()
        raise
    errors = "upstream" if args.bare_errors else args.errors or "http"
    failures = 'failures answered HTTP 200 "error" (upstream error mode)' if errors == "upstream" else \
        "failures answered 4xx/5xx with a reason"
    print(f"serving WAM '{wam.name}' from {args.ckpt} at http://{args.host}:{args.port}/act "
          f"({'shared secret required' if secret else 'no shared secret'}; {failures}; health: /health)", flush=True)
    print(f"{field_map(*resolve_maps(tuple(wam.cameras)))}; {proprio_rule(wam.task.proprio_dim, args.fit_proprio)}; "
          f"{wam.chunk_length} x {wam.action_dim} actions", flush=True)
    try:
        serve(wam, host=args.host, port=args.port, instruction_default=args.instruction, log_level=args.log_level,
              secret=secret, max_request_bytes=int(args.max_request_mb * 2**20), errors=errors, sock=sock,
              fit_proprio=args.fit_proprio)
    finally:
        wam.close()
    return 0


def _train(args: argparse.Namespace) -> int:
    from wamplan.config import from_args
    from wamplan.data.store import MANIFEST
    from wamplan.wam.tinywam import TinyWAMConfig
    from wamplan.wam.train import WAMTrainConfig, saved_configs, train_tinywam

    from wamplan.errors import require_dir, require_distinct

    require_dir(args.out)
    stores = [s.strip() for s in args.data.split(",") if s.strip()]
    if not stores:
        raise UserError("--data is empty; pass an episode store directory (several: DIR1,DIR2)")
    require_distinct(stores, "--data", "store")  # read twice, its episodes would weigh double
    for s in stores:
        if not (Path(s) / MANIFEST).is_file():
            raise UserError(f"--data {s} is not an episode store (no {MANIFEST}); collect one with "
                            f"`wamplan collect --source expert --episodes N --out {s}`")
    if args.max_steps is not None and args.max_steps <= 0:
        raise UserError(f"--max-steps must be > 0, got {args.max_steps}")
    sources = [s.strip() for s in args.sources.split(",") if s.strip()] if args.sources else None
    saved = saved_configs(args.out) if args.out.is_dir() else None
    model_cfg = from_args(TinyWAMConfig, args, base=saved[0] if saved else None)
    train_cfg = from_args(WAMTrainConfig, args, base=saved[1] if saved else None)
    from wamplan.device import resolve_device
    from wamplan.train_log import require_backends

    require_backends(train_cfg.log)  # before reading any data

    resolve_device(train_cfg.device)  # before reading any data
    result = train_tinywam(stores, args.out, model_cfg, train_cfg, sources=sources, max_steps=args.max_steps,
                           progress=not args.no_progress)
    if not result.finished_before:
        print(f"checkpoint: {args.out} (epoch {result.state['epoch']}, step {result.state['global_step']}); "
              f"load it with wamplan.wam.load_wam or `wamplan env rollout --policy {args.out}`")
    return 0


def _viz(args: argparse.Namespace) -> int:
    import json

    from wamplan.errors import require_file
    from wamplan.wam import load_wam
    from wamplan.wam.viz import prediction_figure

    require_file(args.out, "--out")
    errs = prediction_figure(load_wam(args.ckpt), args.data, args.episode, tuple(args.starts), args.out)
    print(json.dumps(errs))
    print(f"wrote {args.out}")
    return 0
