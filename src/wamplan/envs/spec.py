"""A task, as everything above the env layer sees it: :class:`TaskSpec`, and the registry of tasks, ``TASKS``.

A spec says what a task shows a policy (cameras, proprioception), what it accepts (the action vector: its size,
which entry is the gripper, what "hold still" is), how long its episodes and chunks are, and how an episode is
judged (success from the env's own ``evaluate()``; optional stage flags and the outcomes they name). Models,
stores and planners take their dimensions from a spec or from the checkpoint they load, never from constants.

Actions are the task controller's normalised actions, every entry in [-1, 1] (ManiSkill's delta controllers:
``pd_ee_delta_pose``, ``pd_joint_delta_pos``, and the cube task's ``pd_ee_delta_xyzyaw``); the env refuses a
controller whose action space is not that box.

This module imports neither ManiSkill nor torch. How an env reads a spec's proprioception, stages and privileged
state from ManiSkill lives in the spec's ``adapter`` (a ``module:Class`` path, imported by the env).
"""

from __future__ import annotations

from dataclasses import dataclass, field as dc_field
from typing import Any

import numpy as np

from wamplan.config import field, require
from wamplan.errors import UserError
from wamplan.registry import Registry

@dataclass
class Observation:
    """What a policy sees at control step ``step`` (any task)."""

    step: int
    proprio: np.ndarray  # (P,) float32: the task's proprioception (TaskSpec.proprio_dim)
    images: dict[str, np.ndarray] | None = None  # camera -> (H, W, 3) uint8; None if not rendered
    state: dict[str, np.ndarray] = dc_field(default_factory=dict)  # privileged sim state (experts only)


DEFAULT_TASK = "cube-insertion"  # the task of whatever records none (stores, checkpoints, configs made before tasks)

PLUGIN_GROUP = "wamplan.tasks"  # the entry-point group of task plug-ins: each names a module that registers tasks
TASKS = Registry("task", modules=("wamplan.envs.contract", "wamplan.envs.maniskill"), group=PLUGIN_GROUP)


@dataclass(frozen=True)
class TaskSpec:
    name: str = field(help="the registry name, e.g. cube-insertion")
    env_id: str = field(help="the gymnasium / ManiSkill env id, e.g. CubeInsertion-v1")
    cameras: tuple[str, ...] = field(help="the sensors a policy sees, in the order models stack their views")
    action_dim: int = field(help="A, the size of one action (the controller's normalised action)")
    proprio_dim: int = field(help="P, the size of the proprioception vector")
    control_mode: str = field(help="ManiSkill's controller name")
    max_episode_steps: int = field(help="episodes truncate after this many control steps")
    instruction: str = field(help="what the task asks for, in words (a WAM's text prompt)")
    adapter: str = field(help="module:Class reading proprio, stages and state from the ManiSkill env")
    gripper_index: int | None = field(None, "the gripper's entry of an action (None: no gripper)")
    gripper_open: float = field(1.0, "the gripper command that opens")
    gripper_closed: float = field(-1.0, "the gripper command that closes")
    chunk_len: int = field(16, "actions a WAM predicts per query (its chunk)")
    sigma_scale: tuple[float, ...] = field(
        (), "per action entry (length A), the planners' factor on their sampling sigma, so that one sigma moves "
        "the robot about as far on every task: the unit is cube-insertion's controller (2 cm and 0.1 rad a step "
        "per unit action); ManiSkill's pd_ee_delta_pose moves 10 cm a unit, hence 0.2 on its translation. "
        "() = 1 everywhere")
    stages: tuple[str, ...] = field((), "boolean entries of evaluate() tracked per episode, in task order")
    outcomes: tuple[tuple[str, str], ...] = field(
        (), "(stage, outcome) pairs, furthest stage first: a failed episode's outcome is that of the furthest "
            "stage it reached")
    failure: str = field("failure", "the outcome of a failed episode that reached none of the outcome stages")
    metrics: tuple[str, ...] = field((), "continuous entries of evaluate() recorded every step")
    env_kwargs: tuple[tuple[str, Any], ...] = field((), "extra gym.make keyword arguments, as (name, value) pairs")
    config_kwargs: tuple[str, ...] = field((), "EnvConfig fields the task's env takes as gym.make keyword arguments")
    expert: str | None = field(None, "the registered policy that solves the task from privileged state, if any")
    demonstrations: str | None = field(None, "where demonstrations come from when there is no scripted expert: "
                                             "'maniskill-motion-planning' (ManiSkill's solver, scripts/maniskill_demos.sh)")
    params: tuple[tuple[str, float], ...] = field((), "named task constants diagnostics may read, as (name, value) "
                                                      "pairs (the cube's align_xy_tol, say)")

    def __post_init__(self):
        require(self.action_dim > 0 and self.proprio_dim > 0, f"task {self.name}: action_dim and proprio_dim "
                                                              f"must be > 0")
        require(len(self.cameras) > 0 and len(set(self.cameras)) == len(self.cameras),
                f"task {self.name}: cameras must be distinct names, got {list(self.cameras)}")
        require(self.gripper_index is None or 0 <= self.gripper_index < self.action_dim,
                f"task {self.name}: gripper_index {self.gripper_index} is not an entry of a {self.action_dim}-D "
                f"action")
        require(all(s in self.stages for s, _ in self.outcomes),
                f"task {self.name}: every outcome stage must be one of its stages {list(self.stages)}")
        require(not self.sigma_scale or (len(self.sigma_scale) == self.action_dim and min(self.sigma_scale) > 0),
                f"task {self.name}: sigma_scale needs {self.action_dim} entries > 0 (one per action entry), got "
                f"{list(self.sigma_scale)}")
        require(self.chunk_len > 0 and self.max_episode_steps > 0, f"task {self.name}: chunk_len and "
                                                                   f"max_episode_steps must be > 0")

    def param(self, name: str, default: float | None = None) -> float | None:
        """The task constant ``name`` of ``params`` (``default`` where the task has none)."""
        return dict(self.params).get(name, default)

    @property
    def arm(self) -> tuple[int, ...]:
        """The action entries that move the arm (every entry but the gripper)."""
        return tuple(i for i in range(self.action_dim) if i != self.gripper_index)

    @property
    def hold_action(self) -> np.ndarray:
        """(A,) float32: the arm still, the gripper open."""
        a = np.zeros(self.action_dim, np.float32)
        if self.gripper_index is not None:
            a[self.gripper_index] = self.gripper_open
        a.setflags(write=False)
        return a

    @property
    def outcome_names(self) -> tuple[str, ...]:
        """Every outcome an episode can end with, in report order: success, then failures from the earliest."""
        return ("success", self.failure, *(o for _, o in reversed(self.outcomes)))

    def outcome(self, success: bool, reached: dict[str, bool]) -> str:
        """The outcome of an episode that ended with ``success`` having reached the stages ``reached``."""
        if success:
            return "success"
        return next((o for s, o in self.outcomes if reached.get(s)), self.failure)

    def describe(self) -> dict[str, Any]:
        """What stores and checkpoints record of their task (and compare on use)."""
        return dict(task=self.name, env_id=self.env_id, cameras=list(self.cameras), action_dim=self.action_dim,
                    proprio_dim=self.proprio_dim, control_mode=self.control_mode)


