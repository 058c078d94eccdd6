"""A toy world with simple, learnable dynamics, for tests and training-speed benchmarks.

A blob sits at position p in [-1, 1]^2. Each view renders it as a token field: the token of the patch
centred at c is ``b * u_v + (1 - b) * w_v + shift * (p_x r_v + p_y s_v)`` with
``b = exp(-|c - p|^2 / (2 s^2))`` and fixed random unit vectors u_v, w_v, r_v, s_v per view (the last
term, a global shift with p, is quick to learn; the bump's motion takes longer). Action step k moves p
by ``step * (a_k[0], a_k[1])`` (clipped to the square); proprioception is ``(p_x, p_y, 0, ...)``.
Copying the last frame is wrong by exactly the motion, which the action block explains, so a working
predictor must beat the copy baseline.
"""

from __future__ import annotations

import torch
from torch.utils.data import Dataset

from wamplan.worldmodel.config import PredictorConfig


class SyntheticWindows(Dataset):
    """``n`` windows of ``frames`` frames shaped for ``cfg``: items {"z", "q", "a"} as the trainer expects."""

    def __init__(self, n: int, cfg: PredictorConfig, frames: int, seed: int = 0, step: float = 0.12,
                 width: float = 0.4, shift: float = 0.5) -> None:
        g = int(round(cfg.num_patches ** 0.5))
        if g * g != cfg.num_patches:
            raise ValueError(f"SyntheticWindows needs a square patch grid, got N = {cfg.num_patches}")
        gen = torch.Generator().manual_seed(seed)
        world = torch.Generator().manual_seed(12345)  # the same rendering for every split
        v, d, da = cfg.num_views, cfg.enc_dim, cfg.action_dim
        u = torch.nn.functional.normalize(torch.randn(v, d, generator=world), dim=-1)  # (V, D)
        w = torch.nn.functional.normalize(torch.randn(v, d, generator=world), dim=-1)  # (V, D)
        rs = torch.nn.functional.normalize(torch.randn(2, v, d, generator=world), dim=-1)  # (2, V, D)
        ticks = (torch.arange(g) + 0.5) / g * 2 - 1  # (g,)
        centres = torch.stack(torch.meshgrid(ticks, ticks, indexing="ij"), -1).reshape(-1, 2)  # (N, 2) row-major
        acts = torch.rand(n, frames, cfg.frameskip, da, generator=gen) * 2 - 1  # (n, T, Delta, A)
        pos = torch.empty(n, frames, 2)
        pos[:, 0] = torch.rand(n, 2, generator=gen) * 1.2 - 0.6
        for t in range(1, frames):
            pos[:, t] = (pos[:, t - 1] + step * acts[:, t - 1, :, :2].sum(dim=1)).clamp(-1, 1)  # (n, 2)
        dist2 = (centres[None, None] - pos[:, :, None]).pow(2).sum(-1)  # (n, T, N)
        b = torch.exp(-dist2 / (2 * width ** 2))[:, :, None, :, None]  # (n, T, 1, N, 1)
        glob = shift * torch.einsum("ntk,kvd->ntvd", pos, rs)[:, :, :, None]  # (n, T, V, 1, D)
        self.z = (b * u[None, None, :, None] + (1 - b) * w[None, None, :, None] + glob).half()  # (n, T, V, N, D)
        self.q = torch.zeros(n, frames, cfg.proprio_dim)  # (n, T, P)
        self.q[..., :2] = pos
        self.a = acts.flatten(2)  # (n, T, Delta*A)

    def __len__(self) -> int:
        return self.z.shape[0]

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        return {"z": self.z[i], "q": self.q[i], "a": self.a[i]}
