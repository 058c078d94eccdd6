"""The drift planner: a response-surface step on one constant per-step offset of the chunk."""

from __future__ import annotations

import pytest
import torch

from wamplan.config import ConfigError
from wamplan.envs.maniskill import maniskill_task
from wamplan.envs.spec import get_task
from wamplan.planning import DriftConfig, make_planner
from wamplan.planning.drift import quadratic_features, surface_step
from test_planning_optimizers import Recorder

H, A = 16, 5
CUBE = get_task("cube-insertion")  # 5-D actions: x, y, z, yaw, then the gripper


def drift(cfg: DriftConfig | None = None):
    """The drift planner built for the cube task (as the planned policy builds it)."""
    return make_planner("drift", cfg).for_task(CUBE)


def _endpoint_problem(seed: int, shift: torch.Tensor):
    """Cost = squared distance of the chunk's summed arm actions (its end point under delta control) to the
    seed's own sum plus ``shift`` (4,): the WAM's chunk misses its end point by ``shift``."""
    g = torch.Generator().manual_seed(seed)
    chunk = torch.rand(H, A, generator=g) * 0.6 - 0.3  # (H, A)
    chunk[:, 4] = 1.0  # gripper open
    target = chunk[:, :4].sum(0) + shift  # (4,)
    return chunk, lambda c: (c[..., :4].sum(-2) - target).square().sum(-1), target


def test_surface_step_recovers_a_quadratic_minimum_and_respects_the_radius():
    g = torch.Generator().manual_seed(0)
    x = torch.randn(40, 3, generator=g)  # (B, d)
    opt, q = torch.tensor([0.3, -0.5, 0.2]), torch.tensor([[2.0, 0.3, 0.0], [0.3, 1.0, 0.1], [0.0, 0.1, 3.0]])
    costs = 5.0 + ((x - opt) @ q * (x - opt)).sum(1) / 2  # (B,)
    step, fitted = surface_step(x, costs, radius=10.0, ridge=0.0)
    torch.testing.assert_close(step, opt, atol=1e-5, rtol=0)
    assert float(fitted) == pytest.approx(5.0, abs=1e-5)
    short, _ = surface_step(x, costs, radius=0.2, ridge=0.0)  # the same direction, cut to the trust region
    assert float(short.norm()) == pytest.approx(0.2) and float(short @ opt / opt.norm() / 0.2) > 0.99
    # a cost that is only linear (no curvature to trust): steepest descent to the radius
    lin, _ = surface_step(x, 1.0 + x @ torch.tensor([1.0, 0.0, -1.0]), radius=0.5, ridge=0.0)
    torch.testing.assert_close(lin, torch.tensor([-1.0, 0.0, 1.0]) * 0.5 / 2**0.5, atol=1e-5, rtol=0)
    costs[3] = float("nan")  # a NaN cost is left out of the fit
    torch.testing.assert_close(surface_step(x, costs, radius=10.0, ridge=0.0)[0], opt, atol=1e-5, rtol=0)
    assert quadratic_features(x).shape == (40, 1 + 3 + 6)


def test_drift_reaches_a_displaced_end_point_with_a_constant_correction():
    shift = torch.tensor([0.3, -0.2, 0.1, 0.05])  # inside the trust region: |shift| / (16 * 0.025) < 1
    chunk, cost, target = _endpoint_problem(1, shift)
    res = drift().plan(chunk, cost, seed=0)
    torch.testing.assert_close(res.actions[:, :4].sum(0), target, atol=1e-4, rtol=0)
    corr = res.actions - chunk  # (H, A)
    torch.testing.assert_close(corr, corr[:1].expand(H, A), atol=1e-6, rtol=0)  # the same offset at every step
    assert torch.equal(res.actions[:, 4], chunk[:, 4])  # the gripper is the WAM's
    assert res.num_evaluations == 2 * 32 and res.history[-1].elite_cost_mean < 1e-4


