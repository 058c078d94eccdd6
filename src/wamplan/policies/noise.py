"""Exploration policies: the noisy expert and the pink-noise explorer.

Both draw all their randomness from ``reset(seed)``, so an episode is reproducible from its seed. Both read the
action's layout from their task (``task``, a :class:`~wamplan.envs.spec.TaskSpec`; default: the cube task): its
size, the arm's entries and the gripper's. The pink-noise explorer acts in any task; the noisy expert wraps the
scripted expert, so it acts where that does.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import colorednoise
import numpy as np

from wamplan.config import check_numbers, field, require, to_dict
from wamplan.envs.spec import Observation, TaskSpec
from wamplan.policies.base import Policy, policy_task, register_policy
from wamplan.policies.expert import ExpertConfig, ExpertPolicy


@dataclass(frozen=True)
class NoisyExpertConfig:
    noise_std: float = field(0.2, "std of the Gaussian noise added to the arm dims (normalised units)")
    gripper_flip_prob: float = field(0.0, "probability per step of inverting the gripper command")
    seed_offset: int = field(1_000_003, "added to the episode seed for the noise stream")

    def __post_init__(self):
        check_numbers(self)
        require(self.noise_std >= 0, f"noise_std must be >= 0, got {self.noise_std}")
        require(0 <= self.gripper_flip_prob <= 1, f"gripper_flip_prob must be in [0, 1], got {self.gripper_flip_prob}")


@register_policy("noisy-expert")
class NoisyExpertPolicy(Policy):
    """The scripted expert plus white Gaussian noise on the arm's entries (the cube's dx, dy, dz, dyaw); the
    expert re-plans from the true state every step, so the noise produces off-nominal but mostly recoverable
    states."""

    def __init__(self, config: NoisyExpertConfig | None = None, expert: ExpertConfig | None = None,
                 task: TaskSpec | None = None):
        self.config = config or NoisyExpertConfig()
        self.expert = ExpertPolicy(expert, task=task)
        self.task = self.expert.task
        self.arm = list(self.task.arm)
        self.rng = np.random.default_rng(0)

    def reset(self, seed: int | None = None) -> None:
        self.expert.reset(seed)
        self.rng = np.random.default_rng(None if seed is None else seed + self.config.seed_offset)

    def act(self, obs: Observation) -> np.ndarray:
        a = self.expert.act(obs).copy()  # (A,)
        a[self.arm] += self.rng.normal(0.0, self.config.noise_std, len(self.arm))  # the arm's entries
        g = self.task.gripper_index
        if self.rng.random() < self.config.gripper_flip_prob and g is not None:
            a[g] = -a[g]
        return np.clip(a, -1, 1).astype(np.float32)

    def config_dict(self) -> dict[str, Any]:
        return {"name": self.name, **to_dict(self.config), "expert": to_dict(self.expert.config)}


EE_DELTA = ("pd_ee_delta", "pd_ee_target_delta")  # controllers whose action starts (dx, dy, dz, ...)


@dataclass(frozen=True)
class PinkNoiseConfig:
    scale: float = field(0.6, "std of the pink noise on the arm dims (normalised units)")
    exponent: float = field(1.0, "power-law exponent beta of the 1/f^beta noise (1 = pink)")
    down_bias: float = field(0.15, "constant downward push on dz (end-effector delta controllers), so the gripper "
                                   "reaches the table and the objects on it")
    horizon: int | None = field(None, "length of the pre-drawn noise sequence (>= episode length; default: the "
                                      "task's max_episode_steps)")
    seed_offset: int = field(2_000_003, "added to the episode seed for the noise stream")

    def __post_init__(self):
        check_numbers(self)
        require(self.scale >= 0, f"scale must be >= 0, got {self.scale}")
        require(self.horizon is None or self.horizon > 0, f"horizon must be > 0, got {self.horizon}")


@register_policy("pink")
class PinkNoisePolicy(Policy):
    """Temporally correlated 1/f (pink) action noise on every entry of the task's action; the gripper command
    (where the task has a gripper) is open or closed by the sign of its own pink-noise channel, so it opens and
    closes now and then, not every step."""

    def __init__(self, config: PinkNoiseConfig | None = None, task: TaskSpec | None = None):
        self.task = policy_task(task)
        c = config or PinkNoiseConfig()
        self.config = replace(c, horizon=c.horizon or self.task.max_episode_steps)
        self.dz = 2 if self.task.control_mode.startswith(EE_DELTA) else None  # the action's dz entry, if any
        self.noise = np.zeros((self.config.horizon, self.task.action_dim), np.float32)

    def reset(self, seed: int | None = None) -> None:
        c, task = self.config, self.task
        rng = np.random.default_rng(None if seed is None else seed + c.seed_offset)
        n = colorednoise.powerlaw_psd_gaussian(c.exponent, (task.action_dim, c.horizon), random_state=rng)  # (A, T)
        a = n.T * c.scale  # (T, A)
        if self.dz is not None:
            a[:, self.dz] -= c.down_bias
        if (g := task.gripper_index) is not None:
            a[:, g] = np.where(n[g] >= 0, task.gripper_open, task.gripper_closed)
        self.noise = np.clip(a, -1, 1).astype(np.float32)

    def act(self, obs: Observation) -> np.ndarray:
        return self.noise[min(obs.step, len(self.noise) - 1)].copy()

    def config_dict(self) -> dict[str, Any]:
        return {"name": self.name, **to_dict(self.config)}
