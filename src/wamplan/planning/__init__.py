"""Planning: costs and the sampling optimisers (CEM, MPPI, gripper-aware CEM) that refine a WAM's action chunk.

Planners are pure: ``make_planner(name, config).plan(seed_actions (H, A), objective) -> PlanResult``,
where ``objective(candidates (B, H_opt, A)) -> costs (B,)`` wraps the caller's dynamics and cost.

The names below are loaded on first use, so that importing a torch-free part of this package (the settings in
``configs``, ``cost_config`` and ``policy_config``) does not import torch.
"""

from __future__ import annotations

from wamplan.registry import lazy_exports

_HOMES = {
    "base": ("PLANNERS", "IterationStats", "Objective", "PlanResult", "Planner", "SamplingPlanner", "make_planner",
             "register_planner"),
    "configs": ("CEMConfig", "CEMGripperConfig", "MPPIConfig", "SamplingConfig"),
    "cost_config": ("CostConfig",),
    "cem": ("CEMPlanner",),
    "cem_gripper": ("CEMGripperPlanner",),
    "mppi": ("MPPIPlanner",),
    "costs": ("COSTS", "CostFn", "cls_cost", "make_cost", "patch_cost", "register_cost"),
}
__getattr__, __all__ = lazy_exports(__name__, _HOMES)
