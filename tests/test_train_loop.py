"""The shared training loop: one run layout, one resume rule (same data, same config) for `wm train` and
`wam train`, metrics.jsonl from both, `wamplan plot`, and the presets and reproduce stages agreeing."""

import argparse
import json
import shutil

import pytest

from wamplan.cli import build_parser, main
from wamplan.config import from_args

TINY_WAM = ["--image-size", "32", "--channels", "8", "16", "--latent-dim", "32", "--trunk-dim", "64"]


pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def stores(tmp_path_factory, expert_store):
    """The session's expert store of 2 episodes (copied: training writes beside it) and a copy of it elsewhere with
    one episode less (other data)."""
    root = tmp_path_factory.mktemp("loop")
    store = root / "expert"
    shutil.copytree(expert_store, store)
    other = root / "other"
    shutil.copytree(store, other)
    sorted((other / "episodes").glob("*.h5"))[-1].unlink()
    return store, other


def _one_line_error(capsys, argv: list[str]) -> str:
    assert main(argv) == 2
    lines = capsys.readouterr().err.strip().splitlines()  # progress bars (\r) may come before the error
    err = lines[-1]
    assert err.startswith("wamplan: error:") and sum("wamplan:" in x for x in lines) == 1, lines
    return err


def test_wm_train_resume_refuses_other_data_and_config(stores, tmp_path, capsys):
    store, other = stores
    run = tmp_path / "wm"
    args = ["wm", "train", "--data", str(store), "--out", str(run), "--preset", "mini", "--batch-size", "4",
            "--epochs", "2", "--max-steps", "3", "--log-every-steps", "1", "--device", "cpu"]
    assert main(args) == 0
    assert (run / "checkpoint" / "model.safetensors").is_file() and (run / "checkpoint" / "training_state").is_dir()
    recs = [json.loads(x) for x in (run / "metrics.jsonl").read_text().splitlines()]
    assert [r["global_step"] for r in recs] == [1, 2, 3] and all(r["event"] == "step" for r in recs)
    assert all({"epoch", "lr", "train/loss", "train/z_mse_h1"} <= set(r) for r in recs)
    capsys.readouterr()

    err = _one_line_error(capsys, [*args[:3], f"{other}", *args[4:]])
    assert "was trained on different data" in err and "different stores" in err and "different episodes" in err
    assert "2 episode files" in err and "1 episode files" in err and "same --data or use another --out" in err
    err = _one_line_error(capsys, [*args, "--lr", "0.5"])
    assert "different config" in err and "different lr: saved 0.001, now 0.5" in err

    # the same command resumes (the max-steps stop is re-logged nowhere: records continue at step 4), a run saved
    # with the retired ranking-loss keys too (stored by older versions, as checkpoints/stack-cube/wm_augmented), and
    # with the retired spread and state heads' keys at their off values (stored by every run of stops 55-77, the
    # state head's by checkpoints/stack-cube/wm_augmented too)
    from wamplan.checkpoint import CONFIG_FILE
    from wamplan.worldmodel.config import RETIRED_PREDICTOR_KEYS, RETIRED_TRAIN_KEYS

    path = run / "checkpoint" / CONFIG_FILE
    ckpt = json.loads(path.read_text())
    ckpt["config"]["train"].update(rank_weight=0.0, rank_wam="", rank_temperature=0.1, spread_weight=0.0,
                                   spread_only=False, state_weight=0.0)
    ckpt["config"]["predictor"].update(spread_head=False, state_dim=0, state_head="mlp")
    assert set(RETIRED_TRAIN_KEYS) <= set(ckpt["config"]["train"])
    assert set(RETIRED_PREDICTOR_KEYS) <= set(ckpt["config"]["predictor"])
    path.write_text(json.dumps(ckpt))
    resume = [*args[:-8], "--log-every-steps", "1", "--device", "cpu", "--epochs", "2"]
    assert main(resume) == 0
    recs = [json.loads(x) for x in (run / "metrics.jsonl").read_text().splitlines()]
    steps = [r["global_step"] for r in recs if r["event"] == "step"]
    assert steps == list(range(1, steps[-1] + 1)) and [r["epoch"] for r in recs if r["event"] == "epoch"] == [1, 2]
    assert "val/z_mse_h1" in recs[-1] and "train/loss" in recs[-1]  # seed 1 is a validation episode

    # a run that trained a spread or a state head holds the head's weights and optimizer state: refused in one line
    saved = json.loads(path.read_text())
    for head, predictor, train in (("spread", {"spread_head": True}, {"spread_weight": 1.0, "spread_only": False}),
                                   ("state", {"state_dim": 6, "state_head": "ridge"}, {"state_weight": 0.1})):
        ckpt = json.loads(json.dumps(saved))
        ckpt["config"]["train"].update(train)
        ckpt["config"]["predictor"].update(predictor)
        path.write_text(json.dumps(ckpt))
        err = _one_line_error(capsys, resume)
        assert f"trained with a {head} head (wm train --{head}-weight)" in err and "another --out" in err, err


