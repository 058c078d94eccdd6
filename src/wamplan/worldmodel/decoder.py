"""The decoder g_psi: one view's patch tokens -> an RGB image, for looking at predictions only.

A ViT (LayerNorm + linear in, learned positions, ``depth`` blocks) over the N tokens, reshaped to the
sqrt(N) x sqrt(N) grid, then a convolutional head of 2x upsampling stages (nearest + 3x3 conv + GELU)
to ``image_size`` and a sigmoid: pixels in [0, 1]. Trained alone with pixel MSE (paper §3.2); it is
never used for planning and never back-propagates into the predictor.

Dataset items for ``train_decoder``: ``{"z": (N, D) features, "image": (H, W, 3) uint8}`` (the image the
features were computed from; resized to ``image_size`` when H, W differ).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Sequence

import torch
import torch.nn.functional as F
from torch import nn
from torch.utils.data import DataLoader, Dataset

from wamplan.checkpoint import checkpoint_dir, load_weights, read_config
from wamplan.config import from_dict, require, to_dict
from wamplan.device import resolve_device
from wamplan.errors import UserError
from wamplan.train_loop import DatasetBatches, fit, shown
from wamplan.worldmodel.config import RETIRED_TRAIN_KEYS, DecoderConfig, DecoderTrainConfig, TrainConfig
from wamplan.worldmodel.layers import Block, init_weights

KIND = "wm-decoder"
# The predictor's training keys a decoder's does not have. Decoder runs made before the decoder had its own training
# config stored them in their ``train`` section: loading never reads that section, and resuming ignores these keys.
PREDICTOR_ONLY_TRAIN_KEYS = tuple(sorted((TrainConfig.__dataclass_fields__.keys()
                                           - DecoderTrainConfig.__dataclass_fields__.keys()) | set(RETIRED_TRAIN_KEYS)))


class Decoder(nn.Module):
    def __init__(self, cfg: DecoderConfig) -> None:
        super().__init__()
        self.cfg = cfg
        w = cfg.width
        self.in_norm = nn.LayerNorm(cfg.enc_dim)
        self.in_proj = nn.Linear(cfg.enc_dim, w)
        self.pos = nn.Parameter(torch.zeros(cfg.num_patches, w))  # (N, w)
        self.blocks = nn.ModuleList(Block(w, cfg.heads, w // cfg.heads, cfg.mlp_dim) for _ in range(cfg.depth))
        self.norm = nn.LayerNorm(w)
        stages = int(math.log2(cfg.image_size // cfg.grid))
        chans = [max(16, cfg.head_channels >> i) for i in range(stages + 1)]
        layers: list[nn.Module] = [nn.Conv2d(w, chans[0], kernel_size=1)]
        for c_in, c_out in zip(chans[:-1], chans[1:]):
            layers += [nn.Upsample(scale_factor=2, mode="nearest"), nn.Conv2d(c_in, c_out, 3, padding=1), nn.GELU()]
        layers += [nn.Conv2d(chans[-1], 3, 3, padding=1), nn.Sigmoid()]
        self.head = nn.Sequential(*layers)
        init_weights(self)
        nn.init.trunc_normal_(self.pos, std=0.02)

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        """z (B, N, D) -> images (B, 3, S, S) in [0, 1]."""
        b, g = z.shape[0], self.cfg.grid
        x = self.in_proj(self.in_norm(z.float())) + self.pos  # (B, N, w)
        for blk in self.blocks:
            x, _ = blk(x)  # (B, N, w), full attention within the view
        x = self.norm(x).transpose(1, 2).reshape(b, -1, g, g)  # (B, w, g, g), row-major patches
        return self.head(x)  # (B, 3, S, S)

    def num_params(self) -> int:
        return sum(p.numel() for p in self.parameters())


def _target(images: torch.Tensor, size: int) -> torch.Tensor:
    """uint8 (B, H, W, 3) -> float (B, 3, S, S) in [0, 1]."""
    x = images.permute(0, 3, 1, 2).float() / 255.0  # (B, 3, H, W)
    if x.shape[-2:] != (size, size):
        x = F.interpolate(x, size=(size, size), mode="bilinear", align_corners=False, antialias=True)
    return x


def decoder_loss(model: Decoder, batch: dict[str, torch.Tensor]) -> tuple[torch.Tensor, dict[str, float]]:
    """Pixel MSE between the decoded image and the (resized) original."""
    pred = model(batch["z"])  # (B, 3, S, S)
    loss = F.mse_loss(pred, _target(batch["image"], model.cfg.image_size))
    return loss, {}


@torch.no_grad()
def evaluate_decoder(model: Decoder, dataset: Dataset, batch_size: int = 64,
                     device: torch.device | None = None) -> dict[str, float]:
    """Pixel MSE and PSNR (dB) on ``dataset``."""
    device = device or next(model.parameters()).device
    total, count = 0.0, 0
    for batch in DataLoader(dataset, batch_size=batch_size, shuffle=False):
        pred = model(batch["z"].to(device))  # (B, 3, S, S)
        err = (pred - _target(batch["image"].to(device), model.cfg.image_size)).pow(2).flatten(1).mean(1)  # (B,)
        total, count = total + float(err.sum()), count + err.numel()
    mse = total / max(count, 1)
    return {"pixel_mse": mse, "psnr": 10 * math.log10(1.0 / max(mse, 1e-12))}


@torch.no_grad()
def decoded_beside_target(model: Decoder, dataset: Dataset, device: torch.device, n: int = 4) -> Any:
    """The first ``n`` items of ``dataset`` decoded, each beside the image it was encoded from: (n * S, 2 * S, 3)
    uint8 (``train_log.beside_targets``)."""
    from wamplan.train_log import beside_targets

    batch = next(iter(DataLoader(dataset, batch_size=n, shuffle=False)))
    pred = model(batch["z"].to(device))  # (n, 3, S, S)
    target = _target(batch["image"].to(device), model.cfg.image_size)  # (n, 3, S, S)
    return beside_targets(*(x.permute(0, 2, 3, 1).float().cpu().numpy() for x in (pred, target)))


def train_decoder(train_set: Dataset, cfg: DecoderConfig, train: DecoderTrainConfig, out_dir: str | Path, *,
                  val_set: Dataset | None = None, device: str | torch.device = "auto", resume: bool = False,
                  max_steps: int | None = None, progress: bool = True,
                  encoder_info: dict[str, Any] | None = None,
                  data: dict[str, Any] | None = None, task: str | None = None,
                  cameras: Sequence[str] | None = None) -> tuple[Decoder, dict[str, Any]]:
    """Train (or resume) a decoder on (features, image) pairs; same checkpoint layout as the predictor. ``task``
    and ``cameras``: what the images show, recorded (not part of the data a resumed run must match) so that
    :func:`load_decoder` can refuse another task's model."""
    require(isinstance(train, DecoderTrainConfig),
            f"train_decoder takes a DecoderTrainConfig, got {type(train).__name__}; build one with the same "
            f"optimisation values")
    dev = resolve_device(device) if isinstance(device, str) else device
    torch.manual_seed(train.seed)
    model = Decoder(cfg).to(dev)
    trained_on = shown(task, cameras)
    config = {"decoder": to_dict(cfg), "train": to_dict(train), "encoder": encoder_info,
              **({"data": trained_on} if trained_on else {})}
    def evaluate(m: torch.nn.Module) -> dict[str, float]:
        return evaluate_decoder(m, val_set, 2 * train.batch_size, dev)  # type: ignore[arg-type]

    def pictures(m: torch.nn.Module) -> dict[str, Any]:
        return {"val/decoded_vs_target": decoded_beside_target(m, val_set, dev)}  # type: ignore[arg-type]

    result = fit(model, DatasetBatches(train_set, train.num_workers, dev.type != "cpu"), decoder_loss, train,
                 run_dir=out_dir, kind=KIND, config=config, data=data, device=dev,
                 evaluate=evaluate if val_set is not None else None, resume=resume, max_steps=max_steps,
                 progress=progress, desc="decoder", log=print if progress else None,
                 retired={"train": PREDICTOR_ONLY_TRAIN_KEYS}, pictures=pictures if val_set is not None else None)
    return model.eval(), result.metrics


