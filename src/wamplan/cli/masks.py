"""``wamplan wm train-masks``: train the ``object-masks`` encoder on the simulator's segmentation."""

from __future__ import annotations

import argparse
from pathlib import Path

from wamplan.errors import UserError, checkpoint_kind, require_dir, require_seeds, require_writable

COLLECT_DEFAULTS = {"policy": "noisy-expert", "episodes": 40, "seed_start": 3200, "every": 4, "camera_size": 224}


def masks_options(p: argparse.ArgumentParser) -> None:
    from wamplan.config import add_arguments, choices_metavar
    from wamplan.encoders.object_masks import MaskTrainConfig
    from wamplan.envs.spec import TASKS

    d = COLLECT_DEFAULTS
    p.add_argument("--out", type=Path, required=True, help="run directory (checkpoint/, metrics.jsonl, masks.png)")
    p.add_argument("--frames", type=Path, required=True,
                   help="the pictures and segmentation as one .npz file: read if it exists (its task, episodes and "
                        "settings with it), else collected and written there")
    p.add_argument("--task", default=None, metavar=choices_metavar(sorted(TASKS)),
                   help="the task whose episodes are collected (default: the frames file's, else cube-insertion)")
    p.add_argument("--policy", default=None,
                   help=f"who drives the episodes: a registered policy or a WAM checkpoint (default: {d['policy']})")
    p.add_argument("--episodes", type=int, default=None,
                   help=f"episodes to collect (the last fifth held out; default: {d['episodes']})")
    p.add_argument("--seed-start", type=int, default=None, help=f"first seed (default: {d['seed_start']})")
    p.add_argument("--every", type=int, default=None, help=f"keep every N-th step's pictures (default: {d['every']})")
    p.add_argument("--camera-size", type=int, default=None,
                   help=f"rendered side in px, the stores' (default: {d['camera_size']}); a multiple of 16")
    p.add_argument("--max-steps", type=int, default=None, help="stop after this many steps (resumable)")
    p.add_argument("--device", default="auto", help="torch device (default: %(default)s)")
    add_arguments(p, MaskTrainConfig)
    p.set_defaults(func=cmd_masks)


def _mask_run(out: Path):
    """The saved training settings of the object-masks run in ``out`` (None for a new run); one line where ``out``
    holds something else."""
    from wamplan.checkpoint import CKPT_DIR, has_training_state, read_config
    from wamplan.config import from_dict
    from wamplan.encoders.object_masks import KIND, MaskTrainConfig
    from wamplan.train_loop import check_run_dir

    check_run_dir(out, "an object-masks run")
    if not has_training_state(out / CKPT_DIR):
        return None
    kind = checkpoint_kind(out / CKPT_DIR)
    if kind != KIND:
        raise UserError(f"--out {out} holds a '{kind}' run, not an object-masks run; pass a new --out")
    return from_dict(MaskTrainConfig, read_config(out / CKPT_DIR, KIND)["train"])


def _mask_frames(args: argparse.Namespace):
    """The frames of ``--frames``: read where the file exists (collection options refused: the file fixes them),
    else collected with the options (their defaults where not given) and written there."""
    from wamplan.data.foreground import collect_foreground, load_frames, require_frames_path, save_frames
    from wamplan.envs.config import EnvConfig
    from wamplan.envs.core import TaskEnv
    from wamplan.evaluation.build import load_policy

    given = [k for k in COLLECT_DEFAULTS if getattr(args, k) is not None]
    if args.frames.exists():
        if given:
            flag = "--" + given[0].replace("_", "-")
            raise UserError(f"{flag}: {args.frames} exists and fixes the episodes; drop {flag}, or pass a new "
                            f"--frames to collect with it")
        frames = load_frames(args.frames)
        if args.task and frames.task and frames.task != args.task:
            raise UserError(f"{args.frames} holds frames of task '{frames.task}', not '{args.task}'; pass --task "
                            f"{frames.task} or another --frames file")
        print(f"read {len(frames.episode)} frames of {len(set(frames.episode.tolist()))} episodes from {args.frames}")
        return frames
    opt = {k: COLLECT_DEFAULTS[k] if getattr(args, k) is None else getattr(args, k) for k in COLLECT_DEFAULTS}
    require_frames_path(args.frames)
    require_writable(args.frames.parent, "--frames")
    if opt["episodes"] < 2:
        raise UserError(f"--episodes {opt['episodes']}: training needs at least 2 episodes (the last fifth held out)")
    if opt["every"] < 1:
        raise UserError(f"--every must be >= 1, got {opt['every']}")
    if opt["camera_size"] % 16:
        raise UserError(f"--camera-size {opt['camera_size']} does not split into 16 x 16 cells; pass a multiple of "
                        f"16 (e.g. {16 * max(1, opt['camera_size'] // 16)})")
    require_seeds(opt["seed_start"], opt["episodes"])
    env = TaskEnv(EnvConfig(task=args.task or "cube-insertion", camera_size=opt["camera_size"]))
    try:
        policy = load_policy(opt["policy"], task=env.task)
        seeds = list(range(opt["seed_start"], opt["seed_start"] + opt["episodes"]))
        frames = collect_foreground(env, policy, seeds, every=opt["every"],
                                    progress=lambda i, n: print(f"episode {i}/{n}", flush=True))
    finally:
        env.close()
    print(f"wrote {save_frames(frames, args.frames)}")
    return frames


def cmd_masks(args: argparse.Namespace) -> int:
    from wamplan.config import from_args
    from wamplan.device import resolve_device
    from wamplan.encoders import make_encoder
    from wamplan.encoders.object_masks import MaskTrainConfig, draw_masks, held_out, train_object_masks

    resolve_device(args.device)  # a device this machine lacks: one line, before any work
    if args.max_steps is not None and args.max_steps <= 0:
        raise UserError(f"--max-steps must be > 0, got {args.max_steps}")
    out = require_dir(args.out)
    saved = _mask_run(out)  # before any collection: an --out that cannot take the run is refused first
    # a resumed run keeps its saved settings where no option overrides them (the defaults may have changed since)
    cfg = from_args(MaskTrainConfig, args, base=saved)
    frames = _mask_frames(args)
    metrics = train_object_masks(frames, out, cfg, task=frames.task or args.task or "cube-insertion",
                                 device=args.device, max_steps=args.max_steps, resume=saved is not None)
    if metrics.get("stopped"):
        print(f"stopped at step {metrics['global_step']} (--max-steps); re-run the same command to continue")
        return 0
    print("held out: " + ", ".join(f"{k.split('/')[-1]} {v:.3f}" for k, v in metrics.items() if k.startswith("val/")))
    encoder = make_encoder("object-masks", ckpt=str(out))
    seed = int(frames.episode[held_out(frames)].max())
    picture = draw_masks(frames, encoder, out / "masks.png", seed=seed)
    print(f"wrote {out} (use it: --encoder-kwargs '{{\"parts\": [{{\"name\": \"patch-pixels\"}}, "
          f"{{\"name\": \"object-masks\", \"ckpt\": \"{out}\"}}], \"scales\": [1, S]}}' with --encoder concat); "
          f"picture {picture}")
    return 0
