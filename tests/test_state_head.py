"""The world model's training-only state head (``wm train --state-weight``): what it learns from, that it adds
nothing to a model without it, and that a fine-tune adds it to a checkpoint that has none."""

import json
import shutil

import h5py
import numpy as np
import pytest
import torch

from wamplan.data.readers import STATE_QUANTITIES, WorldModelWindows, state_targets
from wamplan.worldmodel.load import load_predictor

pytestmark = pytest.mark.usefixtures("one_thread")


def test_state_targets_are_the_cube_relative_to_the_tcp_and_in_the_world_in_cm(expert_store):
    path = sorted((expert_store / "episodes").glob("*.h5"))[0]
    with h5py.File(path, "r") as f:
        steps = [0, 4, 8]
        s = state_targets(f, steps)
        cube, tcp = f["cube_pose"][steps][:, :3], f["tcp_pose"][steps][:, :3]
    assert s.shape == (3, len(STATE_QUANTITIES)) and s.dtype == np.float32
    np.testing.assert_allclose(s[:, :3], (cube - tcp) * 100, rtol=1e-6)
    np.testing.assert_allclose(s[:, 3:], cube * 100, rtol=1e-6)
    windows = WorldModelWindows([expert_store], split="all", state=True)
    item = windows[0]
    assert item["s"].shape == (5, 6) and "s" not in WorldModelWindows([expert_store], split="all")[0]


def test_shipped_model_has_no_state_head_and_says_how_to_get_one():
    model = load_predictor("checkpoints/mini/wm_augmented")
    assert model.state_head is None and model.cfg.state_dim == 0
    assert not any(k.startswith("state_head") for k in model.state_dict())
    with pytest.raises(ValueError, match="--state-weight"):
        model.read_state(torch.zeros(1, 3, 16, 128))


def test_state_weight_trains_a_head_and_a_fine_tune_adds_it_to_a_checkpoint_without_one(expert_store, tmp_path,
                                                                                          capsys):
    from wamplan.cli import main

    store = tmp_path / "expert"
    shutil.copytree(expert_store, store)
    base = tmp_path / "base"
    args = ["wm", "train", "--data", str(store), "--epochs", "1", "--batch-size", "8", "--log-every-steps", "1"]
    assert main([*args, "--out", str(base)]) == 0
    run = tmp_path / "state"
    assert main([*args, "--out", str(run), "--state-weight", "0.5", "--init", str(base / "checkpoint")]) == 0
    tuned, start = load_predictor(run), load_predictor(base)
    assert tuned.cfg.state_dim == len(STATE_QUANTITIES) and tuned.state_head is not None
    shared = {k: v for k, v in start.state_dict().items()}
    assert set(shared) == {k for k in tuned.state_dict() if not k.startswith("state_head.")}
    logged = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    train_logs = [m for m in logged if "train/state_mm_h1" in m]
    assert train_logs and all(m["train/state_mm_true"] > 0 for m in train_logs)
    val = [m for m in logged if "val/state_pred_mm_h1" in m]
    assert val and val[-1]["val/state_true_mm_h1"] > 0 and val[-1]["val/state_gap_mm_h1"] >= 0
    # the head reads a frame's latents into the six quantities, true or predicted alike
    z = torch.randn(2, 3, 16, 128)  # (B, V, N, D)
    assert tuned.read_state(z).shape == (2, 6)
    # the no-head model's predictions are untouched by the option's existence
    zc, qc, ac = torch.randn(1, 3, 3, 16, 128), torch.randn(1, 3, 10), torch.randn(1, 2, 20)
    a = torch.randn(4, 2, 20)
    again = load_predictor(base)
    for x, y in zip(start.rollout(zc, qc, ac, a), again.rollout(zc, qc, ac, a)):
        assert torch.equal(x, y)


def test_the_pose_term_adds_the_squared_distance_of_the_state_readings():
    from wamplan.config import ConfigError
    from wamplan.planning.costs import CostConfig, build_cost, patch_cost, with_state_term

    read = lambda z: z.flatten(-3)[..., :2]  # noqa: E731  (a reader of two "quantities": the first two entries)
    pred, target = torch.zeros(3, 2, 1, 2), torch.zeros(2, 1, 2)  # (B, V, N, D), (V, N, D)
    pred[1, 0, 0, 0], pred[2, 0, 0, 1] = 2.0, 4.0
    cost = with_state_term(patch_cost, read, 0.5)
    # patch: the mean of 4 squared entries; pose: the mean of the 2 read ones, times 0.5
    torch.testing.assert_close(cost(pred, target), torch.tensor([0.0, 4 / 4 + 0.5 * 4 / 2, 16 / 4 + 0.5 * 16 / 2]))
    assert build_cost(CostConfig()) is patch_cost
    with pytest.raises(ConfigError, match="needs a world model with a state head"):
        build_cost(CostConfig(state_weight=0.1))
    with pytest.raises(ConfigError, match="state_weight"):
        CostConfig(state_weight=-1)


def test_fidelity_refuses_a_pose_term_for_models_without_a_state_head(capsys):
    from wamplan.cli import main

    args = ["wm", "fidelity", "--wam", "checkpoints/mini/tinywam", "--wm", "checkpoints/mini/wm_augmented",
            "--seeds", "500", "--plan"]
    assert main([*args, "--plan-state-weight", "0.1"]) == 2
    assert "none of these has one" in capsys.readouterr().err
    assert main([*args, "--plan-state-weight", "0"]) == 2
    assert "must be above 0" in capsys.readouterr().err


