"""Frozen encoders: the registry, patch-pixels, and DINOv3/DINOv2 loading on tiny random configs."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from wamplan.encoders import (DINOV3_ENV, FrozenEncoder, PatchPixelEncoder, dct_projection, encoder_names, make_encoder,
                              orthogonal_projection, register_encoder)
from wamplan.errors import UserError


pytestmark = pytest.mark.usefixtures("one_thread")


def _images(b: int = 2, size: int = 64, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.randint(0, 256, (b, size, size, 3), dtype=torch.uint8, generator=g)  # (B, H, W, 3)


def test_registry_lists_entries_and_rejects_unknown_names():
    names = encoder_names()
    for n in ("patch-pixels", "dinov3-vitl16", "dinov2-vits14", "dinov2-vitb14"):
        assert n in names
    with pytest.raises(UserError, match="unknown encoder 'nope'.*patch-pixels"):
        make_encoder("nope")
    with pytest.raises(ValueError, match="twice"):
        register_encoder("patch-pixels")(PatchPixelEncoder)
    for name, kwargs, last in (("object-masks", {"ckpt": "runs/masks"}, "f07acf1"),  # encoders that left the core
                               ("task-cnn", {"ckpt": "enc16"}, "9c6eb5d"),  # (lab/README.md)
                               ("concat", {"parts": [{"name": "patch-pixels"}]}, "9c6eb5d")):
        with pytest.raises(UserError, match=f"encoder '{name}' left wamplan .* at commit {last} or earlier"):
            make_encoder(name, **kwargs)


def test_patch_pixels_shapes_and_frozen():
    enc = make_encoder("patch-pixels", input_size=64, patch_size=16, proj_dim=128)
    assert make_encoder(**enc.config_dict()).config_dict() == enc.config_dict()
    assert (enc.num_patches, enc.dim, enc.input_size) == (16, 128, 64)
    z = enc.encode(_images(3, 100))  # resized from 100 px
    assert z.shape == (3, 16, 128) and z.dtype == torch.float32
    z1, cls = enc.encode(_images(1, 64)[0], return_cls=True)  # a single (H, W, 3) image
    assert z1.shape == (1, 16, 128) and cls is None
    enc.train()
    assert not enc.training and all(not b.requires_grad for b in enc.buffers())


def test_patch_pixels_raw_tokens_are_patches_in_row_major_order():
    enc = make_encoder("patch-pixels", input_size=32, patch_size=8, proj_dim=None)
    assert (enc.num_patches, enc.dim) == (16, 192)
    img = torch.zeros(1, 32, 32, 3, dtype=torch.uint8)
    img[0, 8:16, 16:24] = 255  # patch row 1, column 2 -> token 1 * 4 + 2 = 6
    z = enc.encode(img)[0]  # (16, 192)
    energy = (z - z[0]).abs().sum(-1)  # (16,), every other patch is black like patch 0
    assert int(energy.argmax()) == 6 and float(energy.sum() - energy[6]) == 0.0
    white = (torch.ones(3) - torch.tensor([0.485, 0.456, 0.406])) / torch.tensor([0.229, 0.224, 0.225])
    assert torch.allclose(z[6].view(3, 64), white[:, None].expand(3, 64), atol=1e-5)  # ImageNet-normalised


def test_patch_pixels_projection_is_fixed_orthogonal_and_scale_preserving():
    p = orthogonal_projection(192, 64, seed=3)  # (192, 64)
    assert torch.allclose(p.T @ p, torch.eye(64), atol=1e-5)  # orthonormal columns
    assert torch.equal(p, orthogonal_projection(192, 64, seed=3))
    assert not torch.equal(p, orthogonal_projection(192, 64, seed=4))
    a = make_encoder("patch-pixels", input_size=64, patch_size=8, proj_dim=64, seed=3)
    b = make_encoder("patch-pixels", input_size=64, patch_size=8, proj_dim=64, seed=3)
    imgs = _images(2)
    assert torch.equal(a.encode(imgs), b.encode(imgs))
    raw = make_encoder("patch-pixels", input_size=64, patch_size=8, proj_dim=None).encode(imgs)
    ratio = a.encode(imgs).pow(2).mean() / raw.pow(2).mean()
    assert 0.8 < float(ratio) < 1.25  # mean squared value kept in expectation


def test_patch_pixels_rejects_bad_inputs():
    enc = make_encoder("patch-pixels")
    with pytest.raises(UserError, match="uint8"):
        enc.encode(torch.rand(1, 64, 64, 3))
    with pytest.raises(UserError, match=r"\(B, H, W, 3\)"):
        enc.encode(torch.zeros(1, 3, 64, 64, dtype=torch.uint8))
    with pytest.raises(UserError, match="multiple of patch_size"):
        make_encoder("patch-pixels", input_size=60, patch_size=16)
    with pytest.raises(UserError, match="proj_dim"):
        make_encoder("patch-pixels", input_size=64, patch_size=8, proj_dim=500)


def _tiny_dinov3():
    from transformers import DINOv3ViTConfig, DINOv3ViTModel
    cfg = DINOv3ViTConfig(hidden_size=32, num_hidden_layers=2, num_attention_heads=2, intermediate_size=64,
                          patch_size=16, image_size=64, num_register_tokens=4)
    torch.manual_seed(0)
    return DINOv3ViTModel(cfg).eval()


def _tiny_dinov2():
    from transformers import Dinov2Config, Dinov2Model
    cfg = Dinov2Config(hidden_size=32, num_hidden_layers=2, num_attention_heads=2, mlp_ratio=2,
                       patch_size=14, image_size=56)
    torch.manual_seed(0)
    return Dinov2Model(cfg).eval()


@pytest.mark.parametrize("name, build, n_prefix, grid", [
    ("dinov3-vitl16", _tiny_dinov3, 1 + 4, 4),  # CLS + 4 registers, 64 px / 16
    ("dinov2-vits14", _tiny_dinov2, 1, 4),  # CLS only, 56 px / 14
])
def test_hf_encoder_loads_from_a_local_dir_and_slices_patch_tokens(tmp_path, name, build, n_prefix, grid):
    model = build()
    model.save_pretrained(tmp_path)
    size = model.config.image_size
    enc = make_encoder(name, path=tmp_path, input_size=size)
    assert isinstance(enc, FrozenEncoder) and not enc.training
    assert not any(p.requires_grad for p in enc.parameters())
    assert (enc.num_patches, enc.dim, enc.num_prefix_tokens) == (grid * grid, 32, n_prefix)
    imgs = _images(2, 80)
    z, cls = enc.encode(imgs, return_cls=True)
    assert z.shape == (2, grid * grid, 32) and cls.shape == (2, 32)
    with torch.no_grad():  # the same model run by hand: patches are the last N tokens after CLS (+ registers)
        hidden = model(pixel_values=enc.preprocess(imgs)).last_hidden_state  # (B, 1 + R + N, D)
    assert hidden.shape[1] == n_prefix + grid * grid
    assert torch.allclose(z, hidden[:, -grid * grid:], atol=1e-5)
    assert torch.allclose(cls, hidden[:, 0], atol=1e-5)
    cfg = enc.config_dict()
    assert cfg == {"name": name, "input_size": size, "dtype": "float32", "path": str(tmp_path)}
    assert torch.equal(make_encoder(**cfg).encode(imgs), z)  # the config rebuilds the encoder


def test_dinov3_from_env_var_and_from_config(tmp_path, monkeypatch):
    model = _tiny_dinov3()
    model.save_pretrained(tmp_path)
    monkeypatch.setenv(DINOV3_ENV, str(tmp_path))
    enc = make_encoder("dinov3-vitl16", input_size=64)
    assert enc.encode(_images(1)).shape == (1, 16, 32)
    rand = make_encoder("dinov3-vitl16", config=model.config, input_size=32)  # random init, same class
    assert type(rand.model) is type(model) and rand.encode(_images(1)).shape == (1, 4, 32)
    with pytest.raises(UserError, match="multiple of the patch size"):
        make_encoder("dinov3-vitl16", config=model.config, input_size=40)
    with pytest.raises(UserError, match="Dinov2Config"):
        make_encoder("dinov2-vits14", config=model.config)


def test_missing_weights_name_what_to_get_and_where(tmp_path, monkeypatch):
    empty = tmp_path / "nothing-here"
    want = r"facebook/dinov3-vitl16-pretrain-lvd1689m.*--encoder-path DIR.*WAMPLAN_DINOV3_PATH"
    with pytest.raises(UserError, match=want):
        make_encoder("dinov3-vitl16", path=empty)
    monkeypatch.setenv("WAMPLAN_DINOV2_PATH", str(empty))
    with pytest.raises(UserError, match=r"facebook/dinov2-small.*WAMPLAN_DINOV2_PATH"):
        make_encoder("dinov2-vits14")


def test_numpy_images_are_accepted():
    enc = make_encoder("patch-pixels")
    imgs = _images(2).numpy()
    assert isinstance(imgs, np.ndarray)
    assert torch.equal(enc.encode(imgs), enc.encode(torch.from_numpy(imgs)))


def test_patch_pixels_dct_basis_is_an_orthonormal_low_pass():
    p = dct_projection(8, 48)  # (192, 48): the 16 lowest frequencies in each of 3 channels
    assert p.shape == (192, 48) and torch.allclose(p.T @ p, torch.eye(48), atol=1e-5)
    assert torch.allclose(p[:64, 0], torch.full((64,), 1 / 8.0))  # first column: the red channel's mean
    enc = make_encoder("patch-pixels", input_size=32, patch_size=8, proj_dim=48, basis="dct")
    assert enc.config_dict()["basis"] == "dct" and make_encoder(**enc.config_dict()).config_dict() == enc.config_dict()
    assert "basis" not in make_encoder("patch-pixels").config_dict()  # the default keeps its feature key
    ramp = torch.linspace(0, 255, 32).round().to(torch.uint8)  # a smooth horizontal ramp
    smooth = ramp.view(1, 1, 32, 1).expand(1, 32, 32, 3).contiguous()
    noise = _images(1, 32)  # white noise: energy at every frequency
    raw = make_encoder("patch-pixels", input_size=32, patch_size=8, proj_dim=None)
    kept = [float(enc.encode(x).pow(2).sum() / raw.encode(x).pow(2).sum()) for x in (smooth, noise)]
    assert kept[0] > 0.99 and kept[1] < 0.5  # a low-pass: keeps the ramp, drops most of the noise
    with pytest.raises(UserError, match="basis must be one of random, dct"):
        make_encoder("patch-pixels", basis="wavelet")


def test_unknown_encoder_settings_are_named_with_the_ones_it_takes():
    with pytest.raises(UserError, match="encoder patch-pixels has no setting foo; it takes input_size, patch_size"):
        make_encoder("patch-pixels", foo=1)

