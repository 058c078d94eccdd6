"""World-model variants (issue 41): adaLN action conditioning, action tokens, the change-weighted loss, the
architecture options of `wm train`; old checkpoints load with the defaults. Causality and the KV cache of every
variant are tested in test_worldmodel.py (``VARIANTS``)."""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

import pytest
import torch

from wamplan.config import ConfigError, from_dict, to_dict
from wamplan.train_loop import CKPT_DIR
from wamplan.worldmodel import PredictorConfig, TrainConfig, WorldModelPredictor, load_predictor, train_predictor
from wamplan.worldmodel.config import ARCHITECTURE_FIELDS, add_architecture_arguments, architecture_from_args
from wamplan.worldmodel.layers import AdaLNBlock
from wamplan.worldmodel.synthetic import SyntheticWindows
from wamplan.worldmodel.losses import change_weights, window_loss

SHIPPED = Path(__file__).parents[1] / "checkpoints" / "mini"
TINY = PredictorConfig(num_views=1, num_patches=4, enc_dim=8, frameskip=2, context=3, depth=2, heads=2, head_dim=8,
                       mlp_dim=32, proprio_emb=16, action_emb=16)
VARIANTS = {"adaln": dict(action_conditioning="adaln"), "tokens": dict(action_tokens=True),
            "adaln+tokens": dict(action_conditioning="adaln", action_tokens=True),
            "wide": dict(depth=3, heads=4, mlp_dim=64)}


pytestmark = pytest.mark.usefixtures("one_thread")


def _frames(cfg: PredictorConfig, b: int, t: int, seed: int = 1):
    g = torch.Generator().manual_seed(seed)
    z = torch.randn(b, t, cfg.num_views, cfg.num_patches, cfg.enc_dim, generator=g)  # (B, T, V, N, D)
    q = torch.randn(b, t, cfg.proprio_dim, generator=g)  # (B, T, P)
    a = torch.rand(b, t, cfg.action_block_dim, generator=g) * 2 - 1  # (B, T, Δ·A)
    return z, q, a


# -- configs and old checkpoints -----------------------------------------------------------------------------
def test_variants_are_off_by_default_and_old_configs_load_with_the_defaults():
    cfg = PredictorConfig()
    assert (cfg.action_conditioning, cfg.action_tokens, cfg.frame_tokens) == ("input", False, cfg.tokens_per_frame)
    assert TrainConfig().change_weight == 0.0
    for name in ("wm_augmented", "wm_plain"):
        saved = json.loads((SHIPPED / name / "config.json").read_text())["config"]
        assert "action_conditioning" not in saved["predictor"] and "change_weight" not in saved["train"]
        model = load_predictor(SHIPPED / name)  # keys the file lacks take their defaults
        assert model.cfg.action_conditioning == "input" and not model.cfg.action_tokens
        assert not any(isinstance(b, AdaLNBlock) for b in model.blocks)
        assert from_dict(TrainConfig, saved["train"]).change_weight == 0.0
    with pytest.raises(ConfigError, match="action_conditioning must be one of"):
        PredictorConfig(action_conditioning="film")
    with pytest.raises(ConfigError, match="change_weight must be >= 0"):
        TrainConfig(change_weight=-1)
    from wamplan.errors import UserError
    from wamplan.presets import get_world_model_preset
    from wamplan.worldmodel.finetune import check_init

    mini = get_world_model_preset("mini").predictor
    check_init(SHIPPED / "wm_augmented", mini, None)  # `wm train --init` from a checkpoint saved before the options
    with pytest.raises(UserError, match="is another predictor .*action_conditioning"):
        check_init(SHIPPED / "wm_augmented", dataclasses.replace(mini, action_conditioning="adaln"), None)
    wide = PredictorConfig(action_tokens=True, frameskip=4)
    assert wide.frame_tokens == wide.tokens_per_frame + 4
    assert from_dict(PredictorConfig, json.loads(json.dumps(to_dict(wide)))) == wide


