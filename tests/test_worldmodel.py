"""World model: block causality, KV-cached rollout == naive, checkpoints, exact resume, learning, decoder."""

from __future__ import annotations

import dataclasses
import json

import pytest
import torch

from wamplan.config import ConfigError, from_dict, to_dict
from wamplan.errors import UserError
from wamplan.presets import PRESETS as ALL_PRESETS
from wamplan.presets import get_world_model_preset as get_preset
from wamplan.train_loop import CKPT_DIR, METRICS_FILE
from wamplan.worldmodel import (Decoder, DecoderConfig, DecoderTrainConfig, PredictorConfig, TrainConfig,
                                WorldModelPredictor, evaluate_predictor, load_decoder, load_predictor, train_decoder,
                                train_predictor)
from wamplan.worldmodel.synthetic import SyntheticWindows

PRESETS = {name: p.world_model for name, p in ALL_PRESETS.items()}
TINY = PredictorConfig(num_views=2, num_patches=4, enc_dim=8, proprio_dim=10, action_dim=5, frameskip=2, context=3,
                       depth=2, heads=2, head_dim=8, mlp_dim=32, proprio_emb=16, action_emb=16)
# the model variants (PredictorConfig options, off by default): each must keep causality and the KV cache exact
VARIANTS = {"default": {}, "adaln": dict(action_conditioning="adaln"), "tokens": dict(action_tokens=True),
            "adaln+tokens+direct": dict(action_conditioning="adaln", action_tokens=True, predict_delta=False)}


pytestmark = pytest.mark.usefixtures("one_thread")


def _model(cfg: PredictorConfig = TINY, seed: int = 0) -> WorldModelPredictor:
    """A predictor with all weights random (the zero-initialised delta heads would hide bugs)."""
    torch.manual_seed(seed)
    m = WorldModelPredictor(cfg).eval()
    with torch.no_grad():
        for p in m.parameters():
            p.normal_(0.0, 0.3)
        m.set_feature_stats(torch.randn(cfg.enc_dim) * 0.1, torch.rand(cfg.enc_dim) + 0.5)
    return m


def _frames(cfg: PredictorConfig, b: int, t: int, seed: int = 1):
    g = torch.Generator().manual_seed(seed)
    z = torch.randn(b, t, cfg.num_views, cfg.num_patches, cfg.enc_dim, generator=g)  # (B, T, V, N, D)
    q = torch.randn(b, t, cfg.proprio_dim, generator=g)  # (B, T, P)
    a = torch.randn(b, t, cfg.action_block_dim, generator=g)  # (B, T, Delta*A)
    return z, q, a


# -- configs and presets ---------------------------------------------------------------------------------
def test_configs_validate_with_messages_that_say_what_to_fix():
    with pytest.raises(ConfigError, match="head_dim must be even"):
        PredictorConfig(head_dim=7)
    with pytest.raises(ConfigError, match="context must be a positive int"):
        PredictorConfig(context=0)
    with pytest.raises(ConfigError, match="power of 2"):
        DecoderConfig(num_patches=16, image_size=48)
    with pytest.raises(ConfigError, match="warmup_epochs must be in"):
        TrainConfig(epochs=2, warmup_epochs=3)
    with pytest.raises(ConfigError, match="pass a positive --lr"):
        TrainConfig(lr=0)
    for cfg in (TINY, DecoderConfig(), TrainConfig(), DecoderTrainConfig()):
        assert from_dict(type(cfg), json.loads(json.dumps(to_dict(cfg)))) == cfg


