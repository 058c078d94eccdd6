"""Build the policy a command names: a registered policy (expert, noisy-expert, pink), a WAM checkpoint
directory run open loop, or that WAM with planning in a world model (condition 7's policy). It sits above
the WAM and planning layers because it may load both; lower layers that need a policy by name
(``wamplan.data.collect``) take this function as an argument."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Sequence

from wamplan.errors import UserError
from wamplan.policies import POLICIES, Policy, make_policy


def planned_policy(cfg: Any, wam: Any, dynamics: Any, encoder: Any, target_wam: Any = None,
                   world_models: Sequence[str] = ()) -> Policy:
    """``wam`` refined by planning in ``dynamics`` with the planner, cost and chunk rules of ``cfg`` (an
    ``EvalConfig``): the one place the evaluation and the planned collection build a planned policy.
    ``world_models``: the checkpoints behind ``dynamics``, recorded resolved (none for the simulator)."""
    from wamplan.planning import make_planner
    from wamplan.planning.policy import PlannedPolicy

    return PlannedPolicy(wam, make_planner(cfg.planner, cfg.planner_config), dynamics, encoder, cfg.cost.build(),
                         target_wam=target_wam, config=cfg.policy,
                         world_models=tuple(str(Path(p).resolve()) for p in world_models))


def load_policy(spec: str, instruction: str | None = None, plan_with: str = "", **kwargs: Any) -> Policy:
    """A registered policy name (``kwargs`` go to its constructor), or a directory holding a WAM checkpoint:
    run open loop, or with ``plan_with`` (world model checkpoints, comma-separated for an ensemble) planned
    as condition 7 plans it, at the evaluation's default planner, cost and chunk rules."""
    if spec in POLICIES:
        if plan_with:
            raise UserError(f"--plan-with plans a WAM's chunks; '{spec}' is a scripted policy, pass a WAM checkpoint")
        return make_policy(spec, **kwargs)
    if kwargs:
        raise UserError(f"settings {sorted(kwargs)} are for the registered policies, not for '{spec}'")
    if not Path(spec).is_dir():
        raise UserError(f"unknown policy '{spec}': choose one of {sorted(POLICIES)} or pass a WAM checkpoint directory")
    from wamplan.wam import WAMPolicy, load_wam

    if not plan_with:
        wam = load_wam(spec)
        return WAMPolicy(wam, instruction=instruction) if instruction else WAMPolicy(wam)
    from wamplan.evaluation.config import EvalConfig
    from wamplan.planning.dynamics import learned_dynamics
    from wamplan.worldmodel.train import load_world_model

    cfg = EvalConfig(wam=spec, wm_augmented=plan_with)  # on cfg.device, as the evaluation loads them
    paths = plan_with.split(",")
    dyn, enc = learned_dynamics([load_world_model(p, device=cfg.device) for p in paths])
    return planned_policy(cfg, load_wam(spec, device=cfg.device), dyn, enc, world_models=paths)