def test_a_predictor_saved_with_the_retired_heads_loads_without_them(tmp_path):
    """A checkpoint of the spread head (``wm train --spread-weight``) or the state head (``--state-weight``), both
    removed in stop 78 (their config keys and their heads' weights), loads as the same model without the head; the
    shipped StackCube model, which stored the state head's keys off, loads."""
    import torch
    from safetensors.torch import save_file

    from wamplan.checkpoint import MODEL_FILE, load_tensors, read_meta, save_checkpoint
    from wamplan.worldmodel.load import load_predictor

    shipped = load_predictor("checkpoints/mini/wm_augmented")
    meta = read_meta("checkpoints/mini/wm_augmented")
    d, dim, m = shipped.cfg.width, shipped.cfg.enc_dim, shipped.cfg.tokens_per_frame
    heads = {  # as each head was built: its config keys and its weights
        "spread": ({"spread_head": True}, {"spread_weight": 1.0, "spread_only": True},
                   {"spread_head.0.weight": torch.ones(d, d), "spread_head.0.bias": torch.ones(d),
                    "spread_head.2.weight": torch.ones(dim, d), "spread_head.2.bias": torch.ones(dim)}),
        "state": ({"state_dim": 6, "state_head": "ridge"}, {"state_weight": 0.1},
                  {"state_head.linear.weight": torch.ones(6, m * dim), "state_head.linear.bias": torch.ones(6)})}
    want = shipped.state_dict()
    for name, (predictor, train, weights) in heads.items():
        record = json.loads(json.dumps(meta["config"]))
        record["predictor"].update(predictor)
        record["train"].update(train)
        ckpt = save_checkpoint(tmp_path / name, shipped, record, kind=meta["kind"])
        save_file({**load_tensors(ckpt / MODEL_FILE), **weights}, str(ckpt / MODEL_FILE))
        model = load_predictor(ckpt)
        assert model.cfg == shipped.cfg and not hasattr(model, f"{name}_head")
        assert model.state_dict().keys() == want.keys()
        assert all(torch.equal(v, want[k]) for k, v in model.state_dict().items())
    stack = "checkpoints/stack-cube/wm_augmented"
    assert {"state_dim", "state_head"} <= set(read_meta(stack)["config"]["predictor"])
    assert load_predictor(stack).task.name == "stack-cube"


