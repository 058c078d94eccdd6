"""``wamplan collect`` and ``wamplan data info|check|alignment|view|export|import``."""

from __future__ import annotations

import argparse
import json
from collections import Counter, defaultdict
from pathlib import Path

from wamplan.config import add_arguments, from_args
from wamplan.errors import UserError, require_dir, require_file, require_positive, require_seeds
from wamplan.cli.main import add_command, add_group, first_screen, register_command

SOURCES = ("expert", "noisy-expert", "pink", "policy")
EXPERT_PREFIX, NOISY_PREFIX = "expert_", "noisy_"  # collect's --expert-<field> and --noisy-<field> options


@register_command("data")
def register(sub: argparse._SubParsersAction) -> None:
    add_command(sub, "collect", _collect_options, help="collect episodes into an episode store (parallel, resumable)")
    add_group(sub, "data", _data_commands, help="episode stores: info, check, alignment, view; import and export")


def _collect_options(p: argparse.ArgumentParser) -> None:
    from wamplan.envs.config import EnvConfig
    from wamplan.parallel import add_backend_argument
    from wamplan.policies.expert import ExpertConfig
    from wamplan.policies.noise import NoisyExpertConfig

    p.add_argument("--source", required=True, choices=SOURCES,
                   help="who acts: the scripted expert, the noisy expert, pink-noise exploration, or a WAM "
                        "checkpoint (policy, with --policy)")
    p.add_argument("--episodes", type=int, required=True, help="number of seeds, from --seed-start")
    p.add_argument("--out", type=Path, required=True, help="the store directory (created or resumed)")
    p.add_argument("--seed-start", type=int, default=0, help="the first episode seed (default: 0)")
    p.add_argument("--workers", type=int, default=1,
                   help="worker processes (one simulator each), or Ray actors with --ray")
    add_backend_argument(p)
    p.add_argument("--policy", default=None, help="with --source policy: a WAM checkpoint directory")
    p.add_argument("--plan-with", default="", metavar="WM",
                   help="with --source policy: plan every chunk of the WAM in this world model (condition 7's "
                        "policy at eval's default planner and cost), so episodes and branches follow the planner's "
                        "own trajectories")
    p.add_argument("--image-every", type=int, default=4, help="store the task's views every N steps (and the last)")
    p.add_argument("--max-steps", type=int, default=None, help="truncate episodes earlier than the env's limit")
    p.add_argument("--branches", type=int, default=0,
                   help="with --source policy: also store this many counterfactual branches per chunk boundary "
                        "(the policy's chunk plus Gaussian noise; wamplan/data/branch.py)")
    p.add_argument("--branch-sigmas", type=float, nargs="+", default=[0.05, 0.1, 0.2],
                   help="noise std of the branches, cycled (default: 0.05 0.1 0.2)")
    p.add_argument("--branch-steps", type=int, nargs=2, metavar=("LO", "HI"),
                   help="branch only the chunk boundaries at steps LO..HI (default: every boundary), to aim the "
                        "data at one phase of the task, e.g. 96 128 for the descent onto the mount")
    p.add_argument("--branch-context", type=int, default=8,
                   help="steps of the parent's history each branch episode keeps: (H_ctx - 1) x frameskip")
    add_arguments(p.add_argument_group("task"), EnvConfig)
    g = p.add_argument_group("expert", "the scripted expert's settings (--source expert or noisy-expert)")
    add_arguments(g, ExpertConfig, prefix=EXPERT_PREFIX)
    g = p.add_argument_group("noisy expert", "the noise's settings (--source noisy-expert)")
    add_arguments(g, NoisyExpertConfig, prefix=NOISY_PREFIX)
    first_screen(p, "--seed-start", "--workers", "--policy", "--image-every", "--max-steps", "--task", "--camera-size")
    p.set_defaults(func=cmd_collect)


