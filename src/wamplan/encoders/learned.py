"""``task-cnn``: an encoder learned from a task's own images, trained once and then frozen.

No pretrained encoder can be downloaded on a machine without the model hubs, and a fixed projection of pixel
patches (``patch-pixels``) spends most of its numbers on the table's texture, which sweeps through every patch
of the wrist camera as the arm moves. This encoder is a small CNN trained on the episode stores of the task with
training-only supervision: from each view's tokens a linear read-out must give the frame's privileged state
(``data.readers.STATE_QUANTITIES``: the held object relative to the gripper and in the world, cm), and a small
decoder must redraw the view at 16 x 16 px (``recon_weight``), which keeps the arm and the scene's layout but
not fine texture. Nothing privileged is read once it is trained: the encoder sees images only.

Layout: 64 x 64 px -> four stride-2 convolutions -> a 4 x 4 grid of 128-D tokens, the ``patch-pixels`` layout
(N = 16, D = 128), so the ``mini`` predictor fits it unchanged.

    wamplan wm train-encoder --data STORES --out runs/enc        # trains; exports nothing
    python -c "from wamplan.checkpoint import export_for_inference as e; e('runs/enc/checkpoint', 'enc16')"
    wamplan wm train --encoder task-cnn --encoder-kwargs '{"ckpt": "enc16"}' --data STORES --out runs/wm

A world model's checkpoint records the encoder's directory and a digest of its weights; loading it with other
weights in that directory is refused.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

import torch
import torch.nn.functional as F
from torch import nn
from torch.utils.data import Dataset, TensorDataset

from wamplan.checkpoint import MODEL_FILE, checkpoint_dir, load_tensors, read_config
from wamplan.config import check_numbers, field, require, to_dict, with_default
from wamplan.encoders.base import ENCODERS, FrozenEncoder, encoder_settings, register_encoder
from wamplan.errors import UserError
from wamplan.train_config import AdamWConfig

KIND = "encoder-task-cnn"
NET_PREFIX = "net."  # the CNN's weights inside a training checkpoint (read-out and decoder are dropped)


class CNNTokens(nn.Module):
    """pixels (B, 3, 64, 64) normalised -> tokens (B, 16, width): four 4x4 stride-2 convolutions."""

    def __init__(self, width: int = 128) -> None:
        super().__init__()
        chans = (3, 32, 64, width, width)
        layers: list[nn.Module] = []
        for i in range(4):
            layers += [nn.Conv2d(chans[i], chans[i + 1], 4, stride=2, padding=1)] + ([nn.GELU()] if i < 3 else [])
        self.body = nn.Sequential(*layers)

    def forward(self, pixels: torch.Tensor) -> torch.Tensor:
        return self.body(pixels).flatten(2).transpose(1, 2)  # (B, C, 4, 4) -> (B, 16, C)


def weights_digest(ckpt: str | Path) -> str:
    """The first 12 hex digits of the sha1 of a checkpoint's weights file."""
    return hashlib.sha1((Path(ckpt) / MODEL_FILE).read_bytes()).hexdigest()[:12]


def locate_weights(name: str, info: dict[str, Any], near: str | Path) -> dict[str, Any]:
    """The settings ``info`` of encoder ``name`` (from a world model's ``encoder`` record) with ``near`` (the world
    model's checkpoint) given to each trained encoder in it (one that takes ``near``), its own or a ``concat``
    part's, to find relative weights by (see ``task-cnn``'s ``near``); the record itself (``config_dict``) is
    unchanged."""
    if name == "concat" and isinstance(info.get("parts"), list):
        return {**info, "parts": [{"name": p.get("name"), **locate_weights(p.get("name"), p, near)}
                                  for p in info["parts"]]}
    takes_near = name in ENCODERS and "near" in (encoder_settings(name) or [])
    return {**info, "near": str(near)} if takes_near and info.get("ckpt") else info


def load_trained(name: str, kind: str, ckpt: str, near: str | None, sha: str | None,
                 build: Callable[[dict[str, Any]], nn.Module]) -> tuple[nn.Module, str, dict[str, Any]]:
    """A trained encoder ``name``'s network from checkpoint directory ``ckpt`` (of ``kind``; found as :func:`_find`
    says): ``build(saved config)`` makes it, its ``net.`` weights are loaded. Returns (network, weights digest,
    saved config); one line where the digest is not ``sha`` (unless None)."""
    path = checkpoint_dir(_find(ckpt, near, sha, name))
    saved = read_config(path, kind)
    net = build(saved)
    digest = weights_digest(path)
    if sha is not None and sha != digest:
        raise UserError(f"{name}: the weights in {path} (digest {digest}) are not the ones this model was "
                        f"trained on ({sha}); restore that encoder at {ckpt}")
    net.load_state_dict({k[len(NET_PREFIX):]: v.float() for k, v in load_tensors(path / MODEL_FILE).items()
                         if k.startswith(NET_PREFIX)})
    return net, digest, saved