def test_wm_train_takes_architecture_options_over_the_preset():
    p = argparse.ArgumentParser()
    add_architecture_arguments(p)
    base = PredictorConfig()
    assert architecture_from_args(p.parse_args([]), base) == base
    args = p.parse_args(["--depth", "6", "--head-dim", "48", "--action-conditioning", "adaln", "--action-tokens",
                         "--no-predict-delta", "--frameskip", "16", "--context", "2"])
    cfg = architecture_from_args(args, base)
    assert (cfg.depth, cfg.width, cfg.action_conditioning, cfg.action_tokens, cfg.predict_delta) == \
        (6, 4 * 48, "adaln", True, False)
    assert (cfg.frameskip, cfg.context, cfg.action_block_dim) == (16, 2, 16 * base.action_dim)
    assert cfg.num_patches == base.num_patches and "num_patches" not in ARCHITECTURE_FIELDS  # the encoder's layout
    with pytest.raises(ConfigError, match=r"^--action-conditioning must be one of"):  # named as the option
        architecture_from_args(p.parse_args(["--action-conditioning", "tokens"]), base)


# -- the variants ---------------------------------------------------------------------------------------------
@torch.no_grad()
def test_adaln_zero_starts_every_block_as_the_identity():
    torch.manual_seed(0)
    m = WorldModelPredictor(dataclasses.replace(TINY, action_conditioning="adaln")).eval()
    assert all(isinstance(b, AdaLNBlock) and not b.ada[-1].weight.any() for b in m.blocks)
    z, q, a = _frames(m.cfg, 2, 4)
    out = m(z, q, a)
    m.blocks = torch.nn.ModuleList()  # no blocks at all
    for x, y in zip(out, m(z, q, a)):
        torch.testing.assert_close(x, y)


@pytest.mark.parametrize("variant", ["adaln", "tokens"])
@torch.no_grad()
def test_each_variant_carries_the_action_past_the_input(variant):
    """With the input path's action weights zeroed, the actions still move the prediction: through every
    block's modulation (adaln) or through the action tokens."""
    torch.manual_seed(0)
    m = WorldModelPredictor(dataclasses.replace(TINY, **VARIANTS[variant])).eval()
    for p in m.parameters():
        p.normal_(0.0, 0.3)
    i_a = TINY.enc_dim + TINY.proprio_emb
    m.in_proj.weight[:, i_a:] = 0  # (d, Ea): the input concatenation no longer sees the actions
    z, q, a = _frames(m.cfg, 2, 3)
    zp, _ = m.rollout(z, q, a[:, :-1], a[:, -1:])
    zp2, _ = m.rollout(z, q, a[:, :-1], -a[:, -1:])
    assert (zp - zp2).abs().max() > 1e-3
    plain = WorldModelPredictor(TINY).eval()
    plain.load_state_dict({k: v for k, v in m.state_dict().items() if k in plain.state_dict()}, strict=True)
    zp, _ = plain.rollout(z, q, a[:, :-1], a[:, -1:])
    zp2, _ = plain.rollout(z, q, a[:, :-1], -a[:, -1:])
    torch.testing.assert_close(zp, zp2)  # the input model, the same weights: blind to the action


@pytest.mark.parametrize("variant", VARIANTS)
def test_variant_shapes_training_and_save_load_round_trip(variant, tmp_path):
    cfg = dataclasses.replace(TINY, **VARIANTS[variant])
    train = TrainConfig(lr=3e-3, batch_size=8, epochs=1, warmup_epochs=0, weight_decay=0.0, seed=1)
    data = SyntheticWindows(64, cfg, cfg.context + train.horizon, seed=0, shift=1.0)
    torch.manual_seed(0)
    fresh = WorldModelPredictor(cfg)
    batch = {k: torch.stack([data[i][k] for i in range(16)]) for k in ("z", "q", "a")}
    with torch.no_grad():
        before, _ = window_loss(fresh, batch, train.horizon, train.gamma)
    model, _ = train_predictor(data, cfg, dataclasses.replace(train, epochs=3), tmp_path, device="cpu",
                               progress=False)  # 24 steps
    with torch.no_grad():
        after, _ = window_loss(model, batch, train.horizon, train.gamma)
        zp, qp = model(batch["z"], batch["q"], batch["a"])
    assert zp.shape == batch["z"].shape and qp.shape == batch["q"].shape
    assert float(after) < 0.7 * float(before), (float(before), float(after))
    loaded = load_predictor(tmp_path / CKPT_DIR)
    assert loaded.cfg == cfg and loaded.num_params() == model.num_params()
    with torch.no_grad():
        for x, y in zip(model(batch["z"], batch["q"], batch["a"]), loaded(batch["z"], batch["q"], batch["a"])):
            assert torch.equal(x, y)


