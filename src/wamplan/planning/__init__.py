"""Planning: costs and the sampling optimisers (CEM, MPPI, gripper-aware CEM, drift) that refine a WAM's action chunk.

Planners are pure: ``make_planner(name, config).plan(seed_actions (H, A), objective) -> PlanResult``,
where ``objective(candidates (B, H_opt, A)) -> costs (B,)`` wraps the caller's dynamics and cost.
"""

from wamplan.planning.base import (
    PLANNERS,
    IterationStats,
    Objective,
    PlanResult,
    Planner,
    SamplingConfig,
    SamplingPlanner,
    make_planner,
    register_planner,
)
from wamplan.planning.cem import CEMConfig, CEMPlanner
from wamplan.planning.cem_gripper import CEMGripperConfig, CEMGripperPlanner
from wamplan.planning.drift import DriftConfig, DriftPlanner
from wamplan.planning.costs import COSTS, CostConfig, CostFn, cls_cost, make_cost, patch_cost, register_cost
from wamplan.planning.mppi import MPPIConfig, MPPIPlanner

__all__ = [
    "COSTS", "PLANNERS", "CEMConfig", "CEMGripperConfig", "CEMGripperPlanner", "CEMPlanner", "CostConfig", "CostFn", "DriftConfig",
    "DriftPlanner", "IterationStats",
    "MPPIConfig", "MPPIPlanner", "Objective", "PlanResult", "Planner", "SamplingConfig",
    "SamplingPlanner", "cls_cost", "make_cost", "make_planner", "patch_cost", "register_cost",
    "register_planner",
]
