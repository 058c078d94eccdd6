"""Gripper-aware CEM on toy costs: it can delay, advance or cancel the WAM's grasp, and keeps it otherwise; its
gripper settings come from the task it plans for."""

import argparse

import pytest
import torch

from wamplan.config import ConfigError
from wamplan.envs.maniskill import maniskill_task
from wamplan.envs.spec import get_task
from wamplan.planning import PLANNERS, CEMGripperConfig, make_planner
from wamplan.planning.cem_gripper import gripper_categories
from wamplan.cli.planner_options import add_planner_arguments, planner_config_from_args

H, A = 16, 5
CUBE = get_task("cube-insertion")  # 5-D actions, the gripper last: +1 open, -1 closed


def planner(cfg: CEMGripperConfig | None = None):
    """cem-gripper built for the cube task (as the planned policy builds it)."""
    return make_planner("cem-gripper", cfg).for_task(CUBE)


def step_gripper(close_at: int, n: int = H) -> torch.Tensor:
    """Open (+1) before ``close_at``, closed (-1) from it on: (n,)."""
    return torch.where(torch.arange(n) < close_at, 1.0, -1.0)


def grasp_seed(close_at: int = 8) -> torch.Tensor:
    seed = torch.full((H, A), 0.2)  # (H, A) the arm drifts; the toy optimum is 0
    seed[:, 4] = step_gripper(close_at)
    return seed


def toy_cost(target_gripper: torch.Tensor):
    """cost = ||arm||^2 + ||gripper - target||^2 per candidate: (B, H, A) -> (B,)."""
    return lambda c: c[:, :, :4].square().sum((1, 2)) + (c[:, :, 4] - target_gripper.to(c)).square().sum(1)


def test_categories_are_every_single_switch_sequence():
    g = torch.linspace(0.9, -0.9, 4)  # (4,) the WAM's continuous gripper values
    cats, names = gripper_categories(g, 1.0, -1.0)
    assert names == ["keep", "close@0", "close@1", "close@2", "close@3", "close@4", "open@1", "open@2", "open@3"]
    torch.testing.assert_close(cats[0], g)
    assert cats[1].tolist() == [-1, -1, -1, -1] and cats[5].tolist() == [1, 1, 1, 1]
    assert cats[3].tolist() == [1, 1, -1, -1] and cats[7].tolist() == [-1, -1, 1, 1]
    assert len({tuple(r.tolist()) for r in cats[1:]}) == 2 * 4  # no duplicates besides keep


def test_prior_centres_on_the_wam():
    cats, names = gripper_categories(step_gripper(8), 1.0, -1.0)
    p = planner(CEMGripperConfig(gripper_prior_steps=2.0)).prior(cats)
    assert p.sum().item() == pytest.approx(1.0)
    assert p[0] == p[names.index("close@8")] == p.max()  # keep and its binarised twin
    ratio = (p[names.index("close@12")] / p[0]).item()
    assert ratio == pytest.approx(torch.exp(torch.tensor(-4 / 2.0)).item())  # 4 steps apart, width 2


@pytest.mark.parametrize("target,label", [(12, "delay"), (4, "advance"), (H, "cancel")])
def test_moves_the_grasp(target, label):
    want = step_gripper(target)  # the WAM closes at step 8; the cost wants the switch at ``target``
    for s in range(5):
        res = planner().plan(grasp_seed(8), toy_cost(want), seed=s)
        assert torch.equal(res.actions[:, 4], want), (label, s, res.actions[:, 4])


def test_closes_at_once_in_most_seeds():
    want = step_gripper(0)  # the farthest change besides cancelling (8 steps from the WAM's)
    hits = sum(torch.equal(planner().plan(grasp_seed(8), toy_cost(want), seed=s).actions[:, 4], want)
               for s in range(20))
    assert hits >= 16  # 17 of 20 with the defaults; plain categorical sampling without the stratification: 9


def test_systematic_sampling_covers_a_uniform_distribution():
    from wamplan.planning.cem_gripper import systematic_sample

    idx = systematic_sample(torch.full((31,), 1 / 31), 31, torch.Generator().manual_seed(0))
    assert sorted(idx.tolist()) == list(range(31))
    idx = systematic_sample(torch.tensor([0.5, 0.25, 0.25]), 8, torch.Generator().manual_seed(1))
    assert torch.bincount(idx, minlength=3).tolist() == [4, 2, 2]


