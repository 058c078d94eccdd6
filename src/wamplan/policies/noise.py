"""Exploration policies: the noisy expert and the pink-noise explorer.

Both draw all their randomness from ``reset(seed)``, so an episode is reproducible from its seed.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import colorednoise
import numpy as np

from wamplan.config import field, require, to_dict
from wamplan.envs.contract import ACTION_DIM, ARM, GRIPPER_INDEX, Observation
from wamplan.policies.base import Policy, register_policy
from wamplan.policies.expert import ExpertConfig, ExpertPolicy


@dataclass(frozen=True)
class NoisyExpertConfig:
    noise_std: float = field(0.2, "std of the Gaussian noise added to the arm dims (normalised units)")
    gripper_flip_prob: float = field(0.0, "probability per step of inverting the gripper command")
    seed_offset: int = field(1_000_003, "added to the episode seed for the noise stream")

    def __post_init__(self):
        require(self.noise_std >= 0, f"noise_std must be >= 0, got {self.noise_std}")
        require(0 <= self.gripper_flip_prob <= 1, f"gripper_flip_prob must be in [0, 1], got {self.gripper_flip_prob}")


@register_policy("noisy-expert")
class NoisyExpertPolicy(Policy):
    """The scripted expert plus white Gaussian noise on (dx, dy, dz, dyaw); the expert re-plans from
    the true state every step, so the noise produces off-nominal but mostly recoverable states."""

    def __init__(self, config: NoisyExpertConfig | None = None, expert: ExpertConfig | None = None):
        self.config = config or NoisyExpertConfig()
        self.expert = ExpertPolicy(expert)
        self.rng = np.random.default_rng(0)

    def reset(self, seed: int | None = None) -> None:
        self.expert.reset(seed)
        self.rng = np.random.default_rng(None if seed is None else seed + self.config.seed_offset)

    def act(self, obs: Observation) -> np.ndarray:
        a = self.expert.act(obs).copy()
        a[ARM] += self.rng.normal(0.0, self.config.noise_std, GRIPPER_INDEX)  # (4,) the arm's entries
        if self.rng.random() < self.config.gripper_flip_prob:
            a[GRIPPER_INDEX] = -a[GRIPPER_INDEX]
        return np.clip(a, -1, 1).astype(np.float32)

    def config_dict(self) -> dict[str, Any]:
        return {"name": self.name, **to_dict(self.config), "expert": to_dict(self.expert.config)}


@dataclass(frozen=True)
class PinkNoiseConfig:
    scale: float = field(0.6, "std of the pink noise on the arm dims (normalised units)")
    exponent: float = field(1.0, "power-law exponent beta of the 1/f^beta noise (1 = pink)")
    down_bias: float = field(0.15, "constant downward push on dz, so the gripper reaches the table and cube")
    horizon: int = field(300, "length of the pre-drawn noise sequence (>= episode length)")
    seed_offset: int = field(2_000_003, "added to the episode seed for the noise stream")

    def __post_init__(self):
        require(self.scale >= 0, f"scale must be >= 0, got {self.scale}")
        require(self.horizon > 0, f"horizon must be > 0, got {self.horizon}")


@register_policy("pink")
class PinkNoisePolicy(Policy):
    """Temporally correlated 1/f (pink) action noise on all five dims; the gripper command is the
    sign of its own pink-noise channel, so it opens and closes now and then, not every step."""

    def __init__(self, config: PinkNoiseConfig | None = None):
        self.config = config or PinkNoiseConfig()
        self.noise = np.zeros((self.config.horizon, ACTION_DIM), np.float32)

    def reset(self, seed: int | None = None) -> None:
        c = self.config
        rng = np.random.default_rng(None if seed is None else seed + c.seed_offset)
        n = colorednoise.powerlaw_psd_gaussian(c.exponent, (ACTION_DIM, c.horizon), random_state=rng)  # (5, T)
        a = n.T * c.scale  # (T, 5)
        a[:, 2] -= c.down_bias
        a[:, GRIPPER_INDEX] = np.sign(n[GRIPPER_INDEX]) + (n[GRIPPER_INDEX] == 0)
        self.noise = np.clip(a, -1, 1).astype(np.float32)

    def act(self, obs: Observation) -> np.ndarray:
        return self.noise[min(obs.step, len(self.noise) - 1)].copy()

    def config_dict(self) -> dict[str, Any]:
        return {"name": self.name, **to_dict(self.config)}