def test_wam_train_resume_refuses_other_data_and_logs_metrics(stores, tmp_path, capsys):
    store, other = stores
    run = tmp_path / "wam"
    args = ["wam", "train", "--data", str(store), "--out", str(run), "--epochs", "2", "--batch-size", "8",
            "--log-every-steps", "4", "--no-progress", "--device", "cpu", *TINY_WAM]
    assert main([*args, "--max-steps", "5"]) == 0
    capsys.readouterr()
    err = _one_line_error(capsys, [*args[:3], str(other), *args[4:]])
    assert "was trained on different data" in err and "different stores" in err and "--data" in err
    err = _one_line_error(capsys, [*args, "--sources", "noisy-expert"])
    assert "different data (different sources: saved null, now [\"noisy-expert\"])" in err

    assert main(args) == 0  # resumes from step 5 to the end
    recs = [json.loads(x) for x in (run / "metrics.jsonl").read_text().splitlines()]
    epochs = [r for r in recs if r["event"] == "epoch"]
    steps = [r for r in recs if r["event"] == "step"]
    assert [r["epoch"] for r in epochs] == [1, 2] and steps and all(r["global_step"] % 4 == 0 for r in steps)
    assert {"train/loss", "train/act", "train/img", "lr", "samples_per_s"} <= set(epochs[-1])
    assert "val/action_mse" in epochs[-1]
    assert len({r["global_step"] for r in steps}) == len(steps)  # nothing logged twice across the resume

    # plot: a PNG of the curves
    png = tmp_path / "curves.png"
    assert main(["plot", str(run), "--out", str(png)]) == 0
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    import matplotlib.image
    h, w = matplotlib.image.imread(png).shape[:2]
    assert (w, h) == (1210, 440)
    assert main(["plot", str(run)]) == 0 and (run / "curves.png").is_file()
    err = _one_line_error(capsys, ["plot", str(tmp_path / "nothing")])
    assert "no training metrics" in err


def test_old_layout_checkpoints_load_and_are_not_trained_into(stores, tmp_path, capsys):
    from pathlib import Path

    from wamplan.wam import load_wam
    from wamplan.worldmodel.load import load_world_model

    ck = Path(__file__).parents[1] / "checkpoints" / "mini"
    assert load_wam(ck / "tinywam").name == "tinywam"
    model, enc = load_world_model(ck / "wm_augmented")
    assert (model.cfg.num_patches, enc.name) == (16, "patch-pixels")
    old = tmp_path / "old"
    shutil.copytree(ck / "tinywam", old)
    err = _one_line_error(capsys, ["wam", "train", "--data", str(stores[0]), "--out", str(old)])
    assert "holds a 'tinywam' checkpoint (a checkpoint directory, not a run directory)" in err and "new --out" in err
    # wm train says so before it encodes the stores, and checks --init's kind there too
    fresh = tmp_path / "fresh"  # a store no test has encoded yet
    shutil.copytree(stores[0], fresh, ignore=shutil.ignore_patterns("features"))
    err = _one_line_error(capsys, ["wm", "train", "--data", str(fresh), "--out", str(old)])
    assert "holds a 'tinywam' checkpoint" in err
    err = _one_line_error(capsys, ["wm", "train", "--data", str(fresh), "--out", str(tmp_path / "n"), "--init",
                                   str(old)])
    assert "--init: " in err and "not 'wm-predictor'" in err
    assert not (fresh / "features").exists()  # refused before the store was encoded



def test_trainer_configs_share_one_base_and_read_the_shipped_checkpoints():
    """The three training configs extend LoopConfig; the shipped checkpoints' train sections load into them with
    the keys they were saved with (a decoder's older predictor-only keys aside), and an option generated for one
    config is refused, not dropped, when overlaid on another that lacks the field."""
    from pathlib import Path

    from wamplan.checkpoint import CONFIG_FILE
    from wamplan.config import ConfigError, add_arguments, from_dict, to_dict
    from wamplan.train_loop import LoopConfig
    from wamplan.wam.train import WAMTrainConfig
    from wamplan.worldmodel.config import DecoderTrainConfig, TrainConfig
    from wamplan.worldmodel.decoder import PREDICTOR_ONLY_TRAIN_KEYS

    ck = Path(__file__).parents[1] / "checkpoints" / "mini"
    for name, cls in (("tinywam", WAMTrainConfig), ("wm_plain", TrainConfig), ("wm_augmented", TrainConfig),
                      ("decoder", DecoderTrainConfig)):
        assert issubclass(cls, LoopConfig)
        saved = json.loads((ck / name / CONFIG_FILE).read_text())["config"]["train"]
        if cls is DecoderTrainConfig:
            saved = {k: v for k, v in saved.items() if k not in PREDICTOR_ONLY_TRAIN_KEYS}
        cfg = from_dict(cls, saved)
        assert {k: v for k, v in to_dict(cfg).items() if k in saved} == saved, name
        if name in ("tinywam", "wm_augmented"):  # saved by the current code: the same keys, no more (but fields
            # added since, whose defaults change nothing the checkpoint did)
            newer = {"precision": "float32", "log": ()}
            newer |= {"change_weight": 0} if name == "wm_augmented" else {}
            assert set(to_dict(cls())) - set(newer) == set(saved), name
            assert all(getattr(cls(), k) == v for k, v in newer.items()), name
    parser = argparse.ArgumentParser()
    add_arguments(parser, TrainConfig)
    with pytest.raises(ConfigError, match="--horizon does not apply to DecoderTrainConfig"):
        from_args(TrainConfig, parser.parse_args(["--lr", "0.01", "--horizon", "3"]), DecoderTrainConfig())
    assert from_args(TrainConfig, parser.parse_args(["--lr", "0.01"]), DecoderTrainConfig()) == \
        DecoderTrainConfig(lr=0.01)


