"""A foreground readout: how much of each patch token's picture shows the robot or an object rather than the table.

A small MLP reads one token of a frozen encoder, with its camera and its place in the grid, and gives the fraction of
that patch's pixels that are foreground (0 to 1). It is fit to the simulator's segmentation
(:func:`wamplan.data.foreground.collect_foreground`, training-only supervision) and, at planning time, reads the
WAM's predicted images alone. The planning cost uses it to weigh each token of the target by its foreground
(``CostConfig.foreground``): the object-centric match, where the wrist's table texture sliding under the camera
counts for ``background_weight`` of what the cube, the hole and the gripper count.

    frames = collect_foreground(env, policy, seeds)                 # (F, V, H, W, 3) pictures, (F, V, H, W) masks
    readout, report = fit_foreground(encoder, frames)               # held-out episodes scored
    save_foreground(DIR, readout, encoder, report, task, cameras)
    weigh = foreground_weigher(DIR, encoder, background_weight=0.1)   # target (V, N, D) -> weights (V, N)
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
import torch
from torch import nn

from wamplan.checkpoint import load_weights, read_config, save_checkpoint
from wamplan.config import require
from wamplan.data.features import feature_key
from wamplan.data.foreground import ForegroundFrames
from wamplan.errors import UserError

KIND = "foreground"  # the checkpoint kind of a saved readout


class ForegroundReadout(nn.Module):
    """tokens (..., V, N, D) -> foreground fraction (..., V, N) in [0, 1]: an MLP on [token, one-hot camera,
    one-hot grid cell]."""

    def __init__(self, views: int, num_patches: int, dim: int, hidden: int = 64):
        super().__init__()
        self.views, self.num_patches, self.dim = views, num_patches, dim
        self.net = nn.Sequential(nn.Linear(dim + views + num_patches, hidden), nn.GELU(), nn.Linear(hidden, 1))

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        *lead, v, n, d = z.shape
        if (v, n, d) != (self.views, self.num_patches, self.dim):
            raise ValueError(f"the readout reads ({self.views}, {self.num_patches}, {self.dim}) tokens per frame, got "
                             f"{(v, n, d)}; use a readout fit on this world model's encoder and task")
        where = torch.cat([torch.eye(v).repeat_interleave(n, 0), torch.eye(n).repeat(v, 1)], 1)  # (V*N, V+N)
        where = where.to(z).reshape(v, n, v + n).expand(*lead, v, n, v + n)  # (..., V, N, V+N)
        return torch.sigmoid(self.net(torch.cat([z, where], -1)).squeeze(-1))  # (..., V, N)


def token_fractions(masks: np.ndarray, grid: int) -> np.ndarray:
    """(F, V, H, W) bool -> (F, V, grid * grid) float32: the foreground share of each cell of a grid x grid
    partition, row-major (the encoders' token order); H and W must be multiples of ``grid``."""
    f, v, h, w = masks.shape
    require(h % grid == 0 and w % grid == 0, f"pictures of {h} x {w} px do not split into {grid} x {grid} patches; "
                                             f"render at a multiple of {grid} px (--camera-size)")
    cells = masks.reshape(f, v, grid, h // grid, grid, w // grid).mean(axis=(3, 5))  # (F, V, g, g)
    return cells.reshape(f, v, grid * grid).astype(np.float32)


def _encode(encoder: Any, images: np.ndarray) -> torch.Tensor:
    """(F, V, H, W, 3) uint8 -> (F, V, N, D) float32 tokens."""
    f, v = images.shape[:2]
    with torch.no_grad():
        z = encoder.encode_batched(images.reshape(f * v, *images.shape[2:]))  # (F*V, N, D)
    return z.float().cpu().reshape(f, v, *z.shape[1:])


def fit_foreground(encoder: Any, frames: ForegroundFrames, val_fraction: float = 0.2, steps: int = 2000,
                   lr: float = 3e-3, seed: int = 0) -> tuple[ForegroundReadout, dict[str, Any]]:
    """Fit a readout to ``frames`` encoded by ``encoder``; the last ``val_fraction`` of the episodes (by seed) are
    held out and scored. The report: mean absolute error of the fraction on held-out tokens, against the
    position prior (each camera's and cell's mean fraction on the fitted episodes), per camera and in all."""
    grid = int(round(encoder.num_patches ** 0.5))
    require(grid * grid == encoder.num_patches, f"encoder {encoder.config_dict()['name']} has no square token grid")
    eps = np.unique(frames.episode)
    require(len(eps) >= 2, f"a readout needs frames of at least 2 episodes (one held out), got {len(eps)}")
    held = eps[-max(1, int(round(val_fraction * len(eps)))):]
    val = np.isin(frames.episode, held)  # (F,)
    z = _encode(encoder, frames.images)  # (F, V, N, D)
    y = torch.from_numpy(token_fractions(frames.masks, grid))  # (F, V, N)
    zf, yf = z[~val], y[~val]
    torch.manual_seed(seed)
    readout = ForegroundReadout(z.shape[1], z.shape[2], z.shape[3])
    opt = torch.optim.Adam(readout.parameters(), lr=lr)
    gen = torch.Generator().manual_seed(seed)
    for _ in range(steps):
        idx = torch.randint(len(zf), (min(256, len(zf)),), generator=gen)
        p = readout(zf[idx]).clamp(1e-6, 1 - 1e-6)  # (b, V, N)
        loss = nn.functional.binary_cross_entropy(p, yf[idx])
        opt.zero_grad()
        loss.backward()
        opt.step()
    with torch.no_grad():
        pv = readout(z[val])  # (Fv, V, N)
    prior = yf.mean(0, keepdim=True)  # (1, V, N)
    err, base = (pv - y[val]).abs(), (prior - y[val]).abs()  # (Fv, V, N)
    report = {"frames": int(len(z)), "episodes": int(len(eps)), "held_out_seeds": [int(s) for s in held],
              "cameras": list(frames.cameras), "foreground_share": float(y.mean()),
              "mae": float(err.mean()), "mae_position_prior": float(base.mean()),
              "per_camera": {c: {"mae": float(err[:, i].mean()), "mae_position_prior": float(base[:, i].mean()),
                                 "foreground_share": float(y[:, i].mean())} for i, c in enumerate(frames.cameras)}}
    return readout.eval(), report


def format_report(report: dict[str, Any]) -> str:
    """The fit's held-out figures as a few lines."""
    lines = [f"{report['frames']} frames of {report['episodes']} episodes; held out: seeds "
             f"{', '.join(map(str, report['held_out_seeds']))}; foreground share {report['foreground_share']:.3f}",
             "held-out mean absolute error of each token's foreground fraction (the position prior's in brackets):"]
    lines += [f"  {c:>12}: {r['mae']:.3f} [{r['mae_position_prior']:.3f}]  (share {r['foreground_share']:.3f})"
              for c, r in report["per_camera"].items()]
    lines.append(f"  {'all':>12}: {report['mae']:.3f} [{report['mae_position_prior']:.3f}]")
    return "\n".join(lines)


def save_foreground(path: str | Path, readout: ForegroundReadout, encoder: Any, report: dict[str, Any],
                    task: str, cameras: Sequence[str]) -> Path:
    """Write the readout as a checkpoint of kind ``foreground`` with what it reads (the encoder, by its settings and
    their ``feature_key``; the task; its V cameras in order) and its fit report."""
    cfg = {"views": readout.views, "num_patches": readout.num_patches, "dim": readout.dim, "task": task,
           "cameras": list(cameras), "encoder": encoder.config_dict(),
           "encoder_key": feature_key(encoder.config_dict()), "report": report}
    return save_checkpoint(path, readout, cfg, kind=KIND)


def load_foreground(path: str | Path, encoder: Any | None = None, task: str | None = None,
                    cameras: Sequence[str] | None = None) -> ForegroundReadout:
    """The readout saved at ``path``; refused in one line unless it was fit on ``encoder`` (its settings, a local
    weights path aside), ``task`` and ``cameras`` (in order), each where given."""
    cfg = read_config(path, KIND)
    fix = "fit one for it (`wamplan wm foreground --wm WORLD_MODEL`)"
    if encoder is not None and cfg.get("encoder_key") != feature_key(encoder.config_dict()):
        raise UserError(f"{path} reads tokens of encoder {cfg.get('encoder')}, but the world model's encoder is "
                        f"{encoder.config_dict()}; {fix}")
    if task is not None and cfg.get("task") != task:
        raise UserError(f"{path} was fit on task '{cfg.get('task')}', but the planning acts in '{task}'; {fix}")
    if cameras is not None and cfg.get("cameras") != list(cameras):
        raise UserError(f"{path} reads the cameras {cfg.get('cameras')}, but the world model's views are "
                        f"{list(cameras)}; {fix}")
    readout = ForegroundReadout(cfg["views"], cfg["num_patches"], cfg["dim"])
    load_weights(path, readout)
    return readout.eval()


def cost_weights(foreground: torch.Tensor, background_weight: float) -> torch.Tensor:
    """Foreground shares (...) in [0, 1] -> the cost's token weights (...): ``background_weight`` for pure
    background, 1 for pure foreground, linear between."""
    return background_weight + (1.0 - background_weight) * foreground


def foreground_weigher(path: str | Path, encoder: Any, background_weight: float, task: str | None = None,
                       cameras: Sequence[str] | None = None) -> Callable[[torch.Tensor], torch.Tensor]:
    """target tokens (V, N, D) -> each token's weight in the cost (V, N) (:func:`cost_weights` of the readout's
    shares), on the target's device. A planner scores many candidate batches against one target: the weights of
    the last target are kept while the same tensor comes back."""
    readout = load_foreground(path, encoder, task, cameras)
    last: list = [None, None]  # [target, its weights]

    def weigh(target: torch.Tensor) -> torch.Tensor:
        if last[0] is not target:
            with torch.no_grad():
                fg = readout.to(target.device)(target.float())  # (V, N)
            last[:] = [target, cost_weights(fg, background_weight)]
        return last[1]

    return weigh


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


def draw_foreground(frames: ForegroundFrames, readout: ForegroundReadout, encoder: Any, out: str | Path,
                    seed: int | None = None, count: int = 4) -> Path:
    """A PNG of ``count`` frames of episode ``seed`` (default: the last), spread over the episode: per camera the
    picture, the true foreground share of each patch, and the readout's."""
    seed = int(frames.episode[-1]) if seed is None else seed
    idx = episode_frames(frames, seed, count)  # (count,)
    grid = int(round(readout.num_patches ** 0.5))
    true = token_fractions(frames.masks[idx], grid)  # (count, V, N)
    with torch.no_grad():
        read = readout(_encode(encoder, frames.images[idx])).numpy()  # (count, V, N)
    maps = [("true share", true.reshape(*true.shape[:2], grid, grid)),
            ("readout", read.reshape(*read.shape[:2], grid, grid))]
    return draw_frame_maps(frames, idx, maps, f"foreground per patch token, held-out episode (seed {seed})", out,
                           vmin=0, vmax=1, cmap="magma")
