"""CEM and MPPI on toy objectives with a known optimum; the objective records every call it gets."""

from __future__ import annotations

import argparse
import json
import math
import statistics

import pytest
import torch

from wamplan.config import ConfigError, add_arguments, from_args, from_dict, to_dict
from wamplan.envs.spec import get_task
from wamplan.errors import UserError
from wamplan.planning import CEMConfig, MPPIConfig, MPPIPlanner, PlanResult, make_planner

H, A = 16, 5  # chunk length, action dim
CUBE = get_task("cube-insertion")  # the task a planner that needs one (cem-gripper's gripper) is built for
# the accelerator case is marked `gpu`: on a CPU-only machine it shows as skipped, not silently absent
DEVICES = ["cpu", pytest.param("accelerator", marks=pytest.mark.gpu)]


class Recorder:
    """Wraps a cost fn (B, H_opt, A) -> (B,) and keeps copies of what it was called with."""

    def __init__(self, fn):
        self.fn, self.calls = fn, []

    def __call__(self, cand):  # cand (B, H_opt, A)
        costs = self.fn(cand)  # (B,)
        self.calls.append((cand.detach().cpu().clone(), costs.detach().cpu().clone()))
        return costs


def sum_problem(g: torch.Generator, offset: float, n_opt: int = H - 1):
    """Cost = ||sum_t a_t - s*||^2 with s* reachable inside the box; seed = optimum + noise."""
    opt = torch.rand(n_opt, A, generator=g) * 1.4 - 0.7  # (H_opt, A) one optimum
    target = opt.sum(0)  # (A,)
    seed = torch.cat([(opt + offset * torch.randn(n_opt, A, generator=g)).clamp(-1, 1),
                      torch.rand(H - n_opt, A, generator=g) * 2 - 1])  # (H, A)
    cost = lambda c: (c.sum(1) - target.to(c)).square().sum(1)  # (B, H_opt, A) -> (B,)
    dist = lambda x: (x[:n_opt].sum(0) - target).norm().item()  # distance of a chunk's sum to s*
    return seed, cost, dist


def cem_refit(cand, costs, k, ddof=0):
    """Reference CEM refit: mean and std of the k lowest-cost candidates. cand (B, H_opt, A)."""
    elites = cand[torch.argsort(costs, stable=True)[:k]]  # (k, H_opt, A)
    return elites.mean(0), elites.std(0, correction=ddof)


def test_cem_scores_mean_and_refits_to_exact_elites():
    g = torch.Generator().manual_seed(0)
    seed, cost, _ = sum_problem(g, 0.2)
    cfg = CEMConfig(num_optimized=15)
    rec = Recorder(cost)
    res = make_planner("cem", cfg).plan(seed, rec, seed=7)
    assert len(rec.calls) == cfg.iterations
    noise_gen = torch.Generator().manual_seed(7)  # replays the planner's draws: N(0, 1), (31, 15, 5) a call
    mu, sigma = seed[:15], torch.full((15, A), cfg.init_std)  # (15, A) each
    for it, (cand, costs) in enumerate(rec.calls):
        assert cand.shape == (32, 15, A)
        torch.testing.assert_close(cand[0], mu)  # the current mean is candidate 0, every iteration
        noise = torch.randn(31, 15, A, generator=noise_gen)  # (31, 15, A)
        torch.testing.assert_close(cand[1:], (mu + sigma * noise).clamp(-1, 1))  # N(mu, sigma^2), clipped
        mu, sigma = cem_refit(cand, costs, cfg.num_elites)
        elite_costs = costs.sort().values[: cfg.num_elites]
        h = res.history[it]
        assert h.mean_cost == pytest.approx(costs[0].item())
        assert h.cost_min == pytest.approx(costs.min().item())
        assert h.cost_mean == pytest.approx(costs.mean().item(), rel=1e-5)
        assert h.elite_cost_mean == pytest.approx(elite_costs.mean().item(), rel=1e-5)
        assert h.std_mean == pytest.approx(sigma.mean().item(), rel=1e-5)
    torch.testing.assert_close(res.mean, mu)  # returned = the final refit mean
    torch.testing.assert_close(res.std, sigma)
    all_costs = torch.cat([c for _, c in rec.calls])
    assert res.best_cost == pytest.approx(all_costs.min().item())
    assert res.seed_cost == pytest.approx(rec.calls[0][1][0].item())
    assert res.num_evaluations == 128
    stats = json.loads(json.dumps(res.stats()))  # plain data, and the same numbers
    assert (stats["best_cost"], stats["seed_cost"], stats["num_evaluations"]) == (
        res.best_cost, res.seed_cost, 128)
    assert [h["mean_cost"] for h in stats["history"]] == [c[0].item() for _, c in rec.calls]


