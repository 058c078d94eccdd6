"""Build the policy a command names: a registered policy (expert, noisy-expert, pink), a WAM checkpoint
directory run open loop, or that WAM with planning in a world model (condition 7's policy, built by
``wamplan.planning.build``). It sits above the WAM and planning layers because it may load both; lower layers that
need a policy by name (``wamplan.data.collect``) take this function as an argument."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

from wamplan.config import one_checkpoint
from wamplan.errors import UserError
from wamplan.policies import POLICIES, Policy, make_policy

if TYPE_CHECKING:
    from wamplan.envs.spec import TaskSpec


def load_policy(spec: str, instruction: str | None = None, plan_with: str = "", task: TaskSpec | None = None,
                **kwargs: Any) -> Policy:
    """A registered policy name (``kwargs`` go to its constructor), or a directory holding a WAM checkpoint:
    run open loop, or with ``plan_with`` (a world model checkpoint) planned
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
    from wamplan.planning.build import plan_in_world_model
    from wamplan.planning.dynamics import task_name
    from wamplan.wam import WAMPolicy, load_wam

    if not plan_with:
        wam = load_wam(spec)
        if task is not None:
            check_same_task(task.name, task_name(wam), f"WAM {spec}")
        return WAMPolicy(wam, instruction=instruction) if instruction else WAMPolicy(wam)
    wam = load_wam(spec, device="auto")  # on the evaluation's default device, as it loads them
    if task is not None:
        check_same_task(task.name, task_name(wam), f"WAM {spec}")
    return plan_in_world_model(wam, one_checkpoint(plan_with, "--plan-with"))  # of the WAM's task
