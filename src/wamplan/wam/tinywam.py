"""TinyWAM: a small world action model trained from scratch on expert demonstrations (a CPU stand-in for
Cosmos Policy, paper §3.1).

From the current observation ``o_t = (q_t, I_t)`` it jointly predicts the action chunk ``a_{t:t+H-1}``
and the three views at ``t + H``, at a small square resolution (``image_size``)::

    views (B, V, 3, S, S) ──► shared conv encoder (per view) ──► token (B, V, L) + view embedding ─┐
    proprio (B, P) ──────────► MLP ────────────────────────────► (B, L) ──────────────────────────┴► trunk h (B, T)
    h ──► action head ──► tanh ──► actions (B, H, A) in [-1, 1]
    h ──► FiLM-conditioned U-Net decoder (encoder skips of the same view) ──► residual over the current view
          ──► future views (B, V, 3, S, S) in [0, 1]

Observation images of any size are resized to ``image_size`` (bilinear, antialiased, rounded to uint8:
the same path in training and at deployment). Input normalisation statistics (per-channel image
mean/std, per-dimension proprio mean/std) are buffers, so they travel in ``model.safetensors``.
The language instruction is ignored: TinyWAM is trained on one task, the task of its training stores, which
its checkpoint records (``wam.task``; a checkpoint that records none: cube-insertion). Its action and proprio
sizes and its cameras are that task's unless the config sets them (:meth:`TinyWAMConfig.for_task`).

    wam = load_wam("runs/tinywam")             # a checkpoint written by `wamplan wam train`
    out = wam.predict(obs, "insert the cube")   # out.actions (16, A) float32, out.images[cam] (64, 64, 3) uint8
"""

from __future__ import annotations

import math
import time
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from wamplan.config import ConfigError, from_dict, require, to_dict
from wamplan.envs.spec import Observation, TaskSpec, get_task, require_images
from wamplan.wam.base import LEGACY_TASK, WAM, WAMError, WAMOutput, register_wam, register_wam_loader
from wamplan.wam.tinywam_config import TASK_FIELDS, TinyWAMConfig  # noqa: F401  (its home)

KIND = "tinywam"




# ----------------------------------------------------------------------------------------------- images
def to_model_frames(images: torch.Tensor, size: int) -> torch.Tensor:
    """(..., h, w, 3) uint8 -> (..., 3, size, size) uint8: bilinear antialiased resize, rounded.

    Training (``wamplan.wam.train``) and ``TinyWAM.predict`` both go through this, so the model sees
    identically prepared pictures in both."""
    lead = images.shape[:-3]
    x = images.reshape(-1, *images.shape[-3:]).permute(0, 3, 1, 2)  # (N, 3, h, w)
    if x.shape[-2:] != (size, size):
        x = F.interpolate(x.float(), size=(size, size), mode="bilinear", antialias=True, align_corners=False)
        x = x.round().clamp(0, 255).to(torch.uint8)  # (N, 3, S, S)
    return x.reshape(*lead, 3, size, size).contiguous()


def _norm(c: int) -> nn.GroupNorm:
    return nn.GroupNorm(math.gcd(8, c), c)


class _ConvBlock(nn.Sequential):
    """conv3x3 (stride s) -> GroupNorm -> SiLU, then ``convs - 1`` more at stride 1."""

    def __init__(self, cin: int, cout: int, stride: int = 1, convs: int = 2):
        layers: list[nn.Module] = []
        for i in range(convs):
            layers += [nn.Conv2d(cin if i == 0 else cout, cout, 3, stride if i == 0 else 1, 1), _norm(cout), nn.SiLU()]
        super().__init__(*layers)