def _data_commands(d: argparse.ArgumentParser) -> None:
    dsub = d.add_subparsers(dest="data_command", metavar="DATA_COMMAND")
    add_command(dsub, "info", _info_options, help="episodes, frames, size; per source: success rate and outcomes")
    add_command(dsub, "check", _check_options,
                help="read every byte of every episode, verifying its checksums; names each damaged file")
    add_command(dsub, "alignment", _alignment_options,
                help="per episode: how close the cube came to the hole (xy, yaw, in-hand offset) while carried over "
                     "the mount, from the privileged poses")
    add_command(dsub, "view", _view_options, help="a contact sheet of the stored views over one episode")
    add_command(dsub, "import", _import_options,
                help="turn ManiSkill trajectory files (.h5 + .json) or a LeRobot dataset into an episode store",
                description="--format maniskill: import a ManiSkill trajectory (its motion planner's, its replay "
                            "tool's or its published demonstrations) into the store OUT: actions in another "
                            "controller than the task's are converted by ManiSkill's replay_trajectory first (the "
                            "converted file is written beside the original), then every episode is replayed open loop "
                            "from its seed and recorded with the task's cameras. Episodes that no longer succeed are "
                            "dropped (kept with --keep-failed or --noise-std); OUT/import.json reports the share that "
                            "succeeded. --format lerobot: read a LeRobotDataset directory (v3.0, v2.1 or v2.0; video "
                            "or image features) into a new store OUT of --task (its action and proprio sizes must "
                            "match), views resized to --camera-size; --key-map OURS=THEIRS names the dataset's keys "
                            "where they are not action, observation.state and observation.images.<camera> (openpi's "
                            "LIBERO set: action=actions observation.state=state observation.images.<camera>=image "
                            "...). N frames make T = N-1 steps (the last frame's action is dropped). Such a store has "
                            "no simulator state, stage flags or env seeds: the world model (wm train) and TinyWAM "
                            "(wam train) train on it, but evaluation, the simulator-oracle dynamics, counterfactual "
                            "branches and data alignment need a collected store. OUT appears whole or not at all.")
    add_command(dsub, "export", _export_options,
                help="write a store in another project's training layout (Cosmos Policy HDF5, LeRobotDataset)",
                description="--format cosmos-policy: write the store DIR under OUT in the HDF5 layout Cosmos Policy's "
                            "post-training reads (OUT/demos/*.hdf5 RoboCasa-style demos, OUT/rollouts/*.hdf5 "
                            "on-policy episodes). --format lerobot: write it as a LeRobotDataset at OUT (v3.0, or "
                            "--lerobot-version 2.1): action, observation.state and the index columns in parquet, one "
                            "MP4 a camera (observation.images.<camera>; AV1 by SVT-AV1 where PyAV has it, else H.264), "
                            "meta/info.json, episodes, tasks and stats, wamplan's seed, source, success and outcome as "
                            "episode fields; OUT appears whole or not at all. Both formats take a frame per control "
                            "step, so the store must be collected with --image-every 1. An episode of T steps has T+1 "
                            "frames (the last shows the final state): its actions get one padding row at the last "
                            "frame, a no-op (no motion, the last gripper command), recorded in the export (lerobot "
                            "import drops it again).")


def _info_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("dir", type=Path, help="an episode store directory (`wamplan collect --out`)")
    p.add_argument("--json", action="store_true", help="print JSON instead of text")
    p.set_defaults(func=cmd_info)


def _check_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("dir", type=Path, help="an episode store directory (`wamplan collect --out`)")
    p.add_argument("--json", action="store_true", help="print JSON (every damaged file and the counts) instead of text")
    p.set_defaults(func=cmd_check)


def _alignment_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("dir", type=Path, help="an episode store directory (`wamplan collect --out`)")
    p.add_argument("--json", action="store_true", help="print JSON (every episode and the summary) instead of text")
    p.add_argument("--quiet", action="store_true", help="text: the per-outcome summary only")
    p.set_defaults(func=cmd_alignment)


def _view_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("dir", type=Path, help="an episode store directory (`wamplan collect --out`)")
    p.add_argument("--episode", type=int, default=0, help="index in the store's sorted episode list (default: 0)")
    p.add_argument("--out", type=Path, default=Path("sheet.png"), help="PNG to write (default: sheet.png)")
    p.add_argument("--frames", type=int, default=8, help="frames across the episode (default: 8)")
    p.set_defaults(func=cmd_view)


