"""``wamplan serve``: the planning proxy between a robot and a WAM server (``wamplan.proxy``)."""

from __future__ import annotations

import argparse
import sys

from wamplan.cli.main import add_command, first_screen, register_command
from wamplan.cli.server_options import add_listen_options, listen_secret


@register_command("serve")
def register(sub: argparse._SubParsersAction) -> None:
    add_command(sub, "serve", _options,
                help="a planning proxy: an /act endpoint that plans each chunk of an upstream WAM in a world model",
                description="Serve /act (and /s/ROBOT/act per robot), and openpi's WebSocket protocol on / (and "
                            "/s/ROBOT): each request goes to --upstream, its chunk is planned in --world-model toward "
                            "the upstream's predicted views, and the answer keeps the upstream's format "
                            "(docs/deploy.md).")


def _options(p: argparse.ArgumentParser) -> None:
    from wamplan.config import add_arguments
    from wamplan.proxy.config import ProxyConfig, ProxyPolicyConfig

    from wamplan.cli.eval_options import add_planning_arguments

    add_arguments(p, ProxyConfig)
    add_planning_arguments(p, ProxyPolicyConfig)  # the planner, cost and chunk rules, as `wamplan eval` takes them
    add_listen_options(p, 8778, "shared secret every request must carry (X-WAMplan-Secret header, Authorization: "
                                "Bearer or Api-Key, or ?token=SECRET in the URL); default: $WAMPLAN_ACT_SECRET, none if unset. "
                                "The upstream's own secret, if any, is read from $WAMPLAN_UPSTREAM_SECRET")
    first_screen(p, "--upstream", "--world-model", "--profile", "--errors", "--budget-ms", "--device", "--record",
                 "--planner", "--host", "--port", "--secret")
    p.set_defaults(func=_serve)


def _serve(args: argparse.Namespace) -> int:
    import dataclasses

    from wamplan.proxy.config import ProxyConfig, ProxyPolicyConfig

    secret = listen_secret(args)
    # the options given, onto the defaults; not from_args: ProxyConfig() alone is refused (no upstream)
    cfg = ProxyConfig(**{f.name: getattr(args, f.name) for f in dataclasses.fields(ProxyConfig)
                         if getattr(args, f.name) is not None})
    from wamplan.cli.eval_options import planning_from_args
    from wamplan.device import resolve_device
    from wamplan.proxy.app import create_proxy_app
    from wamplan.proxy.build import build_proxy, unchecked
    from wamplan.proxy.openpi import ws_fields_warning
    from wamplan.serving.runner import bind_socket, run_app

    resolve_device(cfg.device)
    planning = planning_from_args(args, ProxyPolicyConfig)
    if cfg.record:  # an unwritable record directory is refused before anything loads
        from wamplan.proxy.record import check_record_dir

        check_record_dir(cfg.record)
    sock = bind_socket(args.host, args.port)  # a busy port fails here, before loading or announcing anything
    try:
        proxy = build_proxy(cfg, planning=planning)
    except BaseException:
        sock.close()
        raise
    errors = 'HTTP 200 "error" (upstream error mode)' if cfg.errors == "upstream" else "4xx/5xx with a reason"
    budget = f"{cfg.budget_ms:g} ms planning budget" if cfg.budget_ms else "no planning budget"
    print(f"planning proxy for {proxy.upstream.where} with world model {cfg.world_model} at "
          f"http://{args.host}:{args.port}/act and /s/ROBOT/act, openpi clients at ws://{args.host}:{args.port} "
          f"({'shared secret required' if secret else 'no shared secret'}; "
          f"failures answered {errors}; {budget})", flush=True)
    print(proxy.describe(), flush=True)
    if proxy.recorder is not None:
        rec = proxy.recorder
        for line in rec.recovered:
            print(f"--record: {line}", flush=True)
        print(f"recording every session into {cfg.record} (episodes of task {rec.task.name}, a frame every "
              f"{rec.every} steps; `wamplan wm train --data {cfg.record}` trains on them)", flush=True)
    odd = ws_fields_warning(cfg.ws_fields, tuple(proxy.request_map))
    if odd:
        print(odd, file=sys.stderr, flush=True)
    waiting = unchecked(proxy)  # the fit checks the start-up probe could not run, and why
    if waiting:
        print(waiting, file=sys.stderr, flush=True)
    try:
        run_app(create_proxy_app(proxy, secret), args.host, args.port, secret, args.log_level, sock=sock,
                ws_max_bytes=cfg.max_request_bytes)
    finally:
        proxy.close()
    return 0
