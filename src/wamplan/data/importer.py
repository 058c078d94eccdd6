"""``wamplan data import --format maniskill``: ManiSkill trajectory files (``.h5`` + ``.json``, from its motion
planner, its replay tool or its published demonstrations) into a wamplan episode store.

1. The file's env id names the task (the registered task running that env, or ``--task``, which must agree).
2. Actions in another controller than the task's are converted first with ManiSkill's own tool
   (``python -m mani_skill.trajectory.replay_trajectory -c <task controller> --use-first-env-state``), which writes
   the converted file next to the original (kept, and reused on a re-run).
3. Every episode is replayed open loop from ``reset(seed)`` with its converted actions
   (``wamplan.policies.replay``) and recorded as any collected episode (states every step, the task's cameras every
   ``image_every`` steps), in parallel workers, resuming by seed.
4. Episodes that no longer succeed are removed from the store unless ``keep_failed``: the share that succeeds is
   the test of the conversion (it is reported, with the failed seeds, in ``import.json`` beside the store).
"""

from __future__ import annotations

import json
import subprocess
from dataclasses import replace
import sys
from pathlib import Path
from typing import Any

import h5py

from wamplan.data.collect import collect
from wamplan.data.store import EpisodeStore
from wamplan.envs.config import EnvConfig
from wamplan.envs.spec import TASKS, TaskSpec, get_task
from wamplan.errors import UserError, reason
from wamplan.parallel import Backend
from wamplan.policies.replay import trajectory_episodes

SOURCE = "demo"
REPORT = "import.json"


def read_trajectory_info(path: Path) -> dict[str, Any]:
    """The env id and controller a ManiSkill trajectory file was recorded with."""
    if not path.exists():
        raise UserError(f"{path} does not exist; pass a ManiSkill trajectory file (.h5, its .json beside it), e.g. "
                        f"from scripts/maniskill_demos.sh")
    if path.suffix != ".h5" or not path.is_file():
        raise UserError(f"{path} is not a ManiSkill trajectory file; pass the .h5 (its .json lies beside it)")
    meta = path.with_suffix(".json")
    if not meta.is_file():
        raise UserError(f"{meta} is missing: a ManiSkill trajectory is an .h5 file with a .json of the same name")
    if not h5py.is_hdf5(path):
        raise UserError(f"{path} is not an HDF5 file, so not a ManiSkill trajectory; pass the .h5 that ManiSkill "
                        f"wrote (its .json lies beside it)")
    try:
        info = json.loads(meta.read_text(encoding="utf-8"))["env_info"]
        return dict(env_id=info["env_id"], control_mode=info["env_kwargs"].get("control_mode"))
    except (ValueError, KeyError, TypeError, AttributeError) as e:  # not JSON, or not ManiSkill's layout
        raise UserError(f"{meta} is not a ManiSkill trajectory's metadata ({reason(e)}); pass the .h5 and .json "
                        f"that ManiSkill wrote") from None


def task_for(env_id: str, task: str | None) -> TaskSpec:
    """The task that imports ``env_id``'s trajectories: ``task`` if given (it must run that env), else the one
    registered task that does."""
    if task is not None:
        spec = get_task(task)
        if spec.env_id != env_id:
            raise UserError(f"the trajectory was recorded in {env_id}, but task '{spec.name}' runs {spec.env_id}; "
                            f"pass --task with a task that runs {env_id} (`wamplan tasks` lists them)")
        return spec
    found = [s for s in TASKS.values() if s.env_id == env_id]
    if len(found) != 1:
        raise UserError(f"{'no' if not found else 'more than one'} registered task runs {env_id}"
                        f"{'' if not found else ' (' + ', '.join(s.name for s in found) + ')'}; "
                        f"{'register one (README: Bringing your own task)' if not found else 'pass --task'}")
    return found[0]


