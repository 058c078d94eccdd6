"""The frozen-encoder interface and its registry.

An encoder maps uint8 images ``(B, H, W, 3)`` to patch tokens ``(B, N, D)`` (and, where the model has
one, a CLS token ``(B, D)``). Encoders are frozen: always in eval mode, no parameter requires grad, and
``encode`` runs under ``torch.inference_mode``. The world model is trained and plans in this space.

    enc = make_encoder("patch-pixels")            # or "dinov3-vitl16", path=DIR
    z = enc.encode(images)                        # (B, enc.num_patches, enc.dim) float32
"""

from __future__ import annotations

import inspect
from typing import Any, ClassVar

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from wamplan.errors import UserError
from wamplan.registry import Registry

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


class FrozenEncoder(nn.Module):
    """Base class. Subclasses implement ``_features`` and the ``num_patches``/``dim`` properties."""

    name: ClassVar[str] = ""

    def __init__(self, input_size: int, mean: tuple[float, ...] = IMAGENET_MEAN,
                 std: tuple[float, ...] = IMAGENET_STD) -> None:
        super().__init__()
        if input_size <= 0:
            raise UserError(f"encoder input_size must be > 0, got {input_size}")
        self._input_size = int(input_size)
        self.register_buffer("pixel_mean", torch.tensor(mean, dtype=torch.float32).view(1, 3, 1, 1),
                             persistent=False)
        self.register_buffer("pixel_std", torch.tensor(std, dtype=torch.float32).view(1, 3, 1, 1),
                             persistent=False)

    # -- what a subclass provides ------------------------------------------------------------------
    @property
    def num_patches(self) -> int:
        """N, the number of patch tokens per image."""
        raise NotImplementedError

    @property
    def dim(self) -> int:
        """D, the feature size of one token."""
        raise NotImplementedError

    def _features(self, pixels: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        """pixels (B, 3, S, S) normalised float32 -> (patches (B, N, D), cls (B, D) or None)."""
        raise NotImplementedError

    def config_dict(self) -> dict[str, Any]:
        """``{"name": ..., **kwargs}`` such that ``make_encoder(**config_dict())`` rebuilds this encoder
        (stored as provenance next to features and checkpoints)."""
        return {"name": self.name, "input_size": self.input_size}

    # -- shared --------------------------------------------------------------------------------------
    @property
    def input_size(self) -> int:
        """Side S of the square image the encoder sees (inputs are resized to S x S)."""
        return self._input_size

    @property
    def device(self) -> torch.device:
        return self.pixel_mean.device

    def freeze(self) -> "FrozenEncoder":
        """Eval mode and no gradients; called by every constructor."""
        for p in self.parameters():
            p.requires_grad_(False)
        return super().train(False)

    def train(self, mode: bool = True) -> "FrozenEncoder":
        """A frozen encoder stays in eval mode whatever a caller asks."""
        return super().train(False)

    def preprocess(self, images: torch.Tensor | np.ndarray) -> torch.Tensor:
        """uint8 (B, H, W, 3) or (H, W, 3) -> normalised float32 (B, 3, S, S) on the encoder's device."""
        x = torch.as_tensor(images)
        if x.dtype != torch.uint8:
            raise UserError(f"{self.name}: encode expects uint8 images (B, H, W, 3); got dtype {x.dtype} "
                            f"(convert with (img * 255).round().clamp(0, 255).to(torch.uint8))")
        if x.ndim == 3:
            x = x[None]
        if x.ndim != 4 or x.shape[-1] != 3:
            raise UserError(f"{self.name}: encode expects images shaped (B, H, W, 3); got {tuple(x.shape)}")
        x = x.to(self.device).permute(0, 3, 1, 2).float().div_(255.0)  # (B, 3, H, W) in [0, 1]
        s = self.input_size
        if x.shape[-2:] != (s, s):
            x = F.interpolate(x, size=(s, s), mode="bilinear", align_corners=False, antialias=True)
        return (x - self.pixel_mean) / self.pixel_std  # (B, 3, S, S)

    def encode(self, images: torch.Tensor | np.ndarray, return_cls: bool = False
               ) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor | None]:
        """uint8 images (B, H, W, 3) -> patch tokens (B, N, D) float32 [, CLS (B, D) or None].

        Runs under ``torch.inference_mode``: the results are inference tensors (``.clone()`` them
        outside inference mode before an in-place op or saving them for backward)."""
        with torch.inference_mode():
            patches, cls = self._features(self.preprocess(images))
            patches = patches.float()  # (B, N, D)
            cls = cls.float() if cls is not None else None  # (B, D)
        if patches.shape[1:] != (self.num_patches, self.dim):
            raise RuntimeError(f"{self.name}: produced {tuple(patches.shape[1:])} tokens, "
                               f"expected {(self.num_patches, self.dim)}")
        return (patches, cls) if return_cls else patches

    def encode_batched(self, images: torch.Tensor | np.ndarray, batch_size: int = 64) -> torch.Tensor:
        """``encode`` in slices of ``batch_size`` images (bounded memory); returns (B, N, D) on the CPU."""
        x = torch.as_tensor(images)
        if x.ndim == 3:
            x = x[None]
        parts = [self.encode(x[i:i + batch_size]).cpu() for i in range(0, x.shape[0], batch_size)]
        return torch.cat(parts) if parts else torch.empty(0, self.num_patches, self.dim)


ENCODERS = Registry("encoder", modules=("wamplan.encoders.hf", "wamplan.encoders.patch_pixels"))
register_encoder = ENCODERS.register  # a FrozenEncoder subclass or a factory function, by name
# Encoders that left the core (no measured gain; their record is in the lab's table): name -> the last commit that
# has them, where a world model or feature cache made with one still loads.
RETIRED_ENCODERS = {"object-masks": "f07acf1", "task-cnn": "9c6eb5d", "concat": "9c6eb5d"}


def encoder_names() -> list[str]:
    return sorted(ENCODERS)


def encoder_settings(name: str) -> list[str] | None:
    """The settings the registered encoder ``name`` takes (None: any, its factory takes ``**kwargs``); one line for
    one of :data:`RETIRED_ENCODERS`."""
    if name in RETIRED_ENCODERS and name not in ENCODERS:  # a plug-in may register the name again
        raise UserError(f"encoder '{name}' left wamplan (it measured no gain: lab/README.md); what was made with it "
                        f"runs at commit {RETIRED_ENCODERS[name]} or earlier")
    params = inspect.signature(ENCODERS.lookup(name)).parameters
    return None if any(p.kind is p.VAR_KEYWORD for p in params.values()) else list(params)


def make_encoder(name: str, **kwargs: Any) -> FrozenEncoder:
    """Build the registered encoder ``name`` (frozen, eval mode) with ``kwargs``; an unknown setting is a
    UserError naming the ones it takes."""
    takes = encoder_settings(name)
    unknown = sorted(set(kwargs) - set(takes)) if takes is not None else []
    if unknown:
        raise UserError(f"encoder {name} has no setting {', '.join(unknown)}; it takes {', '.join(takes) or 'none'}")
    return ENCODERS.lookup(name)(**kwargs).freeze()
