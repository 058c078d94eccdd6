"""The ``object-masks`` encoder: the simulator's classes per pixel, the cells' shares, the token layout, training on
pictures it then reads, loading (by digest, beside patch-pixels in a concat), and ``wamplan wm train-masks``."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import torch

from wamplan.cli import main
from wamplan.config import ConfigError
from wamplan.data.foreground import ForegroundFrames, load_frames, save_frames
from wamplan.encoders import make_encoder
from wamplan.encoders.learned import locate_weights
from wamplan.encoders.object_masks import (MaskTrainConfig, ObjectMaskEncoder, cell_shares, mask_tokens,
                                           token_maps, train_object_masks)
from wamplan.errors import UserError


def test_cell_shares_and_the_token_layout():
    labels = np.zeros((1, 64, 128), np.uint8)  # 64 rows, 128 columns: 16 x 16 cells of 4 x 8 px
    labels[0, :4, 24:32] = 2  # class 2 fills cell (row 0, column 3)
    labels[0, 60:, 124:] = 1  # class 1 half of cell (15, 15)
    shares = cell_shares(labels, 3)  # (1, 3, 16, 16)
    assert shares.shape == (1, 3, 16, 16)
    assert shares[0, 2, 0, 3] == 1 and shares[0, 1, 15, 15] == 0.5 and shares[0, 0, 15, 15] == 0.5
    assert shares[0, 2, 3, 0] == 0  # rows and columns not swapped
    torch.testing.assert_close(shares.sum(1), torch.ones(1, 16, 16))
    with pytest.raises(ConfigError, match="do not split into 16 x 16 cells"):
        cell_shares(np.zeros((1, 40, 40), np.uint8), 3)
    logits = torch.log(shares.clamp(min=1e-6))  # softmax gives the shares back
    z = mask_tokens(logits)  # (1, 16, 2 classes x 16 cells)
    assert z.shape == (1, 16, 32)
    assert z[0, 0, 16 + 3] == pytest.approx(1, abs=1e-4)  # token 0 (row 0, column 0), class 2, its cell (0, 3)
    assert z[0, 15, 15] == pytest.approx(0.5, abs=1e-4)  # token 15, class 1, its last cell (3, 3)
    assert z[0, 1:15].abs().max() < 1e-4  # nothing elsewhere
    labels = np.zeros((1, 64, 64), np.uint8)
    labels[0, 4:8, 16:20] = 1  # cell (1, 4): token 1 (row 0, column 1), its cell (1, 0)
    z = mask_tokens(torch.log(cell_shares(labels, 2).clamp(min=1e-6)))  # (1, 16, 16)
    assert z[0, 1, 4] == pytest.approx(1, abs=1e-4) and z[0, 4].abs().max() < 1e-4  # not token 4 (row 1, column 0)
    torch.testing.assert_close(token_maps(z), cell_shares(labels, 2), atol=1e-4, rtol=0)  # the maps back, exactly


def _squares(episodes: int, frames: int = 10, size: int = 64) -> ForegroundFrames:
    """A red and a blue square at random places on a random grey texture, one camera: classes 1 and 2."""
    rng = np.random.default_rng(0)
    n = episodes * frames
    images = rng.integers(60, 160, (n, 1, size, size, 3)).astype(np.uint8)
    labels = np.zeros((n, 1, size, size), np.uint8)
    for i in range(n):
        for cls, colour in ((1, (220, 30, 20)), (2, (20, 40, 220))):
            y, x = rng.integers(0, size - 16, 2)
            labels[i, 0, y:y + 16, x:x + 16] = cls
            images[i, 0, y:y + 16, x:x + 16] = colour
    return ForegroundFrames(images, labels, np.repeat(np.arange(episodes), frames), ("cam",),
                            ("background", "red", "blue"), "cube-insertion")


def test_it_learns_to_read_the_objects_and_loads_by_digest_beside_patch_pixels(tmp_path):
    frames = _squares(10)
    cfg = MaskTrainConfig(epochs=12, batch_size=16, lr=3e-3, width=16, warmup_epochs=0.5, log_every_steps=1000)
    metrics = train_object_masks(frames, tmp_path / "run", cfg, task="cube-insertion", progress=False)
    assert metrics["val/iou_red"] > 0.5 and metrics["val/iou_blue"] > 0.5  # held-out episodes 8 and 9
    enc = ObjectMaskEncoder(ckpt=str(tmp_path / "run"))
    assert enc.classes == ["background", "red", "blue"] and (enc.num_patches, enc.dim) == (16, 32)
    z = enc.encode(frames.images[-1, 0])  # (1, 16, 32)
    true = mask_tokens(torch.log(cell_shares(frames.labels[-1:, 0], 3).clamp(min=1e-6)))
    assert (z - true).abs().mean() < 0.1  # the tokens are where the squares are
    again = make_encoder(**enc.config_dict())
    torch.testing.assert_close(again.encode(frames.images[0, 0]), enc.encode(frames.images[0, 0]))
    with pytest.raises(UserError, match="are not the ones this model was trained on"):
        ObjectMaskEncoder(ckpt=str(tmp_path / "run"), sha="0" * 12)
    with pytest.raises(UserError, match="needs its trained weights"):
        ObjectMaskEncoder()
    cat = make_encoder("concat", parts=[{"name": "patch-pixels"}, enc.config_dict()], scales=[1, 2])
    assert cat.dim == 128 + 32 and cat.parts[1].sha == enc.sha
    torch.testing.assert_close(cat.part_tokens(cat.encode(frames.images[0, 0]), 1), enc.encode(frames.images[0, 0]))
    # a world model's record finds a relative encoder under the folders above its checkpoint
    info = locate_weights("concat", cat.config_dict(), tmp_path / "wm" / "checkpoint")
    assert info["parts"][1]["near"] == str(tmp_path / "wm" / "checkpoint") and "near" not in info["parts"][0]


def test_the_simulators_classes_are_the_robot_and_each_object(small_env):
    small_env.reset(0)
    pictures, labels, classes = small_env.render_segmentation()
    assert classes == ("background", "robot", "cube", "mount")
    _, masks = small_env.render_foreground()
    for cam, lab in labels.items():
        np.testing.assert_array_equal(lab > 0, masks[cam])  # the foreground is every class but the background
        assert lab.dtype == np.uint8 and set(np.unique(lab)) <= {0, 1, 2, 3}
    assert (labels["wrist"] == 1).any() and (labels["front"] == 3).any()  # the fingers in the wrist, the mount in front


def test_the_simulators_foreground_is_the_robot_and_the_objects(small_env):
    small_env.reset(0)
    pictures, masks = small_env.render_foreground()
    for cam, pic in small_env.render().items():
        np.testing.assert_array_equal(pictures[cam], pic)  # the same pictures as render
        assert masks[cam].shape == pic.shape[:2] and 0.02 < masks[cam].mean() < 0.5  # the table is most of it
    assert masks["wrist"][-8:].mean() > masks["wrist"][:8].mean()  # the gripper's fingers, at the bottom


def test_wm_train_masks_collects_once_trains_and_draws(tmp_path, capsys, refused):
    frames = tmp_path / "frames.npz"
    train = ["wm", "train-masks", "--epochs", "1", "--batch-size", "4", "--width", "8", "--device", "cpu",
             "--frames", frames]
    collect = ["--policy", "expert", "--episodes", "2", "--every", "50", "--camera-size", "64"]
    assert main([str(a) for a in train + collect + ["--out", tmp_path / "m"]]) == 0
    printed = capsys.readouterr().out
    assert "episode 2/2" in printed and "held out: ce" in printed and (tmp_path / "m" / "masks.png").is_file()
    saved = load_frames(frames)
    assert saved.task == "cube-insertion" and saved.classes == ("background", "robot", "cube", "mount")
    cfg = json.loads((tmp_path / "m" / "checkpoint" / "config.json").read_text())
    assert cfg["config"]["net"]["classes"] == ["background", "robot", "cube", "mount"]
    # a second run reads the frames file instead of collecting; re-running a finished run keeps it
    assert main([str(a) for a in train + ["--out", tmp_path / "m2"]]) == 0
    assert "read " in capsys.readouterr().out
    weights = (tmp_path / "m" / "checkpoint" / "model.safetensors").read_bytes()
    assert main([str(a) for a in train[:2] + ["--device", "cpu", "--frames", frames, "--out", tmp_path / "m"]]) == 0
    assert (tmp_path / "m" / "checkpoint" / "model.safetensors").read_bytes() == weights
    capsys.readouterr()
    refused(train + ["--out", tmp_path / "m3", "--episodes", "80"], "--episodes", "exists and fixes the episodes")
    refused(train + ["--out", tmp_path / "m3", "--task", "stack-cube"],
            "holds frames of task 'cube-insertion', not 'stack-cube'")
    (tmp_path / "bad.npz").write_bytes(b"not a frames file")
    refused(train[:-1] + [tmp_path / "bad.npz", "--out", tmp_path / "m4"], "is not a frames file")
    fresh = train[:-1] + [tmp_path / "new.npz", "--out", tmp_path / "m5"]
    refused(fresh + ["--camera-size", "40"], "--camera-size 40 does not split into 16 x 16 cells")
    refused(train[:-1] + [tmp_path / "frames", "--out", tmp_path / "m5"], "a frames file is named *.npz")
    refused(fresh + ["--max-steps", "0"], "--max-steps must be > 0")
    shutil.copytree(tmp_path / "m", tmp_path / "wm")  # another kind's run in --out, refused before collecting
    cfg["kind"] = "wm-predictor"
    (tmp_path / "wm" / "checkpoint" / "config.json").write_text(json.dumps(cfg))
    refused(fresh[:-2] + ["--out", tmp_path / "wm"], "holds a 'wm-predictor' run, not an object-masks run")
    assert not (tmp_path / "new.npz").exists()  # nothing was collected for the refused runs


def test_frames_round_trip(tmp_path):
    frames = _squares(2, frames=2)
    back = load_frames(save_frames(frames, tmp_path / "f.npz"))
    np.testing.assert_array_equal(back.labels, frames.labels)
    assert (back.cameras, back.classes, back.task) == (frames.cameras, frames.classes, frames.task)
    assert back.masks.dtype == bool and back.masks.sum() == (frames.labels > 0).sum()