def _find(ckpt: str, near: str | None, sha: str | None, name: str = "task-cnn") -> Path:
    """The first of ``ckpt`` as given (from the current folder) and ``ckpt`` under each folder above ``near`` that
    holds it with weights of digest ``sha`` (any, where None); one line naming what was read otherwise."""
    bases = [Path()] + ([] if near is None or Path(ckpt).is_absolute() else list(Path(near).resolve().parents))
    found = [b / ckpt for b in bases if (b / ckpt).exists()]
    for path in found:
        weights = checkpoint_dir(path) / MODEL_FILE
        if sha is None or not weights.is_file() or weights_digest(weights.parent) == sha:
            return path  # (a folder without weights: the checkpoint loader names what is missing)
    if found:
        return found[0]  # other weights: the digest check names them
    if near is None:
        return Path(ckpt)  # the checkpoint loader names what is missing
    raise UserError(f"{near} reads its {name} encoder's weights from {ckpt} (its config.json), found neither from "
                    f"here ({Path.cwd()}) nor in a folder above it; run from the folder it was trained in, or put the "
                    f"encoder's checkpoint there")


@register_encoder("task-cnn")
class TaskCNNEncoder(FrozenEncoder):
    """The trained ``task-cnn`` of checkpoint directory ``ckpt`` (a training run's or an export), frozen.
    ``sha``: the digest its weights must have (a world model records it); None accepts any. ``near``: a world model's
    checkpoint that records this encoder: a relative ``ckpt`` not found from the current folder is looked for under
    the folders above it (``config_dict`` keeps ``ckpt`` as given)."""

    name = "task-cnn"

    def __init__(self, ckpt: str | None = None, sha: str | None = None, input_size: int = 64,
                 net: CNNTokens | None = None, near: str | None = None) -> None:
        super().__init__(input_size)
        if input_size != 64:
            raise UserError(f"task-cnn: input_size must be 64 (its 4 x 4 token grid), got {input_size}")
        if net is None:
            if not ckpt:
                raise UserError("task-cnn needs its trained weights: --encoder-kwargs '{\"ckpt\": DIR}', a run of "
                                "`wamplan wm train-encoder` or its export")
            net, sha, _ = load_trained(self.name, KIND, ckpt, near, sha,
                                       lambda saved: CNNTokens(int(saved["net"]["width"])))
        self.net, self.ckpt, self.sha = net, ckpt, sha

    @property
    def num_patches(self) -> int:
        return 16

    @property
    def dim(self) -> int:
        return self.net.body[-1].out_channels

    def _features(self, pixels: torch.Tensor) -> tuple[torch.Tensor, None]:
        return self.net(pixels), None  # (B, 16, D)

    def config_dict(self) -> dict[str, Any]:
        return {"name": self.name, "ckpt": self.ckpt, "sha": self.sha, "input_size": self.input_size}



@dataclass(frozen=True)
class EncoderTrainConfig(AdamWConfig):
    """Training of the ``task-cnn`` encoder: the loop's fields (defaults: the recipe the candidate encoders were
    trained with, 10 epochs at lr 1e-3 in batches of 64 (docs/results.md), not the world model's), the token width
    and the two objectives' weights."""

    epochs: int = with_default(AdamWConfig, "epochs", 10)
    batch_size: int = with_default(AdamWConfig, "batch_size", 64)
    lr: float = with_default(AdamWConfig, "lr", 1e-3)
    width: int = field(128, "D, the feature size of a token")
    recon_weight: float = field(0.1, "weight of redrawing each view at 16 x 16 px from its tokens, against the "
                                     "state read-out's (cm^2); 0 drops it")

    def __post_init__(self) -> None:
        check_numbers(self)
        super().__post_init__()
        require(isinstance(self.width, int) and self.width > 0, f"width must be a positive int, got {self.width}")
        require(self.recon_weight >= 0, f"recon_weight must be >= 0, got {self.recon_weight}")