def convert(path: Path, control_mode: str, count: int | None = None, workers: int = 1, log=print) -> Path:
    """``path``'s first ``count`` episodes (all: None) with their actions in ``control_mode``, by ManiSkill's replay
    tool in ``workers`` processes; a converted file holding at least as many episodes is reused."""
    out = path.with_name(f"{path.stem}.none.{control_mode}.physx_cpu.h5")
    total = len(json.loads(path.with_suffix(".json").read_text())["episodes"])
    want = min(count or total, total)
    if out.is_file() and out.with_suffix(".json").is_file() and len(trajectory_episodes(out)) >= want:
        return out
    log(f"converting {want} episodes of {path.name} to {control_mode} with ManiSkill's replay_trajectory")
    cmd = [sys.executable, "-m", "mani_skill.trajectory.replay_trajectory", "--traj-path", str(path),
           "-c", control_mode, "-o", "none", "--save-traj", "-b", "physx_cpu", "--use-first-env-state",
           "--allow-failure", "--count", str(want), "-n", str(workers)]
    done = subprocess.run(cmd, capture_output=True, text=True)
    if done.returncode != 0 or not out.is_file():
        for left in (out, out.with_suffix(".json")):  # a failed conversion leaves nothing beside the input
            left.unlink(missing_ok=True)
        lines = [ln for ln in (done.stderr + done.stdout).splitlines() if ln.strip() and "step/s" not in ln]
        raise UserError(f"ManiSkill could not convert {path} to {control_mode} ({(lines or ['no output'])[-1].strip()});"
                        f" its replay tool converts from pd_joint_pos trajectories (record or replay them in it)")
    return out


def import_maniskill(trajectory: str | Path, out: str | Path, *, task: str | None = None,
                     env: EnvConfig | None = None, workers: int = 1, image_every: int = 4, noise_std: float = 0.0,
                     keep_failed: bool = False, limit: int | None = None, progress: bool = True,
                     backend: Backend = Backend(), log=print) -> dict[str, Any]:
    """Import the episodes of ``trajectory`` (the first ``limit``) into the store ``out`` for ``task``; returns the
    summary written to ``out/import.json``: episodes tried, replayed successfully, their share, failed seeds,
    seconds."""
    path = Path(trajectory)
    info = read_trajectory_info(path)
    spec = task_for(info["env_id"], task)
    env = replace(env or EnvConfig(), task=spec.name)
    source_file = (path if info["control_mode"] == spec.control_mode
                   else convert(path, spec.control_mode, limit, workers, log))
    seeds = sorted(trajectory_episodes(source_file))[:limit]
    if not seeds:
        raise UserError(f"{source_file} holds no episodes")
    store_dir = Path(out)
    report_path = store_dir / REPORT
    tag = SOURCE if noise_std == 0 else f"{SOURCE}-noise{noise_std:g}"
    keep_failed = keep_failed or noise_std > 0  # noisy replays are exploration data: every outcome is kept
    previous = json.loads(report_path.read_text()) if report_path.is_file() else {}
    failed_before = set(previous.get("failed_seeds", [])) if previous.get("source") == tag else set()
    todo = [s for s in seeds if s not in failed_before]
    summary = collect(tag, len(todo), store_dir, seeds=todo, workers=workers, image_every=image_every, env=env,
                      progress=progress, log=log, backend=backend,
                      policy_kwargs=dict(trajectory=str(source_file), noise_std=noise_std), policy_name="demo-replay")
    store = EpisodeStore(store_dir)
    failed = set(failed_before)
    for meta in store.iter_meta():
        if meta["source"] == tag and not meta["success"]:
            failed.add(int(meta["seed"]))
            if not keep_failed:
                Path(meta["path"]).unlink()
    kept = len(store.finished_seeds(tag))
    report = dict(trajectory=str(path), converted=str(source_file), task=spec.name, controller=spec.control_mode,
                  source=tag, noise_std=noise_std, episodes=len(seeds), replay_success=len(seeds) - len(failed),
                  replay_success_share=round((len(seeds) - len(failed)) / len(seeds), 4),
                  failed_seeds=sorted(failed), kept=kept, seconds=summary["seconds"])
    report_path.write_text(json.dumps(report, indent=1) + "\n")
    return report