def test_paper_preset_is_table_3_and_mini_divides_the_chunk():
    p = get_preset("paper")
    pr, tr = p.predictor, p.train
    assert (pr.depth, pr.heads, pr.head_dim, pr.mlp_dim, pr.proprio_emb, pr.action_emb) == (6, 16, 64, 2048, 64, 64)
    assert (pr.context, pr.frameskip, tr.horizon, tr.gamma) == (3, 5, 2, 0.95)
    assert (pr.num_views, pr.num_patches, pr.enc_dim, p.encoder) == (3, 196, 1024, "dinov3-vitl16")
    assert (tr.lr, tr.weight_decay, tr.batch_size, tr.epochs, tr.warmup_epochs, tr.grad_clip) == \
        (5e-5, 1e-3, 24, 24, 1, 1.0)
    d, dt = p.decoder, p.decoder_train
    assert (d.depth, d.heads, dt.lr, dt.weight_decay, dt.batch_size, dt.epochs, dt.warmup_epochs) == \
        (4, 8, 3e-4, 1e-5, 16, 24, 2)
    m = PRESETS["mini"]
    assert 16 % m.predictor.frameskip == 0 and (m.predictor.context, m.train.horizon) == (3, 2)
    from wamplan.encoders import make_encoder
    enc = make_encoder(m.encoder, **m.encoder_kwargs)
    assert (enc.num_patches, enc.dim) == (m.predictor.num_patches, m.predictor.enc_dim)
    assert (m.decoder.num_patches, m.decoder.enc_dim) == (enc.num_patches, enc.dim)
    with pytest.raises(UserError, match="unknown world-model preset"):
        get_preset("huge")


def test_preset_stats_counts_params_and_flops(repo_script):
    preset_stats = repo_script("benchmarks/profile_worldmodel.py").preset_stats
    s = preset_stats("mini")
    m = WorldModelPredictor(PRESETS["mini"].predictor)
    assert s["predictor"]["params"] == m.num_params()
    pr = s["predictor"]
    assert 0 < pr["forward_flops"] < pr["plan_flops_cached"] < pr["plan_flops_naive"]
    assert s["decoder"]["params"] == Decoder(PRESETS["mini"].decoder).num_params()


# -- the predictor -------------------------------------------------------------------------------------------
def test_forward_shapes_and_input_checks():
    m = _model()
    z, q, a = _frames(TINY, 3, 4)
    zp, qp = m(z, q, a)
    assert zp.shape == z.shape and qp.shape == q.shape
    with pytest.raises(ValueError, match="z must be"):
        m(z[..., :4], q, a)
    with pytest.raises(ValueError, match="Delta\\*A"):
        m(z, q, a[..., :3])


@pytest.mark.parametrize("variant", VARIANTS)
@torch.no_grad()
def test_block_causal_a_later_frame_never_changes_earlier_outputs(variant):
    m = _model(dataclasses.replace(TINY, **VARIANTS[variant]))
    z, q, a = _frames(TINY, 2, 6)
    zp, qp = m(z, q, a)
    for name, idx in (("z", 0), ("q", 1), ("a", 2)):
        inputs = [z.clone(), q.clone(), a.clone()]
        inputs[idx][:, 3] += 1.0  # perturb frame 3 only
        zp2, qp2 = m(*inputs)
        assert torch.equal(zp2[:, :3], zp[:, :3]) and torch.equal(qp2[:, :3], qp[:, :3]), name
        assert not torch.allclose(zp2[:, 3], zp[:, 3]), name  # and the frame itself does change


@torch.no_grad()
def test_frames_outside_the_window_have_no_effect():
    one_layer = _model(dataclasses.replace(TINY, depth=1))  # receptive field = the H_ctx window exactly
    z, q, a = _frames(TINY, 2, 6)
    zp, _ = one_layer(z, q, a)
    z2 = z.clone()
    z2[:, 0] += 1.0
    zp2, _ = one_layer(z2, q, a)
    assert not torch.allclose(zp2[:, 2], zp[:, 2])  # frame 2 sees frame 0 (distance 2 < H_ctx = 3)
    assert torch.equal(zp2[:, 3:], zp[:, 3:])  # frames 3.. do not (distance >= 3)
    two_layers = _model()  # depth 2: receptive field depth * (H_ctx - 1) = 4 frames back
    zp, _ = two_layers(z, q, a)
    zp2, _ = two_layers(z2, q, a)
    assert not torch.allclose(zp2[:, 4], zp[:, 4]) and torch.equal(zp2[:, 5], zp[:, 5])