def test_cem_sample_ddof_option():
    g = torch.Generator().manual_seed(1)
    seed, cost, _ = sum_problem(g, 0.2, n_opt=H)
    rec = Recorder(cost)
    res = make_planner("cem", CEMConfig(std_ddof=1, iterations=1)).plan(seed, rec, seed=0)
    _, sigma = cem_refit(*rec.calls[0], k=8, ddof=1)
    torch.testing.assert_close(res.std, sigma)


@pytest.mark.parametrize("name", ["cem", "mppi"])
def test_clipping_and_trailing_actions(name):
    g = torch.Generator().manual_seed(2)
    seed = torch.randn(H, A, generator=g) * 1.5  # (H, A), many entries outside [-0.5, 0.5]
    rec = Recorder(lambda c: c.square().sum((1, 2)) * 0 + torch.rand(c.shape[0], generator=g).to(c))
    cfg = {"num_optimized": 12, "init_std": 0.5, "action_low": -0.5, "action_high": 0.5}
    res = make_planner(name, cfg).plan(seed, rec, seed=0)
    for cand, _ in rec.calls:
        assert cand.shape == (32, 12, A)
        assert cand.min() >= -0.5 and cand.max() <= 0.5
    torch.testing.assert_close(rec.calls[0][0][0], seed[:12].clamp(-0.5, 0.5))  # mu0 = clipped seed
    assert res.mean.min() >= -0.5 and res.mean.max() <= 0.5
    assert torch.equal(res.actions[:12], res.mean)
    assert torch.equal(res.actions[12:], seed[12:])  # trailing actions exactly the seed's (unclipped)
    assert res.actions.shape == seed.shape


@pytest.mark.parametrize("name", ["cem", "mppi"])
def test_improves_on_toy_problem_over_many_seeds(name):
    # Paper settings (32 / 8 / 4, sigma0 0.1, 15 of 16 optimised). Measured median ratios ~0.17 (CEM),
    # ~0.16 (MPPI); CEM with worst-cost elites gives ~2.5, random elites ~1.06, a frozen mean 1.0.
    ratios = []
    for s in range(50):
        seed, cost, dist = sum_problem(torch.Generator().manual_seed(100 + s), 0.15)
        res = make_planner(name, {"num_optimized": 15}).plan(seed, cost, seed=s)
        ratios.append(dist(res.actions) / dist(seed))
    assert statistics.median(ratios) < 0.5
    assert sum(r < 1 for r in ratios) >= 45


@pytest.mark.parametrize("name", ["cem", "mppi"])
def test_reproducible(name):
    seed, cost, _ = sum_problem(torch.Generator().manual_seed(3), 0.2)
    planner = make_planner(name, {"num_optimized": 15})
    a = planner.plan(seed, cost, seed=11)
    b = planner.plan(seed, cost, generator=torch.Generator().manual_seed(11))
    c = planner.plan(seed, cost, seed=12)
    assert torch.equal(a.actions, b.actions) and a.history == b.history
    assert not torch.equal(a.actions, c.actions)
    with pytest.raises(ValueError, match="either generator or seed"):
        planner.plan(seed, cost, seed=1, generator=torch.Generator())


def test_mppi_weighted_mean_update():
    seed, cost, _ = sum_problem(torch.Generator().manual_seed(4), 0.2, n_opt=H)
    cfg = MPPIConfig(momentum=0.3, temperature=0.2)
    planner = MPPIPlanner(cfg)
    rec = Recorder(cost)
    res = planner.plan(seed, rec, seed=0)
    mu = seed  # (H, A)
    for cand, costs in rec.calls:
        torch.testing.assert_close(cand[0], mu)  # the current mean is scored every iteration
        z = (costs - costs.min()) / (costs.max() - costs.min())  # (B,) normalised to [0, 1]
        w = torch.softmax(-z / cfg.temperature, 0)  # (B,)
        torch.testing.assert_close(planner.weights(costs), w)
        avg = (w[:, None, None] * cand).sum(0)  # (H, A)
        mu = cfg.momentum * mu + (1 - cfg.momentum) * avg
    torch.testing.assert_close(res.mean, mu)
    raw = MPPIPlanner(MPPIConfig(normalize_costs=False, temperature=0.5))
    costs = torch.tensor([3.0, 1.0, 2.0])
    torch.testing.assert_close(raw.weights(costs), torch.softmax(-(costs - 1.0) / 0.5, 0))


