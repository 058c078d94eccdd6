"""Pictures with the simulator's foreground masks, the training-only supervision of a foreground readout
(:mod:`wamplan.encoders.foreground`): a policy's episodes from given seeds, every ``every``-th step's pictures of the
task's cameras and, per picture, which pixels show the robot or an object rather than the table scene
(:meth:`TaskEnv.render_foreground`). Re-created from the command and seeds alone; nothing is written here."""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial
from typing import Callable, Sequence

import numpy as np

from wamplan.envs.core import TaskEnv
from wamplan.config import require
from wamplan.policies.base import Policy
from wamplan.policies.rollout import run_episode


@dataclass
class ForegroundFrames:
    """F frames of V cameras: ``images`` (F, V, H, W, 3) uint8, ``masks`` (F, V, H, W) bool, ``episode`` (F,) the
    seed each frame came from, ``cameras`` (V,) in the task's order."""

    images: np.ndarray
    masks: np.ndarray
    episode: np.ndarray
    cameras: tuple[str, ...]


def collect_foreground(env: TaskEnv, policy: Policy, seeds: Sequence[int], every: int = 4,
                       cameras: Sequence[str] | None = None,
                       progress: Callable[[int, int], None] | None = None) -> ForegroundFrames:
    """Run ``policy`` from each of ``seeds`` (to success or the step limit) and keep the pictures and foreground masks
    of ``cameras`` (default: the task's, in its order) at steps 0, ``every``, 2 ``every``, ...
    ``progress(done, total)`` is called after each episode."""
    require(every >= 1, f"every must be >= 1 (a frame every N steps), got {every}")
    cams = tuple(cameras or env.task.cameras)
    images, masks, episode = [], [], []

    def keep(seed: int, env: TaskEnv, obs, action) -> None:
        if obs.step % every == 0:
            pics, fg = env.render_foreground(cams)
            images.append(np.stack([pics[c] for c in cams]))  # (V, H, W, 3)
            masks.append(np.stack([fg[c] for c in cams]))  # (V, H, W)
            episode.append(seed)

    for i, seed in enumerate(seeds):
        run_episode(env, policy, seed, on_obs=partial(keep, seed))
        if progress is not None:
            progress(i + 1, len(seeds))
    return ForegroundFrames(np.stack(images), np.stack(masks), np.array(episode), tuple(cams))
