"""How much a world model's one-step prediction moves with the chunk it is given, against how much the true
outcome moves: held-out branch groups (siblings share their past and differ in the chunk run from the boundary).

    python lab/boundary-history/probe_action_response.py CKPT STORE [CKPT ...]

Per model: the siblings' true spread around their mean (per element), the predicted spread, the prediction's
move when the chunk is replaced by another window's chunk (a large change), and by zeros; all per element of z."""

from __future__ import annotations

import sys

import torch

from wamplan.data.readers import BranchGroups
from wamplan.worldmodel.load import load_world_model


@torch.no_grad()
def response(ckpt: str, store: str, groups: int = 24) -> dict[str, float]:
    model, enc = load_world_model(ckpt)
    cfg, h = model.cfg, model.cfg.context
    data = BranchGroups([store], cfg.frameskip, cfg.context, 1, split="val")
    true_spread, pred_spread, swap_move, zero_move = [], [], [], []
    for i in range(min(groups, len(data))):
        item = data[i]
        g, t = item["images"].shape[:2]
        imgs = item["images"].reshape(-1, *item["images"].shape[-3:])  # (G T V, H, W, 3)
        z = enc.encode_batched(imgs).reshape(g, t, cfg.num_views, cfg.num_patches, -1)  # (G, T, V, N, D)
        q, a = item["q"].float(), item["a"].float()  # (G, T, P), (G, T, DA)
        zp, _ = model(z[:, :h], q[:, :h], a[:, :h])  # (G, h, V, N, D): output h-1 predicts frame h
        pred = model.normalised(zp[:, h - 1])
        true = model.normalised(z[:, h])
        true_spread.append(((true - true.mean(0)) ** 2).mean().item())
        pred_spread.append(((pred - pred.mean(0)) ** 2).mean().item())
        other = data[(i + len(data) // 2) % len(data)]["a"].float()[:, h - 1]  # (G, DA) another boundary's chunks
        a_swap = a[:, :h].clone()
        a_swap[:, h - 1] = other
        zs, _ = model(z[:, :h], q[:, :h], a_swap)
        swap_move.append(((model.normalised(zs[:, h - 1]) - pred) ** 2).mean().item())
        a_zero = a[:, :h].clone()
        a_zero[:, h - 1] = 0
        z0, _ = model(z[:, :h], q[:, :h], a_zero)
        zero_move.append(((model.normalised(z0[:, h - 1]) - pred) ** 2).mean().item())
    mean = lambda xs: sum(xs) / len(xs)
    return dict(groups=len(true_spread), true_sibling_spread=mean(true_spread), predicted_sibling_spread=mean(pred_spread),
                move_other_chunk=mean(swap_move), move_zero_chunk=mean(zero_move))


if __name__ == "__main__":
    *ckpts, store = sys.argv[1:]
    for c in ckpts:
        print(c, {k: round(v, 5) if isinstance(v, float) else v for k, v in response(c, store).items()}, flush=True)
