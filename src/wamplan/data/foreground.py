"""Pictures with the simulator's segmentation, the training-only supervision of the ``object-masks`` encoder
(:mod:`wamplan.encoders.object_masks`): a policy's episodes from given seeds, every
``every``-th step's pictures of the task's cameras and, per pixel, which class it shows (the table scene, the robot,
each task object; :meth:`TaskEnv.render_segmentation`). Re-created from the command and seeds alone;
:func:`save_frames` and :func:`load_frames` keep one collection for several fits."""

from __future__ import annotations

import os
import zipfile

from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from wamplan.envs.core import TaskEnv
from wamplan.config import require
from wamplan.errors import UserError
from wamplan.policies.base import Policy
from wamplan.policies.rollout import run_episode


@dataclass
class ForegroundFrames:
    """F frames of V cameras: ``images`` (F, V, H, W, 3) uint8, ``labels`` (F, V, H, W) uint8 the class of each
    pixel (an index into ``classes``, 0 the background), ``episode`` (F,) the seed each frame came from, ``cameras``
    (V,) in the task's order, ``classes`` (C,) the class names, ``task`` the task's name ("" where unrecorded)."""

    images: np.ndarray
    labels: np.ndarray
    episode: np.ndarray
    cameras: tuple[str, ...]
    classes: tuple[str, ...] = ("background", "foreground")
    task: str = ""

    @property
    def masks(self) -> np.ndarray:
        """(F, V, H, W) bool: the pixels that show the robot or an object."""
        return self.labels > 0


def collect_foreground(env: TaskEnv, policy: Policy, seeds: Sequence[int], every: int = 4,
                       cameras: Sequence[str] | None = None,
                       progress: Callable[[int, int], None] | None = None) -> ForegroundFrames:
    """Run ``policy`` from each of ``seeds`` (to success or the step limit) and keep the pictures and segmentation
    of ``cameras`` (default: the task's, in its order) at steps 0, ``every``, 2 ``every``, ...
    ``progress(done, total)`` is called after each episode."""
    require(every >= 1, f"every must be >= 1 (a frame every N steps), got {every}")
    cams = tuple(cameras or env.task.cameras)
    images, labels, episode, classes = [], [], [], [()]

    def keep(seed: int, env: TaskEnv, obs, action) -> None:
        if obs.step % every == 0:
            pics, lab, names = env.render_segmentation(cams)
            if classes[0] and names != classes[0]:
                raise UserError(f"seed {seed} shows the classes {names}, earlier seeds {classes[0]}: a task whose "
                                f"objects change between episodes has no fixed classes to learn")
            classes[0] = names
            images.append(np.stack([pics[c] for c in cams]))  # (V, H, W, 3)
            labels.append(np.stack([lab[c] for c in cams]))  # (V, H, W)
            episode.append(seed)

    for i, seed in enumerate(seeds):
        run_episode(env, policy, seed, on_obs=partial(keep, seed))
        if progress is not None:
            progress(i + 1, len(seeds))
    return ForegroundFrames(np.stack(images), np.stack(labels), np.array(episode), tuple(cams), tuple(classes[0]),
                            env.task.name)


def require_frames_path(path: str | Path) -> Path:
    """``path`` as a Path; one line unless it names a ``.npz`` file (numpy adds the suffix otherwise, and the next
    run would not find the file)."""
    path = Path(path)
    require(path.suffix == ".npz", f"{path}: a frames file is named *.npz (numpy adds the suffix otherwise, and the "
                                   f"next run would not find it); pass e.g. {path.with_suffix('.npz')}")
    return path


def save_frames(frames: ForegroundFrames, path: str | Path) -> Path:
    """Write ``frames`` to one ``.npz`` file ``path`` (uncompressed: pictures are read back whole), whole or not at
    all (a temporary file renamed)."""
    path = require_frames_path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".partial")
    with open(tmp, "wb") as f:
        np.savez(f, images=frames.images, labels=frames.labels, episode=frames.episode,
                 cameras=np.array(frames.cameras), classes=np.array(frames.classes), task=np.array(frames.task))
    os.replace(tmp, path)
    return path


def load_frames(path: str | Path) -> ForegroundFrames:
    """The frames :func:`save_frames` wrote to ``path``; one line if it is not such a file."""
    try:
        with np.load(path) as z:
            return ForegroundFrames(z["images"], z["labels"], z["episode"], tuple(str(c) for c in z["cameras"]),
                                    tuple(str(c) for c in z["classes"]), str(z["task"]) if "task" in z else "")
    except (OSError, KeyError, ValueError, EOFError, zipfile.BadZipFile) as e:
        raise UserError(f"{path} is not a frames file written by `wamplan wm train-masks --frames` ({e}); pass "
                        f"another path or remove it to collect again") from None
