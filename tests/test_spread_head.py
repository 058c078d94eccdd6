"""The world model's spread head (``wm train --spread-weight``): it learns where the prediction's error is large, it
leaves the mean predictions alone (``--spread-only`` keeps an --init model's bit for bit), and the planner's
cost adds its variance (``--disagreement-weight``; an ensemble adds its members' to their disagreement)."""

from __future__ import annotations

import dataclasses
import json
import shutil

import pytest
import torch
from torch.utils.data import Dataset

from wamplan.planning.dynamics import EnsembleDynamics, LearnedDynamics, PlanningContext
from wamplan.worldmodel import PredictorConfig, TrainConfig, WorldModelPredictor, load_predictor, train_predictor
from wamplan.worldmodel.synthetic import SyntheticWindows

pytestmark = pytest.mark.usefixtures("one_thread")

TINY = PredictorConfig(num_views=1, num_patches=4, enc_dim=8, action_dim=3, frameskip=2, context=3, depth=2,
                       heads=2, head_dim=8, mlp_dim=32, proprio_emb=16, action_emb=16)
NOISE = 0.5  # the toy's noise: std NOISE * |a_2| of the frame's first step, on every token of the next frame


class NoisyWindows(Dataset):
    """:class:`SyntheticWindows` whose frames after the first carry Gaussian noise of std NOISE * |a_2| (the
    previous frame's first step's third action entry, which moves nothing): an error no mean can remove, larger
    the larger |a_2|."""

    def __init__(self, n: int, cfg: PredictorConfig, frames: int, seed: int = 0):
        base = SyntheticWindows(n, cfg, frames, seed=seed, shift=1.0)
        g = torch.Generator().manual_seed(seed + 1)
        self.q, self.a = base.q, base.a
        std = NOISE * base.a[:, :-1, 2].abs()  # (n, T-1): action block layout [step 0 (A), step 1 (A), ...]
        noise = torch.randn(base.z[:, 1:].shape, generator=g) * std[:, :, None, None, None]
        self.z = torch.cat([base.z[:, :1].float(), base.z[:, 1:].float() + noise], dim=1)  # (n, T, V, N, D)

    def __len__(self) -> int:
        return self.z.shape[0]

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        return {"z": self.z[i], "q": self.q[i], "a": self.a[i]}


@pytest.fixture(scope="module")
def headed(tmp_path_factory) -> tuple[WorldModelPredictor, dict]:
    """A TINY predictor with a spread head trained jointly on the noisy toy (240 steps at a learning rate of 3e-2,
    about 4 s), its last metrics."""
    cfg = dataclasses.replace(TINY, spread_head=True)
    train = TrainConfig(lr=3e-2, batch_size=16, epochs=10, warmup_epochs=0, weight_decay=0.0, seed=0,
                        spread_weight=1.0)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        data = NoisyWindows(384, cfg, cfg.context + train.horizon)
        return train_predictor(data, cfg, train, tmp_path_factory.mktemp("headed"),
                               val_set=NoisyWindows(96, cfg, cfg.context + 2, 7), device="cpu", progress=False)
    finally:
        torch.set_num_threads(threads)


def _context(cfg: PredictorConfig, a2: float, b: int = 6):
    """A shared history and ``b`` one-block candidates whose third action entry is ``a2`` (the rest random)."""
    g = torch.Generator().manual_seed(3)
    z = torch.randn(1, cfg.context, cfg.num_views, cfg.num_patches, cfg.enc_dim, generator=g)
    q, past = torch.zeros(1, cfg.context, cfg.proprio_dim), torch.zeros(1, cfg.context - 1, cfg.action_block_dim)
    a = torch.rand(b, 1, cfg.frameskip, cfg.action_dim, generator=g) * 2 - 1  # (B, S, Δ, A)
    a[..., 2] = a2
    return z, q, past, a.flatten(2)


def test_the_spread_head_learns_where_the_error_is_and_leaves_the_means_alone(headed):
    model, metrics = headed
    assert 0.7 < metrics["val/spread_ratio_h1"] < 1.4, metrics  # calibrated: squared error / predicted variance ~ 1
    assert metrics["val/spread_corr_h1"] > 0.5, metrics  # the tokens it expects to miss are the ones it misses
    z, q, past, a = _context(model.cfg, 0.0)
    quiet = model.rollout(z, q, past, a, spread=True)
    loud = model.rollout(z, q, past, _context(model.cfg, 1.0)[3], spread=True)
    var_quiet, var_loud = (model.token_variance(lv).mean() for lv in (quiet[2], loud[2]))
    assert var_loud > 3 * var_quiet, (var_quiet, var_loud)  # the toy's noise variance is NOISE**2 at |a_2| = 1
    for x, y in zip(quiet[:2], model.rollout(z, q, past, a)):  # the head feeds nothing back
        assert torch.equal(x, y)
    plain = WorldModelPredictor(TINY)
    with pytest.raises(ValueError, match="--spread-weight"):
        plain.rollout(z, q, past, a, spread=True)