class EncoderTrainer(nn.Module):
    """The CNN with its training-only heads: per view a linear read-out of the state, and a decoder to 16 px."""

    def __init__(self, cfg: EncoderTrainConfig, views: int, state_dim: int) -> None:
        super().__init__()
        self.net = CNNTokens(cfg.width)
        self.readout = nn.ModuleList(nn.Linear(16 * cfg.width, state_dim) for _ in range(views))
        self.decoder = nn.Sequential(nn.ConvTranspose2d(cfg.width, 64, 4, stride=2, padding=1), nn.GELU(),
                                     nn.ConvTranspose2d(64, 3, 4, stride=2, padding=1))

    def losses(self, pixels: torch.Tensor, state: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """pixels (B, V, 3, 64, 64) preprocessed (:func:`preprocessed`), state (B, S) -> (state MSE in cm^2, 16-px
        redraw MSE), each a mean."""
        b, v = pixels.shape[:2]
        pixels = pixels.flatten(0, 1)  # (B V, 3, 64, 64)
        tokens = self.net(pixels)  # (B V, 16, D)
        per_view = tokens.unflatten(0, (b, v)).flatten(2)  # (B, V, 16 D)
        read = torch.stack([head(per_view[:, i]) for i, head in enumerate(self.readout)], 1)  # (B, V, S)
        e_state = (read - state[:, None]).pow(2).mean()
        grid = tokens.transpose(1, 2).unflatten(2, (4, 4))  # (B V, D, 4, 4)
        e_recon = (self.decoder(grid) - F.avg_pool2d(pixels, 4)).pow(2).mean()  # (B V, 3, 16, 16)
        return e_state, e_recon


def preprocessed(frames: Dataset, encoder: FrozenEncoder, progress: bool = True) -> TensorDataset:
    """Every item of ``frames`` (``data.readers.StateFrames``) decoded and resized once, held in memory: a dataset of
    (pixels (V, 3, 64, 64) float32 as the encoder sees them, state (S,)) pairs, so an epoch costs no decoding."""
    from wamplan.progress import progress_bar

    pixels, states = [], []
    for i in progress_bar(range(len(frames)), desc="decode frames", leave=False, disable=not progress):
        item = frames[i]
        pixels.append(encoder.preprocess(item["images"]))  # (V, 3, 64, 64)
        states.append(item["s"])
    if not pixels:
        return TensorDataset(torch.empty(0, 1, 3, 64, 64), torch.empty(0, 1))
    return TensorDataset(torch.stack(pixels), torch.stack(states))


def train_task_cnn(stores: Sequence[str | Path], out: str | Path, cfg: EncoderTrainConfig, *,
                   val_fraction: float = 0.1, device: str = "cpu", resume: bool = False,
                   max_steps: int | None = None, progress: bool = True) -> dict[str, float]:
    """Train (or resume) the ``task-cnn`` encoder on every stored frame of ``stores`` into the run directory
    ``out``; returns the last metrics (``val/state_mm``: the read-out's held-out error, root mean square, mm)."""
    from wamplan.data.readers import STATE_QUANTITIES, STATE_UNIT_MM, StateFrames
    from wamplan.data.store import describe_stores
    from wamplan.device import resolve_device
    from wamplan.train_loop import DatasetBatches, evaluating, fit
    from torch.utils.data import DataLoader

    dev = resolve_device(device)
    tr = StateFrames(stores, split="train", val_fraction=val_fraction)
    va = StateFrames(stores, split="val", val_fraction=val_fraction)
    if progress:
        print(f"frames: {len(tr)} train, {len(va)} val, {len(tr.cameras)} views each")
    torch.manual_seed(cfg.seed)
    model = EncoderTrainer(cfg, len(tr.cameras), len(STATE_QUANTITIES)).to(dev)
    cameras = tr.cameras

    pixels_of = TaskCNNEncoder(net=CNNTokens(cfg.width))  # the encoder's preprocessing (its CNN unused)
    tr, va = preprocessed(tr, pixels_of, progress), preprocessed(va, pixels_of, progress)

    def step(m: EncoderTrainer, batch: list[torch.Tensor]) -> tuple[torch.Tensor, dict[str, float]]:
        e_state, e_recon = m.losses(batch[0].to(dev), batch[1].to(dev).float())
        return e_state + cfg.recon_weight * e_recon, {"state_mm": float(e_state.detach().sqrt()) * STATE_UNIT_MM,
                                                       "recon_mse": float(e_recon.detach())}

    def evaluate(m: EncoderTrainer) -> dict[str, float]:
        tot = torch.zeros(2, dtype=torch.float64)
        n = 0
        with evaluating(m):
            for pixels, state in DataLoader(va, batch_size=cfg.batch_size):
                e = m.losses(pixels.to(dev), state.to(dev).float())
                tot += torch.tensor([float(x) for x in e], dtype=torch.float64) * len(state)
                n += len(state)
        tot /= max(n, 1)
        return {"state_mm": float(tot[0].sqrt()) * STATE_UNIT_MM, "recon_mse": float(tot[1])}

    config = {"net": {"width": cfg.width}, "train": to_dict(cfg), "data": {"cameras": list(cameras)}}
    batches = DatasetBatches(tr, cfg.num_workers, dev.type != "cpu")
    result = fit(model, batches, step, cfg, run_dir=out, kind=KIND, config=config,
                 data=dict(describe_stores(stores), val_fraction=val_fraction), device=dev,
                 evaluate=evaluate if len(va) else None, resume=resume, max_steps=max_steps, progress=progress,
                 desc="task-cnn", log=print if progress else None)
    return result.metrics