def _import_options(p: argparse.ArgumentParser) -> None:
    from wamplan.envs.config import EnvConfig
    from wamplan.parallel import add_backend_argument

    from wamplan.data.lerobot.importer import LeRobotImportConfig

    p.add_argument("trajectory", type=Path, help="maniskill: a trajectory .h5 (its .json beside it); lerobot: the "
                                                 "dataset directory (holding meta/info.json)")
    p.add_argument("out", type=Path, help="the store directory (maniskill: created or resumed; lerobot: created)")
    p.add_argument("--format", required=True, choices=("maniskill", "lerobot"), help="the input's format")
    p.add_argument("--workers", type=int, default=1, help="worker processes (one simulator each), or Ray actors")
    add_backend_argument(p)
    p.add_argument("--image-every", type=int, default=None,
                   help="store the task's views every N steps (and the last); default 4 (maniskill), 1 (lerobot)")
    p.add_argument("--episodes", type=int, default=None, help="import only the first N episodes (maniskill: by seed)")
    g = p.add_argument_group("lerobot", "--format lerobot only")
    g.add_argument("--key-map", nargs="+", default=None, metavar="OURS=THEIRS",
                   help=LeRobotImportConfig.__dataclass_fields__["key_map"].metadata["help"])
    g.add_argument("--lerobot-source", default=None, metavar="NAME",
                   help=LeRobotImportConfig.__dataclass_fields__["source"].metadata["help"] + " (default: lerobot)")
    p.add_argument("--noise-std", type=float, default=0.0,
                   help="add white Gaussian noise of this std to the arm's entries of every replayed action "
                        "(noisy-expert data; episodes are kept whatever their outcome, source demo-noise<STD>)")
    p.add_argument("--keep-failed", action="store_true", help="keep episodes that fail on replay")
    add_arguments(p, EnvConfig)
    p.set_defaults(func=cmd_import, task=None)  # default: the registered task that runs the trajectory's env


def cmd_import(args: argparse.Namespace) -> int:
    from wamplan.data.importer import import_maniskill
    from wamplan.envs.config import EnvConfig
    from wamplan.parallel import Backend

    from wamplan.envs.spec import DEFAULT_TASK

    require_dir(args.out)
    if args.format == "lerobot":
        return _import_lerobot(args)
    if args.key_map or args.lerobot_source:
        raise UserError("--key-map and --lerobot-source are for --format lerobot; drop them")
    args.image_every = 4 if args.image_every is None else args.image_every
    require_positive(("--workers", args.workers), ("--image-every", args.image_every), ("--episodes", args.episodes))
    task, args.task = args.task, args.task or DEFAULT_TASK
    report = import_maniskill(args.trajectory, args.out, task=task, env=from_args(EnvConfig, args),
                              workers=args.workers, image_every=args.image_every, noise_std=args.noise_std,
                              keep_failed=args.keep_failed, limit=args.episodes,
                              backend=Backend.from_option(args.ray))
    print(json.dumps(report))
    return 0


def _import_lerobot(args: argparse.Namespace) -> int:
    from wamplan.data.lerobot.importer import LeRobotImportConfig, import_lerobot
    from wamplan.envs.config import EnvConfig

    if args.noise_std or args.keep_failed or args.workers != 1 or args.ray:
        raise UserError("--noise-std, --keep-failed, --workers and --ray are for --format maniskill; drop them")
    if args.task is None:
        raise UserError("--format lerobot needs --task NAME: the registered task whose action and proprio sizes the "
                        "dataset has (`wamplan tasks` lists them; docs/lerobot.md registers a new one)")
    cfg = LeRobotImportConfig(key_map=tuple(args.key_map or ()), image_every=args.image_every or 1,
                              source=args.lerobot_source or "lerobot", episodes=args.episodes or 0)
    print(json.dumps(import_lerobot(args.trajectory, args.out, from_args(EnvConfig, args), cfg)))
    return 0