class TinyWAMNet(nn.Module):
    """The network. ``forward(images (B, V, 3, S, S) in [0, 1], proprio (B, P))`` ->
    ``(actions (B, H, A) in [-1, 1], future (B, V, 3, S, S) unclamped)``."""

    def __init__(self, cfg: TinyWAMConfig):
        super().__init__()
        unset = [f"--{n.replace('_', '-')}" for n in TASK_FIELDS if getattr(cfg, n) is None]
        require(not unset, f"TinyWAMConfig leaves {', '.join(unset)} to the task: build the network from "
                           f"config.for_task(task)")
        self.cfg = cfg
        V, L, T, ch = len(cfg.cameras), cfg.latent_dim, cfg.trunk_dim, cfg.channels
        g = cfg.grid
        self.register_buffer("image_mean", torch.full((3,), 0.5))
        self.register_buffer("image_std", torch.full((3,), 0.25))
        self.register_buffer("proprio_mean", torch.zeros(cfg.proprio_dim))
        self.register_buffer("proprio_std", torch.ones(cfg.proprio_dim))
        # encoder: stage i maps S / 2^i -> S / 2^(i+1)
        self.down = nn.ModuleList(_ConvBlock(cin, cout, 2) for cin, cout in zip((3, *ch[:-1]), ch))
        self.to_token = nn.Linear(ch[-1] * g * g, L)
        self.view_emb = nn.Parameter(torch.randn(V, L) * 0.02)  # (V, L)
        self.proprio_mlp = nn.Sequential(nn.Linear(cfg.proprio_dim, L), nn.SiLU(), nn.Linear(L, L))
        self.trunk = nn.Sequential(nn.Linear((V + 1) * L, T), nn.SiLU(), nn.Linear(T, T), nn.SiLU())
        self.action_head = nn.Linear(T, cfg.chunk_length * cfg.action_dim)
        # decoder: a per-view condition from the trunk, a latent map, then up-stages mirroring the encoder
        self.dec_view_emb = nn.Parameter(torch.randn(V, T) * 0.02)  # (V, T)
        self.from_cond = nn.Linear(T, ch[-1] * g * g)
        self.bottleneck = _ConvBlock(2 * ch[-1], ch[-1], convs=1)
        ups, films = [], []
        for i in reversed(range(1, len(ch))):  # up-stage i maps S / 2^(i+1) -> S / 2^i, with encoder skip i-1
            ups.append(_ConvBlock(ch[i] + ch[i - 1], ch[i - 1], convs=1))
            films.append(nn.Linear(T, 2 * ch[i]))
        films.append(nn.Linear(T, 2 * ch[0]))  # before the last upsampling to full resolution
        self.up = nn.ModuleList(ups)
        self.film = nn.ModuleList(films)
        # full resolution is the costly one: a single conv over (upsampled features, current view)
        self.to_rgb = nn.Conv2d(ch[0] + 3, 3, 3, 1, 1)
        if cfg.residual:  # start as "nothing changes": the prediction is the current view
            nn.init.zeros_(self.to_rgb.weight)
            nn.init.zeros_(self.to_rgb.bias)
        for film in self.film:  # start FiLM at identity
            nn.init.zeros_(film.weight)
            nn.init.zeros_(film.bias)

    def set_stats(self, image_mean: torch.Tensor, image_std: torch.Tensor, proprio_mean: torch.Tensor,
                  proprio_std: torch.Tensor) -> None:
        """Input normalisation statistics: images per channel (3,) in [0, 1] units, proprio per dimension (P,)."""
        for name, v in (("image_mean", image_mean), ("image_std", image_std.clamp_min(1e-3)),
                        ("proprio_mean", proprio_mean), ("proprio_std", proprio_std.clamp_min(1e-3))):
            getattr(self, name).copy_(v.to(getattr(self, name)))

    def forward(self, images: torch.Tensor, proprio: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        cfg = self.cfg
        B, V, _, S, _ = images.shape
        x = images.reshape(B * V, 3, S, S)  # (BV, 3, S, S) in [0, 1]
        h = (x - self.image_mean.view(1, 3, 1, 1)) / self.image_std.view(1, 3, 1, 1)  # (BV, 3, S, S)
        skips = [x]
        for stage in self.down:
            h = stage(h)  # (BV, C_i, S / 2^(i+1), S / 2^(i+1))
            skips.append(h)
        tokens = self.to_token(h.flatten(1)).view(B, V, -1) + self.view_emb  # (B, V, L)
        q = (proprio - self.proprio_mean) / self.proprio_std  # (B, P)
        fused = torch.cat([tokens.flatten(1), self.proprio_mlp(q)], dim=1)  # (B, (V + 1) L)
        trunk = self.trunk(fused)  # (B, T)
        actions = torch.tanh(self.action_head(trunk)).view(B, cfg.chunk_length, cfg.action_dim)  # (B, H, A)

        cond = (trunk[:, None] + self.dec_view_emb).reshape(B * V, -1)  # (BV, T)
        g = cfg.grid
        z = self.from_cond(cond).view(B * V, -1, g, g)  # (BV, C_last, g, g)
        y = self.bottleneck(torch.cat([z, skips[-1]], dim=1))  # (BV, C_last, g, g)
        for k, film in enumerate(self.film):
            scale, shift = film(cond).chunk(2, dim=1)  # (BV, C) each
            y = y * (1 + scale[:, :, None, None]) + shift[:, :, None, None]
            y = F.interpolate(y, scale_factor=2, mode="nearest")  # (BV, C, 2r, 2r)
            if k < len(self.up):
                y = self.up[k](torch.cat([y, skips[-2 - k]], dim=1))  # (BV, C', 2r, 2r), skip of the same size
        out = self.to_rgb(torch.cat([y, x], dim=1))  # (BV, 3, S, S)
        future = x + out if cfg.residual else torch.sigmoid(out)  # (BV, 3, S, S)
        return actions, future.view(B, V, 3, S, S)


# ----------------------------------------------------------------------------------------------- the WAM
@register_wam("tinywam")
class TinyWAM(WAM):
    """TinyWAM behind the WAM interface for ``task``. ``TinyWAM()`` is randomly initialised (tests, smoke
    runs), its config's unset fields filled from the task; trained ones come from ``load_wam(path)`` /
    :meth:`from_checkpoint`."""

    def __init__(self, config: TinyWAMConfig | None = None, *, net: TinyWAMNet | None = None,
                 device: str | torch.device = "auto", provenance: dict[str, Any] | None = None,
                 task: str | TaskSpec = LEGACY_TASK):
        from wamplan.device import resolve_device

        if net is not None and config is not None and net.cfg != config:
            raise WAMError("TinyWAM got a net and a config that differ; pass only one of them")
        self.task = task
        self.config = (net.cfg if net is not None else config or TinyWAMConfig()).for_task(self.task)
        self.device = resolve_device(device) if isinstance(device, str) else device
        self.net = (net if net is not None else TinyWAMNet(self.config)).to(self.device).eval()
        self.chunk_length = self.config.chunk_length
        self.action_dim = self.config.action_dim
        self.cameras = tuple(self.config.cameras)
        self.provenance = provenance or {}
        # the camera size of the training renders; other sizes are resized, which is not the same picture
        self.trained_camera_size = (self.provenance.get("data") or {}).get("camera_size")
        self._warned_size = False

    @classmethod
    def from_checkpoint(cls, path: str | Path, device: str | torch.device = "auto") -> "TinyWAM":
        from wamplan.checkpoint import checkpoint_dir, load_weights, read_config

        path = checkpoint_dir(path)
        saved = read_config(path, KIND)
        task = get_task((saved.get("data") or {}).get("task") or LEGACY_TASK)  # recorded since tasks exist
        try:
            cfg = from_dict(TinyWAMConfig, saved["model"]).for_task(task)  # a saved config has every field set
        except ConfigError as e:
            raise WAMError(f"{path}: {e}") from None
        net = TinyWAMNet(cfg)
        load_weights(path, net)
        return cls(net=net, device=device, task=task,
                   provenance={"checkpoint": str(Path(path).resolve()), "train": saved.get("train"),
                               "data": saved.get("data")})

    def config_dict(self) -> dict[str, Any]:
        return {"name": self.name, "task": self.task.name, **to_dict(self.config),
                **({"provenance": self.provenance} if self.provenance else {})}

    def predict(self, obs: Observation, instruction: str) -> WAMOutput:
        t0 = time.perf_counter()
        if obs.images is None:
            raise WAMError(f"the observation at step {obs.step} has no images; TinyWAM needs {list(self.cameras)}")
        missing = [c for c in self.cameras if c not in obs.images]
        if missing:
            raise WAMError(f"the observation has no image for {missing} (has {sorted(obs.images)}); render all of "
                           f"{list(self.cameras)}")
        proprio = np.asarray(obs.proprio, dtype=np.float32).reshape(-1)  # (P,)
        if proprio.shape != (self.config.proprio_dim,) or not np.isfinite(proprio).all():
            raise WAMError(f"the observation's proprio has shape {proprio.shape} or non-finite values; TinyWAM "
                           f"needs a finite ({self.config.proprio_dim},) vector")
        require_images(obs, self.cameras, "TinyWAM.predict")
        views = torch.from_numpy(np.stack([obs.images[c] for c in self.cameras]))  # (V, h, w, 3) uint8
        size = views.shape[1]
        if self.trained_camera_size and size != self.trained_camera_size and not self._warned_size:
            self._warned_size = True
            warnings.warn(f"TinyWAM was trained on {self.trained_camera_size}-px renders but gets {size}-px images; a "
                          f"resized render is not a native one (mean |diff| ~8/255 at 64 px): render at "
                          f"{self.trained_camera_size} px (--camera-size {self.trained_camera_size} in eval, collect "
                          f"and env; a store collected at {size} px must be collected again)", stacklevel=2)
        frames = to_model_frames(views, self.config.image_size)  # (V, 3, S, S) uint8
        with torch.inference_mode():
            x = frames[None].to(self.device).float() / 255.0  # (1, V, 3, S, S)
            q = torch.from_numpy(proprio)[None].to(self.device)  # (1, P)
            actions, future = self.net(x, q)  # (1, H, A), (1, V, 3, S, S)
            actions = actions[0].clamp(-1.0, 1.0).float().cpu().numpy().astype(np.float32)  # (H, A)
            imgs = (future[0].clamp(0.0, 1.0) * 255.0).round().to(torch.uint8).permute(0, 2, 3, 1).cpu().numpy()  # (V, S, S, 3)
        return WAMOutput(actions=actions, images={c: imgs[i] for i, c in enumerate(self.cameras)},
                         timing={"query_s": time.perf_counter() - t0})


@register_wam_loader(KIND)
def load_tinywam(path: Path, device: str | torch.device = "auto") -> TinyWAM:
    """A trained TinyWAM from a checkpoint directory, on ``device`` ('auto': the best available)."""
    return TinyWAM.from_checkpoint(path, device=device)
