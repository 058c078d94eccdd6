"""One evaluation's settings, :class:`EvalConfig`: the checkpoints, and the configs of the env, the planner, the
cost and the planned policy, nested as they are used; ``check_for(conditions)`` refuses what those conditions
cannot run with, in one line, before anything loads. The task is the env's (``env.task``, ``--task``)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from wamplan.config import check_numbers, field, one_checkpoint, require
from wamplan.envs.config import EnvConfig
from wamplan.evaluation.conditions import CONDITIONS
from wamplan.planning.build import WM_DTYPES, PlanningConfig
from wamplan.planning.configs import DEFAULT_PLANNER
from wamplan.planning.cost_config import CostConfig
from wamplan.planning.policy_config import PlannedPolicyConfig
from wamplan.wam.profiles import profile_names


# A learned condition's dynamics -> the EvalConfig field holding its world-model checkpoints.
_WORLD_MODEL_FIELDS = {"learned-plain": "wm_plain", "learned-augmented": "wm_augmented"}


def _env_default() -> EnvConfig:
    return EnvConfig()


@dataclass(frozen=True)
class EvalConfig:
    """One evaluation: the checkpoints, and the configs of the env, the planner (by registry name with its
    own config), the cost and the planned policy, nested as they are used."""

    wam: str = field("", "WAM checkpoint directory (e.g. a TinyWAM)")
    wam_url: str = field("", "a served WAM's /act endpoint (Cosmos Policy protocol) instead of --wam, "
                         "e.g. http://127.0.0.1:8777/act")
    wam_profile: str = field("", "with --wam-url: the server's field mapping and sizes by name "
                             "(cosmos-robocasa, cosmos-aloha); left out: ALOHA's field names with the task's "
                             "cameras by position and the task's action size", choices=profile_names)
    wam_send_chunk_frames: tuple[int, ...] = field(
        (), "with --wam-url: in-chunk step offsets whose frames go to the server with the next request, with the "
        "episode's start and seed: what a planning proxy (`wamplan serve`) needs for a world model whose frameskip "
        "is shorter than the chunk, e.g. 4 8 12")
    wm_plain: str = field("", "plain world model checkpoint (condition 6)")
    wm_augmented: str = field("", "augmented world model checkpoint (condition 7)")
    sim_encoder: str = field("", "encoder for the simulator conditions (default: the plain world model's)")
    device: str = field("auto", "torch device for the models")
    wm_dtype: str = field("float32", "arithmetic of the world models' rollouts in the search: float32, or bfloat16 "
                          "(benchmarks/planner.py --dtypes times both on your machine); the planning cost is "
                          "computed in float32 either way", choices=WM_DTYPES)
    oracle_blend: float = field(0.0, "a diagnostic, not the method: conditions 6 and 7 plan with the world model's "
                                "prediction moved this share of the way to the simulator's exact outcome (0: the "
                                "model, as the paper; 1: the oracle's dynamics); every candidate is simulated, so it "
                                "runs at the oracle's speed")
    planner: str = field(DEFAULT_PLANNER, "planner by registry name (wamplan.planning.PLANNERS); the paper's is cem", cli=False)
    planner_config: Any = field(None, "the planner's config (its config_cls, or a dict of overrides); "
                                "None = its defaults", cli=False)
    cost: CostConfig = field(help="the planning cost", default_factory=CostConfig)
    policy: PlannedPolicyConfig = field(help="the planned policy's chunk rules", default_factory=PlannedPolicyConfig)
    env: EnvConfig = field(help="the task and its env (--task, camera size, episode length, ...)",
                           default_factory=_env_default)

    def __post_init__(self):
        check_numbers(self)
        object.__setattr__(self, "planner_config", self.planning.planner_config)  # its config class, checked
        require(self.wm_dtype in WM_DTYPES, f"wm_dtype '{self.wm_dtype}' is not one of {', '.join(WM_DTYPES)}")
        require(0.0 <= self.oracle_blend <= 1.0, f"--oracle-blend {self.oracle_blend} is outside [0, 1]; 0 plans in "
                "the world model alone, 1 with the simulator's dynamics")

    @property
    def planning(self) -> PlanningConfig:
        """How the planned conditions plan: the planner with its config, the cost and the chunk rules."""
        return PlanningConfig(self.planner, self.planner_config, self.cost, self.policy)

    @property
    def task_planner_config(self) -> Any:
        """The planner's config with the settings it leaves to the task filled from the env's task (what the planned
        policy plans with); one line if the task cannot fill them (cem-gripper for a task without a gripper)."""
        fill = getattr(self.planner_config, "for_task", None)
        return self.planner_config if fill is None else fill(self.env.spec)

    @staticmethod
    def world_model_flag(condition: int) -> str | None:
        """The option naming the world model ``condition`` plans in (``--wm-plain``, ``--wm-augmented``);
        None when it plans in none."""
        attr = _WORLD_MODEL_FIELDS.get(CONDITIONS[condition].dynamics)
        return None if attr is None else "--" + attr.replace("_", "-")

    def world_model(self, condition: int) -> str:
        """The world-model checkpoint ``condition`` plans in; "" when it plans in none or none was given. Several
        joined by + or commas (an ensemble, which left the core) are refused in one line."""
        attr = _WORLD_MODEL_FIELDS.get(CONDITIONS[condition].dynamics)
        return one_checkpoint(getattr(self, attr), self.world_model_flag(condition)) if attr else ""

    def check_for(self, conditions: list[int]) -> None:
        from wamplan.errors import UserError, require_paths

        if not self.wam and not self.wam_url:
            raise UserError("--wam CKPT is required (a WAM checkpoint, e.g. from `wamplan wam train`), or "
                            "--wam-url URL for a served WAM")
        if self.wam and self.wam_url:
            raise UserError("pass only one of --wam CKPT and --wam-url URL (one WAM per evaluation)")
        if self.wam_profile and not self.wam_url:
            raise UserError("--wam-profile needs --wam-url (a profile describes a served WAM)")
        if self.wam_send_chunk_frames and not self.wam_url:
            raise UserError("--wam-send-chunk-frames needs --wam-url (the frames go to a served WAM or planning proxy)")
        if self.wam_url:
            from wamplan.wam.cosmos_client import profile_config

            # a bad URL, profile or camera mapping for the task fails now, in one line
            profile_config(self.wam_profile, url=self.wam_url, task=self.env.task,
                           send_chunk_frames=self.wam_send_chunk_frames)
        spec = self.env.spec
        self.env.require_views()  # every condition feeds the WAM the task's views
        self.cost.check_cameras(spec.name, spec.cameras)
        expert = [c for c in conditions if "expert" in (CONDITIONS[c].seed, CONDITIONS[c].target)]
        if expert and spec.expert is None:
            raise UserError(f"conditions {expert} seed or aim the search with the scripted expert, but task "
                            f"'{spec.name}' has none; run conditions 1, 5, 6 and 7")
        if any(CONDITIONS[c].dynamics != "none" for c in conditions):
            _ = self.task_planner_config  # the planner fits the task: one line otherwise
        if self.oracle_blend > 0 and not any(CONDITIONS[c].learned for c in conditions):
            raise UserError(f"--oracle-blend blends a world model's predictions, but conditions {conditions} plan in "
                            "none; add condition 6 or 7, or drop --oracle-blend")
        for c in conditions:
            flag = self.world_model_flag(c)
            if flag is None:
                continue
            path = self.world_model(c)
            if not path:
                raise UserError(f"condition {c} needs {flag} CKPT (a world model from `wamplan wm train`)")
            require_paths([path], flag, "train it or fix the path")
        if self.wam:
            require_paths([self.wam], "--wam", "train one with `wamplan wam train` or fix the path")
