"""``wamplan env check|render|rollout``."""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import time
from collections import Counter
from pathlib import Path

from wamplan.config import add_arguments, from_args
from wamplan.errors import UserError


def register(sub: argparse._SubParsersAction) -> None:
    from wamplan.envs.core import EnvConfig

    env = sub.add_parser("env", help="the CubeInsertion-v1 task: check the renderer, render views, roll out policies")
    esub = env.add_subparsers(dest="env_command", metavar="ENV_COMMAND")

    p = esub.add_parser("check", help="is rendering possible here? timings of physics and cameras")
    p.add_argument("--steps", type=int, default=20, help="steps to time (default 20)")
    p.set_defaults(func=cmd_check)

    p = esub.add_parser("render", help="render the three views of one seed side by side")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, default=Path("views.png"))
    add_arguments(p, EnvConfig)
    p.set_defaults(func=cmd_render)

    p = esub.add_parser("rollout", help="run a policy for N episodes and summarise the outcomes")
    p.add_argument("--policy", default="expert", help="expert | noisy-expert | pink | a WAM checkpoint directory")
    p.add_argument("--episodes", type=int, default=10)
    p.add_argument("--seed-start", type=int, default=0)
    p.add_argument("--json", type=Path, default=None, help="write per-episode records and the summary here")
    p.add_argument("--video", type=Path, default=None, help="write one MP4 per episode (three views) here")
    p.add_argument("--instruction", default=None, help="language instruction for WAM policies")
    add_arguments(p, EnvConfig)
    p.set_defaults(func=cmd_rollout)


# ---------------------------------------------------------------------- check
def _mesa_version() -> str | None:
    try:
        out = subprocess.run(["dpkg-query", "-W", "-f=${Version}", "mesa-vulkan-drivers"], capture_output=True,
                             text=True, timeout=10)
        return out.stdout.strip() or None
    except (OSError, subprocess.SubprocessError):
        return None


def diagnose_renderer() -> list[str]:
    """Human-readable reasons rendering may fail here (empty if nothing looks wrong)."""
    import wamplan.envs.vulkan as vk

    vk.configure_vulkan()
    problems = []
    icd = os.environ.get("VK_ICD_FILENAMES") or os.environ.get("VK_DRIVER_FILES")
    gpu = any(p.exists() for p in vk.GPU_ICDS)
    if not icd and not gpu:
        problems.append("no Vulkan driver found: run `make setup` (installs Mesa lavapipe >= 24.3 from "
                        "bookworm-backports) or set VK_ICD_FILENAMES to your driver's ICD json")
    mesa = _mesa_version()
    if not gpu and mesa is not None:
        parts = mesa.split(".")
        if len(parts) >= 2 and parts[0].isdigit() and parts[1].isdigit() and (int(parts[0]), int(parts[1])) < (24, 3):
            problems.append(f"Mesa {mesa} is too old: SAPIEN needs VK_KHR_external_semaphore_fd, which lavapipe has "
                            f"from Mesa 24.3; run `make setup` to install 25.x from bookworm-backports")
    return problems


def cmd_check(args: argparse.Namespace) -> int:
    import numpy as np

    problems = diagnose_renderer()
    print(f"VK_ICD_FILENAMES={os.environ.get('VK_ICD_FILENAMES', '(unset)')}  mesa-vulkan-drivers={_mesa_version()}")
    try:
        from wamplan.envs.core import InsertionEnv

        env = InsertionEnv()
        env.reset(0)
        env.render()
    except Exception as e:  # report any renderer failure with what to do, then the raw reason
        hint = "; ".join(problems) or "see the error above; `make setup` installs a working software renderer"
        raise UserError(f"cannot render CubeInsertion-v1 here ({type(e).__name__}: {str(e).splitlines()[0]}): {hint}") from e
    for p in problems:
        print(f"warning: {p}")
    zero = np.zeros(5, np.float32)
    t = time.perf_counter()
    for _ in range(args.steps):
        env.step(zero)
    step_ms = (time.perf_counter() - t) / args.steps * 1e3
    print(f"renderer ok; physics step {step_ms:.1f} ms")
    for cam in ("front", "side", "wrist"):
        t = time.perf_counter()
        for _ in range(3):
            env.render((cam,))
        print(f"render {cam:5s} {(time.perf_counter() - t) / 3 * 1e3:.1f} ms")
    t = time.perf_counter()
    for _ in range(5):
        env.step(zero, with_images=True)
    print(f"full step with three cameras {(time.perf_counter() - t) / 5 * 1e3:.1f} ms")
    env.close()
    return 0


# ---------------------------------------------------------------------- render
def save_views(images: dict, path: Path) -> None:
    import imageio.v3 as iio
    import numpy as np

    path.parent.mkdir(parents=True, exist_ok=True)
    iio.imwrite(path, np.concatenate([images[c] for c in ("front", "side", "wrist")], axis=1))


def cmd_render(args: argparse.Namespace) -> int:
    from wamplan.envs.core import EnvConfig, InsertionEnv

    env = InsertionEnv(from_args(EnvConfig, args))
    obs = env.reset(args.seed, with_images=True)
    save_views(obs.images, args.out)
    print(f"wrote {args.out} (front | side | wrist, seed {args.seed})")
    return 0


# ---------------------------------------------------------------------- rollout
def load_policy(spec: str, instruction: str | None = None):
    """A registered policy name, or a directory holding a WAM checkpoint (run open loop)."""
    from wamplan.policies import POLICIES, make_policy

    if spec in POLICIES:
        return make_policy(spec)
    if Path(spec).is_dir():
        from wamplan.wam import WAMPolicy, load_wam

        return WAMPolicy(load_wam(spec), instruction=instruction) if instruction else WAMPolicy(load_wam(spec))
    raise UserError(f"unknown policy '{spec}': choose one of {sorted(POLICIES)} or pass a WAM checkpoint directory")


def cmd_rollout(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from wamplan.envs.core import EnvConfig, InsertionEnv
    from wamplan.envs.rollout import run_episode
    from wamplan.provenance import provenance

    if args.episodes <= 0:
        raise UserError(f"--episodes must be > 0, got {args.episodes}")
    cfg = from_args(EnvConfig, args)
    policy = load_policy(args.policy, args.instruction)
    env = InsertionEnv(cfg)
    records, counts = [], Counter()
    bar = tqdm(range(args.seed_start, args.seed_start + args.episodes), desc=f"rollout {args.policy}", unit="ep")
    for seed in bar:
        frames: list = []
        record = args.video is not None
        r = run_episode(env, policy, seed, images_at=(lambda t: True) if record else None,
                        on_obs=(lambda _e, obs, _a: frames.append(obs.images)) if record else None)
        if args.video is not None:
            _write_video(args.video / f"{args.policy.replace('/', '_')}_seed{seed}.mp4", frames)
        records.append(r.summary())
        counts[r.outcome] += 1
        bar.set_postfix(success=f"{counts['success']}/{len(records)}")
        tqdm.write(f"seed {seed:4d}  success={r.success!s:5s}  outcome={r.outcome:22s} length={r.length}")
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


def _write_video(path: Path, frames: list) -> None:
    import imageio.v2 as imageio
    import numpy as np

    path.parent.mkdir(parents=True, exist_ok=True)
    with imageio.get_writer(path, fps=20, macro_block_size=1) as w:
        for views in frames:
            w.append_data(np.concatenate([views[c] for c in ("front", "side", "wrist")], axis=1))
