"""``wamplan eval``'s options, generated from the configs :class:`EvalConfig` nests: the checkpoints, the
planned policy, the cost (``--cost-*``), the task, and every registered planner's config
(``wamplan.cli.planner_options``), and the nested config built back from them. The planning part alone
(policy, cost, planner) is what ``wamplan serve`` offers too (:func:`add_planning_arguments`)."""

from __future__ import annotations

import argparse
import dataclasses
from typing import Any

from wamplan.config import add_arguments, from_args
from wamplan.envs.config import EnvConfig
from wamplan.evaluation.config import EvalConfig
from wamplan.cli.planner_options import add_planner_arguments, planner_config_from_args
from wamplan.planning.cost_config import CostConfig
from wamplan.planning.policy_config import PlannedPolicyConfig


def add_planning_arguments(p: argparse.ArgumentParser, policy: type = PlannedPolicyConfig) -> None:
    """The planned policy's chunk rules (``policy``: its config class, e.g. one with other defaults), the cost
    (``--cost-*``), ``--planner`` and every planner's options."""
    add_arguments(p.add_argument_group("planned policy"), policy)
    add_arguments(p.add_argument_group("cost"), CostConfig, prefix="cost_")
    add_planner_arguments(p, default=EvalConfig.planner)


def planning_from_args(args: argparse.Namespace, policy: type = PlannedPolicyConfig) -> dict[str, Any]:
    """:class:`EvalConfig`'s planning fields from the options of :func:`add_planning_arguments` (with the same
    ``policy`` class): ``planner``, ``planner_config``, ``policy`` and ``cost``."""
    planner, planner_config = planner_config_from_args(args)
    return dict(planner=planner, planner_config=planner_config, policy=from_args(policy, args),
                cost=from_args(CostConfig, args, prefix="cost_"))


def add_eval_arguments(p: argparse.ArgumentParser) -> None:
    add_arguments(p, EvalConfig)  # checkpoints, device; --planner comes with the planner options
    env = p.add_argument_group("task")
    add_arguments(env, EnvConfig)
    env.add_argument("--max-steps", dest="max_steps_alias", type=int, default=None,
                     help="the same as --max-episode-steps")
    add_planning_arguments(p)


def eval_config_from_args(args: argparse.Namespace) -> EvalConfig:
    """The nested :class:`EvalConfig` from the options (unset options keep the defaults)."""
    from wamplan.errors import UserError, require_positive

    alias = getattr(args, "max_steps_alias", None)  # --max-steps: checked under the name typed
    if alias is not None:
        require_positive(("--max-steps", alias))
        if args.max_episode_steps not in (None, alias):
            raise UserError(f"--max-steps {alias} and --max-episode-steps {args.max_episode_steps} say the same "
                            f"thing differently; give one")
        args.max_episode_steps = alias
    return dataclasses.replace(from_args(EvalConfig, args), env=from_args(EnvConfig, args),
                               **planning_from_args(args))
