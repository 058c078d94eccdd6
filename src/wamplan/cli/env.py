"""``wamplan env check|render|rollout`` and ``wamplan tasks``."""

from __future__ import annotations

import argparse
import json
import os
import time
from collections import Counter
from pathlib import Path
from typing import TYPE_CHECKING

from wamplan.config import add_arguments, choices_metavar, from_args
from wamplan.errors import UserError, require_dir, require_file, require_seeds
from wamplan.cli.main import add_command, add_group, register_command


@register_command("env")
def register(sub: argparse._SubParsersAction) -> None:
    add_group(sub, "env", _env_commands,
              help="a task's env (--task, default cube-insertion): check the renderer, render views, roll out "
                   "policies")


@register_command("tasks")
def register_tasks(sub: argparse._SubParsersAction) -> None:
    add_command(sub, "tasks", _tasks_options, help="list the registered tasks (what --task accepts)")

if TYPE_CHECKING:
    from wamplan.envs.spec import TaskSpec


def _tasks_options(p: argparse.ArgumentParser) -> None:
    p.set_defaults(func=cmd_tasks)


def _demonstrations(t: TaskSpec) -> str:
    """Where the task's demonstrations come from: its scripted expert policy, another source, or none."""
    if t.expert:
        return f"scripted expert (policy '{t.expert}')"
    return t.demonstrations or "none"


def cmd_tasks(args: argparse.Namespace) -> int:
    from wamplan.envs.spec import TASKS

    names = sorted(TASKS)
    width = max(map(len, names))
    for name in names:
        t = TASKS[name]
        print(f"{name:{width}s}  env {t.env_id}  cameras {','.join(t.cameras)}  action {t.action_dim}  proprio "
              f"{t.proprio_dim}  controller {t.control_mode}  episode {t.max_episode_steps} steps  demonstrations "
              f"{_demonstrations(t)}")
    return 0


def _env_commands(env: argparse.ArgumentParser) -> None:
    esub = env.add_subparsers(dest="env_command", metavar="ENV_COMMAND")
    add_command(esub, "check", _check_options, help="is rendering possible here? timings of physics and cameras")
    add_command(esub, "render", _render_options, help="render the three views of one seed side by side")
    add_command(esub, "rollout", _rollout_options, help="run a policy for N episodes and summarise the outcomes")


def _check_options(p: argparse.ArgumentParser) -> None:
    from wamplan.envs.spec import TASKS

    p.add_argument("--steps", type=int, default=20, help="steps to time (default 20)")
    p.add_argument("--task", default="cube-insertion", metavar=choices_metavar(sorted(TASKS)),  # checked by EnvConfig
                   help="the registered task whose env is checked (default: cube-insertion)")
    p.set_defaults(func=cmd_check)


def _render_options(p: argparse.ArgumentParser) -> None:
    from wamplan.envs.config import EnvConfig

    p.add_argument("--seed", type=int, default=0, help="episode seed (default: 0)")
    p.add_argument("--out", type=Path, default=Path("views.png"), help="PNG to write (default: views.png)")
    add_arguments(p, EnvConfig)
    p.set_defaults(func=cmd_render)


def _rollout_options(p: argparse.ArgumentParser) -> None:
    from wamplan.envs.config import EnvConfig

    p.add_argument("--policy", default="expert", help="expert | noisy-expert | pink | a WAM checkpoint directory")
    p.add_argument("--episodes", type=int, default=10, help="number of episodes, seeds --seed-start .. (default: 10)")
    p.add_argument("--seed-start", type=int, default=0, help="the first episode seed (default: 0)")
    p.add_argument("--json", type=Path, default=None, help="write per-episode records and the summary here")
    p.add_argument("--video", type=Path, default=None, help="write one MP4 per episode (every view of the task) here")
    p.add_argument("--instruction", default=None, help="language instruction for WAM policies")
    add_arguments(p, EnvConfig)
    p.set_defaults(func=cmd_rollout)