@pytest.mark.parametrize("variant", VARIANTS)
@pytest.mark.parametrize("context", [1, 2, 3])
@torch.no_grad()
def test_kv_cached_rollout_equals_naive(context, variant):
    cfg = dataclasses.replace(TINY, context=context, **VARIANTS[variant])
    m = _model(cfg)
    b, s = 5, 4  # more steps than the window: the cache must slide
    z, q, a = _frames(cfg, b, context)
    a_future = _frames(cfg, b, s, seed=2)[2]  # (B, S, Delta*A)
    cached = m.rollout(z, q, a[:, :-1], a_future)  # no grad: preallocated KV rings
    with torch.enable_grad():
        concat = m.rollout(z, q, a[:, :-1], a_future)  # with autograd (training): concatenated KV
    naive = m.rollout(z, q, a[:, :-1], a_future, naive=True)
    for c, g, n in zip(cached, concat, naive):
        assert c.shape == n.shape and torch.allclose(c, n, atol=1e-5), float((c - n).abs().max())
        assert g.requires_grad and torch.allclose(g, n, atol=1e-5), float((g - n).abs().max())
    # the first step is the teacher-forced prediction from the ground-truth context
    zf, qf = m(z, q, torch.cat([a[:, :-1], a_future[:, :1]], dim=1))
    assert torch.allclose(cached[0][:, 0], zf[:, -1], atol=1e-5)
    assert torch.allclose(cached[1][:, 0], qf[:, -1], atol=1e-5)


@pytest.mark.parametrize("variant", VARIANTS)
@torch.no_grad()
def test_broadcast_prefix_equals_per_candidate_context_and_is_reusable(variant):
    m = _model(dataclasses.replace(TINY, **VARIANTS[variant]))
    b, s = 6, 3
    z, q, a = _frames(TINY, 1, 3)  # one shared context
    a_future = _frames(TINY, b, s, seed=2)[2]  # (B, S, Delta*A)
    expanded = m.rollout(z.expand(b, -1, -1, -1, -1), q.expand(b, -1, -1), a[:, :-1].expand(b, -1, -1), a_future,
                         naive=True)
    shared = m.rollout(z, q, a[:, :-1], a_future)  # context with batch 1, candidates with batch B
    prefix = m.encode_prefix(z[:, :-1], q[:, :-1], a[:, :-1])  # once per chunk
    assert prefix.batch == 1 and prefix.start == 2 and len(prefix.frames) == 2
    first = m.rollout_from_prefix(prefix, z[:, -1], q[:, -1], a_future)
    again = m.rollout_from_prefix(prefix, z[:, -1], q[:, -1], a_future.flip(0))  # another CEM iteration
    third = m.rollout_from_prefix(prefix, z[:, -1], q[:, -1], a_future)
    for e, sh, f, t, g in zip(expanded, shared, first, third, again):
        assert sh.shape[0] == b
        assert torch.allclose(sh, e, atol=1e-5) and torch.equal(f, sh) and torch.equal(t, f)  # prefix unchanged
        assert torch.allclose(g.flip(0), f, atol=1e-5)


@torch.no_grad()
def test_compiled_blocks_roll_out_as_the_eager_ones():
    graphs = []

    def counting_backend(gm, example_inputs):  # torch.compile's backend contract: return a callable
        graphs.append(gm)
        return gm.forward

    eager = _model()
    compiled = _model().compile_blocks(backend=counting_backend)  # the same weights, blocks through torch.compile
    z, q, a = _frames(TINY, 1, 3)
    a_future = _frames(TINY, 4, 3, seed=2)[2]  # (B, S, Delta*A)
    prefix_e, prefix_c = (m.encode_prefix(z[:, :-1], q[:, :-1], a[:, :-1]) for m in (eager, compiled))
    want = eager.rollout_from_prefix(prefix_e, z[:, -1], q[:, -1], a_future)
    got = compiled.rollout_from_prefix(prefix_c, z[:, -1], q[:, -1], a_future)
    assert graphs  # the blocks ran through the compiler
    for w, g in zip(want, got):
        assert g.shape == w.shape and torch.allclose(g, w, atol=1e-4)


def test_a_bfloat16_cast_keeps_the_rotary_frequencies_in_float32():
    m = _model()
    want = m.inv_freq.clone()
    m = m.to(torch.bfloat16)
    assert m.z_head.weight.dtype == torch.bfloat16 and m.inv_freq.dtype == torch.float32
    assert torch.equal(m.inv_freq, want)