def test_mppi_fixed_std():
    seed, cost, _ = sum_problem(torch.Generator().manual_seed(5), 0.2, n_opt=H)
    res = make_planner("mppi", {"update_std": False, "init_std": 0.2}).plan(seed, cost, seed=0)
    assert torch.all(res.std == 0.2)


def test_sampling_statistics_and_per_dim_std():
    seed = torch.zeros(H, A)
    cfg = CEMConfig(num_candidates=4001, num_elites=8, iterations=1,
                    init_std_per_dim=(0.1, 0.2, 0.05, 0.3, 0.0))
    rec = Recorder(lambda c: torch.zeros(c.shape[0]))
    make_planner("cem", cfg).plan(seed, rec, seed=0)
    samples = rec.calls[0][0][1:]  # (4000, H, A) without the mean
    std = samples.std(0).mean(0)  # (A,)
    torch.testing.assert_close(std, torch.tensor(cfg.init_std_per_dim), atol=0.01, rtol=0.03)
    assert samples.mean(0).abs().max() < 0.03


@pytest.mark.parametrize("name", ["cem", "mppi", "cem-gripper"])
def test_seed_rank_is_the_share_of_first_samples_scored_below_the_seed(name):
    for seed, expect in ((torch.zeros(H, A), 0.0), (None, None)):
        seed = torch.full((H, A), 0.9) if seed is None else seed
        rec = Recorder(lambda c: c[..., :4].square().sum((1, 2)))  # optimum: zero arm actions
        res = make_planner(name).for_task(CUBE).plan(seed, rec, seed=1)
        costs = rec.calls[0][1]  # (B,) of iteration 0, candidate 0 the seed
        assert res.seed_rank == pytest.approx(float((costs[1:] < costs[0]).float().mean()))
        assert res.stats()["seed_rank"] == res.seed_rank
        if expect is not None:
            assert res.seed_rank == expect  # at the optimum nothing beats the seed
    assert res.seed_rank > 0.3  # far from the optimum (by the bound, clipping pulls samples inward) many beat it
    no_mean = make_planner(name, make_planner(name).config_cls(include_mean=False)).for_task(CUBE).plan(seed, rec,
                                                                                                        seed=1)
    assert math.isnan(no_mean.seed_rank)


def test_white_noise_is_the_papers_sampling_bit_for_bit():
    """The samples are exactly what the paper's CEM draws: N(mu, sigma^2) from torch.randn on the seeded
    generator, candidate 0 the mean."""
    g = torch.Generator().manual_seed(3)
    seed = torch.rand(H, A, generator=g) * 0.4 - 0.2
    rec = Recorder(lambda c: c.square().sum((1, 2)))
    make_planner("cem", CEMConfig(iterations=1)).plan(seed, rec, seed=11)
    expected = seed + 0.1 * torch.randn((31, H, A), generator=torch.Generator().manual_seed(11))
    torch.testing.assert_close(rec.calls[0][0][1:], expected.clamp(-1, 1), rtol=0, atol=0)


def test_gripper_stays_with_the_wam_and_can_be_frozen():
    seed = torch.zeros(H, A)
    seed[:, 4] = 1.0  # WAM says: open
    wants_close = lambda c: c[:, :, 4].sum(1) + c[:, :, :4].square().sum((1, 2))  # (B,)
    res = make_planner("cem", {"num_optimized": 15}).plan(seed, wants_close, seed=0)
    assert res.mean[:, 4].min() > 0.5  # pulled toward closing, but far from the 0 threshold
    frozen = CEMConfig(num_optimized=15, init_std_per_dim=(0.1, 0.1, 0.1, 0.1, 0.0), min_std=0.05)
    rec = Recorder(wants_close)
    res = make_planner("cem", frozen).plan(seed, rec, seed=0)
    assert all(torch.all(c[:, :, 4] == 1.0) for c, _ in rec.calls)
    assert torch.all(res.actions[:, 4] == 1.0) and torch.all(res.std[:, 4] == 0)
    assert res.std[:, :4].min() >= 0.05  # the floor applies to the searched dimensions