# ---------------------------------------------------------------------- check
def cmd_check(args: argparse.Namespace) -> int:
    import numpy as np

    from wamplan.envs.config import EnvConfig
    from wamplan.envs.diagnose import diagnose_renderer, driver_file_problem, mesa_version

    if args.steps < 1:
        raise UserError(f"--steps must be >= 1 (physics steps to time), got {args.steps}")
    bad = driver_file_problem()
    if bad:  # before any renderer starts: its own error would not name the variable
        raise UserError(bad)
    problems = diagnose_renderer()
    print(f"VK_ICD_FILENAMES={os.environ.get('VK_ICD_FILENAMES', '(unset)')}  mesa-vulkan-drivers={mesa_version()}")
    cfg = EnvConfig(task=args.task)
    try:
        from wamplan.envs.core import TaskEnv

        env = TaskEnv(cfg)
        env.reset(0)
        env.render()
    except Exception as e:  # report any renderer failure with what to do, then the raw reason
        hint = "; ".join(problems) or "see the error above; `make setup` installs a working software renderer"
        raise UserError(f"cannot render {cfg.spec.env_id} here ({type(e).__name__}: {str(e).splitlines()[0]}): "
                        f"{hint}") from e
    for p in problems:
        print(f"warning: {p}")
    task = env.task
    zero = np.zeros(task.action_dim, np.float32)
    t = time.perf_counter()
    for _ in range(args.steps):
        env.step(zero)
    step_ms = (time.perf_counter() - t) / args.steps * 1e3
    print(f"renderer ok; physics step {step_ms:.1f} ms")
    for cam in task.cameras:
        t = time.perf_counter()
        for _ in range(3):
            env.render((cam,))
        print(f"render {cam:5s} {(time.perf_counter() - t) / 3 * 1e3:.1f} ms")
    t = time.perf_counter()
    for _ in range(5):
        env.step(zero, with_images=True)
    print(f"full step with all {len(task.cameras)} cameras {(time.perf_counter() - t) / 5 * 1e3:.1f} ms")
    env.close()
    return 0


# ---------------------------------------------------------------------- render
def cmd_render(args: argparse.Namespace) -> int:
    from wamplan.envs.config import EnvConfig
    from wamplan.envs.core import TaskEnv
    from wamplan.envs.media import save_views

    require_seeds(args.seed, flag="--seed")
    require_file(args.out, "--out")
    cfg = from_args(EnvConfig, args)
    cfg.require_views()
    env = TaskEnv(cfg)
    obs = env.reset(args.seed, with_images=True)
    save_views(obs.images, args.out)
    print(f"wrote {args.out} ({' | '.join(env.task.cameras)}, seed {args.seed})")
    return 0


# ---------------------------------------------------------------------- rollout
def cmd_rollout(args: argparse.Namespace) -> int:
    from wamplan.progress import progress_bar

    from wamplan.envs.config import EnvConfig
    from wamplan.envs.core import TaskEnv
    from wamplan.envs.media import write_video
    from wamplan.policies.rollout import run_episode
    from wamplan.evaluation.build import load_policy
    from wamplan.provenance import provenance

    if args.episodes <= 0:
        raise UserError(f"--episodes must be > 0, got {args.episodes}")
    require_seeds(args.seed_start, args.episodes)
    require_file(args.json, "--json")
    if args.video is not None:
        require_dir(args.video, "--video")
    cfg = from_args(EnvConfig, args)
    policy = load_policy(args.policy, args.instruction, task=cfg.spec)
    if args.video is not None or policy.wants_images(0):  # a video, or a policy that reads the views
        cfg.require_views()
    env = TaskEnv(cfg)
    records, counts = [], Counter()
    seeds = range(args.seed_start, args.seed_start + args.episodes)
    bar = progress_bar(seeds, desc=f"rollout {args.policy}", unit="ep")
    for seed in bar:
        frames: list = []
        record = args.video is not None
        r = run_episode(env, policy, seed, images_at=(lambda t: True) if record else None,
                        on_obs=(lambda _e, obs, _a: frames.append(obs.images)) if record else None)
        if args.video is not None:
            write_video(args.video / f"{args.policy.replace('/', '_')}_seed{seed}.mp4", frames)
        records.append(r.summary())
        counts[r.outcome] += 1
        bar.set_postfix(success=f"{counts['success']}/{len(records)}")
        bar.write(f"seed {seed:4d}  success={r.success!s:5s}  outcome={r.outcome:22s} length={r.length}")
    lengths = sorted(rec["length"] for rec in records if rec["success"])
    summary = dict(policy=args.policy, episodes=len(records), success_rate=counts["success"] / len(records),
                   outcomes=dict(counts), median_success_length=lengths[len(lengths) // 2] if lengths else None)
    print(json.dumps(summary))
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(dict(summary=summary, episodes=records, env=cfg.task_kwargs(),
                                             policy=policy.config_dict(), provenance=provenance()), indent=1))
    env.close()
    return 0