def register_task(spec: TaskSpec) -> TaskSpec:
    """Add ``spec`` to ``TASKS`` under its name (a plug-in's module calls this when imported; an installed
    distribution names that module in the entry-point group ``wamplan.tasks``)."""
    if not isinstance(spec, TaskSpec):
        hint = f"; a registered task's spec is get_task({spec!r})" if isinstance(spec, str) else ""
        raise TypeError(f"register_task takes a TaskSpec (TaskSpec(name=..., cameras=..., ...)), got "
                        f"{type(spec).__name__} {spec!r}{hint}")
    TASKS.register(spec.name)(spec)
    return spec


def get_task(task: "str | TaskSpec") -> TaskSpec:
    """The registered spec called ``task`` (a spec passes through); one line listing the choices otherwise."""
    return task if isinstance(task, TaskSpec) else TASKS.lookup(task)


def check_same_task(expected: str, found: str | None, what: str, fix: str | None = None) -> None:
    """One line (a :class:`~wamplan.errors.TaskMismatch`) when ``what`` (a store, a checkpoint) was made for
    another task than the one in use; ``fix`` says what to do (default: the command line's ``--task``)."""
    from wamplan.errors import TaskMismatch

    if found is not None and found != expected:
        fix = fix or f"pass --task {found} or use a {what.split()[0]} made for '{expected}'"
        raise TaskMismatch(f"{what} was made for task '{found}', but this run uses task '{expected}'; {fix}")


class ObservationError(UserError, ValueError):
    """An observation lacks what its consumer needs (a camera's image, or pixels of the wrong kind)."""


def require_images(obs: Observation, cameras: Any, where: str) -> None:
    """An :class:`ObservationError` in one line unless ``obs.images`` holds an (H, W, 3) uint8 array for every camera
    of ``cameras`` (floats in [0, 1] or wider integers would otherwise be cast to bytes silently), all of one size
    (H, W) (they are stacked into one batch)."""
    images = obs.images or {}
    missing = [c for c in cameras if c not in images]
    if missing:
        raise ObservationError(f"{where}: the observation at step {obs.step} has no image for {missing} (has "
                               f"{sorted(images)}); give one for each of {list(cameras)}")
    for cam in cameras:
        img = images[cam]
        if not (isinstance(img, np.ndarray) and img.ndim == 3 and img.shape[2] == 3 and img.dtype == np.uint8):
            kind = (f"{img.dtype} of shape {img.shape}" if isinstance(img, np.ndarray) else type(img).__name__)
            raise ObservationError(f"{where}: the '{cam}' image is {kind}; give (H, W, 3) uint8 pixels 0-255 (floats "
                                   f"in [0, 1]: (img * 255).round().astype(np.uint8))")
    sizes = {cam: images[cam].shape[:2] for cam in cameras}
    first = next(iter(sizes), None)
    odd = next((cam for cam, hw in sizes.items() if hw != sizes[first]), None)
    if odd is not None:  # the views are stacked into one batch: one size for all
        raise ObservationError(f"{where}: the '{odd}' image is {'x'.join(map(str, sizes[odd]))} pixels but the "
                               f"'{first}' image is {'x'.join(map(str, sizes[first]))}; give every camera's image the "
                               f"same size (H, W)")


def require_observation(obs: Any, where: str) -> None:
    """A TypeError in one line unless ``obs`` is an :class:`Observation` (what every policy acts on)."""
    if not isinstance(obs, Observation):
        raise TypeError(f"{where} takes a wamplan.Observation, got a {type(obs).__name__}; take one from "
                        f"env.reset(seed, with_images=True) or env.step(action), or build one: "
                        f"Observation(step=t, proprio=(P,) float32, images={{camera: (H, W, 3) uint8}})")