def test_drift_moves_no_farther_than_its_trust_region():
    chunk, cost, _ = _endpoint_problem(2, torch.tensor([3.0, 0.0, 0.0, 0.0]))  # far outside the sampled region
    cfg = DriftConfig(step_radius=1.0, std_shrink=0.5, iterations=2)
    res = drift(cfg).plan(chunk, cost, seed=0)
    offset = (res.actions - chunk)[0, :4]  # (4,) per-step drift
    assert float(offset.norm()) == pytest.approx(0.025 * (1.0 + 0.5), rel=1e-4)  # one full step per iteration
    assert offset[0] > 0 and float(offset[1:].abs().max()) < 1e-3  # straight toward the end point


def test_drift_lowers_a_noisy_cost():
    """Every candidate's cost carries noise as large as the WAM chunk's whole cost; the surface, fitted on all
    candidates, still finds the downhill drift."""
    better = 0
    for s in range(20):
        g = torch.Generator().manual_seed(100 + s)
        chunk, cost, _ = _endpoint_problem(s, torch.randn(4, generator=g) * 0.2)
        scale = float(cost(chunk[None])[0])
        noisy = lambda c: cost(c) + scale * torch.randn(c.shape[0], generator=g)  # noqa: E731
        better += float(cost(drift().plan(chunk, noisy, seed=s).actions[None])[0]) < scale
    assert better >= 18


def test_drift_samples_its_search_dims_at_init_std():
    """init_std sets the drift's std on the searched dimensions; the others (the gripper by default) never move."""
    rec = Recorder(lambda c: torch.zeros(c.shape[0]))
    drift(DriftConfig(num_candidates=4001, iterations=1, init_std=0.05)).plan(
        torch.zeros(H, A), rec, seed=0)
    samples = rec.calls[0][0][1:]  # (4000, H, A)
    torch.testing.assert_close(samples.std(0)[0], torch.tensor([0.05, 0.05, 0.05, 0.05, 0.0]), atol=0.003, rtol=0)
    assert torch.equal(samples, samples[:, :1].expand_as(samples))  # one offset per candidate, every step
    rec = Recorder(lambda c: torch.zeros(c.shape[0]))
    drift(DriftConfig(iterations=1, search_dims=(0, 1))).plan(torch.zeros(H, A), rec, seed=0)
    assert rec.calls[0][0][..., 2:].abs().max() == 0 and rec.calls[0][0][..., :2].abs().max() > 0


def test_drift_config_errors():
    with pytest.raises(ConfigError, match="noise_beta does not apply"):
        DriftConfig(noise_beta=2.0)
    with pytest.raises(ConfigError, match="step_radius"):
        DriftConfig(step_radius=0.0)
    with pytest.raises(ConfigError, match="std_shrink"):
        DriftConfig(std_shrink=1.5)
    chunk, cost, _ = _endpoint_problem(0, torch.zeros(4))
    with pytest.raises(ConfigError, match="raise num_candidates above 15"):
        drift(DriftConfig(num_candidates=12)).plan(chunk, cost, seed=0)
    with pytest.raises(ConfigError, match="search_dims must be distinct"):
        DriftConfig(search_dims=(0, 0))
    with pytest.raises(ConfigError, match="name entries past task 'cube-insertion''s 5-D actions; give indices 0-4"):
        drift(DriftConfig(search_dims=(0, 5))).plan(chunk, cost, seed=0)  # refused with the task, before planning


def test_the_searched_dimensions_come_from_the_task():
    assert drift().config.search_dims == (0, 1, 2, 3)  # the cube's arm: the gripper stays the WAM's
    seven = maniskill_task("Toy-v1", name="toy", cameras=("c",), action_dim=7, proprio_dim=3, max_episode_steps=9,
                           instruction="")
    assert DriftConfig().for_task(seven).search_dims == (0, 1, 2, 3, 4, 5)
    assert DriftConfig(search_dims=(0, 1)).for_task(seven).search_dims == (0, 1)  # given: kept
    chunk, cost, _ = _endpoint_problem(0, torch.zeros(4))
    with pytest.raises(ConfigError, match="drift needs search_dims"):
        make_planner("drift").plan(chunk, cost, seed=0)  # nothing filled them
