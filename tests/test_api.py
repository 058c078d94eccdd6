"""The public Python API (``wamplan.*``): cheap to import, built on the evaluation's own code path, and able to
plan one chunk of the shipped TinyWAM in the shipped world model (the README's example runs in test_readme.py)."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import torch

import wamplan
from wamplan.config import ConfigError
from wamplan.errors import UserError

WAM, WM = "checkpoints/mini/tinywam", "checkpoints/mini/wm_augmented"


def test_import_is_cheap_and_the_api_resolves_on_first_use():
    code = ("import sys, wamplan; assert 'torch' not in sys.modules and 'mani_skill' not in sys.modules; "
            "wamplan.planned_policy; assert 'torch' in sys.modules")
    subprocess.run([sys.executable, "-c", code], check=True)
    from wamplan import api

    assert sorted(wamplan.__all__) == sorted(api.__all__)
    assert all(getattr(wamplan, name) is getattr(api, name) for name in wamplan.__all__)
    assert set(wamplan.__all__) <= set(dir(wamplan))
    with pytest.raises(AttributeError, match="no attribute 'plan'"):
        wamplan.plan  # noqa: B018


def test_wrong_settings_fail_in_one_line_before_anything_loads():
    with pytest.raises(ConfigError, match=r"unknown keys \['gate'\]; known keys are"):
        wamplan.planned_policy(WAM, WM, gate=0.1)
    with pytest.raises(UserError, match="world_model /no/such/wm does not exist"):
        wamplan.planned_policy(WAM, "/no/such/wm")
    # several world models (an ensemble) left the core: one checkpoint, in one line that says so
    with pytest.raises(TypeError, match="a checkpoint directory .* got list .*an ensemble"):
        wamplan.planned_policy(WAM, [WM, WM])
    with pytest.raises(UserError, match=rf"^world_model {WM}\+{WM} joins 2 world models .* pass one checkpoint"):
        wamplan.planned_policy(WAM, f"{WM}+{WM}")
    with pytest.raises(ConfigError, match="unknown keys"):
        wamplan.make_env(camera=64)


def test_the_api_builds_the_evaluations_policy(tmp_path):
    from wamplan.evaluation.build import load_policy
    from wamplan.evaluation.config import EvalConfig
    from wamplan.planning import CostConfig

    pol = wamplan.planned_policy(WAM, WM, device="cpu")
    assert pol.config == EvalConfig().policy and pol.planner.name == EvalConfig().planner
    assert pol.config_dict() == load_policy(WAM, plan_with=WM).config_dict()  # `collect --plan-with`, condition 7
    pol = wamplan.planned_policy(wamplan.load_wam(WAM, device="cpu"), WM, planner="cem",
                                 planner_config={"iterations": 2}, cost=CostConfig(view_weights=(0.0, 0.0, 1.0)),
                                 gate_threshold=0.05)
    assert pol.planner.name == "cem" and pol.planner.config.iterations == 2 and pol.config.gate_threshold == 0.05
    assert type(pol.dynamics).__name__ == "LearnedDynamics"
    pred, target = torch.rand(2, 3, 4, 8), torch.rand(3, 4, 8)  # (B, V, N, D), (V, N, D)
    torch.testing.assert_close(pol.cost(pred, target), (pred[:, 2] - target[2]).square().mean(dim=(1, 2)))
    # the cost also as its name or a dict of its fields, as planner_config takes a dict
    by_dict = wamplan.planned_policy(WAM, WM, device="cpu", cost={"view_weights": [0, 0, 1]})
    torch.testing.assert_close(by_dict.cost(pred, target), pol.cost(pred, target))
    by_name = wamplan.planned_policy(WAM, WM, device="cpu", cost="cls")
    torch.testing.assert_close(by_name.cost(pred, target), (pred.mean(2) - target.mean(1)).square().mean(dim=(1, 2)))
    with pytest.raises(TypeError, match="cost is of type int; pass a CostConfig, a cost name"):
        wamplan.planned_policy(WAM, WM, cost=5)
    assert wamplan.CostConfig is CostConfig


def test_plan_one_chunk_of_the_shipped_wam(env):
    wam = wamplan.load_wam(WAM, device="cpu")
    obs = env.reset(0, with_images=True)
    paper = wamplan.planned_policy(wam, WM, device="cpu")
    paper.reset(0)
    d = paper.plan_chunk(obs)
    assert d.reason == "first-chunk" and d.plan is None and d.target is None
    rest = wamplan.planned_policy(wam, WM, device="cpu", first_chunk="rest-history")
    rest.reset(0)
    d = rest.plan_chunk(obs)
    assert isinstance(d, wamplan.ChunkDecision) and d.reason is None and d.executed.shape == (16, 5)
    assert d.target.shape[0] == 3 and d.costs.best <= d.costs.seed
    np.testing.assert_array_equal(d.executed, d.plan)
    assert rest.info()["planned_chunks"] == 1


def test_the_tasks_are_part_of_the_api():
    assert {"cube-insertion", "peg-insertion-side", "push-cube"} <= set(wamplan.tasks())
    assert wamplan.tasks() == sorted(wamplan.tasks())
    cube = wamplan.get_task("cube-insertion")
    assert isinstance(cube, wamplan.TaskSpec) and (cube.action_dim, cube.proprio_dim) == (5, 10)
    assert wamplan.register_task is __import__("wamplan.envs.spec", fromlist=["x"]).register_task
    with pytest.raises(UserError, match="unknown task 'nope'; choose one of"):
        wamplan.make_env(task="nope")


def test_a_dict_for_an_observation_says_how_to_make_one():
    wam = wamplan.load_wam(WAM, device="cpu")
    obs = {"proprio": np.zeros(10, np.float32)}
    with pytest.raises(TypeError, match=r"PlannedPolicy.plan_chunk takes a wamplan.Observation, got a dict; take one "
                                        r"from env.reset\(seed, with_images=True\)"):
        wamplan.planned_policy(wam, WM, device="cpu").plan_chunk(obs)
    from wamplan.wam import WAMPolicy

    with pytest.raises(TypeError, match="WAMPolicy.act takes a wamplan.Observation, got a dict"):
        WAMPolicy(wam).act(obs)


def test_a_policy_in_an_env_of_another_task_fails_before_the_episode_in_python_terms():
    from types import SimpleNamespace

    from wamplan.errors import TaskMismatch
    from wamplan.wam import WAMPolicy

    env = SimpleNamespace(task=wamplan.get_task("stack-cube"))  # what run_episode reads before anything runs
    with pytest.raises(TaskMismatch, match=r"made for task 'cube-insertion', but this run uses task 'stack-cube'; "
                                           r"run it in make_env\(task='cube-insertion'\)") as e:
        wamplan.run_episode(env, WAMPolicy(wamplan.load_wam(WAM, device="cpu")), seed=0)
    assert isinstance(e.value, ValueError) and "--task" not in str(e.value)
