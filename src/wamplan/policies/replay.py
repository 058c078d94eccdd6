"""Replaying recorded demonstrations: :class:`DemoReplayPolicy` plays back, open loop, the actions a ManiSkill
trajectory file holds for the seed it is reset with (its ``episode_seed``), optionally with white Gaussian noise
on the arm's entries: the noisy-expert data of a task that has demonstrations but no scripted expert.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from wamplan.config import check_numbers, field, require, to_dict
from wamplan.envs.spec import Observation, TaskSpec
from wamplan.errors import UserError
from wamplan.policies.base import Policy, register_policy


def trajectory_episodes(path: str | Path) -> dict[int, dict[str, Any]]:
    """``episode_seed -> episode entry`` of a ManiSkill trajectory's JSON (``traj_<id>`` holds its arrays)."""
    meta = Path(path).with_suffix(".json")
    if not meta.is_file():
        raise UserError(f"{meta} is missing: a ManiSkill trajectory is an .h5 file with a .json of the same name")
    episodes = json.loads(meta.read_text())["episodes"]
    return {int(e.get("episode_seed", e["reset_kwargs"].get("seed"))): e for e in episodes}


@dataclass(frozen=True)
class DemoReplayConfig:
    trajectory: str = field(help="a ManiSkill trajectory .h5 in the task's controller")
    noise_std: float = field(0.0, "std of white Gaussian noise added to the arm's entries of every action")

    def __post_init__(self):
        check_numbers(self)
        require(self.noise_std >= 0, f"--noise-std must be >= 0, got {self.noise_std}")


@register_policy("demo-replay")
class DemoReplayPolicy(Policy):
    """The demonstration of the episode's seed, action by action; after its last action, the arm holds still
    with the gripper as the demonstration left it."""

    def __init__(self, config: DemoReplayConfig | None = None, task: TaskSpec | None = None, **fields: Any):
        self.config = config or DemoReplayConfig(**fields)
        require(task is not None, "demo-replay needs the task it replays in (make_policy(..., task=env.task))")
        self.task = task
        self.episodes = trajectory_episodes(self.config.trajectory)
        self.actions = np.zeros((0, task.action_dim), np.float32)
        self.rng = np.random.default_rng(0)
        self.t = 0

    def reset(self, seed: int | None = None) -> None:
        if seed not in self.episodes:
            raise UserError(f"{self.config.trajectory} has no episode of seed {seed}")
        with h5py.File(self.config.trajectory, "r") as f:
            self.actions = f[f"traj_{self.episodes[seed]['episode_id']}"]["actions"][:].astype(np.float32)  # (T, A)
        if self.actions.shape[1] != self.task.action_dim:
            raise UserError(f"{self.config.trajectory} holds {self.actions.shape[1]}-D actions, but task "
                            f"{self.task.name} takes {self.task.action_dim}-D ones ({self.task.control_mode}); "
                            f"convert it with `wamplan data import`")
        self.rng = np.random.default_rng(seed)
        self.t = 0

    def act(self, obs: Observation) -> np.ndarray:
        if self.t < len(self.actions):
            a = self.actions[self.t].copy()  # (A,)
        else:
            a = self.task.hold_action.copy()
            if self.task.gripper_index is not None and len(self.actions):
                a[self.task.gripper_index] = self.actions[-1, self.task.gripper_index]
        self.t += 1
        if self.config.noise_std > 0:
            arm = list(self.task.arm)
            a[arm] += self.rng.normal(0.0, self.config.noise_std, len(arm)).astype(np.float32)
        return np.clip(a, -1.0, 1.0)

    def config_dict(self) -> dict[str, Any]:
        return {"name": self.name, **to_dict(self.config)}