def test_adamw_betas_are_declared_once_and_fit_reads_them(tmp_path, monkeypatch):
    """The predictor's and the decoder's configs share AdamWConfig's betas (and its check); fit uses cfg.betas,
    and AdamW's default for a config without them."""
    import torch

    import wamplan.train_loop as loop
    from wamplan.config import ConfigError
    from wamplan.wam.train import WAMTrainConfig
    from wamplan.worldmodel.config import DecoderTrainConfig, TrainConfig

    assert issubclass(TrainConfig, loop.AdamWConfig) and issubclass(DecoderTrainConfig, loop.AdamWConfig)
    assert not issubclass(TrainConfig, DecoderTrainConfig) and not issubclass(WAMTrainConfig, loop.AdamWConfig)
    for cls in (TrainConfig, DecoderTrainConfig):
        with pytest.raises(ConfigError, match=f"{cls.__name__}.betas must be two numbers in"):
            cls(betas=(0.9, 1.0))
    with pytest.raises(ConfigError, match="seeds must lie in 0 .. 4294967295"):
        TrainConfig(seed=2**32)
    seen = []

    def spy(model, lr, weight_decay, **kw):
        seen.append(kw.get("betas"))
        return torch.optim.AdamW(model.parameters(), lr=lr, **kw)

    monkeypatch.setattr(loop, "make_adamw", spy)
    data = torch.utils.data.TensorDataset(torch.randn(4, 3))

    def step(m, b):
        return m(b[0]).pow(2).mean(), {}

    for i, cfg in enumerate((DecoderTrainConfig(epochs=1, batch_size=2, betas=(0.5, 0.6)),
                             WAMTrainConfig(epochs=1, batch_size=2))):
        loop.fit(torch.nn.Linear(3, 1), loop.DatasetBatches(data), step, cfg, run_dir=tmp_path / str(i),
                 kind="test", config={}, progress=False, log=None)
    assert seen == [(0.5, 0.6), None]

def test_preset_sizes_agree():
    from wamplan.encoders import make_encoder
    from wamplan.presets import PRESETS
    from wamplan.wam.tinywam import TinyWAMConfig
    from wamplan.wam.train import WAMTrainConfig

    for p in PRESETS.values():
        wm, tw = p.world_model, p.tinywam.for_task("cube-insertion")  # the sizes of the cube task's stores
        side = wm.encoder_kwargs["input_size"] // wm.encoder_kwargs.get("patch_size", 16)
        assert wm.predictor.num_patches == side * side == wm.decoder.num_patches, p.name
        assert wm.predictor.enc_dim == wm.decoder.enc_dim and wm.predictor.encoder == wm.encoder
        assert wm.decoder.image_size == wm.encoder_kwargs["input_size"]
        assert (wm.predictor.action_dim, wm.predictor.proprio_dim, wm.predictor.num_views) == \
            (tw.action_dim, tw.proprio_dim, len(tw.cameras))
        assert wm.predictor.frameskip % p.image_every == 0 and tw.chunk_length % p.image_every == 0
        assert p.wm_epochs == wm.train.epochs and p.wam_epochs == p.tinywam_train.epochs
    mini = PRESETS["mini"].world_model
    enc = make_encoder(mini.encoder, **mini.encoder_kwargs)
    assert (enc.num_patches, enc.dim) == (mini.predictor.num_patches, mini.predictor.enc_dim)
    assert (PRESETS["paper"].expert, PRESETS["paper"].noisy, PRESETS["paper"].eval_episodes) == (100, 500, 50)
    assert (PRESETS["mini"].wm_epochs, PRESETS["mini"].wam_epochs) == (4, 12)  # the demo checkpoints' settings
    assert PRESETS["mini"].tinywam == TinyWAMConfig() and PRESETS["paper"].tinywam_train == WAMTrainConfig(epochs=30)