def load_decoder(path: str | Path, device: str | torch.device = "cpu", encoder: Any = None,
                 task: str | None = None) -> Decoder:
    """A trained decoder (eval mode) from a checkpoint directory (or a training ``out_dir``). ``encoder``: the
    frozen encoder whose tokens it will draw; a decoder trained on another encoder's tokens is refused. ``task``:
    the task of the model it draws; a decoder that records another task is refused (one that records none is
    taken)."""
    from wamplan.data.features import feature_key

    ckpt = checkpoint_dir(path)
    config = read_config(ckpt, KIND)
    drawn = (config.get("data") or {}).get("task")
    if task is not None and drawn is not None and drawn != task:
        raise UserError(f"decoder {path} draws views of task '{drawn}', the world model is of task '{task}'; pass "
                        f"a decoder trained on that task's stores (`wamplan wm train-decoder`)")
    theirs = config.get("encoder")
    if encoder is not None and theirs and feature_key(theirs) != feature_key(encoder.config_dict()):
        mine = {k: v for k, v in encoder.config_dict().items() if k != "path"}
        raise UserError(f"decoder {path} was trained on the tokens of encoder {theirs}, the world model encodes "
                        f"with {mine}; pass a decoder trained with the same encoder settings")
    cfg = from_dict(DecoderConfig, config["decoder"])
    model = Decoder(cfg)
    load_weights(ckpt, model)
    return model.to(resolve_device(device) if isinstance(device, str) else device).eval()