def _export_options(p: argparse.ArgumentParser) -> None:
    from wamplan.data.export import FORMATS, CosmosExportConfig
    from wamplan.data.lerobot.export import LeRobotExportConfig

    p.add_argument("dir", type=Path, help="the episode store to export")
    p.add_argument("out", type=Path, help="the directory to write the exported files under (created)")
    p.add_argument("--format", required=True, choices=(*FORMATS, "lerobot"), help="the target layout")
    add_arguments(p, CosmosExportConfig)
    add_arguments(p.add_argument_group("lerobot", "--format lerobot only"), LeRobotExportConfig)
    p.set_defaults(func=cmd_export)


def cmd_collect(args: argparse.Namespace) -> int:
    from wamplan.data.collect import collect
    from wamplan.envs.config import EnvConfig
    from wamplan.evaluation.build import load_policy
    from wamplan.parallel import Backend

    require_seeds(args.seed_start, args.episodes)
    if args.max_steps is not None and args.max_steps < 1:
        raise UserError(f"--max-steps {args.max_steps} must be at least 1; drop it for the task's own limit")
    require_dir(args.out)
    env = from_args(EnvConfig, args)
    env.require_views()  # every episode records the task's views
    branch = None
    if args.branch_steps and not args.branches:
        raise UserError("--branch-steps chooses where to branch: add --branches N (branches per boundary)")
    if args.branches:
        from wamplan.data.branch import BranchSpec

        require_positive(("--branches", args.branches))
        if min(args.branch_sigmas) <= 0 or args.branch_context < 0:
            bad = (f"--branch-sigmas {min(args.branch_sigmas):g} must be > 0" if min(args.branch_sigmas) <= 0
                   else f"--branch-context {args.branch_context} must be >= 0")
            raise UserError(bad)
        steps = tuple(args.branch_steps) if args.branch_steps else None
        if steps and not 0 <= steps[0] <= steps[1]:
            raise UserError(f"--branch-steps {steps[0]} {steps[1]}: give two steps LO <= HI, both >= 0")
        branch = BranchSpec(branches=args.branches, sigmas=tuple(args.branch_sigmas),
                            context_steps=args.branch_context, steps=steps)
    summary = collect(args.source, args.episodes, args.out, seed_start=args.seed_start, workers=args.workers,
                      policy=args.policy, image_every=args.image_every, max_steps=args.max_steps,
                      env=env, loader=load_policy, backend=Backend.from_option(args.ray),
                      branch=branch, policy_kwargs=expert_kwargs(args), plan_with=args.plan_with)
    print(json.dumps(summary))
    return 0


def expert_kwargs(args: argparse.Namespace) -> dict:
    """The constructor settings of the expert sources from ``--expert-*`` / ``--noisy-*`` (only those given)."""
    from wamplan.policies.expert import ExpertConfig
    from wamplan.policies.noise import NoisyExpertConfig

    given = sorted(k for k, v in vars(args).items() if v is not None and k.startswith((EXPERT_PREFIX, NOISY_PREFIX)))
    allowed = {"expert": (EXPERT_PREFIX,), "noisy-expert": (EXPERT_PREFIX, NOISY_PREFIX)}.get(args.source, ())
    if wrong := [k for k in given if not any(k.startswith(a) for a in allowed)]:
        flags = ", ".join("--" + k.replace("_", "-") for k in wrong)
        raise UserError(f"{flags}: not a setting of --source {args.source}; --expert-* options are for the "
                        f"expert and noisy-expert sources, --noisy-* for noisy-expert only")
    if not given:
        return {}
    expert = from_args(ExpertConfig, args, prefix=EXPERT_PREFIX)
    if args.source == "expert":
        return dict(config=expert)
    return dict(config=from_args(NoisyExpertConfig, args, prefix=NOISY_PREFIX), expert=expert)