# -- the change-weighted loss ----------------------------------------------------------------------------------
def test_change_weights_average_one_and_favour_the_tokens_that_change():
    z_cur = torch.zeros(2, 1, 4, 3)  # (B, V, N, D)
    z_target = torch.zeros(2, 2, 1, 4, 3)  # (B, K, V, N, D)
    z_target[:, :, 0, 0] = 1.0  # token 0 changes, the others do not
    w = change_weights(z_cur, z_target, 3.0)  # (B, K, V, N, 1)
    assert w.shape == (2, 2, 1, 4, 1)
    torch.testing.assert_close(w.mean(dim=(2, 3, 4)), torch.ones(2, 2))
    torch.testing.assert_close(w[0, 0, 0, :, 0], torch.tensor([1 + 3 * 4, 1, 1, 1]) / 4.0)
    still = change_weights(z_cur, torch.zeros_like(z_target), 3.0)  # nothing changes: uniform
    torch.testing.assert_close(still, torch.full_like(still, 0.25))


def test_change_weight_zero_is_eq_2_and_positive_weighs_the_changing_tokens():
    torch.manual_seed(0)
    model = WorldModelPredictor(TINY).eval()
    z, q, a = _frames(TINY, 3, 5)
    batch = dict(z=z, q=q, a=a)
    with torch.no_grad():
        plain, logs = window_loss(model, batch, 2, 0.9)
        off, _ = window_loss(model, batch, 2, 0.9, change_weight=0.0)
        on, wlogs = window_loss(model, batch, 2, 0.9, change_weight=4.0)
        zp, qp = model.rollout(z[:, :3], q[:, :3], a[:, :2], a[:, 2:4])
    assert torch.equal(plain, off) and "z_wmse_h1" not in logs
    w = change_weights(z[:, 2], z[:, 3:5], 4.0)  # (B, K, V, N, 1)
    ez = ((zp - z[:, 3:5]).pow(2) * w).flatten(2).mean(-1).mean(0)  # (K,)
    eq = (qp - q[:, 3:5]).pow(2).mean(-1).mean(0)  # (K,)
    torch.testing.assert_close(on, ((ez + eq) * torch.tensor([1.0, 0.9])).sum())
    assert wlogs["z_mse_h1"] == logs["z_mse_h1"] and wlogs["z_wmse_h1"] == pytest.approx(float(ez[0]))


def test_training_with_change_weight_logs_the_weighted_error(tmp_path):
    train = TrainConfig(lr=1e-3, batch_size=4, epochs=1, warmup_epochs=0, change_weight=2.0, log_every_steps=1)
    data = SyntheticWindows(12, TINY, TINY.context + train.horizon, seed=0)
    train_predictor(data, TINY, train, tmp_path, device="cpu", progress=False)
    logged = [json.loads(x) for x in (tmp_path / "metrics.jsonl").read_text().splitlines()]
    assert any("train/z_wmse_h1" in r for r in logged)
    saved = json.loads((tmp_path / CKPT_DIR / "config.json").read_text())["config"]["train"]
    assert saved["change_weight"] == 2.0


