"""``object-masks``: where each object is, per patch token. An object-centric encoder trained on the simulator's
segmentation, then frozen.

A fixed projection of pixel patches (``patch-pixels``) spends its numbers on colour and texture, and the wrist
camera's table texture sweeps through every patch as the arm moves. This encoder keeps only geometry: a small CNN
reads, for each 4 x 4 px cell of a 64 px picture, the probability that it shows the robot or each of the task's
objects (the cube, the mount; StackCube's two cubes), and a patch token is those probabilities over its 4 x 4 cells
(the table's class is dropped): 16 tokens of (classes - 1) x 16 dims, the ``patch-pixels`` grid, so it sits beside
patch-pixels in a ``concat`` and a grown world model predicts both. Its supervision is training-only (the
simulator's segmentation, :func:`wamplan.data.foreground.collect_foreground`); once trained it sees images only,
real ones or a WAM's predicted ones.

    wamplan wm train-masks --policy checkpoints/mini/tinywam --frames runs/masks.npz --out runs/masks
    wamplan wm train --encoder concat --encoder-kwargs \\
        '{"parts": [{"name": "patch-pixels"}, {"name": "object-masks", "ckpt": "runs/masks"}], "scales": [1, S]}' ...
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from wamplan.config import check_numbers, field, require, to_dict, with_default
from wamplan.data.foreground import ForegroundFrames
from wamplan.encoders.base import FrozenEncoder, register_encoder
from wamplan.encoders.learned import load_trained
from wamplan.errors import UserError
from wamplan.train_config import AdamWConfig

KIND = "encoder-object-masks"
GRID, SUB = 4, 4  # a 4 x 4 token grid, each token 4 x 4 cells: a 16 x 16 class map of a 64 px picture
CELLS = GRID * SUB


class MaskNet(nn.Module):
    """pixels (B, 3, 64, 64) normalised -> class logits (B, C, 16, 16): two stride-2 convolutions, then two 3 x 3
    ones (the second dilated) and a 1 x 1 read-out per cell."""

    def __init__(self, classes: int, width: int = 64) -> None:
        super().__init__()
        self.classes = classes
        self.body = nn.Sequential(
            nn.Conv2d(3, 32, 4, stride=2, padding=1), nn.GELU(),  # 32 x 32
            nn.Conv2d(32, width, 4, stride=2, padding=1), nn.GELU(),  # 16 x 16
            nn.Conv2d(width, width, 3, padding=1), nn.GELU(),
            nn.Conv2d(width, width, 3, padding=2, dilation=2), nn.GELU(),
            nn.Conv2d(width, classes, 1))

    def forward(self, pixels: torch.Tensor) -> torch.Tensor:
        return self.body(pixels)


def mask_tokens(logits: torch.Tensor) -> torch.Tensor:
    """class logits (B, C, 16, 16) -> tokens (B, 16, (C - 1) * 16): each patch's cells' probabilities of every class
    but the background, class-major then row-major within the patch; patches row-major (the encoders' order)."""
    p = logits.softmax(1)[:, 1:]  # (B, K, 16, 16)
    b, k = p.shape[:2]
    p = p.reshape(b, k, GRID, SUB, GRID, SUB).permute(0, 2, 4, 1, 3, 5)  # (B, gy, gx, K, sy, sx)
    return p.reshape(b, GRID * GRID, k * SUB * SUB)


def token_maps(tokens: torch.Tensor) -> torch.Tensor:
    """tokens (B, 16, (C - 1) * 16) of :func:`mask_tokens` (true or predicted) -> class maps (B, C, 16, 16): the
    probabilities back on the 16 x 16 cells, the background's as what the other classes leave (clipped at 0)."""
    b, n, d = tokens.shape
    k = d // (SUB * SUB)
    p = tokens.reshape(b, GRID, GRID, k, SUB, SUB).permute(0, 3, 1, 4, 2, 5).reshape(b, k, CELLS, CELLS)
    return torch.cat([(1 - p.sum(1, keepdim=True)).clamp_min(0), p], 1)  # (B, C, 16, 16)


@register_encoder("object-masks")
class ObjectMaskEncoder(FrozenEncoder):
    """The trained ``object-masks`` network of checkpoint directory ``ckpt`` (a run of ``wm train-masks`` or its
    export), frozen. ``sha`` and ``near`` as ``task-cnn``'s."""

    name = "object-masks"

    def __init__(self, ckpt: str | None = None, sha: str | None = None, input_size: int = 64,
                 net: MaskNet | None = None, near: str | None = None) -> None:
        super().__init__(input_size)
        if input_size != 64:
            raise UserError(f"object-masks: input_size must be 64 (its 16 x 16 cells), got {input_size}")
        classes: list[str] | None = None
        if net is None:
            if not ckpt:
                raise UserError("object-masks needs its trained weights: --encoder-kwargs '{\"ckpt\": DIR}', a run of "
                                "`wamplan wm train-masks` or its export")
            net, sha, saved = load_trained(self.name, KIND, ckpt, near, sha,
                                           lambda saved: MaskNet(len(saved["net"]["classes"]),
                                                                 int(saved["net"]["width"])))
            classes = list(saved["net"]["classes"])
        self.net, self.ckpt, self.sha, self.classes = net, ckpt, sha, classes

    @property
    def num_patches(self) -> int:
        return GRID * GRID

    @property
    def dim(self) -> int:
        return (self.net.classes - 1) * SUB * SUB

    def class_maps(self, images: torch.Tensor | np.ndarray) -> torch.Tensor:
        """uint8 (B, H, W, 3) -> class probabilities (B, C, 16, 16), for pictures of what it reads."""
        with torch.inference_mode():
            return self.net(self.preprocess(images)).softmax(1)

    def _features(self, pixels: torch.Tensor) -> tuple[torch.Tensor, None]:
        return mask_tokens(self.net(pixels)), None  # (B, 16, (C - 1) 16)

    def config_dict(self) -> dict[str, Any]:
        return {"name": self.name, "ckpt": self.ckpt, "sha": self.sha, "input_size": self.input_size}


@dataclass(frozen=True)
class MaskTrainConfig(AdamWConfig):
    """Training of the ``object-masks`` network: the loop's fields (defaults: 20 epochs at lr 2e-3 in batches of 64
    pictures) and its width."""

    epochs: int = with_default(AdamWConfig, "epochs", 20)
    batch_size: int = with_default(AdamWConfig, "batch_size", 64)
    lr: float = with_default(AdamWConfig, "lr", 2e-3)
    width: int = field(64, "channels of the 16 x 16 layers")

    def __post_init__(self) -> None:
        check_numbers(self)
        super().__post_init__()
        require(isinstance(self.width, int) and self.width > 0, f"width must be a positive int, got {self.width}")


def cell_shares(labels: np.ndarray, classes: int) -> torch.Tensor:
    """(B, H, W) class indices -> (B, C, 16, 16) float32: each cell's share of every class (H, W multiples of 16)."""
    b, h, w = labels.shape
    require(h % CELLS == 0 and w % CELLS == 0, f"pictures of {h} x {w} px do not split into {CELLS} x {CELLS} cells; "
                                               f"render at a multiple of {CELLS} px (--camera-size)")
    lab = torch.from_numpy(np.ascontiguousarray(labels)).reshape(b, CELLS, h // CELLS, CELLS, w // CELLS)
    return torch.stack([(lab == c).float().mean((2, 4)) for c in range(classes)], 1)  # (B, C, 16, 16)


class MaskTrainer(nn.Module):
    """The network under training; ``net.`` prefixes its weights as the encoder loads them."""

    def __init__(self, classes: int, width: int) -> None:
        super().__init__()
        self.net = MaskNet(classes, width)

    def loss(self, pixels: torch.Tensor, shares: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """pixels (B, 3, 64, 64), shares (B, C, 16, 16) -> (cross-entropy against the cells' shares, the logits
        (B, C, 16, 16))."""
        logits = self.net(pixels)  # (B, C, 16, 16)
        return -(shares * logits.log_softmax(1)).sum(1).mean(), logits


def intersection_union(logits: torch.Tensor, shares: torch.Tensor) -> torch.Tensor:
    """Per class, the cells where the most likely class is it and where the true majority class is it: their
    intersection and union, counted (2, C)."""
    c = logits.shape[1]
    pred = F.one_hot(logits.argmax(1), c).bool()  # (B, 16, 16, C)
    true = F.one_hot(shares.argmax(1), c).bool()
    return torch.stack([(pred & true).sum((0, 1, 2)), (pred | true).sum((0, 1, 2))]).float()  # (2, C)


def picture_data(frames: ForegroundFrames, encoder: FrozenEncoder, idx: np.ndarray, chunk: int = 64
                 ) -> tuple[torch.Tensor, torch.Tensor]:
    """Frames ``idx`` as single pictures: (pixels (n V, 3, 64, 64) as the encoder sees them, shares
    (n V, C, 16, 16)), made ``chunk`` frames at a time (full-size pictures are never all in memory at once)."""
    pixels, shares = [], []
    for i in range(0, len(idx), chunk):
        part = idx[i:i + chunk]
        pixels.append(encoder.preprocess(frames.images[part].reshape(-1, *frames.images.shape[2:])).cpu())
        shares.append(cell_shares(frames.labels[part].reshape(-1, *frames.labels.shape[2:]), len(frames.classes)))
    if not pixels:
        return torch.empty(0, 3, 64, 64), torch.empty(0, len(frames.classes), CELLS, CELLS)
    return torch.cat(pixels), torch.cat(shares)


VAL_FRACTION = 0.2  # the share of episodes (the last, by seed) a run holds out


def held_out(frames: ForegroundFrames, val_fraction: float = VAL_FRACTION) -> np.ndarray:
    """(F,) bool: the frames of the last ``val_fraction`` of the episodes (by seed), at least one episode and at
    most all but one."""
    eps = np.unique(frames.episode)  # sorted
    require(len(eps) >= 2, f"training needs frames of at least 2 episodes (one held out), got {len(eps)}")
    count = min(len(eps) - 1, max(1, int(round(val_fraction * len(eps)))))
    return np.isin(frames.episode, eps[-count:])


def train_object_masks(frames: ForegroundFrames, out: str | Path, cfg: MaskTrainConfig, *, task: str,
                       val_fraction: float = VAL_FRACTION, device: str = "cpu", resume: bool = False,
                       max_steps: int | None = None, progress: bool = True) -> dict[str, float]:
    """Train (or resume) the ``object-masks`` network on ``frames`` into the run directory ``out``; the last
    ``val_fraction`` of the episodes are held out. Returns the last metrics: ``val/ce`` and ``val/iou_<class>`` (the
    held-out cells' intersection over union of each class, most likely class against the true majority)."""
    from torch.utils.data import DataLoader, TensorDataset

    from wamplan.device import resolve_device
    from wamplan.train_loop import DatasetBatches, evaluating, fit

    dev = resolve_device(device)
    val = held_out(frames, val_fraction)
    pixels_of = ObjectMaskEncoder(net=MaskNet(len(frames.classes)))  # the encoder's preprocessing (its net unused)
    tr = TensorDataset(*picture_data(frames, pixels_of, np.flatnonzero(~val)))
    va = TensorDataset(*picture_data(frames, pixels_of, np.flatnonzero(val)))
    if progress:
        print(f"pictures: {len(tr)} train, {len(va)} held out; classes {', '.join(frames.classes)}")
    torch.manual_seed(cfg.seed)
    model = MaskTrainer(len(frames.classes), cfg.width).to(dev)

    def step(m: MaskTrainer, batch: list[torch.Tensor]) -> tuple[torch.Tensor, dict[str, float]]:
        ce, _ = m.loss(batch[0].to(dev), batch[1].to(dev))
        return ce, {"ce": float(ce.detach())}

    def evaluate(m: MaskTrainer) -> dict[str, float]:
        ce_sum, iu, n = 0.0, torch.zeros(2, len(frames.classes)), 0
        with evaluating(m):
            for pixels, shares in DataLoader(va, batch_size=256):
                ce, logits = m.loss(pixels.to(dev), shares.to(dev))
                iu += intersection_union(logits, shares.to(dev)).cpu()
                ce_sum, n = ce_sum + float(ce) * len(pixels), n + len(pixels)
        iou = iu[0] / iu[1].clamp(min=1)
        return {"ce": ce_sum / max(n, 1), **{f"iou_{c}": float(v) for c, v in zip(frames.classes, iou)}}

    config = {"net": {"classes": list(frames.classes), "width": cfg.width}, "train": to_dict(cfg),
              "data": {"task": task, "cameras": list(frames.cameras)}}
    data = {"episodes": sorted(int(s) for s in np.unique(frames.episode)), "frames": int(len(frames.episode)),
            "val_fraction": val_fraction}
    batches = DatasetBatches(tr, cfg.num_workers, dev.type != "cpu")
    result = fit(model, batches, step, cfg, run_dir=out, kind=KIND, config=config, data=data, device=dev,
                 evaluate=evaluate if len(va) else None, resume=resume, max_steps=max_steps, progress=progress,
                 desc="object-masks", log=print if progress else None)
    return result.metrics


def episode_frames(frames: ForegroundFrames, seed: int, count: int) -> np.ndarray:
    """Indices (count,) of up to ``count`` frames of episode ``seed``, spread evenly over it."""
    idx = np.flatnonzero(frames.episode == seed)
    return idx[np.linspace(0, len(idx) - 1, min(count, len(idx))).round().astype(int)]


def draw_frame_maps(frames: ForegroundFrames, idx: np.ndarray, maps: Sequence[tuple[str, np.ndarray]], title: str,
                    out: str | Path, **imshow: Any) -> Path:
    """A PNG with a row per frame of ``idx``: per camera its picture, then each of ``maps`` (label, (len(idx), V,
    g, g) maps of the frames) drawn with ``imshow``'s settings."""
    import matplotlib.pyplot as plt

    from wamplan.plot import save_figure

    cams, per = frames.cameras, 1 + len(maps)
    fig, axes = plt.subplots(len(idx), per * len(cams), figsize=(2.0 * per * len(cams), 2.1 * len(idx)),
                             squeeze=False)
    for r, i in enumerate(idx):
        for c, cam in enumerate(cams):
            panels = [(frames.images[i, c], f"{cam}, frame {r + 1}")] + [(m[r, c], label) for label, m in maps]
            for k, (img, name) in enumerate(panels):
                ax = axes[r, per * c + k]
                ax.imshow(img, **imshow) if img.ndim == 2 else ax.imshow(img)
                ax.set_title(name, fontsize=8)
                ax.axis("off")
    fig.suptitle(title, fontsize=10)
    return save_figure(fig, out, dpi=70)


def draw_masks(frames: ForegroundFrames, encoder: ObjectMaskEncoder, out: str | Path, seed: int | None = None,
               count: int = 4) -> Path:
    """A PNG of ``count`` frames of episode ``seed`` (default: the highest seed, held out), spread over it: per camera
    the picture, the true class of each cell (majority) and the encoder's most likely one."""
    seed = int(frames.episode.max()) if seed is None else seed
    idx = episode_frames(frames, seed, count)  # (count,)
    v, c = len(frames.cameras), len(frames.classes)
    labels = frames.labels[idx].reshape(-1, *frames.labels.shape[2:])  # (count V, H, W)
    true = cell_shares(labels, c).argmax(1).numpy().reshape(len(idx), v, CELLS, CELLS)
    read = encoder.class_maps(frames.images[idx].reshape(-1, *frames.images.shape[2:])).argmax(1).cpu().numpy()
    maps = [("true class", true), ("read", read.reshape(len(idx), v, CELLS, CELLS))]
    names = ", ".join(f"{i} {n}" for i, n in enumerate(frames.classes))
    return draw_frame_maps(frames, idx, maps, f"object masks, episode {seed}: {names}", out,
                           vmin=0, vmax=c - 1, cmap="tab10", interpolation="nearest")
