"""Run one episode of a policy in a :class:`TaskEnv`, rendering only when someone needs images."""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from wamplan.envs.spec import Observation, TaskSpec, check_same_task
from wamplan.envs.core import TaskEnv
from wamplan.policies.base import Policy

# Called with (env, obs, action) after the reset (action None) and after every step (the action that led to obs).
ObsHook = Callable[[TaskEnv, Observation, "np.ndarray | None"], None]


@dataclass
class EpisodeResult:
    seed: int
    success: bool
    outcome: str
    length: int  # control steps executed (first success, or the truncation limit)
    reached: dict[str, bool]
    wall_time: float
    policy_info: dict[str, Any] = field(default_factory=dict)

    def summary(self) -> dict[str, Any]:
        return dict(seed=self.seed, success=self.success, outcome=self.outcome, length=self.length,
                    wall_time=round(self.wall_time, 3), **({"policy_info": self.policy_info} if self.policy_info else {}))


def run_episode(env: TaskEnv, policy: Policy, seed: int, *, images_at: Callable[[int], bool] | None = None,
                on_obs: ObsHook | None = None, stop_on_success: bool = True,
                max_steps: int | None = None) -> EpisodeResult:
    """Roll ``policy`` out from ``env.reset(seed)``.

    Images are rendered at step t when ``policy.wants_images(t)`` or ``images_at(t)`` is true.
    The episode ends at the first success (``stop_on_success``) or at the step limit (``max_steps``,
    default the env's ``max_episode_steps``).
    A policy that names its task (``policy.task``, as WAM, planned and scripted policies do) must act in an env of
    that task: another task is one line (:class:`~wamplan.errors.TaskMismatch`) before the episode starts.
    """
    if max_steps is not None and max_steps < 1:
        raise ValueError(f"max_steps must be >= 1 (or None: the env's limit), got {max_steps}")
    check_policy(policy, "run_episode")
    check_seed(seed, "run_episode")
    task = getattr(policy, "task", None)
    if isinstance(task, TaskSpec):
        check_same_task(env.task.name, task.name, f"the policy ({type(policy).__name__})",
                        f"run it in make_env(task='{task.name}') or use a policy made for '{env.task.name}'")
    limit = env.max_episode_steps if max_steps is None else min(max_steps, env.max_episode_steps)
    t0 = time.perf_counter()
    want = (lambda t: policy.wants_images(t) or (images_at is not None and images_at(t)))
    policy.reset(seed)
    obs = env.reset(seed, with_images=want(0))
    if on_obs is not None:
        on_obs(env, obs, None)
    steps = 0
    while steps < limit:
        action = env.check_action(policy.act(obs))
        nxt, info = env.step(action, with_images=want(steps + 1))
        steps += 1
        obs = nxt
        if on_obs is not None:
            on_obs(env, obs, action)
        if stop_on_success and info["success"]:
            break
    return EpisodeResult(seed=seed, success=env.success, outcome=env.outcome(), length=steps,
                         reached=dict(env.reached), wall_time=time.perf_counter() - t0, policy_info=policy.info())


POLICY_METHODS = ("reset", "act", "wants_images", "info")  # what run_episode calls of a policy


def check_policy(policy: Any, where: str) -> None:
    """A TypeError in one line unless ``policy`` acts as a :class:`Policy` does (:data:`POLICY_METHODS`); a WAM
    (which predicts chunks, not actions) or a policy's name is told how to make one."""
    if isinstance(policy, Policy) or all(callable(getattr(policy, m, None)) for m in POLICY_METHODS):
        return
    if callable(getattr(policy, "predict", None)):
        fix = ("a WAM predicts chunks: run it open loop as WAMPolicy(wam) (wamplan.wam.base), or planned as "
               "wamplan.planned_policy(wam, world_model=...)")
    elif isinstance(policy, str):
        fix = f"build it first: wamplan.policies.make_policy({policy!r}, task=env.task)"
    else:
        fix = "pass a wamplan.policies.Policy (reset(seed), act(obs) -> (A,) action)"
    raise TypeError(f"{where}'s policy takes a wamplan Policy, got {type(policy).__name__} "
                    f"{policy!r:.60}; {fix}")


def check_seed(seed: Any, where: str) -> None:
    """A TypeError (not an integer) or ValueError (outside 0 .. 2**32 - 1, what NumPy and ManiSkill take) in one line
    naming ``where``'s seed."""
    from wamplan.errors import SEED_LIMIT

    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)):
        raise TypeError(f"{where}'s seed takes an int in 0 .. {SEED_LIMIT - 1}, got {type(seed).__name__} {seed!r}")
    if not 0 <= seed < SEED_LIMIT:
        raise ValueError(f"{where}'s seed must lie in 0 .. {SEED_LIMIT - 1}, got {seed}")