@pytest.mark.parametrize("variant", ["adaln", "adaln+tokens"])
def test_every_variant_plans_through_the_kv_cached_dynamics(variant):
    """The planner's path (LearnedDynamics: a batch-1 prefix, candidates rolled out from it) runs every variant,
    and its terminal predictions are the naive rollout's."""
    from wamplan.planning.dynamics import LearnedDynamics, PlanningContext
    from wamplan.planning.timing import plan_seconds

    cfg = dataclasses.replace(TINY, **VARIANTS[variant])
    torch.manual_seed(0)
    model = WorldModelPredictor(cfg).eval()
    with torch.no_grad():
        for p in model.parameters():
            p.normal_(0.0, 0.3)
    z, q, a = _frames(cfg, 1, cfg.context)
    ctx = PlanningContext(z=z[0], q=q[0], a=a[0, :-1])
    dyn = LearnedDynamics(model)
    dyn.prepare(ctx)
    cand = torch.rand(5, dyn.covered(8), cfg.action_dim) * 2 - 1  # (B, L, A): 8 steps = 4 frames of Δ 2
    with torch.no_grad():
        naive, _ = model.rollout(z, q, a[:, :-1], cand.reshape(5, 4, cfg.action_block_dim), naive=True)
    torch.testing.assert_close(dyn.terminal(cand), naive[:, -1], atol=1e-5, rtol=1e-5)
    assert plan_seconds(model, ctx, z[0, -1], candidates=4, iterations=1, repeats=1, chunk=8) > 0


def test_wm_train_encoder_kwargs_reach_the_features_and_the_checkpoint(expert_store, tmp_path, capsys):
    import shutil

    from wamplan.cli import main
    from wamplan.data.features import feature_key
    from wamplan.worldmodel.load import load_world_model

    store = shutil.copytree(expert_store, tmp_path / "expert")  # a copy: training caches features in the store
    dct = {"name": "patch-pixels", "input_size": 64, "patch_size": 16, "proj_dim": 128, "seed": 0, "basis": "dct"}
    assert main(["wm", "encode", "--data", str(store), "--encoder-kwargs", '{"basis": "dct"}']) == 0
    assert (store / "features" / feature_key(dct)).is_dir()
    assert main(["wm", "train", "--data", str(store), "--out", str(tmp_path / "wm"), "--max-steps", "1",
                 "--batch-size", "4", "--encoder-kwargs", '{"basis": "dct"}']) == 0
    _, enc = load_world_model(tmp_path / "wm")  # the encoder is rebuilt with the settings it was trained on
    assert enc.config_dict() == dct
    capsys.readouterr()
    assert main(["wm", "train", "--data", str(store), "--out", str(tmp_path / "bad"), "--max-steps", "1",
                 "--encoder-kwargs", "{basis: dct}"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--encoder-kwargs '{basis: dct}' is not JSON" in err[0] and not (tmp_path / "bad").exists()


def test_wm_train_frameskip_of_the_chunk_trains_a_boundary_history_model(expert_store, tmp_path, capsys):
    """`wm train --frameskip 16` (the WAM's chunk): the checkpoint's history frames are the chunk boundaries; a
    frameskip off the stores' image stride is refused in one line that names the fix."""
    import shutil

    from wamplan.cli import main
    from wamplan.planning.history import FrameHistory

    store = shutil.copytree(expert_store, tmp_path / "expert")  # a copy: training caches features in the store
    common = ["wm", "train", "--data", str(store), "--max-steps", "1", "--batch-size", "4", "--depth", "1"]
    assert main([*common, "--out", str(tmp_path / "wm16"), "--frameskip", "16", "--horizon", "1"]) == 0
    cfg = load_predictor(tmp_path / "wm16").cfg
    assert (cfg.frameskip, cfg.context, cfg.depth) == (16, 3, 1)
    assert FrameHistory(16, cfg.frameskip, cfg.context, None, torch.device("cpu")).steps(48) == [16, 32, 48]
    capsys.readouterr()
    assert main([*common, "--out", str(tmp_path / "wm6"), "--frameskip", "6"]) == 2
    err = capsys.readouterr().err.strip().splitlines()  # refused before the store is encoded again
    assert len(err) == 1 and err[0].startswith("wamplan: error: frameskip 6 is not a multiple of the store's image "
                                               "stride 4") and "--image-every" in err[0]
    assert not (tmp_path / "wm6").exists()