def test_plain_cem_cannot_delay_the_grasp():
    res = make_planner("cem").plan(grasp_seed(8), toy_cost(step_gripper(12)), seed=0)
    assert res.actions[8:12, 4].max() < 0  # still closing at step 8 (Gaussian steps never flip)


def test_keeps_the_wams_values_when_they_are_best():
    seed = grasp_seed(8)
    seed[:, 4] = torch.linspace(0.8, -0.7, H)  # a continuous WAM gripper no step sequence matches
    res = planner().plan(seed, toy_cost(seed[:, 4].clone()), seed=0)
    assert torch.equal(res.actions[:, 4], seed[:, 4])
    assert res.actions[:, :4].square().sum() < seed[:, :4].square().sum()  # the arm is searched as in CEM


def test_candidates_use_only_the_categories_and_a_frozen_gripper_sigma():
    seen = []

    def cost(c):
        seen.append(c[:, :, 4].clone())
        return toy_cost(step_gripper(12, 15))(c)

    seed = grasp_seed(8)
    res = planner(CEMGripperConfig(num_optimized=15)).plan(seed, cost, seed=1)
    cats = {tuple(r.tolist()) for r in gripper_categories(seed[:15, 4], 1.0, -1.0)[0]}
    assert all(tuple(r.tolist()) in cats for g in seen for r in g)
    assert torch.all(res.std[:, 4] == 0) and res.actions[15, 4] == seed[15, 4]  # trailing action kept
    assert res.num_evaluations == 4 * 32 and len(seen) == 4


def test_reproducible_and_registered_with_cli_options():
    a = planner().plan(grasp_seed(), toy_cost(step_gripper(12)), seed=3)
    b = planner().plan(grasp_seed(), toy_cost(step_gripper(12)), seed=3)
    assert torch.equal(a.actions, b.actions)
    assert "cem-gripper" in PLANNERS and "cem" in PLANNERS
    p = argparse.ArgumentParser()
    add_planner_arguments(p)
    name, cfg = planner_config_from_args(p.parse_args(["--planner", "cem-gripper", "--gripper-prior-steps", "2",
                                                       "--num-elites", "4"]))
    assert name == "cem-gripper" and cfg == CEMGripperConfig(gripper_prior_steps=2.0, num_elites=4)
    with pytest.raises(Exception, match="cem-gripper"):
        planner_config_from_args(p.parse_args(["--gripper-smoothing", "0.2"]))  # the default planner is wamplan


@pytest.mark.parametrize("kwargs,match", [({"gripper_prior_steps": 0}, "gripper_prior_steps"),
                                          ({"gripper_smoothing": 1.0}, "gripper_smoothing"),
                                          ({"gripper_open": 0.0, "gripper_closed": 0.0}, "differ")])
def test_bad_configs(kwargs, match):
    with pytest.raises(ValueError, match=match):
        CEMGripperConfig(**kwargs)


def test_the_gripper_settings_come_from_the_task():
    assert planner().config == CEMGripperConfig(gripper_dim=4, gripper_open=1.0, gripper_closed=-1.0)
    seven = maniskill_task("Toy-v1", name="toy", cameras=("c",), action_dim=7, proprio_dim=3, max_episode_steps=9,
                           instruction="", gripper_closed=-0.5)  # the gripper last, at index 6
    cfg = CEMGripperConfig().for_task(seven)
    assert (cfg.gripper_dim, cfg.gripper_open, cfg.gripper_closed) == (6, 1.0, -0.5)
    mine = CEMGripperConfig(gripper_dim=2, gripper_open=0.5, gripper_closed=-1.0, init_std_per_dim=(0.1,) * 7)
    assert mine.for_task(seven) is mine  # settings given stay as given
    p = make_planner("cem-gripper")
    assert p.for_task(CUBE) is not p and make_planner("cem-gripper", mine).for_task(seven).config is mine
    with pytest.raises(ConfigError, match="build the planned policy for a task"):
        p.plan(grasp_seed(), toy_cost(step_gripper(8)), seed=0)  # nothing filled it
    no_gripper = maniskill_task("Toy-v1", name="toy", cameras=("c",), action_dim=6, proprio_dim=3,
                                max_episode_steps=9, instruction="", gripper_index=None)
    with pytest.raises(ConfigError, match="task 'toy' has no gripper; use --planner cem"):
        p.for_task(no_gripper)