@pytest.mark.parametrize("preset", ["mini", "paper"])
def test_reproduce_calls_match_their_printed_commands(tmp_path, preset):
    """Every stage's printed command parses with the real CLI and means what the library call does."""
    from wamplan.evaluation.reproduce import plan
    from wamplan.presets import PRESETS
    from wamplan.wam.tinywam import TinyWAMConfig
    from wamplan.wam.train import WAMTrainConfig
    from wamplan.worldmodel.config import TrainConfig

    p = PRESETS[preset]
    parser = build_parser()
    stages = plan(p, tmp_path, None, 2)
    for stage in stages:
        for call in stage.calls:
            args = parser.parse_args(list(call.command))
            kw = call.kwargs
            if "stores" in kw:
                assert args.data == ",".join(str(s) for s in kw["stores"]), stage.name
                assert str(args.out) == str(kw["out"])
            if call.command[:2] == ("wam", "train"):
                assert from_args(TinyWAMConfig, args) == kw["model_cfg"]
                assert from_args(WAMTrainConfig, args) == kw["train_cfg"]
            if call.command[:2] == ("wm", "train"):
                assert from_args(TrainConfig, args, p.world_model.train) == kw["train"] == p.world_model.train
            if call.command[0] == "collect":
                assert (args.source, args.episodes, args.seed_start, args.image_every, args.workers) == \
                    (kw["source"], kw["episodes"], kw["seed_start"], kw["image_every"], kw["workers"])
                assert args.max_steps == kw["max_steps"] and args.policy == kw["policy"]
    names = [s.name for s in stages]
    assert names[-2:] == ["evaluate", "report"] and len(stages[names.index("evaluate")].calls) == 2


def test_evaluating_restores_the_mode_the_model_had_even_on_an_error():
    from torch import nn

    from wamplan.train_loop import evaluating

    net = nn.Sequential(nn.Linear(2, 2), nn.Dropout(0.5))
    with evaluating(net) as m:
        assert m is net and not net.training and not net[1].training
    assert net.training  # it was training
    with pytest.raises(RuntimeError, match="boom"):
        with evaluating(net):
            raise RuntimeError("boom")
    assert net.training
    net.eval()
    with evaluating(net):
        pass
    assert not net.training  # an eval-mode model stays in eval mode


def test_bfloat16_precision_runs_the_step_in_autocast_and_keeps_float32_weights(tmp_path):
    """--precision bfloat16: the step's matrix products run in bfloat16, the weights and their updates stay
    float32; an unknown precision is refused with the flag to pass."""
    import torch

    import wamplan.train_loop as loop
    from wamplan.config import ConfigError
    from wamplan.worldmodel.config import TrainConfig

    with pytest.raises(ConfigError, match="pass --precision float32 or bfloat16"):
        TrainConfig(precision="float16")
    data = torch.utils.data.TensorDataset(torch.randn(8, 3))
    for precision in ("float32", "bfloat16"):
        seen = []

        def step(m, b):
            out = m(b[0])  # (B, 1)
            seen.append(out.dtype)
            return out.float().pow(2).mean(), {}

        torch.manual_seed(0)
        model = torch.nn.Linear(3, 1)
        before = model.weight.detach().clone()
        loop.fit(model, loop.DatasetBatches(data), step, TrainConfig(epochs=1, batch_size=4, precision=precision),
                 run_dir=tmp_path / precision, kind="test", config={}, progress=False, log=None)
        assert set(seen) == {getattr(torch, precision)}
        assert model.weight.dtype == torch.float32 and not torch.equal(model.weight, before)
