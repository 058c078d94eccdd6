"""Build the policy a command names: a registered policy (expert, noisy-expert, pink), a WAM checkpoint
directory run open loop, or that WAM with planning in a world model (condition 7's policy). It sits above
the WAM and planning layers because it may load both; lower layers that need a policy by name
(``wamplan.data.collect``) take this function as an argument."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any, Sequence

from wamplan.config import ensemble_members
from wamplan.errors import UserError
from wamplan.policies import POLICIES, Policy, make_policy

if TYPE_CHECKING:
    from wamplan.envs.spec import TaskSpec
    from wamplan.evaluation.config import EvalConfig
    from wamplan.planning.dynamics import Dynamics
    from wamplan.planning.policy import PlannedPolicy
    from wamplan.wam.base import WAM


def planned_policy(cfg: EvalConfig, wam: WAM, dynamics: Dynamics, encoder: Any, target_wam: WAM | None = None,
                   world_models: Sequence[str] = ()) -> PlannedPolicy:
    """``wam`` refined by planning in ``dynamics`` with the planner, cost and chunk rules of ``cfg``: the one
    place the evaluation, the planned collection and the Python API build a planned policy.
    ``world_models``: the checkpoints behind ``dynamics``, recorded resolved (none for the simulator)."""
    from wamplan.planning import make_planner
    from wamplan.planning.costs import build_cost
    from wamplan.planning.policy import PlannedPolicy

    weigh = None
    if cfg.cost.foreground:  # the readout reads the target's tokens: it must be fit on this encoder
        from wamplan.encoders.foreground import foreground_weigher

        weigh = foreground_weigher(cfg.cost.foreground, encoder, cfg.cost.background_weight, wam.task.name,
                                   dynamics.cameras or wam.task.cameras)
    cost = build_cost(cfg.cost, getattr(dynamics, "read_state", None), weigh)  # the pose term reads the state head
    return PlannedPolicy(wam, make_planner(cfg.planner, cfg.planner_config), dynamics, encoder, cost,
                         target_wam=target_wam, config=cfg.policy,
                         world_models=tuple(str(Path(p).resolve()) for p in world_models))


def plan_in_world_model(cfg: EvalConfig, wam: WAM | str, paths: Sequence[str]) -> PlannedPolicy:
    """``wam`` (a WAM, or its checkpoint directory) planned in the world model checkpoints ``paths`` (several:
    an ensemble), every model loaded onto ``cfg.device``, as condition 7 plans with ``cfg``."""
    from wamplan.planning.dynamics import learned_dynamics
    from wamplan.wam import load_wam
    from wamplan.worldmodel.load import load_world_model

    dyn, enc = learned_dynamics([load_world_model(p, device=cfg.device, dtype=cfg.wm_dtype) for p in paths])
    wam = load_wam(wam, device=cfg.device) if isinstance(wam, (str, Path)) else wam
    return planned_policy(cfg, wam, dyn, enc, world_models=paths)


def load_policy(spec: str, instruction: str | None = None, plan_with: str = "", task: TaskSpec | None = None,
                **kwargs: Any) -> Policy:
    """A registered policy name (``kwargs`` go to its constructor), or a directory holding a WAM checkpoint:
    run open loop, or with ``plan_with`` (world model checkpoints, an ensemble's joined by + or commas) planned
    as condition 7 plans it, at the evaluation's default planner, cost and chunk rules. ``task``: the task the
    policy acts in; a registered policy is built for it, a WAM must have been made for it (one line otherwise)."""
    if spec in POLICIES:
        if plan_with:
            raise UserError(f"--plan-with plans a WAM's chunks; '{spec}' is a scripted policy, pass a WAM checkpoint")
        return make_policy(spec, task=task, **kwargs)
    if kwargs:
        raise UserError(f"settings {sorted(kwargs)} are for the registered policies, not for '{spec}'")
    if not Path(spec).is_dir():
        raise UserError(f"unknown policy '{spec}': choose one of {sorted(POLICIES)} or pass a WAM checkpoint directory")
    from wamplan.envs.spec import check_same_task
    from wamplan.planning.dynamics import task_name
    from wamplan.wam import WAMPolicy, load_wam

    if not plan_with:
        wam = load_wam(spec)
        if task is not None:
            check_same_task(task.name, task_name(wam), f"WAM {spec}")
        return WAMPolicy(wam, instruction=instruction) if instruction else WAMPolicy(wam)
    from wamplan.evaluation.config import EvalConfig

    cfg = EvalConfig(wam=spec, wm_augmented=plan_with)  # on cfg.device, as the evaluation loads them
    wam = load_wam(spec, device=cfg.device)
    if task is not None:
        check_same_task(task.name, task_name(wam), f"WAM {spec}")
    return plan_in_world_model(cfg, wam, ensemble_members(plan_with))  # the world models must match the WAM's task