@pytest.fixture(scope="module")
def headed_wm(tmp_path_factory):
    """The shipped world model with a linear state head added (seeded, untrained): its predictions are the shipped
    model's, and the head gives the pose term something to read."""
    from wamplan.checkpoint import load_tensors, read_meta, save_checkpoint
    from wamplan.worldmodel.predictor import WorldModelPredictor

    meta = read_meta("checkpoints/mini/wm_augmented")
    record = json.loads(json.dumps(meta["config"]))
    record["predictor"].update(state_dim=len(STATE_QUANTITIES), state_head="ridge")
    torch.manual_seed(0)
    model = WorldModelPredictor.from_record(record)
    shipped = load_tensors("checkpoints/mini/wm_augmented/model.safetensors")
    missing, unexpected = model.load_state_dict({k: v.float() for k, v in shipped.items()}, strict=False)
    assert not unexpected and missing and all(k.startswith("state_head.") for k in missing)
    return save_checkpoint(tmp_path_factory.mktemp("headed") / "wm", model, record, kind=meta["kind"])


def test_fidelity_plans_with_the_pose_term_of_a_model_with_a_state_head(headed_wm, tmp_path, capsys):
    """The headed model gets a twin LABEL+pose that scores (and with --plan, plans) with the pose term."""
    from wamplan.cli import main

    out = tmp_path / "f.json"
    assert main(["wm", "fidelity", "--wam", "checkpoints/mini/tinywam", "--wm",
                 f"s={headed_wm}", "--seeds", "500", "--boundaries", "1", "--candidates", "4",
                 "--top-k", "2", "--plan-state-weight", "0.3", "--camera-size", "64", "--json", str(out)]) == 0
    rec = json.loads(out.read_text())["records"][0]
    assert set(rec["models"]) == {"s", "s+pose"}
    assert rec["models"]["s+pose"]["model_costs"] != rec["models"]["s"]["model_costs"]  # the term adds to the cost


def test_stack_cube_stores_record_both_cubes_and_the_state_is_relative_to_the_target(tmp_path):
    from wamplan.cli import main

    out = tmp_path / "stack"
    assert main(["collect", "--task", "stack-cube", "--source", "pink", "--episodes", "1", "--max-steps", "8",
                 "--camera-size", "64", "--out", str(out)]) == 0
    path = next((out / "episodes").glob("*.h5"))
    with h5py.File(path, "r") as f:
        a, b, tcp = f["cube_pose"][:, :3], f["target_pose"][:, :3], f["tcp_pose"][:, :3]  # (T+1, 3) each
        s = state_targets(f, [0, 8])
    assert a.shape == b.shape == (9, 3) and 0.02 < np.linalg.norm(a[0, :2] - b[0, :2]) < 0.5  # two cubes apart
    np.testing.assert_allclose(s[:, :3], (a - tcp)[[0, 8]] * 100, rtol=1e-6)
    np.testing.assert_allclose(s[:, 3:], (a - b)[[0, 8]] * 100, rtol=1e-6)


def test_the_state_loss_trains_the_head_on_true_latents_and_the_predictor_through_the_fixed_head():
    from wamplan.worldmodel.config import PredictorConfig
    from wamplan.worldmodel.predictor import WorldModelPredictor
    from wamplan.worldmodel.losses import state_loss

    torch.manual_seed(0)
    cfg = PredictorConfig(num_views=1, num_patches=4, enc_dim=8, proprio_dim=2, action_dim=1, frameskip=1,
                          context=2, depth=1, heads=1, head_dim=8, mlp_dim=16, state_dim=6)
    model = WorldModelPredictor(cfg)
    batch = {"z": torch.randn(2, 4, 1, 4, 8), "s": torch.randn(2, 4, 6)}
    zp = torch.randn(2, 2, 1, 4, 8, requires_grad=True)
    zt = batch["z"][:, 2:]
    _, logs = state_loss(model, batch, zp, zt, 2)
    # the predicted-reading term alone: its gradient reaches the predictions, never the head
    e_true = (model.read_state(batch["z"]) - batch["s"]).pow(2).mean()
    loss, _ = state_loss(model, batch, zp, zt, 2)
    (loss - e_true).backward()
    assert zp.grad is not None and zp.grad.abs().sum() > 0
    assert all(p.grad is None or p.grad.abs().sum() == 0 for p in model.state_head.parameters())
    assert logs["state_mm_true"] > 0 and logs["state_mm_h1"] > 0
    # predictions equal to the truth read the same: the second term is zero
    zero, logs = state_loss(model, batch, zt.clone(), zt, 2)
    assert logs["state_mm_h1"] == 0 and torch.isclose(zero, e_true)


def test_a_ridge_state_head_starts_from_the_ridge_fit_of_the_true_latents():
    from wamplan.worldmodel.config import PredictorConfig
    from wamplan.worldmodel.predictor import WorldModelPredictor

    torch.manual_seed(0)
    cfg = PredictorConfig(num_views=1, num_patches=4, enc_dim=8, proprio_dim=2, action_dim=1, frameskip=1,
                          context=2, depth=1, heads=1, head_dim=8, mlp_dim=16, state_dim=6, state_head="ridge")
    model = WorldModelPredictor(cfg)
    z = torch.randn(400, 1, 4, 8)  # (n, V, N, D); normalisation is the identity here
    w = torch.randn(32, 6)
    s = z.flatten(1) @ w + 3.0  # an exactly linear state
    model.state_head.fit_ridge(z, s, alpha=1e-6)
    torch.testing.assert_close(model.read_state(z), s, atol=1e-3, rtol=1e-3)
    assert sum(p.numel() for p in model.state_head.parameters()) == 32 * 6 + 6