def test_the_planners_spread_is_the_predicted_variance_and_an_ensemble_adds_its_members(headed):
    from wamplan.planning.policy import PlannedPolicyConfig
    from wamplan.planning.policy_config import PlanningError, check_fits

    model, _ = headed
    z, q, past, _ = _context(model.cfg, 0.0)
    ctx = PlanningContext(z[0], q[0], past[0])
    dyn = LearnedDynamics(model)
    dyn.prepare(ctx)
    cands = torch.rand(5, 2, 3, generator=torch.Generator().manual_seed(1)) * 2 - 1  # (B, L, A): one block
    cands[:3, 0, 2], cands[3:, 0, 2] = 0.0, 1.0
    zp, spread = dyn.predict(cands)
    torch.testing.assert_close(zp, dyn.terminal(cands))
    _, _, lv = model.rollout(z, q, past, cands.reshape(5, 1, 6), spread=True)
    torch.testing.assert_close(spread, model.token_variance(lv[:, -1]).flatten(1).mean(1))
    assert spread[3:].min() > spread[:3].max()  # the noisy candidates cost more in the expected cost
    ens = EnsembleDynamics([LearnedDynamics(model), LearnedDynamics(model)])
    ens.prepare(ctx)
    z2, spread2 = ens.predict(cands)  # identical members: no disagreement, their own variance remains
    torch.testing.assert_close(spread2, spread)
    assert dyn.spreads and ens.spreads and not LearnedDynamics(WorldModelPredictor(TINY)).spreads
    check_fits(PlannedPolicyConfig(disagreement_weight=1.0), 2, dyn)  # a headed model may weigh its spread
    with pytest.raises(PlanningError, match="spread head"):
        check_fits(PlannedPolicyConfig(disagreement_weight=1.0), 2, LearnedDynamics(WorldModelPredictor(TINY)))


def test_spread_only_fits_a_head_onto_a_checkpoint_and_keeps_its_means(expert_store, tmp_path, refused):
    from wamplan.cli import main

    store = tmp_path / "expert"
    shutil.copytree(expert_store, store)
    base = tmp_path / "base"
    args = ["wm", "train", "--data", str(store), "--epochs", "1", "--batch-size", "8", "--log-every-steps", "1"]
    assert main([*args, "--out", str(base), "--state-weight", "0.5", "--state-head", "ridge"]) == 0
    run = tmp_path / "spread"
    assert main([*args, "--out", str(run), "--spread-weight", "1", "--spread-only", "--init",
                 str(base / "checkpoint")]) == 0
    tuned, start = load_predictor(run), load_predictor(base)
    assert tuned.cfg.spread_head and tuned.spread_head is not None and start.spread_head is None
    assert tuned.state_head is not None and tuned.cfg.state_head == "ridge"  # the init's state head, kept as it was
    own = tuned.state_dict()
    assert {k for k in own if not k.startswith("spread_head.")} == set(start.state_dict())
    for k, v in start.state_dict().items():  # frozen: the --init checkpoint's weights, bit for bit
        assert torch.equal(own[k], v), k
    logged = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    assert any("train/spread_nll_h2" in m for m in logged)
    val = [m for m in logged if "val/spread_ratio_h2" in m]
    assert val and val[-1]["val/spread_ratio_h2"] > 0 and -1 <= val[-1]["val/spread_corr_h2"] <= 1
    refused([*args, "--out", tmp_path / "alone", "--spread-weight", "1", "--spread-only"], "--spread-only", "--init")
    refused([*args, "--out", tmp_path / "unweighed", "--spread-only"], "--spread-weight")
    refused([*args, "--out", tmp_path / "both", "--spread-weight", "1", "--spread-only", "--state-weight", "0.5",
             "--init", base / "checkpoint"], "--spread-only", "--state-weight", "drop them")


def test_fidelity_refuses_a_spread_weight_without_a_model_that_spreads(refused):
    refused(["wm", "fidelity", "--wam", "checkpoints/mini/tinywam", "--wm", "checkpoints/mini/wm_augmented",
             "--seeds", "500", "--plan-spread-weight", "1"], "--plan-spread-weight", "--spread-weight")
    refused(["wm", "fidelity", "--wam", "checkpoints/mini/tinywam", "--wm", "checkpoints/mini/wm_augmented",
             "--seeds", "500", "--plan-spread-weight", "0"], "--plan-spread-weight 0 must be a finite number above 0")
