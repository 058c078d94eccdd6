"""The representation lever's probes that run at this commit: wrist_warp_probe.py's warp and wm_sibling_picture.py's
drawer (concat_scale.py's test left with ``concat``, stop 78: commit 9c6eb5d has it)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from wamplan.encoders import make_encoder
from wamplan.errors import UserError
from wamplan.worldmodel import DecoderConfig, DecoderTrainConfig, train_decoder


def test_the_wrist_warp_of_a_pose_onto_itself_is_the_picture_and_a_sideways_move_shifts_it(repo_script):
    warp = repo_script("lab/representation/wrist_warp_probe.py").warp
    rng = np.random.default_rng(0)
    h = w = 32
    K = np.array([[20.0, 0, w / 2], [0, 20.0, h / 2], [0, 0, 1]])
    down = np.array([[1.0, 0, 0], [0, -1, 0], [0, 0, -1]])  # looking straight down at z = 0 from 0.5 m
    E = np.concatenate([down, (-down @ np.array([0, 0, 0.5]))[:, None]], 1)  # (3, 4) world -> camera
    img = rng.integers(0, 255, (h, w, 3)).astype(np.uint8)
    none = np.zeros((h, w), bool)
    a = {"K": K, "E": E, "rgb": img, "robot": none, "cube": none, "grasped": False}
    np.testing.assert_array_equal(warp(a, a), img)
    moved = dict(a, E=np.concatenate([down, (-down @ np.array([0.05, 0, 0.5]))[:, None]], 1))  # 5 cm along x
    out = warp(a, moved)  # 5 cm at 0.5 m and f = 20 px: the table moves 2 px in the picture
    np.testing.assert_array_equal(out[:, :-2], img[:, 2:])
    keep = none.copy()
    keep[:4] = True  # the robot's pixels stay where they were
    np.testing.assert_array_equal(warp(dict(a, robot=keep), moved)[:4], img[:4])


class _Pairs(torch.utils.data.Dataset):
    """Images whose patch (i, j) is a flat colour set by token i * grid + j."""

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


def test_sibling_picture_draws_a_model_through_its_encoders_decoder_and_refuses_another(tmp_path, repo_script):
    a = dict(name="patch-pixels", input_size=32, patch_size=16, proj_dim=8)
    b = dict(name="patch-pixels", input_size=32, patch_size=16, proj_dim=4, seed=2)
    cfg = DecoderConfig(num_patches=4, enc_dim=4, image_size=16, width=32, depth=1, heads=4, mlp_dim=64,
                        head_channels=16)
    train_decoder(_Pairs(8, cfg), cfg, DecoderTrainConfig(batch_size=8), tmp_path, device="cpu", max_steps=1,
                  progress=False, encoder_info=make_encoder(**b).config_dict())
    drawer = repo_script("lab/representation/wm_sibling_picture.py").drawer
    enc = make_encoder(**b)
    dec, tokens, part = drawer(enc, tmp_path)
    z = enc.encode(np.random.default_rng(0).integers(0, 256, (2, 32, 32, 3), dtype=np.uint8))  # (2, 4, 4)
    assert part == "" and torch.equal(tokens(z), z)  # its tokens as they are
    with torch.inference_mode():  # as the script draws
        assert dec(tokens(z)).shape == (2, 3, 16, 16)
    with pytest.raises(UserError, match="trained on another encoder's tokens"):
        drawer(make_encoder(**a), tmp_path)
