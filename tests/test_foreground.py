"""The object-centric cost: the foreground readout (fit, save, load, refusal of another encoder), the patch cost
weighted token by token, the simulator's foreground masks, and ``wamplan wm foreground`` / ``eval
--cost-foreground`` on the command line."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from wamplan.cli import main
from wamplan.config import ConfigError
from wamplan.data.foreground import ForegroundFrames
from wamplan.encoders import make_encoder
from wamplan.encoders.foreground import (fit_foreground, foreground_weigher, load_foreground, save_foreground,
                                         token_fractions)
from wamplan.errors import UserError
from wamplan.planning.costs import CostConfig, build_cost, patch_cost, with_token_weights

MINI = Path(__file__).resolve().parents[1] / "checkpoints" / "mini"
B, V, N, D = 5, 3, 16, 8


def test_the_weighted_patch_cost_is_eq3_with_equal_weights_and_ignores_a_zero_weight_token():
    g = torch.Generator().manual_seed(0)
    pred, target = torch.randn(B, V, N, D, generator=g), torch.randn(V, N, D, generator=g)
    equal = with_token_weights(lambda t: torch.full(t.shape[:2], 0.3))
    torch.testing.assert_close(equal(pred, target), patch_cost(pred, target))
    w = torch.ones(V, N)
    w[2, 5] = 1e-9  # the wrist's token 5 does not count
    weighted = with_token_weights(lambda t: w)
    moved = pred.clone()
    moved[:, 2, 5] += 100.0
    torch.testing.assert_close(weighted(moved, target), weighted(pred, target))
    assert (patch_cost(moved, target) > patch_cost(pred, target) + 1).all()
    # by hand, with view weights: the wrist only, its tokens weighted
    wrist = with_token_weights(lambda t: w, view_weights=(0, 0, 1))
    per_token = (pred[:, 2] - target[2]).square().mean(-1)  # (B, N)
    torch.testing.assert_close(wrist(pred, target), (per_token * w[2]).sum(-1) / w[2].sum())


def test_the_foreground_settings_are_checked():
    with pytest.raises(ConfigError, match=r"background_weight must be in \(0, 1\]"):
        CostConfig(foreground="x", background_weight=0)
    with pytest.raises(ConfigError, match="use it with the patch cost unpooled"):
        CostConfig(foreground="x", name="cls")
    with pytest.raises(ConfigError, match="use it with the patch cost unpooled"):
        CostConfig(foreground="x", pool=2)
    with pytest.raises(ConfigError, match="needs its readout's weigher"):
        build_cost(CostConfig(foreground="x"))
    with pytest.raises(ConfigError, match="weighs nothing without a foreground readout"):
        CostConfig(background_weight=0.5)


def test_token_fractions_are_each_patch_share():
    masks = np.zeros((1, 1, 8, 8), bool)
    masks[0, 0, :4, :4] = True  # the top-left cell of a 2 x 2 grid, whole
    masks[0, 0, 4, 4] = True  # one pixel of the bottom-right cell
    np.testing.assert_allclose(token_fractions(masks, 2)[0, 0], [1, 0, 0, 1 / 16])
    with pytest.raises(ConfigError, match="do not split into 3 x 3"):
        token_fractions(masks, 3)


def _squares(episodes: int, frames: int = 12, size: int = 64) -> ForegroundFrames:
    """Red squares at random places on a random grey texture, two cameras: the masks are the squares."""
    rng = np.random.default_rng(0)
    n = episodes * frames
    images = rng.integers(60, 160, (n, 2, size, size, 3)).astype(np.uint8)
    masks = np.zeros((n, 2, size, size), bool)
    for i in range(n):
        for v in range(2):
            y, x = rng.integers(0, size - 20, 2)
            masks[i, v, y:y + 20, x:x + 20] = True
    images[masks] = (220, 30, 20)
    return ForegroundFrames(images, masks.astype(np.uint8), np.repeat(np.arange(episodes), frames), ("a", "b"))


def test_a_readout_reads_the_foreground_of_held_out_frames_and_refuses_another_encoder(tmp_path):
    enc = make_encoder("patch-pixels", input_size=64, patch_size=16, proj_dim=32)
    frames = _squares(10)
    readout, report = fit_foreground(enc, frames, steps=400)
    assert report["held_out_seeds"] == [8, 9] and report["frames"] == 120
    assert report["mae"] < 0.5 * report["mae_position_prior"]  # it reads the picture, not only where tokens sit
    save_foreground(tmp_path / "fg", readout, enc, report, "cube-insertion", ("a", "b"))
    again = load_foreground(tmp_path / "fg", enc, "cube-insertion", ("a", "b"))
    z = torch.randn(4, 2, 16, 32)
    torch.testing.assert_close(again(z), readout(z).detach())
    with pytest.raises(UserError, match="fit one for it"):
        load_foreground(tmp_path / "fg", make_encoder("patch-pixels", input_size=64, patch_size=16, proj_dim=32,
                                                      seed=1))
    with pytest.raises(UserError, match="was fit on task 'cube-insertion', but the planning acts in 'stack-cube'"):
        load_foreground(tmp_path / "fg", enc, "stack-cube")
    with pytest.raises(UserError, match=r"reads the cameras \['a', 'b'\], but the world model's views are \['b', 'a'\]"):
        load_foreground(tmp_path / "fg", enc, cameras=("b", "a"))
    weigh = foreground_weigher(tmp_path / "fg", enc, background_weight=0.1)
    target = enc.encode(frames.images[-1])  # (2, 16, 32): the last held-out frame
    w = weigh(target)  # (2, 16)
    assert weigh(target) is w and weigh(target.clone()) is not w  # kept while the same target comes back
    share = torch.from_numpy(token_fractions(frames.masks[-1:], 4)[0])
    assert w.min() >= 0.1 - 1e-6 and w.max() <= 1 + 1e-6
    assert (w - (0.1 + 0.9 * share)).abs().mean() < 0.1  # background 0.1, foreground 1, linear between
    with pytest.raises(ValueError, match="use a readout fit on this world model's encoder"):
        readout(torch.randn(2, 16, 16))


def test_the_simulators_foreground_is_the_robot_and_the_objects(small_env):
    small_env.reset(0)
    pictures, masks = small_env.render_foreground()
    for cam, pic in small_env.render().items():
        np.testing.assert_array_equal(pictures[cam], pic)  # the same pictures as render
        assert masks[cam].shape == pic.shape[:2] and 0.02 < masks[cam].mean() < 0.5  # the table is most of it
    assert masks["wrist"][-8:].mean() > masks["wrist"][:8].mean()  # the gripper's fingers, at the bottom


def test_wm_foreground_fits_a_readout_that_eval_plans_with(tmp_path, capsys):
    out = tmp_path / "fg"
    assert main(["wm", "foreground", "--wm", str(MINI / "wm_augmented"), "--policy", "expert", "--episodes", "2",
                 "--every", "40", "--camera-size", "64", "--steps", "50", "--device", "cpu", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "held out: seeds 3001" in printed and "wrist:" in printed and (out / "foreground.png").is_file()
    cfg = json.loads((out / "config.json").read_text())
    assert cfg["kind"] == "foreground" and cfg["config"]["task"] == "cube-insertion"
    from wamplan import api

    policy = api.planned_policy(MINI / "tinywam", MINI / "wm_augmented", cost={"foreground": str(out)})
    target = torch.randn(3, 16, 128)
    pred = target.expand(2, -1, -1, -1).clone()
    pred[1, 2, 0] += 1.0  # one wrist token wrong: the cost is its weight's share of the view's, over 3 views
    w = foreground_weigher(out, policy.encoder, 0.1)(target)  # (3, 16)
    want = float(pred[1, 2, 0].sub(target[2, 0]).square().mean() * w[2, 0] / w[2].sum() / 3)
    assert policy.cost(pred, target)[0] == 0 and float(policy.cost(pred, target)[1]) == pytest.approx(want, rel=1e-4)
    assert want != pytest.approx(float(patch_cost(pred, target)[1]), rel=1e-2)  # not eq. 3: the weights count


def test_foreground_inputs_are_refused_in_one_line(tmp_path, capsys, refused):
    wm = ["wm", "foreground", "--wm", MINI / "wm_augmented", "--out", tmp_path / "fg"]
    refused([*wm, "--episodes", "1"], "--episodes 1", "at least 2 episodes")
    refused([*wm, "--every", "0"], "--every must be >= 1")
    refused([*wm, "--device", "nonsense"], "nonsense")
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "config.json").write_text('{"kind": "predictor", "config": {}}')
    refused(["wm", "foreground", "--wm", MINI / "wm_augmented", "--out", tmp_path / "run"],
            "holds a 'predictor' checkpoint, not a foreground readout")
    enc = make_encoder("patch-pixels", input_size=64, patch_size=16, proj_dim=32)
    readout, report = fit_foreground(enc, _squares(2, frames=2), steps=1)
    save_foreground(tmp_path / "other", readout, enc, report, "cube-insertion", ("front", "side", "wrist"))
    save_foreground(tmp_path / "cube", readout_for(MINI / "wm_augmented"), load_encoder(MINI / "wm_augmented"),
                    report, "cube-insertion", ("front", "side", "wrist"))
    ev = ["eval", "--conditions", "7", "--out", tmp_path / "e", "--wam", MINI / "tinywam", "--wm-augmented",
          MINI / "wm_augmented"]
    refused([*ev, "--cost-foreground", tmp_path / "other"], "reads tokens of encoder", "wm foreground")
    refused([*ev, "--cost-foreground", tmp_path / "other", "--cost-name", "cls"], "--cost-foreground weighs patch tokens",
            "--cost-name=patch and --cost-pool=1 (got --cost-name=cls")
    refused([*ev, "--cost-foreground", tmp_path / "nowhere"], "--cost-foreground", "nowhere does not exist",
            "wamplan wm foreground")
    refused([*ev, "--cost-background-weight", "0.5"], "--cost-background-weight 0.5 weighs nothing",
            "give --cost-foreground=DIR too")
    sim = ["eval", "--conditions", "5", "--out", tmp_path / "e", "--wam", MINI / "tinywam"]  # patch-pixels, 128 dims
    refused([*sim, "--cost-foreground", tmp_path / "other"], "reads tokens of encoder")
    stack = ["eval", "--task", "stack-cube", "--conditions", "7", "--out", tmp_path / "e", "--wam",
             MINI.parent / "stack-cube" / "tinywam", "--wm-augmented", MINI.parent / "stack-cube" / "wm_augmented"]
    refused([*stack, "--cost-foreground", tmp_path / "cube"], "fit on task 'cube-insertion'",
            "acts in 'stack-cube'")
    assert not (tmp_path / "e").exists()


def test_wm_fidelity_ranks_in_the_foreground_cost(tmp_path, capsys, refused):
    fid = ["wm", "fidelity", "--wam", MINI / "tinywam", "--wm", f"shipped={MINI / 'wm_augmented'}", "--seeds", "500",
           "--boundaries", "1", "--candidates", "4", "--top-k", "2", "--camera-size", "64"]
    enc = make_encoder("patch-pixels", input_size=64, patch_size=16, proj_dim=32)
    readout, report = fit_foreground(enc, _squares(2, frames=2), steps=1)
    save_foreground(tmp_path / "other", readout, enc, report, "cube-insertion", ("front", "side", "wrist"))
    refused([*fid, "--cost-foreground", tmp_path / "other"], "reads tokens of encoder")
    refused([*fid, "--cost-foreground", tmp_path / "other", "--cost-background-weight", "0"],
            "--cost-background-weight must be in (0, 1]")
    refused([*fid, "--cost-background-weight", "0.5"], "weighs nothing without --cost-foreground")
    real = tmp_path / "fg"
    save_foreground(real, readout_for(MINI / "wm_augmented"), load_encoder(MINI / "wm_augmented"), report,
                    "cube-insertion", ("front", "side", "wrist"))
    assert main([str(a) for a in [*fid, "--cost-foreground", real, "--cost-background-weight", "0.01", "--json",
                                  tmp_path / "fg.json"]]) == 0
    fg = json.loads((tmp_path / "fg.json").read_text())
    assert fg["cost_foreground"] == str(real) and fg["cost_background_weight"] == 0.01
    # a twin that ranks in the weighted cost, scored in the plain yardstick, beside the model in the plain cost
    assert main([str(a) for a in [*fid, "--plan-foreground", real, "--cost-background-weight", "0.01", "--json",
                                  tmp_path / "twin.json"]]) == 0
    twin = json.loads((tmp_path / "twin.json").read_text())["records"][0]["models"]
    weighted = fg["records"][0]["models"]["shipped"]  # the same candidates, costed (model and yardstick) weighted
    assert twin["shipped+fg"]["true_costs"] == twin["shipped"]["true_costs"] != weighted["true_costs"]
    assert twin["shipped+fg"]["model_costs"] == pytest.approx(weighted["model_costs"], rel=1e-5)
    assert twin["shipped+fg"]["model_costs"] != pytest.approx(twin["shipped"]["model_costs"], rel=1e-3)


def load_encoder(wm: Path):
    from wamplan.worldmodel.load import load_world_model

    return load_world_model(wm)[1]


def readout_for(wm: Path):
    """An untrained readout of ``wm``'s encoder's token layout (its weights do not matter to the plumbing)."""
    from wamplan.encoders.foreground import ForegroundReadout

    enc = load_encoder(wm)
    return ForegroundReadout(3, enc.num_patches, enc.dim)
