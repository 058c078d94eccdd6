"""``wamplan wm foreground``: fit a foreground readout on a world model's encoder (the object-centric cost's
weights, ``eval --cost-foreground DIR``)."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from wamplan.errors import UserError, checkpoint_kind, require_dir, require_own_dir, require_paths, require_seeds


def foreground_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--wm", required=True, help="the world model whose encoder the readout reads (its task's cameras)")
    p.add_argument("--out", required=True, help="the readout's checkpoint directory (new or empty)")
    p.add_argument("--policy", default="noisy-expert",
                   help="who drives the episodes: a registered policy or a WAM checkpoint (default: %(default)s)")
    p.add_argument("--episodes", type=int, default=16, help="episodes (the last fifth held out; default: %(default)s)")
    p.add_argument("--seed-start", type=int, default=3000, help="first seed (default: %(default)s)")
    p.add_argument("--every", type=int, default=4, help="keep every N-th step's pictures (default: %(default)s)")
    p.add_argument("--camera-size", type=int, default=224, help="rendered side in px (default: %(default)s)")
    p.add_argument("--steps", type=int, default=2000, help="optimisation steps (default: %(default)s)")
    p.add_argument("--device", default="auto", help="torch device of the encoder (auto, cpu, cuda, ...; default: "
                                                    "%(default)s); the readout itself fits on the CPU")
    p.set_defaults(func=cmd_foreground)


def cmd_foreground(args: argparse.Namespace) -> int:
    from wamplan.data.foreground import collect_foreground
    from wamplan.encoders.foreground import draw_foreground, fit_foreground, format_report, save_foreground
    from wamplan.envs.config import EnvConfig
    from wamplan.envs.core import TaskEnv
    from wamplan.evaluation.build import load_policy
    from wamplan.worldmodel.train import load_world_model

    require_paths([args.wm], "--wm", "pass a world-model checkpoint directory")
    if args.episodes < 2:
        raise UserError(f"--episodes {args.episodes}: a readout needs at least 2 episodes (the last fifth held out)")
    for name in ("every", "steps"):
        if getattr(args, name) < 1:
            raise UserError(f"--{name} must be >= 1, got {getattr(args, name)}")
    require_seeds(args.seed_start, args.episodes)
    out = require_dir(args.out)
    require_own_dir(out, ("config.json",), "a foreground readout")
    kind = checkpoint_kind(out)
    if (out / "config.json").exists() and kind != "foreground":
        raise UserError(f"--out {out} holds a '{kind}' checkpoint, not a foreground readout; pass a new or empty "
                        f"directory")
    from wamplan.device import resolve_device

    device = resolve_device(args.device)  # a device this machine lacks: one line, before any work
    predictor, encoder = load_world_model(args.wm, device=device)
    task, grid = predictor.task, math.isqrt(encoder.num_patches)
    if args.camera_size % grid:
        raise UserError(f"--camera-size {args.camera_size} does not split into the encoder's {grid} x {grid} "
                        f"patches; pass a multiple of {grid} (e.g. {grid * (args.camera_size // grid)})")
    cameras = predictor.cameras or task.cameras  # the world model's views, in its order
    env = TaskEnv(EnvConfig(task=task.name, camera_size=args.camera_size))
    try:
        policy = load_policy(args.policy, task=task)
        seeds = list(range(args.seed_start, args.seed_start + args.episodes))
        frames = collect_foreground(env, policy, seeds, every=args.every, cameras=cameras,
                                    progress=lambda i, n: print(f"episode {i}/{n}", flush=True))
    finally:
        env.close()
    readout, report = fit_foreground(encoder, frames, steps=args.steps)
    save_foreground(out, readout, encoder, report, task.name, cameras)
    print(format_report(report))
    picture = draw_foreground(frames, readout, encoder, Path(out) / "foreground.png")
    print(f"wrote {out} (plan with it: wamplan eval --cost-foreground {out}); picture {picture}")
    return 0
