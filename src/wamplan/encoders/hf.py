"""DINOv3 and DINOv2 ViTs from ``transformers``, frozen, patch tokens only.

Weights are never downloaded: a model loads from a local directory (``path=`` / ``--encoder-path DIR``,
or the environment variable named below) or from the local Hugging Face cache
(``local_files_only=True``). Without weights the error names the repository to obtain and where to
put it. ``config=`` builds a randomly initialised model of the same class (used by the tests).

Token layout of ``last_hidden_state``: ``[CLS, register_1..register_R, patch_1..patch_N]``; DINOv3
LVD-1689M checkpoints have R = 4 registers, Dinov2Model has none. Patches are row-major.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch

from wamplan.encoders.base import IMAGENET_MEAN, IMAGENET_STD, FrozenEncoder, register_encoder
from wamplan.errors import UserError

if TYPE_CHECKING:  # transformers costs ~2.5 s to import: only the HF entries pay for it, when built
    from transformers import PretrainedConfig, PreTrainedModel

DINOV3_ENV = "WAMPLAN_DINOV3_PATH"
DINOV2_ENV = "WAMPLAN_DINOV2_PATH"

# registry name -> (transformers model class, its config class, Hugging Face repo, env var)
HF_ENCODERS: dict[str, tuple[str, str, str, str]] = {
    "dinov3-vits16": ("DINOv3ViTModel", "DINOv3ViTConfig", "facebook/dinov3-vits16-pretrain-lvd1689m", DINOV3_ENV),
    "dinov3-vitb16": ("DINOv3ViTModel", "DINOv3ViTConfig", "facebook/dinov3-vitb16-pretrain-lvd1689m", DINOV3_ENV),
    "dinov3-vitl16": ("DINOv3ViTModel", "DINOv3ViTConfig", "facebook/dinov3-vitl16-pretrain-lvd1689m", DINOV3_ENV),
    "dinov2-vits14": ("Dinov2Model", "Dinov2Config", "facebook/dinov2-small", DINOV2_ENV),
    "dinov2-vitb14": ("Dinov2Model", "Dinov2Config", "facebook/dinov2-base", DINOV2_ENV),
    "dinov2-vitl14": ("Dinov2Model", "Dinov2Config", "facebook/dinov2-large", DINOV2_ENV),
}


def hf_classes(name: str) -> tuple[type["PreTrainedModel"], type["PretrainedConfig"]]:
    """The transformers (model class, config class) of registry entry ``name``."""
    import transformers

    model_name, config_name = HF_ENCODERS[name][:2]
    return getattr(transformers, model_name), getattr(transformers, config_name)


def _resolve_dtype(dtype: torch.dtype | str | None) -> torch.dtype:
    if dtype is None:
        return torch.float32
    if isinstance(dtype, torch.dtype):
        return dtype
    resolved = getattr(torch, str(dtype), None)
    if not isinstance(resolved, torch.dtype):
        raise UserError(f"unknown dtype '{dtype}'; use float32, bfloat16 or float16")
    return resolved


def load_hf_model(name: str, path: str | os.PathLike[str] | None = None) -> "PreTrainedModel":
    """The pretrained model of registry entry ``name`` from ``path``, its env var, or the local HF cache."""
    repo, env = HF_ENCODERS[name][2:]
    model_cls = hf_classes(name)[0]
    src = path if path is not None else os.environ.get(env)
    how = (f"download the Hugging Face repository {repo} (e.g. `hf download {repo} --local-dir DIR`"
           + (", after accepting its licence on the hub" if "dinov3" in repo else "")
           + f") and pass --encoder-path DIR or set {env}=DIR")
    if src is not None:
        p = Path(src).expanduser()
        if not (p / "config.json").is_file():
            raise UserError(f"{name}: no model at {p} (needs config.json and model.safetensors); {how}")
        return model_cls.from_pretrained(str(p), local_files_only=True)
    try:
        return model_cls.from_pretrained(repo, local_files_only=True)
    except OSError as e:
        raise UserError(f"{name}: weights not found locally (no path given, {env} unset, not in the "
                        f"Hugging Face cache); {how}") from e


class HFViTEncoder(FrozenEncoder):
    """A transformers ViT (DINOv3ViTModel or Dinov2Model) as a frozen patch-token encoder."""

    def __init__(self, name: str, model: "PreTrainedModel", input_size: int,
                 dtype: torch.dtype | str | None = None, source: str | None = None) -> None:
        super().__init__(input_size, IMAGENET_MEAN, IMAGENET_STD)
        cfg = model.config
        if input_size % cfg.patch_size:
            raise UserError(f"{name}: input_size {input_size} is not a multiple of the patch size "
                            f"{cfg.patch_size}; use e.g. {cfg.patch_size * (input_size // cfg.patch_size)}")
        self.name = name  # instance attribute: one class serves several registry entries
        self.model = model.to(_resolve_dtype(dtype))
        self.source = source
        self.num_prefix_tokens = 1 + int(getattr(cfg, "num_register_tokens", 0) or 0)  # CLS + registers
        self._grid = input_size // cfg.patch_size
        self._dim = int(cfg.hidden_size)

    @property
    def num_patches(self) -> int:
        return self._grid * self._grid

    @property
    def dim(self) -> int:
        return self._dim

    def _features(self, pixels: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        dtype = next(self.model.parameters()).dtype
        hidden = self.model(pixel_values=pixels.to(dtype)).last_hidden_state  # (B, 1 + R + N, D)
        return hidden[:, self.num_prefix_tokens:], hidden[:, 0]  # (B, N, D), CLS (B, D)

    def config_dict(self) -> dict[str, Any]:
        """make_encoder kwargs that rebuild this encoder; ``path`` only when loaded from a local directory
        (drop it to rely on the env var / HF cache on another machine)."""
        out: dict[str, Any] = {"name": self.name, "input_size": self.input_size,
                               "dtype": str(next(self.model.parameters()).dtype).removeprefix("torch.")}
        if self.source is not None and Path(self.source).expanduser().is_dir():
            out["path"] = self.source
        return out


def _make_factory(name: str):
    model_name, _, repo, env = HF_ENCODERS[name]

    def factory(path: str | os.PathLike[str] | None = None, config: "PretrainedConfig | None" = None,
                input_size: int = 224, dtype: torch.dtype | str | None = None) -> HFViTEncoder:
        if config is not None:
            model_cls, config_cls = hf_classes(name)
            if not isinstance(config, config_cls):
                raise UserError(f"{name}: config must be a {config_cls.__name__}, got {type(config).__name__}")
            return HFViTEncoder(name, model_cls(config), input_size, dtype, source="random-init")
        model = load_hf_model(name, path)
        return HFViTEncoder(name, model, input_size, dtype, source=str(path or os.environ.get(env) or repo))

    factory.__name__ = f"make_{name.replace('-', '_')}"
    factory.__doc__ = (f"{name}: {model_name} from a local copy of {repo} (path=, or ${env}), or a "
                       f"random init from config=; images resized to input_size (224 -> "
                       f"{(224 // 16) ** 2 if 'dinov3' in name else (224 // 14) ** 2} tokens).")
    return factory


for _name in HF_ENCODERS:
    register_encoder(_name)(_make_factory(_name))
