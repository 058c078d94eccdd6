"""wamplan's Python API: load a WAM and a world model, plan a chunk, run an episode with planning.

    import wamplan
    wam = wamplan.load_wam("checkpoints/mini/tinywam")
    policy = wamplan.planned_policy(wam, world_model="checkpoints/mini/wm_augmented")
    env = wamplan.make_env(task=wam.task.name)
    obs = env.reset(seed=0, with_images=True)
    decision = policy.plan_chunk(obs)      # ChunkDecision: .executed (H, A), .reason, .costs
    result = wamplan.run_episode(env, policy, seed=0)

The tasks: ``wamplan.tasks()`` names the registered ones, ``wamplan.get_task(name)`` is one's
:class:`TaskSpec` (cameras, action and proprio sizes, ...), ``wamplan.register_task(spec)`` adds one.

Every name of ``__all__`` is also an attribute of ``wamplan`` itself, imported on first use (so that
``import wamplan`` and the command line stay fast). The settings and their defaults are the evaluation's
(``wamplan eval``, condition 7): one factory (``wamplan.planning.build``) builds the policy for both; the planned
policy plans for its WAM's task, and refuses a world model made for another.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from wamplan.config import from_dict, one_checkpoint
from wamplan.errors import require_paths
from wamplan.envs.spec import TASKS, Observation, TaskSpec, get_task, register_task
from wamplan.envs.config import EnvConfig
from wamplan.envs.core import TaskEnv
from wamplan.planning import CostConfig
from wamplan.planning.build import PlanningConfig, plan_in_world_model
from wamplan.planning.configs import DEFAULT_PLANNER
from wamplan.planning.decision import ChunkDecision
from wamplan.planning.policy import PlannedPolicy
from wamplan.planning.policy_config import PlannedPolicyConfig
from wamplan.policies.base import Policy
from wamplan.policies.rollout import EpisodeResult
from wamplan.policies.rollout import run_episode as _run_episode
from wamplan.wam.base import WAM, WAMOutput, WAMPolicy, load_wam

__all__ = ["ChunkDecision", "CostConfig", "EpisodeResult", "Observation", "PlannedPolicy", "PlannedPolicyConfig", "TaskSpec", "WAM",
           "WAMOutput", "get_task", "load_wam", "make_env", "planned_policy", "register_task", "run_episode", "tasks"]


def planned_policy(wam: WAM | str | Path, world_model: str | Path, *,
                   planner: str | None = None, planner_config: Any = None,
                   cost: CostConfig | str | dict[str, Any] | None = None,
                   device: str = "auto", **settings: Any) -> PlannedPolicy:
    """``wam`` (a :class:`WAM`, or its checkpoint directory) whose chunks are planned in ``world_model`` (a
    checkpoint directory), as ``wamplan eval`` plans condition 7.

    ``planner``: a registered planner name (``wamplan.planning.PLANNERS``; default: the evaluation's);
    ``planner_config``: its config, or a dict of overrides of its fields; ``cost``: a :class:`CostConfig`, a cost
    name (``"patch"``, ``"cls"``) or a dict of its fields (e.g. ``{"view_weights": (0, 0, 1)}``);
    ``settings``: fields of :class:`PlannedPolicyConfig` (e.g. ``first_chunk="rest-history"``). The models go
    to ``device`` ("auto", "cpu", "cuda", ...). The policy acts on :class:`Observation` s with (H, W, 3) uint8
    views and returns (A,) actions of the WAM's task; ``policy.plan_chunk(obs)`` decides one chunk ->
    :class:`ChunkDecision`.
    """
    if not isinstance(world_model, (str, Path)):
        many = " (several world models, an ensemble, are no longer planned in: it measured no gain)" \
            if isinstance(world_model, (list, tuple)) else ""
        raise TypeError(f"world_model must be a checkpoint directory (a str or Path), got "
                        f"{type(world_model).__name__}{many}; pass e.g. world_model='checkpoints/mini/wm_augmented'")
    path = one_checkpoint(str(world_model), "world_model")
    if isinstance(cost, str):
        cost = CostConfig(name=cost)
    elif isinstance(cost, dict):
        cost = from_dict(CostConfig, cost)
    elif cost is not None and not isinstance(cost, CostConfig):
        raise TypeError(f"cost is of type {type(cost).__name__}; pass a CostConfig, a cost name ('patch', 'cls') or a "
                        f"dict of CostConfig's fields")
    planning = PlanningConfig(DEFAULT_PLANNER if planner is None else planner, planner_config, cost or CostConfig(),
                              from_dict(PlannedPolicyConfig, settings))
    require_paths([path], "world_model", "pass a world model checkpoint (from `wamplan wm train`)")
    return plan_in_world_model(wam, path, planning, device=device)


def make_env(task: str = "cube-insertion", **settings: Any) -> TaskEnv:
    """The registered ``task`` (see :func:`tasks`), rendered on the CPU; ``settings``: the other fields of
    ``EnvConfig`` (e.g. ``camera_size=224``, ``max_episode_steps=300``). ``env.task`` is its :class:`TaskSpec`;
    ``env.reset(seed, with_images=True)`` -> :class:`Observation` (proprio (P,), images camera -> (S, S, 3)
    uint8); ``env.step(action (A,))`` -> (observation, info)."""
    return TaskEnv(from_dict(EnvConfig, dict(settings, task=task)))


def run_episode(env: TaskEnv, policy: Policy | WAM, seed: int, **options: Any) -> EpisodeResult:
    """Roll ``policy`` out from ``env.reset(seed)`` to success or the step limit -> :class:`EpisodeResult`; a
    :class:`WAM` runs open loop, each chunk executed whole (``WAMPolicy``). ``options``: ``max_steps``,
    ``images_at``, ``on_obs``, ``stop_on_success`` (``wamplan.policies.rollout.run_episode``). A policy that is
    none, or a seed outside 0 .. 2**32 - 1, is one TypeError or ValueError naming it."""
    if isinstance(policy, WAM):
        policy = WAMPolicy(policy, task=env.task)
    return _run_episode(env, policy, seed, **options)


def tasks() -> list[str]:
    """The names of the registered tasks (``make_env(task=...)``, ``--task``), sorted."""
    return sorted(TASKS)