def test_all_sixteen_optimised_and_nan_costs():
    seed, cost, _ = sum_problem(torch.Generator().manual_seed(6), 0.2, n_opt=H)
    nan_odd = lambda c: torch.where(torch.arange(c.shape[0]) % 2 == 1, float("nan"), cost(c))
    rec = Recorder(nan_odd)
    res = make_planner("cem", CEMConfig()).plan(seed, rec, seed=0)
    assert rec.calls[0][0].shape == (32, H, A)
    assert torch.isfinite(res.mean).all() and res.best_cost == pytest.approx(
        min(c[~c.isnan()].min().item() for _, c in rec.calls))
    # NaN candidates are never elites: the refit uses only even (finite) candidates
    cand, costs = rec.calls[0]
    torch.testing.assert_close(rec.calls[1][0][0], cem_refit(cand[::2], costs[::2], 8)[0])
    assert all(torch.isfinite(make_planner("mppi").plan(seed, nan_odd, seed=0).mean.flatten()))


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("name", ["cem", "mppi"])
def test_device_follows_seed_actions(name, device):
    if device == "accelerator":
        device = str(torch.accelerator.current_accelerator())
    seed, cost, _ = sum_problem(torch.Generator().manual_seed(8), 0.2)
    seed = seed.to(device)
    res = make_planner(name, {"num_optimized": 15}).plan(seed, cost, seed=0)
    assert res.actions.device == seed.device and res.mean.device == seed.device
    cpu = make_planner(name, {"num_optimized": 15}).plan(
        seed, cost, generator=torch.Generator().manual_seed(0))  # CPU draws, device math
    ref = make_planner(name, {"num_optimized": 15}).plan(
        seed.cpu(), cost, generator=torch.Generator().manual_seed(0))
    torch.testing.assert_close(cpu.actions.cpu(), ref.actions, atol=1e-5, rtol=1e-5)


@pytest.mark.parametrize("kwargs, match", [
    ({"num_elites": 33}, "num_elites"),
    ({"num_elites": 0}, "num_elites"),
    ({"num_elites": 1, "std_ddof": 1}, "num_elites"),
    ({"std_ddof": 2}, "std_ddof"),
    ({"num_candidates": 1, "num_elites": 1}, "num_candidates"),
    ({"init_std": -0.1}, "init_std"),
    ({"init_std": 0.0}, "init_std"),
    ({"init_std_per_dim": (0.1, -0.1)}, "init_std_per_dim"),
    ({"init_std_per_dim": (0.0, 0.0)}, "init_std_per_dim"),
    ({"min_std": -1e-3}, "min_std"),
    ({"iterations": 0}, "iterations"),
    ({"num_optimized": 0}, "num_optimized"),
    ({"action_low": 1.0, "action_high": -1.0}, "action_low"),
])
def test_bad_cem_configs(kwargs, match):
    with pytest.raises(ConfigError, match=match):
        CEMConfig(**kwargs)


@pytest.mark.parametrize("kwargs, match", [
    ({"temperature": 0.0}, "temperature"), ({"momentum": 1.0}, "momentum"), ({"init_std": -1.0}, "init_std")])
def test_bad_mppi_configs(kwargs, match):
    with pytest.raises(ConfigError, match=match):
        MPPIConfig(**kwargs)


def test_errors_found_at_plan_time_and_registry():
    seed = torch.zeros(H, A)
    cost = lambda c: c.square().sum((1, 2))
    with pytest.raises(ConfigError, match="num_optimized=17 exceeds"):
        make_planner("cem", {"num_optimized": 17}).plan(seed, cost)
    with pytest.raises(ConfigError, match="init_std_per_dim has 3 entries"):
        make_planner("cem", {"init_std_per_dim": (0.1, 0.1, 0.1)}).plan(seed, cost)
    with pytest.raises(ValueError, match="objective must return costs of shape"):
        make_planner("cem").plan(seed, lambda c: c.square().sum(2))
    with pytest.raises(ValueError, match="seed_actions must be"):
        make_planner("cem").plan(seed[None], cost)
    with pytest.raises(UserError, match="unknown planner 'ilqr'"):
        make_planner("ilqr")
    with pytest.raises(ConfigError, match="needs a CEMConfig"):
        make_planner("cem", MPPIConfig())
    with pytest.raises(ConfigError, match="unknown keys"):
        make_planner("cem", {"num_elite": 4})


def test_config_round_trips_json_and_cli():
    cfg = CEMConfig(num_optimized=15, init_std_per_dim=(0.1, 0.1, 0.1, 0.1, 0.0))
    assert from_dict(CEMConfig, json.loads(json.dumps(to_dict(cfg)))) == cfg
    parser = argparse.ArgumentParser()
    add_arguments(parser, CEMConfig)
    args = parser.parse_args(["--num-elites", "4", "--num-optimized", "15",
                              "--init-std-per-dim", "0.1", "0.1", "0.1", "0.1", "0", "--no-include-mean"])
    got = from_args(CEMConfig, args)
    assert (got.num_elites, got.num_optimized, got.include_mean) == (4, 15, False)
    assert got.init_std_per_dim == (0.1, 0.1, 0.1, 0.1, 0.0)


