"""Building a planned policy: a WAM whose chunks are refined by a planner searching in a dynamics model (a learned world
model, or the simulator) under a cost and chunk rules, the one factory the evaluation, the Python API and the
planning proxy share. :class:`PlanningConfig` holds how it plans; :func:`planned_policy` builds one on given
dynamics, :func:`plan_in_world_model` loads the world model (and the WAM) first. Importing this module does not
import torch."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Sequence

from wamplan.config import field, from_dict, require
from wamplan.planning.configs import DEFAULT_PLANNER, PLANNER_CONFIGS
from wamplan.planning.cost_config import CostConfig
from wamplan.planning.policy_config import PlannedPolicyConfig

if TYPE_CHECKING:
    from wamplan.planning.dynamics import Dynamics
    from wamplan.planning.policy import PlannedPolicy
    from wamplan.wam.base import WAM

WM_DTYPES = ("float32", "bfloat16")  # the world models' arithmetic in the search (--wm-dtype's values)


@dataclass(frozen=True)
class PlanningConfig:
    """How a planned policy plans: the planner by registry name with its config, the cost and the chunk rules."""

    planner: str = field(DEFAULT_PLANNER, "planner by registry name (wamplan.planning.PLANNERS)")
    planner_config: Any = field(None, "the planner's config (its config_cls, or a dict of overrides); "
                                "None = its defaults")
    cost: CostConfig = field(help="the planning cost", default_factory=CostConfig)
    policy: PlannedPolicyConfig = field(help="the planned policy's chunk rules", default_factory=PlannedPolicyConfig)

    def __post_init__(self) -> None:
        cls = PLANNER_CONFIGS.lookup(self.planner)
        pc = self.planner_config
        pc = cls() if pc is None else from_dict(cls, pc) if isinstance(pc, dict) else pc
        require(isinstance(pc, cls), f"planner '{self.planner}' needs a {cls.__name__} as planner_config, "
                f"got {type(pc).__name__}; pass that planner's config or None")
        object.__setattr__(self, "planner_config", pc)


def planned_policy(wam: WAM, dynamics: Dynamics, encoder: Any, planning: PlanningConfig | None = None,
                   target_wam: WAM | None = None, world_models: Sequence[str] = ()) -> PlannedPolicy:
    """``wam`` refined by planning in ``dynamics`` (whose observations ``encoder`` encodes) as ``planning`` says
    (None: the defaults). ``target_wam``: the WAM whose predicted images aim the search (None: ``wam``);
    ``world_models``: the checkpoints behind ``dynamics``, recorded resolved (none for the simulator)."""
    from wamplan.planning import make_planner
    from wamplan.planning.costs import build_cost
    from wamplan.planning.policy import PlannedPolicy

    planning = planning or PlanningConfig()
    # view weights that do not fit the cameras are refused at build, not at the first plan
    planning.cost.check_cameras(wam.task.name, getattr(dynamics, "cameras", None) or wam.task.cameras)
    cost = build_cost(planning.cost)
    return PlannedPolicy(wam, make_planner(planning.planner, planning.planner_config), dynamics, encoder, cost,
                         target_wam=target_wam, config=planning.policy,
                         world_models=tuple(str(Path(p).resolve()) for p in world_models))


def plan_in_world_model(wam: WAM | str | Path, world_model: str | Path, planning: PlanningConfig | None = None,
                        device: str = "auto", wm_dtype: str = "float32") -> PlannedPolicy:
    """``wam`` (a WAM, or its checkpoint directory) planned in the world model checkpoint ``world_model``, both
    loaded onto ``device``, the world model's rollouts in ``wm_dtype`` (``WM_DTYPES``)."""
    from wamplan.planning.dynamics import LearnedDynamics
    from wamplan.wam import load_wam
    from wamplan.worldmodel.load import load_world_model

    predictor, enc = load_world_model(world_model, device=device, dtype=wm_dtype)
    wam = load_wam(wam, device=device) if isinstance(wam, (str, Path)) else wam
    return planned_policy(wam, LearnedDynamics(predictor), enc, planning, world_models=[str(world_model)])