# -- training -----------------------------------------------------------------------------------------------
def test_training_beats_copy_last_frame_on_held_out_dynamics(tmp_path):
    cfg = PredictorConfig(num_views=1, num_patches=4, enc_dim=8, frameskip=2, context=3, depth=2, heads=2,
                          head_dim=16, mlp_dim=64, proprio_emb=16, action_emb=16)
    train = TrainConfig(lr=3e-3, batch_size=8, epochs=12, warmup_epochs=0.5, min_lr_ratio=0.1, weight_decay=0.0)
    frames = cfg.context + train.horizon
    train_set = SyntheticWindows(256, cfg, frames, seed=0, shift=1.0)
    val_set = SyntheticWindows(128, cfg, frames, seed=1, shift=1.0)
    model, metrics = train_predictor(train_set, cfg, train, tmp_path, val_set=val_set, device="cpu", progress=False)
    for h in (1, 2):
        assert metrics[f"val/z_mse_h{h}"] < 0.6 * metrics[f"val/copy_z_mse_h{h}"], metrics
        assert metrics[f"val/q_mse_h{h}"] < 0.2 * metrics[f"val/copy_q_mse_h{h}"], metrics
    lines = (tmp_path / METRICS_FILE).read_text().splitlines()
    assert len(lines) == train.epochs and json.loads(lines[-1])["global_step"] == 12 * (256 // 8)
    # feature statistics were computed from the training set and saved with the weights
    loaded = load_predictor(tmp_path)
    assert torch.allclose(loaded.z_std, train_set.z.float().flatten(0, -2).std(0), rtol=1e-3)
    again = evaluate_predictor(loaded, val_set, train.horizon, train.gamma)
    assert again["z_mse_h1"] == pytest.approx(metrics["val/z_mse_h1"], rel=1e-5)


TRAIN = TrainConfig(lr=1e-3, batch_size=4, epochs=3, warmup_epochs=1, weight_decay=1e-3, seed=3)


def _windows(n: int = 14) -> SyntheticWindows:
    return SyntheticWindows(n, TINY, TINY.context + TRAIN.horizon, seed=0)  # 14 // 4 = 3 steps per epoch


def test_checkpoint_round_trip_gives_identical_outputs(tmp_path):
    from wamplan.encoders import make_encoder
    from wamplan.worldmodel.load import load_world_model
    enc = make_encoder("patch-pixels", input_size=32, patch_size=16, proj_dim=8)  # 4 tokens x 8, as TINY
    model, _ = train_predictor(_windows(), TINY, TRAIN, tmp_path, device="cpu", max_steps=2, progress=False,
                               encoder_info=enc.config_dict())
    fresh = load_predictor(tmp_path / CKPT_DIR)
    wm, enc2 = load_world_model(tmp_path)
    assert enc2.config_dict() == enc.config_dict() and torch.equal(wm.z_std, model.z_std)
    bad = make_encoder("patch-pixels", input_size=32, patch_size=16, proj_dim=16)
    train_predictor(_windows(), TINY, TRAIN, tmp_path / "bad", device="cpu", max_steps=1, progress=False,
                    encoder_info=bad.config_dict())
    with pytest.raises(UserError, match="use the encoder it was trained with"):
        load_world_model(tmp_path / "bad")
    assert torch.equal(fresh.z_mean, model.z_mean) and not torch.equal(fresh.z_mean, torch.zeros_like(fresh.z_mean))
    z, q, a = _frames(TINY, 2, 3)
    with torch.no_grad():
        for x, y in zip(model(z, q, a), fresh(z, q, a)):
            assert torch.equal(x, y)
    with pytest.raises(UserError, match="not a wamplan checkpoint"):
        load_predictor(tmp_path / "missing")
    with pytest.raises(UserError, match="'wm-predictor' checkpoint, not 'wm-decoder'"):
        load_decoder(tmp_path)


def test_checkpoints_record_the_task_and_cameras_and_old_ones_mean_the_cube(tmp_path):
    from wamplan.data.store import EpisodeStore
    from wamplan.envs.config import EnvConfig
    from wamplan.data.store import stores_task
    from wamplan.worldmodel.stores import predictor_for_task

    cams = ("base_camera", "hand_camera")  # TINY has 2 views, as peg-insertion-side
    train_predictor(_windows(), TINY, TRAIN, tmp_path / "peg", device="cpu", max_steps=1, progress=False,
                    task="peg-insertion-side", cameras=cams)
    peg = load_predictor(tmp_path / "peg")
    assert peg.task.name == "peg-insertion-side" and peg.cameras == cams
    train_predictor(_windows(), TINY, TRAIN, tmp_path / "none", device="cpu", max_steps=1, progress=False)
    unnamed = load_predictor(tmp_path / "none")  # records no task: the cube's, whose 3 cameras are not its 2 views
    assert unnamed.task.name == "cube-insertion" and unnamed.cameras is None
    assert WorldModelPredictor(TINY).task is None  # built in memory: not known
    shipped = load_predictor("checkpoints/mini/wm_plain")  # made before tasks
    assert shipped.task.name == "cube-insertion" and shipped.cameras == ("front", "side", "wrist")

    roots = []
    for task in ("cube-insertion", "push-cube"):
        roots.append(tmp_path / task)
        EpisodeStore(roots[-1], create=True, env=EnvConfig(task=task, camera_size=64).task_kwargs(), image_every=4)
    spec, cameras = stores_task(roots[1:])
    assert spec.name == "push-cube" and cameras == ("base_camera",)
    assert predictor_for_task(PredictorConfig(), spec, cameras) == PredictorConfig(num_views=1, proprio_dim=16,
                                                                                     action_dim=7)
    with pytest.raises(UserError, match="--data mixes tasks") as e:
        stores_task(roots)
    assert "push-cube" in str(e.value) and "\n" not in str(e.value)


def test_a_run_another_process_is_training_is_refused_and_left_as_it_was(tmp_path):
    from wamplan.train_loop import run_lock

    run = tmp_path / "run"
    train_predictor(_windows(), TINY, TRAIN, run, device="cpu", max_steps=1, progress=False)
    metrics = (run / METRICS_FILE).read_text()
    with run_lock(run):  # as a second process training it would hold it
        with pytest.raises(UserError, match="is being trained by another process now"):
            train_predictor(_windows(), TINY, TRAIN, run, device="cpu", resume=True, max_steps=2, progress=False)
    assert (run / METRICS_FILE).read_text() == metrics
    train_predictor(_windows(), TINY, TRAIN, run, device="cpu", resume=True, max_steps=2, progress=False)  # free
    again = tmp_path / "again"  # a folder emptied by `rm -rf again/*` keeps its dotted lock: still a fresh --out
    again.mkdir()
    (again / ".lock").touch()
    train_predictor(_windows(), TINY, TRAIN, again, device="cpu", max_steps=1, progress=False)


@pytest.mark.parametrize("stop", [4, 3])  # inside epoch 2; exactly at the end of epoch 1
def test_resume_continues_exactly(tmp_path, stop):
    data = _windows()
    total = 3 * 3  # 3 epochs x 3 steps
    full, _ = train_predictor(data, TINY, TRAIN, tmp_path / "full", device="cpu", progress=False)
    train_predictor(data, TINY, TRAIN, tmp_path / "split", device="cpu", max_steps=stop, progress=False)
    with pytest.raises(UserError, match="pass --resume"):
        train_predictor(data, TINY, TRAIN, tmp_path / "split", device="cpu", progress=False)
    with pytest.raises(UserError, match="different config"):
        train_predictor(data, TINY, dataclasses.replace(TRAIN, lr=2e-3), tmp_path / "split", device="cpu",
                        resume=True, progress=False)
    with pytest.raises(UserError, match="steps per epoch"):
        train_predictor(_windows(30), TINY, TRAIN, tmp_path / "split", device="cpu", resume=True, progress=False)
    resumed, metrics = train_predictor(data, TINY, TRAIN, tmp_path / "split", device="cpu", resume=True,
                                       progress=False)
    assert metrics["global_step"] == total
    for (name, a), b in zip(full.state_dict().items(), resumed.state_dict().values()):
        assert torch.equal(a, b), name
    for run in ("full", "split"):
        state = json.loads((tmp_path / run / CKPT_DIR / "training_state" / "state.json").read_text())
        assert state["train_state"]["global_step"] == total and state["scheduler"]["last_epoch"] == total
    states = [json.loads((tmp_path / r / CKPT_DIR / "training_state" / "state.json").read_text())["optimizer"]
              for r in ("full", "split")]
    assert states[0] == states[1]  # same step counts and learning rates
    logged = [json.loads(x)["epoch"] for x in (tmp_path / "split" / METRICS_FILE).read_text().splitlines()]
    assert logged == [1, 2, 3]  # every epoch validated and logged once


# -- decoder -------------------------------------------------------------------------------------------------
class _Pairs(torch.utils.data.Dataset):
    """Images whose patch (i, j) is a flat colour set by token i * grid + j (checks the row-major layout)."""

    def __init__(self, n: int, cfg: DecoderConfig, size: int = 32):
        g = torch.Generator().manual_seed(0)
        self.z = torch.randn(n, cfg.num_patches, cfg.enc_dim, generator=g)  # (n, N, D)
        colour = torch.sigmoid(2 * self.z[:, :, :3]).view(n, cfg.grid, cfg.grid, 3)  # (n, g, g, 3)
        cell = size // cfg.grid
        img = colour.repeat_interleave(cell, 1).repeat_interleave(cell, 2)  # (n, H, W, 3)
        self.img = (img * 255).round().to(torch.uint8)

    def __len__(self) -> int:
        return len(self.z)

    def __getitem__(self, i: int):
        return {"z": self.z[i], "image": self.img[i]}


def test_decoder_outputs_images_in_unit_range_and_trains(tmp_path):
    cfg = DecoderConfig(num_patches=4, enc_dim=8, image_size=16, width=32, depth=2, heads=4, mlp_dim=64,
                        head_channels=16)
    dec = Decoder(cfg)
    with torch.no_grad():
        out = dec(torch.randn(3, 4, 8) * 10)
    assert out.shape == (3, 3, 16, 16) and float(out.min()) >= 0.0 and float(out.max()) <= 1.0
    data = _Pairs(64, cfg)  # 32 px images, resized to 16 px for the loss
    train = DecoderTrainConfig(lr=3e-3, batch_size=8, epochs=20, warmup_epochs=1, weight_decay=1e-5)
    model, metrics = train_decoder(data, cfg, train, tmp_path, val_set=data, device="cpu", progress=False)
    first = json.loads((tmp_path / METRICS_FILE).read_text().splitlines()[0])
    assert metrics["val/pixel_mse"] < 0.5 * first["val/pixel_mse"], (first, metrics)
    loaded = load_decoder(tmp_path)
    with torch.no_grad():
        assert torch.equal(loaded(data.z[:2]), model(data.z[:2]))



def test_decoder_runs_store_only_decoder_fields_and_old_runs_resume(tmp_path):
    """A decoder's train section holds DecoderTrainConfig's keys; a run saved with the predictor's keys as well
    (before the decoder had its own config, as checkpoints/mini/decoder) loads and resumes, those keys ignored."""
    from pathlib import Path

    from wamplan.checkpoint import CONFIG_FILE
    from wamplan.worldmodel.decoder import PREDICTOR_ONLY_TRAIN_KEYS

    shipped = Path(__file__).parents[1] / "checkpoints" / "mini" / "decoder"
    saved = json.loads((shipped / CONFIG_FILE).read_text())["config"]["train"]
    assert {"horizon", "gamma"} <= set(saved) <= set(TrainConfig.__dataclass_fields__)
    assert load_decoder(shipped).cfg == PRESETS["mini"].decoder
    cfg = DecoderConfig(num_patches=4, enc_dim=8, image_size=16, width=32, depth=1, heads=4, mlp_dim=32,
                        head_channels=16)
    train = DecoderTrainConfig(batch_size=8, epochs=2, warmup_epochs=0)
    with pytest.raises(ConfigError, match="takes a DecoderTrainConfig"):
        train_decoder(_Pairs(16, cfg), cfg, TrainConfig(batch_size=8), tmp_path / "x", device="cpu", progress=False)
    train_decoder(_Pairs(16, cfg), cfg, train, tmp_path, device="cpu", max_steps=1, progress=False)
    path = tmp_path / CKPT_DIR / CONFIG_FILE
    ckpt = json.loads(path.read_text())
    assert set(ckpt["config"]["train"]) == set(DecoderTrainConfig.__dataclass_fields__)
    ckpt["config"]["train"].update({k: saved.get(k, 0) for k in PREDICTOR_ONLY_TRAIN_KEYS})  # the old layout
    path.write_text(json.dumps(ckpt))
    with pytest.raises(UserError, match="different lr"):  # the shared fields must still match
        train_decoder(_Pairs(16, cfg), cfg, dataclasses.replace(train, lr=1e-3), tmp_path, device="cpu",
                      resume=True, progress=False)
    _, metrics = train_decoder(_Pairs(16, cfg), cfg, train, tmp_path, device="cpu", resume=True, progress=False)
    assert metrics["epoch"] == 2

def test_action_blocks_are_time_major_and_models_run_in_bfloat16():
    from wamplan.worldmodel import action_blocks
    acts = torch.arange(2 * 8 * 5).view(2, 8, 5).float()  # (B, S*Delta, A) with Delta = 2
    blocks = action_blocks(acts, 2)  # (B, 4, 10)
    assert blocks.shape == (2, 4, 10) and torch.equal(blocks[1, 2], torch.cat([acts[1, 4], acts[1, 5]]))
    with pytest.raises(ValueError, match="frameskip 3"):
        action_blocks(acts, 3)
    m = _model().to(torch.bfloat16)
    z, q, a = _frames(TINY, 1, 3)
    a_future = _frames(TINY, 4, 2, seed=2)[2]
    with torch.no_grad():
        zc, qc = m.rollout(z, q, a[:, :-1], a_future)
        zn, qn = m.rollout(z, q, a[:, :-1], a_future, naive=True)
    assert zc.dtype == torch.bfloat16 and zc.shape == (4, 2, 2, 4, 8)
    assert torch.allclose(zc.float(), zn.float(), atol=0.1, rtol=0.05)


def test_init_fine_tunes_from_a_checkpoint_and_refuses_another_architecture(tmp_path):
    base, _ = train_predictor(_windows(), TINY, TRAIN, tmp_path / "base", device="cpu", progress=False)
    other = SyntheticWindows(14, TINY, TINY.context + TRAIN.horizon, seed=5)  # other data: other statistics
    start, _ = train_predictor(other, TINY, TRAIN, tmp_path / "ft0", device="cpu", max_steps=1, progress=False,
                               init=tmp_path / "base")
    fresh, _ = train_predictor(other, TINY, TRAIN, tmp_path / "new", device="cpu", max_steps=1, progress=False)
    assert torch.equal(start.z_mean, base.z_mean) and not torch.equal(fresh.z_mean, base.z_mean)
    for (name, a), b in zip(base.state_dict().items(), start.state_dict().values()):  # one small step from the base
        torch.testing.assert_close(a, b, atol=2e-3, rtol=0, msg=name)
    tuned, _ = train_predictor(other, TINY, TRAIN, tmp_path / "ft", device="cpu", progress=False,
                               init=tmp_path / "base")
    assert any(not torch.equal(a, b) for a, b in zip(tuned.parameters(), base.parameters()))
    assert torch.equal(tuned.z_mean, base.z_mean)
    wider = dataclasses.replace(TINY, mlp_dim=64)
    with pytest.raises(UserError, match="is another predictor .*mlp_dim.*; fine-tune with its settings "
                                        r"\(--mlp-dim 32\)"):
        train_predictor(other, wider, TRAIN, tmp_path / "bad", device="cpu", progress=False, init=tmp_path / "base")


def test_a_decoder_draws_only_the_tokens_of_the_encoder_it_was_trained_on():
    from pathlib import Path

    from wamplan.encoders import make_encoder

    shipped = Path(__file__).parents[1] / "checkpoints" / "mini" / "decoder"
    mini = make_encoder("patch-pixels", input_size=64, patch_size=16, proj_dim=128, seed=0)
    assert load_decoder(shipped, encoder=mini).cfg == PRESETS["mini"].decoder  # the shipped pair matches
    low_pass = make_encoder("patch-pixels", input_size=64, patch_size=16, proj_dim=128, basis="dct")
    with pytest.raises(UserError, match="trained on the tokens of encoder .* pass a decoder trained with the same"):
        load_decoder(shipped, encoder=low_pass)


def test_a_spliced_checkpoint_is_refused_in_one_line_naming_the_last_commit_that_loads_it(tmp_path):
    """Splices (``worldmodel.splice``, kind ``wm-splice``) left the core at stop 78 (no measured gain): such a
    checkpoint is refused in one line, not read as a predictor."""
    train_predictor(_windows(), TINY, TRAIN, tmp_path / "wm", device="cpu", max_steps=1, progress=False)
    path = tmp_path / "wm" / CKPT_DIR / "config.json"
    path.write_text(json.dumps({**json.loads(path.read_text()), "kind": "wm-splice"}))
    with pytest.raises(UserError, match="is a spliced model .* left wamplan .* loads at commit 9c6eb5d or earlier"):
        load_predictor(tmp_path / "wm")