def store_info(root: Path) -> dict:
    """Episodes, steps, frames and bytes of the store ``root``, per source; files that cannot be read (their
    header or attributes damaged) are listed under ``damaged``, not counted. Reads no arrays: damage inside
    them is found by :func:`wamplan.data.store.verify_episode` (``wamplan data check``)."""
    from wamplan.data.store import EpisodeStore, StoreError

    store = EpisodeStore(root)
    per: dict[str, dict] = defaultdict(lambda: dict(episodes=0, steps=0, frames=0, outcomes=Counter()))
    damaged = []
    for path in store.episode_paths():
        try:
            m = store.meta(path)
        except StoreError as e:
            damaged.append(dict(path=str(path), problem=str(e)))
            continue
        s = per[m["source"]]
        s["episodes"] += 1
        s["steps"] += m["length"]
        s["frames"] += m["frames"]
        s["outcomes"][m["outcome"]] += 1
    size = sum(p.stat().st_size for p in store.episode_paths())
    sources = {k: dict(v, outcomes=dict(v["outcomes"]), success_rate=v["outcomes"]["success"] / v["episodes"])
               for k, v in sorted(per.items())}
    n = sum(v["episodes"] for v in sources.values())
    return dict(dir=str(root), episodes=n, steps=sum(v["steps"] for v in sources.values()),
                image_frames=sum(v["frames"] for v in sources.values()), bytes=size,
                bytes_per_episode=size // n if n else None, image_every=store.image_every, task=store.task_name,
                cameras=list(store.cameras), env=store.env,
                sources=sources, damaged=damaged)


def cmd_info(args: argparse.Namespace) -> int:
    info = store_info(args.dir)
    if args.json:
        print(json.dumps(info, indent=1))
        return 0
    print(f"{info['dir']} (task {info['task']}): {info['episodes']} episodes, {info['steps']} steps, "
          f"{info['image_frames']} image frames (every {info['image_every']} steps), {info['bytes'] / 2**20:.1f} MiB")
    for src, s in info["sources"].items():
        outs = ", ".join(f"{k} {v}" for k, v in sorted(s["outcomes"].items()))
        print(f"  {src:20s} {s['episodes']:5d} episodes  success {100 * s['success_rate']:5.1f}%  ({outs})")
    for d in info["damaged"]:
        print(f"  damaged: {d['problem']}")
    print(f"  integrity: {len(info['damaged'])} damaged file(s) found by reading headers; `wamplan data check "
          f"{args.dir}` reads every byte and verifies the checksums")
    _refuse_damaged(args.dir, info["damaged"], len(info["damaged"]) + info["episodes"])
    return 0


def _refuse_damaged(root: Path, damaged: list[dict], total: int) -> None:
    """One line (exit status 2) when ``damaged`` (listed above it) is not empty."""
    from wamplan.data.store import RECOLLECT

    if damaged:
        names = [Path(d["path"]).name for d in damaged]
        shown = ", ".join(names[:3]) + (f" and {len(names) - 3} more" if len(names) > 3 else "")
        raise UserError(f"{len(damaged)} of {total} episode files in {root} are damaged ({shown}; listed above); "
                        f"for each, {RECOLLECT}")


def cmd_check(args: argparse.Namespace) -> int:
    from wamplan.data.store import EpisodeStore, verify_episode
    from wamplan.progress import progress_bar

    store = EpisodeStore(args.dir)
    paths = store.episode_paths()
    damaged, unchecked = [], 0
    for path in progress_bar(paths, desc="check", unit="ep", disable=args.json):
        problem, checksummed = verify_episode(path)
        unchecked += not checksummed
        if problem is not None:
            damaged.append(dict(path=str(path), problem=problem))
    if args.json:
        print(json.dumps(dict(dir=str(args.dir), episodes=len(paths), damaged=damaged,
                              without_checksums=unchecked), indent=1))
    else:
        for d in damaged:
            print(f"damaged: {d['path']} ({d['problem']})")
        print(f"{args.dir}: {len(paths)} episodes read, {len(damaged)} damaged"
              + (f"; {unchecked} written before checksums (only damage that breaks decompression or the file's "
                 f"structure shows in those)" if unchecked else ""))
    _refuse_damaged(args.dir, damaged, len(paths))
    return 0