def test_without_mean_candidate():
    seed, cost, _ = sum_problem(torch.Generator().manual_seed(9), 0.2)
    rec = Recorder(cost)
    cfg = CEMConfig(include_mean=False)
    res = make_planner("cem", cfg).plan(seed, rec, seed=0)
    # all 32 candidates are samples around the seed: N(seed, init_std^2), clipped, replayed from the same draws
    noise = torch.randn(32, H, A, generator=torch.Generator().manual_seed(0))  # (32, H, A): all 16 optimised
    torch.testing.assert_close(rec.calls[0][0], (seed + cfg.init_std * noise).clamp(-1, 1))
    assert not any(torch.equal(c, seed) for c in rec.calls[0][0])
    assert math.isnan(res.seed_cost) and math.isnan(res.history[0].mean_cost)  # the mean was never scored
    assert res.best_cost == pytest.approx(min(c.min().item() for _, c in rec.calls))
    assert res.num_evaluations == 32 * cfg.iterations and isinstance(res, PlanResult)


def test_the_wamplan_preset_is_mppi_at_its_tuned_settings():
    """``--planner wamplan`` searches exactly as MPPI with the preset's temperature, and takes MPPI's options."""
    from wamplan.planning.defaults import TEMPERATURE, WamplanConfig

    seed, cost, _ = sum_problem(torch.Generator().manual_seed(4), 0.2)
    preset = make_planner("wamplan").plan(seed, cost, seed=5)
    mppi = make_planner("mppi", {"temperature": TEMPERATURE}).plan(seed, cost, seed=5)
    assert torch.equal(preset.actions, mppi.actions) and preset.history == mppi.history
    other = make_planner("wamplan", {"temperature": TEMPERATURE * 3, "iterations": 2}).plan(seed, cost, seed=5)
    assert not torch.equal(other.actions, preset.actions) and len(other.history) == 2
    assert isinstance(make_planner("wamplan").config, WamplanConfig)


@pytest.mark.parametrize("name", ["cem", "mppi", "wamplan", "cem-gripper"])
def test_the_sampling_sigma_follows_the_tasks_controller(name):
    """A task's sigma_scale multiplies init_std per action entry (ManiSkill's 10 cm-a-unit translation gets a fifth
    of the cube's sigma, its rotation a tenth), an explicit init_std_per_dim is kept as given, and the cube's own config is untouched."""
    from wamplan.envs.maniskill import maniskill_task
    seven = maniskill_task("Toy-v1", name="toy", cameras=("c",), action_dim=7, proprio_dim=3, max_episode_steps=9,
                           instruction="")  # pd_ee_delta_pose: 3 translation, 3 rotation entries, the gripper
    assert seven.sigma_scale == (0.2, 0.2, 0.2, 0.1, 0.1, 0.1, 1.0)
    cls = make_planner(name).config_cls
    base = cls()
    assert base.for_task(seven).init_std_per_dim == pytest.approx([base.init_std * s for s in seven.sigma_scale])
    assert base.for_task(CUBE).init_std_per_dim == ()  # the unit task: nothing to scale
    given = cls(init_std_per_dim=(0.3,) * 7)
    assert given.for_task(seven).init_std_per_dim == (0.3,) * 7
    rec = Recorder(lambda c: c.square().sum((1, 2)))  # candidates of iteration 0 spread by the scaled sigma
    make_planner(name, cls(num_candidates=512, iterations=1)).for_task(seven).plan(torch.zeros(H, 7), rec, seed=0)
    spread = rec.calls[0][0][1:].std(dim=(0, 1))  # (7,) over candidates and steps, the mean left out
    want = torch.tensor([base.init_std * s for s in seven.sigma_scale])  # (7,)
    n = 6 if name == "cem-gripper" else 7  # cem-gripper draws the gripper from categories, not a Gaussian
    assert torch.allclose(spread[:n], want[:n], rtol=0.1)


def test_a_tasks_sigma_scale_is_checked():
    from wamplan.envs.maniskill import maniskill_task
    with pytest.raises(ValueError, match="sigma_scale needs 7 entries > 0"):
        maniskill_task("Toy-v1", name="toy", cameras=("c",), action_dim=7, proprio_dim=3, max_episode_steps=9,
                       instruction="", sigma_scale=(1.0, 0.0))
