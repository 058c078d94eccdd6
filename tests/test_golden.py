"""Golden outputs (as lerobot does): seeded models and a seeded plan must keep producing the numbers stored
in tests/golden/golden.safetensors, so a silent numerical change (an init, a layer, the sampler, a library
upgrade) fails a test instead of drifting results.

* TinyWAM: a small config built under a fixed seed, one forward pass on seeded inputs;
* the world-model predictor: a small config built under a fixed seed, a KV-cached rollout of seeded inputs;
* CEM and MPPI: a seeded plan on a seeded quadratic objective.

Zero-initialised parameters (TinyWAM's residual and FiLM heads, the predictor's positions) are filled with
seeded noise after the seeded build, so those layers are exercised too.

To change the stored outputs ON PURPOSE (a deliberate change of the numerics), regenerate them, look at
the diff of what moved, and commit the file with a message saying why:

    WAMPLAN_REGEN_GOLDEN=1 PYTHONPATH=src python -m pytest -q tests/test_golden.py
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file, save_file

from wamplan.planning import CEMConfig, MPPIConfig, make_planner
from wamplan.wam.tinywam import TinyWAMConfig, TinyWAMNet
from wamplan.worldmodel.config import PredictorConfig
from wamplan.worldmodel.predictor import WorldModelPredictor

GOLDEN = Path(__file__).parent / "golden" / "golden.safetensors"
REGEN = os.environ.get("WAMPLAN_REGEN_GOLDEN") == "1"
RTOL, ATOL = 1e-4, 1e-5  # float32 on a CPU; leaves room for another BLAS, not for a changed computation


@pytest.fixture(scope="module")
def store():
    """Compares (or, with WAMPLAN_REGEN_GOLDEN=1, collects and writes) the named outputs."""
    want = {} if REGEN else load_file(GOLDEN)
    got: dict[str, torch.Tensor] = {}

    def check(name: str, value: torch.Tensor) -> None:
        value = value.detach().to(torch.float32).contiguous().cpu()
        got[name] = value
        if not REGEN:
            assert name in want, f"{name} is not in {GOLDEN}; regenerate with WAMPLAN_REGEN_GOLDEN=1"
            torch.testing.assert_close(value, want[name], rtol=RTOL, atol=ATOL, msg=lambda m: f"{name}: {m}")

    yield check
    if REGEN:
        GOLDEN.parent.mkdir(parents=True, exist_ok=True)
        save_file(dict(sorted(got.items())), GOLDEN)


def _seeded(module: torch.nn.Module, seed: int) -> torch.nn.Module:
    """Fill the all-zero parameters of a seeded build with seeded noise (std 0.05)."""
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in module.parameters():
            if not p.any():
                p.copy_(torch.randn(p.shape, generator=gen) * 0.05)
    return module.eval()


def test_tinywam_forward(store):
    torch.manual_seed(0)
    cfg = TinyWAMConfig(image_size=16, channels=(8, 16), latent_dim=16, trunk_dim=32).for_task("cube-insertion")
    net = _seeded(TinyWAMNet(cfg), 1)
    gen = torch.Generator().manual_seed(2)
    images = torch.rand(2, 3, 3, 16, 16, generator=gen)  # (B, V, 3, S, S)
    proprio = torch.randn(2, 10, generator=gen)  # (B, P)
    with torch.no_grad():
        actions, future = net(images, proprio)  # (B, H, A), (B, V, 3, S, S)
    assert actions.shape == (2, 16, 5) and future.shape == (2, 3, 3, 16, 16)
    store("tinywam.actions", actions)
    store("tinywam.future", future)


def test_predictor_rollout(store):
    torch.manual_seed(0)
    cfg = PredictorConfig(num_patches=4, enc_dim=8, frameskip=2, context=3, depth=2, heads=2, head_dim=8,
                          mlp_dim=32, proprio_emb=8, action_emb=8)
    model = _seeded(WorldModelPredictor(cfg), 1)
    gen = torch.Generator().manual_seed(2)
    z = torch.randn(1, 3, 3, 4, 8, generator=gen)  # (1, Tc, V, N, D)
    q = torch.randn(1, 3, 10, generator=gen)  # (1, Tc, P)
    a_past = torch.rand(1, 2, 10, generator=gen) * 2 - 1  # (1, Tc-1, Δ·A)
    a_future = torch.rand(2, 3, 10, generator=gen) * 2 - 1  # (B, S, Δ·A)
    with torch.no_grad():
        zp, qp = model.rollout(z, q, a_past, a_future)  # (B, S, V, N, D), (B, S, P)
        naive = model.rollout(z, q, a_past, a_future, naive=True)
    torch.testing.assert_close(zp, naive[0], rtol=1e-5, atol=1e-5)  # the KV cache changes nothing
    store("predictor.z", zp)
    store("predictor.q", qp)


@pytest.mark.parametrize("name, config", [("cem", CEMConfig(num_candidates=16, num_elites=4, iterations=3)),
                                          ("mppi", MPPIConfig(num_candidates=16, iterations=3, temperature=0.2))])
def test_seeded_plan_on_a_toy_objective(store, name, config):
    gen = torch.Generator().manual_seed(3)
    target = torch.rand(8, 5, generator=gen) * 2 - 1  # (H, A)
    seed_actions = torch.rand(8, 5, generator=gen) * 2 - 1  # (H, A)

    def objective(cand: torch.Tensor) -> torch.Tensor:  # (B, H, A) -> (B,)
        return (cand - target).square().mean(dim=(1, 2))

    result = make_planner(name, config).plan(seed_actions, objective, seed=0)
    assert result.best_cost < result.seed_cost  # the search improves on the seed
    store(f"{name}.actions", result.actions)
    store(f"{name}.std", result.std)
    store(f"{name}.costs", torch.tensor([[h.cost_mean, h.cost_min, h.elite_cost_mean, h.mean_cost, h.std_mean]
                                         for h in result.history]))
