"""Is the siblings' difference at Δ = 16 a simple function of their chunks? Ridge fits on branch groups.

    python lab/boundary-history/probe_linear_siblings.py CKPT FEATURES STORE [STORE ...]

FEATURES: the stores' cached feature key of CKPT's encoder (``STORE/features/<key>``, e.g. patch-pixels-38fd490f).

Siblings share their past and differ in the chunk run from the boundary, so within a group the deviation of a
sibling's next frame from the group's mean (standardised features, as CKPT's loss sees them) is what the chunk
decides. Three fits say how much of it a simple readout explains (R² against predicting no difference, the
baseline the Δ = 16 models sit at):

* global, chunk: one ridge map from the chunk's deviation (Δ·A entries) to the frame's, fitted on the training
  groups, scored on the held-out groups;
* global, displacement: the same from the chunk's summed commands (A entries: what the chunk asks the arm to move);
* local, displacement: per group, leave one sibling out, a ridge map from the other siblings' summed arm commands
  (xyz, then all A entries) to their frames; the held-out sibling predicted from its own. A state's own linear
  response.

Per view: its share of the siblings' spread, the local fit on its features alone, and CKPT's own slope there.
"""

from __future__ import annotations

import sys

import torch

from wamplan.data.readers import BranchGroups
from wamplan.worldmodel.load import load_world_model
from wamplan.worldmodel.siblings import pool_siblings, sibling_statistics


def deviations(data: BranchGroups, model, h: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Per sibling of every group: its next frame's deviation from the group mean (M, G, F), its chunk's (M, G, Δ·A)
    and its summed commands' (M, G, A)."""
    zs, acts = [], []
    for i in range(len(data)):
        item = data[i]
        zs.append(model.normalised(item["z"][:, h].float()).flatten(1))  # (G, F): the frame after the boundary
        acts.append(item["a"][:, h - 1].float())  # (G, Δ·A): the chunk run from the boundary
    z, a = torch.stack(zs), torch.stack(acts)  # (M, G, F), (M, G, Δ·A)
    s = a.reshape(*a.shape[:2], data.frameskip, -1).sum(2)  # (M, G, A)
    centre = lambda x: x - x.mean(1, keepdim=True)
    return centre(z), centre(a), centre(s)


def model_slopes(data: BranchGroups, model) -> list[float]:
    """Per view, ``model``'s sib_gain at one step (the slope of its predicted sibling differences on the true ones;
    :func:`~wamplan.worldmodel.siblings.pool_siblings` of each view's statistics)."""
    stats = sibling_statistics(model, data, 1, per="view")  # each (groups, 1, V)
    return [pool_siblings({k: v[..., i] for k, v in stats.items()}, 1)["sib_gain_h1"]
            for i in range(model.cfg.num_views)]


def ridge(x: torch.Tensor, y: torch.Tensor, lam: float) -> torch.Tensor:
    """W (k, F) minimising ||x W - y||² + lam ||W||² for x (n, k), y (n, F)."""
    k = x.shape[1]
    return torch.linalg.solve(x.T @ x + lam * torch.eye(k), x.T @ y)


def r2(pred: torch.Tensor, true: torch.Tensor) -> float:
    return 1.0 - float(((pred - true) ** 2).sum() / (true ** 2).sum())


def local_r2(z: torch.Tensor, s: torch.Tensor, lam: float) -> float:
    """Leave one sibling out per group: its deviation from the others' mean, predicted through the others' ridge map
    (``lam``: 5 siblings cannot pin 3 slopes down without it)."""
    err = base = 0.0
    for zg, sg in zip(z, s):  # (G, F), (G, k)
        for j in range(len(zg)):
            keep = [i for i in range(len(zg)) if i != j]
            zk, sk = zg[keep], sg[keep]
            mz, ms = zk.mean(0), sk.mean(0)
            w = ridge(sk - ms, zk - mz, lam)  # (k, F)
            err += float(((mz + (sg[j] - ms) @ w - zg[j]) ** 2).sum())
            base += float(((mz - zg[j]) ** 2).sum())
    return 1.0 - err / base


@torch.no_grad()
def main(ckpt: str, key: str, stores: list[str]) -> dict[str, float]:
    model, _ = load_world_model(ckpt)
    cfg, h = model.cfg, model.cfg.context
    split = {name: BranchGroups(stores, cfg.frameskip, h, 1, split=name, features=key) for name in ("train", "val")}
    (zt, at, st), (zv, av, sv) = (deviations(d, model, h) for d in split.values())
    flat = lambda x: x.flatten(0, 1)
    out = dict(train_groups=len(zt), val_groups=len(zv), sibling_spread=float((zv ** 2).mean()))
    for name, xt, xv in (("chunk", at, av), ("displacement", st, sv)):
        half = len(xt) // 2  # λ chosen on the training groups' second half, fitted on their first
        _, lam = max((r2(flat(xt[half:]) @ ridge(flat(xt[:half]), flat(zt[:half]), lam), flat(zt[half:])), lam)
                     for lam in (1e-2, 1e-1, 1.0, 10.0, 1e2, 1e3, 1e4, 1e5))
        out[f"global_{name}_r2"] = r2(flat(xv) @ ridge(flat(xt), flat(zt), lam), flat(zv))
        out[f"global_{name}_lambda"] = lam
    for lam in (0.1, 1.0, 10.0):  # reported for each: no split is small enough to choose on
        out[f"local_xyz_r2_lambda{lam:g}"] = local_r2(zv, sv[..., :3], lam)
        out[f"local_all_r2_lambda{lam:g}"] = local_r2(zv, sv, lam)  # every commanded entry (gripper, yaw too)
    per_view = zv.shape[-1] // len(split["val"].cameras)  # F = V·N·D, view-major
    slopes = model_slopes(split["val"], model)
    for v, cam in enumerate(split["val"].cameras):  # where the siblings differ, how linear it is, what CKPT follows
        part = slice(v * per_view, (v + 1) * per_view)
        out[f"{cam}_share_of_spread"] = float((zv[..., part] ** 2).sum() / (zv ** 2).sum())
        out[f"{cam}_local_all_r2_lambda1"] = local_r2(zv[..., part], sv, 1.0)
        out[f"{cam}_model_slope"] = float(slopes[v])
    return out


if __name__ == "__main__":
    ckpt, key, *stores = sys.argv[1:]
    print({k: round(v, 4) if isinstance(v, float) else v for k, v in main(ckpt, key, stores).items()}, flush=True)