def cmd_alignment(args: argparse.Namespace) -> int:
    from wamplan.data.alignment import as_dicts, store_alignment, summary

    rows = store_alignment(args.dir)
    if args.json:
        print(json.dumps(dict(episodes=as_dicts(rows), summary=summary(rows)), indent=1))
        return 0
    if not args.quiet:
        print(f"{'source':20s} {'seed':>5s} {'outcome':22s} {'over':>4s} {'step':>4s} {'xy mm':>6s} {'dx':>6s} "
              f"{'dy':>6s} {'yaw deg':>7s} {'in hand mm':>10s}")
        for r in rows:
            yaw = f"{r.yaw_deg:+7.1f}" if r.yaw_deg is not None else f"{'-':>7s}"
            hand = f"{r.in_hand_mm:10.1f}" if r.in_hand_mm is not None else f"{'-':>10s}"
            print(f"{r.source[:20]:20s} {r.seed:5d} {r.outcome:22s} {r.over_steps:4d} {r.step:4d} {r.xy_mm:6.1f} "
                  f"{r.dx_mm:+6.1f} {r.dy_mm:+6.1f} {yaw} {hand}")
    print("per outcome (medians over the episodes that got over the mount):")
    for outcome, s in summary(rows).items():
        line = f"  {outcome:22s} {s['episodes']:4d} episodes, {s['over_mount']:4d} over the mount"
        if s["over_mount"]:
            line += (f": xy {s['median_xy_mm']} mm, |yaw| {s['median_abs_yaw_deg']} deg, "
                     f"in hand {s['median_in_hand_mm']} mm")
        print(line)
    return 0


def cmd_export(args: argparse.Namespace) -> int:
    import dataclasses

    from wamplan.data.export import CosmosExportConfig, export_cosmos_policy
    from wamplan.data.lerobot.export import LeRobotExportConfig, export_lerobot

    require_dir(args.out, "OUT")
    sources = tuple(s for x in args.sources or () for s in x.split(",") if s)
    if args.format == "lerobot":
        if args.split is not None:
            raise UserError("--split is for --format cosmos-policy; drop it")
        cfg = from_args(LeRobotExportConfig, args)  # its own options; the shared ones below
        cfg = dataclasses.replace(cfg, image_size=args.image_size or 0, instruction=args.instruction or "",
                                  sources=sources)
        print(json.dumps(export_lerobot(args.dir, args.out, cfg), indent=1))
        return 0
    if given := [f"--{k.replace('_', '-')}" for k in ("lerobot_version", "fps", "vcodec", "crf")
                 if getattr(args, k) is not None]:
        raise UserError(f"{', '.join(given)}: for --format lerobot; drop {'them' if len(given) > 1 else 'it'}")
    cfg = from_args(CosmosExportConfig, args)  # no --instruction: the store's task's (what a WAM of it is sent)
    cfg = dataclasses.replace(cfg, sources=sources or cfg.sources)
    print(json.dumps(export_cosmos_policy(args.dir, args.out, cfg), indent=1))
    return 0


def cmd_view(args: argparse.Namespace) -> int:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from wamplan.data.store import EpisodeStore

    require_file(args.out, "--out")
    if args.frames < 1:
        raise UserError(f"--frames {args.frames}: a contact sheet needs at least 1 frame (default 8)")
    store = EpisodeStore(args.dir)
    cameras = store.cameras
    paths = store.episode_paths()
    if not 0 <= args.episode < len(paths):
        raise UserError(f"--episode {args.episode} is out of range: {args.dir} holds {len(paths)} episodes (0..{len(paths) - 1})")
    with store.open_episode(paths[args.episode]) as f:
        steps = f["image_steps"][:]
        idx = np.unique(np.linspace(0, len(steps) - 1, min(args.frames, len(steps))).round().astype(int))
        imgs = {c: f["images"][c][idx] for c in cameras}  # (F, H, W, 3) each
        title = (f"{f.attrs['source']} seed {f.attrs['seed']}: {f.attrs['outcome']}, {f.attrs['length']} steps")
    fig, axes = plt.subplots(len(cameras), len(idx), figsize=(2 * len(idx), 2 * len(cameras) + 0.4), squeeze=False)
    for r, c in enumerate(cameras):
        for j, k in enumerate(idx):
            ax = axes[r][j]
            ax.imshow(imgs[c][j])
            ax.set_xticks([]), ax.set_yticks([])
            if r == 0:
                ax.set_title(f"t={steps[k]}", fontsize=9)
            if j == 0:
                ax.set_ylabel(c)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=80)
    print(f"wrote {args.out}")
    return 0
